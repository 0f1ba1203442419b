"""difftex histmatch: the per-polygon histogram-matching stage, from the initialization's crops."""

from __future__ import annotations

NAME = "histmatch"
HELP = ("estimate each polygon's brightness transfers (histogram matching) from its crops (difftex "
        "initialize), through its relief when optimize.relief sweeps one, for the optimize stage "
        "(R/histmatch/<polygon>/transfers.npz; the workflow's histmatch rule)")
REUSE_FREED_MEMORY = True  # difftex.cli._memory: keep freed memory for reuse in this job


def add_arguments(parser) -> None:
    from difftex.cli._polygon import add_common, add_job

    add_common(parser, many=True)
    add_job(parser, decode_cache=False)
    parser.add_argument("--init", required=True, nargs="+",
                        help="the crops file per --visibility file (difftex initialize)")
    parser.add_argument("--out", required=True, nargs="+",
                        help="the transfers file to write per --visibility file (R/histmatch/<polygon>/transfers.npz)")


def run(args) -> int:
    import time

    from difftex.cli._memory import give_back_freed_memory
    from difftex.cli._polygon import load_many
    from difftex.compose.stage_files import Brightness, write_histmatch
    from difftex.errors import DifftexError
    from difftex.scene.files import write_json

    if not len(args.init) == len(args.out) == len(args.visibility):
        raise DifftexError(f"histmatch: {len(args.visibility)} --visibility files, {len(args.init)} --init files and "
                           f"{len(args.out)} --out files")
    cfg, compute, inputs = load_many(args, args.visibility)
    done = []
    for n, (inp, init, out) in enumerate(zip(inputs, args.init, args.out, strict=True), 1):
        t0 = time.perf_counter()
        names = [p.name for p in inp.photos]
        # nothing to sweep or match: no photo to read (the optimization maps them as it would)
        b = (_match(inp, init, cfg, compute) if cfg.relief or cfg.histogram_matching or inp.dense is not None
             else Brightness(None, None))
        write_histmatch(out, inp.polygon_id, names, b)
        matched = sum(t is not None for t in b.transfers) if b.transfers is not None else 0
        print(f"histmatch {inp.polygon_id} ({n}/{len(args.out)}): {matched} of {len(names)} photos matched"
              + (f" to {b.reference}" if b.reference else "") + (", relief swept" if b.relief is not None else "")
              + f", {time.perf_counter() - t0:.1f}s", flush=True)
        done.append({"polygon": inp.polygon_id, "out": str(out), "seconds": round(time.perf_counter() - t0, 3)})
        del b
        give_back_freed_memory()  # the next polygon starts from its own peak, not this one's heap
    if args.done:
        write_json(args.done, {"polygons": done})
    return 0


def _match(inp, init, cfg, compute):
    """The polygon's Brightness from its crops file, on the device the optimization uses."""
    from difftex.compose.stage_files import read_init
    from difftex.compose.texturing import match_brightness
    from difftex.sampling.photos import PhotoSet, pick_device

    crops, _ = read_init(init, inp.polygon_id, [p.name for p in inp.photos])
    photos = PhotoSet.from_crops(inp, crops, pick_device(compute.device), cfg.supersample)
    b = match_brightness(photos, cfg)
    b.mapped = None  # held for the one-process stage only
    return b
