"""difftex compose: the per-polygon composition stage, composite.npz from the optimization's files."""

from __future__ import annotations

NAME = "compose"
HELP = ("compose each polygon's texture (fill of unseen texels, source map, report) from its optimize "
        "stage's files into composite.npz (the workflow's compose rule)")


def add_arguments(p) -> None:
    p.add_argument("--optimized", required=True, nargs="+",
                   help="the polygons' optimize folders (R/optimized/<polygon>); composite.npz is written there")
    p.add_argument("--done", help="write this JSON (the polygons composed) last: the workflow's output of a job")


def run(args) -> int:
    # numpy only: no torch, so a composition job starts in a fraction of a second
    from pathlib import Path

    from difftex.compose.stage_files import read_optimized, write_composed
    from difftex.layout import COMPOSITE
    from difftex.scene.files import write_json

    done = []
    for folder in args.optimized:
        opt = read_optimized(folder)
        report = write_composed(Path(folder) / COMPOSITE, opt)
        done.append(opt.polygon_id)
        print(f"compose {opt.polygon_id}: coverage {report['coverage']:.3f}, {report['filled_texels']} texels filled")
    if args.done:
        write_json(args.done, {"polygons": done})
    return 0
