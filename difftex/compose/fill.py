"""Filling a polygon's unseen texels, and the texel source map: the composition stage's numpy.

Numpy only, no torch, so the workflow's composition job starts in a fraction of a second
(importing torch costs seconds, more than composing a polygon).
"""

from __future__ import annotations

import numpy as np


def pool2_ceil(x: np.ndarray) -> np.ndarray:
    """2 x 2 mean pooling of (H, W, C) with a partial window at an odd edge averaging the
    texels it holds (torch's ``avg_pool2d(x, 2, ceil_mode=True)``).

    Shape: (H, W, C) -> (ceil(H/2), ceil(W/2), C).
    """
    H, W = x.shape[:2]
    h2, w2 = -(-H // 2), -(-W // 2)
    pad = np.zeros((2 * h2, 2 * w2) + x.shape[2:], x.dtype)
    cnt = np.zeros((2 * h2, 2 * w2), x.dtype)
    pad[:H, :W] = x
    cnt[:H, :W] = 1
    s = pad.reshape(h2, 2, w2, 2, *x.shape[2:]).sum((1, 3))
    n = cnt.reshape(h2, 2, w2, 2).sum((1, 3))
    return s / n.reshape(n.shape + (1,) * (x.ndim - 2))


def _linear_taps(n_in: int, n_out: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Bilinear taps along one axis, half-pixel centres (``align_corners=False``): the lower
    index, the upper index and the upper weight of each output sample."""
    src = np.maximum((np.arange(n_out) + 0.5) * (n_in / n_out) - 0.5, 0.0)
    lo = np.minimum(np.floor(src).astype(np.int64), n_in - 1)
    hi = np.minimum(lo + 1, n_in - 1)
    return lo, hi, (src - lo).astype(np.float32)


def resize_bilinear(x: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """(h, w, C) resized to ``shape`` bilinearly with half-pixel centres and clamped edges
    (torch's ``interpolate(mode="bilinear", align_corners=False)``).

    Shape: (h, w, C) -> (*shape, C).
    """
    ylo, yhi, fy = _linear_taps(x.shape[0], shape[0])
    xlo, xhi, fx = _linear_taps(x.shape[1], shape[1])
    rows = x[ylo] * (1 - fy)[:, None, None] + x[yhi] * fy[:, None, None]
    return rows[:, xlo] * (1 - fx)[None, :, None] + rows[:, xhi] * fx[None, :, None]


def fill_holes(img: np.ndarray, known: np.ndarray, levels: int = 16) -> np.ndarray:
    """Fill unknown texels from their neighbours by push-pull (masked pyramid averaging).

    Smooth and fast at 2048^2; skimage's biharmonic inpainting would take minutes at that size
    and nearest-neighbour filling leaves streaks. Known texels are returned unchanged.

    Args:
        img: (H, W, 3) colours; those of unknown texels are ignored.
        known: (H, W) bool texels whose colour is kept.

    Returns:
        (H, W, 3) float32.
    """
    known = np.asarray(known, bool)
    if known.all() or not known.any():
        return img.copy()
    m = known.astype(np.float32)[..., None]
    pyr = [(np.asarray(img, np.float32) * m, m)]
    for _ in range(levels):
        c, w = pyr[-1]
        if min(c.shape[:2]) <= 1 or bool((w > 0).all()):
            break
        pyr.append((pool2_ceil(c), pool2_ceil(w)))
    c, w = pyr[-1]
    est = c / np.maximum(w, np.float32(1e-8))
    if not bool((w > 0).all()):  # coarsest level still has gaps: use the global mean there
        mean = c.sum((0, 1)) / max(float(w.sum()), 1e-8)
        est = np.where(w > 0, est, mean[None, None, :])
    for c, w in reversed(pyr[1:-1]):
        up = resize_bilinear(est, c.shape[:2])
        own = c / np.maximum(w, np.float32(1e-8))
        a = np.clip(w, 0, 1)
        est = a * own + (1 - a) * up
    # the finest level: an unknown texel's own weight is 0, so it takes the upsampled estimate;
    # only those texels are interpolated (the known ones are returned unchanged)
    res = np.asarray(img, np.float32).copy()
    ys, xs = np.nonzero(~known)
    res[ys, xs] = bilinear_at(est, known.shape, ys, xs)
    return res


def bilinear_at(x: np.ndarray, shape: tuple[int, int], ys: np.ndarray, xs: np.ndarray) -> np.ndarray:
    """``resize_bilinear(x, shape)[ys, xs]`` without the whole resized image.

    Shape: (h, w, C), N indices -> (N, C).
    """
    ylo, yhi, fy = (t[ys] for t in _linear_taps(x.shape[0], shape[0]))
    xlo, xhi, fx = (t[xs] for t in _linear_taps(x.shape[1], shape[1]))
    top = x[ylo, xlo] * (1 - fx)[:, None] + x[ylo, xhi] * fx[:, None]
    bottom = x[yhi, xlo] * (1 - fx)[:, None] + x[yhi, xhi] * fx[:, None]
    return top * (1 - fy)[:, None] + bottom * fy[:, None]


def finish_texture(U: np.ndarray, weight_sum: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, dict]:
    """Fill the polygon's unseen texels (and the margin outside it, so bilinear lookups at its
    border never fetch black), and describe what was filled."""
    seen = (weight_sum > 0) & mask
    filled_in_polygon = mask & ~seen
    out = fill_holes(U, seen) if seen.any() else U.copy()
    info = {
        "texels": int(mask.sum()),
        "seen_texels": int(seen.sum()),
        "coverage": float(seen.sum() / max(mask.sum(), 1)),
        "filled_texels": int(filled_in_polygon.sum()),
        "fill": "push-pull from neighbouring seen texels" if filled_in_polygon.any() else None,
        "filled_outside_polygon": True,
    }
    return out, info


def dominant_from_slots(idx: np.ndarray, W: np.ndarray) -> np.ndarray:
    """Dominant photo per texel from a slot layout (-1 where no weight)."""
    j = W.argmax(0)
    d = np.take_along_axis(idx, j[None], 0)[0]
    return np.where(W.max(0) > 0, d, -1)
