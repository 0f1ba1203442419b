"""Evaluation metrics of texture maps (paper Tables 1 and 2); exact definitions in docs/metrics.md.

Images are float (H, W, 3) RGB arrays in [0, 1]; masks are (H, W) bool arrays of valid texels
(``None``: every texel). Each function raises DifftexError on bad input, including an empty mask.

Which library computes what, and why (the comparisons are tests/test_metrics.py):

- PSNR: our own 10 log10(1 / MSE), not ``piq.psnr`` (see :func:`psnr` for why).
- SSIM: scikit-image, not piq. The evaluation needs SSIM *over a mask* (a polygon's texels in
  its bounding rectangle; the textured pixels of a held-out view), i.e. the per-pixel SSIM map
  averaged over the mask. ``piq.ssim`` only returns the mean over the whole image (its map is
  internal), and running it on the mask's bounding rectangle would average texels outside the
  polygon too; ``skimage.metrics.structural_similarity(full=True)`` returns the map. Unmasked,
  the two agree to 1e-12 in float64 with piq's ``downsample=False``; piq's default
  ``downsample=True`` first average-pools by round(min(H, W) / 256), which scores a 2048-texel
  map at 256 texels (0.97 instead of 0.87 on a noisy 512x512 pair) and is not used here. SSIM
  is computed in float64: in float32, E[x^2] - E[x]^2 cancels on flat regions (1e-4 off on a
  constant image).
- Error 90/95: the paper's own definition (percentiles of per-texel RGB distances); no library
  has it.
- LPIPS: piq's (VGG16, the paper's citation), built from piq's and torchvision's weight files in
  the torch hub cache (downloaded there once, as piq does, where the network allows) or a
  configured folder; without them ST-LPIPS from ``stlpips_pytorch``, whose wheel ships its
  weights, said in one line (see :func:`lpips`).
"""

from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np

from difftex.errors import DifftexError
from difftex.evaluation.perceptual import (
    LPIPS_MIN_SIDE,
    lpips_fallback_note,
    lpips_source,
    lpips_weight_files,
    network,
)

log = logging.getLogger(__name__)

SSIM_SIGMA = 1.5  # Wang et al. 2004 (and piq): Gaussian window, sigma 1.5, 11x11
RANGE_TOL = 1e-5  # float rounding of resampled [0, 1] images (bilinear weights in float32)


def _check_pair(name: str, a: np.ndarray, b: np.ndarray,
                mask: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(a, b, mask) checked: same (H, W, 3) shape, finite, in [0, 1] (float64, rounding clipped)."""
    a, b = np.asarray(a), np.asarray(b)
    if a.ndim != 3 or a.shape[2] != 3:
        raise DifftexError(f"{name}: expected an (H, W, 3) image, got shape {a.shape}")
    if a.shape != b.shape:
        raise DifftexError(f"{name}: image shapes differ ({a.shape} vs {b.shape})")
    out = []
    for img in (a, b):
        img = img.astype(np.float64)
        if not np.isfinite(img).all():
            raise DifftexError(f"{name}: the image holds NaN or infinite values")
        lo, hi = float(img.min()), float(img.max())
        if lo < -RANGE_TOL or hi > 1 + RANGE_TOL:
            # Every metric here assumes data range 1 (SSIM's constants, PSNR's peak, LPIPS's
            # mapping to [-1, 1]); HDR values must be mapped by the caller first.
            raise DifftexError(f"{name}: image values must lie in [0, 1], got [{lo:.4g}, {hi:.4g}]")
        out.append(np.clip(img, 0.0, 1.0))
    return out[0], out[1], _check_mask(name, mask, a.shape[:2])


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
    img, ref, _ = _check_pair("texel error", img, ref, None)
    d = np.linalg.norm(img - ref, axis=2)
    return d / math.sqrt(3.0) if normalized else d


def error_percentiles(img: np.ndarray, ref: np.ndarray, mask: np.ndarray | None = None,
                      percentiles: tuple[float, ...] = (90.0, 95.0), normalized: bool = False) -> dict[float, float]:
    """Paper's Error (90%) / (95%): percentiles of the per-texel RGB distance over the mask.

    numpy's default (linear interpolation between order statistics).
    """
    img, ref, mask = _check_pair("error percentiles", img, ref, mask)
    d = texel_error(img, ref, normalized)[mask]
    return {float(p): float(v) for p, v in zip(percentiles, np.percentile(d, percentiles))}


def mean_gradient(img: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Mean colour gradient magnitude over the mask: sharpness, compared with the ground truth's.

    Forward differences between 4-neighbours, mean over channels, over the pairs whose two texels
    are both in the mask. A blurred texture scores below its reference, noise and seams above.

    Args:
        img: (H, W, 3) image in [0, 1].
        mask: (H, W) bool texels, or None for all.
    Returns:
        Mean absolute difference per neighbour pair, in [0, 1].
    """
    img, _, mask = _check_pair("mean gradient", img, img, mask)
    gx = np.abs(np.diff(img, axis=1)).mean(-1)
    gy = np.abs(np.diff(img, axis=0)).mean(-1)
    mx, my = mask[:, 1:] & mask[:, :-1], mask[1:, :] & mask[:-1, :]
    n = int(mx.sum() + my.sum())
    if n == 0:
        raise DifftexError("mean gradient: the mask holds no pair of neighbouring texels")
    return float((gx[mx].sum() + gy[my].sum()) / n)


def detail_gain(img: np.ndarray, ref: np.ndarray, mask: np.ndarray | None = None) -> float:
    """The share of the reference's detail the image reproduces: the least-squares gain of the
    image's gradients on the reference's, sum(grad img . grad ref) / sum(|grad ref|^2).

    Forward differences between 4-neighbours, per channel, over the pairs whose two texels are
    both in the mask (as :func:`mean_gradient`). 1: the reference's edges at their contrast and
    place; below 1: blurred, displaced or missing; noise adds nothing in expectation, since it
    does not correlate with the reference's gradients. :func:`mean_gradient` counts noise, seams
    and an occluder's edges as sharpness; a single photo's texture (the most frontal one) then
    outscores a blend that shows the facade's own edges as well.

    Args:
        img, ref: (H, W, 3) images in [0, 1].
        mask: (H, W) bool texels, or None for all.
    Returns:
        The gain (about [0, 1]; above 1 where the image's edges are stronger than the reference's).
    """
    img, ref, mask = _check_pair("detail gain", img, ref, mask)
    num = den = 0.0
    for axis, m in ((1, mask[:, 1:] & mask[:, :-1]), (0, mask[1:, :] & mask[:-1, :])):
        gi = np.diff(img, axis=axis)[m].astype(np.float64)
        gr = np.diff(ref, axis=axis)[m].astype(np.float64)
        num += float((gi * gr).sum())
        den += float((gr * gr).sum())
    if den <= 0:
        raise DifftexError("detail gain: the reference has no gradient on the mask's neighbouring texels")
    return num / den


def psnr_from_mse(mse: float) -> float:
    """PSNR in dB for peak 1: 10 log10(1 / MSE); inf for MSE 0."""
    if not mse >= 0.0:
        raise DifftexError(f"PSNR: the mean squared error must be >= 0, got {mse}")
    return math.inf if mse == 0.0 else 10.0 * math.log10(1.0 / mse)


def psnr(img: np.ndarray, ref: np.ndarray, mask: np.ndarray | None = None) -> float:
    """PSNR in dB (peak 1) over the masked texels and all three channels; inf if identical.

    Our own two lines rather than ``piq.psnr``: piq adds 1e-8 to the MSE (identical images give
    80 dB; a PSNR of P dB reads 10 log10(1 + 1e-8 * 10^(P/10)) dB low, 4e-4 dB at 40 dB), and the
    evaluation also pools PSNR over all polygons' texels from summed squared errors
    (:func:`psnr_from_mse`), which piq's per-image value cannot give without holding every
    texel at once. On the same texels the two agree within that offset (tests/test_metrics.py).

    Args:
        img, ref: (H, W, 3) images in [0, 1].
        mask: (H, W) bool texels to use, or None for all.
    Returns:
        PSNR in dB.
    """
    img, ref, mask = _check_pair("PSNR", img, ref, mask)
    return psnr_from_mse(float(np.mean((img - ref)[mask] ** 2)))


def ssim(img: np.ndarray, ref: np.ndarray, mask: np.ndarray | None = None) -> float:
    """Mean SSIM (scikit-image, RGB, data_range 1, Gaussian 11x11 window, sigma 1.5).

    scikit-image rather than piq because the mean is taken over a mask (see the module
    docstring). Without a mask this is skimage's mean SSIM (which leaves out a 5-pixel border,
    where the window does not fit), equal to ``piq.ssim(..., downsample=False)``; with a mask,
    the SSIM map is averaged over mask minus that border.

    Args:
        img, ref: (H, W, 3) images in [0, 1], at least 11x11.
        mask: (H, W) bool texels to average over, or None for all.
    Returns:
        Mean SSIM in [-1, 1].
    """
    from skimage.metrics import structural_similarity

    img, ref, mask = _check_pair("SSIM", img, ref, mask)
    win = 2 * int(3.5 * SSIM_SIGMA + 0.5) + 1  # skimage's window for truncate=3.5
    if min(mask.shape) < win:
        raise DifftexError(f"SSIM: images must be at least {win}x{win} pixels, got {mask.shape[1]}x{mask.shape[0]}")
    _, smap = structural_similarity(img, ref, data_range=1.0, channel_axis=2, gaussian_weights=True,
                                    sigma=SSIM_SIGMA, use_sample_covariance=False, full=True)
    pad = (win - 1) // 2
    inner = np.zeros_like(mask)
    inner[pad:-pad, pad:-pad] = True
    sel = mask & inner
    if not sel.any():
        raise DifftexError(f"SSIM: the mask selects no texel at least {pad} texels from the image border")
    return float(smap[sel].mean())


# --- perceptual distance (LPIPS through piq, ST-LPIPS; the networks: difftex.evaluation.perceptual) ---


def lpips(img_a: np.ndarray, img_b: np.ndarray, mask: np.ndarray | None = None, variant: str = "auto",
          required: bool = False, weights_dir: str | Path | None = None,
          device: str = "cpu") -> tuple[float | None, str]:
    """LPIPS distance, and the label of what computed it.

    Args:
        img_a, img_b: (H, W, 3) images in [0, 1], at least 32x32.
        mask: (H, W) bool pixels to average the distance map over (spatial mode), or None for
            the plain (per-layer spatial mean) distance.
        variant: "lpips" (classic LPIPS through piq: VGG16 with piq's linear weights, both read
            from ``weights_dir`` or the torch hub cache, :func:`lpips_weight_files`; missing from
            the hub cache, they are downloaded there once per process, unless there is no
            network or ``DIFFTEX_OFFLINE`` is set), "stlpips" (``stlpips_pytorch``, shift-tolerant
            AlexNet, weights shipped in the package), or "auto" (classic if its weights are on
            disk or could be downloaded, else ST-LPIPS, said in one warning line).
        required: raise instead of returning None when no weights are available.
        weights_dir: the folder holding piq's two weight files (default: the torch hub cache).
        device: torch device of the network (cached per device).
    Returns:
        (distance, label): the label names the package, version and weights, or is
        "unavailable: <why>" with distance None. A configured ``weights_dir`` is only read.
    """
    import torch

    img_a, img_b, mask = _check_pair("LPIPS", img_a, img_b, mask)
    if min(mask.shape) < LPIPS_MIN_SIDE:
        raise DifftexError(f"LPIPS needs images of at least {LPIPS_MIN_SIDE}x{LPIPS_MIN_SIDE} pixels, got "
                           f"{mask.shape[1]}x{mask.shape[0]}")
    kind, label = lpips_source(variant, weights_dir)
    if kind is None:
        if required:
            raise DifftexError(f"LPIPS ({variant}) {label}")
        log.warning("LPIPS (%s) %s", variant, label)
        return None, label
    if variant == "auto" and kind == "stlpips":
        log.warning("%s", lpips_fallback_note(weights_dir))
    spatial = not mask.all()
    # keyed by the folder the files are read from (TORCH_HOME may change within a process)
    folder = str(lpips_weight_files(weights_dir)["lpips"].parent) if kind == "lpips" else None
    net = network(kind, folder, spatial, device)
    a, b = (torch.from_numpy(v.astype(np.float32)).permute(2, 0, 1)[None].to(device) for v in (img_a, img_b))
    cudnn = torch.backends.cudnn
    # full float32 convolutions on a GPU: cuDNN's default TF32 (10-bit mantissa) moved VGG16's
    # LPIPS by 2e-4 relative on an H100, more than the metric's own rounding
    no_tf32 = cudnn.flags(enabled=cudnn.enabled, benchmark=cudnn.benchmark, deterministic=cudnn.deterministic,
                          allow_tf32=False)
    with torch.no_grad(), no_tf32:
        d = net(a, b, normalize=True)  # normalize: inputs in [0, 1] (ST-LPIPS maps them to [-1, 1])
    if not spatial:
        return float(d), label
    m = torch.from_numpy(mask).to(device)
    return float(d[0, 0][m].mean()), label


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
