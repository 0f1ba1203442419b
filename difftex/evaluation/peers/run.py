"""A peer texturing program (texrecon, MeshLab) run on a scene and turned into a difftex results folder.

Every peer runs the same way, so that it is scored by the same code as difftex
(``difftex evaluate``) and timed the same way:

1. **prepare** (difftex, in this process): the photos are resampled as ideal pinhole cameras
   (:mod:`difftex.geometry.pinhole`), the proxy is ear-clipped and subdivided (:mod:`difftex.geometry.meshing`),
   and the peer's own input files are written;
2. **peer** (the program, a child process): its wall time, and the CPU time and peak memory of
   its process tree (``getrusage(RUSAGE_CHILDREN)`` of a launcher that only waits for it: user +
   system CPU of the program and every descendant it waited for);
3. **import** (difftex): the textured OBJ is read back into every polygon's UV frame
   (:mod:`difftex.evaluation.peers.objimport`), unseen texels are filled like difftex's own, and the usual
   ``textures/<pid>/`` files are written.

The folder is built beside ``out`` and renamed onto it only when everything succeeded, so a
failed peer never leaves a half-written results folder. ``out/peer.json`` holds the settings and
the three phases' figures; ``out/work/`` the peer's inputs (photos removed unless kept), output
and log.
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from difftex.errors import DifftexError
from difftex.evaluation.peers.measure import Phase, measure_self
from difftex.layout import Results, visibility_file

PEERS = ("texrecon", "meshlab-face", "meshlab-blend", "reprojection")
LABELS = {"texrecon": "texrecon (mvs-texturing)", "meshlab-face": "MeshLab per-face raster parameterization",
          "meshlab-blend": "MeshLab per-texel raster blend",
          "reprojection": "reprojection (texrecon on the dense mesh, baked)"}


@dataclass(frozen=True)
class PeerConfig:
    """How a peer is run (``difftex peer`` options)."""

    photo_long_side: int | None = None  # resample photos to this long side (None: their own resolution)
    max_edge: float | None = None  # mesh edge bound in scene units (None: from the camera distance)
    max_edge_rel: float = 1 / 20  # ... as this share of the median camera-to-proxy distance
    oversample: int = 2  # MeshLab atlases get this many texels per frame texel along each axis (reprojection: rays)
    max_texture: int = 8192  # MeshLab atlas side limit
    threads: int = 0  # the peer's threads (texrecon --num_threads); 0: its default
    timeout_s: float = 3600.0
    keep_inputs: bool = False  # keep the resampled photos under work/
    dense_mesh: str | None = None  # reprojection: the dense mesh (None: the scene's, reprojection.find_mesh)
    max_faces: int = 500_000  # reprojection: the dense mesh is decimated to at most this many triangles
    relief: float = 1.0  # reprojection: the bake sees surfaces within this many scene units of the plane

    def __post_init__(self):
        if self.photo_long_side is not None and not 16 <= int(self.photo_long_side) <= 65536:
            raise ValueError(f"photo_long_side must be in 16..65536, got {self.photo_long_side}")
        if self.max_edge is not None and not self.max_edge > 0:
            raise ValueError(f"max_edge must be > 0, got {self.max_edge}")
        if not 0 < self.max_edge_rel <= 1:
            raise ValueError(f"max_edge_rel must be in (0, 1], got {self.max_edge_rel}")
        if not 1 <= self.oversample <= 8:
            raise ValueError(f"oversample must be in 1..8, got {self.oversample}")
        if not self.timeout_s > 0:
            raise ValueError(f"timeout_s must be > 0, got {self.timeout_s}")
        if not (self.max_faces >= 100 and self.relief > 0):
            raise ValueError(f"max_faces must be >= 100 and relief > 0, got {self.max_faces}, {self.relief}")


# --------------------------------------------------------------------------------------------
# Inputs shared by the peers


def peer_photos(scene, photos_table: str | Path | None):
    """The photos a peer gets: those the filter kept (``photos.json``), else every registered photo.

    A peer textures the whole mesh at once, so the filter's per-polygon angle limits do not
    apply; it gets the globally kept photos (not blurry, seeing some polygon).
    """
    from difftex.scene.files import read_json

    if photos_table is None:
        return list(scene.photos)
    table = read_json(photos_table)
    try:
        kept = {r["name"] for r in table["photos"] if r["kept"]}
    except (KeyError, TypeError):
        raise DifftexError(f"{photos_table}: not a difftex filter table") from None
    photos = [p for p in scene.photos if p.name in kept]
    if not photos:
        raise DifftexError(f"{photos_table}: keeps no photo of {scene.root}")
    return photos


def export_photos(photos, folder: Path, long_side: int | None) -> list:
    """Resample every photo as an ideal pinhole camera into ``folder/v00000.png``, ...; their cameras.

    Sequential names keep the peers' name matching simple (texrecon pairs a .cam file with the
    image whose name starts like it).
    """
    from difftex.geometry.pinhole import ideal_camera, resample
    from difftex.scene.files import read_image

    folder.mkdir(parents=True, exist_ok=True)
    cams = []
    for i, ph in enumerate(photos):
        cam = ideal_camera(ph, long_side)
        write_fast_png(folder / f"v{i:05d}.png", resample(ph, cam, read_image(ph.image_path, (ph.width, ph.height))))
        cams.append(cam)
    return cams


def write_fast_png(path: Path, img: np.ndarray) -> None:
    """8-bit PNG at zlib level 1, atomically.

    difftex.scene.files.write_image uses the default level 6, 3.5x slower on a 6-megapixel photo (2.4 s
    against 0.7 s, files 9 % smaller); these photos are written once and read once by the peer.
    """
    import OpenImageIO as oiio

    from difftex.scene.files import atomic_path

    u8 = np.ascontiguousarray((np.clip(img, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8))
    with atomic_path(path) as tmp:
        out = oiio.ImageOutput.create(str(tmp))
        spec = oiio.ImageSpec(u8.shape[1], u8.shape[0], 3, oiio.UINT8)
        spec.attribute("png:compressionLevel", 1)
        if out is None or not out.open(str(tmp), spec) or not out.write_image(u8):
            raise DifftexError(f"{path}: cannot write image ({oiio.geterror().strip()})")
        out.close()


@dataclass
class Frames:
    """The polygons to texture: their UV frames and texel masks, and where the frames come from."""

    frames: dict
    masks: dict
    visibility: Path | None  # an existing visibility folder (results link it), or None


def frames_for(
    scene, visibility: str | Path | None, polygons: list[str] | None, long_side: int | None, density: float | None
) -> Frames:
    """Frames from a visibility folder (every polygon some photo sees), or computed at a resolution."""
    from difftex.geometry.frames import texel_mask, uv_frame
    from difftex.geometry.visibility import load_visibility

    ids = scene.proxy.ids
    if polygons:
        bad = [p for p in polygons if p not in ids]
        if bad:
            raise DifftexError(f"{scene.proxy.path}: no polygon with id '{bad[0]}'")
    frames, masks = {}, {}
    if visibility is not None:
        vdir = Path(visibility)
        if not vdir.is_dir():
            raise DifftexError(f"{vdir}: visibility folder not found")
        for pid in polygons or ids:
            path = visibility_file(vdir, pid)
            if not path.is_file():
                if polygons:
                    raise DifftexError(f"{path}: visibility file of polygon '{pid}' is missing")
                continue
            v = load_visibility(path)
            if polygons or v.photos:
                frames[pid], masks[pid] = v.frame, v.texel_mask
        if not frames:
            raise DifftexError(f"{vdir}: no polygon visibility files (run difftex visibility)")
        return Frames(frames, masks, vdir.resolve())
    for poly in scene.proxy.polygons:
        if polygons and poly.id not in polygons:
            continue
        fr = uv_frame(poly, scene.up, long_side=None if density else long_side, density=density)
        frames[poly.id], masks[poly.id] = fr, texel_mask(poly, fr)
    return Frames(frames, masks, None)


def write_frames(folder: Path, fr: Frames) -> None:
    """Frame-only visibility files (no candidate photos), so ``difftex evaluate`` finds the frames."""
    from difftex.geometry.visibility import PolygonVisibility, save_visibility

    for pid, frame in fr.frames.items():
        save_visibility(
            visibility_file(folder, pid),
            PolygonVisibility(
                polygon_id=pid,
                frame=frame,
                texel_mask=fr.masks[pid],
                photos=[],
                texel_visible=np.zeros((0, *frame.shape), bool),
                a_bbox=np.zeros((0, 4), np.int64),
                a_masks=[],
            ),
        )


def write_textures(
    out: Path, method: str, fr: Frames, imported: dict, sources: dict | None, names: list[str], extra: dict
) -> dict:
    """textures/<pid>/ for every polygon from the imported (texture, covered) pairs.

    Texels the peer left untextured are filled by push-pull from its textured ones, as difftex
    fills its unseen texels (a polygon it did not texture at all stays mid-grey). ``sources``:
    per polygon the dominant photo index per texel (-1: unknown), for the source map.
    """
    from difftex.compose.fill import finish_texture
    from difftex.compose.outputs import write_texture_outputs

    rows = {}
    res = Results(out)
    for pid, (tex, cov) in imported.items():
        mask = fr.masks[pid]
        U, fill = finish_texture(tex, cov.astype(np.float32), mask)
        if not cov.any():
            U = np.full_like(U, 0.5)
        dom = sources[pid] if sources is not None else np.full(mask.shape, -1)
        dom = np.where(cov, dom, -1)
        rep = {"polygon_id": pid, "method": method, **fill, "peer_coverage": fill["coverage"], **extra}
        write_texture_outputs(res.polygon_textures(pid), U, mask, cov, dom, names if sources is not None else [], rep)
        rows[pid] = round(fill["coverage"], 4)
    return rows


def run_peer(
    method: str,
    scene_dir: str | Path,
    out: str | Path,
    cfg: PeerConfig = PeerConfig(),
    visibility: str | Path | None = None,
    polygons: list[str] | None = None,
    long_side: int | None = 2048,
    density: float | None = None,
    photos_table: str | Path | None = None,
) -> dict:
    """Texture a scene with a peer and write a difftex results folder ``out``.

    Args:
        method: one of :data:`PEERS`.
        scene_dir: the scene folder.
        out: results folder (replaced when the run succeeds).
        visibility: a ``difftex visibility`` folder whose frames (and polygons) to use; without
            it frames are computed at ``long_side`` / ``density`` for every polygon.
        polygons: only these polygon ids (the peer still sees the whole proxy, for occlusion).
        photos_table: the filter's photos.json; the peer gets the photos it kept.
    Returns:
        The record written to ``out/peer.json``: settings, photos, mesh size, per-polygon
        coverage, and ``prepare`` / ``peer`` / ``import`` phases with their totals.
    """
    from difftex.evaluation.peers import meshlab, reprojection, texrecon
    from difftex.geometry.meshing import default_max_edge, proxy_mesh
    from difftex.scene.files import write_json
    from difftex.scene.loading import load_scene

    if method not in PEERS:
        raise DifftexError(f"unknown peer '{method}' (known: {', '.join(PEERS)})")
    runner = {"texrecon": texrecon, "reprojection": reprojection}.get(method, meshlab)
    runner.check_available()
    if method == "reprojection":  # the scene's dense mesh, or one line saying it has none
        cfg = replace(cfg, dense_mesh=str(reprojection.dense_mesh_path(scene_dir, cfg.dense_mesh)))
    out = Path(out).absolute()  # the programs run in their own working folders
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".partial", dir=out.parent))
    staged = Results(tmp)  # the results folder until it is complete
    try:
        with measure_self() as prep:
            scene = load_scene(scene_dir)
            fr = frames_for(scene, visibility, polygons, long_side, density)
            if fr.visibility is not None:
                staged.visibility_link.write_text(str(fr.visibility))
            else:
                write_frames(staged.visibility_dir, fr)
            photos = peer_photos(scene, photos_table)
            work = tmp / "work"
            cams = export_photos(photos, work / "photos", cfg.photo_long_side)
            edge = cfg.max_edge or default_max_edge(scene.proxy, np.stack([p.center for p in photos]), cfg.max_edge_rel)
            mesh = proxy_mesh(scene.proxy, edge)
            job = runner.prepare(method, work, cams, mesh, fr, cfg)
        # The log lives beside ``out`` while the program runs, so that a failure's message can name it.
        log = out.with_name(out.name + ".log")
        peer = runner.run(job, work, cfg, log)
        shutil.move(log, work / "peer.log")
        with measure_self() as imp:
            imported, sources, extra = runner.collect(job, work, fr, mesh)
            names = [p.name for p in photos]
            coverage = write_textures(tmp, method, fr, imported, sources, names, extra)
        if not cfg.keep_inputs:
            shutil.rmtree(work / "photos", ignore_errors=True)
        total = Phase(
            wall_s=prep.wall_s + peer.wall_s + imp.wall_s,
            cpu_s=prep.cpu_s + peer.cpu_s + imp.cpu_s,
            peak_rss_mib=max(prep.peak_rss_mib, peer.peak_rss_mib, imp.peak_rss_mib),
        )
        record = {
            "method": method,
            "label": LABELS[method],
            "scene": str(scene.root),
            "config": asdict(cfg),
            "photos": names,
            "photo_sizes": [[c.width, c.height] for c in cams],
            "mesh": {"triangles": int(len(mesh.faces)), "vertices": int(len(mesh.vertices)), "max_edge": mesh.max_edge},
            "polygons": coverage,
            "peer_program": runner.describe(job),
            "prepare": asdict(prep),
            "peer": asdict(peer),
            "import": asdict(imp),
            "total": asdict(total),
            "timing_notes": "prepare/import: this process (CPU user+system; peak RSS is the process high-water mark "
            "so far); peer: the program's process tree (getrusage(RUSAGE_CHILDREN) of a launcher "
            "that only waits for it: CPU of the program and its waited-for descendants, peak RSS "
            "of the largest; wall time includes the launcher's start, about 20 ms)",
        }
        # the command line named the temporary folder, which is about to become ``out``
        record = json.loads(json.dumps(record, default=str).replace(str(tmp), str(out)))
        write_json(staged.peer_record, record)
        if out.exists():
            shutil.rmtree(out)
        os.replace(tmp, out)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
    return record
