"""Photos mapped through a relief height field: f_k^i of the displaced surface, and what of it each
photo sees.

A proxy polygon is a plane; the building it stands for has recessed windows, reveals and
balconies. A point of the facade at height h along the polygon's outward normal n (h < 0 in a
recess, h > 0 on a balcony) is where every photo shows that texel's colour:

    X(tx, ty) = O + s tx e_u + s ty e_v + h(tx, ty) n,

so photo k must be sampled at f_k(X), not at f_k of the plane point. Mapped this way, a recessed
window's mullion lands on the same texel in every photo and blending photos no longer smears it.

The height fields that difftex.method.relief estimates are piecewise constant (flat steps at a
few heights), so ``texel_map_relief`` maps the frame once per distinct height, each time as the
frame shifted by h n (an exact :func:`difftex.sampling.texels.texel_map`, lens distortion
included), and picks per texel; its cost grows with the number of steps, not the texels.

Self-occlusion (``relief_visibility``): seen from an angle, the wall above a recess hides the
top of the recessed pane, and a balcony hides the wall beside it. The displaced texels are
splatted into the photo with their depths; a texel is hidden when another texel lies in front
of it in the same photo cell by more than the surface's own depth spread there (a z-buffer of
the height field, as texrecon's and openMVS's visibility tests do on a mesh).

Layer: sampling (difftex.sampling.photos maps photos through these when a polygon has a relief).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from difftex.geometry.frames import UVFrame, shifted_frame, texel_homography  # noqa: F401  (shifted_frame: re-exported)
from difftex.sampling.texels import Region, TexelMap, resample_nearest, texel_map
from difftex.scene.camera import Photo

# Distinct heights a field may hold before they are merged onto a grid: mapping costs one
# texel_map per height, and a regularised field holds a handful.
MAX_STEPS = 32


@dataclass
class Relief:
    """A polygon's height field along its outward normal, on a texel grid over the polygon's
    rectangle (a level of its frame: every other level resamples it, nearest).

    ``heights`` (H, W) float32 scene units (0: on the proxy plane), ``frame`` its texel grid.
    ``hidden`` (N, H, W) bool or None: per candidate photo, the texels the relief hides from it.
    """

    frame: UVFrame
    heights: np.ndarray
    hidden: np.ndarray | None = None

    def __post_init__(self):
        if self.heights.shape != self.frame.shape:
            raise ValueError(f"heights {self.heights.shape} do not match the frame {self.frame.shape}")
        if not np.isfinite(self.heights).all():
            raise ValueError("heights must be finite")

    @property
    def flat(self) -> bool:
        return not bool(np.any(self.heights))

    def at(self, frame: UVFrame, region: Region | None = None) -> np.ndarray:
        """The heights at ``frame``'s texel centres (nearest; the steps keep their heights)."""
        return resample_nearest(self.heights, self.frame, frame, region)

    def seen(self, n: int, frame: UVFrame, region: Region | None = None) -> np.ndarray | None:
        """Whether photo ``n`` sees each texel of ``frame`` past the relief (None: no test)."""
        if self.hidden is None:
            return None
        return ~resample_nearest(self.hidden[n], self.frame, frame, region)


def quantise_heights(heights: np.ndarray, max_steps: int = MAX_STEPS) -> np.ndarray:
    """At most ``max_steps`` distinct heights: the field as is when it holds that few, else
    snapped to an even grid over its range (so mapping costs at most that many texel maps).

    Args:
        heights: (H, W) float heights.
        max_steps: the most distinct heights returned, >= 2.

    Returns:
        (H, W) float32 heights with at most ``max_steps`` distinct values; 0 stays 0.
    """
    if max_steps < 2:
        raise ValueError(f"max_steps must be >= 2, got {max_steps}")
    h = np.asarray(heights, np.float32)
    if np.unique(h).size <= max_steps:
        return h
    lo, hi = float(h.min()), float(h.max())
    step = (hi - lo) / (max_steps - 2)  # one grid point spare for 0 itself
    return np.where(h == 0, 0.0, np.round(h / step) * step).astype(np.float32)


def texel_map_relief(
    frame: UVFrame, photo: Photo, heights: np.ndarray, device: torch.device | str = "cpu", region: Region | None = None
) -> TexelMap:
    """f_k^i of the displaced surface X(tx, ty) at ``frame``'s texel centres.

    Args:
        frame: the texel grid (a level of the polygon's frame).
        photo: the photo mapped.
        heights: (h, w) heights at those texels (``region``'s size when given), scene units.
        region: only that rectangle of texels.

    Returns:
        A TexelMap whose every field is that of the frame shifted to the texel's height.
    """
    y0, y1, x0, x1 = region if region is not None else (0, frame.height, 0, frame.width)
    if heights.shape != (y1 - y0, x1 - x0):
        raise ValueError(f"heights {heights.shape} do not match the texels {(y1 - y0, x1 - x0)}")
    h = quantise_heights(heights)
    levels = np.unique(h)
    if levels.size == 1:
        return texel_map(shifted_frame(frame, float(levels[0])) if levels[0] else frame, photo, device, region)
    out: TexelMap | None = None
    for v in levels:
        tm = texel_map(shifted_frame(frame, float(v)), photo, device, region)
        sel = torch.from_numpy(h == v).to(tm.valid.device)
        if out is None:
            out = tm
            continue
        out.pix = torch.where(sel[..., None], tm.pix, out.pix)
        out.footprint = torch.where(sel, tm.footprint, out.footprint)
        out.view = torch.where(sel[None], tm.view, out.view)
        out.cos = torch.where(sel, tm.cos, out.cos)
        out.valid = torch.where(sel, tm.valid, out.valid)
    assert out is not None
    return out


class GreySweep:
    """One photo prepared for a plane sweep: its grey values at one pyramid level, sampled at the
    texels of planes parallel to the polygon (one bilinear lookup per texel and plane).

    A sweep maps every candidate photo through dozens of planes; the full mapping (three
    channels, trilinear, with the viewing geometry) would cost several times more for what a
    structure comparison needs. The level is the one whose pixels match the frame's texels
    (median footprint); pinhole cameras are mapped in closed form, others through texel_map.
    """

    def __init__(self, sampler, frame: UVFrame, photo: Photo, footprint: float):
        self.frame, self.photo, self.sampler = frame, photo, sampler
        L = int(np.clip(np.floor(np.log2(max(footprint, 1.0))), sampler.base, sampler.top))
        self.L = L
        img = sampler.level_image(L)
        grey = torch.tensor((0.299, 0.587, 0.114), device=img.device, dtype=img.dtype).view(3, 1, 1)
        self.img = (img * grey).sum(0)[None, None]
        dev = img.device
        ty, tx = torch.meshgrid(
            torch.arange(frame.height, device=dev, dtype=torch.float64) + 0.5,
            torch.arange(frame.width, device=dev, dtype=torch.float64) + 0.5,
            indexing="ij",
        )
        # the plane's homogeneous pixels, once; a shifted plane adds h K R n to them
        H = torch.from_numpy(texel_homography(frame, photo)).to(dev)
        self._q0 = torch.stack([tx * H[k, 0] + ty * H[k, 1] + H[k, 2] for k in range(3)], -1)
        self._Kn = torch.from_numpy(photo.K() @ photo.R @ np.asarray(frame.normal, np.float64)).to(dev)

    def pixels(self, h: float) -> torch.Tensor:
        """(H, W, 2) full-resolution pixels of the frame's texels shifted to height h (NaN behind)."""
        if not self.photo.is_pinhole:
            return texel_map(shifted_frame(self.frame, h), self.photo, self.img.device).pix
        q = self._q0 + h * self._Kn
        z = q[..., 2:3]
        return torch.where(z > 1e-9, q[..., :2] / z.clamp_min(1e-9), torch.full_like(q[..., :2], math.nan)).float()

    def sample(self, h: float) -> tuple[torch.Tensor, torch.Tensor]:
        """Grey values (H, W) at height h, and whether the texel lands inside the photo's crop."""
        pix = self.pixels(h)
        s = self.sampler
        img = self.img
        gx = ((pix[..., 0] - s.x0) / 2.0**self.L) / img.shape[3] * 2 - 1
        gy = ((pix[..., 1] - s.y0) / 2.0**self.L) / img.shape[2] * 2 - 1
        grid = torch.nan_to_num(torch.stack([gx, gy], -1), nan=-2.0)[None]
        val = F.grid_sample(img, grid, mode="bilinear", padding_mode="border", align_corners=False)[0, 0]
        inside = (grid[0].abs() <= 1).all(-1)
        return val, inside


def texel_depths(frame: UVFrame, photo: Photo, heights: np.ndarray) -> np.ndarray:
    """Camera-space depth (z) of every displaced texel centre X(tx, ty).

    Args:
        frame: the texel grid; heights: (H, W) its heights.

    Returns:
        (H, W) float64 depths along the photo's optical axis.
    """
    tx, ty = frame.centres()
    X = frame.texel_to_world(tx, ty) + heights[..., None].astype(np.float64) * np.asarray(frame.normal)
    return (X @ np.asarray(photo.R)[2] + float(np.asarray(photo.t)[2])).astype(np.float64)


def relief_visibility(frame: UVFrame, photo: Photo, heights: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Which displaced texels ``photo`` sees: a z-buffer of the height field splatted into the photo.

    Each texel of ``mask`` lands in a photo cell of about one texel's footprint; the nearest depth
    per cell wins, and a texel is hidden when it lies behind that by more than the flat surface's
    own depth change across a cell (2 cells' worth, so texels of one step never hide each other).

    Args:
        frame: the texel grid; heights: (H, W) its heights; mask: (H, W) bool texels considered.

    Returns:
        (H, W) bool: seen (True) or hidden by the relief (False); False outside ``mask`` or where
        the texel is not in front of the camera.
    """
    if heights.shape != frame.shape or mask.shape != frame.shape:
        raise ValueError(f"heights {heights.shape} and mask {mask.shape} must match the frame {frame.shape}")
    tm = texel_map_relief(frame, photo, heights)
    pix, fp = tm.pix.double().numpy(), tm.footprint.double().numpy()
    ok = mask & tm.valid.numpy()
    seen = np.zeros(frame.shape, bool)
    if not ok.any():
        return seen
    depth = texel_depths(frame, photo, heights)
    cell = max(float(np.median(fp[ok])), 1e-6)  # pixels per cell: one texel's footprint
    ij = np.floor(pix[ok] / cell).astype(np.int64)
    ij -= ij.min(0)
    key = ij[:, 1] * (int(ij[:, 0].max()) + 1) + ij[:, 0]
    d = depth[ok]
    nearest = np.full(int(key.max()) + 1, np.inf)
    np.minimum.at(nearest, key, d)
    # depth spread of the plane across one cell at this texel's slant: s / cos per texel along the
    # view, times the cell's size in texels
    slope = frame.texel_size * np.sqrt(np.maximum(1.0 - tm.cos.double().numpy()[ok] ** 2, 0.0)) / np.maximum(
        tm.cos.double().numpy()[ok], 0.05
    )
    tol = 2.0 * slope * (cell / np.maximum(fp[ok], 1e-6)) + 0.5 * frame.texel_size
    seen[ok] = d <= nearest[key] + tol
    return seen
