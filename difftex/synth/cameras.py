"""Camera placement (drone orbits, street level), pose noise, distortion, and the COLMAP model."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from difftex.geometry.frames import look_at
from difftex.synth.buildings import Building


@dataclass
class View:
    """A true camera (what is rendered) and the written one (true pose plus noise)."""

    name: str
    kind: str  # drone | street | heldout
    R: np.ndarray  # (3, 3) cam_from_world, true
    t: np.ndarray  # (3,)
    camera_id: int
    R_written: np.ndarray | None = None
    t_written: np.ndarray | None = None
    gain: float = 1.0
    wb: tuple[float, float, float] = (1.0, 1.0, 1.0)

    @property
    def center(self) -> np.ndarray:
        return -self.R.T @ self.t


@dataclass
class Intrinsics:
    camera_id: int
    width: int
    height: int
    f: float
    k: float  # SIMPLE_RADIAL k1; 0 means PINHOLE

    @property
    def model(self) -> str:
        return "SIMPLE_RADIAL" if self.k != 0 else "PINHOLE"

    def pycolmap(self):
        import pycolmap

        cx, cy = self.width / 2, self.height / 2
        if self.k != 0:
            params = [self.f, cx, cy, self.k]
        else:
            params = [self.f, self.f, cx, cy]
        cam = pycolmap.Camera.create_from_model_name(self.camera_id, self.model, self.f, self.width, self.height)
        cam.params = params
        return cam


def _pose(C: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """cam_from_world (R, t) of an upright camera at C looking at target."""
    R = look_at(C, target)
    return R, -R @ C


def _outside(building: Building, xy, margin: float) -> bool:
    import shapely

    return not building.footprint.buffer(margin).contains(shapely.Point(xy))


DRONE_RINGS = ((1.6, 0.55), (1.9, 1.0), (2.3, 1.6))  # (distance factor, height factor of top): the old presets'


def make_views(building: Building, n: int, street_fraction: float, rng: np.random.Generator,
               prefix: str, kind_prefix: str = "", azimuth_offset: float = 0.0, suffix: str = ".png",
               rings: tuple[tuple[float, float], ...] = DRONE_RINGS) -> list[View]:
    """Drone orbits at several heights looking obliquely down, plus street-level views at walls.

    Drone photo ``i`` flies on ring ``i mod len(rings)``: at ``radius * distance factor + 6 m``
    from the footprint's centre, ``top * height factor + U(2, 8) m`` high. ``suffix`` is the image
    files' (``.jpg`` for JPEG photos); it changes the names only."""
    lo, hi = building.bounds()
    centre = 0.5 * (lo + hi)
    radius_xy = 0.5 * np.linalg.norm(hi[:2] - lo[:2])
    top = building.top
    n_street = int(round(n * street_fraction))
    n_drone = n - n_street
    views = []
    for i in range(n_drone):
        ring = rings[i % len(rings)]
        az = azimuth_offset + 2 * np.pi * (i / max(n_drone, 1)) + rng.uniform(-0.15, 0.15)
        dist = radius_xy * ring[0] * rng.uniform(0.9, 1.1) + 6.0
        h = max(6.0, top * ring[1] + rng.uniform(2.0, 8.0))
        C = np.array([centre[0] + dist * np.cos(az), centre[1] + dist * np.sin(az), h])
        target = np.array([centre[0], centre[1], top * 0.35]) + rng.uniform(-0.25, 0.25, 3) * [
            radius_xy,
            radius_xy,
            top * 0.5,
        ]
        views.append(("drone", *_pose(C, target)))
    walls = [w for w in building.walls if w.outer[:, 2].min() < 1e-6]
    lengths = np.array([w.length for w in walls])
    k = 0
    tries = 0
    while k < n_street and tries < 200 * max(n_street, 1):
        tries += 1
        w = walls[rng.choice(len(walls), p=lengths / lengths.sum())]
        u = rng.uniform(0.2, 0.8) * w.length
        dist = rng.uniform(7.0, 14.0)
        C = w.to3d(np.array([[u + rng.uniform(-4, 4), 1.6]]), dist)[0]
        if not _outside(building, C[:2], 2.0):
            continue
        target = w.to3d(np.array([[u, min(w.eave, 12.0) * rng.uniform(0.35, 0.6)]]), 0.0)[0]
        views.append(("street", *_pose(C, target)))
        k += 1
    out = []
    for j, (kind, R, t) in enumerate(views):
        out.append(View(f"{prefix}{j:04d}{suffix}", kind_prefix or kind, R, t, 1 if kind == "drone" else 2))
    return out


def perturb(R: np.ndarray, t: np.ndarray, rot_deg: float, trans: float, rng: np.random.Generator):
    """The pose a calibration would have written: small random rotation about the centre and shift."""
    from scipy.spatial.transform import Rotation

    C = -R.T @ t
    w = rng.standard_normal(3) * np.deg2rad(rot_deg)
    Rn = Rotation.from_rotvec(w).as_matrix() @ R
    Cn = C + rng.standard_normal(3) * trans
    return Rn, -Rn @ Cn


def write_colmap(
    sparse_dir: Path, intr: list[Intrinsics], views: list[View], points=None, written: bool = True
) -> None:
    """COLMAP text model (pycolmap 4.x: each camera gets a trivial rig, each image a trivial frame).

    points: optional (xyz (P,3), rgb (P,3) uint8, observations {view index: [(point index, xy)]}).
    """
    import pycolmap

    rec = pycolmap.Reconstruction()
    for c in intr:
        rec.add_camera_with_trivial_rig(c.pycolmap())
    obs = points[2] if points is not None else {}
    keyed = {}
    for i, v in enumerate(views):
        kp = obs.get(i, [])
        xy = np.array([p[1] for p in kp], float).reshape(-1, 2)
        img = pycolmap.Image(name=v.name, keypoints=xy, camera_id=v.camera_id, image_id=i + 1)
        R, t = (v.R_written, v.t_written) if written and v.R_written is not None else (v.R, v.t)
        rec.add_image_with_trivial_frame(img, pycolmap.Rigid3d(pycolmap.Rotation3d(R), t))
        for k, (pi, _) in enumerate(kp):
            keyed.setdefault(pi, []).append((i + 1, k))
    if points is not None:
        xyz, rgb, _ = points
        for pi in sorted(keyed):
            if len(keyed[pi]) < 2:
                continue
            tr = pycolmap.Track()
            for image_id, k in keyed[pi]:
                tr.add_element(image_id, k)
            rec.add_point3D(xyz[pi], tr, rgb[pi])
    sparse_dir = Path(sparse_dir)
    sparse_dir.mkdir(parents=True, exist_ok=True)
    # pycolmap writes several files: write them into a temporary folder, then move each into place
    # (a rename each), so an interrupted run never leaves a half-written model file.
    import shutil
    import tempfile

    tmp = Path(tempfile.mkdtemp(prefix=".colmap.", dir=sparse_dir))
    try:
        rec.write_text(str(tmp))
        for f in sorted(tmp.iterdir()):
            f.replace(sparse_dir / f.name)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def undistort_canvas(intr: Intrinsics) -> tuple[int, int]:
    """Size of the undistorted render (same focal length) that covers every distorted pixel."""
    if intr.k == 0:
        return intr.width, intr.height
    cam = intr.pycolmap()
    xs = np.linspace(0, intr.width, 65)
    ys = np.linspace(0, intr.height, 49)
    border = np.concatenate(
        [
            np.stack([xs, np.zeros_like(xs)], 1),
            np.stack([xs, np.full_like(xs, intr.height)], 1),
            np.stack([np.zeros_like(ys), ys], 1),
            np.stack([np.full_like(ys, intr.width), ys], 1),
        ]
    )
    n = np.asarray(cam.cam_from_img(border))
    half_w = np.abs(n[:, 0]).max() * intr.f
    half_h = np.abs(n[:, 1]).max() * intr.f
    return 2 * int(np.ceil(half_w)) + 4, 2 * int(np.ceil(half_h)) + 4


def distortion_map(intr: Intrinsics, canvas: tuple[int, int]) -> np.ndarray:
    """For each distorted output pixel centre, the (x, y) position in the undistorted canvas."""
    cam = intr.pycolmap()
    yy, xx = np.mgrid[0 : intr.height, 0 : intr.width].astype(np.float64) + 0.5
    n = np.asarray(cam.cam_from_img(np.stack([xx.ravel(), yy.ravel()], 1)))
    cw, ch = canvas
    return np.stack([n[:, 0] * intr.f + cw / 2, n[:, 1] * intr.f + ch / 2], 1).reshape(intr.height, intr.width, 2)


def warp(img: np.ndarray, mapping: np.ndarray) -> np.ndarray:
    """Bilinear resampling of ``img`` at pixel-centre coordinates ``mapping`` (H, W, 2)."""
    from scipy.ndimage import map_coordinates

    coords = [mapping[..., 1] - 0.5, mapping[..., 0] - 0.5]
    return np.stack([map_coordinates(img[..., c], coords, order=1, mode="nearest") for c in range(img.shape[2])], -1)
