"""The sparse finer levels (difftex.method.regions): a photo is mapped only over the tiles where
the coarser level gave it weight, and the texture matches the one of a level where every photo is
mapped everywhere."""

from __future__ import annotations

import analytic_relief as ar
import numpy as np
import pytest
import torch

from difftex.compose.texturing import texture_polygon
from difftex.method import levels
from difftex.method.config import ComputeConfig, OptimizeConfig
from difftex.method.regions import tile_runs, upsample_support


def test_tiles_cover_the_support_disjointly_and_merge_into_one_box_when_dense():
    need = torch.zeros((300, 500), dtype=torch.bool)
    need[10:20, 5:30] = True  # a photo's support at the wall's left end ...
    need[250:260, 450:490] = True  # ... and at its right end: one box would span the wall
    runs = tile_runs(need, tile=64)
    cover = torch.zeros_like(need, dtype=torch.int32)
    for y0, y1, x0, x1 in runs:
        cover[y0:y1, x0:x1] += 1
    assert int(cover.max()) == 1  # disjoint: a photo never holds two slots of a texel
    assert bool((cover[need] == 1).all())
    assert int((cover > 0).sum()) <= 3 * 64 * 64 < need.numel() // 8
    need[:] = True
    assert tile_runs(need, tile=64) == [(0, 300, 0, 500)]


def test_support_grows_by_the_reach_of_the_bilinear_upsampling():
    sup = torch.zeros((8, 8), dtype=torch.bool)
    sup[3, 3] = True
    fine = upsample_support(sup, (32, 32), r=0.25, pad=1)
    ys, xs = torch.nonzero(fine, as_tuple=True)
    # coarse texel 3 covers fine 12..15; half a coarse texel (2 fine) plus 1 each side
    assert int(ys.min()) == 12 - 3 and int(ys.max()) == 15 + 3 and int(xs.min()) == 9


@pytest.fixture(scope="module")
def wall():
    torch.set_num_threads(1)
    phs = ar.photos()
    return ar.make_input(phs, [ar.render(p) for p in phs], long_side=192)


def test_the_sparse_finest_level_gives_the_dense_levels_texture(wall, monkeypatch):
    cfg = OptimizeConfig(long_side_start=24, level_step=2.0, histogram_matching=False)
    sparse = texture_polygon(wall, cfg, ComputeConfig(device="cpu"))

    def every_photo_everywhere(photos, frame, mask, prev, prev_known, tau, **_):
        h, w = frame.shape
        return [(n, (0, h, 0, w)) for n in sorted(photos.samplers)]

    monkeypatch.setattr(levels, "photo_entries", every_photo_everywhere)
    dense = texture_polygon(wall, cfg, ComputeConfig(device="cpu"))
    d = np.abs(sparse.texture - dense.texture).max(-1)[wall.texel_mask]
    # the photos a coarser level left without weight start at zero weight in the dense level too;
    # what differs is the few texels where such a photo regains weight at the finer level
    assert d.mean() < 0.005
    assert np.quantile(d, 0.98) < 0.03
