"""Composition of a polygon's texture from per-photo weights.

``compose_from_photos`` streams the candidate photos one at a time at the target resolution:
U(t) = sum_k w_k(t) I^_k(t) / sum_k w_k(t), with I^_k the photo mapped into texel space and w_k
any per-photo weight field (a baseline's). The method composes from its own slots instead
(difftex.compose.texturing), with no second pass over the photos. Hole filling and the source
map are in difftex.compose.fill (numpy only).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

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
