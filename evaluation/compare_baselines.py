"""DiffTex against plain averaging and the most frontal photo, on synthetic and real scenes.

    python evaluation/compare_baselines.py --scene /tmp/synth/tiny --scene ../shared/data/lund-door \
        --polygons wall --long-side 512 --out evaluation/compare

Per scene and polygon it writes a side-by-side figure
``<out>/<scene>/<polygon>.jpg`` = [ground truth |] difftex (texel) | difftex (render) | average |
frontal | difftex source map, and with ground truth (synthetic scenes: ground_truth/maps) the
Error 90/95 %, SSIM and PSNR of every method (difftex.evaluation.metrics, over the ground-truth mask).
Real scenes have no ground truth; they get a no-reference sharpness figure (mean gradient
magnitude of the texture over the polygon) next to the pictures, which are what to look at.
Results: ``<out>/results.json`` and ``<out>/results.md`` (with the command and the machine).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import numpy as np


def sharpness(img: np.ndarray, mask: np.ndarray) -> float:
    gx = np.abs(np.diff(img, axis=1)).mean(-1)
    gy = np.abs(np.diff(img, axis=0)).mean(-1)
    m = mask[:, 1:] & mask[:, :-1]
    n = mask[1:, :] & mask[:-1, :]
    return float((gx[m].sum() + gy[n].sum()) / max(m.sum() + n.sum(), 1))


def area_down(x: np.ndarray, f: int) -> np.ndarray:
    """Box-average by an integer factor (edges replicated to a multiple of f)."""
    if f == 1:
        return x
    h, w = x.shape[:2]
    H, W = -(-h // f) * f, -(-w // f) * f
    pad = [(0, H - h), (0, W - w)] + [(0, 0)] * (x.ndim - 2)
    x = np.pad(x.astype(np.float32), pad, mode="edge")
    return x.reshape(H // f, f, W // f, f, *x.shape[2:]).mean((1, 3))


def run_difftex(inp, cfg, device):
    from difftex.compose.composite import compose_slots, dominant_from_slots, finish_texture
    from difftex.compose.histmatch import polygon_transfers
    from difftex.optimize import optimize_polygon

    t0 = time.perf_counter()
    inp.transfers = None
    if cfg.histogram_matching:
        inp.transfers, _ = polygon_transfers(inp, cfg, device)
    res = optimize_polygon(inp, cfg)
    U, wsum = compose_slots(inp, res.idx, res.W, device=device)
    U, fill = finish_texture(U, wsum, inp.texel_mask)
    stats = {
        "time_s": time.perf_counter() - t0,
        "iterations": [lvl["iterations"] for lvl in res.stats["levels"]],
        "dropped": [d["photo"] for d in res.stats["dropped"]],
        "coverage": fill["coverage"],
    }
    return U, dominant_from_slots(res.idx, res.W), stats


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", action="append", required=True)
    ap.add_argument(
        "--polygons", nargs="*", default=None, help="polygon ids (default: all); ids missing in a scene are skipped"
    )
    ap.add_argument("--long-side", type=int, default=512)
    ap.add_argument("--methods", nargs="+", default=["difftex", "difftex-render", "average", "frontal"])
    ap.add_argument("--config", default=None, help="YAML with an 'optimize:' section")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out", default="evaluation/compare")
    args = ap.parse_args()

    import torch

    from difftex.compose.composite import finish_texture, source_map
    from difftex.config import section
    from difftex.evaluation import metrics
    from difftex.evaluation.baselines import baseline_texture
    from difftex.geometry.visibility import scene_visibility
    from difftex.optimize import OptimizeConfig, pick_device, polygon_input_from_visibility
    from difftex.scene.files import read_image, write_image, write_json, write_text
    from difftex.scene.loading import load_scene

    sys.path.insert(0, str(Path(__file__).parent))
    from bench_optimize import machine

    torch.set_num_threads(args.threads)
    cfg = section(args.config, "optimize", OptimizeConfig)
    device = pick_device(cfg.device)
    out = Path(args.out)
    results = []
    for scene_dir in args.scene:
        sc = load_scene(scene_dir, check_images=False)
        pids = [p for p in sc.proxy.ids if args.polygons is None or p in args.polygons]
        names = [p.name for p in sc.photos]
        t0 = time.perf_counter()
        vis_all = scene_visibility(
            sc.proxy, sc.photos, sc.up, {p: names for p in pids}, args.long_side, None, progress=False
        )
        t_vis = time.perf_counter() - t0
        by_name = {p.name: p for p in sc.photos}
        gt_dir = Path(scene_dir) / "ground_truth"
        for vis in vis_all:
            if vis.polygon_id not in pids or not vis.photos:
                continue
            pid = vis.polygon_id
            row = {
                "scene": sc.name,
                "polygon": pid,
                "photos": len(vis.photos),
                "shape": list(vis.frame.shape),
                "visibility_s": round(t_vis, 1),
                "methods": {},
            }
            gt = mask = None
            if (gt_dir / "maps" / f"{pid}.png").is_file():
                gt = read_image(gt_dir / "maps" / f"{pid}.png")
                mask = read_image(gt_dir / "masks" / f"{pid}.png")[..., 0] > 0.5
                if gt.shape[:2] != vis.frame.shape:
                    print(
                        f"{sc.name}/{pid}: ground truth {gt.shape[:2]} != texture {vis.frame.shape}, metrics skipped",
                        file=sys.stderr,
                    )
                    gt = None
            panels = [gt] if gt is not None else []
            src = None
            for method in args.methods:
                inp = polygon_input_from_visibility(vis, by_name)
                t1 = time.perf_counter()
                if method.startswith("difftex"):
                    mcfg = dataclasses.replace(cfg, loss_mode="render" if method.endswith("render") else "texel")
                    U, dom, st = run_difftex(inp, mcfg, device)
                    if src is None:
                        src = source_map(dom, vis.photos, vis.texel_mask)
                else:
                    U, wsum, dom, info = baseline_texture(inp, method, device)
                    U, fill = finish_texture(U, wsum, vis.texel_mask)
                    st = {"time_s": time.perf_counter() - t1, "coverage": fill["coverage"]}
                m = {"time_s": round(st["time_s"], 1), "sharpness": round(sharpness(U, vis.texel_mask), 5)}
                m.update({k: v for k, v in st.items() if k not in ("time_s",)})
                if gt is not None:
                    e = metrics.error_percentiles(U, gt, mask)
                    m.update(
                        {
                            "error90": round(e[90.0], 4),
                            "error95": round(e[95.0], 4),
                            "ssim": round(metrics.ssim(U, gt, mask), 4),
                            "psnr": round(metrics.psnr(U, gt, mask), 2),
                        }
                    )
                    # the same at half resolution: when the photos resolve the surface more coarsely
                    # than the ground truth, per-texel errors at full size measure unresolvable detail
                    mh = area_down(mask.astype(np.float32), 2) > 0.99
                    e2 = metrics.error_percentiles(area_down(U, 2), area_down(gt, 2), mh)
                    m.update({"error90_half": round(e2[90.0], 4), "error95_half": round(e2[95.0], 4)})
                row["methods"][method] = m
                panels.append(U)
                print(f"{sc.name}/{pid} {method}: {m}", flush=True)
            if src is not None:
                panels.append(src)
            sep = np.ones((vis.frame.shape[0], 4, 3), np.float32)
            fig = np.concatenate([x for p in panels for x in (np.clip(p, 0, 1), sep)][:-1], axis=1)
            write_image(out / sc.name / f"{pid}.jpg", fig)
            row["figure"] = str(out / sc.name / f"{pid}.jpg")
            row["panels"] = (
                (["ground truth"] if gt is not None else [])
                + list(args.methods)
                + (["difftex source map"] if src is not None else [])
            )
            results.append(row)
            write_json(
                out / "results.json",
                {"command": " ".join(sys.argv), "machine": machine(), "config": cfg.to_dict(), "results": results},
            )
    # markdown summary
    lines = [
        "# DiffTex vs plain averaging vs most frontal photo",
        "",
        f"Command: `{' '.join(sys.argv)}`",
        "",
        f"Texture long side {args.long_side}; optimizer config = defaults"
        + (f" + {args.config}" if args.config else "")
        + ".",
        "",
    ]
    with_gt = [r for r in results if any("error95" in m for m in r["methods"].values())]
    if with_gt:
        lines += [
            "## Synthetic scenes (against ground truth)",
            "",
            "| scene/polygon | method | Error 90% | Error 95% | SSIM | PSNR | Error 90% (1/2 res) | Error 95% (1/2 "
            "res) | sharpness | time (s) |",
            "|---|---|---|---|---|---|---|---|---|---|",
        ]
        for r in with_gt:
            for meth, m in r["methods"].items():
                lines.append(
                    f"| {r['scene']}/{r['polygon']} | {meth} | {m['error90']} | {m['error95']} | {m['ssim']} | "
                    f"{m['psnr']} | "
                    f"{m['error90_half']} | {m['error95_half']} | {m['sharpness']} | {m['time_s']} |"
                )
        keys = ("error90", "error95", "ssim", "psnr", "error90_half", "error95_half")
        lines += [
            "",
            "Mean over polygons:",
            "",
            "| method | Error 90% | Error 95% | SSIM | PSNR | Error 90% (1/2) | Error 95% (1/2) |",
            "|---|---|---|---|---|---|---|",
        ]
        for meth in args.methods:
            vals = [r["methods"][meth] for r in with_gt if meth in r["methods"]]
            lines.append(f"| {meth} | " + " | ".join(f"{np.mean([v[k] for v in vals]):.4f}" for k in keys) + " |")
        lines.append("")
    real = [r for r in results if r not in with_gt]
    if real:
        lines += [
            "## Real scenes (no ground truth: look at the figures)",
            "",
            "| scene/polygon | photos | method | sharpness (mean abs. gradient) | time (s) |",
            "|---|---|---|---|---|",
        ]
        for r in real:
            for meth, m in r["methods"].items():
                lines.append(
                    f"| {r['scene']}/{r['polygon']} | {r['photos']} | {meth} | {m['sharpness']} | {m['time_s']} |"
                )
        lines.append("")
    lines += ["Figures (left to right: " + ", ".join(results[0]["panels"] if results else []) + "):", ""]
    lines += [f"- `{r['figure']}`" for r in results]
    write_text(out / "results.md", "\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
