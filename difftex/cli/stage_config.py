"""difftex stage-config: write one stage's config file (the workflow's stage_config rule)."""

from __future__ import annotations

NAME = "stage-config"
HELP = "write TEXT atomically to OUT (the workflow's per-stage config files)"


def add_arguments(p) -> None:
    p.add_argument("--out", required=True, help="the file to write (R/config/<stage>-<digest>.yaml)")
    p.add_argument("--text", required=True, help="its content")


def run(args) -> int:
    from difftex.scene.files import write_text

    write_text(args.out, args.text)
    return 0
