"""The optimizer's diagnostics (difftex.method.diagnostics) on tensors with known answers."""

from __future__ import annotations

import numpy as np
import torch

from difftex.method import diagnostics

torch.set_num_threads(1)


def smooth_pattern(h: int, w: int, seed: int = 0) -> torch.Tensor:
    """(3, h, w) a band-limited random texture: phase correlation needs structure at all scales."""
    rng = np.random.default_rng(seed)
    f = np.fft.fft2(rng.normal(size=(h, w)))
    fy, fx = np.fft.fftfreq(h)[:, None], np.fft.fftfreq(w)[None]
    g = np.real(np.fft.ifft2(f * np.exp(-((fy**2 + fx**2) / 0.02**2))))
    g = (g - g.min()) / (g.max() - g.min())
    return torch.from_numpy(np.stack([g, 0.5 * g + 0.25, 1 - g]).astype(np.float32))


def test_misalignment_measures_a_known_shift_on_a_subsampled_level():
    h, w, dy, dx = 600, 700, 4, -6  # 700 texels: measured at step 2, reported in level texels
    U = smooth_pattern(h, w)
    shifted = torch.roll(U, shifts=(dy, dx), dims=(1, 2))
    colours = torch.stack([shifted, U])  # slot 0: photo 5, misregistered; slot 1: photo 9
    idx = torch.stack([torch.full((h, w), 5), torch.full((h, w), 9)])
    visible = torch.ones((2, h, w), dtype=torch.bool)
    W = torch.full((2, h, w), 0.5)
    mask = torch.ones((h, w), dtype=torch.bool)
    out = diagnostics.misalignment(U, colours, idx, visible, W, mask)
    # the photo's content moved by (+dy, +dx): it must move back by (-dy, -dx) onto the texture
    assert np.allclose(np.abs(out[5]), [abs(dy), abs(dx)], atol=0.5)
    assert np.hypot(*out[9]) < 0.3
    assert 0.0 <= out["median_abs"] <= np.hypot(dy, dx) + 0.5


def test_mean_gradient_counts_pairs_inside_the_mask_only():
    img = torch.zeros((3, 4, 4))
    img[:, :, 2:] = 1.0  # a vertical edge between columns 1 and 2
    left = torch.zeros((4, 4), dtype=torch.bool)
    left[:, :2] = True
    assert diagnostics.mean_gradient(img, left) == 0.0  # the edge's pairs leave the mask
    full = torch.ones((4, 4), dtype=torch.bool)
    assert abs(diagnostics.mean_gradient(img, full) - 4 / 24) < 1e-6  # 4 of 24 pairs cross it
