"""The LTBC-style MRF baseline: graph-cut labelling, seam leveling, and view choice on an analytic wall."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
import torch

from difftex.evaluation.mrf import MRFConfig, energy, level_gains, mrf_texture, patch_sums, run_polygon, solve_labels
from difftex.geometry.frames import look_at, map_texels, texel_mask, uv_frame
from difftex.sampling.photos import PolygonInput
from difftex.scene.camera import Photo
from difftex.scene.proxy import Polygon

from analytic import CENTRE, UP, WALL_H, WALL_W, downsample, wall_points

torch.set_num_threads(1)



def test_patch_sums_cover_partial_blocks():
    f = np.arange(35, dtype=float).reshape(5, 7)
    s = patch_sums(f, 4)
    assert s.shape == (2, 2)
    assert s[0, 0] == f[:4, :4].sum() and s[1, 1] == f[4:, 4:].sum()
    assert s.sum() == f.sum()


def brute_force(unary: np.ndarray, smooth: float) -> float:
    H, W, L = unary.shape
    best = math.inf
    for labs in itertools.product(range(L), repeat=H * W):
        best = min(best, energy(unary, np.array(labs).reshape(H, W), smooth))
    return best


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_alpha_expansion_reaches_the_potts_bound_on_small_grids(seed):
    rng = np.random.default_rng(seed)
    unary = rng.random((2, 3, 3)) * 4
    smooth = 1.0
    lab = solve_labels(unary, smooth, max_cycles=10)
    e = energy(unary, lab, smooth)
    opt = brute_force(unary, smooth)
    # alpha-expansion on a Potts model is within a factor 2 of the optimum (Boykov et al. 2001)
    assert opt - 1e-9 <= e <= 2 * opt + 1e-9
    assert e <= energy(unary, np.argmin(unary, -1), smooth) + 1e-9


def test_smoothness_flips_an_isolated_label():
    # label 0 cheaper on the left half, 1 on the right, one noisy node prefers 1 in the left half
    unary = np.zeros((4, 6, 2))
    unary[:, :3, 1] = 1.0
    unary[:, 3:, 0] = 1.0
    unary[1, 1] = [0.6, 0.0]  # prefers label 1 by 0.6, but has four label-0 neighbours
    no = solve_labels(unary, 0.0, 5)
    assert no[1, 1] == 1
    lab = solve_labels(unary, 0.5, 5)  # 4 * 0.5 = 2 > 0.6: flipping it is cheaper
    assert lab[1, 1] == 0
    assert (lab[:, :3] == 0).all() and (lab[:, 3:] == 1).all()


def test_level_gains_equalise_a_known_exposure_ratio():
    ma = np.array([0.2, 0.3, 0.4])
    g = level_gains({(0, 1): (ma, 2 * ma, 1000)}, [0, 1], prior=1e-6)
    # g0 * ma == g1 * 2 ma, and the regulariser splits the correction evenly (g0 g1 = 1)
    np.testing.assert_allclose(g[0] / g[1], 2.0, rtol=1e-4)
    np.testing.assert_allclose(g[0] * g[1], 1.0, rtol=1e-4)
    assert level_gains({}, [0, 1], 0.1)[1].tolist() == [1.0, 1.0, 1.0]


# --- the analytic wall of tests/analytic.py (plane y = 0, cameras at y < 0), with its own pattern ---


def wall() -> Polygon:
    return Polygon("wall", np.array([[0, 0, 0], [WALL_W, 0, 0], [WALL_W, 0, WALL_H], [0, 0, WALL_H]], float))


def pattern(x, z):
    chk = ((np.floor(x / 0.25) + np.floor(z / 0.25)) % 2).astype(np.float32)
    return np.stack([0.2 + 0.6 * chk, 0.3 + 0.2 * np.sin(2.0 * x), 0.25 + 0.5 * chk * (z / WALL_H)], -1).astype(
        np.float32
    )


def make_photo(name, yaw_deg, dist=6.0, f=150.0, size=(160, 120)) -> Photo:
    import pycolmap

    a = math.radians(yaw_deg)
    C = CENTRE + dist * np.array([math.sin(a), -math.cos(a), 0.0])
    R = look_at(C, CENTRE)
    w, h = size
    cam = pycolmap.Camera(model="PINHOLE", width=w, height=h, params=[f, f, w / 2, h / 2])
    return Photo(name=name, image_path=None, camera=cam, R=R, t=-R @ C, width=w, height=h, model="PINHOLE")


def render(photo: Photo, gain: float = 1.0) -> np.ndarray:
    X, hit = wall_points(photo)
    img = np.full((*hit.shape, 3), 0.5, np.float32)
    img[hit] = pattern(X[..., 0][hit], X[..., 2][hit])
    return np.clip(downsample(img, photo) * gain, 0, 1)


def make_input(photos, images, long_side=64, hide=None) -> PolygonInput:
    frame = uv_frame(wall(), UP, long_side=long_side)
    mask = texel_mask(wall(), frame)
    vis = np.stack([map_texels(frame, ph).valid & mask for ph in photos])
    for n, region in (hide or {}).items():
        vis[n] &= ~region
    by_name = {ph.name: im for ph, im in zip(photos, images)}
    return PolygonInput("wall", frame, mask, list(photos), vis, lambda ph: by_name[ph.name])


def gt(inp):
    tx, ty = inp.frame.centres()
    X = inp.frame.texel_to_world(tx, ty)
    return pattern(X[..., 0], X[..., 2])


def test_frontal_photo_wins_and_texture_matches_the_wall():
    photos = [make_photo("oblique", 55.0), make_photo("front", 0.0)]
    inp = make_input(photos, [render(p) for p in photos])
    U, wsum, dom, info = mrf_texture(inp, MRFConfig(patch=8, leveling=False, feather=0))
    m = inp.texel_mask
    assert (dom[m] == 1).mean() > 0.99  # the frontal photo is better everywhere
    err = np.abs(U - gt(inp))[m].mean()
    assert err < 0.05


def test_occluded_half_takes_the_other_photo_and_seams_are_few():
    photos = [make_photo("left", -25.0), make_photo("front", 0.0)]
    inp0 = make_input(photos, [render(p) for p in photos])
    H, W = inp0.frame.shape
    left = np.zeros((H, W), bool)
    left[:, : W // 2] = True
    inp = make_input(photos, [render(p) for p in photos], hide={1: left})
    U, wsum, dom, info = mrf_texture(inp, MRFConfig(patch=8, leveling=False, feather=0))
    m = inp.texel_mask
    assert (dom[m & left] == 0).all()  # the front photo does not see the left half
    assert (dom[m & ~left][:, None] == 1).mean() > 0.9
    assert info["seam_edges"] <= 2 * (H // 8 + 1)  # about one vertical seam, not a speckle


def test_leveling_removes_an_exposure_step_at_the_seam(tmp_path):
    photos = [make_photo("left", -20.0), make_photo("right", 20.0)]
    images = [render(photos[0], gain=1.0), render(photos[1], gain=0.6)]
    inp0 = make_input(photos, images)
    H, W = inp0.frame.shape
    left = np.zeros((H, W), bool)
    left[:, : W // 2] = True
    inp = make_input(photos, images, hide={0: ~left, 1: left & (np.arange(W)[None] < W // 2 - 8)})
    cfg = MRFConfig(patch=8, leveling=True, feather=0)
    U, wsum, dom, info = mrf_texture(inp, cfg)
    g = info["gains"]
    np.testing.assert_allclose(g["right"][0] / g["left"][0], 1 / 0.6, rtol=0.05)
    U0, *_ = mrf_texture(inp, MRFConfig(patch=8, leveling=False, feather=0))
    ref = gt(inp)
    m = inp.texel_mask

    # mean colour ratio of the two halves after leveling is that of the truth (one gain off overall)
    def ratio(img):
        return img[m & left].mean() / img[m & ~left].mean()

    assert abs(ratio(U) - ratio(ref)) < 0.5 * abs(ratio(U0) - ratio(ref))
    rep = run_polygon(inp, tmp_path / "out", cfg)
    for f in ("texture.png", "source.png", "coverage.png", "report.json"):
        assert (tmp_path / "out" / f).is_file()
    assert rep["method"] == "mrf" and rep["coverage"] == 1.0


def test_config_rejects_bad_values():
    from difftex.errors import DifftexError

    with pytest.raises(DifftexError):
        MRFConfig.from_dict({"patch": 0})
    with pytest.raises(DifftexError):
        MRFConfig.from_dict({"bogus": 1})


def test_consistency_penalty_flags_the_odd_photo_out():
    from difftex.evaluation.mrf import consistency_penalty

    means = np.full((4, 2, 2, 3), 0.5)
    means[2, 0, 0] = [0.1, 0.6, 0.1]  # an occluder (a green tree) in photo 2, patch (0, 0)
    means[1] += 0.02  # small noise stays unpunished
    ok = np.ones((4, 2, 2), bool)
    pen = consistency_penalty(means, ok, sigma=0.1)
    assert pen[2, 0, 0] == 1.0
    assert pen[[0, 1, 3], 0, 0].max() < 0.1 and pen[:, 1, 1].max() < 0.1
    ok[1:, 0, 0] = False  # fewer than 3 photos see the patch: no consensus, no penalty
    assert consistency_penalty(means, ok, 0.1)[:, 0, 0].max() == 0.0


def test_occluder_in_the_frontal_photo_is_avoided():
    photos = [make_photo("left", -20.0), make_photo("front", 0.0), make_photo("right", 20.0)]
    images = [render(p) for p in photos]
    inp0 = make_input(photos, images)
    # paint a green blob into the frontal photo over the wall's left part
    ph = photos[1]
    img = images[1].copy()
    tx, ty = inp0.frame.centres()
    X = inp0.frame.texel_to_world(tx, ty)
    blob = (np.abs(X[..., 0] - 2.0) < 0.5) & (np.abs(X[..., 2] - 1.5) < 0.6)
    pix, _ = ph.project(X[blob])
    for x, y in pix.astype(int):
        img[max(y - 1, 0) : y + 2, max(x - 1, 0) : x + 2] = [0.05, 0.6, 0.05]
    images[1] = img
    inp = make_input(photos, images)
    _, _, dom_off, _ = mrf_texture(inp, MRFConfig(patch=8, leveling=False, feather=0, consistency=0))
    _, _, dom_on, info = mrf_texture(inp, MRFConfig(patch=8, leveling=False, feather=0))
    assert (dom_off[blob] == 1).mean() > 0.9  # quality alone picks the frontal photo, blob and all
    assert (dom_on[blob] == 1).mean() < 0.2 and info["consistency_outliers"] > 0
