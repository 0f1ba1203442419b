"""Texel grids: the resolution levels of a polygon's UV frame, and f_k^i, the map from a frame's
texel centres to a photo's pixels with its viewing geometry (``texel_map``), exact or with the lens
distortion interpolated from a coarse grid of exact projections.

Layer: sampling (difftex.sampling.photos.photos samples photos through these maps).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

# level_frame, resample_nearest and Region: re-exported (the texel grids' helpers live with the frames)
from difftex.geometry.frames import Region, UVFrame, level_frame, resample_nearest, texel_homography  # noqa: F401
from difftex.scene.camera import Photo

# Texel spacing of the exact projections that the distortion displacement is interpolated from
# (texel_map): the displacement of every COLMAP model is a smooth function of the position.
DISTORTION_GRID = 8


# --------------------------------------------------------------------------------------------
# Resolution levels of one UV frame


# --------------------------------------------------------------------------------------------
# f_k^i on a texel grid


@dataclass
class TexelMap:
    """f_k^i and the viewing geometry of one photo at every texel centre of a frame (torch).

    Shapes: ``pix`` (H, W, 2) full-resolution pixel coordinates (COLMAP convention, pixel
    centres at +0.5); ``footprint`` (H, W) the texel's size in pixels, sqrt|det J| of f_k^i;
    ``view`` (3, H, W) unit camera-to-texel directions (V^_k); ``cos`` (H, W) the cosine
    between the texel-to-camera direction and the normal (Q_a); ``valid`` (H, W) in front of
    the camera, inside the image, front-facing.
    """

    pix: torch.Tensor
    footprint: torch.Tensor
    view: torch.Tensor
    cos: torch.Tensor
    valid: torch.Tensor


def _exact_pixels(frame: UVFrame, photo: Photo, tx: np.ndarray, ty: np.ndarray) -> np.ndarray:
    """Projection through the camera model with distortion (pycolmap), NaN behind the camera."""
    from difftex.geometry.frames import texel_to_pixel

    pix, _ = texel_to_pixel(frame, photo, tx, ty)
    return pix




def texel_map(
    frame: UVFrame, photo: Photo, device: torch.device | str = "cpu", region: Region | None = None
) -> TexelMap:
    """f_k^i at the texel centres of ``frame`` for ``photo``, vectorised in torch.

    Pinhole cameras: the homography H = K [R | t] A, exact, with its Jacobian in closed form.
    Other COLMAP models: the homography of the undistorted camera plus the distortion
    displacement, which is computed exactly (pycolmap) every ``DISTORTION_GRID`` texels and
    interpolated bilinearly (it is smooth; tests bound the error), and the footprint likewise.
    Projecting millions of texels through pycolmap one level at a time would cost seconds per
    photo; this costs a few tensor passes. ``region``: only that rectangle of texels.
    """
    device = torch.device(device)
    y0, y1, x0, x1 = region if region is not None else (0, frame.height, 0, frame.width)
    f64 = torch.float64
    Hm = texel_homography(frame, photo)
    # Every term below is separable over the grid (a row vector plus a column vector, or their
    # product): no meshgrid of texel coordinates is built.
    tx = torch.arange(x0, x1, device=device, dtype=f64) + 0.5
    ty = torch.arange(y0, y1, device=device, dtype=f64) + 0.5

    def affine(a: float, b: float, c: float) -> torch.Tensor:  # a tx + b ty + c over the grid (h, w)
        return (a * tx)[None, :] + (b * ty + c)[:, None]

    depth = affine(*Hm[2])
    front = depth > 1e-9
    inv = 1.0 / torch.where(front, depth, torch.ones_like(depth))
    px, py = affine(*Hm[0]) * inv, affine(*Hm[1]) * inv
    # sqrt|det J| of a homography: |det J| = |det H| / depth^3
    footprint = (abs(float(np.linalg.det(Hm))) * inv.abs() ** 3).sqrt()
    pix = torch.stack([px, py], -1)
    if not photo.is_pinhole:
        pix, footprint = _distorted(frame, photo, pix, footprint, device, (y0, y1, x0, x1))
    # viewing geometry in the frame's basis (e_u, e_v, n), relative to the frame origin so that
    # float32 keeps its precision in large (e.g. UTM) coordinates: the texel-to-camera vector is
    # (cu - s tx) e_u + (cv - s ty) e_v + cn n, with c the camera centre in that basis
    s = frame.texel_size
    c = np.asarray(photo.center - frame.origin, np.float64)
    eu, ev, nrm = (np.asarray(a, np.float64) for a in (frame.e_u, frame.e_v, frame.normal))
    a_u, a_v, cn = float(c @ eu) - s * tx, float(c @ ev) - s * ty, float(c @ nrm)  # (w,), (h,)
    dist = ((a_u * a_u)[None, :] + (a_v * a_v + cn * cn)[:, None]).sqrt().clamp_min(1e-30)
    cos = cn / dist
    inv_d = (1.0 / dist).float()
    a_u32, a_v32 = a_u.float(), a_v.float()
    view = torch.stack(
        [
            -(float(eu[k]) * a_u32[None, :] + (float(ev[k]) * a_v32 + float(cn * nrm[k]))[:, None]) * inv_d
            for k in range(3)
        ]
    )
    inside = (pix[..., 0] >= 0) & (pix[..., 0] <= photo.width) & (pix[..., 1] >= 0) & (pix[..., 1] <= photo.height)
    valid = front & inside & (cos > 0) & torch.isfinite(pix).all(-1)
    pix = torch.where(front[..., None], pix, torch.full_like(pix, float("nan")))
    return TexelMap(
        pix=pix.float(),
        footprint=torch.nan_to_num(footprint, nan=1.0).float(),
        view=view,
        cos=cos.clamp(0.0, 1.0).float(),
        valid=valid,
    )


def _distorted(
    frame: UVFrame, photo: Photo, pix_u: torch.Tensor, fp_u: torch.Tensor, device, region: Region
) -> tuple[torch.Tensor, torch.Tensor]:
    """Add the lens distortion to undistorted pixels: exact on a coarse grid, bilinear between."""
    y0, y1, x0, x1 = region
    h, w = y1 - y0, x1 - x0
    g = DISTORTION_GRID
    cx = np.unique(np.minimum(np.arange(0, w + g, g), w - 1)).astype(np.float64) + 0.5 + x0
    cy = np.unique(np.minimum(np.arange(0, h + g, g), h - 1)).astype(np.float64) + 0.5 + y0
    TX, TY = np.meshgrid(cx, cy)
    exact = _exact_pixels(frame, photo, TX, TY)
    Hn = texel_homography(frame, photo)
    qn = np.stack([TX, TY, np.ones_like(TX)], -1) @ Hn.T
    with np.errstate(divide="ignore", invalid="ignore"):
        und = qn[..., :2] / qn[..., 2:3]
    disp = np.nan_to_num(exact - und, nan=0.0)
    # exact footprint on the coarse grid (forward differences of the distorted projection)
    ex_dx = _exact_pixels(frame, photo, TX + 1.0, TY)
    ex_dy = _exact_pixels(frame, photo, TX, TY + 1.0)
    a, b = ex_dx - exact, ex_dy - exact
    with np.errstate(invalid="ignore"):
        fp = np.sqrt(np.abs(a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]))
    und_fp = (
        F.grid_sample(
            fp_u[None, None].float(),
            _grid(TX - x0, TY - y0, w, h, device),
            mode="bilinear",
            padding_mode="border",
            align_corners=False,
        )[0, 0]
        .double()
        .cpu()
        .numpy()
    )
    ratio = np.nan_to_num(fp / np.maximum(und_fp, 1e-12), nan=1.0)
    coarse = torch.from_numpy(np.concatenate([disp.transpose(2, 0, 1), ratio[None]])).to(device)
    # Interpolate the coarse samples (at texel centres cx, cy) at every texel centre.
    fine = _interp_grid(coarse, cx - x0, cy - y0, w, h, device)
    return pix_u + fine[:2].permute(1, 2, 0), fp_u * fine[2]


def _grid(TX: np.ndarray, TY: np.ndarray, w: int, h: int, device) -> torch.Tensor:
    """grid_sample coordinates of texel positions (align_corners=False: -1 is the left edge)."""
    g = np.stack([TX / w * 2 - 1, TY / h * 2 - 1], -1).astype(np.float32)
    return torch.from_numpy(g).to(device)[None]


def _interp_grid(coarse: torch.Tensor, cx: np.ndarray, cy: np.ndarray, w: int, h: int, device) -> torch.Tensor:
    """Bilinear interpolation of (C, ny, nx) samples at (irregularly spaced) texel centres."""
    xs = torch.arange(w, device=device, dtype=torch.float64) + 0.5
    ys = torch.arange(h, device=device, dtype=torch.float64) + 0.5
    cxt, cyt = torch.from_numpy(cx).to(device), torch.from_numpy(cy).to(device)
    ix = (torch.searchsorted(cxt, xs, right=True) - 1).clamp(0, max(len(cx) - 2, 0))
    iy = (torch.searchsorted(cyt, ys, right=True) - 1).clamp(0, max(len(cy) - 2, 0))
    if len(cx) > 1:
        fx = ((xs - cxt[ix]) / (cxt[ix + 1] - cxt[ix])).clamp(0, 1)
    else:
        fx = torch.zeros_like(xs)
    if len(cy) > 1:
        fy = ((ys - cyt[iy]) / (cyt[iy + 1] - cyt[iy])).clamp(0, 1)
    else:
        fy = torch.zeros_like(ys)
    ix1 = (ix + 1).clamp(max=len(cx) - 1)
    iy1 = (iy + 1).clamp(max=len(cy) - 1)
    c00 = coarse[:, iy][:, :, ix]
    c01 = coarse[:, iy][:, :, ix1]
    c10 = coarse[:, iy1][:, :, ix]
    c11 = coarse[:, iy1][:, :, ix1]
    fx, fy = fx[None, None, :], fy[None, :, None]
    return (c00 * (1 - fx) + c01 * fx) * (1 - fy) + (c10 * (1 - fx) + c11 * fx) * fy
