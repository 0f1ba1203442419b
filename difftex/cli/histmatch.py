"""difftex histmatch: final texture of one polygon from its optimized weights and brightness-adjusted photos."""

from __future__ import annotations

NAME = "histmatch"
HELP = "compose one polygon's final texture (brightness-adjusted photos, optimized weights), fill holes, write maps"


def add_arguments(parser) -> None:
    from difftex.cli._polygon import add_common

    add_common(parser)
    parser.add_argument("--optimized", required=True, help="the polygon's optimize output folder (weights.npz, stats.json)")
    parser.add_argument("--out-dir", required=True, help="output folder (R/textures/<polygon>)")


def run(args) -> int:
    from pathlib import Path

    import numpy as np

    from difftex.cli._polygon import load, transfers_by_name
    from difftex.errors import DifftexError
    from difftex.io import read_json, read_npz
    from difftex.optimize import pick_device
    from difftex.texture import compose_slots, dominant_from_slots, finish_texture, write_texture_outputs

    cfg, inp = load(args)
    opt = Path(args.optimized)
    wz = read_npz(opt / "weights.npz")
    stats = read_json(opt / "stats.json")
    names = [p.name for p in inp.photos]
    saved = [str(x) for x in wz["photos"]]
    if saved != names or str(wz["polygon_id"]) != inp.polygon_id:
        raise DifftexError(f"{opt / 'weights.npz'}: made for another polygon or photo set; rerun 'difftex optimize'")
    if tuple(int(v) for v in wz["shape"]) != inp.frame.shape:
        raise DifftexError(f"{opt / 'weights.npz'}: texture size {tuple(wz['shape'])} differs from the visibility's {inp.frame.shape}")
    if cfg.histogram_matching:
        inp.transfers = transfers_by_name(opt / "weights.npz", wz, names)
    idx, W = wz["idx"].astype(np.int64), wz["W"].astype(np.float32)
    U, wsum = compose_slots(inp, idx, W, device=pick_device(cfg.device))
    U, fill = finish_texture(U, wsum, inp.texel_mask)
    seen = (wsum > 0) & inp.texel_mask
    dominant = dominant_from_slots(idx, W)
    report = {"polygon_id": inp.polygon_id, "method": "difftex", "histogram_matching": inp.transfers is not None,
              **fill, "optimize": stats}
    write_texture_outputs(args.out_dir, U, inp.texel_mask, seen, dominant, names, report,
                          bits=cfg.output_bits, exr=cfg.write_exr)
    print(f"histmatch {inp.polygon_id}: coverage {fill['coverage']:.3f}, filled {fill['filled_texels']} texels")
    return 0
