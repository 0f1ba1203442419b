"""Photos re-sampled as ideal pinhole cameras, the only cameras the peer programs read.

texrecon reads undistorted pinhole cameras only; MeshLab's Bundler reader also puts the principal
point at the image centre and has one focal length (square pixels). One resampling per photo gives
all three: the output image is the ideal camera

    K' = [[f, 0, w/2], [0, f, h/2], [0, 0, 1]]

with the photo's own pose (``R``, ``t``). An output pixel's ray ``K'^-1 p`` is projected into the
original photo by its own camera model (:meth:`difftex.scene.camera.Photo.project_camera`, distortion
included) and the photo is sampled there. The output is the largest rectangle centred on the
principal point whose border lies inside the original photo, so no output pixel is black padding
(a peer would take that as colour).

pycolmap's undistorter (``pycolmap.undistort_images``) is not used: it keeps the principal point
where it was and ``fx != fy``, which Bundler cannot express, and centring its output would be a
second resampling of every photo.
"""

from __future__ import annotations

from dataclasses import dataclass
from math import floor

import numpy as np

from difftex.errors import DifftexError
from difftex.scene.camera import Photo


@dataclass(frozen=True)
class IdealCamera:
    """A photo's pose with an ideal pinhole camera: centred principal point, square pixels."""

    name: str  # the original photo's name
    R: np.ndarray  # (3, 3) cam_from_world rotation (the photo's)
    t: np.ndarray  # (3,) cam_from_world translation (the photo's)
    f: float  # focal length in output pixels
    width: int
    height: int

    @property
    def center(self) -> np.ndarray:
        return -self.R.T @ self.t

    def K(self) -> np.ndarray:
        return np.array([[self.f, 0.0, self.width / 2.0], [0.0, self.f, self.height / 2.0], [0.0, 0.0, 1.0]])

    def project(self, X: np.ndarray) -> np.ndarray:
        """World points (..., 3) -> output pixels (..., 2), COLMAP convention (centre of the top-left pixel at 0.5).

        Points behind the camera give NaN.
        """
        Xc = np.asarray(X, dtype=np.float64) @ self.R.T + self.t
        with np.errstate(divide="ignore", invalid="ignore"):
            uv = Xc[..., :2] / Xc[..., 2:3]
        uv[Xc[..., 2] <= 0] = np.nan
        return uv * self.f + np.array([self.width / 2.0, self.height / 2.0])


def to_source_pixels(photo: Photo, cam: IdealCamera, pix: np.ndarray) -> np.ndarray:
    """Output pixels of ``cam`` (..., 2) -> the original photo's pixels (..., 2) on the same rays."""
    pix = np.asarray(pix, dtype=np.float64)
    xy = (pix - np.array([cam.width / 2.0, cam.height / 2.0])) / cam.f
    rays = np.concatenate([xy.reshape(-1, 2), np.ones((xy.size // 2, 1))], axis=1)
    return photo.project_camera(rays).reshape(pix.shape)


def _border_inside(photo: Photo, half: np.ndarray, n: int = 64) -> bool:
    """Whether the border of the normalised rectangle [-half, half] projects inside the photo."""
    s = np.linspace(-1.0, 1.0, n)
    edges = (
        np.concatenate(
            [
                np.stack([s, np.full(n, -1.0)], 1),
                np.stack([s, np.full(n, 1.0)], 1),
                np.stack([np.full(n, -1.0), s], 1),
                np.stack([np.full(n, 1.0), s], 1),
            ]
        )
        * half
    )
    pix = photo.project_camera(np.concatenate([edges, np.ones((len(edges), 1))], axis=1))
    return bool(np.isfinite(pix).all() and photo.in_image(pix).all())


def ideal_camera(photo: Photo, long_side: int | None = None) -> IdealCamera:
    """The ideal pinhole camera a photo is resampled into.

    Args:
        photo: the registered photo (any COLMAP camera model).
        long_side: output long side in pixels; None keeps the photo's resolution (f = its fx).
            Photos are never upsampled.
    Returns:
        The camera: the photo's pose, square pixels, principal point at the centre of a
        ``width`` x ``height`` image whose every pixel sees the inside of the original photo.
    """
    K = photo.K()
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    # Half extents of the centred rectangle in normalised coordinates, without distortion.
    half0 = np.array([min(cx, photo.width - cx) / fx, min(cy, photo.height - cy) / fy])
    if not (half0 > 0).all():
        raise DifftexError(f"{photo.image_path}: principal point ({cx:.1f}, {cy:.1f}) lies outside the image")
    # Distortion can push the rectangle's border out of the photo: shrink it until it fits
    # (bisection on the scale; 1 fits for every pinhole camera and for barrel distortion).
    lo, hi = 0.0, 1.0
    if not _border_inside(photo, half0 * (1 - 1e-9)):
        for _ in range(30):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if _border_inside(photo, half0 * mid) else (lo, mid)
        if lo < 0.25:
            raise DifftexError(f"{photo.image_path}: distortion leaves no usable centred pinhole image")
        half = half0 * lo
    else:
        half = half0
    scale = 1.0 if long_side is None else min(1.0, long_side / (2 * fx * half.max()))
    f = fx * scale
    # floor: the output's extent (w / 2f) never exceeds the rectangle that fits in the photo
    w, h = max(1, floor(2 * half[0] * f + 1e-6)), max(1, floor(2 * half[1] * f + 1e-6))
    return IdealCamera(photo.name, photo.R.copy(), photo.t.copy(), float(f), int(w), int(h))


def resample(photo: Photo, cam: IdealCamera, image: np.ndarray) -> np.ndarray:
    """The photo seen through ``cam``: (cam.height, cam.width, 3) float32.

    Args:
        photo: the original photo; ``image`` its pixels (photo.height, photo.width, 3).
        cam: from :func:`ideal_camera` for this photo.
    Returns:
        Bilinear samples of ``image`` at every output pixel centre. When ``cam`` is coarser than
        the photo, the photo is first box-filtered by the integer factor floor(fx / cam.f), so
        that a downscaled output averages its pixel's footprint instead of aliasing.
    """
    import torch
    import torch.nn.functional as F

    from difftex.geometry.frames import sample_photo

    if image.shape[:2] != (photo.height, photo.width):
        raise DifftexError(
            f"{photo.image_path}: image is {image.shape[1]}x{image.shape[0]}, camera says {photo.width}x{photo.height}"
        )
    jj, ii = np.meshgrid(np.arange(cam.width) + 0.5, np.arange(cam.height) + 0.5)
    src = to_source_pixels(photo, cam, np.stack([jj, ii], -1))
    # Keep samples half a pixel inside: sample_photo pads with zeros, which would darken the rim.
    src = np.clip(src, 0.5, np.array([photo.width, photo.height]) - 0.5)
    k = max(1, int(floor(photo.K()[0, 0] / cam.f + 1e-9)))
    if k > 1:
        # Pixel (i, j) of the k-pooled image averages source pixels [k j, k j + k): its centre
        # k (j + 0.5) is source coordinate p, so pooled coordinates are p / k.
        t = torch.from_numpy(np.ascontiguousarray(image, dtype=np.float32)).permute(2, 0, 1)[None]
        image = F.avg_pool2d(t, k, ceil_mode=True)[0].permute(1, 2, 0).numpy()
        src = src / k
    return np.ascontiguousarray(np.clip(sample_photo(image, src), 0.0, 1.0), dtype=np.float32)
