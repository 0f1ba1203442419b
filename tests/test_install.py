"""What the installs install: scripts/install.sh (constraints.txt), the package's extras
(pyproject.toml) and the conda environment of `snakemake --use-conda` (workflow/envs/difftex.yaml)
must give the same torch, torchvision and piq, and none of them the lpips package."""

from __future__ import annotations

import re
import tomllib
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parents[1]


def pins(lines) -> dict[str, str]:
    """{name: version} of the `name==version` lines (comments, options and others left out)."""
    out = {}
    for ln in lines:
        m = re.fullmatch(r"\s*([A-Za-z0-9_.-]+)\s*==\s*([^\s#;]+)\s*(#.*)?", ln)
        if m:
            out[m.group(1).lower().replace("_", "-")] = m.group(2)
    return out


def conda_pip_lines() -> list[str]:
    env = yaml.safe_load((REPO / "workflow/envs/difftex.yaml").read_text())
    pip = [d["pip"] for d in env["dependencies"] if isinstance(d, dict) and "pip" in d]
    assert len(pip) == 1, env["dependencies"]
    return [str(x) for x in pip[0]]


def test_conda_env_pins_what_constraints_pins():
    constraints = pins((REPO / "constraints.txt").read_text().splitlines())
    conda = pins(conda_pip_lines())
    for pkg in ("torch", "torchvision", "piq"):
        assert pkg in constraints, constraints
        assert conda.get(pkg) == constraints[pkg], (pkg, conda.get(pkg), constraints[pkg])
    # the same registry: no other index (the CPU-only index gave another torch than the .venv's)
    assert not [ln for ln in conda_pip_lines() if "index-url" in ln or "find-links" in ln], conda_pip_lines()


def test_conda_env_installs_the_checkout_with_the_install_scripts_extras():
    editable = [ln for ln in conda_pip_lines() if ln.startswith("-e ")]
    assert editable == ["-e ../..[perceptual]"], editable
    assert '-e ".[test,perceptual]"' in (REPO / "scripts/install.sh").read_text()


def test_no_install_brings_the_lpips_package():
    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    reqs = list(project["dependencies"]) + [r for extra in project["optional-dependencies"].values() for r in extra]
    names = [re.match(r"[A-Za-z0-9_.-]+", r).group(0).lower() for r in reqs]
    assert "lpips" not in names and "stlpips-pytorch" in names, names
    assert not [ln for ln in conda_pip_lines() if re.match(r"lpips\b", ln)]
    script = [ln for ln in (REPO / "scripts/install.sh").read_text().splitlines() if not ln.lstrip().startswith("#")]
    assert not [ln for ln in script if re.search(r"(?<![-\w])lpips\b", ln)], script
