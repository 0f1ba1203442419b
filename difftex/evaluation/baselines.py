"""Baselines sharing the optimizer's photo mapping: plain averaging and the most frontal photo.

- ``average``: every candidate photo that sees a texel, equal weights (ghosting and blur).
- ``frontal``: the polygon's photos ranked by mean frontality (cosine between the viewing ray
  and the normal over the texels they see); each texel takes the highest-ranked photo that
  sees it, so the most frontal photo textures the polygon and the next ones only fill what it
  does not see.
"""

from __future__ import annotations

import time

import numpy as np
import torch

from difftex.compose.composite import compose_from_photos
from difftex.compose.fill import finish_texture
from difftex.compose.outputs import write_texture_outputs
from difftex.errors import DifftexError
from difftex.sampling import SUPERSAMPLE
from difftex.sampling.photos import PhotoSet, PolygonInput, pick_device
from difftex.sampling.texels import level_frame, resample_nearest

METHODS = ("average", "frontal")


def frontality_ranking(photos: PhotoSet) -> list[int]:
    """Photo indices, most frontal first (mean cos over the texels each sees at a coarse level)."""
    inp = photos.inp
    frame = level_frame(inp.frame, min(256, max(inp.frame.shape)))
    mask = resample_nearest(inp.texel_mask, inp.frame, frame)
    scores = {}
    for n in photos.samplers:
        mp = photos.map(n, frame, mask)
        if mp is None:
            continue
        scores[n] = float(mp.cos[mp.visible].mean())
    return sorted(scores, key=lambda n: (-scores[n], n))


def baseline_texture(
    inp: PolygonInput, method: str, device="cpu", supersample: int = SUPERSAMPLE
) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict]:
    """(U (H, W, 3), weight sum (H, W), dominant photo (H, W), info) for a baseline method;
    ``supersample``: the photo sampling of ``optimize.supersample``, so that a comparison with
    difftex compares the blend, not the sampling."""
    if method not in METHODS:
        raise DifftexError(f"unknown baseline method '{method}' (known: {', '.join(METHODS)})")
    device = pick_device(device)
    photos = PhotoSet.load(inp, device, supersample=supersample)
    H, W = inp.frame.shape
    if method == "average":
        best = torch.full((H, W), -1, dtype=torch.long)
        best_cos = torch.full((H, W), -1.0)

        def weight_of(n, mp):
            # dominant photo of an average: the most frontal one seeing the texel (for the map)
            better = mp.visible.cpu() & (mp.cos.cpu() > best_cos)
            best[better] = n
            best_cos[better] = mp.cos.cpu()[better]
            return mp.visible.float()

        U, wsum = compose_from_photos(photos, weight_of)
        return (
            U,
            wsum,
            best.numpy(),
            {"method": "average", "photos": [inp.photos[n].name for n in sorted(photos.samplers)]},
        )
    order = frontality_ranking(photos)
    taken = torch.zeros(H, W, dtype=torch.bool, device=device)
    dominant = torch.full((H, W), -1, dtype=torch.long, device=device)
    weights = {}
    for n in order:
        mp = photos.map(n, inp.frame, inp.texel_mask)
        if mp is None:
            continue
        w = mp.visible & ~taken
        weights[n] = w.float()
        dominant[w] = n
        taken |= w
    U, wsum = compose_from_photos(photos, lambda n, mp: weights.get(n))
    info = {"method": "frontal", "ranking": [inp.photos[n].name for n in order]}
    return U, wsum, dominant.cpu().numpy(), info


def write_baseline_polygon(inp: PolygonInput, U: np.ndarray, wsum: np.ndarray, dominant: np.ndarray, info: dict,
                           out_dir, t0: float) -> dict:
    """Fill a baseline's texture (no histogram matching), write the per-polygon outputs and
    return the report; ``t0``: the polygon's start (time.perf_counter) for its time_s."""
    U, fill = finish_texture(U, wsum, inp.texel_mask)
    seen = (wsum > 0) & inp.texel_mask
    report = {
        "polygon_id": inp.polygon_id,
        **info,
        **fill,
        "histogram_matching": False,
        "time_s": time.perf_counter() - t0,
    }
    write_texture_outputs(out_dir, U, inp.texel_mask, seen, dominant, [p.name for p in inp.photos], report)
    return report
