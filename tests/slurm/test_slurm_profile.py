"""Fast checks of the cluster side that need no SLURM: both profiles parse with every key known
to Snakemake 9 and the SLURM plugin (a dry run), and the SLURM-vs-local output comparison of
tests/slurm/run_slurm_e2e.sh --real catches differences, to a tolerance or (--tolerance 0, the
--block run) byte for byte. The SLURM run itself is tests/slurm/run_slurm_e2e.sh (root, Debian;
about 80 s; --block, the 100-polygon block through SLURM and locally, about 5 min on 2 cores)."""

import importlib.util
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from difftex.scene.files import write_image, write_npz

REPO = Path(__file__).resolve().parents[2]
HERE = Path(__file__).resolve().parent


def _compare_module():
    spec = importlib.util.spec_from_file_location("compare_outputs", HERE / "compare_outputs.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.mark.parametrize("profile", ["local", "slurm"])
def test_profile_dry_run(profile, tmp_path):
    """An unknown or misspelt key in a profile makes snakemake exit with an error."""
    snakemake = shutil.which("snakemake") or str(Path(sys.executable).parent / "snakemake")
    if not Path(snakemake).exists():
        pytest.skip("snakemake not installed")
    proc = subprocess.run(
        [snakemake, "--profile", str(REPO / "workflow" / "profiles" / profile),
         "-s", str(HERE / "Snakefile"), "-n", "--quiet", "rules"],
        cwd=tmp_path, capture_output=True, text=True, timeout=120,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    # the dry run plans the fan-out: two per-polygon jobs and the gather job
    assert "per_polygon" in proc.stdout and "gather" in proc.stdout, proc.stdout


def _tree(root: Path, texture: np.ndarray, weights: np.ndarray) -> Path:
    write_image(root / "results/s/textures/p0/texture.png", texture)
    write_npz(root / "results/s/optimized/p0/weights.npz", W=weights)
    return root


def test_compare_identical_and_different(tmp_path):
    cmp = _compare_module()
    rng = np.random.default_rng(0)
    tex = rng.random((8, 6, 3), dtype=np.float32)
    w = rng.random((2, 8, 6)).astype(np.float16)
    a = _tree(tmp_path / "a", tex, w)
    b = _tree(tmp_path / "b", tex, w)
    assert cmp.main([str(a), str(b)]) == 0

    c = _tree(tmp_path / "c", np.clip(tex + 0.2, 0, 1), w)  # far beyond the 0.02 tolerance
    assert cmp.main([str(a), str(c)]) == 1
    assert cmp.main([str(a), str(c), "--tolerance", "0.5"]) == 0


def test_compare_missing_texture_and_shape(tmp_path):
    cmp = _compare_module()
    tex = np.zeros((4, 4, 3), np.float32)
    w = np.zeros((2, 4, 4), np.float16)
    a = _tree(tmp_path / "a", tex, w)
    b = _tree(tmp_path / "b", tex, np.zeros((2, 4, 5), np.float16))  # weights of another shape
    assert cmp.main([str(a), str(b)]) == 1
    (tmp_path / "empty").mkdir()
    assert cmp.main([str(a), str(tmp_path / "empty")]) == 1  # the local run wrote no texture
    assert cmp.main([str(tmp_path / "empty"), str(a)]) == 1  # the SLURM run wrote no texture


def test_compare_partial_run(tmp_path):
    """Runs stopped before the textures (a --target) compare their arrays; empty trees fail."""
    cmp = _compare_module()
    for name in "ab":
        write_npz(tmp_path / name / "results/s/visibility/p0.npz", m=np.ones((3, 3), np.uint8))
    a, b = tmp_path / "a", tmp_path / "b"
    assert cmp.main([str(a), str(b)]) == 1  # no textures: a full run must have them
    assert cmp.main([str(a), str(b), "--partial"]) == 0
    write_npz(b / "results/s/visibility/p0.npz", m=np.ones((3, 4), np.uint8))
    assert cmp.main([str(a), str(b), "--partial"]) == 1
    (tmp_path / "e1").mkdir()
    (tmp_path / "e2").mkdir()
    assert cmp.main([str(tmp_path / "e1"), str(tmp_path / "e2"), "--partial"]) == 1


def test_compare_exact(tmp_path):
    """--tolerance 0 (the --block run's mode): texture PNGs byte for byte, NPZ arrays equal."""
    cmp = _compare_module()
    rng = np.random.default_rng(1)
    tex = rng.random((8, 6, 3), dtype=np.float32)
    w = rng.random((2, 8, 6)).astype(np.float16)
    a = _tree(tmp_path / "a", tex, w)
    b = _tree(tmp_path / "b", tex, w)
    assert cmp.main([str(a), str(b), "--tolerance", "0"]) == 0
    assert cmp.main([str(a), str(b), "--exact"]) == 0

    # one texel one 8-bit step off: within the default tolerance, not identical
    tex2 = tex.copy()
    tex2[0, 0, 0] = (np.round(tex[0, 0, 0] * 255) + (1 if tex[0, 0, 0] < 0.5 else -1)) / 255
    c = _tree(tmp_path / "c", tex2, w)
    assert cmp.main([str(a), str(c)]) == 0
    assert cmp.main([str(a), str(c), "--tolerance", "0"]) == 1

    # same texture, weights one float16 step apart: only the exact mode fails
    w2 = w.copy()
    w2[0, 0, 0] = np.nextafter(w[0, 0, 0], np.float16(2))
    d = _tree(tmp_path / "d", tex, w2)
    assert cmp.main([str(a), str(d)]) == 0
    assert cmp.main([str(a), str(d), "--tolerance", "0"]) == 1


def test_compare_exact_ignores_npz_text(tmp_path):
    """A composite's JSON report (timings) differs between runs; its numeric arrays must not."""
    cmp = _compare_module()
    tex = np.full((4, 4, 3), 0.5, np.float32)
    for name, report in (("a", '{"time_s": 0.1}'), ("b", '{"time_s": 0.25}')):
        write_image(tmp_path / name / "results/s/textures/p0/texture.png", tex)
        write_npz(tmp_path / name / "results/s/optimized/p0/composite.npz",
                  rgb=np.ones((4, 4, 3), np.float32), report=np.array(report))
    assert cmp.main([str(tmp_path / "a"), str(tmp_path / "b"), "--tolerance", "0"]) == 0
