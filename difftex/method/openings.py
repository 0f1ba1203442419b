"""Openings as rectangles: completing a height field's steps to the boxes they belong to.

A facade's relief is made of rectangles at one depth each: window and door recesses, balconies,
string courses. The sweep (difftex.method.relief) finds only part of each: drone photos see a
recessed pane's upper part hidden by its lintel and agree only on its lower part and sill, so a
window's field comes out as a ragged blob, and the texture mapped through it tears along the
blob's edges (docs/optimizer.md, "Openings as rectangles"). This module completes each step:

1. every connected component of one height off the plane (:func:`step_components`) that covers
   at least ``min_fill`` of its bounding box (a diagonal strip, such as a gable's cornice, covers
   little of its box and is left as found) and at least ``min_texels`` texels (below the sweep's
   window, a component is noise the window cannot resolve);
2. ``mode="grow"`` first grows the box one row or column at a time on each side while the strip
   added agrees better at the component's height than at the plane (:func:`cost_gain` < ``tol``);
3. the box's plane texels take the component's height if, together, they agree at that height at
   least as well as at the plane (cost gain <= ``tol``): a box spanning two windows and the plaster
   between them, where the plane is cheaper, is left as found.

The axes of the boxes are the polygon's UV axes, which follow its minimum-area rectangle
(difftex.geometry.frames.uv_frame): a wall's are its horizontal and vertical, as its openings'.
"""

from __future__ import annotations

from typing import Literal

import numpy as np
from scipy import ndimage

Box = tuple[int, int, int, int]  # rows [y0, y1), columns [x0, x1)


def cost_gain(cost: np.ndarray, label: int, zero: int, region: np.ndarray) -> float:
    """Mean over ``region`` of cost[label] - cost[zero] (< 0: the texels agree better at ``label``'s
    height than at the plane); texels where either cost is not finite are not counted.

    Args:
        cost: (D, h, w) the sweep's cost volume; label, zero: indices into its first axis;
        region: (h, w) bool.

    Returns:
        the mean difference, +inf where no texel of ``region`` counts.
    """
    a, b = cost[label][region], cost[zero][region]
    ok = np.isfinite(a) & np.isfinite(b)
    return float((a[ok] - b[ok]).mean()) if ok.any() else float("inf")


def step_components(h: np.ndarray, mask: np.ndarray, min_fill: float, min_texels: int) -> list[tuple[float, Box]]:
    """The connected components (8-connected) of each height off the plane, as (height, bounding
    box), that hold at least ``min_texels`` texels and ``min_fill`` of their box.

    Args:
        h: (h, w) heights (flat steps); mask: (h, w) bool texels of the polygon.

    Returns:
        list of (height, (y0, y1, x0, x1)).
    """
    out = []
    for v in np.unique(h[mask & (h != 0)]):
        lab, _ = ndimage.label((h == v) & mask, structure=np.ones((3, 3), bool))
        for i, sl in enumerate(ndimage.find_objects(lab)):
            comp = lab[sl] == i + 1
            if comp.sum() >= min_texels and comp.mean() >= min_fill:
                out.append((float(v), (sl[0].start, sl[0].stop, sl[1].start, sl[1].stop)))
    return out


def grow_box(box: Box, free: np.ndarray, cost: np.ndarray, label: int, zero: int, tol: float) -> Box:
    """Grow ``box`` a row or column at a time, on any side where the strip's ``free`` texels agree
    better at ``label`` than at the plane (:func:`cost_gain` < ``tol``), until no side grows.

    Args:
        box: (y0, y1, x0, x1); free: (h, w) bool texels a box may take (the polygon's, at the plane).

    Returns:
        the grown box.
    """
    y0, y1, x0, x1 = box
    H, W = free.shape
    grown = True
    while grown:
        grown = False
        for side in ((y0 - 1, y0, x0, x1), (y1, y1 + 1, x0, x1), (y0, y1, x0 - 1, x0), (y0, y1, x1, x1 + 1)):
            a0, a1, b0, b1 = side
            if a0 < 0 or b0 < 0 or a1 > H or b1 > W:
                continue
            strip = np.zeros_like(free)
            strip[a0:a1, b0:b1] = free[a0:a1, b0:b1]
            if strip.any() and cost_gain(cost, label, zero, strip) < tol:
                y0, y1, x0, x1 = min(y0, a0), max(y1, a1), min(x0, b0), max(x1, b1)
                grown = True
    return y0, y1, x0, x1


def fill_openings(
    h: np.ndarray,
    mask: np.ndarray,
    cost: np.ndarray,
    heights: np.ndarray,
    mode: Literal["box", "grow"],
    min_fill: float = 0.3,
    min_texels: int = 50,
    tol: float = 0.0,
) -> np.ndarray:
    """Each step component completed to its (grown) bounding box where the box's plane texels
    agree at its height at least as well as at the plane (the module's docstring).

    Args:
        h: (h, w) float heights, flat steps at values of ``heights``; mask: (h, w) bool;
        cost: (D, h, w) the sweep's cost volume; heights: (D,) its heights, 0 among them;
        mode: "box" the component's bounding box, "grow" grown by :func:`grow_box` first.

    Returns:
        (h, w) float32 heights: ``h`` with the boxes' plane texels filled; the plane outside ``mask``.
    """
    if h.shape != mask.shape or cost.shape[1:] != h.shape or cost.shape[0] != len(heights):
        raise ValueError(f"field {h.shape}, mask {mask.shape}, cost {cost.shape}, {len(heights)} heights disagree")
    if mode not in ("box", "grow") or not 0 <= min_fill <= 1 or min_texels < 1:
        raise ValueError(
            f"openings mode box|grow, min_fill in [0, 1], min_texels >= 1; got {mode!r}, {min_fill}, {min_texels}"
        )
    zero = int(np.argmin(np.abs(heights)))
    out = h.astype(np.float32).copy()
    for v, box in step_components(h, mask, min_fill, min_texels):
        label = int(np.argmin(np.abs(heights - v)))
        if mode == "grow":
            box = grow_box(box, mask & (out == 0), cost, label, zero, tol)
        y0, y1, x0, x1 = box
        fill = np.zeros_like(mask)
        fill[y0:y1, x0:x1] = mask[y0:y1, x0:x1] & (out[y0:y1, x0:x1] == 0)
        if fill.any() and cost_gain(cost, label, zero, fill) <= tol:
            out[fill] = v
    return np.where(mask, out, 0.0).astype(np.float32)
