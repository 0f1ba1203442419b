"""The low-pass under which the photos are compared, from the candidates' resolutions (not in the paper).

L_Render, Q_c, settling and elimination judge each photo by how well it agrees with the others
at every texel. A photo with fewer pixels than texels is blurred, in texels, by its pixels, and
misregistered by a pixel or so of its own, while a photo that resolves the texel is not: compared
at the texel's resolution, the sharp photo disagrees with a consensus of far photos exactly at
its detail (a street photo's brick joints among drone photos), and the optimization trades its
weight for agreement. Comparing under a Gaussian that brings the sharpest candidate to the
typical candidate's misfit removes that bias, while an occluder, many pixels across, still
disagrees. The texture keeps full detail (``Level.detail``).

A photo with f pixels per texel (its footprint) misfits the texel grid by about

    s(f) = sqrt((0.5 max(1, 1/f))^2 + (r / f)^2)  texels,

the first term its trilinear sampling (half the larger of a texel and a pixel), the second ``r``
of its own pixels of lens blur and registration error. The comparison low-pass is

    sigma = sqrt(max(0, s(f_med)^2 - s(f_max)^2)),

f_med the median candidate's footprint and f_max the finest's: zero where the candidates
resolve the texel alike, a fraction of a texel where all of them resolve it (a preset at a
fraction of the photos' density), about the typical photo's misfit where the texel is finer than
most photos see.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch

from difftex.geometry.frames import UVFrame, level_frame
from difftex.sampling.photos import PhotoSet
from difftex.sampling.texels import resample_nearest

PROBE_SIDE = 64  # long side of the grid on which each candidate's footprint is taken


def misfit(footprint: float, registration_px: float) -> float:
    """s(f): a photo's misfit to the texel grid, in texels.

    Args:
        footprint: f, the photo's pixels per texel (> 0).
        registration_px: r, its blur and registration error in its own pixels (>= 0).

    Returns:
        s(f) in texels.
    """
    if footprint <= 0 or registration_px < 0:
        raise ValueError(f"footprint must be > 0 and registration_px >= 0, got {footprint}, {registration_px}")
    return math.hypot(0.5 * max(1.0, 1.0 / footprint), registration_px / footprint)


def witness_sigma(footprints: Sequence[float], registration_px: float) -> float:
    """sigma = sqrt(max(0, s(f_med)^2 - s(f_max)^2)): the comparison low-pass, in texels.

    Args:
        footprints: the candidates' pixels per texel (the non-positive are ignored).
        registration_px: r of :func:`misfit`.

    Returns:
        sigma in texels (0 with fewer than two candidates).
    """
    fm = _finest_and_median(footprints)
    if fm is None:
        return 0.0
    finest, med = fm
    return math.sqrt(max(0.0, misfit(med, registration_px) ** 2 - misfit(finest, registration_px) ** 2))


def resolution_spread(footprints: Sequence[float]) -> float:
    """The finest candidate's pixels per texel over the median candidate's: how much more detail
    the best photos resolve than the typical one (scale-free: the same at any texel size).

    A drone survey's street photos: 4-8 on the facades they see; photos taken from similar
    distances: 1-2.

    Args:
        footprints: the candidates' pixels per texel (the non-positive are ignored).

    Returns:
        the spread, >= 1 (1 with fewer than two candidates).
    """
    fm = _finest_and_median(footprints)
    return 1.0 if fm is None else fm[0] / fm[1]


def _finest_and_median(footprints: Sequence[float]) -> tuple[float, float] | None:
    """(largest, median) of the positive footprints, or None with fewer than two."""
    f = np.asarray([x for x in footprints if x > 0], float)
    return None if f.size < 2 else (float(f.max()), float(np.median(f)))


def candidate_footprints(photos: PhotoSet, frame: UVFrame, which: Sequence[int]) -> list[float]:
    """Each candidate's median footprint (pixels per texel of ``frame``) over the texels it sees.

    Taken on a grid of PROBE_SIDE texels and scaled by the texel sizes: a footprint is
    proportional to the texel's size. The probe footprints depend only on the photo and the
    polygon, so they are taken once per photo (``PhotoSet.probe_footprints``) for the polygon's
    mixed-resolution decision and every level's low-pass.
    """
    inp = photos.inp
    probe = level_frame(inp.frame, min(PROBE_SIDE, max(inp.frame.shape)))
    memo = photos.probe_footprints
    missing = [n for n in which if n not in memo]
    if missing:
        mask = torch.from_numpy(resample_nearest(inp.texel_mask, inp.frame, probe)).to(photos.device)
        memo.update({n: photos.footprint_on(n, probe, mask)[1] for n in missing})
    scale = frame.texel_size / probe.texel_size
    fps = (memo[n] for n in which)
    return [fp * scale for fp in fps if fp is not None]
