"""The hand-written texel-space gradient equals autograd's on the objective, and Adam by hand
equals torch.optim.Adam."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from difftex.method import losses
from difftex.method.config import OptimizeConfig
from difftex.method.gradient import Adam, texel_data, texel_value_and_grad
from difftex.method.objective import objective

torch.set_num_threads(1)


def random_level(K: int, H: int, W: int, photos: int, seed: int):
    """A random slot layout: ``photos`` photos over K slots (fixed when photos <= K)."""
    g = torch.Generator().manual_seed(seed)
    fixed = photos <= K
    if fixed:
        idx = torch.arange(K)[:, None, None].expand(K, H, W).clone()
    else:
        idx = torch.stack([torch.randperm(photos, generator=g)[:K] for _ in range(H * W)], -1).reshape(K, H, W)
    visible = torch.rand(K, H, W, generator=g) > 0.2
    visible[0] = True  # every texel has a source
    idx = torch.where(visible, idx, torch.full_like(idx, -1))
    mask = torch.rand(H, W, generator=g) > 0.1
    colours = torch.rand(K, 3, H, W, generator=g) * visible[:, None]
    Q = torch.rand(K, H, W, generator=g) * visible
    cost = torch.rand(K, H, W, generator=g)
    theta = (torch.randn(K, H, W, generator=g) * visible).double()  # logits
    G = torch.rand(H, W, generator=g)
    return idx, visible, mask, colours.double(), Q.double(), cost.double(), theta, G.double(), fixed


@pytest.mark.parametrize("photos", [4, 7])
@pytest.mark.parametrize(
    "kw",
    [
        {},
        {"ghost": 0.0},
        {"ghost": 0.3, "para_eps": 0.0},
        {"ghost_margin": 2.0},
        {"use_para": False},
        {"use_render": False},
        {"use_persp": False},
    ],
)
def test_texel_gradient_matches_autograd(photos, kw):
    K, H, W = 4, 9, 11
    idx, visible, mask, colours, Q, cost, theta, G, fixed = random_level(K, H, W, photos, seed=photos)
    cfg = dataclasses.replace(OptimizeConfig(), **kw)
    active = visible & (torch.rand(K, H, W, generator=torch.Generator().manual_seed(1)) > 0.1)
    active[0] |= visible[0]
    n_tex = float(mask.sum())
    matches = {a: losses.neighbour_match(idx, mask, a, fixed=fixed) for a in (1, 2)}
    U0 = losses.compose(losses.blend_weights(theta, active), colours)
    D = losses.edge_weights(U0, G, (1, 2))
    th = theta.clone().requires_grad_(True)
    margin = kw.get("ghost_margin", 0.0) * 0.01
    ref = objective(th, active, colours, Q, cost, D, matches, None, None, n_tex, cfg, margin)
    ref["total"].backward()
    terms, grad = texel_value_and_grad(theta, active, texel_data(colours, Q, cost, n_tex, margin), D, matches, cfg)
    for k in ("total", "render", "persp", "para", "ghost"):
        if k in ref:
            assert float(terms[k]) == pytest.approx(float(ref[k].detach()), rel=1e-9, abs=1e-12), k
    assert torch.allclose(grad, th.grad, rtol=1e-7, atol=1e-10)


def test_adam_matches_torch():
    g = torch.Generator().manual_seed(0)
    p1 = torch.rand(5, 6, generator=g)
    p2 = p1.clone().requires_grad_(True)
    mine = Adam(lr=0.01, betas=(0.9, 0.99))
    ref = torch.optim.Adam([p2], lr=0.01, betas=(0.9, 0.99))
    for _ in range(7):
        grad = torch.randn(5, 6, generator=g)
        mine.step(p1, grad)
        p2.grad = grad.clone()
        ref.step()
    assert torch.allclose(p1, p2.detach(), atol=1e-7)
