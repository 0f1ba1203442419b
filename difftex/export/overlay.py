"""Pictures for a person to check alignment: proxy polygons drawn over a photo."""

from __future__ import annotations

from math import ceil

import numpy as np

from difftex.geometry.visibility import id_buffer
from difftex.scene.camera import Photo
from difftex.scene.proxy import Proxy


def palette(n: int, seed: int = 7) -> np.ndarray:
    """n distinct, saturated colours (stable for a seed)."""
    import colorsys

    rng = np.random.default_rng(seed)
    hues = (np.arange(n) * 0.618033988749895 + rng.random()) % 1.0
    return np.array([colorsys.hsv_to_rgb(h, 0.75, 1.0) for h in hues], dtype=np.float32).reshape(n, 3)


def proxy_overlay(proxy: Proxy, photo: Photo, image: np.ndarray, long_side: int = 1200) -> np.ndarray:
    """Downscaled photo tinted by the visible polygon (id buffer) with all polygon edges drawn.

    Edges are sampled densely and projected point by point, so lens distortion bends them as it
    bends the building in the photo.
    """
    from skimage.draw import disk
    from skimage.transform import resize

    stride = max(1, ceil(max(photo.width, photo.height) / long_side))
    ids, _ = id_buffer(proxy, photo, stride=stride)
    h, w = ids.shape
    small = resize(image, (h, w), anti_aliasing=True).astype(np.float32)
    colours = palette(len(proxy.polygons))
    out = small.copy()
    seen = ids >= 0
    out[seen] = 0.55 * small[seen] + 0.45 * colours[ids[seen]]
    for j, poly in enumerate(proxy.polygons):
        for loop in (poly.outer, *poly.holes):
            a, b = loop, np.roll(loop, -1, axis=0)
            t = np.linspace(0, 1, 200)[None, :, None]
            pts = (a[:, None] * (1 - t) + b[:, None] * t).reshape(-1, 3)
            pix, depth = photo.project(pts)
            ok = (depth > 0) & photo.in_image(pix)
            for x, y in pix[ok] / stride:
                rr, cc = disk((y, x), 1.2, shape=(h, w))
                out[rr, cc] = colours[j] * 0.5 + 0.5
    return out
