"""The combined markdown of evaluation/reproduce.py: every table of a results folder in one page.

The page is rebuilt from the files the folder holds (not from one run's memory), so a run of one
table (``--only``) keeps the other tables' sections, each with the stamp it was made with: the
stamp check (evaluation/stamp.py) then reads every section's own stamp.
"""

from __future__ import annotations

import json
import os
import re
from pathlib import Path

# the tables in the order of the page; reproduce.py's --only takes these names
TITLES = {
    "table1": "Table 1: synthetic survey buildings against ground truth",
    "table2": "Table 2: real scenes, held-out photos",
    "relief": "Relief: the height field from the dense cloud and from the photos against the true one",
    "ablation": "Ablation: each loss term and data-quality step off in turn",
    "tradeoff": "Speed/quality trade-off: several resolutions per preset",
    "speed": "Speed: the workflow per preset against texrecon",
    "scale": "Scale: the workflow on generated districts",
}
LINK_RE = re.compile(r"(\]\()([^)\s]+)(\))")


def _relink(text: str, src_dir: Path, dst_dir: Path) -> str:
    """Relative links of a table file, made relative to the page's folder instead."""

    def fix(m: re.Match) -> str:
        target = m[2]
        if re.match(r"^[a-z]+:|^/|^#", target):
            return m[0]
        return m[1] + os.path.relpath(src_dir / target, dst_dir).replace(os.sep, "/") + m[3]

    return LINK_RE.sub(fix, text)


def _section(text: str, levels: int = 2) -> str:
    """A table file as a subsection of the page: headings ``levels`` down, and without its date
    line (the stamp says whether a table is current; its file keeps the date, so the page adds
    no dated line to docs/)."""
    lines = [("#" * levels + ln) if ln.startswith("#") else ln
             for ln in text.splitlines() if not ln.startswith("Date: ")]
    return "\n".join(lines)


def _stamp_of(md: Path) -> dict:
    """The JSON twin's stamp (wall time and date of the run that made the table), if any."""
    try:
        data = json.loads(md.with_suffix(".json").read_text())
    except (OSError, json.JSONDecodeError):
        return {}
    return (data.get("stamp") or {}) if isinstance(data, dict) else {}


def _index(out: Path, page_dir: Path) -> list[str]:
    lines = ["| Table | File | Wall (s) | Defaults |", "|---|---|---|---|"]
    for table, title in TITLES.items():
        for md in sorted((out / table).glob("*.md")):
            s = _stamp_of(md)
            rel = os.path.relpath(md, page_dir).replace(os.sep, "/")
            lines.append(f"| {title.split(':')[0]} | [{md.stem}]({rel}) | {s.get('wall_s', 'n/a')} | "
                         f"{s.get('defaults_hash', 'unstamped')} |")
    return lines


def write_summary(path: Path, out: Path, smoke: bool, records: list[dict]) -> str:
    """Write the page ``path`` from the tables under ``out``; ``records``: this run's jobs, whose
    failures the page names. Returns the markdown."""
    from difftex.scene.files import write_text

    path, out = Path(path), Path(out)
    page_dir = path.parent
    kind = "a tiny version of every table, to check the pipeline, not to quote" if smoke else "the full run"
    lines = [
        "# Results" + (" (smoke)" if smoke else ""),
        "",
        f"The headline tables as `python evaluation/reproduce.py{' --smoke' if smoke else ''}` made them ({kind}), "
        f"from `{out}/<table>/`. Each table ends with a stamp: the difftex version and a hash of the defaults that "
        "made it (`config/config.yaml`, the presets, the code's config defaults; evaluation/stamp.py). "
        "`tests/test_results_stamp.py` fails when a default changes and a table is not re-made; "
        "`python evaluation/stamp.py --check` lists the stale ones with the command that re-makes each. "
        "Wall: the seconds the table's command took; its date and machine are in its own file.",
        "",
        *_index(out, page_dir),
        "",
    ]
    failed = [r for r in records if r.get("rc") != 0]
    if failed:
        lines += ["Not made by the last run (the section below, if any, is an earlier run's):", ""]
        lines += [f"- {r['table']}/{r['name']}: {r.get('error') or 'exit ' + str(r.get('rc'))}" for r in failed]
        lines.append("")
    for table, title in TITLES.items():
        files = sorted((out / table).glob("*.md"))
        if not files:
            continue
        lines += [f"## {title}", ""]
        for md in files:
            lines += [_section(_relink(md.read_text(), md.parent, page_dir)).rstrip(), ""]
    text = "\n".join(lines).rstrip() + "\n"
    write_text(path, text)
    return text
