"""difftex init: candidate photos, Q at the coarse level and brightness transfers for one polygon."""

from __future__ import annotations

NAME = "init"
HELP = "prepare one polygon's optimization: candidates, coarse Q, HSV histogram-matching transfers"


def add_arguments(parser) -> None:
    from difftex.cli._polygon import add_common

    add_common(parser)
    parser.add_argument("--out", required=True, help="output .npz (R/init/<polygon>.npz)")


def run(args) -> int:
    import json
    import time

    import numpy as np

    from difftex.cli._polygon import load, pack_transfers
    from difftex.histmatch import polygon_transfers
    from difftex.io import write_npz
    from difftex.optimize import build_level, build_samplers, level_frame, pick_device

    t0 = time.perf_counter()
    cfg, inp = load(args)
    device = pick_device(cfg.device)
    samplers = build_samplers(inp, device)
    transfers, ref = (None, None)
    if cfg.histogram_matching:
        transfers, ref = polygon_transfers(inp, cfg, device, samplers)
        inp.transfers = transfers
    frame = level_frame(inp.frame, min(cfg.long_side_start, max(inp.frame.shape)))
    lv = build_level(inp, frame, samplers, cfg, device)
    info = {
        "polygon_id": inp.polygon_id, "photos": [p.name for p in inp.photos],
        "photos_seeing": [inp.photos[n].name for n in sorted(samplers)],
        "histmatch_reference": ref, "histmatch_mode": cfg.histmatch_reference if cfg.histogram_matching else None,
        "coarse_shape": list(frame.shape), "seconds": time.perf_counter() - t0,
    }
    write_npz(
        args.out,
        polygon_id=np.array(inp.polygon_id),
        photos=np.array([p.name for p in inp.photos], dtype=str),
        coarse_idx=lv.idx.cpu().numpy().astype(np.int16),
        coarse_Q=lv.Q.cpu().numpy().astype(np.float16),
        info=np.array(json.dumps(info)),
        **pack_transfers(transfers, len(inp.photos)),
    )
    refname = ref or (f"per-texel {cfg.histmatch_reference}" if cfg.histogram_matching else "none (matching off)")
    print(f"init {inp.polygon_id}: {len(samplers)}/{len(inp.photos)} photos see it, brightness reference {refname}")
    return 0
