"""A scene folder: images/, sparse/0/ (COLMAP model), proxy.{obj,ply,off,glb,gltf,city.json,json}; and the check
that the proxy and the COLMAP model share a frame and units."""

from __future__ import annotations

import itertools
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from difftex.errors import DifftexError
from difftex.scene.camera import Photo, load_photos, read_reconstruction, scene_up
from difftex.scene.proxy import Proxy, load_proxy

log = logging.getLogger(__name__)

# the first one present is the proxy; proxy.city.json / proxy.json are CityJSON (difftex.scene.cityjson)
PROXY_NAMES = ("proxy.obj", "proxy.ply", "proxy.off", "proxy.glb", "proxy.gltf", "proxy.city.json", "proxy.json")

# Proxy-to-points agreement (measured on the shared scenes and the synthetic one: the median
# distance of the COLMAP points to the proxy is 0.000-0.013 of the points' extent, and 0.22-24
# when the proxy is scaled by 0.1 to 100; docs/failures.md).
MIN_POINTS = 20  # fewer: no check (the filter's "no photo sees the proxy" error remains)
MAX_POINTS = 5000  # a strided subset is enough for medians
FAR_ERROR, FAR_WARN = 0.5, 0.15  # median point-to-proxy distance / points' extent
SMALL_ERROR = 0.05  # proxy size / points' extent


@dataclass(frozen=True, eq=False)
class Scene:
    root: Path
    photos: list[Photo]
    proxy: Proxy
    up: np.ndarray

    @property
    def name(self) -> str:
        return self.root.resolve().name

    def photo(self, name: str) -> Photo:
        for p in self.photos:
            if p.name == name:
                return p
        raise DifftexError(f"{self.root}: no photo named '{name}' in the COLMAP model")


def find_proxy(root: Path) -> Path:
    for name in PROXY_NAMES:
        if (root / name).is_file():
            return root / name
    raise DifftexError(f"{root}: no proxy model ({', '.join(PROXY_NAMES)})")


def find_sparse(root: Path) -> Path:
    for cand in (root / "sparse" / "0", root / "sparse"):
        if (cand / "cameras.bin").is_file() or (cand / "cameras.txt").is_file():
            return cand
    raise DifftexError(f"{root}: no COLMAP model in sparse/0 (cameras.bin/.txt)")


def model_points(rec, limit: int = MAX_POINTS) -> np.ndarray:
    """(N, 3) positions of at most ``limit`` COLMAP points, evenly strided over the point ids."""
    n = len(rec.points3D)
    step = max(1, -(-n // limit))
    pts = [p.xyz for p in itertools.islice(rec.points3D.values(), 0, None, step)]
    return np.asarray(pts, dtype=np.float64).reshape(-1, 3)


def distance_to_proxy(proxy: Proxy, points: np.ndarray) -> np.ndarray:
    """Euclidean distance of each point (N, 3) to the nearest proxy polygon (holes excluded).

    Per polygon: the offset from its plane and, in the plane, the distance to the polygon
    (0 inside), combined by Pythagoras. shapely measures the in-plane distance.
    """
    import shapely

    best = np.full(len(points), np.inf)
    for poly in proxy.polygons:
        uv = poly.to_plane(points)
        h = (points - poly.outer[0]) @ poly.normal
        shape = shapely.Polygon(poly.to_plane(poly.outer), [poly.to_plane(x) for x in poly.holes])
        inplane = shapely.distance(shapely.points(uv), shape)
        best = np.minimum(best, np.hypot(h, np.nan_to_num(inplane, nan=np.inf)))
    return best


def check_alignment(proxy: Proxy, points: np.ndarray, model_path: Path) -> None:
    """Stop when the proxy cannot be in the COLMAP model's frame and units.

    A correct proxy runs through the reconstructed points: most lie on it. Wrong units (a
    proxy in centimetres, millimetres or kilometres) or another frame leave the points far from
    every polygon (error when the median distance exceeds half the points' extent, warning above
    0.15), or make the proxy a speck inside the cloud (error below 1/20 of the extent).

    Args:
        proxy: the loaded proxy.
        points: (N, 3) COLMAP points; fewer than MIN_POINTS skips the check.
        model_path: the COLMAP model folder, for the message.
    """
    if len(points) < MIN_POINTS:
        return
    lo, hi = np.percentile(points, 5, axis=0), np.percentile(points, 95, axis=0)
    extent = float(np.linalg.norm(hi - lo))
    if not extent > 0:
        return
    verts = np.concatenate([p.outer for p in proxy.polygons])
    size = float(np.linalg.norm(np.ptp(verts, axis=0)))
    far = float(np.median(distance_to_proxy(proxy, points))) / extent
    what = (
        f"the proxy is {size:.4g} across and the COLMAP points of {model_path} {extent:.4g} "
        f"(ratio {size / extent:.3g}); the median point lies {far:.2g} x that extent from the proxy"
    )
    if far > FAR_ERROR or size / extent < SMALL_ERROR:
        raise DifftexError(
            f"{proxy.path}: the proxy does not fit the COLMAP model: {what}. Wrong units or another frame?"
        )
    if far > FAR_WARN:
        log.warning("%s: many COLMAP points are far from the proxy: %s", proxy.path, what)


def load_scene(
    root: str | Path,
    proxy_path: str | Path | None = None,
    check_images: bool = True,
    angle_tol_deg: float = 1.0,
    dist_tol_rel: float = 1e-3,
) -> Scene:
    root = Path(root)
    if not root.is_dir():
        raise DifftexError(f"{root}: scene folder not found")
    proxy = load_proxy(proxy_path or find_proxy(root), angle_tol_deg=angle_tol_deg, dist_tol_rel=dist_tol_rel)
    sparse = find_sparse(root)
    rec = read_reconstruction(sparse)
    photos = load_photos(sparse, root / "images", check_images=check_images, reconstruction=rec)
    check_alignment(proxy, model_points(rec), sparse)
    return Scene(root=root, photos=photos, proxy=proxy, up=scene_up(photos))
