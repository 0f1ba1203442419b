"""The pinhole z-buffer gives the id buffer that exact ray casting gives, and steps aside where it cannot."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pycolmap
import pytest

from difftex.geometry.frames import look_at
from difftex.geometry.raycast import ProxyCaster, id_buffer
from difftex.geometry.zbuffer import Pieces, _convex, zbuffer
from difftex.scene.camera import Photo
from difftex.scene.proxy import Polygon, Proxy


def _photo(centre, target, f=300.0, size=(320, 240), model="PINHOLE") -> Photo:
    C = np.asarray(centre, float)
    R = look_at(C, np.asarray(target, float))
    w, h = size
    params = [f, f, w / 2 + 3.3, h / 2 - 2.1] if model == "PINHOLE" else [f, w / 2, h / 2, -0.05]
    cam = pycolmap.Camera(model=model, width=w, height=h, params=params)
    return Photo(name="p", image_path=Path("p.png"), camera=cam, R=R, t=-R @ C, width=w, height=h, model=model)


def _proxy() -> Proxy:
    """An L-shaped wall with a window (triangulated), a convex wall behind it, and a roof slope
    (convex pieces), some of them hiding others from the cameras."""
    L = np.array([[0, 0, 0], [4, 0, 0], [4, 0, 1.5], [1.5, 0, 1.5], [1.5, 0, 3], [0, 0, 3]], float)
    window = np.array([[0.5, 0, 1.0], [0.5, 0, 2.0], [1.0, 0, 2.0], [1.0, 0, 1.0]], float)  # clockwise from outside
    back = np.array([[-1, 2, 0], [5, 2, 0], [5, 2, 4], [-1, 2, 4]], float)
    roof = np.array([[0, 0, 3], [1.5, 0, 3], [1.5, 1.5, 4], [0, 1.5, 4]], float)
    polys = [Polygon("L", L, (window,)), Polygon("back", back), Polygon("roof", roof)]
    return Proxy(polys, Path("proxy.obj"))


def test_convex_pieces():
    sq = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float)
    assert _convex(sq) and _convex(sq[::-1])
    assert _convex(np.array([[0, 0], [0.5, 0], [1, 0], [1, 1], [0, 1]], float))  # a collinear vertex
    assert not _convex(np.array([[0, 0], [2, 0], [2, 1], [1, 1], [1, 2], [0, 2]], float))  # L
    pieces = Pieces.of(_proxy())
    # the L with its window is ear-clipped; the back wall and the roof are one piece each
    assert (pieces.polygon == 0).sum() >= 6 and (pieces.polygon == 1).sum() == 1 and (pieces.polygon == 2).sum() == 1


@pytest.mark.parametrize("stride", [1, 3])
@pytest.mark.parametrize("centre", [(2.0, -6.0, 1.5), (-3.0, -4.0, 3.5), (7.0, -2.5, 0.5), (2.0, -0.8, 1.5)], ids=str)
def test_zbuffer_equals_exact_ray_casting(centre, stride):
    """Same polygon and distance per pixel as the numpy caster (float64 ray-plane + point in
    polygon), up to pixels whose ray grazes an edge; the window's pixels see the back wall."""
    proxy = _proxy()
    ph = _photo(centre, (2.0, 0.0, 1.5))
    got = zbuffer(Pieces.of(proxy), ph, stride)
    assert got is not None
    ids, dist = got
    ref_ids, ref_dist = id_buffer(ProxyCaster.build(proxy, "numpy"), ph, stride)
    assert ids.shape == ref_ids.shape == (math.ceil(240 / stride), math.ceil(320 / stride))
    assert len(np.unique(ref_ids[ref_ids >= 0])) >= 2
    assert (ids != ref_ids).mean() < 2e-3
    same = (ids == ref_ids) & (ids >= 0)
    np.testing.assert_allclose(dist[same], ref_dist[same], rtol=1e-5)
    assert np.isinf(dist[ids < 0]).all()


def test_window_pixels_see_the_wall_behind():
    proxy = _proxy()
    ph = _photo((0.75, -5.0, 1.5), (0.75, 0.0, 1.5))
    ids, _ = zbuffer(Pieces.of(proxy), ph)
    pix, _ = ph.project(np.array([[0.75, 0.0, 1.5], [3.0, 0.0, 0.75]]))
    (xw, yw), (xl, yl) = pix.astype(int)
    assert ids[yw, xw] == 1  # through the window: the back wall
    assert ids[yl, xl] == 0  # the L wall


def test_zbuffer_steps_aside_for_distortion_and_the_camera_plane():
    proxy = _proxy()
    pieces = Pieces.of(proxy)
    assert zbuffer(pieces, _photo((2.0, -6.0, 1.5), (2.0, 0.0, 1.5), model="SIMPLE_RADIAL")) is None
    # a camera between the L wall and the back wall, looking along the wall: the back wall and
    # the roof cross its plane
    inside = _photo((2.0, 1.0, 2.0), (6.0, 1.0, 2.0))
    assert zbuffer(pieces, inside) is None
    # id_buffer then casts every ray, with the exact answer
    auto, _ = id_buffer(ProxyCaster.build(proxy), inside)
    exact, _ = id_buffer(ProxyCaster.build(proxy, "numpy"), inside)
    assert (auto >= 0).any() and (auto != exact).mean() < 2e-3
    # every piece behind the camera: nothing is seen, and nothing fails
    away = _photo((2.0, -6.0, 1.5), (2.0, -12.0, 1.5))
    ids, dist = zbuffer(pieces, away)
    assert (ids < 0).all() and np.isinf(dist).all()


def test_auto_caster_rasterises_pinhole_photos(monkeypatch):
    """The default caster takes the z-buffer for a pinhole photo (no ray is cast)."""
    proxy = _proxy()
    caster = ProxyCaster.build(proxy)
    ph = _photo((2.0, -6.0, 1.5), (2.0, 0.0, 1.5))

    def no_cast(*a, **k):
        raise AssertionError("a ray was cast")

    monkeypatch.setattr(caster, "cast", no_cast)
    ids, _ = id_buffer(caster, ph)
    assert (ids >= 0).any()
    far = dataclasses.replace(ph, t=ph.t + np.array([0.0, 0.0, 1000.0]))
    ids, _ = id_buffer(caster, far)  # the proxy a few pixels wide
    assert 0 < (ids >= 0).sum() < 50


def test_zbuffer_in_utm_coordinates():
    """A scene 500 km from the origin (UTM) gives the buffer of the same scene at the origin."""
    shift = np.array([512345.25, 5412345.75, 230.5])
    proxy = _proxy()
    moved = Proxy(
        [Polygon(p.id, p.outer + shift, tuple(h + shift for h in p.holes)) for p in proxy.polygons], Path("p.obj")
    )
    ph = _photo((-3.0, -4.0, 3.5), (2.0, 0.0, 1.5))
    far = _photo(np.array([-3.0, -4.0, 3.5]) + shift, np.array([2.0, 0.0, 1.5]) + shift)
    a, da = zbuffer(Pieces.of(proxy), ph)
    b, db = zbuffer(Pieces.of(moved), far)
    assert (a != b).mean() < 1e-3
    same = (a == b) & (a >= 0)
    np.testing.assert_allclose(da[same], db[same], rtol=1e-5)


def test_pieces_beside_the_photo_change_nothing():
    """The cull of pieces outside the photo (one array pass, not a call per piece) keeps every
    piece that a ray could meet: a street of walls in front of the camera and another behind it,
    most beside or behind the photo, gives the ids of the walls in view alone (re-indexed), at
    the image's edges too."""
    walls = []
    for side, x in (("front", 10.0), ("back", -10.0)):
        for k in range(-60, 60):
            y0, y1 = 1.5 * k, 1.5 * k + 1.4
            outline = [[x, y1, 0], [x, y0, 0], [x, y0, 3], [x, y1, 3]] if x > 0 else \
                [[x, y0, 0], [x, y1, 0], [x, y1, 3], [x, y0, 3]]
            walls.append(Polygon(f"{side}{k + 60}", np.array(outline, float)))
    whole = Proxy(walls, Path("street.obj"))
    photo = _photo([0, 0, 1.5], [10, 0, 1.5], f=200.0)
    ids, dist = zbuffer(Pieces.of(whole), photo)
    seen = np.unique(ids[ids >= 0])
    assert 5 <= len(seen) < 30  # the rest of the 240 walls are beside or behind the camera
    alone = Proxy([walls[i] for i in seen], Path("seen.obj"))
    ids2, dist2 = zbuffer(Pieces.of(alone), photo)
    assert np.array_equal(np.where(ids2 >= 0, seen[np.maximum(ids2, 0)], -1), ids)
    assert np.array_equal(dist2, dist)
    # and the walls in view are every wall the exact ray caster finds (the cull dropped none)
    ref_ids, _ = id_buffer(ProxyCaster.build(whole, "numpy"), photo)
    assert set(np.unique(ref_ids[ref_ids >= 0])) == set(seen) and (ids != ref_ids).mean() < 2e-3
    # a polygon's normal and centroid are computed once and cannot be changed in place
    w = walls[0]
    assert w.normal is w.normal and not w.normal.flags.writeable and not w.centroid.flags.writeable
