"""difftex report: static HTML report of a results folder (tables, maps, loss curves, timings)."""

from __future__ import annotations

NAME = "report"
HELP = "write a static HTML report of a results folder (opens from disk, no network)"


def add_arguments(p) -> None:
    p.add_argument("--results", required=True, help="results folder (textures/, optional optimized/, evaluation/)")
    p.add_argument("--scene", help="scene folder, to show the ground-truth maps of synthetic scenes")
    p.add_argument("--out", help="HTML file (default: RESULTS/report/index.html)")


def run(args) -> int:
    from difftex.evaluation.report import write_report

    out = write_report(args.results, args.out, args.scene)
    print(f"report: {out}")
    return 0
