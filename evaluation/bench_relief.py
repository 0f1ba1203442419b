"""Relief-compensated mapping on the analytic relief wall: what the sweep costs and what it buys.

    python evaluation/bench_relief.py --long-side 512 1024 --device cpu --out evaluation/results/bench_relief_cpu
    python evaluation/bench_relief.py --long-side 1024 2048 --device cuda --out OUT   # on a GPU machine

The scene is tests/analytic_relief.py's wall (4 x 3 m, a window recessed 0.3 m, a balcony 0.4 m
out), photographed from 15 directions at ``--photo-size``, rendered by exact ray casting, so the
truth is known without noise. For each texture long side, the texturing stage runs twice in the
same process, without and with ``optimize.relief``, at the `fast` schedule; the table gives the
stage's wall time, the sweep's own time, and the mean absolute error against the truth over the
wall, in the recess and on the balcony (texels within 2 texels of a relief edge left out, where
both are off by the truth's point sampling of a step). Writes <out>.json and <out>.md.
"""

from __future__ import annotations

import argparse
import json
import platform
import shlex
import sys
import time
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))


def _interior(region: np.ndarray, r: int) -> np.ndarray:
    import torch
    import torch.nn.functional as F

    t = torch.from_numpy(~region).float()[None, None]
    return ~(F.max_pool2d(t, 2 * r + 1, 1, r)[0, 0].numpy() > 0)


def run_one(inp, device: str, relief: bool, side: int) -> dict:
    import analytic_relief as ar
    import torch

    from difftex.compose.texturing import texture_polygon
    from difftex.method.config import ComputeConfig, OptimizeConfig

    keys = dict(long_side_start=64, level_step=4.0, max_iters_per_level=(40, 20, 10), histogram_matching=False)
    if relief:
        keys.update(relief=True, relief_range=(-0.5, 0.5), relief_long_side=min(512, side))
    if device == "cuda":
        torch.cuda.synchronize()
    t0 = time.perf_counter()
    tp = texture_polygon(inp, OptimizeConfig(**keys), ComputeConfig(device=device, compile="off"))
    if device == "cuda":
        torch.cuda.synchronize()
    wall = time.perf_counter() - t0
    col, h = ar.truth(inp.frame)
    err = np.abs(tp.texture - col).mean(-1)
    edge = ~(_interior(h < 0, 2) | _interior(h > 0, 2) | _interior(h == 0, 2))
    m = inp.texel_mask & ~edge
    rel = tp.stats.get("relief") or {}
    return {
        "relief": relief,
        "wall_s": wall,
        "sweep_s": rel.get("time_s"),
        "mae": float(err[m].mean()),
        "mae_recess": float(err[m & (h < 0)].mean()),
        "mae_balcony": float(err[m & (h > 0)].mean()),
        "mae_wall": float(err[m & (h == 0)].mean()),
        "heights": rel.get("levels"),
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--long-side", type=int, nargs="+", default=[512, 1024])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--photo-size", type=int, nargs=2, default=[1024, 768])
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out", default="evaluation/results/bench_relief")
    args = ap.parse_args(argv)

    import analytic_relief as ar
    import torch

    torch.set_num_threads(args.threads)
    w, hgt = args.photo_size
    phs = ar.photos(size=(w, hgt), f=300.0 * w / 320)
    t0 = time.perf_counter()
    images = [ar.render(p) for p in phs]
    render_s = time.perf_counter() - t0
    rows = []
    for side in args.long_side:
        inp = ar.make_input(phs, images, long_side=side)
        for relief in (False, True):
            r = run_one(inp, args.device, relief, side)
            r.update(long_side=side, texels=int(inp.texel_mask.sum()))
            rows.append(r)
            print(json.dumps(r), flush=True)
    dev = torch.cuda.get_device_name(0) if args.device == "cuda" else platform.processor() or platform.machine()
    meta = {
        "command": shlex.join(["python", "evaluation/bench_relief.py", *(argv if argv is not None else sys.argv[1:])]),
        "date": datetime.now(UTC).strftime("%Y-%m-%d %H:%M UTC"),
        "device": dev,
        "torch": torch.__version__,
        "threads": args.threads,
        "photos": len(phs),
        "photo_size": [w, hgt],
        "render_s": render_s,
    }
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps({"meta": meta, "rows": rows}, indent=1))
    lines = [
        "# Relief-compensated mapping on the analytic relief wall",
        "",
        f"Command: `{meta['command']}`  ",
        f"Date: {meta['date']}  ",
        f"Device: {dev}, torch {torch.__version__}, {args.threads} CPU thread(s); {len(phs)} photos of {w}x{hgt}",
        "",
        "Texturing stage (`fast` schedule, no histogram matching) without and with `optimize.relief`, same",
        "process; MAE against the noise-free truth, texels within 2 texels of a relief edge left out.",
        "",
        "| long side | texels | relief | stage (s) | sweep (s) | MAE | recess | balcony | wall |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        sweep = f"{r['sweep_s']:.2f}" if r["sweep_s"] is not None else "-"
        lines.append(
            f"| {r['long_side']} | {r['texels']} | {'on' if r['relief'] else 'off'} | {r['wall_s']:.2f} | {sweep} | "
            f"{r['mae']:.4f} | {r['mae_recess']:.4f} | {r['mae_balcony']:.4f} | {r['mae_wall']:.4f} |"
        )
    out.with_suffix(".md").write_text("\n".join(lines) + "\n")
    print(f"wrote {out.with_suffix('.md')}")
    return 0


if __name__ == "__main__":
    from evaluation.common import run_script

    run_script(main)
