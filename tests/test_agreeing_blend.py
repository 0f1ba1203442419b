"""The final agreeing blend (difftex.method.elimination.agreeing_blend, ``optimize.reblend_sigma``)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import torch

from difftex.method.elimination import agreeing_blend

from analytic import fast_cfg, make_input, make_photo, occluded_region, optimize, paint_occluder, render


def _level(colours, Q, noise=0.02):
    K, _, h, w = colours.shape
    return SimpleNamespace(colours=colours, blend_Q=Q, noise=noise, mask=torch.ones(h, w, dtype=torch.bool))


def test_agreeing_photos_join_the_chosen_one_and_disagreeing_ones_stay_out():
    # three slots, four texels: grey 0.5 in slots 0 and 1 (1 is 0.01 off: within 3 sigma_c = 0.06),
    # an occluder (0.9) in slot 2
    col = torch.tensor([0.5, 0.51, 0.9])[:, None, None, None].expand(3, 3, 1, 4).clone()
    col[:, :, 0, 1] = torch.tensor([0.2, 0.8, 0.5])[:, None]  # texel 1: two photos 0.6 apart
    Q = torch.tensor([1.0, 0.5, 1.0])[:, None, None].expand(3, 1, 4).clone()
    W = torch.zeros(3, 1, 4)
    W[0, 0, 0] = 1.0  # texel 0: the optimizer chose slot 0
    W[:2, 0, 1] = 0.5  # texel 1: a seam's blend of two disagreeing photos
    W[0, 0, 2] = 1.0  # texel 2: slot 1 agrees but was eliminated
    base = torch.ones(3, 1, 4, dtype=torch.bool)
    base[1, 0, 2] = False
    out, st = agreeing_blend(_level(col, Q), W, base, 3.0)
    assert torch.allclose(out[:, 0, 0], torch.tensor([2 / 3, 1 / 3, 0.0]))  # Q-weighted; the occluder out
    assert torch.equal(out[:, 0, 1], W[:, 0, 1])  # nothing within 3 sigma_c of 0.5: kept
    assert torch.equal(out[:, 0, 2], W[:, 0, 2])  # the eliminated slot stays out
    assert torch.equal(out[:, 0, 3], W[:, 0, 3])  # no weight (untextured): stays so
    assert st["changed_share"] == 0.25 and st["photos_before"] == 1.0 and st["photos_after"] == 2.0
    assert torch.isfinite(out).all()
    # k = 0 admits only exact matches: the chosen photo alone, its weights unchanged
    out0, _ = agreeing_blend(_level(col, Q), W, base, 1e-9)
    assert torch.equal(out0[:, 0, 0], W[:, 0, 0])


def test_where_the_optimizer_chose_past_an_occluder_the_agreeing_photos_average_the_noise():
    # five noisy photos, an occluder in two: in the occluded region the optimizer keeps the
    # photos that see past it; the agreeing blend takes in all three of them (not the occluded two)
    photos = [make_photo(f"p{y}", y) for y in (-24.0, -12.0, 0.0, 12.0, 24.0)]
    rng = np.random.default_rng(0)
    imgs = [render(ph) + rng.normal(0.0, 0.03, (ph.height, ph.width, 3)).astype(np.float32) for ph in photos]
    imgs[1], imgs[3] = paint_occluder(photos[1], imgs[1]), paint_occluder(photos[3], imgs[3])
    inp = make_input(photos, imgs, long_side=64)
    reg = occluded_region(inp) & inp.texel_visible.all(0)

    def run(**kw):
        res = optimize(inp, fast_cfg(**kw))
        occ = sum(np.where(res.idx == n, res.W, 0.0).sum(0) for n in (1, 3))
        neff = 1.0 / np.maximum((res.W**2).sum(0), 1e-9)
        return float(occ[reg].mean()), float(neff[reg].mean()), res

    occ0, n0, _ = run()
    occ1, n1, res = run(reblend_sigma=3.0)
    assert occ1 < 0.02 and occ0 < 0.02  # the occluder stays out either way
    assert n1 > n0 + 0.3  # more photos per texel where the optimizer chose
    assert res.stats["reblend"]["changed_share"] > 0
