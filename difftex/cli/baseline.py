"""difftex baseline: plain averaging or most-frontal-photo texture of one polygon (same outputs as histmatch)."""

from __future__ import annotations

NAME = "baseline"
HELP = "texture one polygon with a baseline (average of candidate photos, or most frontal photo)"


def add_arguments(parser) -> None:
    from difftex.cli._polygon import add_common

    add_common(parser)
    parser.add_argument("--method", required=True, choices=["average", "frontal"])
    parser.add_argument(
        "--out-dir",
        required=True,
        help="output folder for texture.png, source.png, source.npz, coverage.png, report.json",
    )


def run(args) -> int:
    import time

    from difftex.cli._polygon import load
    from difftex.evaluation.baselines import baseline_texture, write_baseline_polygon

    t0 = time.perf_counter()
    cfg, compute, inp = load(args)
    U, wsum, dominant, info = baseline_texture(inp, args.method, compute.device, cfg.supersample)
    report = write_baseline_polygon(inp, U, wsum, dominant, info, args.out_dir, t0)
    print(f"baseline {args.method} {inp.polygon_id}: coverage {report['coverage']:.3f}")
    return 0
