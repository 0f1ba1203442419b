"""Semi-global aggregation of the relief sweep's cost volume (difftex.method.semiglobal): each path
against a texel-by-texel transcription of Hirschmueller's recursion, the penalties at their
extremes, and the occlusion-robust per-texel cost."""

from __future__ import annotations

import math

import pytest
import torch

from difftex.method.semiglobal import DIRECTIONS_8, aggregate, best_share_mean, path_cost


def _path_cost_by_texel(c: torch.Tensor, d: tuple[int, int], p1: float, p2: float) -> torch.Tensor:
    """L_r(p, d) visited texel by texel in an order where each predecessor p - r comes first."""
    D, H, W = c.shape
    dy, dx = d
    ys = range(H) if dy >= 0 else range(H - 1, -1, -1)
    xs = range(W) if dx >= 0 else range(W - 1, -1, -1)
    order = [(y, x) for x in xs for y in ys] if dx else [(y, x) for y in ys for x in xs]
    L = torch.zeros_like(c)
    inf = torch.tensor([math.inf], dtype=c.dtype)
    for y, x in order:
        py, px = y - dy, x - dx
        if not (0 <= py < H and 0 <= px < W):
            L[:, y, x] = c[:, y, x]
            continue
        p = L[:, py, px]
        m = p.min()
        step = torch.minimum(torch.cat([p[1:], inf]), torch.cat([inf, p[:-1]])) + p1
        L[:, y, x] = c[:, y, x] + torch.minimum(torch.minimum(p, step), m + p2) - m
    return L


@pytest.mark.parametrize("direction", DIRECTIONS_8)
def test_each_path_is_the_recursion_texel_by_texel(direction):
    g = torch.Generator().manual_seed(3)
    c = torch.rand(5, 6, 7, generator=g, dtype=torch.float64)
    got = path_cost(c, direction, 0.1, 0.4)
    assert torch.allclose(got, _path_cost_by_texel(c, direction, 0.1, 0.4), atol=1e-12)


def test_no_penalty_leaves_each_texels_cheapest_label():
    g = torch.Generator().manual_seed(4)
    c = torch.rand(9, 12, 10, generator=g, dtype=torch.float64)
    assert torch.equal(aggregate(c, 0.0, 0.0).argmin(0), c.argmin(0))


def test_a_large_jump_penalty_flattens_noise_and_keeps_a_wide_step():
    # label 2 everywhere, label 6 in a wide block; one-texel noise prefers random labels
    g = torch.Generator().manual_seed(5)
    truth = torch.full((40, 40), 2)
    truth[10:30, 12:32] = 6
    c = torch.ones(8, 40, 40, dtype=torch.float64)
    c.scatter_(0, truth[None], 0.6)
    noise = torch.rand(40, 40, generator=g) < 0.1
    c[:, noise] = 1.0
    c[2][noise & (truth == 2)] = 0.7
    c[6][noise & (truth == 6)] = 0.7
    c[0][noise] = 0.6  # scattered texels prefer label 0 by 0.1
    assert bool((c.argmin(0) != truth).any())
    got = aggregate(c, 0.05, 0.5).argmin(0)
    assert torch.equal(got, truth)
    # without the jump penalty the scattered texels keep their own label
    assert bool((aggregate(c, 0.0, 0.0).argmin(0)[noise] == 0).all())


def test_aggregate_checks_its_input_and_passes_inf_texels_on():
    c = torch.ones(3, 5, 5, dtype=torch.float64)
    c[1] = 0.0
    c[:, 2, 2] = math.inf  # no photo compares there: it takes its neighbours' label
    assert torch.all(aggregate(c, 0.1, 0.3).argmin(0) == 1)
    with pytest.raises(ValueError):
        aggregate(c[0], 0.1, 0.3)
    with pytest.raises(ValueError):
        aggregate(c, 0.3, 0.1)
    with pytest.raises(ValueError):
        path_cost(c, (0, 0), 0.1, 0.3)
    with pytest.raises(ValueError):
        path_cost(c, (2, 0), 0.1, 0.3)


def test_best_share_mean_at_its_extremes():
    costs = torch.tensor([0.1, 0.9, 0.5, 0.3, 0.7, 2.0]).view(6, 1, 1)
    valid = torch.tensor([True, True, True, True, True, False]).view(6, 1, 1)
    # share 1: the mean over the valid photos (the invalid 2.0 is ignored)
    assert best_share_mean(costs, valid, 1.0).item() == pytest.approx(0.5)
    # the best half of 5 is 3 photos: 0.1, 0.3, 0.5
    assert best_share_mean(costs, valid, 0.5).item() == pytest.approx(0.3)
    # a tiny share keeps at least `least` photos
    assert best_share_mean(costs, valid, 0.01, least=2).item() == pytest.approx(0.2)
    # fewer valid photos than `least`: all of them
    two = torch.tensor([True, True, False, False, False, False]).view(6, 1, 1)
    assert best_share_mean(costs, two, 0.5).item() == pytest.approx(0.5)
    assert best_share_mean(costs, torch.zeros_like(valid), 0.5).item() == math.inf
    with pytest.raises(ValueError):
        best_share_mean(costs, valid, 0.0)
    with pytest.raises(ValueError):
        best_share_mean(costs, valid[:3], 0.5)
