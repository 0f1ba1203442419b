"""Hole filling in numpy (difftex.compose.fill): its pooling and bilinear resampling against the
torch operators they stand in for, at odd and degenerate sizes, and the fill's extremes."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from difftex.compose.fill import (
    bilinear_at,
    dominant_from_slots,
    fill_holes,
    finish_texture,
    pool2_ceil,
    resize_bilinear,
)

SIZES = [(1, 1), (1, 7), (2, 3), (5, 9), (9, 5), (33, 17), (130, 257)]


def _torch_hwc(fn, x: np.ndarray, **kw) -> np.ndarray:
    return fn(torch.from_numpy(x).permute(2, 0, 1)[None], **kw)[0].permute(1, 2, 0).numpy()


@pytest.mark.parametrize("shape", SIZES)
def test_pooling_is_torchs_ceil_mode_average(shape):
    x = np.random.default_rng(1).random((*shape, 3)).astype(np.float32)
    ref = _torch_hwc(F.avg_pool2d, x, kernel_size=2, ceil_mode=True)
    assert pool2_ceil(x).shape == ref.shape
    np.testing.assert_allclose(pool2_ceil(x), ref, atol=1e-6)


@pytest.mark.parametrize("shape", SIZES)
@pytest.mark.parametrize("factor", [(2, 2), (3, 1), (1, 4)])
def test_resampling_is_torchs_half_pixel_bilinear(shape, factor):
    x = np.random.default_rng(2).random((*shape, 3)).astype(np.float32)
    out = (shape[0] * factor[0] + 1, shape[1] * factor[1])
    ref = _torch_hwc(F.interpolate, x, size=out, mode="bilinear", align_corners=False)
    got = resize_bilinear(x, out)
    # torch computes the source coordinate in float32: 1e-4 is far below an 8-bit step
    np.testing.assert_allclose(got, ref, atol=1e-4)
    ys, xs = np.nonzero(np.random.default_rng(3).random(out) < 0.3)
    np.testing.assert_allclose(bilinear_at(x, out, ys, xs), got[ys, xs], atol=1e-6)


def test_fill_extremes():
    rng = np.random.default_rng(4)
    img = rng.random((17, 23, 3)).astype(np.float32)
    # nothing known or everything known: returned unchanged
    assert np.array_equal(fill_holes(img, np.zeros((17, 23), bool)), img)
    assert np.array_equal(fill_holes(img, np.ones((17, 23), bool)), img)
    # one known texel: every texel takes its colour
    known = np.zeros((17, 23), bool)
    known[16, 0] = True
    out = fill_holes(img, known)
    np.testing.assert_allclose(out, np.broadcast_to(img[16, 0], out.shape), atol=1e-6)
    # a 1-texel-wide strip and a 1x1 texture
    strip = rng.random((1, 9, 3)).astype(np.float32)
    k = np.array([[True] + [False] * 7 + [True]])
    filled = fill_holes(strip, k)
    assert np.isfinite(filled).all() and np.array_equal(filled[k], strip[k])
    assert (filled[0, 1:8].min() >= strip[k].min() - 1e-6) and (filled[0, 1:8].max() <= strip[k].max() + 1e-6)


def test_finish_texture_reports_what_it_filled_and_dominant_marks_unweighted_texels():
    U = np.ones((4, 5, 3), np.float32) * 0.5
    wsum = np.ones((4, 5), np.float32)
    wsum[0, :2] = 0
    mask = np.ones((4, 5), bool)
    mask[3, 4] = False
    out, info = finish_texture(U * (wsum > 0)[..., None], wsum, mask)
    assert info["filled_texels"] == 2 and info["seen_texels"] == 17 and info["coverage"] == pytest.approx(17 / 19)
    np.testing.assert_allclose(out, 0.5, atol=1e-6)
    idx = np.array([[[3, 1]], [[2, 0]]])  # (K=2, 1, 2)
    W = np.array([[[0.2, 0.0]], [[0.7, 0.0]]])
    assert dominant_from_slots(idx, W).tolist() == [[2, -1]]
