"""Texel density from the photos: each polygon's texel size from the detail its photos hold.

The ground sampling distance (GSD) of photo k at a point of polygon P_i is the side of a pixel's
footprint on the polygon's plane, g = s / sqrt|det J| for a texel of size s and J the Jacobian
of the mapping f_k^i (pixels per texel). ``density: auto`` gives each polygon the texel size

    s_i = percentile_p over its texels t of (min over frontal photos k seeing t of g_k(t)) / scale

(frontal: within FRONTAL_DEG of the normal; where no frontal photo sees a texel, all photos
count), so the map holds what the best photo of each texel holds, at ``density_scale`` of it.
Caps: ``max_long_side`` and ``max_mb`` of optimization memory; the texture section's report
says which one set the size.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from difftex.config import TextureConfig
from difftex.geometry.frames import UVFrame, map_texels, texel_footprint
from difftex.scene.camera import Photo

FRONTAL_DEG = 60.0
# Optimizer memory per texel and slot (weights, Adam state, mapped colours, masks, autograd
# temporaries), texel loss, measured: evaluation/bench_optimize.md (herzjesu facade at 2048).
# optimize.consistency_sigma > 0 adds 12 (the full-detail colours beside the compared ones).
BYTES_PER_TEXEL_SLOT = 224
PROBE_LONG_SIDE = 64


def probe_gsd(frame: UVFrame, photo: Photo, seen: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """GSD (scene units per pixel) and frontality (cos) of ``photo`` at the texels of ``frame``.

    Args:
        frame: a (coarse) frame of the polygon.
        photo: the photo.
        seen: (h, w) bool, texels the photo sees (visibility).

    Returns:
        (gsd (h, w), cos (h, w)), NaN where the photo does not see the texel.
    """
    m = map_texels(frame, photo)
    fp = texel_footprint(frame, photo, m.pix)
    ok = seen & m.valid & np.isfinite(fp) & (fp > 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        gsd = np.where(ok, frame.texel_size / fp, np.nan)
    return gsd, np.where(ok, m.cos_angle, np.nan)


def photo_texel_size(gsd: np.ndarray, cos: np.ndarray, percentile: float) -> float | None:
    """The texel size the photos support: ``percentile`` over texels of the finest frontal GSD.

    Args:
        gsd: (N, h, w) GSD per photo and probe texel (NaN: not seen).
        cos: (N, h, w) frontality per photo and probe texel.
        percentile: in [0, 100].

    Returns:
        The texel size in scene units, or None when no photo sees the polygon.
    """
    if gsd.size == 0:
        return None
    frontal = cos >= math.cos(math.radians(FRONTAL_DEG))
    inf = np.full_like(gsd, np.inf)
    best_frontal = np.where(frontal & np.isfinite(gsd), gsd, inf).min(0)
    best_any = np.where(np.isfinite(gsd), gsd, inf).min(0)
    best = np.where(np.isfinite(best_frontal), best_frontal, best_any)
    vals = best[np.isfinite(best)]
    if vals.size == 0:
        return None
    return float(np.percentile(vals, percentile))


@dataclass(frozen=True)
class TexelSize:
    """A polygon's chosen texel size and why."""

    texel_size: float  # scene units per texel
    photo_texel_size: float | None  # what the photos support (before the scale and the caps)
    bound: str  # "photos", "max_long_side", "memory", "min_long_side", "density", "long_side"


def choose_texel_size(
    extent: tuple[float, float], area: float, photo_size: float | None, cfg: TextureConfig, slots: int
) -> TexelSize:
    """The texel size of a polygon with rectangle ``extent`` (width, height) and ``area`` (scene units).

    Args:
        extent: the UV rectangle's sides (scene units).
        area: the rectangle's area (texels of the map = area / s^2).
        photo_size: photo_texel_size(...) (auto) or None.
        cfg: the texture section.
        slots: candidate slots per texel, min(candidates, top_k), for the memory cap.
    """
    long_m = max(extent)
    if cfg.mode == "long_side":
        return TexelSize(long_m / int(cfg.long_side), photo_size, "long_side")  # type: ignore[arg-type]  # set in this mode
    if cfg.mode == "density":
        s, bound = 1.0 / float(cfg.density), "density"  # type: ignore[arg-type]  # set in this mode
    else:
        if photo_size is None:  # nothing sees it: the coarsest map allowed
            return TexelSize(long_m / int(cfg.min_long_side), None, "min_long_side")
        s, bound = photo_size / float(cfg.density_scale), "photos"
    if long_m / s > cfg.max_long_side:
        s, bound = long_m / cfg.max_long_side, "max_long_side"
    max_texels = float(cfg.max_mb) * 2**20 / (max(slots, 1) * BYTES_PER_TEXEL_SLOT)
    if area / (s * s) > max_texels:
        s, bound = math.sqrt(area / max_texels), "memory"
    if cfg.mode == "auto" and long_m / s < cfg.min_long_side:
        s, bound = long_m / cfg.min_long_side, "min_long_side"
    return TexelSize(float(s), photo_size, bound)
