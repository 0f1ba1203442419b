"""difftex texture: one polygon's texture maps from its candidate photos (the per-polygon stage)."""

from __future__ import annotations

NAME = "texture"
HELP = ("texture one polygon: brightness transfers, blend-weight optimization and composition, "
        "reading each candidate photo once")


def add_arguments(parser) -> None:
    from difftex.cli._polygon import add_common

    add_common(parser)
    parser.add_argument("--out-dir", required=True,
                        help="folder for weights.npz, stats.json and composite.npz (R/optimized/<polygon>)")
    parser.add_argument(
        "--png-dir",
        help="also write texture.png, source.png, source.npz, coverage.png, report.json here "
        "(the workflow's finish rule does this)",
    )
    parser.add_argument("--no-progress", action="store_true")


def run(args) -> int:
    from difftex.cli._polygon import load
    from difftex.compose.outputs import write_texture_outputs
    from difftex.compose.texturing import texture_polygon, write_polygon

    cfg, compute, inp = load(args)
    tp = texture_polygon(inp, cfg, compute, progress=not args.no_progress)
    write_polygon(tp, args.out_dir)
    if args.png_dir:
        write_texture_outputs(
            args.png_dir,
            tp.texture,
            inp.texel_mask,
            tp.seen,
            tp.dominant,
            [p.name for p in inp.photos],
            dict(tp.report, optimize=tp.stats),
        )
    st = tp.stats
    lv = st["levels"]
    print(
        f"texture {inp.polygon_id}: {inp.frame.width}x{inp.frame.height} texels, {st['photo_reads']} photos read, "
        f"levels {[lvl['long_side'] for lvl in lv]} iterations {[lvl['iterations'] for lvl in lv]}, "
        f"coverage {tp.report['coverage']:.3f}, dropped {len(st['dropped'])}, {st['time_stage_s']:.1f}s on "
        f"{st['device']}"
    )
    return 0
