"""A COLMAP-like dense reconstruction of a synthetic scene, written beside it in ``<scene>/dense/``.

Real scenes may come with one (docs/dense.md); a synthetic scene gets the equivalent from the
detailed model its photos were rendered from (rebuilt from ``synth.json``, not rendered), as
COLMAP's ``stereo_fusion`` and ``poisson_mesher`` would leave it:

- ``fused.ply``: points on the surfaces that at least two photos see, about one per pixel
  footprint (a voxel grid at the photos' median ground sampling distance), moved by Gaussian
  noise along the ray of the photo that found them (a depth error), normals towards that photo,
  the model's albedo as colour; none on glass (stereo fails on its reflections), ground only
  near the building.
- ``meshed-poisson.ply``: pymeshlab's screened Poisson surface of the cloud, less its faces far
  from every point. ``dense.json``: sizes, settings and seconds.

Mitsuba (LLVM) casts the rays against the scene the photos were rendered from: per photo a
jittered grid of pixel rays finds surface samples, a voxel grid keeps the most frontal one per
voxel, and shadow rays from the other photos' centres find a second photo that sees it.
Everything random is drawn from the scene's seed.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from difftex.errors import DifftexError
from difftex.layout import DENSE_RECORD

GLASS_FRAME = 0.07  # facades._window's frame width: the glass is an opening's rectangle less it
COLOUR_SOURCE = "albedo of the detailed model (sRGB, unshaded)"
_FACE, _PLAIN, _OCCLUDER, _GROUND = 1, 2, 3, 4  # kinds of the Mitsuba scene's shapes
_VOXEL_BITS = 21  # per axis in a voxel key: 2M voxels, 20 km at 1 cm
_SAMPLE_KEYS = ("X", "n", "d", "ptr", "uv", "score", "photo", "sid")  # what a surface sample carries


@dataclass(frozen=True)
class DenseSettings:
    """How the reconstruction is simulated; every length in scene units (metres)."""

    noise: float = 0.015  # std of the depth error along the viewing ray
    stride: int = 0  # one ray per stride x stride pixels (jittered); 0: from the photo count
    ground_margin: float = 4.0  # ground points within this distance of the footprint
    max_incidence_deg: float = 80.0  # views more grazing than this do not reconstruct a point
    mesh_detail: float = 0.05  # Poisson octree cell aimed at (its depth follows from the extent)
    mesh_max_depth: int = 11
    trim_voxels: float = 3.0  # mesh faces farther than this many voxels from every point go


@dataclass
class View:
    """A photo's true camera: ``R``, ``t`` cam_from_world, ``camera`` a pycolmap.Camera."""

    name: str
    R: np.ndarray  # (3, 3)
    t: np.ndarray  # (3,)
    camera: Any

    @property
    def centre(self) -> np.ndarray:
        return -self.R.T @ self.t


@dataclass
class Source:
    """A synthetic building as the photos show it: the detailed model and the true cameras."""

    building: Any  # difftex.synth.buildings.Building
    layouts: dict  # face id -> facades.Layout
    model: Any  # detail.DetailedModel
    ground: np.ndarray  # (h, w, 3) linear albedo, tiled every 6 m
    ground_size: float
    lighting: dict
    occluders: bool
    views: list[View]
    seed: int
    building_index: int


@dataclass
class Cloud:
    """A fused cloud: ``xyz`` (N, 3) float64, ``normals`` (N, 3) float32 unit, ``rgb`` (N, 3)
    uint8, ``photo`` (N,) int32 index of the photo whose ray found each point."""

    xyz: np.ndarray
    normals: np.ndarray
    rgb: np.ndarray
    photo: np.ndarray
    stats: dict


def source_from_model(cfg, spec, seed: int, building_index: int, views: list[View]) -> Source:
    """The detailed model of building ``spec`` (rebuilt as ``difftex synth`` built it) seen by ``views``."""
    from difftex.synth.pipeline import build_model

    building, layouts, _, model, ground, ground_size, lighting, _, _ = build_model(cfg, spec, seed, building_index)
    return Source(building, layouts, model, ground, ground_size, lighting, bool(cfg.occluders), views, int(seed),
                  int(building_index))


def read_manifest(scene_dir: str | Path) -> tuple:
    """What a ``difftex synth`` building scene's ``synth.json`` says about its model and photos.

    Returns:
        (SynthConfig, BuildingSpec, seed, building index, views): the arguments of
        :func:`source_from_model`.

    Raises:
        DifftexError: the folder is not such a scene (one line naming what is missing).
    """
    from difftex.synth.cameras import Intrinsics
    from difftex.synth.presets import BuildingSpec, SynthConfig

    scene = Path(scene_dir)
    path = scene / "synth.json"
    if not scene.is_dir():
        raise DifftexError(f"{scene}: not a folder")
    if not path.is_file():
        hint = "; give one building's folder" if any(scene.glob("*/synth.json")) else ""
        raise DifftexError(f"{path}: missing (not a `difftex synth` building scene{hint})")
    try:
        meta = json.loads(path.read_text())
        conf = dict(meta["config"])
        specs = tuple(BuildingSpec(**b) for b in conf.pop("buildings"))
        names = set(SynthConfig.__dataclass_fields__)  # a manifest's keys this version does not know are dropped
        cfg = SynthConfig(buildings=specs, **{k: v for k, v in conf.items() if k in names})
        spec = next(b for b in specs if b.name == meta["building"]["name"])
        cams = {c["camera_id"]: Intrinsics(c["camera_id"], c["width"], c["height"], c["f"], c["k"]).pycolmap()
                for c in meta["cameras"]}
        views = [View(v["name"], np.array(v["R_true"], float), np.array(v["t_true"], float), cams[v["camera_id"]])
                 for v in meta["views"]]
        seed, index = int(meta["seed"]), int(meta["building_index"])
    except (ValueError, KeyError, TypeError, StopIteration) as exc:
        what = f"no {exc}" if isinstance(exc, KeyError) else type(exc).__name__
        raise DifftexError(f"{path}: not the manifest of a `difftex synth` building scene ({what})") from None
    if not views:
        raise DifftexError(f"{path}: no photos")
    return cfg, spec, seed, index, views


def load_source(scene_dir: str | Path) -> Source:
    """A ``difftex synth`` building scene's model (rebuilt, not rendered) and true cameras."""
    return source_from_model(*read_manifest(scene_dir))


class _Caster:
    """The scene the photos were rendered from, in Mitsuba, with what each shape is."""

    def __init__(self, src: Source):
        import drjit as dr
        import mitsuba as mi

        from difftex.synth import render as rd

        if rd.choose_variant("auto") != "llvm_ad_rgb":
            raise DifftexError("synth-dense: Mitsuba's llvm_ad_rgb variant does not run here (apt-get install "
                               "libllvm19); casting millions of rays needs it")
        self.mi, self.dr = mi, dr
        mi.set_variant("llvm_ad_rgb")
        self.scene = rd.build_scene("llvm_ad_rgb", src.model, src.ground, src.ground_size, src.lighting,
                                    occluders=src.occluders)
        faces = {f.id: k for k, f in enumerate(src.building.faces)}
        shapes = self.scene.shapes()
        ptrs = [int(dr.reinterpret_array(mi.UInt32, mi.ShapePtr(s))[0]) for s in shapes]
        # Per shape pointer (Mitsuba's registry index; 0 is a miss): kind, face index, albedo.
        self.kind = np.zeros(max(ptrs) + 1, np.int8)
        self.face = np.full(len(self.kind), -1, np.int32)
        self.part: list[Any] = [None] * len(self.kind)
        self.colour = np.zeros((len(self.kind), 3), np.float32)
        for s, p in zip(shapes, ptrs):
            name = s.id()
            if name == "ground":
                self.kind[p] = _GROUND
            elif name.startswith("occ"):
                self.kind[p] = _OCCLUDER
                self.colour[p] = src.model.occluders[int(name[3:])].color
            elif name.startswith("part"):
                part = src.model.parts[int(name[4:])]
                self.part[p] = part
                if part.bitmap is not None:
                    self.kind[p], self.face[p] = _FACE, faces[part.name.removeprefix("face_")]
                else:
                    self.kind[p], self.colour[p] = _PLAIN, part.color

    def _ray(self, origin: np.ndarray, dirs: np.ndarray, maxt: np.ndarray | None = None):
        mi = self.mi
        o = np.broadcast_to(np.asarray(origin, np.float32), dirs.shape)
        ray = mi.Ray3f(mi.Point3f(*[o[:, k].copy() for k in range(3)]),
                       mi.Vector3f(*[dirs[:, k].astype(np.float32) for k in range(3)]))
        if maxt is not None:
            ray.maxt = mi.Float(maxt.astype(np.float32))
        return ray

    def hit(self, origin: np.ndarray, dirs: np.ndarray) -> dict[str, np.ndarray]:
        """First hits of rays from ``origin`` (3,) along unit ``dirs`` (N, 3): ``t`` (N,) (inf:
        miss), ``ptr`` (N,) shape pointer, ``n`` (N, 3) geometric normal, ``uv`` (N, 2)."""
        si = self.scene.ray_intersect(self._ray(origin, dirs))
        t = np.array(si.t, np.float64)
        t[~np.array(si.is_valid())] = np.inf
        ptr = np.array(self.dr.reinterpret_array(self.mi.UInt32, si.shape), np.int64)
        n = np.stack([np.array(si.n.x), np.array(si.n.y), np.array(si.n.z)], 1)
        return {"t": t, "ptr": ptr, "n": n, "uv": np.stack([np.array(si.uv.x), np.array(si.uv.y)], 1)}

    def blocked(self, origin: np.ndarray, dirs: np.ndarray, maxt: np.ndarray) -> np.ndarray:
        """Whether anything lies on each ray before ``maxt`` (N,): a shadow ray per point."""
        return np.array(self.scene.ray_test(self._ray(origin, dirs, maxt)), bool)


def _pixel_rays(view: View, stride: int, rng: np.random.Generator):
    """World directions (N, 3) of one jittered ray per ``stride`` x ``stride`` pixel cell, and
    each one's 1 / |(x, y, 1)| (z-depth per unit distance)."""
    cam = view.camera
    gx, gy = np.meshgrid(np.arange(0, cam.width, stride), np.arange(0, cam.height, stride))
    xy = np.stack([gx.ravel(), gy.ravel()], 1).astype(np.float64)
    xy = np.minimum(xy + rng.uniform(0, stride, xy.shape), [cam.width - 1e-3, cam.height - 1e-3])
    xn = np.asarray(cam.cam_from_img(xy), np.float64)
    d_cam = np.column_stack([xn, np.ones(len(xn))])
    inv = 1.0 / np.linalg.norm(d_cam, axis=1)
    return (d_cam * inv[:, None]) @ view.R, inv  # R^T d_cam, row-wise


def _glass(src: Source, face_index: np.ndarray, X: np.ndarray) -> np.ndarray:
    """Whether each point of a face part (its wall or an opening's back pane) is on glass: inside
    a window's or shop front's painted pane, the opening less its frame (facades._window)."""
    out = np.zeros(len(X), bool)
    for k in np.unique(face_index):
        face = src.building.faces[k]
        lay = src.layouts[face.id]
        sel = np.nonzero(face_index == k)[0]
        uv = face.to2d(X[sel])
        g = np.zeros(len(sel), bool)
        for u0, v0, u1, v1 in lay.windows + lay.shopfronts:
            g |= ((uv[:, 0] > u0 + GLASS_FRAME) & (uv[:, 0] < u1 - GLASS_FRAME)
                  & (uv[:, 1] > v0 + GLASS_FRAME) & (uv[:, 1] < v1 - GLASS_FRAME))
        out[sel] = g
    return out


def _samples(src: Source, caster: _Caster, i: int, stride: int, s: DenseSettings, rng, near) -> dict:
    """Surface samples of photo ``i``'s pixel rays that stereo could reconstruct, and counts of
    those dropped: glass, grazing views, ground far from the building."""
    import shapely

    view = src.views[i]
    dirs, inv = _pixel_rays(view, stride, rng)
    h = caster.hit(view.centre, dirs)
    ok = np.isfinite(h["t"])
    X = view.centre + h["t"][:, None] * dirs
    n = h["n"] * -np.sign(np.sum(h["n"] * dirs, 1))[:, None]  # towards the photo (shapes are two-sided)
    cos = -np.sum(n * dirs, 1)
    kind = caster.kind[h["ptr"]]
    glass = ok & (kind == _FACE)
    glass[glass] = _glass(src, caster.face[h["ptr"][glass]], X[glass])
    far = ok & (kind == _GROUND)
    far[far] = ~shapely.contains_xy(near, X[far, 0], X[far, 1])
    grazing = ok & ~glass & ~far & (cos < np.cos(np.deg2rad(s.max_incidence_deg)))
    keep = ok & ~glass & ~far & ~grazing
    return {"X": X[keep], "n": n[keep].astype(np.float32), "d": dirs[keep].astype(np.float32),
            "ptr": h["ptr"][keep], "uv": h["uv"][keep].astype(np.float32), "score": cos[keep].astype(np.float32),
            "gsd": h["t"][keep] * inv[keep] / float(view.camera.mean_focal_length()),
            "photo": np.full(int(keep.sum()), i, np.int32),
            "sid": (np.int64(i) << 32) + np.nonzero(keep)[0].astype(np.int64),
            "rays": len(dirs),
            "dropped": {"glass": int(glass.sum()), "grazing": int(grazing.sum()), "far_ground": int(far.sum())}}


def _thin(acc: dict, origin: np.ndarray, voxel: float) -> dict:
    """One sample per voxel: the most frontal, ties to the first cast (so batching does not matter)."""
    q = np.clip(np.floor((acc["X"] - origin) / voxel), 0, (1 << _VOXEL_BITS) - 1).astype(np.int64)
    key = (q[:, 0] << (2 * _VOXEL_BITS)) | (q[:, 1] << _VOXEL_BITS) | q[:, 2]
    order = np.lexsort((acc["sid"], -acc["score"], key))
    first = order[np.r_[True, key[order][1:] != key[order][:-1]]]
    return {k: v[first] for k, v in acc.items()}


def _seen_twice(src: Source, caster: _Caster, pts: dict, s: DenseSettings) -> tuple[np.ndarray, int]:
    """Whether a photo besides the one that found each point sees it: in front of it, inside its
    image, not more grazing than ``max_incidence_deg`` and nothing between. Returns the mask (N,)
    and the number of shadow rays cast. A point leaves the test once a second photo sees it."""
    X, n, photo = pts["X"], pts["n"].astype(np.float64), pts["photo"]
    seen = np.zeros(len(X), bool)
    cos_min = np.cos(np.deg2rad(s.max_incidence_deg))
    rays = 0
    for j, view in enumerate(src.views):
        idx = np.nonzero(~seen & (photo != j))[0]
        if len(idx) == 0:
            break
        cam = view.camera
        Xc = X[idx] @ view.R.T + view.t
        idx, Xc = idx[Xc[:, 2] > 0.05], Xc[Xc[:, 2] > 0.05]
        if len(idx) == 0:
            continue
        xy = np.asarray(cam.img_from_cam(Xc), np.float64)
        inside = (xy[:, 0] >= 0) & (xy[:, 0] < cam.width) & (xy[:, 1] >= 0) & (xy[:, 1] < cam.height)
        v = view.centre - X[idx]
        dist = np.linalg.norm(v, axis=1)
        facing = np.sum(n[idx] * v, 1) >= cos_min * dist  # signed: a point's back side is not seen
        idx, v, dist = idx[inside & facing], v[inside & facing], dist[inside & facing]
        if len(idx) == 0:
            continue
        # The shadow ray stops 1 cm short of the point: its own surface must not block it.
        seen[idx] = ~caster.blocked(view.centre, -v / dist[:, None], dist - 0.01)
        rays += len(idx)
    return seen, rays


def _albedo(src: Source, caster: _Caster, ptr: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """sRGB 8-bit albedo (N, 3) of each hit: its part's bitmap at the hit's uv (Mitsuba's v = 0 is
    row 0), a constant colour, or the ground's tiled bitmap."""
    from difftex.synth.render import to_srgb

    lin = caster.colour[ptr].copy()

    def sample(img: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        h, w = img.shape[:2]
        return img[np.clip((v * h).astype(int), 0, h - 1), np.clip((u * w).astype(int), 0, w - 1)]

    for p in np.unique(ptr):
        sel = ptr == p
        if caster.kind[p] == _FACE:
            lin[sel] = sample(caster.part[p].bitmap, uv[sel, 0], uv[sel, 1])
        elif caster.kind[p] == _GROUND:  # build_scene tiles the ground bitmap every 6 m
            tiled = np.mod(uv[sel] * (src.ground_size / 6.0), 1.0)
            lin[sel] = sample(src.ground, tiled[:, 0], tiled[:, 1])
    return (np.clip(to_srgb(lin), 0, 1) * 255).round().astype(np.uint8)


def fuse(src: Source, s: DenseSettings = DenseSettings(), progress=None) -> Cloud:
    """The fused cloud of ``src`` as stereo fusion would give it (module docstring).

    Args:
        src: the model and the true cameras.
        s: the settings.
        progress: called with (done, total) photo passes, or None.

    Returns:
        The cloud (N points, possibly 0) and its statistics.
    """
    import shapely

    t0 = time.perf_counter()
    caster = _Caster(src)
    rng = np.random.default_rng([src.seed, src.building_index, 0xD3E5])
    # A surface seen by a twelfth of the photos still gets about a sample per voxel.
    stride = s.stride or int(np.clip(round(np.sqrt(len(src.views) / 12.0)), 1, 8))
    near = src.building.footprint.buffer(s.ground_margin)
    shapely.prepare(near)  # contains_xy on many points
    # The voxel (the photos' median ground sampling distance) from a coarse pass first.
    gsd = np.concatenate([_samples(src, caster, i, 16, s, rng, near)["gsd"] for i in range(len(src.views))])
    if len(gsd) == 0:
        raise DifftexError("synth-dense: no photo sees the building")
    voxel = float(np.median(gsd))
    lo = src.building.bounds()[0] - 100.0  # voxel keys need non-negative indices
    dropped = {"glass": 0, "grazing": 0, "far_ground": 0}
    kept: dict | None = None
    batch: list[dict] = []
    rays = 0
    for i in range(len(src.views)):
        smp = _samples(src, caster, i, stride, s, rng, near)
        rays += smp["rays"]
        dropped = {k: n + smp["dropped"][k] for k, n in dropped.items()}
        batch.append(smp)
        if len(batch) == 16 or i == len(src.views) - 1:  # bounded memory: thin every 16 photos
            parts = ([kept] if kept else []) + batch
            kept = _thin({k: np.concatenate([p[k] for p in parts]) for k in parts[0] if k in _SAMPLE_KEYS}, lo, voxel)
            batch = []
        if progress:
            progress(i + 1, 2 * len(src.views))
    assert kept is not None
    t1 = time.perf_counter()
    seen, shadow_rays = _seen_twice(src, caster, kept, s)
    if progress:
        progress(2 * len(src.views), 2 * len(src.views))
    pts = {k: v[seen] for k, v in kept.items()}
    noise = np.random.default_rng([src.seed, src.building_index, 0x0415E]).normal(0.0, s.noise, len(pts["X"]))
    xyz = pts["X"] + noise[:, None] * pts["d"]  # a depth error: along the ray of the photo that found it
    stats = {"photos": len(src.views), "stride": stride, "voxel": voxel, "primary_rays": rays,
             "shadow_rays": shadow_rays, "voxels_sampled": int(len(seen)), "single_view": int((~seen).sum()),
             "dropped_samples": dropped, "cast_s": t1 - t0, "visibility_s": time.perf_counter() - t1}
    return Cloud(xyz, pts["n"], _albedo(src, caster, pts["ptr"], pts["uv"]), pts["photo"], stats)


# --- files ----------------------------------------------------------------------------------------

PLY_CLOUD_DTYPE = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4"),
                            ("red", "u1"), ("green", "u1"), ("blue", "u1")])
_PLY_MESH_DTYPE = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("red", "u1"), ("green", "u1"), ("blue", "u1")])


def ply_header(dtype: np.dtype, n: int, faces: int | None = None) -> bytes:
    """A binary little-endian PLY header: ``n`` vertices with ``dtype``'s float / uchar fields, and
    ``faces`` triangles. For PLY_CLOUD_DTYPE it is COLMAP stereo_fusion's (WriteBinaryPlyPoints)."""
    props = "".join(f"property {'float' if dtype[k].kind == 'f' else 'uchar'} {k}\n" for k in dtype.names)
    tris = "" if faces is None else f"element face {faces}\nproperty list uchar int vertex_indices\n"
    return f"ply\nformat binary_little_endian 1.0\nelement vertex {n}\n{props}{tris}end_header\n".encode("ascii")


def _write_ply(path: str | Path, dtype: np.dtype, columns: list, faces: np.ndarray | None = None) -> None:
    """Vertices (one array (N,) per field of ``dtype``) and triangles (F, 3), written atomically."""
    from difftex.scene.files import atomic_path

    rec = np.empty(len(columns[0]), dtype)
    for name, col in zip(dtype.names, columns):
        rec[name] = col
    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        f.write(ply_header(dtype, len(rec), None if faces is None else len(faces)))
        f.write(rec.tobytes())
        if faces is not None:
            tri = np.empty(len(faces), np.dtype([("n", "u1"), ("v", "<i4", (3,))]))
            tri["n"], tri["v"] = 3, faces
            f.write(tri.tobytes())


def write_fused_ply(path: str | Path, cloud: Cloud) -> None:
    """``cloud`` as COLMAP's ``fused.ply``: binary little endian, float xyz and normals, uchar rgb."""
    _write_ply(path, PLY_CLOUD_DTYPE, [*cloud.xyz.T, *cloud.normals.T, *cloud.rgb.T])


def write_mesh_ply(path: str | Path, V: np.ndarray, F: np.ndarray, rgb: np.ndarray) -> None:
    """A mesh as binary PLY: vertices ``V`` (V, 3) with colours ``rgb`` (V, 3) uint8, triangles ``F`` (F, 3)."""
    _write_ply(path, _PLY_MESH_DTYPE, [*V.T, *rgb.T], F)


def poisson_mesh(cloud: Cloud, s: DenseSettings = DenseSettings()):
    """Screened Poisson surface (pymeshlab) of ``cloud``, trimmed of faces farther than
    ``trim_voxels`` voxels (at least 4 noise stds) from every point.

    Returns:
        (vertices (V, 3) float64, faces (F, 3) int64, colours (V, 3) uint8, stats dict).
    """
    # OpenMP's busy waiting made Poisson 10x slower on a shared, loaded machine; passive waits
    # cost nothing when it is idle. Only takes effect if pymeshlab is not loaded yet.
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    import pymeshlab
    from scipy.spatial import cKDTree

    extent = float(np.ptp(cloud.xyz, axis=0).max()) * 1.1  # pymeshlab's default scale
    depth = int(np.clip(np.ceil(np.log2(max(extent, 1e-6) / s.mesh_detail)), 5, s.mesh_max_depth))
    rgba = np.column_stack([cloud.rgb / 255.0, np.ones(len(cloud.rgb))])
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=cloud.xyz, v_normals_matrix=cloud.normals.astype(np.float64),
                               v_color_matrix=rgba))
    ms.generate_surface_reconstruction_screened_poisson(depth=depth, preclean=True, threads=os.cpu_count() or 1)
    m = ms.current_mesh()
    V, F = np.asarray(m.vertex_matrix(), np.float64), np.asarray(m.face_matrix(), np.int64)
    rgb = (np.clip(np.asarray(m.vertex_color_matrix())[:, :3], 0, 1) * 255).round().astype(np.uint8)
    trim = max(s.trim_voxels * cloud.stats["voxel"], 4 * s.noise)
    far = cKDTree(cloud.xyz).query(V, distance_upper_bound=trim)[0] > trim
    keep = ~far[F].any(1)
    used = np.unique(F[keep])
    remap = np.full(len(V), -1, np.int64)
    remap[used] = np.arange(len(used))
    stats = {"depth": depth, "octree_cell": extent / 2**depth, "trim_distance": trim,
             "faces_before_trim": int(len(F)), "trimmed_faces": int((~keep).sum())}
    return V[used], remap[F[keep]], rgb[used], stats


def write_dense(scene_dir: str | Path, s: DenseSettings = DenseSettings(), progress=None) -> dict:
    """Write ``fused.ply``, ``meshed-poisson.ply`` and, last, ``dense.json`` into ``<scene_dir>/dense/``,
    each under a temporary name renamed into place.

    Args:
        scene_dir: a ``difftex synth`` building scene.
        s: the settings.
        progress: called with (done, total) photo passes, or None.

    Returns:
        The summary written to ``dense.json``.
    """
    from difftex.scene.files import write_json

    t0 = time.perf_counter()
    src = load_source(scene_dir)
    t_model = time.perf_counter() - t0
    cloud = fuse(src, s, progress)
    if len(cloud.xyz) < 100:
        raise DifftexError(f"{scene_dir}: only {len(cloud.xyz)} point(s) seen by two photos; no dense reconstruction")
    out = Path(scene_dir) / "dense"
    write_fused_ply(out / "fused.ply", cloud)
    t1 = time.perf_counter()
    V, F, rgb, mesh = poisson_mesh(cloud, s)
    write_mesh_ply(out / "meshed-poisson.ply", V, F, rgb)
    st = cloud.stats
    summary = {
        "generator": "difftex synth-dense", "seed": src.seed, "building_index": src.building_index,
        "settings": asdict(s), "points": int(len(cloud.xyz)), "noise": s.noise, "voxel": st["voxel"],
        "stride": st["stride"], "photos": st["photos"], "colour": COLOUR_SOURCE,
        "rays": {"primary": st["primary_rays"], "shadow": st["shadow_rays"]},
        "dropped": {**st["dropped_samples"], "single_view_points": st["single_view"]},
        "mesh": {"vertices": int(len(V)), "faces": int(len(F)), **mesh},
        "seconds": {"model": t_model, "cast": st["cast_s"], "visibility": st["visibility_s"],
                    "mesh": time.perf_counter() - t1, "total": time.perf_counter() - t0},
    }
    write_json(out / DENSE_RECORD, summary)  # the record, as the GPU stage names its own
    return summary
