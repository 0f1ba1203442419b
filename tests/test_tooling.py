"""The linters run as part of the tests, because CI runs exactly the README's pytest command:
ruff on the whole repository and mypy on the layers it is configured for (pyproject.toml,
[tool.ruff] and [tool.mypy]). Both come with the ``test`` extra (scripts/install.sh installs it)."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def _tool(name: str) -> list[str]:
    exe = Path(sys.executable).with_name(name)
    if exe.is_file():
        return [str(exe)]
    found = shutil.which(name)
    if found is None:
        pytest.skip(f"{name} is not installed (pip install -e '.[test]' installs it)")
    return [found]


def _run(cmd: list[str]) -> None:
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    p = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, env=env)
    assert p.returncode == 0, f"{' '.join(cmd)} failed:\n{p.stdout}\n{p.stderr}"


def test_ruff_is_clean():
    _run([*_tool("ruff"), "check", "--no-cache", "."])


def test_mypy_is_clean():
    _run([*_tool("mypy"), "--no-incremental", "--cache-dir", os.devnull])
