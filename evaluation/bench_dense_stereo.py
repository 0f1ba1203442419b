"""Dense stereo on a GPU (``difftex dense``: COLMAP PatchMatch through pycolmap-cuda12): its time on
a scene and, on a ``difftex synth`` scene, its depth accuracy against the true geometry.

    python evaluation/bench_dense_stereo.py --scene data/synth/tiny              # GPU, pycolmap-cuda12
    python evaluation/bench_dense_stereo.py --scene ../shared/data/lund-door     # time and map figures only
    python evaluation/bench_dense_stereo.py --scene S --workspace W              # score a workspace made before (CPU)

Without ``--workspace`` the dense stage runs on every registered photo of the scene into
``--work`` (default ``evaluation/out/dense_stereo/<scene>``); without CUDA in pycolmap the script
prints one line and exits 0. Writes ``evaluation/results/dense_stereo_<scene>.md`` and ``.json``.

Scoring (synthetic scenes: their ``synth.json`` rebuilds the building, difftex.synth.pipeline):
for each scored photo, Mitsuba ray-traces the true surface point under every pixel of the
original (distorted) photo, as the photo was rendered. Each depth-map pixel's ray (the
undistorted pinhole camera and the original one share the pose, so a ray is the same in both)
is mapped to the original photo's pixel it passes through, whose true point gives the true
depth along the model's optical axis. Building pixels are those whose true point lies on the
building (inside its box grown by the relief depth, above the ground) and, in a scene with
occluders, is the same with the occluders removed. Figures over the building pixels: the share
with a depth (completeness), the median, mean and 90th percentile of |depth error|, its median
relative to the depth, and the shares within 1 % of the depth and within 5 cm (the synthetic
scenes are in metres).
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import sys
import time
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

SKIP_LINE = "bench_dense_stereo: skipped, pycolmap has no CUDA (install pycolmap-cuda12 on a GPU machine)"


def synth_truth(scene: Path) -> dict | None:
    """What scoring needs of a ``difftex synth`` scene (None for any other scene): its manifest,
    generator config, building spec, and the building's box grown by the relief depth."""
    from difftex.errors import DifftexError
    from difftex.synth.pipeline import build_model
    from difftex.synth.presets import BuildingSpec, SynthConfig

    path = scene / "synth.json"
    if not path.is_file():
        return None
    man = json.loads(path.read_text())
    c = dict(man["config"])
    c["buildings"] = tuple(BuildingSpec(**b) for b in c["buildings"])
    cfg = SynthConfig(**c)
    specs = [b for b in cfg.buildings if b.name == man["building"]["name"]]
    if not specs:
        raise DifftexError(f"{path}: building '{man['building']['name']}' is not in its config")
    building, *_ = build_model(cfg, specs[0], man["seed"], man["building_index"])
    lo, hi = building.bounds()
    grow = float(cfg.relief_depth) + 0.05
    return {"manifest": man, "cfg": cfg, "spec": specs[0], "lo": lo - grow, "hi": hi + grow, "ground": lo[2] + 0.05}


def true_points(truth: dict, view: dict, occluders: bool | None, spp: int) -> np.ndarray:
    """(H, W, 3) world points under the original photo's pixels, ray traced as it was rendered."""
    from difftex.synth.cameras import Intrinsics
    from difftex.synth.pipeline import position_image

    man = truth["manifest"]
    c = next(c for c in man["cameras"] if c["camera_id"] == view["camera_id"])
    intr = Intrinsics(c["camera_id"], c["width"], c["height"], c["f"], c["k"])
    return position_image(truth["cfg"], truth["spec"], man["seed"], man["building_index"],
                          np.array(view["R_true"]), np.array(view["t_true"]), intr, occluders=occluders, spp=spp)


def read_depth(workspace: Path, name: str) -> np.ndarray | None:
    """A photo's geometric depth map (the photometric one where none), or None."""
    import pycolmap

    from difftex.scene.mvs import DEPTH_DIR

    for kind in ("geometric", "photometric"):
        path = workspace / DEPTH_DIR / f"{name}.{kind}.bin"
        if path.is_file():
            dm = pycolmap.DepthMap()
            dm.read(str(path))
            return np.asarray(dm.to_array(), np.float64)
    return None


def pixel_rays(ws_cam, shape: tuple[int, int], orig_cam) -> tuple[np.ndarray, np.ndarray]:
    """For every pixel of a depth map of ``shape`` (h, w) in the workspace camera: the original
    photo's pixel its ray passes through (N, 2), and the ray at unit depth in camera space (N, 3)."""
    h, w = shape
    sx, sy = w / ws_cam.width, h / ws_cam.height
    ys, xs = np.mgrid[0:h, 0:w]
    px = np.stack([(xs.ravel() + 0.5) / sx, (ys.ravel() + 0.5) / sy], 1)
    ray = np.concatenate([np.asarray(ws_cam.cam_from_img(px)), np.ones((len(px), 1))], 1)
    return np.asarray(orig_cam.img_from_cam(ray)), ray


def true_depth_map(truth: dict, view: dict, ws_image, ws_cam, orig_cam, shape, spp: int = 4):
    """The true depth (along the model's optical axis) and the building mask of a depth map's
    pixels: (h, w) float64 (0 off the building or outside the photo) and (h, w) bool."""
    pos = true_points(truth, view, None, spp)
    clean = true_points(truth, view, False, spp) if truth["cfg"].occluders else pos
    uv, _ = pixel_rays(ws_cam, shape, orig_cam)
    H, W = pos.shape[:2]
    u, v = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
    inside = (u >= 0) & (v >= 0) & (u < W) & (v < H)
    X = np.zeros((len(u), 3))
    Xc = np.zeros((len(u), 3))
    X[inside], Xc[inside] = pos[v[inside], u[inside]], clean[v[inside], u[inside]]
    cfw = ws_image.cam_from_world()
    z = X @ np.asarray(cfw.rotation.matrix())[2] + np.asarray(cfw.translation)[2]
    on = (inside & (np.linalg.norm(X, axis=1) > 1e-6) & (X[:, 2] > truth["ground"])
          & np.all((X >= truth["lo"]) & (X <= truth["hi"]), axis=1)
          & (np.linalg.norm(X - Xc, axis=1) < 1e-3 * np.maximum(z, 1e-6)) & (z > 0))
    return np.where(on, z, 0.0).reshape(shape), on.reshape(shape)


def depth_errors(est: np.ndarray, true: np.ndarray, on: np.ndarray) -> dict:
    """The figures of one or more depth maps over the building pixels ``on``."""
    has = on & np.isfinite(est) & (est > 0)
    err = np.abs(est[has] - true[has])
    n = int(on.sum())
    return {
        "building_pixels": n,
        "completeness": float(has.sum() / max(n, 1)),
        "median_abs_err": float(np.median(err)) if err.size else None,
        "median_rel_err": float(np.median(err / true[has])) if err.size else None,
        "mean_abs_err": float(err.mean()) if err.size else None,
        "p90_abs_err": float(np.percentile(err, 90)) if err.size else None,
        "within_1pct": float((err < 0.01 * true[has]).sum() / max(n, 1)),
        "within_5cm": float((err < 0.05).sum() / max(n, 1)),
    }


def score_workspace(scene: Path, workspace: Path, truth: dict, max_views: int, spp: int) -> dict:
    """Depth accuracy of a workspace's maps against a synthetic scene's truth, per photo and pooled
    over at most ``max_views`` photos (evenly spread over the names)."""
    import pycolmap

    from difftex.scene.loading import find_sparse

    ws = pycolmap.Reconstruction(str(workspace / "sparse"))
    orig = pycolmap.Reconstruction(str(find_sparse(scene)))
    views = {v["name"]: v for v in truth["manifest"]["views"]}
    images = sorted((im for im in ws.images.values() if im.has_pose and im.name in views), key=lambda im: im.name)
    images = images[:: max(1, -(-len(images) // max_views))]
    rows, pooled = [], {"est": [], "true": [], "on": []}
    for im in images:
        est = read_depth(workspace, im.name)
        if est is None:
            rows.append({"name": im.name, "depth_map": False})
            continue
        orig_im = orig.find_image_with_name(im.name)
        true, on = true_depth_map(truth, views[im.name], im, ws.cameras[im.camera_id],
                                  orig.cameras[orig_im.camera_id], est.shape, spp)
        rows.append({"name": im.name, "depth_map": True, "size": [est.shape[1], est.shape[0]],
                     **depth_errors(est, true, on)})
        for k, a in (("est", est), ("true", true), ("on", on)):
            pooled[k].append(a.ravel())
    allv = depth_errors(*(np.concatenate(pooled[k]) for k in ("est", "true", "on"))) if pooled["on"] else None
    noise = {k: truth["cfg"].__dict__[k] for k in ("pose_noise_rot_deg", "pose_noise_trans", "occluders")}
    return {"views": rows, "all": allv, "scene_config": noise}


def markdown(data: dict) -> str:
    """The results page."""
    m, rec = data["meta"], data["record"]
    lines = [f"# Dense stereo on a GPU: {m['scene']}", "",
             f"Command: `{m['command']}`  ", f"Date: {m['date']}  ",
             f"Device: {m['gpu'] or 'none'}; pycolmap {m['pycolmap']}", ""]
    sec = {k: rec.get("seconds", {}).get(k, float("nan")) for k in ("undistort", "patch_match", "total")}
    photos = rec.get("photos") or []
    maps = [p for p in photos if p.get("kind")]
    lines += [f"Workspace: `{m['workspace']}`; {len(maps)} depth maps of {len(photos)} photos; "
              f"undistortion {sec['undistort']:.1f} s, PatchMatch {sec['patch_match']:.1f} s, "
              f"total {sec['total']:.1f} s; config `{json.dumps(rec.get('config'))}`", ""]
    if maps:
        share = np.median([p["valid_share"] for p in maps])
        lines += [f"Median share of a map's pixels with a depth: {100 * share:.0f} %", ""]
    score = data.get("score")
    if score is None:
        lines.append("No ground truth (not a `difftex synth` scene): no accuracy figures.")
        return "\n".join(lines) + "\n"
    lines += [f"Accuracy against the true geometry, building pixels only (scene: {score['scene_config']}):", "",
              "| photo | building px | completeness | median abs err | mean | p90 | median rel err | within 1 % "
              "| within 5 cm |",
              "|---|---|---|---|---|---|---|---|---|"]

    def fmt(v, nd=3):
        return "-" if v is None else f"{v:.{nd}f}"

    for r in [*score["views"], {"name": "**all**", "depth_map": True, **(score["all"] or {})}]:
        if not r.get("depth_map"):
            lines.append(f"| {r['name']} | no depth map | | | | | | | |")
            continue
        lines.append(f"| {r['name']} | {r.get('building_pixels', 0)} | {fmt(r.get('completeness'))} | "
                     f"{fmt(r.get('median_abs_err'), 4)} | {fmt(r.get('mean_abs_err'), 4)} | "
                     f"{fmt(r.get('p90_abs_err'), 4)} | {fmt(r.get('median_rel_err'), 4)} | "
                     f"{fmt(r.get('within_1pct'))} | {fmt(r.get('within_5cm'))} |")
    return "\n".join(lines) + "\n"


def _gpu_name() -> str | None:
    try:
        import torch

        return torch.cuda.get_device_name(0) if torch.cuda.is_available() else None
    except Exception:  # noqa: BLE001 -- a label only
        return None


def main(argv=None) -> int:
    import pycolmap

    from difftex.errors import DifftexError
    from difftex.scene import mvs

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", required=True, type=Path, help="scene folder (a `difftex synth` one is scored)")
    ap.add_argument("--workspace", type=Path, help="score this workspace (made before) instead of running stereo")
    ap.add_argument("--work", type=Path, help="where the stage writes its workspace "
                                              "(default evaluation/out/dense_stereo/<scene>)")
    ap.add_argument("--max-image-size", type=int, default=mvs.DenseStereoConfig.max_image_size)
    ap.add_argument("--max-views", type=int, default=12, help="photos scored at most (ray tracing each takes seconds)")
    ap.add_argument("--spp", type=int, default=4, help="samples per pixel of the true points")
    ap.add_argument("--out", type=Path, help="results stem (default evaluation/results/dense_stereo_<scene>)")
    args = ap.parse_args(argv)

    scene = args.scene
    name = scene.resolve().name
    if not (scene / "images").is_dir():
        raise DifftexError(f"{scene}: not a scene folder (no images/)")
    t0 = time.perf_counter()
    if args.workspace is not None:
        workspace = args.workspace
        rec_path = workspace / mvs.RECORD
        record = json.loads(rec_path.read_text()) if rec_path.is_file() else {}
    else:
        if not mvs.cuda_available():
            print(SKIP_LINE)
            return 0
        workspace = args.work or ROOT / "evaluation" / "out" / "dense_stereo" / name
        cfg = mvs.DenseStereoConfig(max_image_size=args.max_image_size, photos="all")
        record = mvs.run_dense_stereo(scene, workspace, None, cfg, threads=os.cpu_count() or 1)
        print(f"stereo: {record['seconds']}", flush=True)
    truth = synth_truth(scene)
    score = score_workspace(scene, workspace, truth, args.max_views, args.spp) if truth else None
    meta = {"scene": str(scene), "workspace": str(workspace),
            "command": shlex.join(["python", "evaluation/bench_dense_stereo.py",
                                   *(argv if argv is not None else sys.argv[1:])]),
            "date": datetime.now(UTC).strftime("%Y-%m-%d %H:%M UTC"), "gpu": _gpu_name(),
            "pycolmap": pycolmap.__version__, "cuda": mvs.cuda_available(),
            "bench_seconds": round(time.perf_counter() - t0, 1)}
    data = {"meta": meta, "record": record, "score": score}
    stem = args.out or ROOT / "evaluation" / "results" / f"dense_stereo_{name}"
    stem.parent.mkdir(parents=True, exist_ok=True)
    Path(f"{stem}.json").write_text(json.dumps(data, indent=1, default=float) + "\n")
    Path(f"{stem}.md").write_text(markdown(data))
    if score and score["all"]:
        a = score["all"]
        print(f"all: completeness {a['completeness']:.3f}, median |err| {a['median_abs_err']}, "
              f"within 1 % {a['within_1pct']:.3f}", flush=True)
    print(f"wrote {stem}.md", flush=True)
    return 0


if __name__ == "__main__":
    from evaluation.common import run_script

    run_script(main)
