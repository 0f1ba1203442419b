"""The comparison low-pass from the candidates' resolutions (difftex.method.witnesses)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from difftex.method.config import OptimizeConfig
from difftex.method.witnesses import candidate_footprints, misfit, resolution_spread, witness_sigma
from difftex.sampling.photos import PhotoSet

from analytic import make_input, make_photo, render


def test_misfit_is_half_a_texel_or_half_a_pixel_plus_the_registration():
    assert misfit(1.0, 0.0) == pytest.approx(0.5)
    assert misfit(8.0, 0.0) == pytest.approx(0.5)  # a photo finer than the texel: the texel's own
    assert misfit(0.25, 0.0) == pytest.approx(2.0)  # a pixel of 4 texels
    assert misfit(0.5, 1.0) == pytest.approx(math.hypot(1.0, 2.0))
    assert math.isfinite(misfit(1e-9, 1.0)) and misfit(1e9, 1.0) == pytest.approx(0.5)
    for bad in ((0.0, 1.0), (-1.0, 1.0), (1.0, -0.1)):
        with pytest.raises(ValueError):
            misfit(*bad)


def test_witness_sigma_is_zero_where_every_candidate_resolves_the_texel():
    assert witness_sigma([2.0, 3.0, 4.0, 8.0], 0.0) == 0.0
    assert witness_sigma([3.0] * 5, 1.0) == 0.0  # all alike
    assert witness_sigma([], 1.0) == 0.0 and witness_sigma([0.5], 1.0) == 0.0  # nothing to compare
    # non-positive footprints (a photo that sees nothing) do not count
    assert witness_sigma([0.0, -1.0, 0.5, 0.5, 2.0], 1.0) == witness_sigma([0.5, 0.5, 2.0], 1.0)


def test_witness_sigma_follows_the_typical_photo_not_the_finest():
    """Drone photos at 0.6 pixels per texel and one street photo at 2.6: the low-pass is about
    the drone photos' misfit, and it grows as the texels get finer (the drone photos coarser)."""
    drone = [0.6] * 6 + [2.6]
    s = witness_sigma(drone, 1.0)
    assert s == pytest.approx(math.sqrt(misfit(0.6, 1.0) ** 2 - misfit(2.6, 1.0) ** 2))
    assert 1.5 < s < 2.0
    finer = witness_sigma([f / 2 for f in drone], 1.0)  # texels of half the size
    assert finer > 1.8 * s
    assert witness_sigma(drone, 0.0) < s  # without registration error, only the sampling


def test_candidate_footprints_scale_with_distance_and_texel_size():
    near, far = make_photo("near", 0.0, dist=4.0), make_photo("far", 0.0, dist=8.0)
    inp = make_input([near, far], [render(near), render(far)], long_side=64)
    ps = PhotoSet.load(inp, "cpu")
    fp = candidate_footprints(ps, inp.frame, [0, 1])
    assert fp[0] == pytest.approx(2 * fp[1], rel=0.05)  # twice the distance, half the pixels per texel
    coarse = inp.frame.resized(32)
    fp2 = candidate_footprints(ps, coarse, [0, 1])
    assert np.allclose(fp2, [2 * f for f in fp], rtol=1e-6)  # texels twice the size


def test_consistency_px_is_checked():
    with pytest.raises(ValueError, match="consistency_px"):
        OptimizeConfig(consistency_px=-1.0)
    assert OptimizeConfig(consistency_px=1.0).consistency_px == 1.0


def test_comparing_at_the_witnesses_resolution_brings_the_texture_closer_to_the_truth():
    """One close photo that resolves the checker and four far ones that blur it (their pixels
    span several texels at 128 texels): compared at the texels' resolution the close photo
    disagrees with the far consensus at every edge; compared under the witnesses' low-pass
    (consistency_px) the texture is closer to the truth, the close photo keeping its share."""
    from analytic import fast_cfg, gt_texture, optimize

    photos = [make_photo("near", 0.0, dist=3.0, f=300.0, size=(320, 240))]
    photos += [make_photo(f"far{i}", y, dist=14.0, f=120.0) for i, y in enumerate((-20.0, -8.0, 8.0, 20.0))]
    inp = make_input(photos, [render(p) for p in photos], long_side=128)
    gt = gt_texture(inp)
    m = inp.texel_mask
    out = {}
    for px in (0.0, 1.0):
        cfg = fast_cfg(consistency_px=px, resolution_weight=4, resolution_knee=1.5, settle_sigma=0, mixed_spread=0)
        r = optimize(inp, cfg)
        near_w = ((r.idx == 0) * r.W).sum(0)[m].mean()
        err = np.abs(r.U - gt)[m].mean()
        out[px] = (near_w, err, r.stats["levels"][-1]["compare_sigma"])
    assert out[0.0][2] == 0.0 and out[1.0][2] > 2.0  # the far photos' pixels span several texels
    assert out[1.0][1] < 0.95 * out[0.0][1]
    assert out[1.0][0] > out[0.0][0] - 0.02  # the close photo keeps its share of the wall


def test_resolution_spread_is_the_finest_over_the_median_and_scale_free():
    assert resolution_spread([0.5, 0.5, 0.6, 2.4]) == pytest.approx(2.4 / 0.55)
    assert resolution_spread([3.0, 3.0]) == 1.0 and resolution_spread([]) == 1.0 and resolution_spread([2.0]) == 1.0
    assert resolution_spread([0.0, -1.0, 1.0, 4.0, 1.0]) == pytest.approx(4.0)  # non-positive ignored
    f = [0.3, 0.4, 0.35, 2.1, 0.5]
    assert resolution_spread([x * 7.5 for x in f]) == pytest.approx(resolution_spread(f))  # any texel size


def test_for_spread_swaps_in_the_mixed_values_from_the_threshold_on():
    cfg = OptimizeConfig(mixed_spread=3.0)
    assert cfg.for_spread(2.99) is cfg
    m = cfg.for_spread(3.0)
    assert (m.consistency_px, m.resolution_weight, m.resolution_knee, m.witness_resolution_weight) == (
        cfg.mixed_consistency_px, cfg.mixed_resolution_weight, cfg.mixed_resolution_knee,
        cfg.mixed_witness_resolution_weight,
    )
    # the detail per facade element: "mixed" is on for a mixed-resolution polygon ...
    assert cfg.detail == "mixed" and m.detail == "all"
    assert OptimizeConfig(mixed_spread=3.0, detail="off").for_spread(3.0).detail == "off"  # ... never if off
    five = {"consistency_px", "resolution_weight", "resolution_knee", "witness_resolution_weight", "detail"}
    rest = {k: v for k, v in dataclasses.asdict(m).items() if k not in five}
    assert rest == {k: v for k, v in dataclasses.asdict(cfg).items() if k not in five}  # nothing else moves
    assert OptimizeConfig(mixed_spread=0.0).for_spread(1e9).resolution_weight == 1.0  # never
    assert OptimizeConfig(mixed_spread=1.0).for_spread(1.0).resolution_weight == 8.0  # always
    for bad in (dict(mixed_spread=0.5), dict(mixed_spread=-1.0), dict(mixed_resolution_knee=0.9),
                dict(mixed_resolution_weight=-1.0), dict(mixed_witness_resolution_weight=None)):
        with pytest.raises(ValueError, match="mixed_"):
            OptimizeConfig(**bad)


def test_a_close_and_far_capture_is_textured_as_mixed_resolution_by_default():
    """One close photo that resolves the checker and four far ones that blur it: the defaults
    find the spread (about 12x) and texture the wall with the mixed values, exactly as if asked
    to always; never asked, the far photos' consensus outweighs the close photo and the texture
    is further from the truth."""
    from analytic import fast_cfg, gt_texture, optimize

    photos = [make_photo("near", 0.0, dist=3.0, f=300.0, size=(320, 240))]
    photos += [make_photo(f"far{i}", y, dist=14.0, f=120.0) for i, y in enumerate((-20.0, -8.0, 8.0, 20.0))]
    inp = make_input(photos, [render(p) for p in photos], long_side=128)
    gt, m = gt_texture(inp), inp.texel_mask
    out = {}
    for name, spread in (("default", OptimizeConfig().mixed_spread), ("always", 1.0), ("never", 0.0)):
        r = optimize(inp, fast_cfg(mixed_spread=spread))
        out[name] = (float(((r.idx == 0) * r.W).sum(0)[m].mean()), float(np.abs(r.U - gt)[m].mean()), r.stats)
    st = out["default"][2]
    assert st["mixed_resolution"] and st["resolution_spread"] > 8.0
    assert st["config"]["resolution_weight"] == 8.0  # the values it ran with
    assert out["default"][:2] == out["always"][:2]
    assert not out["never"][2]["mixed_resolution"] and out["never"][2]["resolution_spread"] is None
    assert out["default"][1] < 0.9 * out["never"][1], out
    assert out["default"][0] > out["never"][0] + 0.05, out


def test_photos_from_similar_distances_keep_the_defaults_blend():
    """Five photos at one distance (spread about 1): the switch stays off and the texture is the
    same bytes as with it disabled."""
    from analytic import fast_cfg, optimize

    photos = [make_photo(f"p{i}", y, dist=8.0, f=200.0) for i, y in enumerate((-24.0, -10.0, 0.0, 10.0, 24.0))]
    inp = make_input(photos, [render(p) for p in photos], long_side=96)
    a = optimize(inp, fast_cfg())
    b = optimize(inp, fast_cfg(mixed_spread=0.0))
    assert not a.stats["mixed_resolution"] and 1.0 <= a.stats["resolution_spread"] < 2.0
    assert np.array_equal(a.U, b.U)
