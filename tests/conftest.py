"""Fixtures shared by several test modules."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

# No test uses the network: classic LPIPS's weight files are never downloaded into the torch hub
# cache (difftex.evaluation.perceptual; the Snakemake runs of the tests inherit it), so "auto"
# reports ST-LPIPS wherever the hub cache lacks them. tests/test_lpips_download.py unsets it and
# replaces the download.
os.environ["DIFFTEX_OFFLINE"] = "1"


@pytest.fixture(scope="session")
def small_synth_scene(tmp_path_factory) -> Path:
    """A reduced copy of the tiny synthetic scene: the same building (6 polygons, COLMAP text
    model with points, PINHOLE cameras), 10 photos of 160x120, no previews; about 5 s to make.
    Its model is in the classic layout of the shared scenes and of most COLMAP exports (poses
    in images.txt): the synthetic one's rigs.txt/frames.txt (one camera per rig, the same
    poses) are dropped. Tests copy it before changing it."""
    from difftex.synth import generate

    out = tmp_path_factory.mktemp("small_synth") / "small"
    generate("tiny", out, progress=False, views=10, held_out_views=1, width=160, height=120,
             spp=4, gt_spp=4, gt_long_side=64, previews=False)
    for name in ("rigs.txt", "frames.txt"):
        (out / "sparse" / "0" / name).unlink(missing_ok=True)
    return out
