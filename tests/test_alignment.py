"""Alignment refinement on the analytic wall: four photos whose written poses are off by 2-2.6 px
in different directions (so no subset of them is right), rendered with their true poses."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

from difftex.compose.texturing import texture_polygon
from difftex.geometry.frames import texel_to_pixel
from difftex.method.config import ComputeConfig
from difftex.sampling.photos import Correction

from analytic import fast_cfg, gt_texture, make_input, make_photo, render

torch.set_num_threads(1)

NAMES = ["a", "b", "c", "d"]


def rotated(ph, ax: float, ay: float):
    """The photo with its rotation perturbed about the camera's x and y axes (radians)."""
    Rx = np.array([[1, 0, 0], [0, math.cos(ax), -math.sin(ax)], [0, math.sin(ax), math.cos(ax)]])
    Ry = np.array([[math.cos(ay), 0, math.sin(ay)], [0, 1, 0], [-math.sin(ay), 0, math.cos(ay)]])
    R = Rx @ Ry @ ph.R
    return dataclasses.replace(ph, R=R, t=-R @ ph.center)


@pytest.fixture(scope="module")
def scene():
    f = 300.0
    true = [
        make_photo(n, y, pitch_deg=p, size=(320, 240), f=f)
        for n, y, p in zip(NAMES, [-12.0, 12.0, -4.0, 4.0], [6.0, 6.0, -6.0, -6.0])
    ]
    imgs = [render(ph) for ph in true]
    # about 2.5 px right, 2.5 px left, 2 px down, 2 px up
    given = [
        rotated(true[0], 0, 2.5 / f),
        rotated(true[1], 0, -2.5 / f),
        rotated(true[2], 2.0 / f, 0),
        rotated(true[3], -2.0 / f, 0),
    ]
    return true, given, imgs


def run(photos, imgs, **kw):
    inp = make_input(photos, imgs, long_side=128)
    tp = texture_polygon(inp, fast_cfg(**kw), ComputeConfig(device="cpu", compile="off"))
    m = inp.texel_mask & inp.texel_visible.all(0)
    err = np.linalg.norm(tp.texture - gt_texture(inp), axis=-1)[m]
    return inp, tp, float(np.percentile(err, 95))


def reprojection_error(inp, given, true, correction: dict | None) -> float:
    """Mean distance (px) over the polygon between the corrected mapping and the true one."""
    ty, tx = np.nonzero(inp.texel_mask)
    pg, _ = texel_to_pixel(inp.frame, given, tx + 0.5, ty + 0.5)
    pt, _ = texel_to_pixel(inp.frame, true, tx + 0.5, ty + 0.5)
    if correction is not None:
        c = Correction(
            torch.tensor(correction["params"], dtype=torch.float64), tuple(correction["centre"]), correction["scale"]
        )
        pg = c.apply(torch.from_numpy(pg)).numpy()
    return float(np.linalg.norm(pg - pt, axis=1).mean())


def test_corrections_recover_the_poses_and_the_texture(scene):
    true, given, imgs = scene
    _, _, e95_true = run(true, imgs, align=False)
    _, _, e95_off = run(given, imgs, align=False)
    inp, tp, e95_aligned = run(given, imgs, align=True)
    corr = tp.stats["corrections"]
    for k, name in enumerate(NAMES):
        before = reprojection_error(inp, given[k], true[k], None)
        after = reprojection_error(inp, given[k], true[k], corr.get(name))
        assert before > 1.9 and after < 0.3, (name, before, after)
    # misregistered photos ghost (a blend) or shift (a selection); aligned, the texture is as
    # good as with the true poses. (Measured: E95 0.169 true poses, 0.249 off, 0.173 aligned;
    # with the mean-based noise, 0.169 / 0.303 / 0.174; with settle_sigma 0, 0.173 / 0.614 / 0.180.)
    assert e95_off > 1.35 * e95_true
    assert e95_aligned < 1.15 * e95_true and e95_aligned < 0.75 * e95_off


def test_correct_poses_get_no_correction(scene):
    true, _, imgs = scene
    inp, tp, _ = run(true, imgs, align=True)
    for k, name in enumerate(NAMES):
        assert reprojection_error(inp, true[k], true[k], tp.stats["corrections"].get(name)) < 0.3


def test_render_pixel_sets_follow_the_alignment_correction():
    """Render mode maps photo pixels back to texels: with a correction of f_k^i the pixel sets must
    use its inverse, so a pixel's colour is the texel-space colour of its texel."""
    from difftex.method.config import OptimizeConfig
    from difftex.method.levels import build_level
    from difftex.method.render import build_pixel_sets
    from difftex.sampling.photos import PhotoSet
    from difftex.sampling.texels import level_frame

    from analytic import photo_masks

    ph = make_photo("p", 0.0, size=(320, 240), f=300.0)
    img = np.roll(render(ph), 3, axis=1)  # the photo's content 3 px to the right of its pose's
    inp = make_input([ph], [img], long_side=96)
    boxes, crops = photo_masks(inp)
    inp = dataclasses.replace(inp, a_bbox=boxes, a_masks=crops)
    frame = level_frame(inp.frame, 96)
    cfg = OptimizeConfig(loss_mode="render", histogram_matching=False)

    def mismatch(correct: bool) -> float:
        photos = PhotoSet.load(inp, "cpu")
        if correct:
            photos.corrections[0] = Correction(
                torch.tensor([3.0, 0, 0, 0, 0, 0], dtype=torch.float64), (160.0, 120.0), 100.0
            )
        lv = build_level(photos, frame, cfg)
        pb = build_pixel_sets(photos, lv, None)
        ok = pb.slot >= 0
        K = lv.colours.shape[0]
        tex_col = lv.colours.reshape(K, 3, -1)[pb.slot[ok], :, pb.texel[ok]]
        return float((pb.colour[ok] - tex_col).abs().mean())

    # without a correction both sides read the same (shifted) content: they agree
    assert mismatch(False) < 0.03
    # with it, texel space reads the content where it is; the pixel sets must follow
    assert mismatch(True) < 0.03
