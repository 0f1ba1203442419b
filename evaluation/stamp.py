"""Stamps on the headline results: the difftex version and a hash of the defaults that made them.

A headline result (``evaluation/results/<table>/*.md|json``, ``docs/results.md``) is only worth
quoting while the defaults that made it are still the defaults. ``evaluation/reproduce.py``
stamps every file it writes with :func:`current_stamp`; :func:`check_results` (run by
tests/test_results_stamp.py and ``python evaluation/stamp.py --check``) compares every stamp with
the hash of the current defaults and names each file a change of a default has made stale.

The hash covers the *effective* defaults: ``config/config.yaml``, each preset of
``config/presets/*.yaml`` merged over it, and the dataclass defaults the config files do not
spell out (``difftex.method.config.OptimizeConfig`` and the stage configs of ``difftex.config``).
It is a SHA-256 of their canonical JSON (sorted keys, no whitespace), so the order of keys in a
YAML file or a comment does not change it; a changed value, an added or removed key does.

This module lives beside the evaluation scripts, not in ``difftex.evaluation``: it reads the
method's config, which the package's evaluation layer may not import (tests/test_layers.py).
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from evaluation.common import _merge  # noqa: E402

RESULTS = ROOT / "evaluation" / "results"
SUMMARY = ROOT / "docs" / "results.md"
ARCHIVE = "archive"  # evaluation/results/archive/: old results, made by older defaults on purpose
HASH_LEN = 16  # hex digits: 64 bits, far more than enough to tell two sets of defaults apart
# the markdown form; one per table file, and one per section of docs/results.md
STAMP_RE = re.compile(r"^Stamp: difftex (?P<version>\S+), defaults (?P<hash>[0-9a-f]+)(?P<rest>.*)$", re.M)


def _dataclass_defaults(cls) -> dict:
    """Every field of a config dataclass at its default (nested sub-configs included)."""
    return dataclasses.asdict(cls())


def code_defaults() -> dict:
    """The defaults that live in code: what a key missing from the config files falls back to."""
    from difftex.config import FilterConfig, TextureConfig, VisibilityConfig
    from difftex.method.config import OptimizeConfig

    return {
        "optimize": _dataclass_defaults(OptimizeConfig),
        "texture": _dataclass_defaults(TextureConfig),
        "filter": _dataclass_defaults(FilterConfig),
        "visibility": _dataclass_defaults(VisibilityConfig),
    }


def effective_defaults(root: Path = ROOT, code: dict | None = None) -> dict:
    """config.yaml, each preset merged over it, and the code's defaults (``code``: these instead,
    for tests that show a changed default)."""
    import yaml

    from difftex.errors import DifftexError

    cfg_dir = Path(root) / "config"
    try:
        base = yaml.safe_load((cfg_dir / "config.yaml").read_text()) or {}
        presets = {p.stem: _merge(base, yaml.safe_load(p.read_text()) or {})
                   for p in sorted((cfg_dir / "presets").glob("*.yaml"))}
    except (OSError, yaml.YAMLError) as e:
        raise DifftexError(f"cannot read the defaults under {cfg_dir}: {e}") from None
    return {"default": base, "presets": presets, "code": code_defaults() if code is None else code}


def _canonical(obj) -> str:
    # sorted keys and fixed separators: the same values give the same text whatever their order;
    # anything JSON does not know (a Path, an enum) by its repr, which is stable for a value
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), ensure_ascii=True, default=repr)


def defaults_hash(defaults: dict | None = None) -> str:
    """The hash of ``defaults`` (default: :func:`effective_defaults` of this checkout)."""
    data = effective_defaults() if defaults is None else defaults
    return hashlib.sha256(_canonical(data).encode()).hexdigest()[:HASH_LEN]


def current_stamp(defaults: dict | None = None) -> dict:
    """{"difftex_version", "defaults_hash"} of this checkout (or of ``defaults``)."""
    import difftex

    return {"difftex_version": difftex.__version__, "defaults_hash": defaults_hash(defaults)}


def stamp_line(stamp: dict, rerun: str = "") -> str:
    """The markdown line of a stamp; ``rerun``: the command that re-makes the result."""
    tail = f"; re-made by `{rerun}`" if rerun else ""
    return f"Stamp: difftex {stamp['difftex_version']}, defaults {stamp['defaults_hash']}{tail}."


def stamp_markdown(text: str, stamp: dict, rerun: str = "") -> str:
    """``text`` with its stamp lines replaced by one at the end."""
    body = STAMP_RE.sub("", text).rstrip("\n")
    return f"{body}\n\n{stamp_line(stamp, rerun)}\n"


def stamp_file(path: Path, stamp: dict, rerun: str = "") -> None:
    """Stamp a result file in place: a line at the end of markdown, a ``stamp`` key in JSON."""
    from difftex.scene.files import read_json, write_json, write_text

    path = Path(path)
    if path.suffix == ".md":
        write_text(path, stamp_markdown(path.read_text(), stamp, rerun))
    elif path.suffix == ".json":
        data = read_json(path)
        data["stamp"] = dict(stamp, rerun=rerun) if rerun else dict(stamp)
        write_json(path, data)


def read_stamps(path: Path) -> list[dict]:
    """Every stamp in a result file: the markdown lines, or a JSON file's ``stamp`` key."""
    path = Path(path)
    if path.suffix == ".json":
        try:
            data = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError):
            return []
        s = data.get("stamp") if isinstance(data, dict) else None
        return [s] if isinstance(s, dict) and "defaults_hash" in s else []
    out = []
    for m in STAMP_RE.finditer(path.read_text()):
        rerun = re.search(r"`([^`]+)`", m["rest"])
        out.append({"difftex_version": m["version"], "defaults_hash": m["hash"],
                    "rerun": rerun[1] if rerun else ""})
    return out


def headline_files(results: Path = RESULTS, summary: Path | None = SUMMARY) -> list[Path]:
    """The stamped results: every .md/.json under the table folders of ``results`` (any depth,
    archive/ excepted; files directly in ``results`` are the pre-stamp runs), and ``summary``."""
    results = Path(results)
    files = []
    if results.is_dir():
        for d in sorted(p for p in results.iterdir() if p.is_dir() and p.name != ARCHIVE):
            files += sorted(f for f in d.rglob("*") if f.suffix in (".md", ".json") and f.is_file())
    if summary is not None and Path(summary).is_file():
        files.append(Path(summary))
    return files


def check_results(results: Path = RESULTS, summary: Path | None = SUMMARY,
                  expected: str | None = None) -> list[str]:
    """One line per headline file whose stamp is missing or is not ``expected`` (default: the
    hash of the current defaults); empty when every result was made by the current defaults."""
    expected = expected or defaults_hash()
    problems = []
    for f in headline_files(results, summary):
        stamps = read_stamps(f)
        if not stamps:
            problems.append(f"{f}: no stamp (results here are made by evaluation/reproduce.py, which stamps them)")
            continue
        for s in stamps:
            if s["defaults_hash"] != expected:
                how = s.get("rerun") or "python evaluation/reproduce.py"
                problems.append(f"{f}: stale, made with defaults {s['defaults_hash']}, now {expected}; re-run `{how}`")
    return problems


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--check", action="store_true", help="check every headline result's stamp against the defaults")
    args = ap.parse_args(argv)
    print(stamp_line(current_stamp()))
    if not args.check:
        return 0
    problems = check_results()
    for p in problems:
        print(p)
    print(f"{len(headline_files())} stamped files checked, {len(problems)} stale or unstamped")
    return 1 if problems else 0


if __name__ == "__main__":
    from evaluation.common import run_script

    run_script(main)
