"""Photo filtering: sharpness, photos that see nothing, inclined views."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

from difftex.config import FilterConfig
from difftex.geometry.photo_filter import filter_photos, luminance, sharpness
from difftex.scene.files import write_image
from difftex.scene.loading import load_scene

from tests.scenes import make_scene


def test_sharpness_falls_with_blur():
    rng = np.random.default_rng(1)
    img = rng.random((200, 300, 3)).astype(np.float32)
    values = [sharpness(gaussian_filter(img, (s, s, 0)) if s else img) for s in (0, 1, 2, 4)]
    assert all(a > b for a, b in zip(values, values[1:]))


def test_sharpness_of_a_flat_image_is_zero():
    assert sharpness(np.full((64, 64, 3), 0.5, np.float32)) == 0.0


def test_sharpness_of_stored_8_and_16_bit_values_equals_that_of_the_floats():
    """The filter measures photos as decoded (as_stored): no float copy of the whole photo."""
    rng = np.random.default_rng(2)
    for dtype, top in ((np.uint8, 255), (np.uint16, 65535)):
        stored = rng.integers(0, top + 1, (90, 130, 4), dtype=dtype)  # RGBA: alpha ignored
        floats = stored.astype(np.float32) * np.float32(1.0 / top)
        assert np.allclose(luminance(stored), luminance(floats), rtol=0, atol=2e-7)
        assert sharpness(stored) == pytest.approx(sharpness(floats), rel=1e-5)
    white = np.full((8, 8, 3), 255, np.uint8)
    assert np.allclose(luminance(white), 1.0, atol=1e-6)  # the extremes of the range
    assert luminance(np.zeros((8, 8, 3), np.uint16)).max() == 0.0


def test_blurry_photo_is_dropped_relative_to_the_set(tmp_path):
    centers = [(x, -6.0, 1.0) for x in (-1.0, -0.5, 0.0, 0.5, 1.0)]
    root = make_scene(tmp_path / "s", centers=centers)
    img = np.random.default_rng(3).random((120, 160, 3)).astype(np.float32)
    write_image(root / "images" / "img02.png", gaussian_filter(img, (3, 3, 0)))
    sc = load_scene(root)
    table = filter_photos(sc.proxy, sc.photos, FilterConfig(), progress=False)
    rec = {r["name"]: r for r in table["photos"]}
    assert not rec["img02.png"]["kept"] and "blurry" in rec["img02.png"]["reason"]
    assert sum(r["kept"] for r in table["photos"]) == 4
    assert "img02.png" in table["polygons"]["front"]["dropped"]


def test_inclined_views_are_dropped_per_polygon(tmp_path):
    # one frontal camera and one almost along the wall
    root = make_scene(tmp_path / "s", centers=[(0.0, -6.0, 1.0), (8.0, -0.6, 1.0)], target=(0.0, 0.0, 1.0))
    sc = load_scene(root)
    table = filter_photos(sc.proxy, sc.photos, FilterConfig(max_angle_deg=70.0, min_pixels=4), progress=False)
    poly = table["polygons"]["front"]
    assert poly["kept"] == ["img00.png"]
    assert "inclined" in poly["dropped"]["img01.png"]
    angles = {r["name"]: r["polygons"]["front"]["angle_deg"] for r in table["photos"]}
    assert angles["img00.png"] < 15 and angles["img01.png"] > 70


@pytest.mark.parametrize("model", ["PINHOLE", "SIMPLE_RADIAL"])
@pytest.mark.parametrize("backend", ["default", "numpy"])
def test_photos_measured_side_by_side_give_the_records_of_one_thread(tmp_path, monkeypatch, backend, model):
    """The filter measures photos in worker threads (OMP_NUM_THREADS of them); the records are
    those of one thread, in photo order. Distorted photos are ray-cast from the worker threads
    under the caster's lock; so is a pinhole photo whose plane the back wall crosses (the last
    camera stands beside it looking along it); with the numpy caster too."""
    from difftex.geometry import raycast
    from difftex.geometry.photo_filter import photo_records

    from tests.scenes import wall

    if backend == "numpy":  # as without Mitsuba: shapely's prepared polygons, under the lock
        monkeypatch.setattr(raycast, "mitsuba_available", lambda: False)
    polys = {"back": wall(-2, 2, 0, 2, y=0.0), "front": wall(-0.5, 0.5, 0, 1, y=-1.0)}
    centers = [(0.0, -6.0, 1.0), (2.0, -6.0, 1.5), (-2.0, -5.0, 0.5), (1.0, -7.0, 0.8), (0.5, -0.6, 1.0)]
    targets = [(0.0, 0.0, 1.0)] * 4 + [(-2.0, 0.0, 1.0)]
    sc = load_scene(make_scene(tmp_path / "s", polys, centers=centers, target=targets, model=model))
    cfg = FilterConfig(min_pixels=4)
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    one = [r.__dict__ for r in photo_records(sc.proxy, sc.photos, cfg, progress=False)]
    monkeypatch.setenv("OMP_NUM_THREADS", "3")
    three = [r.__dict__ for r in photo_records(sc.proxy, sc.photos, cfg, progress=False)]
    assert [r["name"] for r in three] == [p.name for p in sc.photos]
    assert three == one
    assert one[-1]["polygons"] and "back" in one[-1]["polygons"]  # the cast photo sees the wall
