"""difftex optimize: the per-polygon optimization stage, from the initialization's crops."""

from __future__ import annotations

NAME = "optimize"
HELP = ("optimize each polygon's blend weights from its crops (difftex initialize) and brightness transfers "
        "(difftex histmatch; without --transfers they are estimated here): pyramids, the coarse-to-fine "
        "optimization; decodes no photo (the workflow's optimize rule)")
REUSE_FREED_MEMORY = True  # difftex.cli._memory: keep freed memory for reuse in this job


def add_arguments(parser) -> None:
    from difftex.cli._polygon import add_common, add_job

    add_common(parser, many=True)
    add_job(parser, decode_cache=False)
    parser.add_argument("--init", required=True, nargs="+",
                        help="the crops file per --visibility file (difftex initialize)")
    parser.add_argument("--transfers", nargs="+",
                        help="the transfers file per --visibility file (difftex histmatch); without it, "
                        "the relief sweep and the transfers run here")
    parser.add_argument("--out-dir", required=True, nargs="+",
                        help="folder for weights.npz, optimized.npz and stats.json per --visibility file "
                        "(R/optimized/<polygon>)")
    parser.add_argument("--no-progress", action="store_true")


def run(args) -> int:
    import time

    from difftex.cli._memory import give_back_freed_memory
    from difftex.cli._polygon import load_many
    from difftex.compose.stage_files import read_histmatch, read_init, write_optimized
    from difftex.compose.texturing import optimize_photos
    from difftex.errors import DifftexError
    from difftex.sampling.photos import PhotoSet, pick_device
    from difftex.scene.files import write_json

    if not len(args.init) == len(args.out_dir) == len(args.visibility) == len(args.transfers or args.init):
        raise DifftexError(f"optimize: {len(args.visibility)} --visibility files, {len(args.init)} --init files, "
                           f"{len(args.transfers or [])} --transfers files and {len(args.out_dir)} --out-dir folders")
    cfg, compute, inputs = load_many(args, args.visibility)
    device = pick_device(compute.device)
    done = []
    transfers = args.transfers or [None] * len(args.init)
    for n, (inp, init, tr, out_dir) in enumerate(zip(inputs, args.init, transfers, args.out_dir, strict=True), 1):
        t0 = time.perf_counter()
        names = [p.name for p in inp.photos]
        crops, read_stats = read_init(init, inp.polygon_id, names)
        brightness = read_histmatch(tr, inp.polygon_id, names) if tr is not None else None
        photos = PhotoSet.from_crops(inp, crops, device, cfg.supersample)
        opt = optimize_photos(photos, cfg, compute, progress=not args.no_progress, read_stats=read_stats,
                              brightness=brightness)
        write_optimized(out_dir, opt)
        st = opt.stats
        lv = st["levels"]
        print(
            f"optimize {inp.polygon_id} ({n}/{len(args.out_dir)}): {inp.frame.width}x{inp.frame.height} texels, "
            f"{len(crops)} photos, levels {[lvl['long_side'] for lvl in lv]} iterations "
            f"{[lvl['iterations'] for lvl in lv]}, dropped {len(st['dropped'])}, "
            f"{time.perf_counter() - t0:.1f}s on {st['device']}",
            flush=True,
        )
        done.append({"polygon": inp.polygon_id, "out_dir": str(out_dir), "seconds": round(time.perf_counter() - t0, 3)})
        del opt, photos, crops
        give_back_freed_memory()  # the next polygon starts from its own peak, not this one's heap
    if args.done:
        write_json(args.done, {"polygons": done})
    return 0
