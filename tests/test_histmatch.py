"""HSV histogram matching: conversions, transfer functions, and two exposures of the same wall."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from difftex.compose import histmatch
from difftex.sampling import colour
from difftex.sampling.photos import PhotoSet
from difftex.sampling.texels import level_frame, resample_nearest

from analytic import make_input, make_photo, render

torch.set_num_threads(1)


def test_hsv_round_trip_and_agreement_with_skimage():
    from skimage.color import rgb2hsv

    rng = np.random.default_rng(0)
    rgb = rng.random((3, 50, 40)).astype(np.float32)
    rgb[:, :5] = 0.3  # greys: hue undefined, saturation 0
    t = torch.from_numpy(rgb)
    hsv = colour.rgb_to_hsv(t)
    ref = np.moveaxis(rgb2hsv(np.moveaxis(rgb, 0, -1)), -1, 0)
    assert np.abs(hsv.numpy() - ref).max() < 1e-5
    assert torch.allclose(colour.hsv_to_rgb(hsv), t, atol=1e-5)


def test_identity_transfer_changes_nothing_and_knots_are_monotone():
    rng = np.random.default_rng(1)
    rgb = rng.random((20, 30, 3)).astype(np.float32)
    assert np.abs(colour.apply_transfer(rgb, colour.identity_transfer()) - rgb).max() < 1e-5
    k = histmatch.quantile_knots(rng.random(1000) * 0.5, rng.random(1000))
    assert (np.diff(k[0]) > 0).all() and (np.diff(k[1]) >= 0).all()


@pytest.mark.parametrize("g", [0.25, 0.8, 1.0, 1.7, 4.0])
def test_a_gain_transfer_is_applied_as_a_multiply_that_follows_its_knots(g):
    rng = np.random.default_rng(2)
    v = torch.from_numpy(rng.random(20000).astype(np.float32))
    knots = histmatch.gain_knots(np.array([1.0]), np.array([g]), paired=True)
    assert colour.knots_gain(knots[0], knots[1]) == pytest.approx(g, rel=1e-6)
    fast = colour._apply_channel(v, knots[0], knots[1])
    poly = colour._interp(v, torch.from_numpy(knots[0]), torch.from_numpy(knots[1]))
    assert torch.allclose(fast, (g * v).clamp(0, 1))
    # the knots' polyline cuts the corner at 1 inside one knot interval (< 0.8 % of the range)
    step = float(np.diff(knots[0]).max())
    off = (fast - poly).abs() > 1e-5
    assert bool(((g * v[off] - 1).abs() < g * step).all())
    # a quantile map is not a gain, and goes through its knots
    q = histmatch.quantile_knots(rng.random(1000) ** 2, rng.random(1000))
    assert colour.knots_gain(q[0], q[1]) is None
    through = colour._interp(v, torch.from_numpy(q[0]), torch.from_numpy(q[1]))
    assert torch.allclose(colour._apply_channel(v, q[0], q[1]), through)


def matched_before_after(inp, reference: str, model: str = "gain"):
    """Every photo mapped into texel space without and with the transfers of ``reference``."""
    photos = PhotoSet.load(inp, "cpu")
    n = len(inp.photos)
    coarse = level_frame(inp.frame, min(64, max(inp.frame.shape)))
    mask = resample_nearest(inp.texel_mask, inp.frame, coarse)
    tr, ref = histmatch.mapped_transfers(
        {k: photos.map(k, coarse, mask) for k in range(n)}, n, reference, names=[p.name for p in inp.photos],
        model=model,
    )
    before = [photos.map(k, inp.frame, inp.texel_mask) for k in range(n)]
    after = [photos.map(k, inp.frame, inp.texel_mask, tr[k]) for k in range(n)]
    return before, after, ref


@pytest.mark.parametrize("model", ["gain", "quantile"])
@pytest.mark.parametrize("reference", ["best", "median", "pooled"])
def test_two_exposures_are_brought_together(reference, model):
    a, b = make_photo("a", -10.0), make_photo("b", 15.0)
    img_a = render(a)
    img_b = np.clip(render(b) * 0.6, 0, 1)  # one stop and a bit darker
    before, after, ref = matched_before_after(make_input([a, b], [img_a, img_b], long_side=64), reference, model)
    both = before[0].visible & before[1].visible
    d0 = (before[0].colour - before[1].colour).abs().mean(0)[both].mean()
    d1 = (after[0].colour - after[1].colour).abs().mean(0)[both].mean()
    # pooled matches both photos to the mixture of their histograms, content that only one sees
    # included (hence not the default): it brings them less close than a per-texel reference
    assert d1 < (0.25 if reference == "pooled" else 0.2) * d0
    if reference == "best":
        assert ref == "a"  # the more frontal photo, seeing the whole wall
        assert torch.allclose(after[0].colour, before[0].colour, atol=1e-4)  # the reference is unchanged


@pytest.mark.parametrize("model", ["gain", "quantile"])
@pytest.mark.parametrize("reference", ["best", "median"])
def test_a_dark_frontal_photo_does_not_set_the_brightness_under_median(reference, model):
    """The most frontal photo is a stop darker than two agreeing oblique ones. ``best`` makes it
    the reference (the whole texture goes dark); ``median`` matches everything to the consensus,
    so the two agreeing photos stay as they are and the dark one is brought up to them."""
    cams = [make_photo("dark", 0.0), make_photo("b", -20.0), make_photo("c", 22.0)]
    imgs = [np.clip(render(cams[0]) * 0.5, 0, 1), render(cams[1]), render(cams[2])]
    before, after, ref = matched_before_after(make_input(cams, imgs, long_side=64), reference, model)
    seen = before[0].visible & before[1].visible & before[2].visible
    bright = 0.5 * (before[1].colour + before[2].colour).mean(0)[seen].mean()
    dark = before[0].colour.mean(0)[seen].mean()
    assert dark < 0.7 * bright  # the set-up: the frontal photo really is darker
    level = [a.colour.mean(0)[seen].mean() for a in after]
    if reference == "best":
        assert ref == "dark"
        assert all(abs(v - dark) < 0.1 * dark for v in level)
    else:
        assert ref is None
        assert all(abs(v - bright) < 0.05 * bright for v in level)


def test_median_reference_is_the_same_computed_in_blocks(monkeypatch):
    """The per-texel median is computed in blocks of texels to bound memory; block size must
    not change the transfers. Also: texels seen by one photo only do not define the median."""
    rng = np.random.default_rng(3)
    h, w = 20, 30
    colours = {n: torch.from_numpy(rng.random((3, h, w)).astype(np.float32) * (0.5 + 0.2 * n)) for n in range(4)}
    visible = {n: torch.from_numpy(rng.random((h, w)) > 0.3) for n in range(4)}
    front = {n: torch.ones(h, w) for n in range(4)}
    whole, _ = histmatch.transfers_from_mapped(colours, visible, front, reference="median", min_overlap=8)
    monkeypatch.setattr(histmatch, "MEDIAN_BLOCK_VALUES", 37)
    blocked, ref = histmatch.transfers_from_mapped(colours, visible, front, reference="median", min_overlap=8)
    assert ref is None
    for n in range(4):
        assert np.array_equal(whole[n], blocked[n])
        assert not np.array_equal(whole[n], colour.identity_transfer())  # exposures differ: real maps
    single = {0: colours[0]}
    alone, _ = histmatch.transfers_from_mapped(single, {0: visible[0]}, {0: front[0]}, reference="median")
    assert np.array_equal(alone[0], colour.identity_transfer())


def test_gain_recovers_an_exposure_past_outliers_and_stays_finite_at_the_extremes():
    rng = np.random.default_rng(5)
    ref = rng.uniform(0.1, 0.8, 4000)
    src = ref / 1.5  # the photo is darker by a gain of 1.5 ...
    src[:1200] = rng.uniform(0.0, 1.0, 1200)  # ... and 30 % of its texels show an occluder
    k = histmatch.gain_knots(src, ref, paired=True)
    assert np.interp(0.4, k[0], k[1]) == pytest.approx(0.6, abs=0.01)
    assert (np.diff(k[0]) > 0).all() and (np.diff(k[1]) >= 0).all() and k[1].max() <= 1.0
    # unpaired (whole views): the ratio of the medians
    k = histmatch.gain_knots(rng.permutation(ref / 2.0), ref, paired=False)
    assert np.interp(0.2, k[0], k[1]) == pytest.approx(0.4, abs=0.02)
    # black or empty source: no gain to measure, the identity; absurd gains are capped at 2 stops
    ident = colour.identity_transfer()[0]
    assert np.array_equal(histmatch.gain_knots(np.zeros(100), ref[:100], paired=True), ident)
    assert np.array_equal(histmatch.gain_knots(np.zeros(0), ref, paired=False), ident)
    k = histmatch.gain_knots(ref * 1e-3 + 0.021, ref, paired=True)
    assert np.isfinite(k).all() and np.interp(0.1, k[0], k[1]) == pytest.approx(0.4)


def test_gain_does_not_turn_a_photos_noise_into_steps_between_tile_colours():
    """Tiles of two flat colours 0.02 apart; a photo with noise 0.01 matched onto their
    per-texel median (noise-free). The quantile map is a staircase: flat on each tile colour,
    steep between them, so a noisy value is thrown to one colour or the other (the texture's
    salt-and-pepper); one gain keeps the photo's values in order and their noise as it was."""
    rng = np.random.default_rng(6)
    ref = np.where(rng.random(20000) < 0.5, 0.50, 0.52)
    src = ref + rng.normal(0.0, 0.01, ref.size)
    for model, steepest in (("quantile", 5.0), ("gain", 1.1)):
        k = histmatch._knots(src, ref, model, paired=True)
        lo, hi = np.searchsorted(k[0], [0.45, 0.57])
        slope = np.diff(k[1][lo:hi]) / np.diff(k[0][lo:hi])
        assert (slope.max() > steepest) == (model == "quantile")
