"""difftex optimize: DiffTex blend-weight optimization of one polygon (weights.npz, stats.json)."""

from __future__ import annotations

NAME = "optimize"
HELP = "optimize one polygon's per-texel blend weights by differentiable rendering"


def add_arguments(parser) -> None:
    from difftex.cli._polygon import add_common

    add_common(parser)
    parser.add_argument("--init", required=True, help="the polygon's init .npz (difftex init)")
    parser.add_argument("--out-dir", required=True, help="output folder (R/optimized/<polygon>)")
    parser.add_argument("--no-progress", action="store_true")


def run(args) -> int:
    from pathlib import Path

    import numpy as np

    from difftex.cli._polygon import frame_json, load, pack_transfers, transfers_by_name
    from difftex.io import read_npz, write_json, write_npz
    from difftex.optimize import optimize_polygon

    cfg, inp = load(args)
    init = read_npz(args.init)
    if str(init.get("polygon_id", "")) != inp.polygon_id:
        from difftex.errors import DifftexError

        raise DifftexError(f"{args.init}: made for polygon '{init.get('polygon_id')}', not '{inp.polygon_id}'")
    if cfg.histogram_matching:
        inp.transfers = transfers_by_name(args.init, init, [p.name for p in inp.photos])
    res = optimize_polygon(inp, cfg, progress=not args.no_progress)
    out = Path(args.out_dir)
    H, W = inp.frame.shape
    write_npz(
        out / "weights.npz",
        polygon_id=np.array(inp.polygon_id),
        photos=np.array([p.name for p in inp.photos], dtype=str),
        frame=frame_json(inp.frame),
        shape=np.array([H, W]),
        texel_mask=np.packbits(inp.texel_mask.ravel()),
        idx=res.idx.astype(np.int16),
        W=res.W.astype(np.float16),
        **pack_transfers(inp.transfers, len(inp.photos)),
    )
    stats = dict(res.stats)
    stats["histmatch"] = bool(inp.transfers is not None)
    write_json(out / "stats.json", stats)
    lv = stats["levels"]
    print(f"optimize {inp.polygon_id}: {len(lv)} levels, iterations {[l['iterations'] for l in lv]}, "
          f"coverage {stats['coverage']:.3f}, dropped {len(stats['dropped'])}, {stats['time_total_s']:.1f}s")
    return 0
