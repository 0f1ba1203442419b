"""Detail from one photo per facade element (difftex.method.detail): the labelling's graph cut,
the agreement test, the seams' placement, the composition, and the analytic wall's mullions."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import torch

from difftex.method import detail as D
from difftex.method.config import OptimizeConfig
from difftex.method.selection import patch_costs


def _brute(unary, right, down):
    ph, pw, L = unary.shape
    return min(D.energy(np.array(c).reshape(ph, pw), unary, right, down)
               for c in itertools.product(range(L), repeat=ph * pw))


def test_expansion_is_exact_on_two_labels_and_close_on_three():
    rng = np.random.default_rng(0)
    for L in (2, 3):
        for _ in range(6):
            u = rng.random((3, 3, L)) * 3
            r, d = rng.random((3, 3)) * 2, rng.random((3, 3)) * 2
            e = D.energy(D.solve_labels(u, r, d, cycles=5), u, r, d)
            best = _brute(u, r, d)
            assert e <= best + 1e-9 if L == 2 else e <= 2 * best
    u = rng.random((4, 5, 3))
    assert (D.solve_labels(u, np.zeros((4, 5)), np.zeros((4, 5))) == u.argmin(-1)).all()


def test_sharpest_agreeing_photo_is_cheapest_and_an_occluded_one_is_no_candidate():
    h, w = 4, 4
    resolve = torch.stack([torch.full((h, w), 2.0), torch.full((h, w), 1.0), torch.full((h, w), 4.0)])
    dist = torch.stack([torch.full((h, w), 0.5), torch.full((h, w), 0.8), torch.full((h, w), 40.0)])  # photo 2: a tree
    where = torch.ones((3, h, w), dtype=torch.bool)
    cost = D.texel_costs(resolve, dist, where, agree=3.0)
    assert cost.shape == (4, h, w)
    assert torch.all(cost[0] == D.BLEND_COST)
    assert torch.all(cost[3] == D.UNSEEN_COST)  # the finest photo, but it sees the occluder
    assert torch.all(cost[1] < cost[2]) and torch.all(cost[1] < cost[0])
    # where every photo differs from the blend alike (parallax on a recessed pane), none is singled out
    dist = torch.stack([torch.full((h, w), 9.0), torch.full((h, w), 11.0), torch.full((h, w), 10.0)])
    cost = D.texel_costs(resolve, dist, where, agree=3.0)
    assert torch.all(cost[1:] < D.UNSEEN_COST) and torch.all(cost[3] < cost[1])
    # a photo without colours at a texel is no candidate there
    where[2, 0, 0] = False
    assert D.texel_costs(resolve, dist, where, agree=3.0)[3, 0, 0] == D.UNSEEN_COST


def _two_photo_wall(w: int = 64, patch: int = 4):
    """Photo A is the best left of x = 16, B right of x = 48, either as good between; the photos
    disagree (a window's parallax) on columns 16-40 and agree on 40-48."""
    h = 16
    ua = np.zeros((h, w))
    ub = np.zeros((h, w))
    ua[:, 48:] = 1.0
    ub[:, :16] = 1.0
    spread = torch.zeros((h, w))
    spread[:, 16:40] = 4.0
    unary = patch_costs(np.stack([ua, ub]), patch)
    right, down = D.seam_costs(spread, torch.ones((h, w), dtype=torch.bool), patch, smoothness=1.0)
    return D.solve_labels(unary, right, down), patch


def test_seams_run_where_the_photos_agree_and_a_window_is_not_split():
    labels, patch = _two_photo_wall()
    assert (labels[:, : 16 // patch] == 0).all() and (labels[:, 48 // patch :] == 1).all()
    cols = np.nonzero(np.diff(labels, axis=1).any(0))[0]
    assert len(cols) == 1  # one seam ...
    seam_x = (cols[0] + 1) * patch
    assert 40 <= seam_x <= 48  # ... where the photos agree, not through the window (16-40)
    assert (labels[:, 16 // patch : 40 // patch] == 0).all()  # the window from one photo


def test_composition_is_the_blend_where_it_keeps_the_detail_and_the_photo_above_the_band():
    torch.manual_seed(0)
    h, w = 32, 48
    blend = torch.rand(3, h, w) * 0.2 + 0.4
    seen = torch.ones((h, w), dtype=torch.bool)
    photo = torch.rand(3, h, w)
    lab0 = torch.zeros((h, w), dtype=torch.long)
    out = D.compose_detail(blend, [(photo, seen)], lab0, seen, band=2.0, feather=1.0)
    assert torch.allclose(out, blend, atol=1e-5)
    lab1 = torch.ones((h, w), dtype=torch.long)
    out = D.compose_detail(blend, [(photo, seen)], lab1, seen, band=2.0, feather=1.0)
    from difftex.method.filters import masked_blur
    expect = (masked_blur(blend, seen, 2.0) + photo - masked_blur(photo, seen, 2.0)).clamp(0, 1)
    assert torch.allclose(out, expect, atol=1e-5)
    # outside ``seen`` the blend stays
    seen2 = seen.clone()
    seen2[:, :4] = False
    out = D.compose_detail(blend, [(photo, seen)], lab1, seen2, band=2.0, feather=1.0)
    assert torch.equal(out[:, :, :4], blend[:, :, :4])


def test_an_occluder_in_the_sharpest_photo_stays_out():
    """Three photos of a striped wall: the sharpest sees a dark tree over its left half. The blend
    (here the two others' mean) has no tree; the detail takes the sharp photo only right of it."""
    h, w, K = 40, 80, 3
    x = torch.arange(w).float()
    wall = (0.5 + 0.3 * torch.sign(torch.sin(x * 0.8)))[None, None].expand(3, h, w)
    soft = wall * 0.5 + 0.25
    sharp = torch.stack([wall.clone(), soft, soft])
    sharp[0, :, 5:35, 5:35] = 0.05  # the tree
    idx = torch.stack([torch.full((h, w), n) for n in range(K)])
    present = torch.ones((K, h, w), dtype=torch.bool)
    resolve = torch.stack([torch.full((h, w), 3.0), torch.full((h, w), 1.0), torch.full((h, w), 1.0)])
    blend = (sharp[1] + sharp[2]) / 2
    seen = torch.ones((h, w), dtype=torch.bool)
    st = D.DetailSettings(band=3.0, patch=4)
    U, who, stats = D.detail_texture(blend, sharp, idx, present, resolve, seen, 0.02, st)
    assert (who[10:30, 10:30] != 0).all()  # the tree's photo gives no detail over the tree
    assert (who[:, 50:] == 0).all()  # but right of it, it is the sharpest
    assert U[:, 10:30, 10:30].mean() > 0.3  # no dark tree in the texture
    assert stats["photos"] >= 1 and 0.0 < stats["blend_share"] + 1e-9


def test_detail_settings_are_checked():
    with pytest.raises(ValueError):
        OptimizeConfig(detail="all", detail_band=0.0)
    with pytest.raises(ValueError):
        OptimizeConfig(detail="all", detail_patch=0)
    with pytest.raises(ValueError):
        D.solve_labels(np.zeros((2, 2, 2)), np.zeros((3, 2)), np.zeros((2, 2)))
    with pytest.raises(ValueError):
        D.texel_costs(torch.zeros(2, 3, 3), torch.zeros(2, 3, 4), torch.zeros(2, 3, 3, dtype=torch.bool), 3.0)


@pytest.fixture(scope="module")
def recessed_window():
    """The analytic wall (tests/analytic_relief.py): a window recessed 0.3 m with a cross of
    8 cm mullions, photographed from 5 directions at each of three heights."""
    import analytic_relief as ar

    torch.set_num_threads(1)
    phs = ar.photos()
    return ar, ar.make_input(phs, [ar.render(p) for p in phs], long_side=128)


def _mullion_profile(ar, inp, texture):
    """The texture's grey level across the vertical mullion, averaged over the pane's rows, and
    the x of each column relative to the mullion's centre (metres)."""
    tx, ty = inp.frame.centres()
    X = inp.frame.texel_to_world(tx, ty)
    x, z = X[..., 0], X[..., 2]
    cx = (ar.WINDOW[0] + ar.WINDOW[1]) / 2
    rows = ((z > ar.WINDOW[2] + 0.15) & (z < ar.WINDOW[3] - 0.15)).any(1)
    cols = np.abs(x[0] - cx) < 0.25
    return texture.mean(-1)[rows][:, cols].mean(0), x[0][cols] - cx


def test_the_detail_keeps_the_recessed_windows_mullion_where_the_blend_loses_it(recessed_window):
    from difftex.compose.texturing import texture_polygon
    from difftex.method.config import ComputeConfig

    ar, inp = recessed_window
    base = dict(long_side_start=32, level_step=2.0, histogram_matching=False)
    plain = texture_polygon(inp, OptimizeConfig(**base, detail="off"), ComputeConfig(device="cpu"))
    comp = texture_polygon(inp, OptimizeConfig(**base, detail="all"), ComputeConfig(device="cpu"))
    p_plain, _ = _mullion_profile(ar, inp, plain.texture)
    p_comp, off = _mullion_profile(ar, inp, comp.texture)
    # the truth: 0.95 on the mullion, about 0.25 on the glass. The blend smears it to a faint bump
    assert p_plain.max() - np.median(p_plain) < 0.15
    assert p_comp.max() - np.median(p_comp) > 0.25  # contrast kept ...
    assert abs(off[np.argmax(p_comp)]) <= 0.035  # ... at its place, within a texel (3.1 cm)
    # the window comes from one photo: no seam of the labelling crosses the pane
    st = comp.stats["detail"]
    assert st["photos"] >= 1 and st["blend_share"] < 0.5
