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
    from difftex.compose.composite import finish_texture
    from difftex.compose.outputs import write_texture_outputs
    from difftex.evaluation.baselines import baseline_texture

    t0 = time.perf_counter()
    _, compute, inp = load(args)
    U, wsum, dominant, info = baseline_texture(inp, args.method, compute.device)
    U, fill = finish_texture(U, wsum, inp.texel_mask)
    seen = (wsum > 0) & inp.texel_mask
    report = {
        "polygon_id": inp.polygon_id,
        **info,
        **fill,
        "histogram_matching": False,
        "time_s": time.perf_counter() - t0,
    }
    write_texture_outputs(args.out_dir, U, inp.texel_mask, seen, dominant, [p.name for p in inp.photos], report)
    print(f"baseline {args.method} {inp.polygon_id}: coverage {fill['coverage']:.3f}")
    return 0
