"""Colour spaces and brightness transfers: RGB <-> HSV and monotone per-channel HSV maps.

A transfer is an array (3, 2, N_KNOTS): for each HSV channel, knots (source value, reference
value) of a piecewise-linear monotone map (estimated by difftex.compose.histmatch). Photos are mapped
through their transfer at every resolution level and in the final composition.

Why not a library: kornia (torch HSV) is not a dependency, and scikit-image's rgb2hsv works on
numpy arrays on the CPU, while these run on the optimizer's torch tensors (and device).
"""

from __future__ import annotations

import numpy as np
import torch

N_KNOTS = 129
QUANTILES = np.linspace(0.005, 0.995, N_KNOTS - 2)


def rgb_to_hsv(rgb: torch.Tensor) -> torch.Tensor:
    """(3, ...) RGB in [0, 1] to HSV with H in [0, 1)."""
    r, g, b = rgb[0], rgb[1], rgb[2]
    v, _ = rgb.max(0)
    mn, _ = rgb.min(0)
    c = v - mn
    s = torch.where(v > 0, c / v.clamp_min(1e-12), torch.zeros_like(v))
    cz = c.clamp_min(1e-12)
    h = torch.where(v == r, ((g - b) / cz) % 6, torch.where(v == g, (b - r) / cz + 2, (r - g) / cz + 4))
    h = torch.where(c > 0, h / 6.0, torch.zeros_like(h)) % 1.0
    return torch.stack([h, s, v])


def hsv_to_rgb(hsv: torch.Tensor) -> torch.Tensor:
    h, s, v = hsv[0] % 1.0, hsv[1].clamp(0, 1), hsv[2]
    out = []
    for n in (5.0, 3.0, 1.0):
        k = (n + h * 6.0) % 6.0
        out.append(v - v * s * torch.clamp(torch.minimum(k, 4.0 - k), 0.0, 1.0))
    return torch.stack(out)


def identity_transfer() -> np.ndarray:
    """(3, 2, N_KNOTS) knots (source, reference) per HSV channel that map every value to itself."""
    x = np.concatenate([[0.0], QUANTILES, [1.0]])
    return np.stack([np.stack([x, x])] * 3).astype(np.float32)


def _interp(x: torch.Tensor, xs: torch.Tensor, ys: torch.Tensor) -> torch.Tensor:
    """Piecewise-linear map (np.interp for torch, clamped at the ends)."""
    i = torch.searchsorted(xs, x.contiguous().clamp(float(xs[0]), float(xs[-1])), right=True).clamp(1, len(xs) - 1)
    x0, x1, y0, y1 = xs[i - 1], xs[i], ys[i - 1], ys[i]
    t = ((x - x0) / (x1 - x0).clamp_min(1e-12)).clamp(0.0, 1.0)
    return y0 + t * (y1 - y0)


def knots_gain(xs: np.ndarray, ys: np.ndarray) -> float | None:
    """g when the knots (xs, ys) of one channel are y = min(1, g x) (a brightness gain), else None."""
    if xs[0] != 0.0 or ys[0] != 0.0 or xs[1] <= 0:
        return None
    g = float(ys[1] / xs[1])
    return g if np.allclose(ys, np.minimum(1.0, g * xs), rtol=0, atol=1e-6) else None


def _apply_channel(x: torch.Tensor, xs: np.ndarray, ys: np.ndarray) -> torch.Tensor:
    """One HSV channel through its knots: unchanged (identity knots, hue by default), scaled (a
    gain: one multiply instead of a search among the knots, which differs from the knots'
    polyline only inside the one interval that holds the kink at 1) or piecewise linear."""
    if np.array_equal(xs, ys):
        return x
    g = knots_gain(xs, ys)
    if g is not None:
        return (g * x).clamp(0.0, 1.0)
    t = torch.as_tensor(np.stack([xs, ys]), dtype=x.dtype, device=x.device)
    return _interp(x.reshape(-1), t[0], t[1]).reshape(x.shape)


def apply_transfer_torch(rgb: torch.Tensor, transfer: np.ndarray) -> torch.Tensor:
    """Apply a (3, 2, N_KNOTS) HSV transfer to colours (3, ...) in [0, 1]."""
    t = np.asarray(transfer, np.float32)
    hsv = rgb_to_hsv(rgb.clamp(0.0, 1.0))
    return hsv_to_rgb(torch.stack([_apply_channel(hsv[c], t[c, 0], t[c, 1]) for c in range(3)]))


def apply_transfer(rgb: np.ndarray, transfer: np.ndarray) -> np.ndarray:
    """numpy (..., 3) convenience wrapper of apply_transfer_torch."""
    t = torch.from_numpy(np.moveaxis(np.asarray(rgb, np.float32), -1, 0).copy())
    return np.moveaxis(apply_transfer_torch(t, transfer).numpy(), 0, -1)
