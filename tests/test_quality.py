"""Q = Q_a Q_c Q_r (difftex.method.quality): the resolution factor Q_r, alone and in the optimizer."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from difftex.method.quality import quality, relative_footprint, resolution_factor

from analytic import fast_cfg, make_input, make_photo, occluded_region, optimize, paint_occluder, render


def test_relative_footprint_is_one_for_the_best_photo_and_absolute_below_one_pixel():
    best = torch.tensor([4.0, 4.0, 0.5, 0.5, 0.0, 1e6])
    fp = torch.tensor([4.0, 2.0, 0.5, 0.25, 0.0, 1e6])
    out = relative_footprint(fp, best)
    # 2 px against the best's 4: half; where no photo has a pixel per texel: the footprint itself
    assert torch.allclose(out, torch.tensor([1.0, 0.5, 0.5, 0.25, 0.0, 1.0]))
    assert torch.isfinite(out).all()
    assert torch.allclose(relative_footprint(fp, None), fp.clamp(max=1.0))  # resolution_reference: pixel


def test_the_knee_counts_photos_near_the_best_as_fully_resolved():
    best = torch.tensor([4.0, 4.0, 4.0, 4.0, 0.5, 0.0])
    fp = torch.tensor([4.0, 3.0, 2.0, 1.0, 0.25, 0.0])
    out = relative_footprint(fp, best, knee=1.5)
    # within 1.5x of the best: 1; half the best's pixels: 0.75; a quarter: 0.375; no best pixel: 1.5 x fp
    assert torch.allclose(out, torch.tensor([1.0, 1.0, 0.75, 0.375, 0.375, 0.0]))
    assert torch.equal(relative_footprint(fp, best, knee=1.0), relative_footprint(fp, best))  # 1: no knee
    assert torch.allclose(relative_footprint(fp, best, knee=1e9)[:5], torch.ones(5))  # a huge knee: all alike
    from difftex.method.config import OptimizeConfig

    with pytest.raises(ValueError, match="resolution_knee"):
        OptimizeConfig(resolution_knee=0.5)


@pytest.mark.parametrize("weight", [0.0, 1.0, 2.0])
def test_quality_scales_with_the_relative_footprint(weight):
    h, w = 2, 3
    colour = torch.full((3, h, w), 0.5)
    args = (torch.ones(h, w), colour, colour.clone(), torch.zeros(h, w), torch.ones(h, w, dtype=torch.bool), 0.02)
    fp = torch.tensor([[1.0, 0.5, 0.25], [0.0, 1.0, 0.1]])
    q = quality(*args) * resolution_factor(fp, weight, args[4])
    assert torch.allclose(q, fp**weight)  # Q_a = 1, Q_c = 1: Q is Q_r; weight 0 is the paper's Q (0**0 = 1)
    unseen = torch.zeros(h, w, dtype=torch.bool)
    hidden = quality(*args[:4], unseen, 0.02) * resolution_factor(fp, weight, unseen)
    assert (hidden == 0).all()


def test_the_photo_with_more_pixels_per_texel_gets_more_of_the_blend():
    # two frontal photos of a flat wall, one twice as far: they agree everywhere, so every texel
    # keeps its Q blend; the near photo holds twice the pixels per texel, so Q_r is 1 against 0.5
    near, far = make_photo("near", 0.0, dist=6.0), make_photo("far", 0.0, dist=12.0)
    photos = [near, far]
    inp = make_input(photos, [render(ph, kind="flat") for ph in photos], long_side=64)
    m = inp.texel_mask & inp.texel_visible.all(0)

    def near_share(**kw) -> float:
        res = optimize(inp, fast_cfg(align=False, **kw))
        w_near = np.where(res.idx == 0, res.W, 0.0).sum(0)
        return float(np.median(w_near[m]))

    assert near_share() == pytest.approx(2.0 / 3.0, abs=0.03)
    assert near_share(resolution_weight=0.0) == pytest.approx(0.5, abs=0.03)  # the paper's Q: alike
    # the earlier Q_r, min(1, pixels per texel): 1 against the far photo's 0.78 pixels per texel
    assert near_share(resolution_reference="pixel") == pytest.approx(1.0 / 1.78, abs=0.03)


def test_a_close_photo_with_an_occluder_does_not_outvote_the_farther_photos():
    # the near photo holds three times the pixels per texel of the two far ones and has an
    # occluder in front of the wall: its relative Q_r makes it the blend's first choice, but as a
    # witness of what the texel shows it counts like the others (resolution_in_consensus: false),
    # so the two far photos that see past the occluder outvote it
    near = make_photo("near", 0.0, dist=6.0)
    far = [make_photo("left", -20.0, dist=18.0), make_photo("right", 20.0, dist=18.0)]
    photos = [near, *far]
    inp = make_input(photos, [paint_occluder(near, render(near)), *(render(ph) for ph in far)], long_side=32)
    reg = occluded_region(inp) & inp.texel_visible.all(0)

    def near_share(**kw) -> float:
        res = optimize(inp, fast_cfg(align=False, **kw))
        return float(np.where(res.idx == 0, res.W, 0.0).sum(0)[reg].mean())

    # the default weighting (three times the pixels per texel reaches mixed_spread: see below)
    split = near_share(mixed_spread=0.0)
    assert split < 0.1
    assert near_share(mixed_spread=0.0, resolution_in_consensus=True) > split + 0.2


def _lone_occluder_scene():
    near = make_photo("near", 0.0, dist=6.0)
    far = [make_photo("left", -20.0, dist=18.0), make_photo("right", 20.0, dist=18.0)]
    photos = [near, *far]
    inp = make_input(photos, [paint_occluder(near, render(near)), *(render(ph) for ph in far)], long_side=32)
    return inp, occluded_region(inp) & inp.texel_visible.all(0)


def test_the_lone_occluder_scene_is_a_mixed_resolution_polygon():
    """The precondition of the xfail below, kept outside it so that the xfail cannot pass for
    another reason: the close photo's three times the pixels per texel put the scene just past
    mixed_spread (3.1 against 3)."""
    inp, _ = _lone_occluder_scene()
    res = optimize(inp, fast_cfg(align=False))
    assert res.stats["mixed_resolution"] and 3.0 <= res.stats["resolution_spread"] < 3.5


@pytest.mark.xfail(strict=True, reason="known limitation of mixed-resolution polygons (docs/optimizer.md): the "
                   "steep blend Q_r starts the far photos below tau, so they neither carry weight nor let the "
                   "elimination outvote a lone close photo's occluder; a floor under their start weight or "
                   "starting from the witnesses' Q fixes this scene but lost the survey facades' detail")
def test_on_a_mixed_resolution_polygon_a_lone_close_photos_occluder_is_outvoted():
    inp, reg = _lone_occluder_scene()
    res = optimize(inp, fast_cfg(align=False))
    assert float(np.where(res.idx == 0, res.W, 0.0).sum(0)[reg].mean()) < 0.1


def test_witness_resolution_weight_keeps_the_far_witnesses_under_a_steep_q_r():
    """The blend's Q_r may be steep (resolution_weight 8: the close photo takes the texel wherever
    it is clean), but with witness_resolution_weight 1 a witness's vote falls only in proportion
    to its pixels per texel (min(1, f)): with the far photos below a pixel per texel, 0.8^8 would
    leave the three of them half the close one's vote on whether it shows an occluder. The
    witnesses' Q is then the same at resolution_weight 8 as at 1, and the blend's is not; without
    the option the witnesses follow resolution_weight."""
    from difftex.method.levels import build_level
    from difftex.sampling.photos import PhotoSet

    near = make_photo("near", 0.0, dist=6.0)  # 1.6 pixels per texel at 64 texels
    far = [make_photo(f"far{i}", yaw, dist=12.0) for i, yaw in enumerate((-20.0, -8.0, 20.0))]  # 0.8
    photos = [near, *far]
    inp = make_input(photos, [render(ph) for ph in photos], long_side=64)
    ps = PhotoSet.load(inp, "cpu")

    def level(rw: float, witness: float | None):
        return build_level(ps, inp.frame, fast_cfg(resolution_weight=rw, resolution_knee=1.5,
                                                   witness_resolution_weight=witness))

    steep, linear, plain = level(8.0, 1.0), level(1.0, 1.0), level(8.0, None)
    assert steep.fixed_slots and torch.equal(steep.idx, linear.idx)  # slot j is photo j in each
    assert torch.allclose(steep.Q, linear.Q)
    assert not torch.allclose(steep.blend_Q, linear.blend_Q)
    far_slots = steep.visible[1:]
    assert float(plain.Q[1:][far_slots].sum()) < 0.5 * float(steep.Q[1:][far_slots].sum())
    with pytest.raises(ValueError, match="witness_resolution_weight"):
        fast_cfg(witness_resolution_weight=-1.0)


def test_frontality_weight_raises_q_a_to_its_power():
    """Q = Q_a^p Q_c: p = 1 is the paper's Q_a (bit for bit), p = 0 drops the angle, p > 1 ranks
    frontal photos further above oblique ones; a grazing view (cos 0) stays at zero."""
    cos = torch.tensor([[1.0, 0.7071, 0.5, 0.0]])
    colour = torch.full((3, 1, 4), 0.4)
    mu = torch.full((3, 1, 4), 0.5)
    msd = torch.full((1, 4), 0.01)
    vis = torch.ones(1, 4, dtype=torch.bool)
    qc = torch.exp(torch.tensor(-0.5 * 0.03 / (0.01 + 0.02**2)))
    assert torch.equal(quality(cos, colour, mu, msd, vis, 0.02), quality(cos, colour, mu, msd, vis, 0.02, 1.0))
    for p in (0.0, 1.0, 3.0):
        q = quality(cos, colour, mu, msd, vis, 0.02, p)
        expected = (cos**p if p else torch.ones_like(cos)) * qc
        assert torch.allclose(q, expected, rtol=1e-5), p
    q3 = quality(cos, colour, mu, msd, vis, 0.02, 3.0)[0]
    assert q3[3] == 0.0 and q3[0] / q3[2] == pytest.approx(8.0, rel=1e-5)  # twice as frontal: 8x at p = 3
    assert float(quality(-cos, colour, mu, msd, vis, 0.02, 3.0).min()) == 0.0  # a back-facing cos is no weight


def test_frontality_weight_is_checked():
    from difftex.method.config import OptimizeConfig

    assert OptimizeConfig(frontality_weight=0.0).frontality_weight == 0.0
    with pytest.raises(ValueError, match="frontality_weight"):
        OptimizeConfig(frontality_weight=-1.0)


def test_tilt_frontality_is_the_cosine_of_the_views_tilt_alone():
    """cos of the view's angle to the normal in the wall's vertical plane: 1 for a photo level with
    the texel whatever its angle sideways, cos(tilt) for one above or below it, 0 at grazing or
    from behind; shapes are checked."""
    from difftex.method.quality import tilt_frontality

    normal = torch.tensor([0.0, -1.0, 0.0])  # the wall faces -y
    axis = torch.tensor([0.0, 0.0, 1.0])
    to_cam = []  # texel-to-camera directions
    for side, tilt in ((0, 0), (60, 0), (0, 45), (30, -60), (0, 89.999), (0, 0)):
        a, t = np.radians(side), np.radians(tilt)
        to_cam.append([np.sin(a) * np.cos(t), -np.cos(a) * np.cos(t), np.sin(t)])
    to_cam[-1] = [0.0, 1.0, 0.0]  # behind the wall
    view = -torch.tensor(to_cam, dtype=torch.float32).T.reshape(3, 1, 6)
    out = tilt_frontality(view, normal, axis)[0]
    # 30 degrees sideways and 60 below: the tilt of its projection on the vertical plane,
    # atan(sin 60 / (cos 30 cos 60)), steeper than its elevation
    c30, c60, s60 = np.cos(np.radians(30)), np.cos(np.radians(60)), np.sin(np.radians(60))
    side_and_below = c30 * c60 / np.hypot(c30 * c60, s60)
    expected = torch.tensor([1.0, 1.0, np.cos(np.radians(45)), side_and_below, 0.0, 0.0], dtype=torch.float32)
    assert torch.allclose(out, expected, atol=1e-4)
    grazing = -torch.tensor([1.0, 0.0, 0.0]).reshape(3, 1, 1)  # along the wall: no tilt defined
    assert float(tilt_frontality(grazing, normal, axis)) == 0.0
    with pytest.raises(ValueError, match="tilt_frontality"):
        tilt_frontality(view[0], normal, axis)


def _street_and_drone_wall():
    """A wall seen by two street photos (a tree painted into the left one only) and three photos
    from 40 to 50 degrees above (their median elevation: 40 degrees, so the tilt is on)."""
    import dataclasses

    photos = [make_photo("left", -30.0), make_photo("right", 30.0), make_photo("above", 0.0, pitch_deg=50.0)]
    photos += [make_photo("above_l", -20.0, pitch_deg=40.0), make_photo("above_r", 20.0, pitch_deg=45.0)]
    images = [render(ph) for ph in photos]
    images[0] = paint_occluder(photos[0], images[0])
    inp = dataclasses.replace(make_input(photos, images, long_side=64), up=np.array([0.0, 0.0, 1.0]))
    return photos, images, inp


def test_tilt_weighs_the_witnesses_where_the_level_photos_agree():
    """frontality_tilt_witness_agree k: the witnesses' Q takes the blend's tilt at the texels
    where two or more level photos agree within k sigma_c (they see the pane a drone photo sees
    the sill over), and keeps its untilted Q where one level photo shows an occluder the other
    does not (a street tree, far in front of the wall, lands on different texels in each); 0 or
    fewer than two level photos: the witnesses are never tilted."""
    import dataclasses

    from difftex.method.levels import build_level
    from difftex.sampling.photos import PhotoSet

    photos, images, inp = _street_and_drone_wall()
    up = inp.up

    def level(**kw):
        lv = build_level(PhotoSet.load(inp, "cpu"), inp.frame, fast_cfg(**kw))
        assert lv.fixed_slots  # slot j is photo j
        return lv

    plain, agree = level(frontality_tilt_witness_agree=0.0), level(frontality_tilt_witness_agree=1.0)
    assert torch.equal(level().Q, agree.Q)  # the default
    assert torch.equal(agree.blend_Q, plain.blend_Q)  # the blend is tilted alike
    both = plain.visible[0] & plain.visible[1] & plain.visible[2] & (plain.Q[2] > 1e-3)
    occ = torch.from_numpy(occluded_region(inp)) & both
    clear = both & ~torch.from_numpy(occluded_region(inp))
    clear &= ~torch.nn.functional.max_pool2d(occ[None, None].float(), 9, 1, 4)[0, 0].bool()  # away from its edge
    assert bool(occ.any()) and bool(clear.any())
    ratio = agree.Q[2] / plain.Q[2]  # the photo from above as a witness
    untilted = level(frontality_tilt=0.0, frontality_tilt_witness_agree=0.0)
    tilt = (plain.blend_Q[2] / untilted.blend_Q[2])[clear]  # the blend's tilt factor
    tilted = ratio < 0.99
    # tilted where the street photos agree (the checker's edges, sampled differently by each, aside)
    assert float(tilted[clear].float().mean()) > 0.7 and float(ratio[clear].median()) < 0.5
    assert torch.allclose(ratio[clear][tilted[clear]], tilt[tilted[clear]], rtol=1e-4)  # by that factor
    assert not bool(tilted[occ].any())  # untilted where they disagree
    assert torch.equal(level(frontality_tilt=0.0).Q, plain.Q)  # no tilt: nothing to weigh them by
    inp1 = dataclasses.replace(make_input(photos[1:], images[1:], long_side=64), up=up)
    photos1 = PhotoSet.load(inp1, "cpu")
    q1 = [build_level(photos1, inp1.frame, fast_cfg(frontality_tilt_witness_agree=k)).Q for k in (0.0, 1.0)]
    assert torch.equal(q1[0], q1[1])  # one level photo agrees with nothing
    with pytest.raises(ValueError, match="frontality_tilt_witness_agree"):
        fast_cfg(frontality_tilt_witness_agree=-1.0)


@pytest.mark.gpu
def test_tilt_and_witness_agreement_on_cuda_match_cpu():
    """The default tilt and the witnesses' agreement (streamed level-photo sums, quantiles of the
    elevation) give the same Q on CUDA as on the CPU, and the same texture from the optimizer."""
    if not torch.cuda.is_available():
        pytest.skip("no CUDA")
    from difftex.method.levels import build_level
    from difftex.sampling.photos import PhotoSet

    _, _, inp = _street_and_drone_wall()
    lv = {d: build_level(PhotoSet.load(inp, d), inp.frame, fast_cfg()) for d in ("cpu", "cuda")}
    assert torch.equal(lv["cpu"].visible, lv["cuda"].visible.cpu())
    for name in ("Q", "blend_Q"):
        a, b = getattr(lv["cpu"], name), getattr(lv["cuda"], name).cpu()
        assert torch.allclose(a, b, atol=1e-4, rtol=1e-3), name
    runs = {d: optimize(inp, fast_cfg(), device=d) for d in ("cpu", "cuda")}
    assert runs["cpu"].stats["frontality_tilt_on"] and runs["cuda"].stats["frontality_tilt_on"]
    # the tree's edge holds a few texels whose elimination is decided at the margin: the CPU alone
    # moves two of them by 0.03 when the photos change by 1e-6, so the rounding of another device
    # may too; every other texel must agree
    diff = np.abs(runs["cpu"].U - runs["cuda"].U).max(-1)
    assert float((diff > 2e-3).mean()) < 0.01 and float(diff.mean()) < 1e-3
    assert np.abs(runs["cpu"].W - runs["cuda"].W).mean() < 2e-3


def test_wall_tilt_axis_is_the_in_plane_up_of_walls_only():
    from difftex.method.quality import WALL_MAX_UP_COS, wall_tilt_axis

    up = np.array([0.0, 0.0, 1.0])
    assert np.allclose(wall_tilt_axis(np.array([0.0, -1.0, 0.0]), up), up)
    lean = np.array([0.0, -np.cos(0.3), np.sin(0.3)])  # a wall leaning back by 0.3 rad
    axis = wall_tilt_axis(lean, up)
    assert abs(float(axis @ lean)) < 1e-12 and float(axis @ up) > 0.9 and np.isclose(np.linalg.norm(axis), 1.0)
    assert wall_tilt_axis(up, up) is None  # a flat roof
    steep = np.arccos(WALL_MAX_UP_COS) - 1e-6  # a roof just past the limit
    assert wall_tilt_axis(np.array([0.0, -np.sin(steep), np.cos(steep)]), up) is None


def test_frontality_tilt_lowers_photos_from_above_on_a_wall_and_not_on_a_roof():
    """In a level's blend Q, frontality_tilt p multiplies each photo's Q at each texel by (cos(tilt) /
    the texel's most level candidate's)^p on a wall, the tilt measured from the texel to the
    photo's centre in the wall's vertical plane: a photo 50 degrees above the wall loses about
    cos(50)^3 against one level with it (40 degrees sideways, which keeps its Q). With the
    scene's up along the normal (the same plane as a roof) Q is unchanged, p = 0 is bit for bit
    the earlier Q, and the witnesses' Q has the tilt only with frontality_tilt_witnesses."""
    import dataclasses

    from difftex.method.levels import build_level
    from difftex.sampling.photos import PhotoSet

    photos = [make_photo("level", 40.0), make_photo("above", 0.0, pitch_deg=50.0)]
    inp = make_input(photos, [render(ph) for ph in photos], long_side=64)

    def level(cfg, up):
        lv = build_level(PhotoSet.load(dataclasses.replace(inp, up=up), "cpu"), inp.frame, cfg)
        assert lv.fixed_slots  # slot j is photo j
        return lv

    up = np.array([0.0, 0.0, 1.0])
    off = level(fast_cfg(frontality_tilt=0.0), up)
    on = level(fast_cfg(frontality_tilt=3.0, frontality_tilt_min_elevation=-90.0), up)
    # the default: the tilt 3 where the photos' median elevation reaches 20 degrees (here 25)
    assert torch.equal(level(fast_cfg(), up).blend_Q, on.blend_Q)
    fr = inp.frame
    X = fr.texel_to_world(*fr.centres())
    tilt = []
    for ph in photos:
        d = ph.center - X
        cn, ca = d @ fr.normal, d @ up
        tilt.append(torch.from_numpy(cn / np.hypot(cn, ca)).float())
    best = torch.maximum(*[torch.where(off.visible[j], tilt[j], 0.0) for j in range(2)])
    for j, ph in enumerate(photos):
        expected = (tilt[j] / best) ** 3  # relative to the texel's most level candidate
        seen = off.visible[j] & (off.blend_Q[j] > 1e-3)
        assert bool(seen.any())
        assert torch.allclose(on.blend_Q[j][seen] / off.blend_Q[j][seen], expected[seen], rtol=0.02), ph.name
    both = off.visible.all(0)
    ratio = [float(on.blend_Q[j][both].mean() / off.blend_Q[j][both].mean()) for j in range(2)]
    assert ratio[0] == pytest.approx(1.0) and 0.2 < ratio[1] < 0.4  # cos(50)^3 = 0.27 against a level view
    assert torch.equal(on.Q, off.Q)  # the witnesses' Q: no tilt (a street photo's occluder is still outvoted)
    witnesses = level(fast_cfg(frontality_tilt=3.0, frontality_tilt_witnesses=True), up)
    assert torch.equal(witnesses.blend_Q, on.blend_Q)
    for j in range(2):  # ... unless they are tilted too
        seen = off.visible[j] & (off.Q[j] > 1e-3)
        tilted = on.blend_Q[j][seen] / off.blend_Q[j][seen]
        assert torch.allclose(witnesses.Q[j][seen] / off.Q[j][seen], tilted, rtol=1e-4)
    # with one Q for blend and witnesses otherwise (resolution_reference: pixel), the tilt still
    # leaves the witnesses' Q alone
    pixel_off = level(fast_cfg(resolution_reference="pixel", frontality_tilt=0.0), up)
    pixel_on = level(fast_cfg(resolution_reference="pixel", frontality_tilt=3.0), up)
    assert pixel_off.Qb is None and torch.equal(pixel_on.Q, pixel_off.Q)
    assert not torch.equal(pixel_on.blend_Q, pixel_off.blend_Q)
    roof = level(fast_cfg(frontality_tilt=3.0), -fr.normal)  # up along the normal: a roof
    assert torch.equal(roof.blend_Q, off.blend_Q)
    # the photos' median elevation seen from the wall is 25 degrees (0 and 50): a limit above it
    # leaves Q bit for bit, one below it tilts as without a limit
    limited = [level(fast_cfg(frontality_tilt=3.0, frontality_tilt_min_elevation=e), up).blend_Q for e in (30.0, 20.0)]
    assert torch.equal(limited[0], off.blend_Q) and torch.equal(limited[1], on.blend_Q)
    # the same decision, as the optimizer's stats.json reports it
    from difftex.method.levels import tilt_axis

    walled = dataclasses.replace(inp, up=up)
    assert np.allclose(tilt_axis(walled, fast_cfg()), up)
    assert tilt_axis(walled, fast_cfg(frontality_tilt_min_elevation=30.0)) is None
    assert tilt_axis(walled, fast_cfg(frontality_tilt=0.0)) is None
    assert tilt_axis(dataclasses.replace(inp, up=-fr.normal), fast_cfg()) is None  # a roof
    stats = optimize(walled, fast_cfg(max_iters_per_level=(2,), min_iters_per_level=1)).stats
    assert stats["frontality_tilt_on"] is True and stats["photo_elevation_deg"] == pytest.approx(25.0, abs=1.0)
    with pytest.raises(ValueError, match="frontality_tilt"):
        fast_cfg(frontality_tilt=-1.0)
    with pytest.raises(ValueError, match="frontality_tilt_min_elevation"):
        fast_cfg(frontality_tilt_min_elevation=100.0)


def test_level_photos_agree_needs_two_photos_within_k_sigma():
    from difftex.method.quality import level_photos_agree

    a = torch.tensor([0.2, 0.4, 0.6], dtype=torch.float64)[:, None, None].expand(3, 1, 4)
    b = a + torch.tensor([0.0, 0.1, 0.5, 0.0], dtype=torch.float64)  # the 4th texel: one photo only
    count = torch.tensor([[2.0, 2.0, 2.0, 1.0]])
    s1 = a + b * (count > 1)
    s2 = (a * a).sum(0) + (b * b).sum(0) * (count > 1)
    # RMS distance to the mean: 0, 0.05 * sqrt(3), 0.25 * sqrt(3)
    assert level_photos_agree(s1, s2, count, 0.1, 1.0).tolist() == [[True, True, False, False]]
    assert level_photos_agree(s1, s2, count, 0.1, 5.0).tolist() == [[True, True, True, False]]
    assert level_photos_agree(s1, s2, count, 0.1, 1e-6).tolist() == [[True, False, False, False]]
    with pytest.raises(ValueError, match="k must be > 0"):
        level_photos_agree(s1, s2, count, 0.1, 0.0)
