"""Evaluation metrics of texture maps (paper Tables 1 and 2); exact definitions in docs/metrics.md.

Images are float (H, W, 3) RGB arrays in [0, 1]; masks are (H, W) bool arrays of valid texels
(``None``: every texel). Each function raises DifftexError on bad input, including an empty mask.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np

from difftex.errors import DifftexError

log = logging.getLogger(__name__)

SSIM_SIGMA = 1.5  # Wang et al. 2004 (and piq): Gaussian window, sigma 1.5, 11x11


def _check_pair(name: str, a: np.ndarray, b: np.ndarray, mask: np.ndarray | None) -> np.ndarray:
    a, b = np.asarray(a), np.asarray(b)
    if a.ndim != 3 or a.shape[2] != 3:
        raise DifftexError(f"{name}: expected an (H, W, 3) image, got shape {a.shape}")
    if a.shape != b.shape:
        raise DifftexError(f"{name}: image shapes differ ({a.shape} vs {b.shape})")
    return _check_mask(name, mask, a.shape[:2])


def _check_mask(name: str, mask: np.ndarray | None, shape: tuple[int, ...]) -> np.ndarray:
    if mask is None:
        return np.ones(shape, bool)
    mask = np.asarray(mask)
    if mask.shape != tuple(shape):
        raise DifftexError(f"{name}: mask shape {mask.shape} does not match the image {tuple(shape)}")
    mask = mask.astype(bool)
    if not mask.any():
        raise DifftexError(f"{name}: the mask selects no texel")
    return mask


# --- pixel metrics -----------------------------------------------------------------------------


def texel_error(img: np.ndarray, ref: np.ndarray, normalized: bool = False) -> np.ndarray:
    """Per-texel Euclidean RGB distance (H, W); in [0, sqrt(3)], or [0, 1] if ``normalized``."""
    _check_pair("texel error", img, ref, None)
    d = np.linalg.norm(np.asarray(img, np.float64) - np.asarray(ref, np.float64), axis=2)
    return d / math.sqrt(3.0) if normalized else d


def error_percentiles(img: np.ndarray, ref: np.ndarray, mask: np.ndarray | None = None,
                      percentiles: tuple[float, ...] = (90.0, 95.0), normalized: bool = False) -> dict[float, float]:
    """Paper's Error (90%) / (95%): percentiles of the per-texel RGB distance over the mask.

    numpy's default (linear interpolation between order statistics).
    """
    mask = _check_pair("error percentiles", img, ref, mask)
    d = texel_error(img, ref, normalized)[mask]
    return {float(p): float(v) for p, v in zip(percentiles, np.percentile(d, percentiles))}


def psnr(img: np.ndarray, ref: np.ndarray, mask: np.ndarray | None = None) -> float:
    """PSNR in dB for peak 1 over the masked texels and all three channels; inf if identical."""
    mask = _check_pair("PSNR", img, ref, mask)
    mse = float(np.mean((np.asarray(img, np.float64) - np.asarray(ref, np.float64))[mask] ** 2))
    return math.inf if mse == 0.0 else 10.0 * math.log10(1.0 / mse)


def ssim(img: np.ndarray, ref: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Mean SSIM (scikit-image, RGB, data_range 1, Gaussian 11x11 window, sigma 1.5).

    Without a mask this is skimage's mean SSIM (which leaves out a 5-pixel border, where the
    window does not fit); with a mask, the SSIM map is averaged over mask minus that border.
    """
    from skimage.metrics import structural_similarity

    mask = _check_pair("SSIM", img, ref, mask)
    win = 2 * int(3.5 * SSIM_SIGMA + 0.5) + 1  # skimage's window for truncate=3.5
    if min(mask.shape) < win:
        raise DifftexError(f"SSIM: images must be at least {win}x{win} pixels, got {mask.shape[1]}x{mask.shape[0]}")
    _, smap = structural_similarity(
        np.asarray(img, np.float64), np.asarray(ref, np.float64), data_range=1.0, channel_axis=2,
        gaussian_weights=True, sigma=SSIM_SIGMA, use_sample_covariance=False, full=True)
    pad = (win - 1) // 2
    inner = np.zeros_like(mask)
    inner[pad:-pad, pad:-pad] = True
    sel = mask & inner
    if not sel.any():
        raise DifftexError(f"SSIM: the mask selects no texel at least {pad} texels from the image border")
    return float(smap[sel].mean())


def lpips(img_a: np.ndarray, img_b: np.ndarray, mask: np.ndarray | None = None, variant: str = "auto",
          required: bool = False, alexnet_path: str | Path | None = None,
          stlpips_path: str | Path | None = None, device: str = "cpu") -> tuple[float | None, str]:
    """LPIPS distance and the variant used: "lpips" (v0.1, AlexNet) or "stlpips" (shift-tolerant).

    ``variant="auto"`` prefers classic LPIPS when torchvision's AlexNet weights are on disk
    (``alexnet_path`` or the torch hub cache), else ST-LPIPS. Nothing is downloaded. When no
    weights fit, returns ``(None, "unavailable")`` with a logged reason, or raises if ``required``.
    Networks are cached per weight files (``perceptual.load_network``).
    """
    from difftex import perceptual

    mask = _check_pair("LPIPS", img_a, img_b, mask)
    source, why = perceptual.find_weights(variant, alexnet_path, stlpips_path)
    if source is None:
        if required:
            raise DifftexError(f"LPIPS ({variant}) unavailable: {why}")
        log.warning("LPIPS (%s) unavailable: %s", variant, why)
        return None, "unavailable"
    net = perceptual.load_network(source, device)
    value = perceptual.distance(net, img_a, img_b, None if mask.all() else mask, device)
    return value, source.variant


# --- perspective quality -----------------------------------------------------------------------


def _unit(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    ok = (n[..., 0] > 1e-12) & np.isfinite(n[..., 0])
    return np.where(ok[..., None], v / np.where(ok[..., None], n, 1.0), 0.0), ok


def _coverage(name: str, view_dirs: np.ndarray, mask: np.ndarray | None,
              weights: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """Unit view directions and per-texel weights of the covered texels (flattened)."""
    view_dirs = np.asarray(view_dirs, np.float64)
    if view_dirs.ndim != 3 or view_dirs.shape[2] != 3:
        raise DifftexError(f"{name}: view_dirs must be (H, W, 3), got shape {view_dirs.shape}")
    dirs, ok = _unit(view_dirs)
    if mask is None:
        mask = ok
    else:
        mask = _check_mask(name, mask, view_dirs.shape[:2])
        if not ok[mask].all():
            raise DifftexError(f"{name}: {int((~ok[mask]).sum())} masked texels have no view direction")
    w = np.ones(view_dirs.shape[:2]) if weights is None else np.asarray(weights, np.float64)
    if w.shape != view_dirs.shape[:2] or (w < 0).any() or not np.isfinite(w).all():
        raise DifftexError(f"{name}: weights must be finite, non-negative and (H, W)")
    sel = mask & (w > 0)
    if not sel.any():
        raise DifftexError(f"{name}: no covered texel with positive weight")
    return dirs[sel], w[sel]


def q_front(view_dirs: np.ndarray, normal: np.ndarray, mask: np.ndarray | None = None,
            weights: np.ndarray | None = None) -> float:
    """Viewing-angle frontality: weighted mean over covered texels of max(0, v . n), in [0, 1]."""
    dirs, w = _coverage("Q_front", view_dirs, mask, weights)
    normal = np.asarray(normal, np.float64)
    if normal.size != 3:
        raise DifftexError(f"Q_front: the normal must have 3 components, got shape {normal.shape}")
    n, ok = _unit(normal.reshape(3))
    if not ok:
        raise DifftexError("Q_front: the polygon normal is zero or not finite")
    return float(np.average(np.clip(dirs @ n, 0.0, 1.0), weights=w))


def q_vc(view_dirs: np.ndarray, mask: np.ndarray | None = None, weights: np.ndarray | None = None) -> float:
    """Viewing-angle consistency: 1 - mean angle to the mean direction / (pi/2), clipped to [0, 1]."""
    dirs, w = _coverage("Q_vc", view_dirs, mask, weights)
    mean, ok = _unit((dirs * w[:, None]).sum(axis=0))
    if not ok:
        return 0.0  # directions cancel out: no consistent direction at all
    dev = np.arccos(np.clip(dirs @ mean, -1.0, 1.0))
    return float(np.clip(1.0 - np.average(dev, weights=w) / (math.pi / 2), 0.0, 1.0))


def view_directions(points: np.ndarray, centres: np.ndarray, weights: np.ndarray | None = None,
                    mode: str = "blend") -> np.ndarray:
    """Per-texel unit direction from the texel's 3D point to the camera(s) that coloured it.

    points (H, W, 3) world points of texel centres; centres (K, 3) camera centres; weights
    (K, H, W) blend weights (None: a single camera, K = 1). ``mode="blend"``: normalised
    weighted sum of the unit directions to each camera; ``"dominant"``: the direction to the
    camera with the largest weight. Texels whose weights are all zero get a zero vector.
    """
    points = np.asarray(points, np.float64)
    centres = np.asarray(centres, np.float64).reshape(-1, 3)
    if points.ndim != 3 or points.shape[2] != 3:
        raise DifftexError(f"view directions: points must be (H, W, 3), got shape {points.shape}")
    if weights is None:
        if len(centres) != 1:
            raise DifftexError("view directions: weights are needed for more than one camera")
        weights = np.ones((1,) + points.shape[:2])
    weights = np.asarray(weights, np.float64)
    if weights.shape != (len(centres),) + points.shape[:2]:
        raise DifftexError(f"view directions: weights shape {weights.shape} is not (K, H, W) = "
                           f"{(len(centres),) + points.shape[:2]}")
    if mode not in ("blend", "dominant"):
        raise DifftexError(f"view directions: mode {mode!r} unknown (blend, dominant)")
    if mode == "dominant":
        best = np.argmax(weights, axis=0)
        dirs, _ = _unit(centres[best] - points)
        return np.where((weights.max(axis=0) > 0)[..., None], dirs, 0.0)
    acc = np.zeros_like(points)
    for c, w in zip(centres, weights):  # one camera at a time: K*H*W*3 at once can be GBs
        acc += w[..., None] * _unit(c - points)[0]
    return _unit(acc)[0]


# --- all at once ---------------------------------------------------------------------------------


def texture_metrics(img: np.ndarray, ref: np.ndarray, mask: np.ndarray | None = None,
                    lpips_variant: str = "auto", **lpips_kwargs) -> dict[str, float | str | None]:
    """Error90/95, SSIM, PSNR and LPIPS of a texture map against its ground truth (JSON-ready)."""
    err = error_percentiles(img, ref, mask)
    value, used = lpips(img, ref, mask, variant=lpips_variant, **lpips_kwargs)
    return {"error90": err[90.0], "error95": err[95.0], "ssim": ssim(img, ref, mask),
            "psnr": psnr(img, ref, mask), "lpips": value, "lpips_variant": used}
