"""A scene folder: images/, sparse/0/ (COLMAP model), proxy.{obj,ply,off,glb,gltf}."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from difftex.camera import Photo, load_photos, scene_up
from difftex.errors import DifftexError
from difftex.proxy import Proxy, load_proxy

PROXY_NAMES = ("proxy.obj", "proxy.ply", "proxy.off", "proxy.glb", "proxy.gltf")


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
    photos = load_photos(find_sparse(root), root / "images", check_images=check_images)
    return Scene(root=root, photos=photos, proxy=proxy, up=scene_up(photos))
