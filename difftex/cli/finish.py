"""difftex finish: polygons' PNGs and reports from their composite.npz (the workflow's finish rule)."""

from __future__ import annotations

NAME = "finish"
HELP = "write each polygon's texture.png, source.png/.npz, coverage.png and report.json from its composite.npz"


def add_arguments(p) -> None:
    p.add_argument("--composite", required=True, nargs="+", help="the polygons' composite.npz (difftex texture)")
    p.add_argument("--config", help="YAML config; its 'output' section (bit depth, EXR) is read")
    p.add_argument("--out-dir", required=True, nargs="+",
                   help="a folder per composite, in the same order (R/textures/<polygon>)")
    p.add_argument("--done", help="write this JSON (the polygons finished) last: the workflow's output of a job")


def run(args) -> int:
    # numpy and the image writers only: no torch, so a finish job starts in a tenth of a second;
    # the workflow gives it a texture job's polygons, so a district is not one job per polygon
    from difftex.compose.outputs import OutputConfig, finish_polygon
    from difftex.config import section
    from difftex.errors import DifftexError
    from difftex.scene.files import write_json

    if len(args.composite) != len(args.out_dir):
        raise DifftexError(f"{len(args.composite)} --composite files but {len(args.out_dir)} --out-dir folders")
    cfg = section(args.config, "output", OutputConfig)
    done = []
    for composite, out_dir in zip(args.composite, args.out_dir):
        report = finish_polygon(composite, out_dir, cfg)
        done.append(report.get("polygon_id"))
        print(f"finish {report.get('polygon_id')}: {out_dir} ({cfg.bits}-bit" + (", exr" if cfg.exr else "") + ")")
    if args.done:
        write_json(args.done, {"polygons": done})
    return 0
