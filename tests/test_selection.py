"""Selection of one photo per patch from the optimized weights (difftex.method.selection)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from difftex.method.selection import UNSEEN_COST, detail_band, select_weights, solve_potts, texel_costs


def _slots(h=16, w=32):
    # three photos in three slots at every texel, equal weights
    idx = torch.stack([torch.full((h, w), n) for n in range(3)])
    W = torch.full((3, h, w), 1.0 / 3)
    Q = torch.ones(3, h, w)
    return idx, W, Q


def test_costs_are_zero_for_the_best_score_and_high_where_a_photo_holds_no_weight():
    idx, W, Q = _slots(4, 4)
    Q[1] = 2.0
    W[2, 0, 0] = 0.0
    c = texel_costs(W, Q, idx, 4)
    assert torch.allclose(c[1], torch.zeros(4, 4))
    assert torch.allclose(c[0, 1:, 1:], torch.full((3, 3), 0.5))
    assert c[2, 0, 0] == UNSEEN_COST and (c[3] == UNSEEN_COST).all()  # photo 3 is in no slot
    with pytest.raises(ValueError):
        texel_costs(W, Q[:2], idx, 4)


def test_each_half_takes_its_best_photo_with_one_short_cross_fade():
    h, w = 16, 32
    idx, W, Q = _slots(h, w)
    Q[0, :, : w // 2] = 1.5  # photo 0 best on the left
    Q[1, :, w // 2 :] = 1.5  # photo 1 on the right
    W[2] = 0.0  # photo 2 occluded everywhere: never selected
    W = W / W.sum(0, keepdim=True)
    mask = torch.ones(h, w, dtype=torch.bool)
    out, st = select_weights(W, Q, idx, mask, 3, patch=4, smoothness=1.0, feather=1.0)
    assert torch.allclose(out.sum(0), torch.ones(h, w), atol=1e-5)
    assert (out[2] == 0).all()
    # one photo away from the seam, a cross-fade at it
    assert (out[0, :, :12] > 0.99).all() and (out[1, :, 20:] > 0.99).all()
    mid = out[0, :, 15:17]
    assert ((mid > 0.1) & (mid < 0.9)).all()
    assert st["labels"] == 2 and st["kept_share"] == 0.0
    # hard seams without feathering
    hard, _ = select_weights(W, Q, idx, mask, 3, patch=4, feather=0.0)
    assert set(torch.unique(hard).tolist()) <= {0.0, 1.0}


def test_smoothness_removes_isolated_patches():
    unary = np.zeros((6, 6, 2))
    unary[..., 1] = 1.0
    unary[3, 3] = (1.0, 0.0)  # one patch prefers label 1 by 1
    assert solve_potts(unary, 0.0)[3, 3] == 1
    assert (solve_potts(unary, 1.0) == 0).all()  # 4 seam edges cost more than it gains


def test_a_texel_whose_selected_photo_does_not_see_it_keeps_its_weights():
    h, w = 8, 8
    idx, W, Q = _slots(h, w)
    Q[0] = 2.0
    W[0, 2, 2] = 0.0  # the selected photo has no weight at one texel
    W = W / W.sum(0, keepdim=True)
    out, st = select_weights(W, Q, idx, torch.ones(h, w, dtype=torch.bool), 3, patch=4, feather=0.0)
    assert torch.allclose(out[:, 2, 2], W[:, 2, 2])
    assert st["kept_share"] == pytest.approx(1 / 64)
    assert torch.isfinite(out).all()


def test_one_photo_or_none_changes_nothing():
    idx, W, Q = _slots(4, 4)
    W[1:] = 0.0
    W[0] = 1.0
    out, st = select_weights(W, Q, idx, torch.ones(4, 4, dtype=torch.bool), 3)
    assert torch.equal(out, W) and st["labels"] == 1
    zero = torch.zeros(3, 4, 4)
    out, st = select_weights(zero, Q, idx, torch.ones(4, 4, dtype=torch.bool), 3)
    assert torch.equal(out, zero) and st["labels"] == 0


def test_where_the_photos_agree_the_blend_stays_and_the_seam_goes_there():
    h, w = 16, 32
    idx, W, Q = _slots(h, w)
    Q[0, :, :12] = 1.5  # photo 0 best on the left, photo 1 on the right
    Q[1, :, 12:] = 1.5
    free = torch.zeros(h, w, dtype=torch.bool)
    free[:, :8] = True  # the photos disagree only at both ends
    free[:, 24:] = True
    mask = torch.ones(h, w, dtype=torch.bool)
    out, st = select_weights(W, Q, idx, mask, 3, patch=4, smoothness=1.0, feather=0.0, free=free)
    assert (out[0, :, :8] == 1).all() and (out[1, :, 24:] == 1).all()  # selected where they disagree
    assert torch.allclose(out[:, :, 8:24], W[:, :, 8:24])  # the blend where they agree
    assert st["selected_share"] == pytest.approx(0.5)
    # with a cross-fade, the weights still sum to one
    soft, _ = select_weights(W, Q, idx, mask, 3, patch=4, feather=1.5, free=free)
    assert torch.allclose(soft.sum(0), torch.ones(h, w), atol=1e-5)


def test_detail_band_keeps_the_selections_edges_and_the_blends_colours_below_the_band():
    """A mullion (a dark bar) that the selected photo shows and the blend smears: the band keeps the
    bar's full contrast from the selection, while the selection's exposure (+0.2 everywhere) and
    its slow shading are replaced by the blend's; outside the polygon the blend stays."""
    h, w = 24, 48
    x = torch.arange(w, dtype=torch.float32)
    shading = 0.1 * x / w  # slow, below the band
    selected = (0.6 + 0.2 + shading).expand(3, h, w).clone()
    selected[:, :, 22:25] -= 0.4  # the bar, three texels wide
    blended = (0.6 + shading).expand(3, h, w).clone()
    blended[:, :, 18:29] -= 0.4 * 3 / 11  # the same bar smeared over eleven texels
    mask = torch.ones(h, w, dtype=torch.bool)
    mask[:, -4:] = False
    out = detail_band(blended, selected, mask, 4.0)
    assert torch.equal(out[:, :, -4:], blended[:, :, -4:])
    inner = out[:, 4:-4, 4:-8]
    # the bar at full contrast, the plain wall at the blend's level (the +0.2 exposure gone)
    bar_depth = float(out[0, 12, 12] - out[0, 12, 23])
    assert bar_depth == pytest.approx(0.4, abs=0.06)
    assert float(out[0, 12, 8]) == pytest.approx(float(blended[0, 12, 8]), abs=0.03)
    # next to texels outside the mask (unseen), the selection's exposure is still taken out whole
    assert float(out[0, 12, w - 5]) == pytest.approx(float(blended[0, 12, w - 5]), abs=0.03)
    assert float(inner.mean()) < float(selected[:, 4:-4, 4:-8].mean()) - 0.15
    # the extremes: a band edge under a texel leaves no detail to hand over (the blend); one far
    # wider than the polygon hands over all of it, at the blend's mean level
    thin = detail_band(blended, selected, mask, 0.1)
    assert torch.allclose(thin[:, mask], blended[:, mask], atol=1e-3)
    wide = detail_band(blended, selected, mask, 1e4)
    shift = blended[:, mask].mean() - selected[:, mask].mean()
    assert torch.allclose(wide[:, mask], selected[:, mask] + shift, atol=1e-3)
    # a bright selected edge over a dark blend would overshoot: the colours stay in [0, 1]
    over = detail_band(torch.zeros(3, h, w), torch.where(x < 24, 0.0, 1.0).expand(3, h, w), mask, 3.0)
    assert float(over.min()) >= 0.0 and float(over.max()) <= 1.0 and float(over.max()) > 0.3
    with pytest.raises(ValueError):
        detail_band(blended, selected, mask, 0.0)
    with pytest.raises(ValueError):
        detail_band(blended, selected[:, :-1], mask, 1.0)
