"""The headline results cannot go stale: each carries the hash of the defaults that made it
(evaluation/stamp.py), and this test fails when a default changes and they are not re-made.

The last test is the real check over the repository's stamped results (evaluation/results/<table>/
and docs/results.md); the others show, on temporary folders, that the hash is stable, that it
follows every kind of default, and that the checker calls a result stale once a default changes
without a re-run. Fix a failure of the real check by re-running the command it prints
(``python evaluation/reproduce.py [--smoke] --only <table>``), not by editing a stamp.
"""

from __future__ import annotations

import copy
import json
import shutil
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from evaluation import stamp as S  # noqa: E402
from evaluation.reproduce_summary import write_summary  # noqa: E402


def _write_table(results: Path, table: str, name: str, stamp: dict, rerun: str = "") -> list[Path]:
    """A results pair as a table script writes it, stamped as evaluation/reproduce.py does."""
    d = results / table
    d.mkdir(parents=True, exist_ok=True)
    (d / f"{name}.md").write_text(f"# {table}\n\n| Method | SSIM |\n|---|---|\n| difftex | 0.9 |\n")
    (d / f"{name}.json").write_text(json.dumps({"rows": [{"method": "difftex", "ssim": 0.9}]}))
    for f in (d / f"{name}.md", d / f"{name}.json"):
        S.stamp_file(f, stamp, rerun)
    return [d / f"{name}.md", d / f"{name}.json"]


@pytest.fixture(scope="module")
def defaults() -> dict:
    return S.effective_defaults()


def test_hash_is_stable_and_ignores_key_order(defaults):
    h = S.defaults_hash(defaults)
    assert h == S.defaults_hash() == S.defaults_hash(copy.deepcopy(defaults))
    assert len(h) == S.HASH_LEN and int(h, 16) >= 0
    reordered = {k: defaults[k] for k in reversed(list(defaults))}
    reordered["default"] = dict(reversed(list(defaults["default"].items())))
    assert S.defaults_hash(reordered) == h


def test_the_hash_covers_config_presets_and_code_defaults(defaults):
    assert "optimize" in defaults["default"] and defaults["presets"].keys() >= {"fast", "balanced", "paper"}
    assert "lr" in json.dumps(defaults["code"]["optimize"])  # OptimizeConfig's fields, at their defaults
    h = S.defaults_hash(defaults)
    for edit in (
        lambda d: d["default"]["optimize"].__setitem__("top_k", d["default"]["optimize"]["top_k"] + 1),
        lambda d: d["presets"]["fast"]["texture"].__setitem__("density_scale", 0.3),
        lambda d: d["code"]["optimize"].__setitem__("a_new_option", True),
        lambda d: d["code"]["texture"].__setitem__("max_mb", 1),
    ):
        changed = copy.deepcopy(defaults)
        edit(changed)
        assert S.defaults_hash(changed) != h


def test_stamps_round_trip_in_markdown_and_json(tmp_path):
    stamp = S.current_stamp()
    md, js = _write_table(tmp_path, "table1", "x", stamp, "python evaluation/reproduce.py --only table1")
    S.stamp_file(md, stamp, "python evaluation/reproduce.py --only table1")  # again: still one stamp
    (got,) = S.read_stamps(md)
    assert got["defaults_hash"] == stamp["defaults_hash"] and got["rerun"].endswith("--only table1")
    assert S.read_stamps(js)[0]["defaults_hash"] == stamp["defaults_hash"]
    assert S.check_results(tmp_path, None) == []


def test_changing_a_default_without_a_rerun_makes_the_check_fail(tmp_path, defaults):
    """A result made with today's defaults; then a default changes (here: optimize.lr of the
    config file and a dataclass default) and nothing is re-run: every stamped file is stale."""
    results = tmp_path / "results"
    files = _write_table(results, "table1", "survey_gable", S.current_stamp(defaults), "python r.py --only table1")
    write_summary(tmp_path / "results.md", results, smoke=False, records=[])
    assert S.check_results(results, tmp_path / "results.md", S.defaults_hash(defaults)) == []

    changed = copy.deepcopy(defaults)
    changed["default"]["optimize"]["lr"] = 2 * defaults["default"]["optimize"]["lr"]
    problems = S.check_results(results, tmp_path / "results.md", S.defaults_hash(changed))
    assert len(problems) == 3 and all("stale" in p for p in problems)
    assert {Path(p.split(":")[0]).name for p in problems} == {f.name for f in files} | {"results.md"}
    assert "python r.py --only table1" in problems[0]


def test_a_changed_config_file_is_seen(tmp_path):
    """The hash is read from the config files themselves: editing a preset's value changes it."""
    shutil.copytree(REPO / "config", tmp_path / "config")
    code = S.code_defaults()
    before = S.defaults_hash(S.effective_defaults(tmp_path, code))
    fast = tmp_path / "config" / "presets" / "fast.yaml"
    fast.write_text(fast.read_text() + "\nfilter:\n  blur_ratio: 0.31\n")
    assert S.defaults_hash(S.effective_defaults(tmp_path, code)) != before


def test_unstamped_results_are_reported(tmp_path):
    (tmp_path / "speed").mkdir()
    (tmp_path / "speed" / "hand_made.md").write_text("# Speed\n")
    (tmp_path / "archive").mkdir()
    (tmp_path / "archive" / "old.md").write_text("# old, unstamped on purpose\n")
    (tmp_path / "flat_old_table.md").write_text("# a pre-stamp result directly in the folder\n")
    (problem,) = S.check_results(tmp_path, None)
    assert "hand_made.md" in problem and "no stamp" in problem


def test_headline_results_match_the_current_defaults():
    """The real check: every stamped headline result of the repository was made by the defaults
    of this checkout."""
    problems = S.check_results()
    assert not problems, "results made by other defaults than the current ones:\n" + "\n".join(problems)
