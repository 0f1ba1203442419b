"""MeshLab (through pymeshlab) as a peer, in two modes.

- ``meshlab-face``: "Parameterization + texturing from registered rasters"
  (``compute_texcoord_parametrization_and_texture_from_registered_rasters``): every triangle
  takes the raster that sees it best, patches of triangles are packed into one texture, with
  MeshLab's colour correction across patch borders.
- ``meshlab-blend``: "Project active rasters color to current mesh, filling the texture"
  (``compute_color_and_texture_from_active_rasters_projection``): every texel blends all rasters
  that see it (weighted by angle, distance and image border, depth-tested), over a
  parameterization difftex provides: each polygon's own UV frame packed into one atlas at
  ``oversample`` texels per frame texel, so MeshLab fills exactly the texels that are scored.

Cameras go in as a Bundler file (``bundle.out`` + image list): one focal length, no principal
point (MeshLab puts it at the image centre), camera looking down -z with y up, i.e.
``R_b = diag(1, -1, -1) R`` and ``t_b = diag(1, -1, -1) t``. The photos are the ideal pinhole
resamplings of :mod:`difftex.geometry.pinhole`, which satisfy exactly that.

MeshLab needs an OpenGL context and Qt's platform plugins, and a crash in it must not take
difftex down: it runs in a child process (``python -m difftex.evaluation.peers.meshlab JOB.json``) under
``xvfb-run`` (unless a display is already set), with ``QT_PLUGIN_PATH`` and
``QT_QPA_PLATFORM_PLUGIN_PATH`` pointing at the system's Qt5 plugins (Debian: libqt5gui5).
"""

from __future__ import annotations

import glob
import importlib.util
import json
import os
import shutil
import sys
from math import ceil, log2, sqrt
from pathlib import Path

import numpy as np

from difftex.errors import DifftexError

FLIP = np.diag([1.0, -1.0, -1.0])  # COLMAP/OpenCV camera axes -> Bundler's (y up, looking down -z)
PAD = 2  # atlas texels around every polygon in blend mode (bilinear lookups stay on the polygon)


def qt_plugin_dir() -> str | None:
    """The system's Qt5 plugin folder (it holds platforms/libqxcb.so), if any."""
    for d in sorted(glob.glob("/usr/lib/*/qt5/plugins")) + ["/usr/lib/qt5/plugins"]:
        if Path(d, "platforms").is_dir():
            return d
    return None


def unavailable_reason() -> str:
    if importlib.util.find_spec("pymeshlab") is None:
        return "meshlab: pymeshlab is not installed (pip install pymeshlab)"
    if not os.environ.get("DISPLAY") and shutil.which("xvfb-run") is None:
        return "meshlab: no display and no xvfb-run for MeshLab's OpenGL context (apt install xvfb xauth)"
    if qt_plugin_dir() is None and "QT_PLUGIN_PATH" not in os.environ:
        return "meshlab: no system Qt5 plugins (apt install libqt5gui5) and QT_PLUGIN_PATH unset"
    return ""


def available() -> bool:
    return not unavailable_reason()


def check_available() -> None:
    why = unavailable_reason()
    if why:
        raise DifftexError(why)


# --------------------------------------------------------------------------------------------
# Inputs


def bundler_text(cams: list) -> str:
    """Bundler v0.3 file of ideal pinhole cameras (no points: MeshLab only needs the cameras)."""
    lines = ["# Bundle file v0.3", f"{len(cams)} 0"]
    for c in cams:
        R, t = FLIP @ np.asarray(c.R), FLIP @ np.asarray(c.t)
        lines.append(f"{c.f:.12g} 0 0")
        lines += [" ".join(f"{x:.12g}" for x in row) for row in R]
        lines.append(" ".join(f"{x:.12g}" for x in t))
    return "\n".join(lines) + "\n"


def face_texture_size(frames, oversample: int, max_side: int) -> int:
    """Side of MeshLab's per-face texture: twice the frames' texel area (packing loss) at ``oversample``."""
    area = sum(f.width * f.height for f in frames.frames.values()) * oversample**2
    return int(min(max_side, max(512, 1 << ceil(log2(sqrt(2.0 * area))))))


def blend_atlas(frames, oversample: int, max_side: int) -> tuple[dict, int, int]:
    """Placement of every polygon's frame (``k`` texels per frame texel, padded) on one square page.

    Returns:
        ({polygon id: (x, y)}, page side, k). ``k`` starts at ``oversample`` and halves until the
        frames fit one page of at most ``max_side``.
    """
    from difftex.export.assemble import pack

    k = oversample
    while True:
        sizes = {pid: (f.width * k + 2 * PAD, f.height * k + 2 * PAD) for pid, f in frames.frames.items()}
        sizes["_unused"] = (4, 4)  # a corner for triangles of polygons that are not scored
        try:
            where, pages = pack(sizes, max_side)
        except DifftexError:
            where, pages = None, [None, None]
        if where is not None and len(pages) == 1:
            side = max(pages[0])
            return {pid: (x, y) for pid, (_, x, y) in where.items()}, int(side), k
        if k == 1:
            raise DifftexError(f"MeshLab blend: the polygons' maps do not fit one {max_side} texture; "
                               "lower the texture resolution")
        k = max(1, k // 2)


def blend_uvs(mesh, frames, place: dict, side: int, k: int) -> np.ndarray:
    """(F, 3, 2) per-corner UVs (v up) of the mesh in the blend atlas.

    A polygon that is not scored (not in ``frames``) maps to a point in the reserved corner: its
    triangles still occlude in MeshLab's depth test but own no texel.
    """
    ux, uy = place["_unused"]
    uv = np.tile([(ux + 2) / side, 1 - (uy + 2) / side], (len(mesh.faces), 3, 1))
    for pid, fr in frames.frames.items():
        sel = mesh.faces_of(pid)
        x, y = place[pid]
        t = fr.world_to_texel(mesh.vertices[mesh.faces[sel]]) * k
        uv[sel, :, 0] = (x + PAD + t[..., 0]) / side
        uv[sel, :, 1] = 1 - (y + PAD + t[..., 1]) / side
    return uv


def write_uv_obj(path: Path, mesh, uv: np.ndarray) -> None:
    """OBJ with one ``vt`` per face corner (MeshLab reads them as wedge texture coordinates)."""
    from difftex.scene.files import write_text

    lines = [f"v {x:.10g} {y:.10g} {z:.10g}" for x, y, z in mesh.vertices]
    lines += [f"vt {u:.9f} {v:.9f}" for u, v in uv.reshape(-1, 2)]
    for j, (a, b, c) in enumerate(mesh.faces + 1):
        lines.append(f"f {a}/{3 * j + 1} {b}/{3 * j + 2} {c}/{3 * j + 3}")
    write_text(path, "\n".join(lines) + "\n")


def prepare(method: str, work: Path, cams: list, mesh, frames, cfg) -> dict:
    """Bundler cameras, image list, the mesh (with the atlas UVs in blend mode) and the child's job file."""
    from difftex.geometry.meshing import write_ply
    from difftex.scene.files import write_json, write_text

    write_text(work / "bundle.out", bundler_text(cams))
    write_text(work / "list.txt", "".join(f"photos/v{i:05d}.png\n" for i in range(len(cams))))
    job = {
        "mode": method.split("-", 1)[1],
        "bundle": "bundle.out",
        "list": "list.txt",
        "out": "out/model.obj",
        "texture": "texture.png",
        "views": len(cams),
        "faces": int(len(mesh.faces)),
    }
    if job["mode"] == "face":
        write_ply(work / "mesh.ply", mesh)
        job.update(mesh="mesh.ply", texsize=face_texture_size(frames, cfg.oversample, cfg.max_texture))
    else:
        place, side, k = blend_atlas(frames, cfg.oversample, cfg.max_texture)
        write_uv_obj(work / "mesh.obj", mesh, blend_uvs(mesh, frames, place, side, k))
        job.update(mesh="mesh.obj", texsize=side, oversample=k)
    (work / "out").mkdir(parents=True, exist_ok=True)
    write_json(work / "job.json", job)
    return job


def child_env() -> dict:
    """The environment of the MeshLab child: the system's Qt5 plugins unless already set."""
    env = dict(os.environ)
    qt = qt_plugin_dir()
    if qt and "QT_PLUGIN_PATH" not in env:
        env["QT_PLUGIN_PATH"] = qt
    if qt and "QT_QPA_PLATFORM_PLUGIN_PATH" not in env:
        env["QT_QPA_PLATFORM_PLUGIN_PATH"] = str(Path(qt) / "platforms")
    # the child imports difftex from wherever this process did
    root = str(Path(__file__).resolve().parents[1])
    env["PYTHONPATH"] = os.pathsep.join([root] + ([env["PYTHONPATH"]] if env.get("PYTHONPATH") else []))
    return env


def command(work: Path) -> list[str]:
    cmd = [sys.executable, "-m", "difftex.evaluation.peers.meshlab", str(work / "job.json")]
    if os.environ.get("DISPLAY"):
        return cmd
    # -a: a free display number, so parallel runs do not collide
    return ["xvfb-run", "-a", "-s", "-screen 0 1024x768x24", *cmd]


def run(job: dict, work: Path, cfg, log: Path):
    from difftex.evaluation.peers.measure import run_measured

    phase = run_measured(command(work), log, cfg.timeout_s, env=child_env(), cwd=work, what=f"MeshLab ({job['mode']})")
    steps = work / "out" / "steps.json"
    if steps.is_file():  # the child's own filter times, for the benchmark
        phase.notes["meshlab_steps_s"] = json.loads(steps.read_text())
    return phase


def collect(job: dict, work: Path, frames, mesh) -> tuple[dict, None, dict]:
    """(imported textures, no source maps: MeshLab does not report which raster coloured a texel, extras)."""
    from difftex.evaluation.peers.objimport import import_obj

    obj = work / job["out"]
    if not obj.is_file():
        raise DifftexError(f"{obj}: MeshLab wrote no textured model")
    # blend: the atlas holds every frame at exactly ``oversample`` texels per texel, and its alpha
    # is 0 where no raster reached (no refill); face: triangles no raster sees are painted black
    cov = "alpha" if job["mode"] == "blend" else "nonblack"
    imported = import_obj(obj, frames.frames, frames.masks, supersample=job.get("oversample"), coverage=cov)
    return imported, None, {"texture_size": job["texsize"]}


def describe(job: dict) -> dict:
    filt = {
        "face": "compute_texcoord_parametrization_and_texture_from_registered_rasters",
        "blend": "compute_color_and_texture_from_active_rasters_projection",
    }[job["mode"]]
    return {"program": "pymeshlab", "filter": filt, "texture_size": job["texsize"]}


# --------------------------------------------------------------------------------------------
# The child process


def _child(job_path: str) -> int:
    """Run one MeshLab job (in ``xvfb-run``): load cameras and mesh, apply the filter, save the OBJ."""
    import time

    import pymeshlab

    job = json.loads(Path(job_path).read_text())
    os.chdir(Path(job_path).parent)
    steps = {}
    t = time.perf_counter()
    ms = pymeshlab.MeshSet()
    ms.load_project([job["bundle"], job["list"]])
    if ms.raster_number() != job["views"]:
        print(f"MeshLab loaded {ms.raster_number()} of {job['views']} rasters", file=sys.stderr)
        return 3
    ms.load_new_mesh(job["mesh"])
    steps["load_s"] = time.perf_counter() - t
    if ms.current_mesh().face_number() != job["faces"]:
        print(f"MeshLab loaded {ms.current_mesh().face_number()} of {job['faces']} faces", file=sys.stderr)
        return 3
    t = time.perf_counter()
    if job["mode"] == "face":
        ms.compute_texcoord_parametrization_and_texture_from_registered_rasters(
            texturesize=int(job["texsize"]), texturename=job["texture"]
        )
    else:
        # no refill: texels no raster sees keep alpha 0 and are filled by difftex like everyone's
        ms.compute_color_and_texture_from_active_rasters_projection(
            textname=job["texture"], texsize=int(job["texsize"]), dorefill=False
        )
    steps["filter_s"] = time.perf_counter() - t
    t = time.perf_counter()
    out = Path(job["out"])
    ms.save_current_mesh(str(out))
    steps["save_s"] = time.perf_counter() - t
    (out.parent / "steps.json").write_text(json.dumps(steps))
    return 0


if __name__ == "__main__":
    sys.exit(_child(sys.argv[1]))
