"""Gaussian filters of texel maps: plain (weights, masks) and masked (colours defined on a visibility mask)."""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F


def blur(x: torch.Tensor, sigma: float) -> torch.Tensor:
    """(C, h, w) maps blurred by a separable Gaussian of ``sigma`` texels (edges replicated;
    sigma 0: unchanged)."""
    if sigma <= 0:
        return x
    r = max(1, int(np.ceil(3 * sigma)))
    t = torch.arange(-r, r + 1, dtype=torch.float32, device=x.device)
    g = torch.exp(-0.5 * (t / sigma) ** 2)
    g = g / g.sum()
    y = F.conv2d(F.pad(x[:, None], (r, r, 0, 0), mode="replicate"), g.view(1, 1, 1, -1))
    return F.conv2d(F.pad(y, (0, 0, r, r), mode="replicate"), g.view(1, 1, -1, 1))[:, 0]


def masked_blur(colour: torch.Tensor, visible: torch.Tensor, sigma: float) -> torch.Tensor:
    """Normalised convolution: the Gaussian mean of the colours over the visible texels only.

    A plain blur would mix in the zeros of the texels the photo does not see, darkening its
    colours along every visibility edge (an occluder's outline, the polygon's border).

    Args:
        colour: (3, h, w) colours (anything where not visible).
        visible: (h, w) bool.
        sigma: Gaussian sigma in texels (0: the colours unchanged).

    Returns:
        (3, h, w) filtered colours, zero where not visible.
    """
    if colour.dim() != 3 or colour.shape[1:] != visible.shape:
        raise ValueError(
            f"colour (3, h, w) and visible (h, w) must match, got {tuple(colour.shape)}, {tuple(visible.shape)}"
        )
    v = visible.to(colour.dtype)[None]
    if sigma <= 0:
        return colour * v
    num = blur(colour * v, sigma)
    den = blur(v, sigma)
    return torch.where(den > 1e-6, num / den.clamp_min(1e-6), torch.zeros_like(num)) * v
