"""Gaussian filters of texel maps: plain (weights, masks) and masked (colours defined on a visibility mask)."""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F


def gaussian_kernel(sigma: float) -> torch.Tensor:
    """(2r + 1,) normalised Gaussian taps of ``sigma``, r = ceil(3 sigma) (at least 1)."""
    r = max(1, int(np.ceil(3 * sigma)))
    t = torch.arange(-r, r + 1, dtype=torch.float32)
    g = torch.exp(-0.5 * (t / sigma) ** 2)
    return g / g.sum()


def blur(x: torch.Tensor, sigma: float) -> torch.Tensor:
    """(C, h, w) maps blurred by a separable Gaussian of ``sigma`` texels (edges replicated;
    sigma 0: unchanged).

    Each pass is a weighted sum of the shifted maps, one tap at a time, written out rather than
    ``F.conv2d`` with the one-channel kernel (kept on a GPU): on a CPU that convolution ran
    several times slower for the same values (tests/test_filters.py compares them), and the low-passed comparison
    colours of every candidate photo made it most of a level's set-up (docs/optimizer.md).

    Args:
        x: (C, h, w) float maps.
        sigma: Gaussian sigma in texels.

    Returns:
        (C, h, w) blurred maps.
    """
    if x.dim() != 3:
        raise ValueError(f"blur expects (C, h, w) maps, got {tuple(x.shape)}")
    if sigma <= 0:
        return x
    if x.is_cuda:  # one library kernel per pass, not 2 r + 1 launches
        k = gaussian_kernel(sigma).to(x.device)
        r = len(k) // 2
        y = F.conv2d(F.pad(x[:, None], (r, r, 0, 0), mode="replicate"), k.view(1, 1, 1, -1))
        return F.conv2d(F.pad(y, (0, 0, r, r), mode="replicate"), k.view(1, 1, -1, 1))[:, 0]
    g = gaussian_kernel(sigma).tolist()
    return _taps(_taps(x, g, dim=2), g, dim=1)


def _taps(x: torch.Tensor, g: list[float], dim: int) -> torch.Tensor:
    """One pass of :func:`blur`: sum_i g[i] x shifted by i - r along ``dim`` (edges replicated)."""
    r, n = len(g) // 2, x.shape[dim]
    pad = (r, r, 0, 0) if dim == 2 else (0, 0, r, r)
    p = F.pad(x[None], pad, mode="replicate")[0]
    out = p.narrow(dim, 0, n) * g[0]
    for i in range(1, 2 * r + 1):
        out.add_(p.narrow(dim, i, n), alpha=g[i])
    return out


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
