"""Where each photo is mapped at a level: the whole level at the first, after it only the tiles
where the coarser level gave it weight (the sparse finer levels).

At full density a survey wall has 50-60 candidate photos and about a million texels at its finest
level, while the coarser level has already decided that a few photos per texel hold the blend:
mapping every candidate over the whole level is most of a polygon's time. A photo the coarser
level outranked at a texel starts there at zero weight anyway (difftex.method.levels.build_level),
so it is mapped only over the tiles where it held weight (> tau), or where the coarser level knew
nothing. One rectangle around all of a photo's support (the earlier scheme) spans the wall as soon
as a photo holds weight at two of its ends, as drone photos do; tiles keep each photo's mapping
to its support. A photo's tiles are disjoint rectangles (runs of tiles along a row), so it never
holds two slots of a texel.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from difftex.geometry.frames import UVFrame
from difftex.sampling.photos import PhotoSet
from difftex.sampling.texels import Region, resample_nearest

TILE = 128  # side of the tiles a photo is mapped over at the finer levels, texels
DENSE_SHARE = 0.8  # tiles covering this share of their bounding box: one rectangle instead

Entry = tuple[int, Region]  # (photo, rectangle of the level it is mapped over)


def bbox(m: torch.Tensor) -> Region:
    """(y0, y1, x0, x1) of a non-empty (h, w) bool mask."""
    ys = torch.nonzero(m.any(1)).flatten()
    xs = torch.nonzero(m.any(0)).flatten()
    return int(ys[0]), int(ys[-1]) + 1, int(xs[0]), int(xs[-1]) + 1


def upsample_support(sup: torch.Tensor, shape: tuple[int, int], r: float, pad: int) -> torch.Tensor:
    """A coarse level's (h', w') bool support at a finer level's texels, grown by the reach of the
    bilinear upsampling of weights (half a coarse texel) plus ``pad`` fine texels.

    Args:
        sup: (h', w') bool.
        shape: the finer level's (h, w).
        r: a fine texel's size in coarse texels (< 1 when finer).
        pad: extra fine texels.

    Returns:
        (h, w) bool.
    """
    h, w = shape
    cy = ((torch.arange(h, device=sup.device) + 0.5) * r).long().clamp(0, sup.shape[0] - 1)
    cx = ((torch.arange(w, device=sup.device) + 0.5) * r).long().clamp(0, sup.shape[1] - 1)
    fine = sup[cy][:, cx]
    grow = int(np.ceil(0.5 / max(r, 1e-6))) + pad
    return F.max_pool2d(fine.float()[None, None], 2 * grow + 1, stride=1, padding=grow)[0, 0] > 0


def tile_runs(need: torch.Tensor, tile: int = TILE) -> list[Region]:
    """Disjoint rectangles that cover ``need``: the tiles that hold any of it, merged into runs
    along each row of tiles; one bounding rectangle where the tiles fill most of it.

    Args:
        need: (h, w) bool, not empty.
        tile: tile side, texels.

    Returns:
        rectangles (y0, y1, x0, x1), clipped to the level.
    """
    h, w = need.shape
    box = bbox(need)
    th, tw = -(-h // tile), -(-w // tile)
    pad = torch.zeros((th * tile, tw * tile), dtype=torch.bool, device=need.device)
    pad[:h, :w] = need
    active = pad.reshape(th, tile, tw, tile).any(3).any(1).cpu().numpy()
    if active.sum() * tile * tile >= DENSE_SHARE * (box[1] - box[0]) * (box[3] - box[2]):
        return [box]
    out = []
    for ty in range(th):
        cols = np.nonzero(active[ty])[0]
        if cols.size == 0:
            continue
        starts = np.r_[cols[0], cols[1:][np.diff(cols) > 1]]
        ends = np.r_[cols[:-1][np.diff(cols) > 1], cols[-1]]
        for a, b in zip(starts, ends):
            out.append((ty * tile, min(h, (ty + 1) * tile), int(a) * tile, min(w, (int(b) + 1) * tile)))
    return out


def photo_entries(
    photos: PhotoSet,
    frame: UVFrame,
    mask: np.ndarray,
    prev: tuple | None,
    prev_known: torch.Tensor | None,
    tau: float,
    pad: int = 2,
    tile: int = TILE,
) -> list[Entry]:
    """The rectangles of ``frame`` each photo is mapped over (module docstring): all of it at the
    first level (``prev`` None); after it, the tiles around the texels where the photo held weight
    (> tau) at the coarser level, and those the coarser level knew nothing about that it sees.
    Photos without either are not mapped.

    Args:
        photos: the polygon's decoded photos.
        frame: this level's frame.
        mask: (h, w) bool polygon texels at this level.
        prev: (coarser Level, its blend weights (K, h', w')) or None.
        prev_known: (h, w) bool texels whose coarse neighbourhood had a candidate (with ``prev``).
        tau: activation threshold on W.
        pad: fine texels added around a photo's support.
        tile: tile side, texels.

    Returns:
        (photo, region) entries, photo by photo, each photo's regions disjoint.
    """
    h, w = frame.shape
    if prev is None:
        return [(n, (0, h, 0, w)) for n in sorted(photos.samplers)]
    plv, pW = prev
    assert prev_known is not None  # given with prev
    r = frame.texel_size / plv.frame.texel_size
    unknown = torch.from_numpy(mask).to(prev_known.device) & ~prev_known
    ubox = bbox(unknown) if bool(unknown.any()) else None
    held = (pW > tau) & plv.visible
    out: list[Entry] = []
    for n in sorted(photos.samplers):
        sup = ((plv.idx == n) & held).any(0)
        need = upsample_support(sup, (h, w), r, pad) if bool(sup.any()) else torch.zeros_like(unknown)
        if ubox is not None:  # what the photo sees of the unknown texels, resampled over their box only
            y0, y1, x0, x1 = ubox
            sees = torch.from_numpy(resample_nearest(photos.inp.texel_visible[n], photos.inp.frame, frame, ubox))
            need = need.clone()
            need[y0:y1, x0:x1] |= unknown[y0:y1, x0:x1] & sees.to(unknown.device)
        if bool(need.any()):
            out.extend((n, reg) for reg in tile_runs(need, tile))
    return out
