"""difftex texture: polygons' texture maps from their candidate photos (the per-polygon stage)."""

from __future__ import annotations

NAME = "texture"
HELP = ("texture one or more polygons: brightness transfers, blend-weight optimization and composition, "
        "reading each candidate photo once per polygon")
REUSE_FREED_MEMORY = True  # difftex.cli._memory: keep freed memory for reuse in this job


def add_arguments(parser) -> None:
    from difftex.cli._polygon import add_common, add_job

    add_common(parser, many=True)
    add_job(parser, decode_cache=True)
    parser.add_argument("--out-dir", required=True, nargs="+",
                        help="folder for weights.npz, stats.json and composite.npz (R/optimized/<polygon>), "
                        "one per --visibility file")
    parser.add_argument(
        "--png-dir",
        help="also write texture.png, source.png, source.npz, coverage.png, report.json here "
        "(one polygon only; the workflow's finish rule does this)",
    )
    parser.add_argument("--no-progress", action="store_true")


def run(args) -> int:
    import time

    from difftex.cli._memory import give_back_freed_memory
    from difftex.cli._polygon import decoder, load_many
    from difftex.compose.outputs import write_texture_outputs
    from difftex.compose.texturing import texture_polygon, write_polygon
    from difftex.errors import DifftexError
    from difftex.scene.files import DecodeCache, write_json

    if len(args.out_dir) != len(args.visibility):
        raise DifftexError(
            f"texture: {len(args.visibility)} --visibility files but {len(args.out_dir)} --out-dir folders"
        )
    if args.png_dir and len(args.visibility) > 1:
        raise DifftexError("texture: --png-dir takes one polygon")
    # One process for several polygons: torch and the scene are loaded once (about 2 s that a
    # small polygon's own work does not reach).
    cfg, compute, inputs = load_many(args, args.visibility)
    # the polygons of a job usually share their photos: decode each once (run.decode_cache_mb)
    decode = decoder(args, len(args.visibility))
    done = []
    for n, (inp, out_dir) in enumerate(zip(inputs, args.out_dir, strict=True), 1):
        t0 = time.perf_counter()
        tp = texture_polygon(inp, cfg, compute, progress=not args.no_progress, decode=decode)
        write_polygon(tp, out_dir)
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
            f"texture {inp.polygon_id} ({n}/{len(args.out_dir)}): {inp.frame.width}x{inp.frame.height} texels, "
            f"{st['photo_reads']} photos read, levels {[lvl['long_side'] for lvl in lv]} iterations "
            f"{[lvl['iterations'] for lvl in lv]}, coverage {tp.report['coverage']:.3f}, dropped {len(st['dropped'])}, "
            f"{st['time_stage_s']:.1f}s on {st['device']}",
            flush=True,
        )
        done.append({"polygon": inp.polygon_id, "out_dir": str(out_dir), "seconds": round(time.perf_counter() - t0, 3)})
        del tp
        give_back_freed_memory()  # the next polygon starts from its own peak, not this one's heap
    if isinstance(decode, DecodeCache):
        print(f"photos: {decode.decodes} decoded, {decode.hits} reused")
    if args.done:
        write_json(args.done, {"polygons": done})
    return 0
