"""difftex initialize: the first per-polygon stage, each candidate photo decoded once and cropped."""

from __future__ import annotations

NAME = "initialize"
HELP = ("decode and crop each polygon's candidate photos once, for the optimize stage "
        "(R/init/<polygon>/crops.npz; the workflow's initialize rule)")
REUSE_FREED_MEMORY = True  # difftex.cli._memory: keep freed memory for reuse in this job


def add_arguments(parser) -> None:
    from difftex.cli._polygon import add_common, add_job

    add_common(parser, many=True)
    add_job(parser, decode_cache=True)
    parser.add_argument("--out", required=True, nargs="+",
                        help="the crops file to write per --visibility file (R/init/<polygon>/crops.npz)")


def run(args) -> int:
    import time

    from difftex.cli._memory import give_back_freed_memory
    from difftex.cli._polygon import decoder, load_many
    from difftex.compose.stage_files import initialize_polygon, write_init
    from difftex.errors import DifftexError
    from difftex.scene.files import DecodeCache, write_json

    if len(args.out) != len(args.visibility):
        raise DifftexError(f"initialize: {len(args.visibility)} --visibility files but {len(args.out)} --out files")
    # no torch in this process: importing it would cost more than a small polygon's crops
    cfg, _, inputs = load_many(args, args.visibility, torch_threads=False)
    decode = decoder(args, len(args.visibility))
    done = []
    for n, (inp, out) in enumerate(zip(inputs, args.out, strict=True), 1):
        t0 = time.perf_counter()
        crops, stats = initialize_polygon(inp, cfg, decode)
        write_init(out, inp.polygon_id, [p.name for p in inp.photos], crops, stats)
        mpix = sum(c.pixels.shape[0] * c.pixels.shape[1] for c in crops.values()) / 1e6
        print(f"initialize {inp.polygon_id} ({n}/{len(args.out)}): {stats['photo_reads']} photos read, "
              f"{mpix:.1f} Mpixel of crops, {time.perf_counter() - t0:.1f}s", flush=True)
        done.append({"polygon": inp.polygon_id, "out": str(out), "seconds": round(time.perf_counter() - t0, 3)})
        del crops
        give_back_freed_memory()  # the next polygon starts from its own peak, not this one's heap
    if isinstance(decode, DecodeCache):
        print(f"photos: {decode.decodes} decoded, {decode.hits} reused")
    if args.done:
        write_json(args.done, {"polygons": done})
    return 0
