"""The free texels as a sub-level (difftex.method.sparse) against the whole level."""

from __future__ import annotations

import pytest
import torch

from difftex.geometry.frames import UVFrame
from difftex.method import losses, sparse
from difftex.method.config import OptimizeConfig
from difftex.method.gradient import texel_data, texel_value_and_grad
from difftex.method.levels import Level

torch.set_num_threads(1)


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
    # free texels scattered and in clusters, as along edges and around occluders
    seeds = (torch.rand(1, 1, h, w, generator=g) < 0.01).float()
    free = (torch.nn.functional.max_pool2d(seeds, 3, 1, 1)[0, 0] > 0) & mask
    frame = UVFrame.from_dict(
        {"origin": [0, 0, 0], "e_u": [1, 0, 0], "e_v": [0, 0, -1], "normal": [0, -1, 0], "texel_size": 0.01,
         "width": w, "height": h}
    )
    lv = Level(frame=frame, mask=mask, idx=idx, visible=idx >= 0, colours=colours, Q=Q, cost=cost, G=G,
               z0=z.clone(), v_tilde=None, n_candidates=6, fixed_slots=fixed)
    return lv, active, z, free


@pytest.mark.parametrize("fixed", [False, True])
def test_sub_level_gradient_equals_the_level_gradient_on_free_texels(fixed):
    lv, active, z, free = random_level(3, fixed=fixed)
    cfg = OptimizeConfig()
    n_tex = lv.n_tex
    # the whole level, L_Para coupling the free texels only (as the optimizer builds it)
    matches = {a: losses.neighbour_match(lv.idx, free, a, fixed=fixed) for a in (1, 2)}
    U = losses.compose(losses.blend_weights(z, active), lv.colours)
    D = losses.edge_weights(U, lv.G, (1, 2))
    terms_full, g_full = texel_value_and_grad(z, active, texel_data(lv.colours, lv.Q, lv.cost, n_tex, 0.05), D,
                                              matches, cfg)
    sp = sparse.sparse_level(lv, free, lv.Q, 0.05)
    assert sp.sub.idx.shape == (lv.idx.shape[0], 1, int(free.sum()))
    z_f, a_f = sparse.gather(z, sp.src), sparse.gather(active, sp.src)
    terms, g = sparse.value_and_grad(sp, z_f, a_f, cfg, refresh=True)
    assert torch.allclose(g, sparse.gather(g_full, sp.src), atol=1e-6, rtol=1e-4)
    # L_Para couples free texels only: its value is the whole level's
    assert torch.allclose(terms["para"], terms_full["para"], rtol=1e-4)


def test_edges_are_the_free_neighbour_pairs():
    lv, _, _, free = random_level(5)
    sp = sparse.sparse_level(lv, free, lv.Q, 0.0)
    h, w = free.shape
    for axis, e in sp.edges.items():
        o, q = sp.src[e.o], sp.src[e.q]
        step = w if axis == 1 else 1
        assert torch.equal(o - q, torch.full_like(o, step))
        pairs = free[1:, :] & free[:-1, :] if axis == 1 else free[:, 1:] & free[:, :-1]
        assert e.o.numel() == int(pairs.sum())
    assert not any((sp.src[e.o] % w == 0).any() for a, e in sp.edges.items() if a == 2)  # no wrap-around


def test_scatter_puts_values_back_where_they_came_from():
    lv, _, z, free = random_level(7)
    sp = sparse.sparse_level(lv, free, lv.Q, 0.0)
    out = torch.zeros_like(z)
    sparse.scatter_into(out, sparse.gather(z, sp.src), sp.src)
    assert torch.equal(out[:, free], z[:, free]) and (out[:, ~free] == 0).all()
