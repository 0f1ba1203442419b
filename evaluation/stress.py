"""Stress test: random photo subsets of decreasing size, every method, scored against ground truth.

    python evaluation/stress.py                         # tiny scene, 2 facades, 20/10/5 photos, 128-texel maps
    python evaluation/stress.py --sizes 20,10,5,3 --seed 1 --polygons all

For each size a seeded random subset of the scene's photos is kept (the scene is copied with the
others removed from its COLMAP model: `difftex.evaluation.holdout.prepare_holdout(..., keep=...)`), the
whole pipeline runs on the copy and every method is scored on the ground-truth maps.
"""

from __future__ import annotations

import argparse
import shlex
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from evaluation import common as C  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="evaluation/out/scenes/tiny")
    ap.add_argument("--sizes", default="20,10,5", help="photo counts, decreasing")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--polygons", default="wall00,wall01", help="comma-separated ids, or 'all'")
    ap.add_argument("--long-side", type=int, default=128)
    ap.add_argument("--preset", default="fast")
    ap.add_argument("--methods", default="difftex,average,frontal,mrf")
    C.add_table_args(ap, "stress")
    args = ap.parse_args(argv)

    import numpy as np
    import torch

    from difftex.evaluation.holdout import prepare_holdout
    from difftex.scene.camera import read_reconstruction
    from difftex.scene.loading import find_sparse
    from evaluation.table1 import ensure_synth

    torch.set_num_threads(args.threads)
    t_all = time.perf_counter()
    scene, work = Path(args.scene), Path(args.work)
    ensure_synth(scene)
    names = sorted(im.name for im in read_reconstruction(find_sparse(scene)).images.values())
    rng = np.random.default_rng(args.seed)
    order = list(rng.permutation(names))  # nested subsets: each smaller one is part of the larger
    only = C.polygon_ids(args.polygons)
    cfg = C.base_config(args.long_side, args.preset, {"evaluate": {"views": False}})
    rows = []
    for n in [int(s) for s in args.sizes.split(",")]:
        keep = sorted(order[: min(n, len(names))])
        sub = work / f"n{n:03d}"
        prepare_holdout(scene, 0, sub / "scene", keep=keep)
        common = C.run_common(sub / "scene", sub, cfg, only)
        for m in args.methods.split(","):
            if not common["polygons"]:
                rows.append({"photos": n, "method": m, "skipped": "no polygon seen"})
                continue
            r = C.run_method(m, sub / "scene", sub / m, common)
            ev = C.evaluate(sub / "scene", sub / m, args.lpips, config=common["config"])
            cov = [row["coverage"] for row in common["polygons"]]
            rows.append(
                {
                    "photos": n,
                    "method": m,
                    "run": r,
                    "metrics": ev,
                    "kept": keep,
                    "coverage": float(np.mean(cov)),
                    "polygons": len(cov),
                }
            )
            print(f"stress: {n} photos, {m} done in {r['total_s']:.0f} s", flush=True)
    mach = C.machine()
    notes = [
        f"Scene `{scene}`; polygons {args.polygons}; nested random photo subsets (seed {args.seed}) of sizes "
        f"{args.sizes}.",
        f"**Reduced sizes**: texture long side {args.long_side}, difftex preset `{args.preset}`.",
        "Coverage: mean share of the polygons' texels that some kept photo sees (the rest is filled from neighbours "
        "by every method alike). Maps scored against ground truth as in Table 1.",
    ]
    lines = [
        C.header(
            "Stress test: fewer and fewer photos",
            "python evaluation/stress.py " + shlex.join(sys.argv[1:] if argv is None else argv),
            mach,
            notes,
        )
    ]
    lv = next((r["metrics"]["maps"]["overall"]["lpips_variant"] for r in rows if "metrics" in r), "n/a")
    lines.append(f"| Photos | Method | coverage | Error (90%) | Error (95%) | SSIM | LPIPS ({lv}) | Time (s) |")
    lines.append("|---|---|---|---|---|---|---|---|")
    for r in rows:
        if "metrics" not in r:
            lines.append(
                f"| {r['photos']} | {C.LABELS.get(r['method'], r['method'])} | 0 | n/a | n/a | n/a | n/a | n/a |"
            )
            continue
        o = r["metrics"]["maps"]["overall"]
        lines.append(
            f"| {r['photos']} | {C.LABELS.get(r['method'], r['method'])} | {r['coverage']:.3f} | "
            f"{C.fmt(o['error90'])} | "
            f"{C.fmt(o['error95'])} | {C.fmt(o['ssim'])} | {C.fmt(o['lpips'])} | {r['run']['total_s']:.0f} |"
        )
    C.finish_table(Path(args.out), lines, t_all, mach, args, rows)
    return 0


if __name__ == "__main__":
    C.run_script(main)
