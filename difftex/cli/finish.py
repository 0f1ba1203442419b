"""difftex finish: a polygon's PNGs and report from its composite.npz (the workflow's finish rule)."""

from __future__ import annotations

NAME = "finish"
HELP = "write a polygon's texture.png, source.png/.npz, coverage.png and report.json from its composite.npz"


def add_arguments(p) -> None:
    p.add_argument("--composite", required=True, help="the polygon's composite.npz (difftex texture)")
    p.add_argument("--config", help="YAML config; its 'output' section (bit depth, EXR) is read")
    p.add_argument("--out-dir", required=True, help="folder for the polygon's maps (R/textures/<polygon>)")


def run(args) -> int:
    # numpy and the image writers only: no torch, so the workflow's 1-2 jobs per polygon
    # start in a tenth of a second
    from difftex.compose.outputs import OutputConfig, finish_polygon
    from difftex.config import section

    cfg = section(args.config, "output", OutputConfig)
    report = finish_polygon(args.composite, args.out_dir, cfg)
    print(f"finish {report.get('polygon_id')}: {args.out_dir} ({cfg.bits}-bit" + (", exr" if cfg.exr else "") + ")")
    return 0
