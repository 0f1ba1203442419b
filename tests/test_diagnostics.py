"""The optimizer's diagnostics (difftex.method.diagnostics) on tensors with known answers."""

from __future__ import annotations

import numpy as np
import pytest
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


def slots_two_photos(h: int = 20, w: int = 30) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Photo 3 in slot 0 on the left half, slot 1 on the right half (photo 7 the other slot):
    a photo moves between slots, as after ranking."""
    idx = torch.full((2, h, w), 7)
    idx[0, :, : w // 2] = 3
    idx[1, :, w // 2 :] = 3
    visible = torch.ones((2, h, w), dtype=torch.bool)
    visible[:, :5] = idx[:, :5] != 7  # photo 7 does not see the top five rows
    return idx, visible, torch.ones((h, w), dtype=torch.bool)


def test_photo_coverage_counts_a_photo_once_per_texel_whatever_its_slot():
    idx, visible, mask = slots_two_photos()
    W = torch.where(idx == 3, 0.75, 0.25)
    W[:, :5] = torch.where(idx[:, :5] == 3, 1.0, 0.0)
    cov = diagnostics.photo_coverage(idx, visible, W, mask)
    assert cov[3][0] == 20 * 30 and cov[7][0] == 15 * 30
    assert abs(cov[3][1] - (5 * 30 * 1.0 + 15 * 30 * 0.75)) < 1e-6
    assert abs(cov[7][1] - 15 * 30 * 0.25) < 1e-6
    mask[:, 10:] = False  # only the left third counts
    assert diagnostics.photo_coverage(idx, visible, None, mask)[3] == (20 * 10, 0.0)
    assert diagnostics.photo_coverage(idx, torch.zeros_like(visible), W, mask) == {}


def test_photo_colours_gathers_a_photo_from_whichever_slot_holds_it():
    idx, visible, _ = slots_two_photos()
    colours = torch.stack([torch.full((3, 20, 30), 0.1), torch.full((3, 20, 30), 0.9)])
    colours[idx[:, None].expand(-1, 3, -1, -1) == 3] = 0.5  # photo 3's colour in either slot
    col, seen = diagnostics.photo_colours(colours, idx, visible, 3)
    assert bool(seen.all()) and torch.allclose(col, torch.full_like(col, 0.5))
    col7, seen7 = diagnostics.photo_colours(colours, idx, visible, 7)
    assert not bool(seen7[:5].any()) and bool(seen7[5:].all())
    assert float(col7[:, :5].abs().max()) == 0.0  # unseen texels are zero, not another photo's colour
    assert torch.allclose(col7[:, 5:], torch.where(idx[0, 5:] == 7, 0.1, 0.9).expand(3, -1, -1))


def test_sharpness_names_the_sharpest_photo_and_compares_the_texture_on_its_texels():
    h, w = 32, 32
    stripes = (torch.arange(w) % 2).float().expand(3, h, w)  # gradient 1 along x
    idx = torch.stack([torch.full((h, w), 4), torch.full((h, w), 6)])
    visible = torch.ones((2, h, w), dtype=torch.bool)
    colours = torch.stack([0.5 * stripes, 0.1 * stripes])  # photo 4 sharper than photo 6
    U = 0.25 * stripes
    out = diagnostics.sharpness(U, colours, idx, visible, torch.ones((h, w), dtype=torch.bool))
    assert out["photo"] == 4
    assert abs(out["ratio"] - 0.5) < 1e-6  # the texture has half photo 4's contrast


def test_misalignment_measures_only_the_photos_that_carry_the_most_weight():
    h, w = 64, 64
    U = smooth_pattern(h, w)
    K = 4
    colours = U[None].expand(K, -1, -1, -1).clone()
    idx = torch.stack([torch.full((h, w), n) for n in (10, 11, 12, 13)])
    visible = torch.ones((K, h, w), dtype=torch.bool)
    W = torch.tensor([0.4, 0.3, 0.2, 0.1])[:, None, None].expand(K, h, w)
    out = diagnostics.misalignment(U, colours, idx, visible, W, torch.ones((h, w), dtype=torch.bool), max_photos=2)
    assert set(k for k in out if k != "median_abs") == {10, 11}


@pytest.mark.parametrize(("shape", "shift"), [((64, 96), (3.3, -7.6)), ((37, 51), (-12.0, 0.45)), ((1, 40), (0.0, 5.2)),
                                              ((48, 48), (0.0, 0.0)), ((50, 30), (24.0, -14.9))])
def test_phase_shift_is_scikit_images_phase_correlation(shape, shift):
    """phase_shift (written out: scikit-image's import cost more than the measurement) gives
    scikit-image's result, on odd sizes, one row, no shift and shifts near half the image."""
    from scipy.ndimage import fourier_shift
    from skimage.registration import phase_cross_correlation

    rng = np.random.default_rng(3)
    ref = rng.random(shape)
    mov = np.fft.ifftn(fourier_shift(np.fft.fftn(ref), shift)).real
    got = diagnostics.phase_shift(ref, mov, upsample=10)
    want = phase_cross_correlation(ref, mov, upsample_factor=10, normalization=None)[0]
    assert np.allclose(got, want, atol=1e-9), (got, want)
    if shape[0] > 1:
        assert np.allclose(got, -np.asarray(shift), atol=0.06)  # registers moving back onto reference
    with pytest.raises(ValueError):
        diagnostics.phase_shift(ref, mov[:, :-1] if shape[1] > 1 else mov[:-1])
