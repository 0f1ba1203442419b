"""The UV frame of a polygon (the paper's virtual camera K~_i) and the mapping f_k^i to photos.

See docs/conventions.md for the frame definition; everything here follows it exactly.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from math import ceil

import numpy as np

from difftex.errors import DifftexError
from difftex.scene.camera import Photo
from difftex.scene.proxy import Polygon

_HORIZONTAL_SIN = float(np.sin(np.radians(10.0)))


@dataclass(frozen=True, eq=False)
class UVFrame:
    """Orthographic, fronto-parallel texel grid over a polygon's minimum-area bounding rectangle."""

    origin: np.ndarray  # (3,) world position of texel coordinate (0, 0): the rectangle corner
    e_u: np.ndarray  # (3,) unit, texel x (columns)
    e_v: np.ndarray  # (3,) unit, texel y (rows, "down")
    normal: np.ndarray  # (3,) unit outward normal; e_u x e_v = -normal
    texel_size: float  # scene units per texel
    width: int
    height: int

    @property
    def shape(self) -> tuple[int, int]:
        return self.height, self.width

    @property
    def A(self) -> np.ndarray:
        """3x3 matrix with X = A @ [tx, ty, 1]."""
        s = self.texel_size
        return np.stack([s * self.e_u, s * self.e_v, self.origin], axis=1)

    def texel_to_world(self, tx: np.ndarray, ty: np.ndarray) -> np.ndarray:
        tx = np.asarray(tx, dtype=np.float64)[..., None]
        ty = np.asarray(ty, dtype=np.float64)[..., None]
        s = self.texel_size
        return self.origin + s * tx * self.e_u + s * ty * self.e_v

    def world_to_texel(self, X: np.ndarray) -> np.ndarray:
        d = np.asarray(X, dtype=np.float64) - self.origin
        return np.stack([d @ self.e_u, d @ self.e_v], axis=-1) / self.texel_size

    def centres(self) -> tuple[np.ndarray, np.ndarray]:
        """Texel-centre coordinates (H, W) each."""
        ty, tx = np.mgrid[0 : self.height, 0 : self.width].astype(np.float64) + 0.5
        return tx, ty

    def resized(self, long_side: int) -> UVFrame:
        """Same rectangle at another resolution (coarse-to-fine levels)."""
        W_m, H_m = self.width * self.texel_size, self.height * self.texel_size
        return _frame_with_size(self.origin, self.e_u, self.e_v, self.normal, W_m, H_m, long_side, None)

    def to_dict(self) -> dict:
        return {
            "origin": self.origin.tolist(),
            "e_u": self.e_u.tolist(),
            "e_v": self.e_v.tolist(),
            "normal": self.normal.tolist(),
            "texel_size": self.texel_size,
            "width": self.width,
            "height": self.height,
        }

    @classmethod
    def from_dict(cls, d: dict) -> UVFrame:
        return cls(
            origin=np.asarray(d["origin"], float),
            e_u=np.asarray(d["e_u"], float),
            e_v=np.asarray(d["e_v"], float),
            normal=np.asarray(d["normal"], float),
            texel_size=float(d["texel_size"]),
            width=int(d["width"]),
            height=int(d["height"]),
        )


def _frame_with_size(origin, e_u, e_v, normal, W_m, H_m, long_side, density) -> UVFrame:
    if long_side is not None:
        if long_side < 1:
            raise DifftexError(f"texture long side must be >= 1, got {long_side}")
        s = max(W_m, H_m) / long_side
    elif density is not None:
        if not density > 0:
            raise DifftexError(f"texel density must be > 0, got {density}")
        s = 1.0 / density
    else:
        raise DifftexError("give a texture long side or a texel density")
    # The 1e-9 slack keeps an exact fit (W_m / s == long_side) from rounding up to long_side + 1.
    width = max(1, ceil(W_m / s - 1e-9))
    height = max(1, ceil(H_m / s - 1e-9))
    return UVFrame(origin, e_u, e_v, normal, float(s), int(width), int(height))


def uv_frame(
    polygon: Polygon,
    up: np.ndarray,
    long_side: int | None = None,
    density: float | None = None,
) -> UVFrame:
    """The polygon's UV frame per docs/conventions.md (minimum-area rectangle, 'down' = -up)."""
    import shapely

    n = polygon.normal
    if not np.isfinite(n).all() or np.linalg.norm(n) < 0.5:
        raise DifftexError(f"polygon '{polygon.id}' has no normal (degenerate)")
    o, b1, b2 = polygon.plane_basis()
    pts2 = polygon.to_plane(polygon.outer)
    # shapely's oriented envelope is the minimum-area rotated rectangle (rotating calipers).
    rect = shapely.oriented_envelope(shapely.MultiPoint(pts2))
    if rect.geom_type != "Polygon":
        raise DifftexError(f"polygon '{polygon.id}' is degenerate (its bounding rectangle is a {rect.geom_type})")
    c = np.asarray(rect.exterior.coords)[:4]
    d1_2 = c[1] - c[0]
    d1 = d1_2[0] * b1 + d1_2[1] * b2
    d1 /= np.linalg.norm(d1)
    d2 = np.cross(n, d1)
    up = np.asarray(up, dtype=np.float64)
    down = -(up - (up @ n) * n)
    # Below ~10 degrees of tilt the in-plane 'down' is dominated by the error of the estimated up
    # (1-2 degrees), so such polygons take the horizontal rule to keep their frame stable.
    if np.linalg.norm(down) > _HORIZONTAL_SIN:
        cands = [d1, -d1, d2, -d2]
        e_v = max(cands, key=lambda v: float(v @ down))
    else:
        # Horizontal polygon (roof, ceiling): no 'down' in its plane; the longer side is e_u.
        ext1 = np.ptp(polygon.outer @ d1)
        ext2 = np.ptp(polygon.outer @ d2)
        e_u0 = d1 if ext1 >= ext2 else d2
        if e_u0[int(np.argmax(np.abs(e_u0)))] < 0:
            e_u0 = -e_u0
        e_v = np.cross(e_u0, n)
    e_u = np.cross(n, e_v)
    allpts = polygon.outer
    u = allpts @ e_u
    v = allpts @ e_v
    origin = u.min() * e_u + v.min() * e_v + (polygon.offset) * n
    W_m, H_m = float(np.ptp(u)), float(np.ptp(v))
    return _frame_with_size(origin, e_u, e_v, n, W_m, H_m, long_side, density)


def look_at(center: np.ndarray, target: np.ndarray, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """cam_from_world rotation R of an upright camera at ``center`` looking at ``target``.

    COLMAP convention: R's rows are the camera's x (right), y (down) and z (forward, towards
    ``target``) in world coordinates; x = z x up, y = z x x, so y is ``-up`` made orthogonal to z.
    When ``up`` is parallel to the view direction, world y stands in for it. The translation is
    ``-R @ center``.
    """
    c = np.asarray(center, dtype=np.float64)
    z = np.asarray(target, dtype=np.float64) - c
    z /= np.linalg.norm(z)
    x = np.cross(z, np.asarray(up, dtype=np.float64))
    if np.linalg.norm(x) < 1e-9:
        x = np.cross(z, [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z])


def texel_mask(polygon: Polygon, frame: UVFrame) -> np.ndarray:
    """(H, W) bool: texel centres inside the polygon (outer boundary minus holes)."""
    from skimage.draw import polygon as fill

    def raster(loop: np.ndarray) -> np.ndarray:
        t = frame.world_to_texel(loop)
        m = np.zeros(frame.shape, bool)
        # skimage fills pixels whose integer centre is inside; texel centres sit at +0.5.
        rr, cc = fill(t[:, 1] - 0.5, t[:, 0] - 0.5, shape=frame.shape)
        m[rr, cc] = True
        return m

    mask = raster(polygon.outer)
    for h in polygon.holes:
        mask &= ~raster(h)
    if not mask.any():
        # A sliver thinner than a texel still covers the texel(s) it passes through.
        t = frame.world_to_texel(polygon.outer)
        ix = np.clip(np.floor(t[:, 0]).astype(int), 0, frame.width - 1)
        iy = np.clip(np.floor(t[:, 1]).astype(int), 0, frame.height - 1)
        mask[iy, ix] = True
    return mask


@dataclass(frozen=True, eq=False)
class TexelMapping:
    """f_k^i evaluated at texel centres: pixel position, viewing geometry, validity."""

    pix: np.ndarray  # (H, W, 2) pixel coordinates in photo k (NaN where behind the camera)
    depth: np.ndarray  # (H, W) camera z
    view_dir: np.ndarray  # (H, W, 3) unit vector from the texel's 3D point towards the camera
    cos_angle: np.ndarray  # (H, W) cosine between view_dir and the polygon normal
    valid: np.ndarray  # (H, W) bool: in front, inside the image, front-facing


def texel_homography(frame: UVFrame, photo: Photo) -> np.ndarray:
    """H = K [R | t] A: texel (tx, ty, 1) to homogeneous undistorted pixels (third entry = depth)."""
    return photo.K() @ (photo.R @ frame.A + np.outer(photo.t, [0.0, 0.0, 1.0]))


def texel_to_pixel(frame: UVFrame, photo: Photo, tx: np.ndarray, ty: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """f_k^i: continuous texel coordinates (...) to pixels (..., 2) and depth (...)."""
    if photo.is_pinhole:
        # the homography: exact for pinhole cameras and cheaper than projecting 3D points (no
        # world coordinates at all, one multiply-add per entry)
        H = texel_homography(frame, photo)
        tx, ty = np.asarray(tx, np.float64), np.asarray(ty, np.float64)
        depth = H[2, 0] * tx + H[2, 1] * ty + H[2, 2]
        pix = np.empty((*depth.shape, 2))
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / depth
            pix[..., 0] = (H[0, 0] * tx + H[0, 1] * ty + H[0, 2]) * inv
            pix[..., 1] = (H[1, 0] * tx + H[1, 1] * ty + H[1, 2]) * inv
        pix[depth <= 1e-9] = np.nan
        return pix, depth
    return photo.project(frame.texel_to_world(tx, ty))


def texel_footprint(
    frame: UVFrame, photo: Photo, pix: np.ndarray, tx: np.ndarray | None = None, ty: np.ndarray | None = None
) -> np.ndarray:
    """Texel size in pixels, sqrt(|det J|) of f_k^i by forward differences (h, w).

    Args:
        pix: (h, w, 2) f_k^i at the texel positions (``map_texels(...).pix``).
        tx, ty: (h, w) those positions; default: every texel centre of ``frame``.
    """
    if tx is None or ty is None:
        tx, ty = frame.centres()
    px, _ = texel_to_pixel(frame, photo, tx + 1.0, ty)
    py, _ = texel_to_pixel(frame, photo, tx, ty + 1.0)
    dx, dy = px - pix, py - pix
    with np.errstate(invalid="ignore"):
        area = np.abs(dx[..., 0] * dy[..., 1] - dx[..., 1] * dy[..., 0])
    return np.sqrt(area)


def pixel_to_texel(frame: UVFrame, photo: Photo, pix: np.ndarray) -> np.ndarray:
    """Inverse of f_k^i: pixels (..., 2) to texel coordinates (..., 2) on the polygon's plane.

    Rays parallel to the plane or hitting it behind the camera give NaN.
    """
    d = photo.unproject(pix)
    C = photo.center
    n = frame.normal
    denom = d @ n
    with np.errstate(divide="ignore", invalid="ignore"):
        s = ((frame.origin - C) @ n) / denom
    X = C + s[..., None] * d
    out = frame.world_to_texel(X)
    out[~(s > 0)] = np.nan
    return out


def map_texels(frame: UVFrame, photo: Photo, margin: float = 0.0) -> TexelMapping:
    """Evaluate f_k^i and the viewing geometry at every texel centre (vectorised)."""
    tx, ty = frame.centres()
    pix, depth = texel_to_pixel(frame, photo, tx, ty)
    X = frame.texel_to_world(tx, ty)
    v = photo.center - X
    v /= np.linalg.norm(v, axis=-1, keepdims=True)
    cos = v @ frame.normal
    valid = (depth > 1e-9) & photo.in_image(pix, margin) & (cos > 0)
    return TexelMapping(pix=pix, depth=depth, view_dir=v, cos_angle=cos, valid=valid)


def sample_photo(image: np.ndarray, pix: np.ndarray) -> np.ndarray:
    """Bilinear samples of an (H, W, C) image at pixel coordinates (..., 2) (COLMAP convention).

    Outside the image or at NaN coordinates the result is 0, and pixels beyond the edge count as
    0 in the interpolation (torch's grid_sample with zero padding, as the optimizer samples).
    scipy's map_coordinates does it here, not torch: the assembly and evaluation stages that call
    this would otherwise import torch for it (about 2 s per job).
    """
    from scipy.ndimage import map_coordinates

    shape = pix.shape[:-1]
    p = np.asarray(pix, dtype=np.float64).reshape(-1, 2)
    bad = np.asarray(~np.isfinite(p).all(axis=-1))
    # pixel centres at x + 0.5: array index = coordinate - 0.5
    coords = np.where(bad[:, None], -10.0, p - 0.5)[:, ::-1].T
    img = np.asarray(image, dtype=np.float32)
    res = np.stack(
        [map_coordinates(img[..., c], coords, order=1, mode="grid-constant", cval=0.0) for c in range(img.shape[2])], -1
    )
    res[bad] = 0.0
    return res.reshape(*shape, img.shape[2])  # float32: map_coordinates keeps the input's dtype


def level_sides(target_long: int, start: int, coarse_to_fine: bool, step: float = 2.0) -> list[int]:
    """Long sides of the levels: start, start x step, ... then the target (paper: 256 -> 2048, step 2).

    A last intermediate level within sqrt(step) of the target is left out (600 texels: 256 -> 600,
    not 256 -> 512 -> 600): it would cost a level's set-up and iterations (a mapping of every
    photo at nearly the full size) to refine weights that the target level refines again.
    """
    if step <= 1.0:
        raise ValueError(f"level step must be > 1, got {step}")
    if not coarse_to_fine or target_long <= start:
        return [target_long]
    sides = []
    s = float(start)
    while s < target_long:
        sides.append(round(s))
        s *= step
    if len(sides) > 1 and target_long < sides[-1] * step**0.5:
        sides.pop()
    sides.append(target_long)
    return sides


Region = tuple[int, int, int, int]  # (y0, y1, x0, x1): a rectangle of a frame's texels


def resample_nearest(arr: np.ndarray, src: UVFrame, dst: UVFrame, region: Region | None = None) -> np.ndarray:
    """(..., H, W) array of ``src`` to ``dst`` texel centres (same rectangle), nearest texel;
    ``region``: only that rectangle of ``dst``."""
    y0, y1, x0, x1 = region if region is not None else (0, dst.height, 0, dst.width)
    if src.shape == dst.shape and src.texel_size == dst.texel_size:
        return arr[..., y0:y1, x0:x1] if region is not None else arr
    r = dst.texel_size / src.texel_size
    ix = np.clip(np.floor((np.arange(x0, x1) + 0.5) * r).astype(int), 0, src.width - 1)
    iy = np.clip(np.floor((np.arange(y0, y1) + 0.5) * r).astype(int), 0, src.height - 1)
    return arr[..., iy[:, None], ix[None, :]]


def level_frame(frame: UVFrame, long_side: int) -> UVFrame:
    """The same rectangle as ``frame`` with ``long_side`` texels on its longer side."""
    return frame if long_side == max(frame.shape) else frame.resized(long_side)


def shifted_frame(frame: UVFrame, h: float) -> UVFrame:
    """``frame`` moved by ``h`` along its normal: its texel (tx, ty) is X(tx, ty) at height h."""
    origin = np.asarray(frame.origin, np.float64) + float(h) * np.asarray(frame.normal, np.float64)
    return dataclasses.replace(frame, origin=origin)
