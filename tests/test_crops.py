"""The initialization's torch-free probe (difftex.sampling.crops): the probe mapping against the
optimization's texel_map, the any-texel pooling against torch's, and a process that crops photos
without importing torch."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from difftex.geometry.frames import UVFrame, uv_frame
from difftex.sampling.crops import any_pool, probe_map
from difftex.sampling.texels import texel_map

SHARED = Path(os.environ.get("DIFFTEX_SHARED", Path(__file__).resolve().parents[2] / "shared")) / "data"


def _scene(name: str):
    from difftex.scene.loading import load_scene

    if not (SHARED / name).is_dir():
        pytest.skip(f"{SHARED / name} missing")
    return load_scene(SHARED / name, check_images=False)


@pytest.mark.parametrize("name", ["herzjesu-p8", "lund-door"])
def test_probe_mapping_is_the_optimizations_texel_map(name):
    scene = _scene(name)
    pinhole = all(p.is_pinhole for p in scene.photos)
    checked = 0
    for poly in scene.proxy.polygons[:4]:
        frame = uv_frame(poly, scene.up, long_side=64)
        for photo in scene.photos[:6]:
            pix, fp, valid = probe_map(frame, photo)
            tm = texel_map(frame, photo, "cpu")
            ref_valid, ref_pix, ref_fp = tm.valid.numpy(), tm.pix.numpy(), tm.footprint.numpy()
            both = valid & ref_valid
            checked += int(both.sum())
            if pinhole:  # the same float64 operations: the same bits
                assert np.array_equal(valid, ref_valid)
                assert np.array_equal(pix[both], ref_pix[both]) and np.array_equal(fp[both], ref_fp[both])
            elif both.any():  # exact projection here, texel_map interpolates the distortion every few texels
                assert (valid != ref_valid).mean() < 0.01
                assert np.abs(pix[both] - ref_pix[both]).max() < 2.0
                assert np.abs(fp[both] / ref_fp[both] - 1).max() < 0.01
    assert checked > 1000


def _frame(h: int, w: int) -> UVFrame:
    return UVFrame(origin=np.zeros(3), e_u=np.array([1.0, 0, 0]), e_v=np.array([0, -1.0, 0]),
                   normal=np.array([0, 0, 1.0]), texel_size=1.0, width=w, height=h)


@pytest.mark.parametrize("src,dst", [((100, 37), (64, 24)), ((7, 5), (3, 2)), ((1, 9), (1, 4)), ((30, 3), (64, 6)),
                                     ((129, 65), (64, 32)), ((5, 5), (5, 5))])
def test_any_pool_is_torchs_adaptive_max_or_nearest(src, dst):
    masks = np.random.default_rng(0).random((3, *src)) < 0.05
    t = torch.from_numpy(masks.astype(np.float32))[:, None]
    small = dst[0] <= src[0] and dst[1] <= src[1]
    ref = (F.adaptive_max_pool2d(t, dst) if small else F.interpolate(t, size=dst, mode="nearest"))[:, 0].numpy() > 0
    assert np.array_equal(any_pool(masks, _frame(*src), _frame(*dst)), ref)


def test_the_initialization_imports_no_torch():
    code = (
        "import sys\n"
        "import difftex.cli.initialize, difftex.compose.stage_files, difftex.cli._polygon\n"
        "from difftex.compose.stage_files import initialize_polygon\n"
        "from difftex.method.config import OptimizeConfig\n"
        "OptimizeConfig(relief=True).relief_settings()\n"
        "assert not [m for m in sys.modules if m.split('.')[0] == 'torch'], 'torch imported'\n"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       env=dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[1])))
    assert r.returncode == 0, r.stderr
