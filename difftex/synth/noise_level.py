"""How noisy a photo is: a flat-patch noise estimator, to put synthetic photos next to real ones.

The estimator is Immerkaer's ("Fast noise variance estimation", CVIU 64(2), 1996): the image is
filtered with the 3x3 mask ``[[1, -2, 1], [-2, 4, -2], [1, -2, 1]]``, the difference of two
Laplacians, which cancels constants, ramps and (mostly) smooth shading; for white Gaussian noise
of std ``s`` the filtered values have std ``6 s``, and ``E|.| = 6 s sqrt(2 / pi)``. Texture and
edges leak through the mask, so it is taken only on *flat* tiles: the image is cut into tiles,
tiles holding clipped pixels (no noise there) are dropped, the rest are ranked by the std of their
Gaussian-smoothed luminance (structure, little noise), and the median estimate of the flattest
``flat_fraction`` is the image's noise. scikit-image's ``estimate_sigma`` (a wavelet MAD, Donoho)
would do as well but needs PyWavelets, which difftex does not depend on.

It measures noise at the scale of the pixels given: box-downsample first (``box_downsample``)
to measure it at the texel scale. On strongly textured images at coarse scales, texture the
smoothing cannot tell from noise still leaks in, so the value is an upper bound there.
"""

from __future__ import annotations

import numpy as np

from difftex.errors import DifftexError

_MASK = np.array([[1.0, -2.0, 1.0], [-2.0, 4.0, -2.0], [1.0, -2.0, 1.0]])


def _check(img: np.ndarray, name: str) -> np.ndarray:
    a = np.asarray(img)
    if a.ndim == 2:
        a = a[..., None]
    if a.ndim != 3 or not np.issubdtype(a.dtype, np.floating):
        raise DifftexError(f"{name}: expected a float (H, W) or (H, W, C) image, got {a.shape} {a.dtype}")
    if min(a.shape[:2]) < 3:
        raise DifftexError(f"{name}: image too small ({a.shape[:2]}), need at least 3x3 pixels")
    return a


def box_downsample(img: np.ndarray, factor: int) -> np.ndarray:
    """Average ``factor`` x ``factor`` blocks (a trailing partial block is dropped).

    Args:
        img: image.
        factor: block size, >= 1.

    Returns:
        The downsampled image, float32.

    Shape:
        img: (H, W, C); returns (H // factor, W // factor, C).
    """
    a = _check(img, "box_downsample")
    if factor < 1:
        raise DifftexError(f"box_downsample: factor must be >= 1, got {factor}")
    if factor == 1:
        return a.astype(np.float32)
    h, w = a.shape[0] // factor * factor, a.shape[1] // factor * factor
    return a[:h, :w].reshape(h // factor, factor, w // factor, factor, -1).mean((1, 3)).astype(np.float32)


def immerkaer_sigma(img: np.ndarray) -> float:
    """Noise std of a whole image (or tile) by Immerkaer's estimator, averaged over channels.

    Args:
        img: image with at least 3x3 pixels, in the units the noise is wanted in.

    Returns:
        The estimated std of additive white noise.

    Shape:
        img: (H, W) or (H, W, C).
    """
    from scipy import ndimage

    a = _check(img, "immerkaer_sigma").astype(np.float64)
    sig = []
    for c in range(a.shape[-1]):
        r = ndimage.convolve(a[..., c], _MASK, mode="reflect")[1:-1, 1:-1]
        sig.append(np.sqrt(np.pi / 2) * np.abs(r).mean() / 6.0)
    return float(np.mean(sig))


def noise_sigma(img: np.ndarray, tile: int = 32, flat_fraction: float = 0.1, clip_margin: float = 2 / 255,
                min_tiles: int = 8) -> float:
    """Noise std of an image measured on its flattest unclipped tiles (see the module docstring).

    Args:
        img: image in [0, 1] (e.g. sRGB floats of an 8-bit photo).
        tile: tile side in pixels, >= 8.
        flat_fraction: share of the usable tiles, flattest first, whose median is returned.
        clip_margin: a tile with a value within this of 0 or 1 is dropped (clipped, no noise).
        min_tiles: fewer usable tiles than this raises (too small or too clipped an image).

    Returns:
        The estimated noise std, in the image's units.

    Shape:
        img: (H, W) or (H, W, C).
    """
    from scipy import ndimage

    a = _check(img, "noise_sigma")
    if tile < 8 or not 0 < flat_fraction <= 1:
        raise DifftexError(f"noise_sigma: need tile >= 8 and 0 < flat_fraction <= 1, got {tile}, {flat_fraction}")
    # Structure, not noise: a Gaussian of sigma 2 leaves about 1/7 of white noise's std.
    smooth = ndimage.gaussian_filter(a.mean(-1).astype(np.float64), 2.0)
    rows = []
    for y in range(0, a.shape[0] - tile + 1, tile):
        for x in range(0, a.shape[1] - tile + 1, tile):
            t = a[y:y + tile, x:x + tile]
            if (t <= clip_margin).any() or (t >= 1 - clip_margin).any():
                continue
            rows.append((smooth[y:y + tile, x:x + tile].std(), immerkaer_sigma(t)))
    if len(rows) < min_tiles:
        raise DifftexError(f"noise_sigma: only {len(rows)} unclipped {tile}x{tile} tiles (need {min_tiles})")
    arr = np.array(rows)
    flat = arr[np.argsort(arr[:, 0], kind="stable")[: max(1, int(round(len(arr) * flat_fraction)))], 1]
    return float(np.median(flat))
