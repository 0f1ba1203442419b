"""A level's top-K slots (difftex.method.slots) and its candidates' streamed statistics
(difftex.method.candidate_stats), on hand-made photos: what build_level composes."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from difftex.method.candidate_stats import CandidateStats, gradient_magnitude
from difftex.method.slots import EMPTY_SCORE, Slots
from difftex.sampling.photos import MappedPhoto

from analytic import fast_cfg


def _values(rng, h: int, w: int, detail: bool) -> list[torch.Tensor]:
    vals = [torch.from_numpy(rng.random((h, w)) > 0.2), torch.from_numpy(rng.random((3, h, w))).float()]
    vals += [torch.from_numpy(rng.random((h, w))).float() for _ in range(3)]
    return vals + ([torch.from_numpy(rng.random((3, h, w))).float()] if detail else [])


@pytest.mark.parametrize("detail", [False, True])
def test_slots_keep_the_k_best_scores_and_their_values_deferred_or_not(detail):
    rng = np.random.default_rng(3)
    h, w, K, n = 5, 6, 2, 5
    photos = [(rng.random((h, w)).astype(np.float32), _values(rng, h, w, detail)) for _ in range(n)]
    reg = (0, h, 0, w)
    filled = []
    for defer in (False, True):
        s = Slots(K, (h, w), "cpu", detail=detail, blend_q=False)
        for j, (score, values) in enumerate(photos):
            s.rank(j, reg, torch.from_numpy(score), values, defer=defer)
        s.write_deferred()
        filled.append(s)
    scores = np.stack([p[0] for p in photos])  # (n, h, w)
    best = np.argsort(-scores, axis=0, kind="stable")[:K]  # the K best photos per texel, best first
    a, b = filled
    assert np.array_equal(a.idx.numpy(), best) and torch.equal(a.idx, b.idx)
    assert np.allclose(a.score.numpy(), np.take_along_axis(scores, best, 0))
    for i, (t_a, t_b) in enumerate(zip(a.data, b.data)):
        assert torch.equal(t_a, t_b), i  # one masked write at the end equals gathering every time
        for k in range(K):
            for y in range(h):
                for x in range(w):
                    want = photos[best[k, y, x]][1][i][..., y, x]
                    assert torch.equal(t_a[k, ..., y, x], want), (i, k, y, x)  # the values follow their photo
    # an empty slot stays empty: a region no photo sees keeps idx -1 and the empty score
    s = Slots(K, (h, w), "cpu", detail=False, blend_q=True)
    s.rank(0, (0, 2, 0, 3), torch.ones(2, 3), _values(rng, 2, 3, False) + [torch.ones(2, 3)], defer=False)
    assert (s.idx[1] == -1).all() and (s.idx[0, 2:] == -1).all() and (s.score[:, 2:] == EMPTY_SCORE).all()
    assert s.Qb is not None and len(s.data) == 6


def _photo(colour: torch.Tensor, visible: torch.Tensor, footprint: float) -> MappedPhoto:
    h, w = visible.shape
    view = torch.zeros(3, h, w)
    view[1] = 1.0  # looking straight at a wall whose normal is -y
    return MappedPhoto(colour=colour, visible=visible, view=view, cos=torch.ones(h, w),
                       footprint=torch.full((h, w), footprint))


def test_candidate_stats_are_the_visible_candidates_mean_spread_and_best_footprint():
    h, w = 4, 5
    grey = torch.full((3, h, w), 0.25)
    bright = torch.full((3, h, w), 0.75)
    half = torch.zeros(h, w, dtype=torch.bool)
    half[:, :2] = True
    st = CandidateStats((h, w), "cpu", torch.tensor([0.0, -1.0, 0.0]), None, fast_cfg())
    st.add(_photo(grey, torch.ones(h, w, dtype=torch.bool), 2.0), grey, (0, h, 0, w))
    st.add(_photo(bright, half, 5.0), bright, (0, h, 0, w))
    st.finish()
    assert torch.allclose(st.mu[:, :, :2], torch.full((3, h, 2), 0.5))  # both photos
    assert torch.allclose(st.mu[:, :, 2:], torch.full((3, h, 3), 0.25))  # the grey one alone
    # mean squared distance to the mean: 3 channels x 0.25^2 where both see, 0 where one does
    assert torch.allclose(st.msd[:, :2].float(), torch.full((h, 2), 0.1875)) and (st.msd[:, 2:] == 0).all()
    assert torch.equal(st.fpbest, torch.where(half, 5.0, 2.0))
    assert (st.G == 0).all() and st.tbest is None and st.level_agree is None  # flat colours, no tilt


def test_gradient_magnitude_is_zero_across_visibility_borders():
    col = torch.zeros(3, 4, 4)
    col[:, :, 2:] = 1.0  # a step between columns 1 and 2
    vis = torch.ones(4, 4, dtype=torch.bool)
    assert torch.allclose(gradient_magnitude(col, vis)[:, 2], torch.ones(4))
    vis[:, 2] = False  # the step on a visibility border
    assert (gradient_magnitude(col, vis) == 0).all()
