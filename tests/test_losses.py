"""The loss terms on hand-made slot layouts: values that follow from the definitions."""

from __future__ import annotations

import torch

from difftex.method import losses

torch.set_num_threads(1)


def test_blend_weights_normalised_inactive_zero_and_all_zero_is_uniform():
    theta = torch.tensor([[[0.5]], [[0.5]], [[0.9]]])
    active = torch.tensor([[[True]], [[True]], [[False]]])
    W = losses.blend_weights(theta, active)
    assert torch.allclose(W[:, 0, 0], torch.tensor([0.5, 0.5, 0.0]))
    W0 = losses.blend_weights(torch.zeros(3, 1, 1), active)  # every raw weight at 0
    assert torch.allclose(W0[:, 0, 0], torch.tensor([0.5, 0.5, 0.0]))
    Wn = losses.blend_weights(theta, torch.zeros_like(active))
    assert torch.isfinite(Wn).all() and Wn.sum() == 0


def test_render_texel_zero_when_photos_agree_and_inactive_slots_carry_no_weight():
    col = torch.rand(3, 4, 5)
    colours = col[None].repeat(2, 1, 1, 1)
    theta = torch.rand(2, 4, 5)
    active = torch.ones(2, 4, 5, dtype=torch.bool)
    W = losses.blend_weights(theta, active)
    U = losses.compose(W, colours)
    assert torch.allclose(U, col, atol=1e-6)
    assert losses.render_loss_texel(U, colours, active, torch.ones(2, 4, 5), 20.0) < 1e-10
    active[1] = False
    W = losses.blend_weights(theta, active)
    assert torch.equal(W[1], torch.zeros_like(W[1])) and torch.allclose(W[0], torch.ones_like(W[0]))


def test_render_view_of_a_constant_texture_is_constant_up_to_the_border():
    U = torch.zeros(3, 6, 8)
    U[:, :, :] = torch.tensor([0.2, 0.4, 0.6])[:, None, None]
    support = torch.zeros(6, 8, dtype=torch.bool)
    support[1:5, 1:7] = True
    U = U * support  # outside the polygon U is black
    # pixels at texel coordinates on the polygon's border (bilinear footprint crosses it)
    t = torch.tensor([[1.0, 1.0], [6.9, 4.9], [3.5, 2.5]])
    grid = torch.stack([t[:, 0] / 8 * 2 - 1, t[:, 1] / 6 * 2 - 1], -1)[None, :, None, :]
    R = losses.render_view(U, support, grid)
    assert torch.allclose(R, torch.tensor([0.2, 0.4, 0.6]).expand(3, 3), atol=1e-5)


def test_guidance_direction_and_persp_cost_prefer_the_frontal_photo():
    n = torch.tensor([0.0, -1.0, 0.0])
    v = torch.tensor([[0.0, 1.0, 0.0], [0.0, 1.0, 0.0]])  # both cameras look straight at the wall
    assert torch.allclose(losses.guidance_direction(v, n), torch.tensor([0.0, 1.0, 0.0]))
    oblique = torch.tensor([0.5, 0.866, 0.0])
    v2 = torch.stack([torch.tensor([0.0, 1.0, 0.0]), oblique])
    vt = losses.guidance_direction(v2, n)
    field = v2[:, :, None, None].expand(2, 3, 1, 1)
    cost = losses.persp_cost(field, vt)
    assert cost[0, 0, 0] < cost[1, 0, 0]
    theta = torch.full((2, 1, 1), 0.5, requires_grad=True)
    W = losses.blend_weights(theta, torch.ones(2, 1, 1, dtype=torch.bool))
    losses.persp_loss(W, cost, 1.0).backward()
    assert theta.grad[0, 0, 0] < 0 < theta.grad[1, 0, 0]  # gradient descent moves weight to the frontal photo


def _layout(idx_rows):
    return torch.tensor(idx_rows, dtype=torch.long)


def test_para_loss_follows_photos_not_slot_order():
    # two texels side by side; the same two photos in swapped slots with the same weights
    idx = torch.tensor([[[3, 7]], [[7, 3]]])  # (K=2, h=1, w=2)
    W = torch.tensor([[[0.8, 0.2]], [[0.2, 0.8]]])  # photo 3: 0.8 at both texels; photo 7: 0.2 at both
    mask = torch.ones(1, 2, dtype=torch.bool)
    active = torch.ones(2, 1, 2, dtype=torch.bool)
    U = torch.rand(3, 1, 2)
    G = torch.zeros(1, 2)
    m = {2: losses.neighbour_match(idx, mask, 2)}
    assert losses.para_loss(W, U, active, G, m, 0.5, 1.0) < 1e-7
    # now a real change of source: photo 3 -> 0.2 on the right texel
    W2 = torch.tensor([[[0.8, 0.8]], [[0.2, 0.2]]])
    val = losses.para_loss(W2, U, active, G, m, 0.5, 1.0)
    D = torch.sigmoid((U[:, 0, 1] - U[:, 0, 0]).norm())  # G = 0; both photos overlap: m = 1
    assert torch.isclose(val, (D + 0.5) * (0.6 + 0.6), atol=1e-6)


def test_para_loss_counts_a_photo_missing_from_one_texel():
    idx = torch.tensor([[[1], [1]], [[2], [-1]]])  # (K=2, h=2, w=1): texel above has photos 1,2; below only 1
    W = torch.tensor([[[0.5], [1.0]], [[0.5], [0.0]]])
    mask = torch.ones(2, 1, dtype=torch.bool)
    active = idx >= 0
    U = torch.zeros(3, 2, 1)
    G = torch.zeros(2, 1)
    m = {1: losses.neighbour_match(idx, mask, 1)}
    val = losses.para_loss(W, U, active, G, m, 0.5, 1.0)
    # o = lower texel (photo 1 only, m = 0 there), q = upper texel: |1 - 0.5| * 0.5 + photo 2 alone 0.5 * 0.5
    assert torch.isclose(val, torch.tensor(0.5 * 0.5 + 0.5 * 0.5), atol=1e-6)


def test_para_smoothing_is_exact_l1_with_eps_zero_and_close_with_small_eps():
    idx = torch.zeros(1, 3, 3, dtype=torch.long)
    W = torch.rand(1, 3, 3)
    mask = torch.ones(3, 3, dtype=torch.bool)
    active = torch.ones(1, 3, 3, dtype=torch.bool)
    m = {1: losses.neighbour_match(idx, mask, 1), 2: losses.neighbour_match(idx, mask, 2)}
    U, G = torch.zeros(3, 3, 3), torch.zeros(3, 3)
    exact = losses.para_loss(W, U, active, G, m, 0.5, 1.0)
    ref = 0.5 * ((W[0, 1:] - W[0, :-1]).abs().sum() + (W[0, :, 1:] - W[0, :, :-1]).abs().sum())
    assert torch.isclose(exact, ref, atol=1e-6)
    smooth = losses.para_loss(W, U, active, G, m, 0.5, 1.0, eps=1e-4)
    assert abs(float(smooth - exact)) < 1e-3


def test_para_fixed_slot_shortcut_equals_the_general_matching():
    g = torch.Generator().manual_seed(0)
    K, h, w = 3, 5, 6
    idx = torch.arange(K)[:, None, None].expand(K, h, w).clone()
    idx[1, :2, :3] = -1  # photo 1 does not see the top-left corner
    active = idx >= 0
    theta = torch.rand(K, h, w, generator=g)
    W = losses.blend_weights(theta, active)
    U = torch.rand(3, h, w, generator=g)
    G = torch.rand(h, w, generator=g)
    mask = torch.ones(h, w, dtype=torch.bool)
    mask[-1, -1] = False
    gen = {a: losses.neighbour_match(idx, mask, a) for a in (1, 2)}
    fix = {a: losses.neighbour_match(idx, mask, a, fixed=True) for a in (1, 2)}
    a = losses.para_loss(W, U, active, G, gen, 0.5, 30.0, eps=0.01)
    b = losses.para_loss(W, U, active, G, fix, 0.5, 30.0, eps=0.01)
    assert torch.isclose(a, b, rtol=1e-5)
