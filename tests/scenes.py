"""Small scenes built in code for tests: COLMAP text models, images, proxies."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from difftex.geometry import frames
from difftex.scene.files import write_image


def look_at(center, target, up=(0.0, 0.0, 1.0)) -> tuple[np.ndarray, np.ndarray]:
    """cam_from_world (R, t) of a camera at ``center`` looking at ``target``, upright."""
    R = frames.look_at(center, target, up)
    return R, -R @ np.asarray(center, float)


def rot_to_qvec(R: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(R).as_quat()
    return np.array([w, x, y, z])


def write_colmap_text(sparse: Path, cameras: list[tuple], images: list[tuple]) -> None:
    """cameras: (id, model, w, h, params); images: (id, name, cam_id, R, t)."""
    sparse.mkdir(parents=True, exist_ok=True)
    with open(sparse / "cameras.txt", "w") as f:
        for cid, model, w, h, params in cameras:
            f.write(f"{cid} {model} {w} {h} " + " ".join(f"{p:.17g}" for p in params) + "\n")
    with open(sparse / "images.txt", "w") as f:
        for iid, name, cid, R, t in images:
            q = rot_to_qvec(R) if np.isfinite(R).all() else np.full(4, np.nan)
            f.write(f"{iid} " + " ".join(f"{v:.17g}" for v in (*q, *t)) + f" {cid} {name}\n\n")
    (sparse / "points3D.txt").write_text("")


def write_obj(path: Path, polygons: dict[str, np.ndarray]) -> None:
    lines, n = [], 0
    faces = []
    for name, loop in polygons.items():
        for v in loop:
            lines.append("v {:.12g} {:.12g} {:.12g}".format(*v))
        faces.append((name, range(n + 1, n + 1 + len(loop))))
        n += len(loop)
    for name, idx in faces:
        lines += [f"g {name}", "f " + " ".join(map(str, idx))]
    path.write_text("\n".join(lines) + "\n")


def wall(x0, x1, z0, z1, y=0.0) -> np.ndarray:
    """A vertical rectangle in the plane y = const, facing -y (counter-clockwise seen from -y)."""
    return np.array([[x0, y, z0], [x1, y, z0], [x1, y, z1], [x0, y, z1]], float)


def make_scene(
    root: Path,
    polygons: dict[str, np.ndarray] | None = None,
    centers=((0.0, -6.0, 1.0), (2.0, -6.0, 1.5), (-2.0, -5.0, 0.5)),
    target=(0.0, 0.0, 1.0),
    size=(160, 120),
    model="PINHOLE",
    params=None,
    seed=0,
) -> Path:
    """A scene folder with a wall proxy seen by a few cameras (noise images); ``target``: one
    point all cameras look at, or one per camera."""
    rng = np.random.default_rng(seed)
    polygons = polygons if polygons is not None else {"front": wall(-2, 2, 0, 2)}
    w, h = size
    f = 0.9 * w
    if params is None:
        params = {"PINHOLE": [f, f, w / 2, h / 2], "SIMPLE_RADIAL": [f, w / 2, h / 2, -0.05]}[model]
    (root / "images").mkdir(parents=True, exist_ok=True)
    images = []
    targets = np.broadcast_to(np.asarray(target, float), (len(centers), 3))
    for i, c in enumerate(centers):
        R, t = look_at(c, targets[i])
        name = f"img{i:02d}.png"
        write_image(root / "images" / name, rng.random((h, w, 3)).astype(np.float32))
        images.append((i + 1, name, 1, R, t))
    write_colmap_text(root / "sparse" / "0", [(1, model, w, h, params)], images)
    write_obj(root / "proxy.obj", polygons)
    return root
