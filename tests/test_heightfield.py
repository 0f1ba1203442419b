"""Height fields from dense geometry (difftex.geometry.heightfield) and texturing through them
(difftex.compose.texturing.dense_relief), on the analytic relief scene (tests/analytic_relief.py):
a wall with a window recessed 0.3 m and a balcony 0.4 m out, which its proxy (one plane) lacks."""

from __future__ import annotations

import analytic_relief as ar
import numpy as np
import pytest
import torch

from difftex.compose.texturing import texture_polygon
from difftex.geometry.dense import DenseMesh
from difftex.geometry.heightfield import (
    HeightFieldConfig,
    cloud_evidence,
    find_layers,
    height_field,
    mesh_evidence,
)
from difftex.method.config import ComputeConfig, OptimizeConfig
from difftex.sampling.texels import level_frame

LONG = 128  # 3.1 cm texels on the 4 m wall
CFG = HeightFieldConfig(range=(-0.5, 0.5))
NOISE = 0.015  # a dense cloud's noise along the viewing ray, metres (COLMAP's on a drone survey: 1-2 cm)


def surface_points(step: float, rng: np.random.Generator, glass: bool = False) -> np.ndarray:
    """Points every ``step`` metres on the detailed wall's front-facing surfaces (the wall but its
    opening, the pane's frame and mullions (the glass too with ``glass``), the reveals, the
    balcony's front and sides), jittered within their cell. World frame: y = -height."""
    x, z = np.meshgrid(np.arange(0, ar.WALL_W, step), np.arange(0, ar.WALL_H, step))
    x = x.ravel() + rng.uniform(0, step, x.size)
    z = z.ravel() + rng.uniform(0, step, z.size)
    wx0, wx1, wz0, wz1 = ar.WINDOW
    win = (x > wx0) & (x < wx1) & (z > wz0) & (z < wz1)
    box = (x > ar.BOX[0]) & (x < ar.BOX[1]) & (z > ar.BOX[2]) & (z < ar.BOX[3])
    bar = ar.colour(x, z, "pane")[:, 0] > 0.9  # the frame and the mullions: glass is not reconstructed
    keep = ~win | bar | glass
    y = np.where(win, ar.RECESS, np.where(box, -ar.BALCONY, 0.0))
    pts = [np.stack([x, y, z], 1)[keep]]
    for _, axis, value, ranges in ar.surfaces()[1:]:  # reveals and balcony sides, one row of points per step
        a, b = sorted(ranges)
        (a0, a1), (b0, b1) = ranges[a], ranges[b]
        ga, gb = np.meshgrid(np.arange(a0, a1, step / 2), np.arange(b0, b1, step / 2))
        p = np.zeros((ga.size, 3))
        p[:, axis], p[:, a], p[:, b] = value, ga.ravel(), gb.ravel()
        pts.append(p)
    return np.concatenate(pts)


def noisy(points: np.ndarray, rng: np.random.Generator, sigma: float, outliers: float = 0.0) -> np.ndarray:
    """Noise along the rays of a camera 6 m in front of the wall, and a share of wild outliers."""
    cam = np.array([ar.WALL_W / 2, -6.0, ar.WALL_H / 2])
    ray = points - cam
    ray /= np.linalg.norm(ray, axis=1, keepdims=True)
    out = points + rng.normal(0, sigma, (len(points), 1)) * ray
    wild = rng.random(len(points)) < outliers
    out[wild, 1] += rng.uniform(-0.5, 0.5, wild.sum())
    return out


def box_mesh() -> DenseMesh:
    """The detailed wall as triangles: a grid of 2 cm quads, each at its true height."""
    step = 0.02
    x, z = np.meshgrid(np.arange(0, ar.WALL_W, step), np.arange(0, ar.WALL_H, step))
    xc, zc = x + step / 2, z + step / 2
    win = (xc > ar.WINDOW[0]) & (xc < ar.WINDOW[1]) & (zc > ar.WINDOW[2]) & (zc < ar.WINDOW[3])
    box = (xc > ar.BOX[0]) & (xc < ar.BOX[1]) & (zc > ar.BOX[2]) & (zc < ar.BOX[3])
    y = np.where(win, ar.RECESS, np.where(box, -ar.BALCONY, 0.0)).ravel()
    x, z = x.ravel(), z.ravel()
    corners = [(0, 0), (step, 0), (step, step), (0, step)]
    V = np.stack([np.stack([x + dx, y, z + dz], 1) for dx, dz in corners], 1).reshape(-1, 3)
    base = 4 * np.arange(len(x))[:, None]
    F = np.concatenate([base + [0, 1, 2], base + [0, 2, 3]])
    return DenseMesh(V, F)


@pytest.fixture(scope="module")
def wall():
    torch.set_num_threads(1)
    inp = ar.make_input(ar.photos(), [np.zeros((1, 1, 3), np.float32)] * 15, long_side=LONG)
    return inp.frame, inp.texel_mask


def _accuracy(field: np.ndarray, truth: np.ndarray, tol: float) -> tuple[float, float, float]:
    """(share of recess texels found, of balcony texels found, of plain wall given relief)."""
    rec = truth < 0
    bal = truth > 0
    found = [float((np.abs(field[m] - truth[m]) < tol).mean()) for m in (rec, bal)]
    return found[0], found[1], float((np.abs(field[truth == 0]) > tol).mean())


def test_a_mesh_gives_the_true_field(wall):
    frame, mask = wall
    _, truth = ar.truth(frame)
    field, stats = height_field(frame, mask, CFG, mesh=box_mesh())
    found_r, found_b, false = _accuracy(field, truth, 0.01)
    # a texel straddling a box's edge may take either side: one texel ring of the two boxes
    assert found_r > 0.93 and found_b > 0.93 and false < 0.01
    assert sorted(float(k) for k in stats["layers"]) == pytest.approx([-ar.RECESS, 0.0, ar.BALCONY], abs=1e-3)


def test_a_noisy_cloud_without_glass_gives_the_field_within_a_texel(wall):
    """1.5 cm noise, 3 % wild outliers, no point on the glass: the pane's texels take their
    frame's layer, the field is within a texel (3.1 cm) of the truth but along the boxes' edges."""
    frame, mask = wall
    _, truth = ar.truth(frame)
    rng = np.random.default_rng(0)
    pts = noisy(surface_points(0.02, rng), rng, NOISE, outliers=0.03)
    field, stats = height_field(frame, mask, CFG, points=pts)
    found_r, found_b, false = _accuracy(field, truth, frame.texel_size)
    # false relief: at most the texel ring around the two boxes (2.5 % of the wall)
    assert found_r > 0.9 and found_b > 0.9 and false < 0.03
    assert stats["noise"] == pytest.approx(NOISE, rel=0.5)
    assert len(stats["layers"]) == 3


def test_without_evidence_the_plane_stays(wall):
    frame, mask = wall
    rng = np.random.default_rng(1)
    pts = surface_points(0.02, rng)
    left = pts[pts[:, 0] < 2.0]  # only the window's half of the wall has points
    field, stats = height_field(frame, mask, CFG, points=left)
    tx, _ = frame.centres()
    x = frame.texel_to_world(tx, np.zeros_like(tx))[..., 0]
    assert not field[x > 2.2].any()  # the balcony's half: no evidence, the plane
    assert (field[(x < 1.7) & (ar.truth(frame)[1] < 0)] < -0.25).mean() > 0.9
    empty, st = height_field(frame, mask, CFG, points=np.zeros((0, 3)))
    assert not empty.any() and st["evidence_share"] == 0


def test_points_outside_the_range_or_the_rectangle_are_no_evidence(wall):
    frame, _ = wall
    P = frame.texel_to_world(np.array([5.5, 5.5, -3.0, 5.5]), np.array([5.5, 5.5, 5.5, 5.5]))
    P = P + np.array([0.1, 0.2, 0.0, 2.0])[:, None] * frame.normal
    med, weight, _ = cloud_evidence(P, frame, -0.5, 0.5)
    assert np.isfinite(med).sum() == 1 and weight[5, 5] == pytest.approx(2 / 3)
    assert med[5, 5] == pytest.approx(0.1)  # the lower median of two


def test_layers_need_support_and_keep_the_plane():
    rng = np.random.default_rng(2)
    wall = rng.normal(0.004, 0.005, 5000)
    recess = rng.normal(-0.3, 0.005, 800)
    stray = rng.uniform(-0.5, 0.5, 10)  # too few for a layer
    layers = find_layers(np.concatenate([wall, recess, stray]), 0.03, 4, -0.5, 0.5)
    assert layers == pytest.approx([-0.3, 0.0], abs=0.005)
    assert 0.0 in find_layers(np.full(100, 0.25), 0.03, 4, -0.5, 0.5)  # the plane for texels without evidence


def test_mesh_rays_see_the_front_most_surface(wall):
    frame, _ = wall
    small = level_frame(frame, 32)
    mesh = box_mesh()
    h = mesh_evidence(mesh, small, -0.5, 0.5)
    assert np.isfinite(h).all()
    assert h.max() == pytest.approx(ar.BALCONY, abs=1e-4) and h.min() == pytest.approx(-ar.RECESS, abs=1e-4)
    # a range that stops short of the recess: its texels have no evidence
    assert np.isnan(mesh_evidence(mesh, small, -0.2, 0.5)).any()


def test_texturing_through_the_measured_field_keeps_the_mullions(wall):
    """The photos mapped through the field from a noisy cloud: the pane's error against the
    truth at most half the plane's, and the mullion is bright where the plane smears it."""
    phs = ar.photos()
    inp = ar.make_input(phs, [ar.render(p) for p in phs], long_side=LONG)
    col, h = ar.truth(inp.frame)
    rng = np.random.default_rng(3)
    field, _ = height_field(inp.frame, inp.texel_mask, CFG, points=noisy(surface_points(0.02, rng), rng, NOISE))
    cfg = OptimizeConfig(long_side_start=32, level_step=2.0, histogram_matching=False)
    plain = texture_polygon(inp, cfg, ComputeConfig(device="cpu"))
    inp.dense = (inp.frame, field)
    dense = texture_polygon(inp, cfg, ComputeConfig(device="cpu"))
    pane = (h < 0) & (field < 0)
    err_plain = np.abs(plain.texture - col).mean(-1)[pane].mean()
    err_dense = np.abs(dense.texture - col).mean(-1)[pane].mean()
    assert err_dense < 0.5 * err_plain
    assert dense.stats["relief"]["source"] == "dense" and dense.stats["relief"]["relief_share"] > 0.1
    tx, _ = inp.frame.centres()
    x = inp.frame.texel_to_world(tx, np.zeros_like(tx))[..., 0]
    mull = pane & (np.abs(x - (ar.WINDOW[0] + ar.WINDOW[1]) / 2) < 0.02)
    assert dense.texture[mull].mean() > 0.7 > plain.texture[mull].mean()


def test_config_checks():
    with pytest.raises(Exception, match="range must hold 0"):
        HeightFieldConfig(range=(0.1, 0.5))
    with pytest.raises(Exception, match="long_side"):
        HeightFieldConfig(long_side=2)


def test_a_window_whose_glass_has_no_points_takes_its_frames_layer_not_the_walls(wall):
    """A sparse cloud (6 cm apart: drone photos' resolution) with no point on the glass and the
    pane's frame and mullions its only points: the window is a hole in the wall's evidence, and
    it takes the layer its few points vote for, behind the wall."""
    frame, mask = wall
    _, truth = ar.truth(frame)
    rng = np.random.default_rng(4)
    field, stats = height_field(frame, mask, CFG, points=noisy(surface_points(0.06, rng), rng, NOISE))
    found_r, found_b, false = _accuracy(field, truth, frame.texel_size)
    assert found_r > 0.85 and found_b > 0.85 and false < 0.03
    assert stats["noise"] == pytest.approx(NOISE, rel=0.5)


def test_a_hole_takes_a_layer_behind_the_wall_only():
    """hole_evidence: a hole amid the wall's evidence with points 0.3 behind the wall on its rim
    takes that layer; one with points 0.4 in front (an occluder's) stays without evidence; one
    with too few points for its size too."""
    from difftex.geometry.frames import UVFrame
    from difftex.geometry.heightfield import hole_evidence

    fr = UVFrame(np.zeros(3), np.array([1.0, 0, 0]), np.array([0, 0, -1.0]), np.array([0, -1.0, 0]), 0.1, 60, 20)
    layers = np.array([-0.3, 0.0, 0.4])
    evidence = np.zeros(fr.shape, np.float32)
    weight = np.ones(fr.shape)
    for x0 in (5, 25, 45):  # three 10 x 10 holes
        weight[5:15, x0 : x0 + 10] = 0
        evidence[5:15, x0 : x0 + 10] = np.nan
    pts = [fr.texel_to_world(np.full(20, 10.5), np.linspace(5, 15, 20)) + h * fr.normal for h in (-0.3, 0.4)]
    pts = np.concatenate([pts[0], pts[1] + 20 * 0.1 * fr.e_u,  # 20 points behind in hole 1, 20 in front in hole 2
                          fr.texel_to_world(np.array([50.5, 51.5]), np.array([10.5, 10.5])) - 0.3 * fr.normal])
    ev, w = hole_evidence(pts, fr, np.ones(fr.shape, bool), evidence, weight, layers, 0.05, -1, 1)
    assert (ev[5:15, 5:15] == -0.3).all() and (w[5:15, 5:15] > 0).all()
    assert (w[5:15, 25:35] == 0).all() and (w[5:15, 45:55] == 0).all()  # in front; 2 points for 100 texels
