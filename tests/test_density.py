"""Texel density: auto from the photos' ground sampling distance, numeric density, long side, caps.

Every expectation follows from the geometry: a pinhole camera of focal length f pixels, frontal
to a wall at distance d, sees d / f scene units per pixel everywhere on the wall.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from difftex.config import TextureConfig
from difftex.geometry.density import BYTES_PER_TEXEL_SLOT, choose_texel_size, photo_texel_size
from difftex.geometry.visibility import scene_visibility
from difftex.scene.loading import load_scene

from tests.scenes import make_scene, wall

SIZE = (320, 240)
FOCAL = 0.9 * SIZE[0]  # make_scene's focal length in pixels
WALL = wall(-2, 2, 0, 2)  # 4 m x 2 m


@pytest.fixture(scope="module")
def frontal_scene(tmp_path_factory):
    # frontal at 6 m and at 12 m, and a close photo at 75 degrees (fine GSD along one axis only)
    centers = [
        (0.0, -6.0, 1.0),
        (0.0, -12.0, 1.0),
        (-3.0 * math.sin(math.radians(75)), -3.0 * math.cos(math.radians(75)), 1.0),
    ]
    root = make_scene(
        tmp_path_factory.mktemp("density") / "s", {"front": WALL}, centers=centers, target=(0.0, 0.0, 1.0), size=SIZE
    )
    return load_scene(root)


def _vis(sc, cfg):
    return scene_visibility(sc.proxy, sc.photos, sc.up, {"front": [p.name for p in sc.photos]}, cfg, progress=False)[0]


def test_auto_density_is_the_nearest_frontal_photos_gsd(frontal_scene):
    vis = _vis(frontal_scene, TextureConfig(density="auto", density_scale=1.0))
    expected = 6.0 / FOCAL  # the 6 m photo; the 12 m one is coarser, the 75 degree one not frontal
    ts = vis.texel_size
    assert ts["bound"] == "photos"
    assert ts["photo_texel_size"] == pytest.approx(expected, rel=0.03)
    assert ts["texel_size"] == pytest.approx(expected, rel=0.03)
    assert vis.frame.width == pytest.approx(4.0 / expected, rel=0.04)


def test_density_scale_divides_the_texel_count_per_unit(frontal_scene):
    full = _vis(frontal_scene, TextureConfig(density="auto", density_scale=1.0)).texel_size["texel_size"]
    half = _vis(frontal_scene, TextureConfig(density="auto", density_scale=0.5)).texel_size["texel_size"]
    assert half == pytest.approx(2 * full, rel=1e-9)


def test_numeric_density_is_honoured(frontal_scene):
    vis = _vis(frontal_scene, TextureConfig(density=10.0))
    assert vis.texel_size["bound"] == "density" and vis.texel_size["texel_size"] == pytest.approx(0.1)
    assert vis.frame.shape == (20, 40)


def test_long_side_is_honoured(frontal_scene):
    vis = _vis(frontal_scene, TextureConfig(density=None, long_side=64))
    assert vis.frame.width == 64 and vis.texel_size["bound"] == "long_side"


def test_max_long_side_binds_and_says_so(frontal_scene):
    vis = _vis(frontal_scene, TextureConfig(density="auto", max_long_side=100))
    assert vis.texel_size["bound"] == "max_long_side"
    assert vis.frame.width == 100 and vis.texel_size["texel_size"] == pytest.approx(0.04)


def test_memory_cap_binds_and_bounds_the_texels():
    cfg = TextureConfig(density=1000.0, max_mb=1.0)
    size = choose_texel_size((4.0, 2.0), 8.0, None, cfg, slots=8)
    assert size.bound == "memory"
    texels = 8.0 / size.texel_size**2
    assert texels * 8 * BYTES_PER_TEXEL_SLOT == pytest.approx(2**20, rel=1e-9)


def test_min_long_side_for_a_polygon_no_photo_sees():
    size = choose_texel_size((30.0, 3.0), 90.0, None, TextureConfig(), slots=1)
    assert size.bound == "min_long_side" and 30.0 / size.texel_size == pytest.approx(TextureConfig().min_long_side)


def test_same_texel_size_for_a_balcony_and_a_wall():
    # a 1 m balcony and a 30 m wall seen at the same GSD get the same texel size (not the same map size)
    cfg = TextureConfig(density="auto", density_scale=0.5)
    small = choose_texel_size((1.0, 1.0), 1.0, 0.01, cfg, slots=8)
    large = choose_texel_size((30.0, 10.0), 300.0, 0.01, cfg, slots=8)
    assert small.texel_size == large.texel_size == pytest.approx(0.02)


def test_photo_texel_size_prefers_frontal_photos_and_falls_back_to_oblique():
    gsd = np.array([[[0.05, 0.05]], [[0.01, 0.01]]])  # photo 1 is finer but oblique
    cos = np.array([[[0.9, 0.9]], [[0.2, 0.2]]])
    assert photo_texel_size(gsd, cos, 25) == pytest.approx(0.05)
    only_oblique = photo_texel_size(gsd[1:], cos[1:], 25)
    assert only_oblique == pytest.approx(0.01)
    assert photo_texel_size(np.full((1, 2, 2), np.nan), np.full((1, 2, 2), np.nan), 25) is None


@pytest.mark.parametrize("bad", [0.0, -1.0, "dense", float("nan")])
def test_bad_density_is_rejected(bad):
    with pytest.raises(ValueError):
        TextureConfig(density=bad)
