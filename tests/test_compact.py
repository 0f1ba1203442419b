"""The objective on the free texels' tiles (difftex.method.compact) against the whole level."""

from __future__ import annotations

import pytest
import torch

from difftex.method import compact, losses
from difftex.method.config import OptimizeConfig
from difftex.method.gradient import texel_data, texel_value_and_grad


def random_level(seed: int, K: int = 4, h: int = 97, w: int = 130, fixed: bool = False):
    g = torch.Generator().manual_seed(seed)
    colours = torch.rand(K, 3, h, w, generator=g)
    Q = torch.rand(K, h, w, generator=g) + 0.1
    cost = torch.rand(K, h, w, generator=g)
    G = torch.rand(h, w, generator=g)
    if fixed:
        idx = torch.arange(K)[:, None, None].expand(K, h, w).clone()
    else:  # a different photo order per texel, some empty slots
        idx = torch.argsort(torch.rand(6, h, w, generator=g), 0)[:K]
        idx[torch.rand(K, h, w, generator=g) < 0.1] = -1
    mask = torch.ones(h, w, dtype=torch.bool)
    mask[:5, :7] = False  # a notch outside the polygon
    active = (idx >= 0) & (torch.rand(K, h, w, generator=g) < 0.8) & mask
    z = torch.randn(K, h, w, generator=g)
    # free texels in clusters, as around occluders and edges
    free = torch.nn.functional.max_pool2d((torch.rand(1, 1, h, w, generator=g) < 0.003).float(), 5, 1, 2)[0, 0] > 0
    return colours, Q, cost, G, idx, mask, active, z, free & mask


@pytest.mark.parametrize("fixed", [False, True])
def test_strip_gradient_equals_the_level_gradient_on_free_texels(fixed):
    colours, Q, cost, G, idx, mask, active, z, free = random_level(3, fixed=fixed)
    cfg = OptimizeConfig()
    n_tex = float(mask.sum())
    matches = {a: losses.neighbour_match(idx, mask, a, fixed=fixed) for a in (1, 2)}
    U = losses.compose(losses.blend_weights(z, active), colours)
    D = losses.edge_weights(U, G, (1, 2))
    _, g_full = texel_value_and_grad(z, active, texel_data(colours, Q, cost, n_tex, 0.05), D, matches, cfg)
    lay = compact.tile_layout(free, max_share=0.7)
    assert lay is not None and lay.src.numel() < 0.7 * free.numel()
    co = compact.compact_objective(lay, colours, Q, cost, G, idx, mask, n_tex, 0.05, fixed, True)
    _, g = compact.value_and_grad(z, active, co, cfg, refresh_D=True)
    assert torch.allclose(g[:, free], g_full[:, free], atol=1e-6, rtol=1e-4)
    assert (g[:, ~free] == 0).all()


def test_every_free_texel_is_one_interior_position():
    *_, free = random_level(5)
    lay = compact.tile_layout(free, max_share=0.7)
    assert lay is not None
    hit = torch.bincount(lay.src[lay.interior], minlength=free.numel()).reshape(free.shape)
    assert torch.equal(hit > 0, free) and int(hit.max()) == 1


def test_no_strip_when_it_would_not_pay():
    free = torch.ones(40, 40, dtype=torch.bool)
    assert compact.tile_layout(free) is None
    assert compact.tile_layout(torch.zeros(40, 40, dtype=torch.bool)) is None
    one = torch.zeros(40, 40, dtype=torch.bool)
    one[39, 39] = True  # a corner texel: its tile's halo reaches outside the level
    lay = compact.tile_layout(one, max_share=0.7)
    assert lay is not None and int(lay.interior.sum()) == 1
