"""Openings as rectangles (difftex.method.openings): a partly found recess completed to its box,
grown to the rectangle where the cost volume agrees and no further, and left alone where the
box would take plaster the photos place on the plane."""

from __future__ import annotations

import numpy as np
import pytest

from difftex.method.openings import cost_gain, fill_openings, grow_box, step_components

HEIGHTS = np.array([-0.2, -0.1, 0.0, 0.1], np.float32)
ZERO, RECESS = 2, 0


def _volume(shape=(40, 60), window=(slice(10, 30), slice(15, 35))):
    """A cost volume whose texels agree at the plane (cost 0.3 there, 0.8 elsewhere) except inside
    ``window``, where they agree at -0.2 (0.2 there, 0.6 at the plane)."""
    cost = np.full((len(HEIGHTS), *shape), 0.8, np.float32)
    cost[ZERO] = 0.3
    cost[:, window[0], window[1]] = 0.8
    cost[RECESS, window[0], window[1]] = 0.2
    cost[ZERO, window[0], window[1]] = 0.6
    return cost


def test_a_partly_found_recess_is_completed_to_its_box_and_grown_to_the_rectangle():
    cost = _volume()
    mask = np.ones((40, 60), bool)
    h = np.zeros((40, 60), np.float32)
    h[20:30, 15:35] = -0.2  # the lower half of the window, ragged: two notches
    h[20:24, 15:18] = 0.0
    h[27:30, 30:35] = 0.0
    boxed = fill_openings(h, mask, cost, HEIGHTS, "box")
    expect = np.zeros_like(h)
    expect[20:30, 15:35] = -0.2
    assert np.array_equal(boxed, expect)
    grown = fill_openings(h, mask, cost, HEIGHTS, "grow")
    expect[10:30, 15:35] = -0.2  # up to the window's top, where the plane is cheaper again
    assert np.array_equal(grown, expect)


def test_a_box_over_plaster_the_photos_place_on_the_plane_is_left_as_found():
    # two found windows joined by a thin bridge: their common box would take the plaster between
    cost = _volume(window=(slice(10, 30), slice(5, 55)))
    cost[:, 10:30, 20:40] = 0.8
    cost[ZERO, 10:30, 20:40] = 0.3
    mask = np.ones((40, 60), bool)
    h = np.zeros((40, 60), np.float32)
    h[10:30, 5:20] = -0.2
    h[10:30, 40:55] = -0.2
    h[19:21, 20:40] = -0.2  # the bridge
    [(v, box)] = step_components(h, mask, 0.3, 50)
    assert v == pytest.approx(-0.2) and box == (10, 30, 5, 55)
    assert np.array_equal(fill_openings(h, mask, cost, HEIGHTS, "box"), h)
    assert np.array_equal(fill_openings(h, mask, cost, HEIGHTS, "grow"), h)


def test_strips_small_components_and_texels_without_cost_are_not_filled():
    cost = np.full((len(HEIGHTS), 50, 50), 0.5, np.float32)  # every height alike: a gain of 0 fills
    mask = np.ones((50, 50), bool)
    h = np.zeros((50, 50), np.float32)
    idx = np.arange(50)
    h[idx, idx] = 0.1  # a diagonal strip covers 2 % of its box
    h[3:7, 40:44] = -0.2  # 16 texels
    assert step_components(h, mask, 0.3, 50) == []
    assert np.array_equal(fill_openings(h, mask, cost, HEIGHTS, "box"), h)
    # with no minimum, the small square fills its own (full) box and the strip is still too sparse
    assert np.array_equal(fill_openings(h, mask, cost, HEIGHTS, "box", min_texels=1), h)
    # a box whose texels have no finite cost is never filled
    h2 = np.zeros_like(h)
    h2[10:20, 10:20] = -0.2
    h2[10:15, 10:15] = 0.0
    c2 = cost.copy()
    c2[:, 10:15, 10:15] = np.inf
    assert np.array_equal(fill_openings(h2, mask, c2, HEIGHTS, "box", min_texels=1), h2)
    assert cost_gain(c2, RECESS, ZERO, np.pad(np.ones((5, 5), bool), ((10, 35), (10, 35)))) == np.inf


def test_the_polygon_mask_bounds_the_fill_and_a_flat_field_is_unchanged():
    cost = _volume()
    mask = np.ones((40, 60), bool)
    mask[:, 25:] = False  # the window runs off the polygon
    h = np.zeros((40, 60), np.float32)
    h[20:30, 15:25] = -0.2
    h[22:30, 15:17] = 0.0
    out = fill_openings(h, mask, cost, HEIGHTS, "grow")
    assert (out[~mask] == 0).all() and (out[10:30, 15:25] == -0.2).all()
    flat = np.zeros((40, 60), np.float32)
    assert np.array_equal(fill_openings(flat, mask, cost, HEIGHTS, "grow"), flat)


def test_grow_box_stops_at_the_frame_and_where_the_plane_is_cheaper():
    cost = _volume(window=(slice(0, 25), slice(0, 60)))
    free = np.ones((40, 60), bool)
    assert grow_box((15, 20, 10, 20), free, cost, RECESS, ZERO, 0.0) == (0, 25, 0, 60)
    assert grow_box((15, 20, 10, 20), free, cost, RECESS, ZERO, -0.5) == (15, 20, 10, 20)


def test_fill_openings_checks_its_input():
    cost = _volume()
    h = np.zeros((40, 60), np.float32)
    with pytest.raises(ValueError, match="disagree"):
        fill_openings(h, np.ones((40, 61), bool), cost, HEIGHTS, "box")
    with pytest.raises(ValueError, match="disagree"):
        fill_openings(h, np.ones((40, 60), bool), cost[:3], HEIGHTS, "box")
    with pytest.raises(ValueError, match="box|grow"):
        fill_openings(h, np.ones((40, 60), bool), cost, HEIGHTS, "rectangle")  # type: ignore[arg-type]
