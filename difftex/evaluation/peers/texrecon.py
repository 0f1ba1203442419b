"""mvs-texturing's ``texrecon`` (Waechter et al. 2014, "Let There Be Color!") as a peer.

The executable is ``$DIFFTEX_TEXRECON`` when set, else ``texrecon`` on PATH; build it with
``../shared/peers/build_texrecon.sh PREFIX`` (it lands in ``PREFIX/build/apps/texrecon/``).
:func:`difftex.evaluation.peers.run.run_peer` drives it through :func:`prepare`, :func:`run` and :func:`collect`.

Input is texrecon's "scene folder": one image and one ``.cam`` file per photo. A ``.cam`` file
holds the world-to-camera pose (``tx ty tz R00 .. R22``) on its first line and
``f d0 d1 paspect ppx ppy`` on its second, with ``f`` divided by the larger image side and the
principal point divided by width / height. texrecon's own projection (MVE ``fill_calibration``
then ``TextureView::get_pixel_coords``, which subtracts 0.5) puts pixel centres at +0.5 like
COLMAP, so the ideal pinhole cameras of :mod:`difftex.geometry.pinhole` are written as they are
(``paspect`` 1, principal point 0.5 0.5, no distortion). The mesh is the ear-clipped, subdivided
proxy as a PLY: texrecon textures a triangle from a view only if all its corners are visible.

Its view selection (one photo per triangle, ``<prefix>_labeling.vec``: label 0 none, label l the
l-th view in name order) becomes the per-texel source map, so Q_front / Q_vc are scored for it
like for the other view-selection methods.
"""

from __future__ import annotations

import os
import shlex
import shutil
from pathlib import Path

import numpy as np

from difftex.errors import DifftexError
from difftex.evaluation.peers.objimport import import_obj  # noqa: F401  (re-exported: texrecon's OBJ is read with it)

BUILD_HINT = "build it with ../shared/peers/build_texrecon.sh and put it on PATH or set DIFFTEX_TEXRECON"


def _find() -> tuple[str | None, str]:
    """(executable or None, why not)."""
    env = os.environ.get("DIFFTEX_TEXRECON")
    if env:
        if Path(env).is_file() and os.access(env, os.X_OK):
            return env, ""
        return None, f"{env}: DIFFTEX_TEXRECON is not an executable file"
    exe = shutil.which("texrecon")
    return (
        (exe, "")
        if exe
        else (None, f"texrecon: no 'texrecon' executable on PATH and DIFFTEX_TEXRECON unset ({BUILD_HINT})")
    )


def executable() -> str | None:
    return _find()[0]


def available() -> bool:
    return executable() is not None


def unavailable_reason() -> str:
    return _find()[1]


def check_available() -> None:
    exe, why = _find()
    if exe is None:
        raise DifftexError(why)


def cam_file_text(cam) -> str:
    """The ``.cam`` file of a pinhole camera (anything with ``R``, ``t``, ``K()``, ``width``, ``height``)."""
    K = cam.K()
    w, h = cam.width, cam.height
    t = " ".join(f"{x:.12g}" for x in cam.t)
    R = " ".join(f"{x:.12g}" for x in np.asarray(cam.R).reshape(-1))
    f = K[0, 0] / max(w, h)
    return f"{t} {R}\n{f:.12g} 0 0 {K[1, 1] / K[0, 0]:.12g} {K[0, 2] / w:.12g} {K[1, 2] / h:.12g}\n"


def prepare(method: str, work: Path, cams: list, mesh, frames, cfg) -> dict:
    """Write the .cam files beside the resampled photos (``work/photos/v00000.png``) and the mesh PLY."""
    from difftex.geometry.meshing import write_ply
    from difftex.scene.files import write_text

    for i, cam in enumerate(cams):
        write_text(work / "photos" / f"v{i:05d}.cam", cam_file_text(cam))
    write_ply(work / "mesh.ply", mesh)
    (work / "out").mkdir(parents=True, exist_ok=True)
    prefix = work / "out" / "model"
    cmd = [executable(), str(work / "photos"), str(work / "mesh.ply"), str(prefix), "--write_timings"]
    if cfg.threads:
        cmd.append(f"--num_threads={cfg.threads}")
    return {"cmd": cmd, "prefix": str(prefix), "views": len(cams), "faces": int(len(mesh.faces))}


def run(job: dict, work: Path, cfg, log: Path):
    from difftex.evaluation.peers.measure import run_measured

    phase = run_measured(job["cmd"], log, cfg.timeout_s, what="texrecon")
    timings = Path(job["prefix"] + "_timings.csv")
    if timings.is_file():  # texrecon's own per-step wall times, for the benchmark
        phase.notes["texrecon_steps_ms"] = read_timings(timings)
    return phase


def read_timings(path: Path) -> dict[str, float]:
    """{step: milliseconds} from texrecon's ``--write_timings`` CSV ('Relative milliseconds' column)."""
    import csv

    rows = list(csv.reader(path.read_text().splitlines()))
    if not rows:
        return {}
    head = [h.strip() for h in rows[0]]
    col = head.index("Relative milliseconds") if "Relative milliseconds" in head else len(head) - 1
    out = {}
    for r in rows[1:]:
        try:
            out[r[0].strip()] = float(r[col])
        except (IndexError, ValueError):
            continue
    return out


def read_labels(path: Path, n_faces: int) -> np.ndarray | None:
    """texrecon's per-face view labels (0: none, l: view l-1), or None if absent or for another mesh."""
    if not path.is_file():
        return None
    lab = np.fromfile(path, dtype=np.uint64)
    return lab.astype(np.int64) if len(lab) == n_faces else None


def collect(job: dict, work: Path, frames, mesh) -> tuple[dict, dict | None, dict]:
    """(imported textures, per-polygon source photo index maps or None, report extras)."""
    from difftex.evaluation.peers.objimport import polygon_face_map

    obj = Path(job["prefix"] + ".obj")
    if not obj.is_file():
        raise DifftexError(f"{obj}: texrecon wrote no textured model")
    imported = import_obj(obj, frames.frames, frames.masks)
    labels = read_labels(Path(job["prefix"] + "_labeling.vec"), len(mesh.faces))
    sources = None
    if labels is not None:
        sources = {}
        for pid, fr in frames.frames.items():
            sel = mesh.faces_of(pid)
            face = polygon_face_map(fr, mesh.vertices[mesh.faces[sel]])
            lab = np.where(face >= 0, labels[sel][np.maximum(face, 0)], 0)
            sources[pid] = lab - 1  # view l -> photo index l - 1; 0 (unseen) -> -1
    return imported, sources, {"source_map": "texrecon view selection" if sources is not None else None}


def describe(job: dict) -> dict:
    return {"program": "texrecon", "command": shlex.join(job["cmd"])}
