"""Assembly of per-polygon textures into a textured model: atlas pages, OBJ + MTL + PNG, GLB.

Each polygon's texture is a rectangle in its UV frame (docs/conventions.md), so the atlas is a
rectangle packing problem: rectpack places every texture, with a border of ``padding`` texels
filled by dilating the texture's valid texels outwards (nearest valid texel), so bilinear
filtering and mip-mapping never blend in the neighbour's texels or black. xatlas would
re-parameterise the mesh; here the parameterisation is fixed by the UV frames and only the
rectangles have to be placed.

The proxy geometry is written unchanged: one OBJ group / one glTF node per polygon, named by its
id. OBJ keeps convex n-gons; non-convex polygons and polygons with holes are triangulated with
earcut in their plane (glTF always gets triangles). Polygons without a texture (no photo sees
them) are still in the model, mapped onto a small neutral grey patch, and listed in the summary.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from difftex.errors import DifftexError
from difftex.geometry.frames import UVFrame
from difftex.layout import MODEL_NAME
from difftex.scene.proxy import Polygon, triangulate

log = logging.getLogger(__name__)

UNTEXTURED_PATCH = 4  # texels per side of the grey patch of an untextured polygon (before padding)


@dataclass(frozen=True)
class AssembleConfig:
    max_page_size: int = 8192  # longest side of an atlas page, texels
    padding: int = 8  # dilated border around each texture; 2^k keeps k mip levels seam-free
    power_of_two: bool = False  # round page sizes up to powers of two (for old WebGL1 viewers)
    untextured_color: tuple[float, float, float] = (0.5, 0.5, 0.5)  # polygons no photo sees
    glb: bool = True  # also write model.glb (binary glTF)
    verify: bool = True  # reload the written GLB and compare its colours with the textures
    tileset: bool = False  # also write tileset/ (3D Tiles 1.1: tileset.json, a GLB per building; export.tiles)
    tileset_georef: dict | None = None  # the tileset's place on Earth ({lon, lat, height} or {ecef}); None: local

    def __post_init__(self):
        if not 64 <= int(self.max_page_size) <= 32768:
            raise ValueError(f"max_page_size must be in 64..32768, got {self.max_page_size}")
        if not 0 <= int(self.padding) <= 256:
            raise ValueError(f"padding must be in 0..256, got {self.padding}")
        c = tuple(self.untextured_color)
        if len(c) != 3 or not all(0.0 <= float(x) <= 1.0 for x in c):
            raise ValueError(f"untextured_color must be three values in [0, 1], got {list(c)}")


@dataclass(frozen=True, eq=False)
class PolygonTexture:
    """What assembly needs of one polygon; ``texture`` None = untextured (grey patch)."""

    polygon: Polygon
    frame: UVFrame | None
    texture: np.ndarray | None = None  # (h, w, 3) float in [0, 1]; any size, mapped onto the frame
    mask: np.ndarray | None = None  # (h, w) bool valid texels (None: all valid)
    coverage: float = 0.0
    photos: int = 0
    normal: np.ndarray | None = None  # (h, w, 3) tangent-space normal map in [0, 1] of the relief, if any

    @property
    def textured(self) -> bool:
        return self.texture is not None and self.frame is not None


@dataclass(frozen=True, eq=False)
class Placement:
    page: int
    x: int  # top-left of the padded rectangle in the page, texels
    y: int
    width: int  # padded size
    height: int
    scale: float  # texture texels per frame texel (< 1 when a texture had to be shrunk to fit)


@dataclass(eq=False)
class Atlas:
    pages: list[np.ndarray]  # (H, W, 3) float32
    placements: dict[str, Placement] = field(default_factory=dict)
    # the relief's normal maps at the same placements (flat (0.5, 0.5, 1) elsewhere); None: no relief
    normal_pages: list[np.ndarray] | None = None


# ---------------------------------------------------------------------------------------------
# Textures and packing


def dilate(texture: np.ndarray, mask: np.ndarray | None, pad: int) -> np.ndarray:
    """The texture with ``pad`` extra texels on each side, every invalid texel set to its nearest
    valid texel, so filtering across the polygon's edge sees the polygon's own colours."""
    from scipy.ndimage import distance_transform_edt

    h, w = texture.shape[:2]
    out = np.zeros((h + 2 * pad, w + 2 * pad, 3), np.float32)
    out[pad : pad + h, pad : pad + w] = texture[..., :3]
    valid = np.zeros(out.shape[:2], bool)
    valid[pad : pad + h, pad : pad + w] = True if mask is None else mask
    if not valid.any():
        return out
    if not valid.all():
        _, (iy, ix) = distance_transform_edt(~valid, return_indices=True)
        out = out[iy, ix]
    return out


def _fit(sizes: dict[str, tuple[int, int]], side: int):
    """rectpack placement of all (w, h) rectangles into as many side x side bins as needed."""
    import rectpack

    packer = rectpack.newPacker(
        mode=rectpack.PackingMode.Offline,
        bin_algo=rectpack.PackingBin.BFF,
        pack_algo=rectpack.MaxRectsBssf,
        sort_algo=rectpack.SORT_AREA,
        rotation=False,  # a rotated texture would need rotated UVs; not worth the complexity
    )
    for rid, (w, h) in sizes.items():
        packer.add_rect(w, h, rid=rid)
    packer.add_bin(side, side, count=float("inf"))
    packer.pack()
    out = {}
    for b, x, y, _w, _h, rid in packer.rect_list():
        out[rid] = (b, x, y)
    if len(out) != len(sizes):
        raise DifftexError(f"atlas packing placed {len(out)} of {len(sizes)} textures")
    return out


def pack(
    sizes: dict[str, tuple[int, int]], max_side: int
) -> tuple[dict[str, tuple[int, int, int]], list[tuple[int, int]]]:
    """Place padded rectangles (w, h) on pages of at most ``max_side``: {id: (page, x, y)} and
    the page sizes (w, h), each cropped to what it uses.

    A single page is searched from the smallest power of two that can hold the total area up to
    ``max_side``, so a small model gets a small atlas rather than one mostly empty 8k page.
    """
    if not sizes:
        return {}, []
    for rid, (w, h) in sizes.items():
        if w > max_side or h > max_side:
            raise DifftexError(f"texture '{rid}' ({w}x{h}) does not fit an atlas page of {max_side}")
    area = sum(w * h for w, h in sizes.values())
    longest = max(max(w, h) for w, h in sizes.values())
    side = max(64, 1 << math.ceil(math.log2(max(longest, math.sqrt(area)))))
    while True:
        side = min(side, max_side)
        where = _fit(sizes, side)
        if side >= max_side or max(b for b, _, _ in where.values()) == 0:
            break
        side *= 2
    n_pages = max(b for b, _, _ in where.values()) + 1
    used = [[0, 0] for _ in range(n_pages)]
    for rid, (b, x, y) in where.items():
        w, h = sizes[rid]
        used[b][0] = max(used[b][0], x + w)
        used[b][1] = max(used[b][1], y + h)
    return where, [(int(w), int(h)) for w, h in used]


def _round_size(n: int, pow2: bool) -> int:
    return 1 << math.ceil(math.log2(max(n, 1))) if pow2 else 4 * math.ceil(n / 4)


def _shrink(texture: np.ndarray, mask: np.ndarray | None, scale: float):
    from skimage.transform import resize

    h, w = texture.shape[:2]
    nh, nw = max(1, int(h * scale)), max(1, int(w * scale))
    tex = resize(texture, (nh, nw, texture.shape[2]), order=1, anti_aliasing=True, preserve_range=True)
    m = None if mask is None else resize(mask.astype(np.float32), (nh, nw), order=1) > 0.5
    return tex.astype(np.float32), m


def build_atlas(items: list[PolygonTexture], cfg: AssembleConfig) -> Atlas:
    """Pack every polygon (textured or grey patch) onto atlas pages."""
    pad = int(cfg.padding)
    max_side = int(cfg.max_page_size)
    prepared: dict[str, np.ndarray] = {}
    scales: dict[str, float] = {}
    grey = np.asarray(cfg.untextured_color, np.float32)
    for it in items:
        pid = it.polygon.id
        if it.textured:
            tex, mask = it.texture, it.mask
            h, w = tex.shape[:2]
            scale = tex.shape[1] / it.frame.width
            if max(h, w) + 2 * pad > max_side:
                # A texture larger than a page (density mode on a huge facade) is shrunk to fit.
                shrink = (max_side - 2 * pad) / max(h, w)
                log.warning(
                    "texture of '%s' (%dx%d) shrunk by %.3f to fit a %d atlas page", pid, w, h, shrink, max_side
                )
                tex, mask = _shrink(tex, mask, shrink)
                scale = tex.shape[1] / it.frame.width
            prepared[pid] = dilate(tex, mask, pad)
            scales[pid] = scale
        else:
            n = UNTEXTURED_PATCH + 2 * pad
            prepared[pid] = np.broadcast_to(grey, (n, n, 3))
            scales[pid] = 0.0
    sizes = {pid: (a.shape[1], a.shape[0]) for pid, a in prepared.items()}
    where, used = pack(sizes, max_side)
    page_sizes = [
        (min(_round_size(w, cfg.power_of_two), max_side), min(_round_size(h, cfg.power_of_two), max_side))
        for w, h in used
    ]
    atlas = Atlas(pages=[np.zeros((h, w, 3), np.float32) for w, h in page_sizes])
    # Unused page area gets the grey too: a viewer's coarsest mip levels average it in.
    for p in atlas.pages:
        p[:] = grey
    for pid, img in prepared.items():
        b, x, y = where[pid]
        h, w = img.shape[:2]
        atlas.pages[b][y : y + h, x : x + w] = img
        atlas.placements[pid] = Placement(page=b, x=x, y=y, width=w, height=h, scale=scales[pid])
    if any(it.normal is not None for it in items if it.textured):
        atlas.normal_pages = _normal_pages(items, atlas, pad)
    return atlas


def _normal_pages(items: list[PolygonTexture], atlas: Atlas, pad: int) -> list[np.ndarray]:
    """The relief normal maps packed like the textures (each resized to its texture's placement)."""
    flat = np.array([0.5, 0.5, 1.0], np.float32)
    pages = [np.broadcast_to(flat, p.shape).copy() for p in atlas.pages]
    for it in items:
        if it.normal is None or not it.textured:
            continue
        pl = atlas.placements[it.polygon.id]
        h, w = pl.height - 2 * pad, pl.width - 2 * pad
        n = it.normal
        if n.shape[:2] != (h, w):  # a texture shrunk to fit its page: nearest keeps the steps
            iy = np.minimum(((np.arange(h) + 0.5) * n.shape[0] / h).astype(int), n.shape[0] - 1)
            ix = np.minimum(((np.arange(w) + 0.5) * n.shape[1] / w).astype(int), n.shape[1] - 1)
            n = n[iy][:, ix]
        pages[pl.page][pl.y : pl.y + pl.height, pl.x : pl.x + pl.width] = dilate(n, None, pad)
    return pages


# ---------------------------------------------------------------------------------------------
# Geometry


def is_convex(polygon: Polygon) -> bool:
    if polygon.holes:
        return False
    p = polygon.to_plane(polygon.outer)
    d1 = np.roll(p, -1, axis=0) - p
    d2 = np.roll(d1, -1, axis=0)
    cross = d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0]
    tol = 1e-12 * float(np.abs(cross).max() or 1.0)
    return bool((cross >= -tol).all() or (cross <= tol).all())


def vertex_uvs(
    item: PolygonTexture, verts: np.ndarray, place: Placement, page_size: tuple[int, int], pad: int
) -> np.ndarray:
    """OBJ/trimesh UVs (v up) of world points on the polygon: frame texel -> atlas texel -> [0, 1]."""
    pw, ph = page_size
    if item.textured:
        t = item.frame.world_to_texel(verts) * place.scale
        ax = place.x + pad + t[:, 0]
        ay = place.y + pad + t[:, 1]
    else:
        ax = np.full(len(verts), place.x + place.width / 2.0)
        ay = np.full(len(verts), place.y + place.height / 2.0)
    return np.stack([ax / pw, 1.0 - ay / ph], axis=1)


# ---------------------------------------------------------------------------------------------
# Writers


def _fmt(a: np.ndarray) -> str:
    return " ".join(f"{x:.9g}" for x in a)


def write_obj(
    out_dir: Path, items: list[PolygonTexture], atlas: Atlas, page_names: list[str], pad: int, name: str = MODEL_NAME
) -> tuple[Path, Path]:
    from difftex.scene.files import write_text

    mtl_lines = ["# difftex texture atlas materials"]
    for k, png in enumerate(page_names):
        mtl_lines += [f"newmtl atlas{k}", "Ka 1 1 1", "Kd 1 1 1", "Ks 0 0 0", "d 1", "illum 1", f"map_Kd {png}", ""]
    lines = [f"# difftex textured proxy: {len(items)} polygons, {len(page_names)} atlas page(s)", f"mtllib {name}.mtl"]
    nv = nt = nn = 0
    for it in items:
        poly = it.polygon
        place = atlas.placements[poly.id]
        page = atlas.pages[place.page]
        if is_convex(poly):
            verts, faces = poly.outer, [list(range(len(poly.outer)))]
        else:
            verts, tris = triangulate(poly)
            faces = tris.tolist()
        uv = vertex_uvs(it, verts, place, (page.shape[1], page.shape[0]), pad)
        lines += [f"o {poly.id}", f"g {poly.id}", f"usemtl atlas{place.page}"]
        lines += [f"v {_fmt(v)}" for v in verts]
        lines += [f"vt {_fmt(t)}" for t in uv]
        lines.append(f"vn {_fmt(poly.normal)}")
        nn += 1
        for f in faces:
            lines.append("f " + " ".join(f"{nv + i + 1}/{nt + i + 1}/{nn}" for i in f))
        nv += len(verts)
        nt += len(verts)
    obj, mtl = out_dir / f"{name}.obj", out_dir / f"{name}.mtl"
    write_text(mtl, "\n".join(mtl_lines))
    write_text(obj, "\n".join(lines) + "\n")
    return obj, mtl


def write_glb(
    path: Path,
    items: list[PolygonTexture],
    atlas: Atlas,
    page_paths: list[Path],
    pad: int,
    transform: np.ndarray | None = None,
    normal_paths: list[Path] | None = None,
) -> None:
    """One glTF node/mesh per polygon (named by its id); one PBR material per atlas page.
    ``transform`` (4 x 4): every node's matrix (a 3D Tiles tile's z-up to glTF y-up); None: identity.
    ``normal_paths``: the relief's normal-map pages, the materials' ``normalTexture`` (viewers
    shade the recesses and balconies the flat proxy lacks)."""
    import trimesh
    from PIL import Image

    from difftex.scene.files import atomic_path

    def load(png: Path):
        img = Image.open(png)
        img.load()
        return img

    materials = []
    for k, png in enumerate(page_paths):
        normal = {"normalTexture": load(normal_paths[k])} if normal_paths else {}
        materials.append(
            trimesh.visual.material.PBRMaterial(
                name=f"atlas{k}", baseColorTexture=load(png), metallicFactor=0.0, roughnessFactor=1.0,
                doubleSided=False, **normal,
            )
        )
    scene = trimesh.Scene()
    for it in items:
        poly = it.polygon
        place = atlas.placements[poly.id]
        page = atlas.pages[place.page]
        verts, tris = triangulate(poly)
        uv = vertex_uvs(it, verts, place, (page.shape[1], page.shape[0]), pad)
        normals = np.repeat(poly.normal[None], len(verts), axis=0)
        mesh = trimesh.Trimesh(
            vertices=verts,
            faces=tris,
            vertex_normals=normals,
            visual=trimesh.visual.TextureVisuals(uv=uv, material=materials[place.page]),
            process=False,
        )
        scene.add_geometry(mesh, geom_name=poly.id, node_name=poly.id, transform=transform)
    with atomic_path(path) as tmp:
        tmp.write_bytes(scene.export(file_type="glb"))


# ---------------------------------------------------------------------------------------------


def assemble(
    items: list[PolygonTexture],
    out_dir: str | Path,
    cfg: AssembleConfig = AssembleConfig(),
    name: str = MODEL_NAME,
    bits: int = 8,
) -> dict:
    """Write atlas pages, OBJ + MTL and GLB for ``items`` into ``out_dir``; return the summary."""
    from difftex.scene.files import write_image

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    if not items:
        raise DifftexError(f"{out_dir}: no polygons to assemble")
    pad = int(cfg.padding)
    atlas = build_atlas(items, cfg)
    for stale in out_dir.glob(f"{name}_atlas*.png"):
        stale.unlink()  # pages of an earlier run with more pages (or with normal maps)
    page_paths = []
    for k, page in enumerate(atlas.pages):
        p = out_dir / f"{name}_atlas{k}.png"
        write_image(p, page, bits=bits)
        page_paths.append(p)
    normal_paths = []
    for k, page in enumerate(atlas.normal_pages or []):
        p = out_dir / f"{name}_atlas{k}_normal.png"
        write_image(p, page, bits=8)
        normal_paths.append(p)
    obj, mtl = write_obj(out_dir, items, atlas, [p.name for p in page_paths], pad, name=name)
    summary = {
        "obj": obj.name,
        "mtl": mtl.name,
        "atlas_pages": [
            {"file": p.name, "width": pg.shape[1], "height": pg.shape[0]} for p, pg in zip(page_paths, atlas.pages)
        ],
        "polygons": [],
    }
    if normal_paths:
        summary["normal_pages"] = [p.name for p in normal_paths]
    for it in items:
        pl = atlas.placements[it.polygon.id]
        summary["polygons"].append(
            {
                "id": it.polygon.id,
                "textured": it.textured,
                "coverage": round(float(it.coverage), 4),
                "photos": int(it.photos),
                "area": round(float(it.polygon.area), 6),
                "texture_size": list(it.texture.shape[1::-1]) if it.textured else None,
                "page": pl.page,
                "rect": [pl.x, pl.y, pl.width, pl.height],
                "scale": round(pl.scale, 6),
            }
        )
    summary["untextured"] = [it.polygon.id for it in items if not it.textured]
    total = sum(it.polygon.area for it in items)
    summary["textured_area_share"] = round(
        sum(it.polygon.area * it.coverage for it in items if it.textured) / max(total, 1e-12), 4
    )
    if cfg.glb:
        glb = out_dir / f"{name}.glb"
        write_glb(glb, items, atlas, page_paths, pad, normal_paths=normal_paths or None)
        summary["glb"] = glb.name
        if cfg.verify:
            from difftex.export.check import verify_glb

            summary["check"] = verify_glb(glb, items)
    return summary
