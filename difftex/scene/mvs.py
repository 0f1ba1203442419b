"""COLMAP's PatchMatch stereo of a scene's photos on a GPU: a COLMAP dense workspace with depth maps.

The ``dense`` stage (``difftex dense``, the workflow's rule ``dense_stereo``, docs/dense.md)
undistorts the chosen photos of the scene's COLMAP model into a dense workspace (``images/``,
``sparse/``, ``stereo/``) and runs PatchMatch stereo with geometric consistency there, leaving
``stereo/depth_maps/<photo>.geometric.bin``: the layout difftex.geometry.dense reads.

PatchMatch needs CUDA, which only the ``pycolmap-cuda12`` build has (the same import name as the
CPU ``pycolmap``); :func:`cuda_available` says which one is installed. The undistortion runs on
the CPU with either build.

The workspace is made in a sibling folder ``.<name>.partial`` and renamed onto ``out_dir`` only
when complete: an interrupted run leaves no folder that looks finished, and the next run starts
the partial one again from scratch.
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from difftex.errors import DifftexError
from difftex.layout import DENSE_RECORD as RECORD  # the stage's record in the workspace, written last

DEPTH_DIR = Path("stereo") / "depth_maps"
PHOTO_CHOICES = ("visible", "all")
SKIP_REASON = "pycolmap has no CUDA (install pycolmap-cuda12 on a GPU machine)"
# PatchMatch's cache of photos, depth and normal maps in host memory, GiB (COLMAP's default, 32,
# would outgrow the job's memory request on a large scene; the rule asks for this plus a working set)
CACHE_GB = 8.0


@dataclass(frozen=True)
class DenseStereoConfig:
    """PatchMatch stereo of the ``dense`` stage (the ``dense:`` config keys of the same names)."""

    max_image_size: int = 2000
    """Longest side of the undistorted photos and of their depth maps, pixels; -1: the photos' own.
    PatchMatch's time and GPU memory grow with the pixel count (about 1 s per 2000-pixel photo
    and pass on a recent GPU)."""
    photos: str = "visible"
    """Which photos get a depth map: ``visible``, those the photo filter kept (they see the proxy
    and are sharp enough; every registered photo when no filter table is given), or ``all``."""
    num_iterations: int = 5
    """PatchMatch's propagation sweeps per pass (COLMAP's default)."""
    window_radius: int = 5
    """Half the matching window's side, pixels (5: an 11 x 11 window, COLMAP's default)."""
    geom_consistency: bool = True
    """A second, geometrically consistent pass after the photometric one: its filtered maps are
    the ``*.geometric.bin`` ones; without it only unfiltered ``*.photometric.bin`` maps remain."""
    num_source_images: int = 20
    """Source photos per photo, which COLMAP picks by their shared sparse points (``__auto__``)."""
    gpu_index: str | int | None = None
    """CUDA devices PatchMatch runs on: None (or -1) every visible one, or ``0``, ``"0,1"``."""

    def __post_init__(self):
        if not (self.max_image_size == -1 or self.max_image_size >= 64):
            raise DifftexError(f"dense: max_image_size must be -1 or >= 64, got {self.max_image_size}")
        if self.photos not in PHOTO_CHOICES:
            raise DifftexError(f"dense: photos must be one of {', '.join(PHOTO_CHOICES)}, got {self.photos!r}")
        # COLMAP's CUDA kernel is compiled for window radii up to 32
        if not (self.num_iterations >= 1 and 1 <= self.window_radius <= 32 and self.num_source_images >= 1):
            raise DifftexError("dense: num_iterations >= 1, window_radius in 1..32 and num_source_images >= 1")


def cuda_available() -> bool:
    """Whether the installed pycolmap can run PatchMatch stereo (the ``pycolmap-cuda12`` build).

    Returns:
        ``pycolmap.has_cuda``; False where pycolmap does not say (builds before 3.10).
    """
    import pycolmap

    return bool(getattr(pycolmap, "has_cuda", False))


def read_photo_list(path: str | Path) -> list[str]:
    """Photo names from a file: the photo filter's table (``R/photos.json``: its kept photos) or
    a text file with one COLMAP image name per line.

    Args:
        path: the file.

    Returns:
        The names, in the file's order.
    """
    path = Path(path)
    if not path.is_file():
        raise DifftexError(f"{path}: photo list not found")
    text = path.read_text()
    if path.suffix.lower() == ".json":
        try:
            table = json.loads(text)
            return [r["name"] for r in table["photos"] if r["kept"]]
        except (ValueError, KeyError, TypeError):
            raise DifftexError(f"{path}: not a table of the difftex filter stage (photos with name and kept)") from None
    return [line.strip() for line in text.splitlines() if line.strip() and not line.startswith("#")]


def chosen_photos(rec, names: list[str] | None, model_dir: Path) -> list[str]:
    """The registered photos PatchMatch gets, checked against the model ``rec``.

    Args:
        rec: the scene's pycolmap.Reconstruction.
        names: photo names, or None for every registered photo.
        model_dir: the model's folder (named in errors).

    Returns:
        The names, sorted.
    """
    registered = {im.name for im in rec.images.values() if getattr(im, "has_pose", True)}
    if names is None:
        names = sorted(registered)
    missing = sorted(set(names) - registered)
    if missing:
        shown = ", ".join(missing[:3]) + (", ..." if len(missing) > 3 else "")
        raise DifftexError(f"{model_dir}: {len(missing)} photo(s) to match are not registered in the model ({shown})")
    if len(set(names)) < 2:
        raise DifftexError(f"{model_dir}: dense stereo needs at least 2 photos, got {len(set(names))}")
    return sorted(set(names))


def _subset_model(rec, keep: set[str], out: Path) -> None:
    """Write ``rec`` with only the frames that hold a photo of ``keep`` registered.

    The undistorter writes every registered image into the workspace model, and PatchMatch's
    ``__auto__`` picks source photos from that model; an image whose file was not undistorted
    would be picked and fail to load. Deregistered frames leave both.
    """
    frames = {im.frame_id for im in rec.images.values() if im.name in keep}
    for frame_id in list(rec.reg_frame_ids()):
        if frame_id not in frames:
            rec.deregister_frame(frame_id)
    out.mkdir(parents=True)
    rec.write(str(out))


def patch_match_options(cfg: DenseStereoConfig):
    """pycolmap.PatchMatchOptions from the config (COLMAP's defaults for everything else)."""
    import pycolmap

    opts = pycolmap.PatchMatchOptions()
    opts.max_image_size = cfg.max_image_size
    opts.num_iterations = cfg.num_iterations
    opts.window_radius = cfg.window_radius
    opts.geom_consistency = cfg.geom_consistency
    opts.gpu_index = "-1" if cfg.gpu_index is None else str(cfg.gpu_index)
    opts.cache_size = CACHE_GB
    return opts


def patch_match(workspace: Path, options) -> None:
    """Run PatchMatch stereo in a COLMAP workspace (needs CUDA; tests replace this function).

    With ``geom_consistency``, COLMAP runs the photometric pass over every photo first, then the
    geometric one, in this one call.

    Args:
        workspace: the undistorter's output (images/, sparse/, stereo/patch-match.cfg).
        options: pycolmap.PatchMatchOptions.
    """
    import pycolmap

    try:
        pycolmap.patch_match_stereo(str(workspace), workspace_format="COLMAP", options=options)
    except (RuntimeError, ValueError) as exc:
        # pycolmap raises its C++ check text; one line naming the workspace
        raise DifftexError(f"{workspace}: PatchMatch stereo failed ({exc})") from None


def undistort(sparse_dir: Path, images_dir: Path, workspace: Path, cfg: DenseStereoConfig, threads: int) -> None:
    """Undistort the registered photos of the model in ``sparse_dir`` into a COLMAP workspace.

    Args:
        sparse_dir: a COLMAP model (only the photos to match registered).
        images_dir: the scene's photos.
        workspace: the new workspace folder (images/, sparse/, stereo/ with patch-match.cfg).
        cfg: ``max_image_size`` and ``num_source_images`` are used.
        threads: CPU threads of the undistorter.
    """
    import pycolmap

    undist = pycolmap.UndistortCameraOptions()
    undist.max_image_size = cfg.max_image_size
    try:
        pycolmap.undistort_images(
            str(workspace), str(sparse_dir), str(images_dir), output_type="COLMAP",
            num_patch_match_src_images=cfg.num_source_images, undistort_options=undist, num_threads=threads,
        )
    except (RuntimeError, ValueError) as exc:
        raise DifftexError(f"{images_dir}: undistorting the photos failed ({exc})") from None


def depth_map_stats(workspace: Path, name: str) -> dict:
    """One photo's figures: its undistorted size and its depth map's (the geometric one, else the
    photometric one): size, share of pixels with a depth, median depth.

    Args:
        workspace: a COLMAP dense workspace.
        name: the photo's COLMAP name.

    Returns:
        {"name", "kind" ("geometric", "photometric" or None), "size", "valid_share", "median_depth"}.
    """
    import pycolmap

    row = {"name": name, "kind": None, "size": None, "valid_share": 0.0, "median_depth": None}
    for kind in ("geometric", "photometric"):
        path = workspace / DEPTH_DIR / f"{name}.{kind}.bin"
        if path.is_file():
            dm = pycolmap.DepthMap()
            dm.read(str(path))
            depth = np.asarray(dm.to_array())
            valid = np.isfinite(depth) & (depth > 0)
            row.update(kind=kind, size=[int(depth.shape[1]), int(depth.shape[0])],
                       valid_share=round(float(valid.mean()), 4),
                       median_depth=float(np.median(depth[valid])) if valid.any() else None)
            break
    return row


def replace_dir(src: Path, dst: Path) -> None:
    """Put the folder ``src`` at ``dst``, replacing what is there (an older workspace, or the
    empty folder Snakemake makes for an output file), by renames in one file system."""
    old = dst.parent / f".{dst.name}.old"
    if old.exists():
        shutil.rmtree(old)
    if dst.exists():
        os.replace(dst, old)
    os.replace(src, dst)
    if old.exists():
        shutil.rmtree(old)


def partial_dir(out_dir: Path) -> Path:
    """The folder a workspace is made in before it is renamed onto ``out_dir``."""
    return out_dir.parent / f".{out_dir.name}.partial"


def write_skipped(out_dir: str | Path, reason: str = SKIP_REASON) -> dict:
    """Make ``out_dir`` a folder holding only its record saying that the stage was skipped.

    Args:
        out_dir: the workspace folder.
        reason: why (written to the record).

    Returns:
        The record.
    """
    out_dir = Path(out_dir)
    tmp = partial_dir(out_dir)
    if tmp.exists():
        shutil.rmtree(tmp)
    tmp.mkdir(parents=True)
    record = {"status": "skipped", "reason": reason, "photos": []}
    (tmp / RECORD).write_text(json.dumps(record, indent=2) + "\n")
    replace_dir(tmp, out_dir)
    return record


def run_dense_stereo(
    scene_dir: str | Path, out_dir: str | Path, image_names: list[str] | None, cfg: DenseStereoConfig,
    threads: int = 1,
) -> dict:
    """Undistort the scene's photos into a COLMAP dense workspace and run PatchMatch stereo there.

    Args:
        scene_dir: the scene (``images/``, ``sparse/0/`` or ``sparse/``).
        out_dir: the workspace to make (replaced when it exists): ``images/``, ``sparse/``,
            ``stereo/depth_maps/<photo>.geometric.bin`` and the record ``dense.json``.
        image_names: the photos to match (COLMAP names), or None for every registered one.
        cfg: the stage's parameters.
        threads: CPU threads of the undistortion.

    Returns:
        The record written to ``out_dir/dense.json``: status, seconds of each step, the
        parameters, and per photo its depth map's figures (:func:`depth_map_stats`).
    """
    from difftex.scene.camera import read_reconstruction
    from difftex.scene.loading import find_sparse

    t0 = time.perf_counter()
    scene_dir, out_dir = Path(scene_dir), Path(out_dir)
    sparse = find_sparse(scene_dir)
    rec = read_reconstruction(sparse)
    names = chosen_photos(rec, image_names, sparse)
    tmp = partial_dir(out_dir)
    if tmp.exists():  # an interrupted run's: start again
        shutil.rmtree(tmp)
    _subset_model(rec, set(names), tmp / "input-model")
    workspace = tmp / "workspace"
    undistort(tmp / "input-model", scene_dir / "images", workspace, cfg, threads)
    t_undistort = time.perf_counter()
    patch_match(workspace, patch_match_options(cfg))
    t_stereo = time.perf_counter()
    rows = [depth_map_stats(workspace, n) for n in names]
    if not any(r["kind"] for r in rows):
        raise DifftexError(f"{workspace / DEPTH_DIR}: PatchMatch wrote no depth map")
    record = {
        "status": "done",
        "seconds": {"undistort": round(t_undistort - t0, 3), "patch_match": round(t_stereo - t_undistort, 3),
                    "total": round(time.perf_counter() - t0, 3)},
        "config": dataclasses.asdict(cfg),
        "photos": rows,
    }
    (workspace / RECORD).write_text(json.dumps(record, indent=2) + "\n")
    replace_dir(workspace, out_dir)
    shutil.rmtree(tmp)
    return record


def workspace_status(out_dir: str | Path) -> str | None:
    """What the stage left in ``out_dir``: ``"done"`` (depth maps), ``"skipped"`` (no CUDA), or
    None (no record: never run, or interrupted)."""
    path = Path(out_dir) / RECORD
    if not path.is_file():
        return None
    try:
        return json.loads(path.read_text()).get("status")
    except (ValueError, AttributeError):
        return None
