"""Calibrated photos: a COLMAP model read with pycolmap, projection with every COLMAP camera model.

Lens distortion is always honoured: projection goes through ``pycolmap.Camera.img_from_cam``
(and back through ``cam_from_img``), which implements every COLMAP camera model. Pinhole
models take a closed-form path that gives the same numbers without the per-call overhead.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from difftex.errors import DifftexError

log = logging.getLogger(__name__)

# the photo files a scene's images/ folder is read for (load_photos) and the workflow tracks as inputs
IMAGE_SUFFIXES = {".jpg", ".jpeg", ".png", ".tif", ".tiff", ".exr", ".bmp"}
_PINHOLE = {"SIMPLE_PINHOLE", "PINHOLE"}
# Points closer than this (in camera z, scene units) count as behind the camera.
_MIN_DEPTH = 1e-6


@dataclass(frozen=True, eq=False)
class Photo:
    """One registered photo: intrinsics (a pycolmap camera) and the cam_from_world pose."""

    name: str
    image_path: Path
    camera: Any  # pycolmap.Camera; typed loosely so the dataclass stays picklable-free of pycolmap
    R: np.ndarray  # (3, 3) rotation, cam_from_world
    t: np.ndarray  # (3,) translation, cam_from_world
    width: int
    height: int
    model: str = field(default="PINHOLE")

    @property
    def center(self) -> np.ndarray:
        return -self.R.T @ self.t

    @property
    def up(self) -> np.ndarray:
        """The world direction that appears upwards in the photo (-y of the camera)."""
        return -self.R[1]

    @property
    def forward(self) -> np.ndarray:
        return self.R[2]

    @property
    def is_pinhole(self) -> bool:
        return self.model in _PINHOLE

    def K(self) -> np.ndarray:
        return np.asarray(self.camera.calibration_matrix(), dtype=np.float64)

    def to_camera(self, X: np.ndarray) -> np.ndarray:
        """World points (..., 3) to camera coordinates (..., 3)."""
        return np.asarray(X, dtype=np.float64) @ self.R.T + self.t

    def project_camera(self, Xc: np.ndarray) -> np.ndarray:
        """Camera-frame points (N, 3) with z > 0 to pixels (N, 2), distortion included."""
        Xc = np.asarray(Xc, dtype=np.float64).reshape(-1, 3)
        if self.is_pinhole:
            K = self.K()
            uv = Xc[:, :2] / Xc[:, 2:3]
            return uv @ K[:2, :2].T + K[:2, 2]
        if len(Xc) == 0:
            return np.zeros((0, 2))
        return np.asarray(self.camera.img_from_cam(Xc), dtype=np.float64).reshape(-1, 2)

    def project(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World points (..., 3) -> (pixels (..., 2), depth (...)).

        Points behind the camera get NaN pixels and their (non-positive) depth.
        """
        X = np.asarray(X, dtype=np.float64)
        shape = X.shape[:-1]
        Xc = self.to_camera(X.reshape(-1, 3))
        depth = Xc[:, 2]
        pix = np.full((len(Xc), 2), np.nan)
        front = depth > _MIN_DEPTH
        if front.any():
            pix[front] = self.project_camera(Xc[front])
        return pix.reshape(*shape, 2), depth.reshape(shape)

    def unproject(self, pix: np.ndarray) -> np.ndarray:
        """Pixels (..., 2) -> unit ray directions in world coordinates (..., 3)."""
        pix = np.asarray(pix, dtype=np.float64)
        shape = pix.shape[:-1]
        flat = pix.reshape(-1, 2)
        if self.is_pinhole:
            K = self.K()
            xy = (flat - K[:2, 2]) / np.array([K[0, 0], K[1, 1]])
        else:
            xy = np.asarray(self.camera.cam_from_img(flat), dtype=np.float64).reshape(-1, 2)
        d = np.concatenate([xy, np.ones((len(xy), 1))], axis=1) @ self.R  # R^T d
        d /= np.sqrt(np.einsum("ij,ij->i", d, d))[:, None]
        return d.reshape(*shape, 3)

    def in_image(self, pix: np.ndarray, margin: float = 0.0) -> np.ndarray:
        x, y = pix[..., 0], pix[..., 1]
        with np.errstate(invalid="ignore"):
            return (
                np.isfinite(x)
                & (x >= margin)
                & (y >= margin)
                & (x <= self.width - margin)
                & (y <= self.height - margin)
            )


def _rigid(image) -> tuple[np.ndarray, np.ndarray]:
    cfw = image.cam_from_world() if callable(image.cam_from_world) else image.cam_from_world
    return np.asarray(cfw.rotation.matrix(), dtype=np.float64), np.asarray(cfw.translation, dtype=np.float64)


def read_reconstruction(sparse_dir: str | Path):
    """pycolmap.Reconstruction from a binary or text COLMAP model, checked (difftex.scene.colmap)."""
    from difftex.scene.colmap import read_model

    return read_model(sparse_dir)


def model_file(sparse_dir: Path, stem: str) -> Path:
    """The file that defines ``stem`` (cameras/images): the binary one when both exist, as read."""
    binary = sparse_dir / f"{stem}.bin"
    return binary if binary.is_file() else sparse_dir / f"{stem}.txt"


def image_files(images_dir: str | Path) -> list[Path]:
    """The scene's photo files, in name order: every file under ``images_dir`` (searched
    recursively, as COLMAP names may hold folders) with an image suffix; none when the folder is
    not there. The workflow's inputs, the filter's photo chunks and the unlisted-photo warning all
    list the photos with this, so they agree on them."""
    root = Path(images_dir)
    if not root.is_dir():
        return []
    return sorted(p for p in root.rglob("*") if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file())


def unlisted_photos(images_dir: Path, listed: set[str]) -> list[str]:
    """Photo files under ``images_dir`` (relative names, as COLMAP writes them) that the model
    does not list, sorted."""
    names = (p.relative_to(images_dir).as_posix() for p in image_files(images_dir))
    return sorted(n for n in names if n not in listed)


def check_photo_file(photo: Photo, sparse_dir: str | Path) -> None:
    """Stop with one line naming the photo's file when it is missing or its size is not its
    camera's (the header only is read)."""
    from difftex.scene.files import image_size

    sparse_dir = Path(sparse_dir)
    path = photo.image_path
    if not path.is_file():
        raise DifftexError(f"{path}: image listed in {model_file(sparse_dir, 'images')} is missing")
    size = image_size(path)
    if size != (photo.width, photo.height):
        raise DifftexError(
            f"{path}: image is {size[0]}x{size[1]} but camera {photo.camera.camera_id} in "
            f"{model_file(sparse_dir, 'cameras')} says {photo.width}x{photo.height}"
        )


def load_photos(
    sparse_dir: str | Path, images_dir: str | Path, check_images: bool = True, reconstruction=None
) -> list[Photo]:
    """All registered images of a COLMAP model, sorted by name.

    The model is checked when read (difftex.scene.colmap: cameras, poses, duplicate names). With
    ``check_images``, a missing image file or one whose size disagrees with its camera is an error
    naming the image (header only is read here; pixels are read on use), and photos in
    ``images_dir`` that the model does not list are ignored with one warning giving their count.

    Args:
        sparse_dir: the COLMAP model folder.
        images_dir: the photos; the model's image names are relative to it.
        check_images: check the files (False where only the cameras are needed).
        reconstruction: the already read model of ``sparse_dir``, to avoid reading it again.
    """
    sparse_dir = Path(sparse_dir)
    rec = reconstruction if reconstruction is not None else read_reconstruction(sparse_dir)
    images_dir = Path(images_dir)
    if check_images and not images_dir.is_dir():
        raise DifftexError(f"{images_dir}: images folder not found")
    images_file = model_file(sparse_dir, "images")
    photos = []
    for image in rec.images.values():
        if hasattr(image, "has_pose") and not image.has_pose:
            continue  # unregistered image: COLMAP keeps it in the model without a pose
        cam = rec.cameras[image.camera_id]
        R, t = _rigid(image)
        path = images_dir / image.name
        if abs(np.linalg.det(R) - 1.0) > 1e-3:
            raise DifftexError(
                f"{images_file}: image '{image.name}': rotation is not a rotation (det {np.linalg.det(R):.3f})"
            )
        photo = Photo(
            name=image.name,
            image_path=path,
            camera=cam,
            R=R,
            t=t,
            width=int(cam.width),
            height=int(cam.height),
            model=str(cam.model_name),
        )
        if check_images:
            check_photo_file(photo, sparse_dir)
        photos.append(photo)
    if not photos:
        raise DifftexError(f"{images_file}: COLMAP model has no registered images")
    if check_images:
        warn_unlisted(images_dir, rec, images_file)
    return sorted(photos, key=lambda p: p.name)


def warn_unlisted(images_dir: Path, rec, images_file: Path) -> None:
    """One warning giving the count of photos in ``images_dir`` that the model ``rec`` (read from
    ``images_file``) does not list: they are ignored."""
    extra = unlisted_photos(images_dir, {im.name for im in rec.images.values()})
    if extra:
        shown = ", ".join(extra[:3]) + (", ..." if len(extra) > 3 else "")
        log.warning(
            "%s: %d photo%s not in the COLMAP model %s, ignored (%s)",
            images_dir,
            len(extra),
            "s are" if len(extra) > 1 else " is",
            images_file,
            shown,
        )


def scene_up(photos: list[Photo]) -> np.ndarray:
    """Unit 'up' of the scene: photos are taken upright, so their up vectors agree on it."""
    ups = np.stack([p.up for p in photos])
    up = ups.mean(axis=0)
    norm = np.linalg.norm(up)
    if norm < 1e-6:  # cameras disagree (e.g. nadir-only set): fall back to the first photo's up
        return ups[0] / np.linalg.norm(ups[0])
    return up / norm
