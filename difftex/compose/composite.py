"""Composition of a polygon's texture from per-photo weights, hole filling, the texel source
map, and the per-polygon output files.

``compose_from_photos`` streams the candidate photos one at a time at the target resolution:
U(t) = sum_k w_k(t) I^_k(t) / sum_k w_k(t), with I^_k the photo mapped into texel space and w_k
any per-photo weight field (a baseline's). The method composes from its own slots instead
(difftex.compose.texturing), with no second pass over the photos.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch
import torch.nn.functional as F

from difftex.sampling.photos import MappedPhoto, PhotoSet


def compose_from_photos(
    photos: PhotoSet, weight_of: Callable[[int, MappedPhoto], torch.Tensor | None], transfers: list | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """(U (H, W, 3), weight sum (H, W)) at the target frame; ``weight_of(n, mapped)`` gives photo n's (H, W) weights."""
    inp, device = photos.inp, photos.device
    H, W = inp.frame.shape
    acc = torch.zeros(3, H, W, device=device)
    wsum = torch.zeros(H, W, device=device)
    for n in sorted(photos.samplers):
        mp = photos.map(n, inp.frame, inp.texel_mask, transfers[n] if transfers is not None else None)
        if mp is None:
            continue
        w = weight_of(n, mp)
        if w is None:
            continue
        w = w.to(device) * mp.visible
        acc += mp.colour * w[None]
        wsum += w
    U = acc / wsum.clamp_min(1e-12)[None]
    U = torch.where(wsum[None] > 0, U, torch.zeros_like(U))
    return U.permute(1, 2, 0).cpu().numpy(), wsum.cpu().numpy()


def fill_holes(img: np.ndarray, known: np.ndarray, levels: int = 16) -> np.ndarray:
    """Fill unknown texels from their neighbours by push-pull (masked pyramid averaging).

    Smooth and fast at 2048^2; skimage's biharmonic inpainting would take minutes at that size
    and nearest-neighbour filling leaves streaks. Known texels are returned unchanged.
    """
    known = np.asarray(known, bool)
    if known.all() or not known.any():
        return img.copy()
    x = torch.from_numpy(np.ascontiguousarray(img, dtype=np.float32)).permute(2, 0, 1)[None]
    m = torch.from_numpy(known.astype(np.float32))[None, None]
    pyr = [(x * m, m)]
    for _ in range(levels):
        c, w = pyr[-1]
        if min(c.shape[-2:]) <= 1 or bool((w > 0).all()):
            break
        pyr.append((F.avg_pool2d(c, 2, ceil_mode=True), F.avg_pool2d(w, 2, ceil_mode=True)))
    c, w = pyr[-1]
    est = c / w.clamp_min(1e-8)
    if not bool((w > 0).all()):  # coarsest level still has gaps: use the global mean there
        mean = (c.sum((2, 3)) / w.sum((2, 3)).clamp_min(1e-8))[:, :, None, None]
        est = torch.where(w > 0, est, mean.expand_as(est))
    for c, w in reversed(pyr[:-1]):
        up = F.interpolate(est, size=c.shape[-2:], mode="bilinear", align_corners=False)
        own = c / w.clamp_min(1e-8)
        a = w.clamp(0, 1)
        est = a * own + (1 - a) * up
    out = est[0].permute(1, 2, 0).numpy()
    res = img.astype(np.float32).copy()
    res[~known] = out[~known]
    return res


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
