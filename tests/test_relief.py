"""Relief-compensated mapping (difftex.method.relief, difftex.sampling.relief) on the analytic
relief scene (tests/analytic_relief.py): a wall with a window recessed 0.3 m and a balcony
standing 0.4 m out, photographed from 15 directions, that the proxy (one plane) lacks."""

from __future__ import annotations

import dataclasses

import analytic_relief as ar
import numpy as np
import pytest
import torch
import torch.nn.functional as F

from difftex.compose.stage_files import crop_relief_range
from difftex.compose.texturing import texture_polygon
from difftex.method.config import ComputeConfig, OptimizeConfig
from difftex.method.relief import (
    ReliefSettings,
    box_filter,
    directional_difference,
    estimate_relief,
    height_field,
    merge_steps,
    parallax_directions,
    sweep_heights,
    sweep_photos,
    zncc,
)
from difftex.sampling.crops import median_elevation, seen_from_above
from difftex.sampling.photos import PhotoSet
from difftex.sampling.relief import Relief, quantise_heights, relief_visibility, shifted_frame, texel_map_relief
from difftex.sampling.texels import texel_map

from analytic import make_photo

LONG = 128  # texels of the wall's frame: 3.1 cm texels on the 4 m wall
SWEEP = ReliefSettings(lo=-0.5, hi=0.5, long_side=LONG, window=9, smooth=5)
# the heights are recovered to within this (scene units): 1.5 steps of the sweep (its step is set
# by the photos' parallax; 0.021 m here)
HEIGHT_TOL = 0.032


@pytest.fixture(scope="module")
def scene():
    torch.set_num_threads(1)
    phs = ar.photos()
    imgs = [ar.render(p) for p in phs]
    inp = ar.make_input(phs, imgs, long_side=LONG)
    ps = PhotoSet.load(inp, "cpu", relief_range=(SWEEP.lo, SWEEP.hi))
    relief, stats = estimate_relief(ps, SWEEP)
    return inp, ps, relief, stats


def _interior(region: np.ndarray, r: int = 3) -> np.ndarray:
    """``region`` eroded by r texels (the field's edges are a window's half-width wide)."""
    t = torch.from_numpy(~region).float()[None, None]
    return ~(F.max_pool2d(t, 2 * r + 1, 1, r)[0, 0].numpy() > 0)


def _assert_recovers_the_recess_and_the_balcony(inp, relief: Relief, recess_share: float) -> None:
    """Both depths within HEIGHT_TOL (median, and on ``recess_share`` of the recess's interior and
    90 % of the balcony's), the wall at 0 on 95 %, and a handful of flat steps, not one per texel."""
    _, h = ar.truth(relief.frame)
    got = relief.heights
    recess, balcony = _interior(h < 0), _interior(h > 0)
    wall = _interior(h == 0) & _interior(inp.texel_mask)
    assert abs(np.median(got[recess]) + ar.RECESS) <= HEIGHT_TOL
    assert abs(np.median(got[balcony]) - ar.BALCONY) <= HEIGHT_TOL
    assert np.mean(np.abs(got[recess] + ar.RECESS) <= HEIGHT_TOL) >= recess_share
    assert np.mean(np.abs(got[balcony] - ar.BALCONY) <= HEIGHT_TOL) >= 0.9
    assert np.mean(got[wall] == 0) >= 0.95
    assert len(np.unique(got)) <= 6


def test_height_field_recovers_the_recess_and_the_balcony(scene):
    inp, _, relief, stats = scene
    _assert_recovers_the_recess_and_the_balcony(inp, relief, 0.9)
    assert 0.15 <= stats["relief_share"] <= 0.4


def _mapped(ps: PhotoSet, n: int, frame, heights: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    ph = ps.inp.photos[n]
    tm = texel_map_relief(frame, ph, heights, "cpu") if heights is not None else texel_map(frame, ph, "cpu")
    col = ps.samplers[n].sample(tm.pix, tm.footprint, 1).permute(1, 2, 0).numpy()
    return col, tm.valid.numpy()


def test_mapping_through_the_relief_makes_two_oblique_photos_of_the_window_agree(scene):
    inp, ps, _, _ = scene
    frame = inp.frame
    _, h = ar.truth(frame)
    names = [p.name for p in inp.photos]
    a, b = names.index("p02.png"), names.index("p12.png")  # yaw -35 pitch 30, yaw +35 pitch -15
    window = _interior(h < 0, 6)  # the pane away from the reveals (which one of them hides)
    hf = h.astype(np.float32)
    # where both photos see the pane past the reveals (checked against the geometry above)
    both = window & relief_visibility(frame, inp.photos[a], hf, inp.texel_mask)
    both &= relief_visibility(frame, inp.photos[b], hf, inp.texel_mask)
    assert both.sum() > 0.3 * window.sum()
    flat = [_mapped(ps, n, frame, None) for n in (a, b)]
    relief = [_mapped(ps, n, frame, hf) for n in (a, b)]

    truth, _ = ar.truth(frame)

    def rms(pair):
        (ca, va), (cb, vb) = pair
        m = both & va & vb
        return float(np.sqrt(((ca - cb)[m] ** 2).mean()))

    assert rms(relief) < 0.2 * rms(flat)
    # each photo through the relief shows the pane where the truth has it: what is left is its
    # resampling of the sharp mullions (at 3 cm texels, the photos hold 2-3 pixels per texel)
    for (c, v), (c0, _) in zip(relief, flat):
        err = float(np.sqrt(((c - truth)[both & v] ** 2).mean()))
        err_flat = float(np.sqrt(((c0 - truth)[both & v] ** 2).mean()))
        assert err < 0.3 * err_flat, (err, err_flat)


def test_relief_visibility_hides_the_top_of_the_recess_from_a_photo_above(scene):
    inp, _, _, _ = scene
    frame = inp.frame
    _, h = ar.truth(frame)
    ph = make_photo("above", 0.0, dist=6.0, pitch_deg=30.0, f=300.0, size=(320, 240))
    seen = relief_visibility(frame, ph, h.astype(np.float32), inp.texel_mask)
    hidden = inp.texel_mask & ~seen
    tx, ty = frame.centres()
    X = frame.texel_to_world(tx, ty)
    assert not hidden[h > 0].any()
    # on the wall, only what the balcony hides below and beside itself from a camera above its left
    # (0.4 m deep: up to 0.33 m below it, 0.11 m to its right, by the rays through its edges)
    x, z = X[..., 0][hidden & (h == 0)], X[..., 2][hidden & (h == 0)]
    assert len(x) > 0
    assert (x > ar.BOX[0] - 0.05).all() and (x < ar.BOX[1] + 0.15).all()  # + perspective: the camera is at x = 2
    assert (z < ar.BOX[3] + 1e-6).all() and (z > ar.BOX[2] - 0.35).all()
    # the wall above the window hides a band of depth x tan(elevation) of the pane's top, the
    # elevation of the ray over the window's top edge (0.3 m x 0.40 = 0.12 m)
    # (away from the pane's left edge, which its left reveal hides from a camera right of it)
    middle = (h < 0) & (np.abs(X[..., 0] - (ar.WINDOW[0] + ar.WINDOW[1]) / 2) < 0.3)
    rows = np.nonzero((hidden & middle).any(1))[0]
    band = X[..., 2][rows, 0]
    assert band.min() >= ar.WINDOW[3] - 0.3 and band.max() <= ar.WINDOW[3] + 1e-6
    frac = hidden[middle].mean()
    tan_elev = (ph.center[2] - ar.WINDOW[3]) / -ph.center[1]
    expect = ar.RECESS * tan_elev / (ar.WINDOW[3] - ar.WINDOW[2])
    assert abs(frac - expect) < 0.35 * expect


def test_texturing_with_relief_keeps_the_mullions(scene):
    inp, _, _, _ = scene
    col, h = ar.truth(inp.frame)
    base = dict(long_side_start=32, level_step=2.0, histogram_matching=False)
    relief_keys = dict(relief=True, relief_range=(SWEEP.lo, SWEEP.hi), relief_long_side=LONG, relief_window=9,
                       relief_smooth=5)
    plain = texture_polygon(inp, OptimizeConfig(**base), ComputeConfig(device="cpu"))
    comp = texture_polygon(inp, OptimizeConfig(**base, **relief_keys), ComputeConfig(device="cpu"))
    pane = _interior(h < 0, 2)
    err_plain = np.abs(plain.texture - col).mean(-1)[pane].mean()
    err_relief = np.abs(comp.texture - col).mean(-1)[pane].mean()
    assert err_relief < 0.5 * err_plain
    assert comp.heights is not None and comp.heights.shape == inp.frame.shape
    assert comp.stats["relief"]["relief_share"] > 0.1
    # the mullion's column in the texture: bright (0.95) in the truth and with relief, smeared without
    tx, _ = inp.frame.centres()
    x = inp.frame.texel_to_world(tx, np.zeros_like(tx))[..., 0]
    mull = pane & (np.abs(x - (ar.WINDOW[0] + ar.WINDOW[1]) / 2) < 0.02)
    assert comp.texture[mull].mean() > 0.7 > plain.texture[mull].mean()


def test_a_flat_wall_gets_no_relief():
    torch.set_num_threads(1)
    phs = ar.photos(n_yaw=(-30, 0, 30), pitches=(-10, 20))
    saved = ar.RECESS, ar.BALCONY
    ar.RECESS, ar.BALCONY = 1e-9, 1e-9  # boxes of no depth: the wall is its plane
    try:
        imgs = [ar.render(p) for p in phs]
    finally:
        ar.RECESS, ar.BALCONY = saved
    rng = np.random.default_rng(0)
    imgs = [np.clip(im + rng.normal(0, 0.01, im.shape).astype(np.float32), 0, 1) for im in imgs]
    inp = ar.make_input(phs, imgs, long_side=96)
    ps = PhotoSet.load(inp, "cpu", relief_range=(SWEEP.lo, SWEEP.hi))
    relief, stats = estimate_relief(ps, ReliefSettings(lo=-0.5, hi=0.5, long_side=96, window=9, smooth=5))
    assert np.mean(relief.heights[inp.texel_mask] == 0) >= 0.98
    assert relief.hidden is None or relief.flat or stats["relief_share"] < 0.02


def _banded_flat_wall(phs):
    """Renders of the plane wall with faint plaster and one dark horizontal band (a string
    course's shadow), with a camera's noise."""
    saved = ar.RECESS, ar.BALCONY, ar.colour

    def colour(x, z, surface):
        if surface != "wall":
            return saved[2](x, z, surface)
        g = 0.6 + 0.02 * np.sin(37.0 * x + 3.0 * np.sin(23.0 * z)) * np.cos(29.0 * z) - 0.35 * ((z > 2.0) & (z < 2.15))
        return np.stack([g, 0.9 * g, 0.7 * g], -1)

    ar.RECESS, ar.BALCONY, ar.colour = 1e-9, 1e-9, colour
    try:
        imgs = [ar.render(p) for p in phs]
    finally:
        ar.RECESS, ar.BALCONY, ar.colour = saved
    rng = np.random.default_rng(0)
    return [np.clip(im + rng.normal(0, 0.01, im.shape).astype(np.float32), 0, 1) for im in imgs]


def test_photos_from_above_pull_grey_plaster_to_a_band_but_not_the_parallax_sweep():
    # drone-like: every photo 35-45 degrees from above, spread left to right. At a wrong height
    # all of them move alike up the wall, so the band lands in the plaster's windows in all of
    # them and their grey values agree there; along each photo's own parallax direction (left or
    # right of the others') the band is uniform and tells nothing.
    torch.set_num_threads(1)
    phs = ar.photos(n_yaw=(-35, -20, -8, 8, 20, 35), pitches=(35, 45))
    inp = ar.make_input(phs, _banded_flat_wall(phs), long_side=96)
    ps = PhotoSet.load(inp, "cpu", relief_range=(-0.5, 0.5))
    base = ReliefSettings(lo=-0.5, hi=0.5, long_side=96, window=9, smooth=5, min_cos=0.3)
    off = {}
    for name, s in {"grey": base, "parallax": dataclasses.replace(base, structure="parallax"),
                    "parallax, semiglobal": dataclasses.replace(base, structure="parallax", regularise="semiglobal",
                                                                smooth=1),
                      "parallax, semiglobal, openings": dataclasses.replace(
                          base, structure="parallax", regularise="semiglobal", smooth=1, openings="grow")}.items():
        relief, _ = estimate_relief(ps, s, max_steps=10**9)
        off[name] = float(np.mean(relief.heights[inp.texel_mask] != 0))
    assert off["grey"] >= 0.15
    assert off["parallax"] <= 0.02 and off["parallax, semiglobal"] <= 0.02
    assert off["parallax, semiglobal, openings"] <= 0.02


@pytest.mark.parametrize("openings", ["none", "grow"])
def test_the_parallax_sweep_with_semiglobal_matching_recovers_the_recess_and_the_balcony(scene, openings):
    inp, ps, _, _ = scene
    s = dataclasses.replace(SWEEP, structure="parallax", regularise="semiglobal", smooth=1, openings=openings)
    relief, stats = estimate_relief(ps, s)
    # differences of noise-free renders carry less than their grey values: 85 %, not 90 % (the grey sweep's)
    _assert_recovers_the_recess_and_the_balcony(inp, relief, 0.85)
    assert stats.get("reason") is None


def test_parallax_directions_and_the_directional_difference():
    par = np.array([[0.0, -2.0], [0.5, -2.0], [-0.5, -2.0], [0.0, 1.0], [0.0, -2.0]])
    d = parallax_directions(par)  # median (0, -2): left, right, down; the median photos get (1, 0)
    assert np.allclose(d, [[1, 0], [1, 0], [-1, 0], [0, 1], [1, 0]])
    assert np.allclose(np.linalg.norm(d, axis=1), 1)
    ramp = torch.arange(5.0)[None, :, None] * 2.0 + torch.arange(6.0)[None, None, :]  # 2 per row, 1 per column
    x = ramp.expand(3, 5, 6).clone()
    valid = torch.ones(3, 5, 6, dtype=torch.bool)
    valid[2, 2, 3] = False
    dirs = torch.tensor([[1.0, 0.0], [0.0, 1.0], [0.6, 0.8]])
    diff, ok = directional_difference(x, valid, dirs)
    assert torch.allclose(diff[0, :-1, :-1], torch.tensor(1.0)) and torch.allclose(diff[1, :-1, :-1], torch.tensor(2.0))
    assert torch.allclose(diff[2, :-1, :-1], torch.tensor(0.6 + 1.6))
    # the last row and column have no forward neighbour; an invalid texel spoils itself and its
    # left and upper neighbours
    assert not ok[:, -1].any() and not ok[:, :, -1].any()
    assert not ok[2, 2, 3] and not ok[2, 2, 2] and not ok[2, 1, 3] and ok[2, 1, 2]


def test_the_sweep_runs_only_where_the_photos_look_from_as_high_as_asked():
    # aimed at the wall's centre from 35 and 45 degrees above: the median elevation is 40 degrees
    phs = ar.photos(n_yaw=(-20, 0, 20), pitches=(35, 45))
    # the scene's up given (estimated from photos all on one side, it tilts: levels.py)
    inp = dataclasses.replace(ar.make_input(phs, [ar.render(p) for p in phs], long_side=48), up=np.array([0, 0, 1.0]))
    ps = PhotoSet.load(inp, "cpu")
    assert median_elevation(inp, 0.5) == pytest.approx(40, abs=0.5)
    # within 41 degrees of the normal only the photos from 35 degrees above (45 * cos 0 > 41)
    assert median_elevation(inp, 0.75) == pytest.approx(35, abs=0.5)
    assert median_elevation(inp, 0.99) is None
    s = ReliefSettings(lo=-0.5, hi=0.5, long_side=48, min_elevation=45)
    relief, stats = estimate_relief(ps, s)
    assert relief.flat and "not from above" in stats["reason"] and stats["elevation"] == pytest.approx(40, abs=0.5)
    assert not seen_from_above(inp, 0.5, 45) and seen_from_above(inp, 0.5, 35) and seen_from_above(inp, 0.99, -90)
    assert not seen_from_above(inp, 0.99, 0)  # no photo within the angle: no sweep
    _, stats = estimate_relief(ps, dataclasses.replace(s, min_elevation=35))
    assert "not from above" not in str(stats.get("reason")) and stats["heights"]
    # the initialization crops the photos for the sweep's heights only where it runs
    cfg = OptimizeConfig(relief=True, relief_range=(-0.5, 0.5), relief_min_elevation=45)
    assert crop_relief_range(cfg, inp) == (0.0, 0.0)
    assert crop_relief_range(dataclasses.replace(cfg, relief_min_elevation=35), inp) == (-0.5, 0.5)
    assert crop_relief_range(dataclasses.replace(cfg, relief=False, relief_min_elevation=35), inp) == (0.0, 0.0)


def test_fewer_than_five_photos_give_a_flat_field():
    phs = ar.photos(n_yaw=(-10, 10), pitches=(-10, 20))
    inp = ar.make_input(phs, [ar.render(p) for p in phs], long_side=48)
    ps = PhotoSet.load(inp, "cpu")
    relief, stats = estimate_relief(ps, ReliefSettings(lo=-0.5, hi=0.5, long_side=48))
    assert relief.flat and stats["reason"] == "fewer than 5 photos"


def test_sweep_heights_hold_zero_and_step_with_the_parallax(scene):
    inp, ps, _, _ = scene
    which = sweep_photos(ps, inp.frame, inp.texel_mask, SWEEP.min_cos, SWEEP.max_photos)
    assert len(which) >= 3
    hs = sweep_heights(ps, which, inp.frame, SWEEP)
    assert np.any(hs == 0) and hs.min() >= SWEEP.lo - 1e-9 and hs.max() <= SWEEP.hi + 1e-9
    assert np.all(np.diff(hs) > 0) and len(hs) <= SWEEP.max_heights
    # a coarser frame (texels 4x larger) needs no finer steps than 4x these
    coarse = inp.frame.resized(LONG // 4)
    assert np.min(np.diff(sweep_heights(ps, which, coarse, SWEEP))) >= np.min(np.diff(hs)) - 1e-12


def test_box_filter_is_the_zero_padded_window_mean():
    x = torch.rand(2, 37, 53)
    for w in (3, 9, 31):
        ref = F.avg_pool2d(x[:, None], w, 1, w // 2, count_include_pad=True)[:, 0]
        assert torch.allclose(box_filter(x, w), ref, atol=1e-6)
    big = torch.full((1, 4, 2000), 1000.0) + torch.rand(1, 4, 2000)  # long rows of large values
    ref = F.avg_pool2d(big[:, None], 3, 1, 1, count_include_pad=True)[:, 0]
    assert torch.allclose(box_filter(big, 3), ref, rtol=1e-6)


def test_zncc_ignores_gain_and_offset_and_flat_windows_score_zero():
    g = torch.rand(1, 30, 30)
    v = torch.ones_like(g, dtype=torch.bool)
    r = zncc(2.5 * g + 0.3, g[0], v, 7, eps=1e-9)
    assert torch.allclose(r[:, 3:-3, 3:-3], torch.ones(1, 24, 24), atol=1e-4)
    # the default variance floor costs textured windows (variance ~0.08) under 1 %
    assert (zncc(2.5 * g + 0.3, g[0], v, 7)[:, 3:-3, 3:-3] > 0.99).all()
    assert (zncc(-g, g[0], v, 7)[:, 3:-3, 3:-3] < -0.99).all()
    flat = torch.full((1, 30, 30), 0.5)
    assert zncc(flat, flat[0], v, 7).abs().max() < 1e-3
    none = torch.zeros_like(v)
    assert (zncc(g, g[0], none, 7) == 0).all()


def test_height_field_keeps_the_plane_without_a_clear_gain():
    heights = np.array([-0.2, -0.1, 0.0, 0.1])
    cost = torch.full((4, 8, 8), 0.5)
    cost[0, :4] = 0.3  # a clear minimum at -0.2 over the top half
    cost[3, 4:] = 0.48  # a gain below the margin over the bottom half
    mask = np.ones((8, 8), bool)
    h = height_field(cost, heights, mask, margin=0.05, smooth=1)
    assert (h[:4] == -0.2).all() and (h[4:] == 0).all()
    assert (height_field(cost, heights, np.zeros((8, 8), bool), 0.05, 1) == 0).all()
    with pytest.raises(ValueError, match="include 0"):
        height_field(cost, heights + 0.05, mask, 0.05, 1)


def test_merge_steps_snaps_near_heights_and_rare_ones():
    h = np.zeros((10, 10), np.float32)
    h[:5, :5] = -0.3
    h[0, :3] = -0.28  # within tol of -0.3
    h[9, 9] = 0.5  # one texel: under min_share
    out = merge_steps(h, np.ones_like(h, bool), tol=0.05, min_share=0.02)
    assert set(np.unique(out)) == {np.float32(-0.3), np.float32(0.0)}
    assert out[9, 9] == 0.0 and out[0, 0] == np.float32(-0.3)


def test_quantise_heights_and_texel_map_relief_of_a_constant_field():
    h = np.linspace(-0.5, 0.5, 400, dtype=np.float32).reshape(20, 20)
    q = quantise_heights(h, 8)
    assert len(np.unique(q)) <= 8 and np.abs(q - h).max() <= 1.0 / 6 / 2 + 1e-6
    with pytest.raises(ValueError):
        quantise_heights(h, 1)
    inp = ar.make_input(ar.photos(n_yaw=(20,), pitches=(10,)), [np.zeros((240, 320, 3), np.float32)], long_side=32)
    ph = inp.photos[0]
    const = np.full(inp.frame.shape, -0.25, np.float32)
    a = texel_map_relief(inp.frame, ph, const)
    b = texel_map(shifted_frame(inp.frame, -0.25), ph)
    assert torch.allclose(a.pix, b.pix) and torch.equal(a.valid, b.valid)
    with pytest.raises(ValueError, match="do not match"):
        texel_map_relief(inp.frame, ph, const[:-1])


def test_relief_and_settings_check_their_input():
    frame = ar.make_input(ar.photos(n_yaw=(0,), pitches=(0,)), [np.zeros((240, 320, 3), np.float32)], 16).frame
    with pytest.raises(ValueError, match="match"):
        Relief(frame, np.zeros((3, 3), np.float32))
    with pytest.raises(ValueError, match="finite"):
        Relief(frame, np.full(frame.shape, np.nan, np.float32))
    for bad in (dict(lo=0.1, hi=0.5), dict(lo=0.0, hi=0.0), dict(lo=-1, hi=1, window=4), dict(lo=-1, hi=1, smooth=0),
                dict(lo=-1, hi=1, share=0.0), dict(lo=-1, hi=1, share=1.5), dict(lo=-1, hi=1, p1=0.6, p2=0.5),
                dict(lo=-1, hi=1, p1=-0.1), dict(lo=-1, hi=1, regularise="median"), dict(lo=-1, hi=1, structure="rgb"),
                dict(lo=-1, hi=1, openings="rectangle"),
                dict(lo=-1, hi=1, min_elevation=91.0)):
        with pytest.raises(ValueError):
            ReliefSettings(**bad)
    with pytest.raises(ValueError):
        OptimizeConfig(relief=True, relief_range=(0.2, 0.4))
    with pytest.raises(ValueError):
        OptimizeConfig(relief_regularise="graph-cut")
    with pytest.raises(ValueError):
        OptimizeConfig(relief_openings="rectangle")
    assert OptimizeConfig(relief_range=[-0.3, 0.2]).relief_range == (-0.3, 0.2)


@pytest.mark.gpu
def test_relief_on_cuda_matches_cpu(scene):
    if not torch.cuda.is_available():
        pytest.skip("no CUDA")
    inp, _, relief, _ = scene
    ps = PhotoSet.load(inp, "cuda", relief_range=(SWEEP.lo, SWEEP.hi))
    on_gpu, _ = estimate_relief(ps, SWEEP)
    assert np.mean(on_gpu.heights == relief.heights) >= 0.98
    assert on_gpu.hidden is not None and relief.hidden is not None
    assert np.mean(on_gpu.hidden == relief.hidden) >= 0.99


# ------------------------------------------------------------------------------------------
# Export: the height field and its normal map beside the texture, and in the GLB


def test_normal_map_of_flat_ramp_and_step():
    from difftex.compose.outputs import normal_map

    flat = normal_map(np.zeros((4, 5), np.float32), 0.1)
    assert np.allclose(flat, [0.5, 0.5, 1.0])
    # rising along x (texel columns) by one texel size per texel: a 45 degree slope facing -x
    ramp = normal_map(np.tile(np.arange(6, dtype=np.float32) * 0.1, (3, 1)), 0.1)
    n = ramp * 2 - 1
    assert np.allclose(n[..., 0], -np.sqrt(0.5), atol=1e-6) and np.allclose(n[..., 2], np.sqrt(0.5), atol=1e-6)
    # rising down the image (texel rows) tilts the normal towards glTF's +Y (up the image)
    down = normal_map(np.tile((np.arange(6, dtype=np.float32) * 0.1)[:, None], (1, 3)), 0.1) * 2 - 1
    assert (down[..., 1] > 0.7).all()
    step = normal_map(np.array([[0, 0, -0.3, -0.3]] * 3, np.float32), 0.01) * 2 - 1
    assert np.allclose(np.linalg.norm(step, axis=-1), 1, atol=1e-5) and (step[:, 1:3, 0] > 0.99).all()
    assert np.allclose(normal_map(np.zeros((1, 1), np.float32), 1.0), [0.5, 0.5, 1.0])
    with pytest.raises(ValueError):
        normal_map(np.zeros((3, 3), np.float32), 0.0)


def test_finish_writes_height_and_normal_and_removes_them_without_relief(tmp_path):
    from difftex.compose.outputs import finish_polygon, read_relief, write_composite
    from difftex.scene.files import read_image

    H, W = 6, 8
    U = np.full((H, W, 3), 0.5, np.float32)
    mask = np.ones((H, W), bool)
    h = np.zeros((H, W), np.float32)
    h[2:4, 3:6] = -0.25
    comp = tmp_path / "composite.npz"
    write_composite(comp, U, mask, mask, np.zeros((H, W), int), ["a.png"], {}, relief=(h, 0.05))
    got, s = read_relief(comp)
    assert np.array_equal(got, h) and s == 0.05
    out = tmp_path / "tex"
    finish_polygon(comp, out)
    assert np.allclose(read_image(out / "height.exr")[..., 0], h)
    normal = read_image(out / "normal.png")
    assert normal.shape == (H, W, 3) and np.allclose(normal[0, 0], [0.5, 0.5, 1.0], atol=1 / 255)
    write_composite(comp, U, mask, mask, np.zeros((H, W), int), ["a.png"], {})
    assert read_relief(comp) is None
    finish_polygon(comp, out)
    assert not (out / "height.exr").exists() and not (out / "normal.png").exists()


def test_the_glb_carries_the_normal_map(tmp_path):
    import trimesh

    from difftex.export.assemble import AssembleConfig, PolygonTexture, assemble
    from difftex.geometry.frames import texel_mask, uv_frame
    from difftex.scene.proxy import Polygon

    poly = Polygon("w", np.array([[0, 0, 0], [4.0, 0, 0], [4.0, 0, 3], [0, 0, 3]]))
    frame = uv_frame(poly, np.array([0.0, 0, 1]), long_side=40)
    tex = np.full((*frame.shape, 3), 0.4, np.float32)
    normal = np.broadcast_to(np.array([0.9, 0.5, 0.7], np.float32), (*frame.shape, 3)).copy()
    items = [PolygonTexture(poly, frame, tex, texel_mask(poly, frame), 1.0, 3, normal=normal)]
    summary = assemble(items, tmp_path, AssembleConfig(padding=2))
    assert summary["normal_pages"] == ["model_atlas0_normal.png"]
    geom = next(iter(trimesh.load(tmp_path / "model.glb").geometry.values()))
    page = np.asarray(geom.visual.material.normalTexture.convert("RGB"), np.float32) / 255
    pl = summary["polygons"][0]["rect"]
    assert np.allclose(page[pl[1] + 5, pl[0] + 5], [0.9, 0.5, 0.7], atol=2 / 255)
    plain = assemble([PolygonTexture(poly, frame, tex, texel_mask(poly, frame), 1.0, 3)], tmp_path / "b")
    assert "normal_pages" not in plain and not list((tmp_path / "b").glob("*_normal.png"))


def test_photos_that_agree_on_nothing_keep_the_plane():
    """Each photo of pure, independent noise: no height makes them agree, whatever chance finds."""
    torch.set_num_threads(1)
    phs = ar.photos(n_yaw=(-30, 0, 30), pitches=(-10, 20))
    rng = np.random.default_rng(1)
    imgs = [rng.random((240, 320, 3)).astype(np.float32) for _ in phs]
    inp = ar.make_input(phs, imgs, long_side=64)
    ps = PhotoSet.load(inp, "cpu", relief_range=(SWEEP.lo, SWEEP.hi))
    relief, stats = estimate_relief(ps, ReliefSettings(lo=-0.5, hi=0.5, long_side=64, window=9, smooth=5))
    assert np.mean(relief.heights[inp.texel_mask] == 0) >= 0.95, stats


def test_the_split_stages_give_the_one_process_relief_texture(scene):
    from difftex.compose.stage_files import compose_polygon, initialize_polygon
    from difftex.compose.texturing import optimize_photos

    inp = scene[0]
    cfg = OptimizeConfig(long_side_start=32, level_step=2.0, histogram_matching=False, relief=True,
                         relief_range=(SWEEP.lo, SWEEP.hi), relief_long_side=LONG, relief_window=9, relief_smooth=5)
    one = texture_polygon(inp, cfg, ComputeConfig(device="cpu"))
    # the crops hold the rectangle shifted to both ends of the sweep, as PhotoSet.load's do
    crops, stats = initialize_polygon(inp, cfg)
    photos = PhotoSet.from_crops(inp, crops, "cpu", cfg.supersample)
    opt = optimize_photos(photos, cfg, ComputeConfig(device="cpu"), read_stats=stats)
    U, _, _ = compose_polygon(opt)
    assert opt.heights is not None and np.array_equal(opt.heights, one.heights)
    assert np.array_equal(U, one.texture)
