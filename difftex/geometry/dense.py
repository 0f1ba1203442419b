"""Dense geometry the user already holds, read into the proxy's world frame.

Photogrammetry users who hold a proxy and COLMAP photos nearly always hold a dense reconstruction
of the same photos as well. Its surface is the relief the proxy lacks (recessed windows, balconies,
a cornice): mapped through it, the photos agree on the facade's detail (difftex.sampling.relief),
and no plane sweep from oblique photos has to find it (difftex.method.relief; docs/dense.md).

Three kinds are read (:func:`find_source` picks one from a scene's ``dense/`` folder or a path):

- a point cloud: COLMAP's ``fused.ply`` (binary x, y, z, nx, ny, nz, red, green, blue) or
  OpenMVS's ``scene_dense.ply``, any PLY without faces (:func:`read_cloud`);
- a mesh: COLMAP's ``meshed-poisson.ply`` / ``meshed-delaunay.ply``, OpenMVS's
  ``scene_dense_mesh.ply``, a Metashape or RealityCapture export as PLY, OBJ or GLB
  (:func:`read_mesh`);
- a COLMAP dense workspace: ``stereo/depth_maps/*.geometric.bin`` (photometric ones where no
  geometric one exists) with the undistorted cameras of ``sparse/``, back-projected to points
  (:func:`read_depth_maps`); what ``difftex dense`` (the GPU stage) writes.

PLY and mesh files are parsed by trimesh (a dependency); depth maps by pycolmap's DepthMap.
Every reader raises one DifftexError line naming the file on bad input; :func:`check_frame`
rejects geometry that is not in the proxy's coordinate frame (a cloud of another scene, or
left in a local frame when the proxy is georeferenced).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from difftex.errors import DifftexError

# Names the photogrammetry tools give their outputs, best evidence first: the fused cloud holds
# every point the photos agreed on; a Poisson mesh smooths and invents surface over holes.
CLOUD_NAMES = ("fused.ply", "scene_dense.ply", "scene_dense_filtered.ply")
MESH_NAMES = ("meshed-delaunay.ply", "meshed-poisson.ply", "scene_dense_mesh_refine.ply", "scene_dense_mesh.ply")
MESH_SUFFIXES = (".ply", ".obj", ".glb", ".gltf")
DEPTH_DIR = Path("stereo") / "depth_maps"
# A cloud with fewer of its points than this share near the proxy (its box grown by a tenth of its
# size) is not of this building in this frame: a survey's cloud also holds the ground and the
# neighbours, but not 99 % of them away from the proxy.
MIN_NEAR_SHARE = 0.01


@dataclass(frozen=True)
class DenseSource:
    """Where a scene's dense geometry is: its ``kind`` and ``path`` (a file, or a COLMAP dense
    workspace folder for ``depth``)."""

    kind: Literal["cloud", "mesh", "depth"]
    path: Path


@dataclass
class DenseMesh:
    """A triangle mesh: ``vertices`` (V, 3) float64 world, ``faces`` (F, 3) int64."""

    vertices: np.ndarray
    faces: np.ndarray
    _scene: Any = field(default=None, init=False, repr=False)

    @property
    def centre(self) -> np.ndarray:
        """(3,) the origin of the ray scene's float32 coordinates (UTM coordinates are large)."""
        return self.vertices.mean(0)

    def scene(self):
        """Its Mitsuba scene (difftex.geometry.raycast.mitsuba_scene) relative to ``centre``, built
        once: a tile's polygons all cast against the same mesh."""
        if self._scene is None:
            from difftex.geometry.raycast import mitsuba_scene

            self._scene = mitsuba_scene(self.vertices - self.centre, self.faces)
        return self._scene


def ply_elements(path: Path) -> dict[str, int]:
    """The element counts of a PLY file's header ({"vertex": N, "face": F, ...}).

    Raises:
        DifftexError: the file is not PLY, or its header is cut.
    """
    with open(path, "rb") as f:
        if f.readline().strip() != b"ply":
            raise DifftexError(f"{path}: not a PLY file (no 'ply' header line)")
        counts: dict[str, int] = {}
        for _ in range(1000):  # a header holds a few dozen lines
            line = f.readline()
            if not line:
                break
            words = line.split()
            if words[:1] == [b"element"] and len(words) == 3:
                counts[words[1].decode("ascii", "replace")] = int(words[2])
            elif words[:1] == [b"end_header"]:
                return counts
    raise DifftexError(f"{path}: PLY header without end_header (a cut or corrupt file)")


def classify(path: Path) -> DenseSource:
    """The kind of one file or folder of dense geometry (a PLY's header says cloud or mesh)."""
    path = Path(path)
    if path.is_dir():
        if (path / DEPTH_DIR).is_dir():
            return DenseSource("depth", path)
        found = _search(path)
        if found is None:
            raise DifftexError(f"{path}: no dense geometry here (a cloud, a mesh or stereo/depth_maps/)")
        return found
    if not path.is_file():
        raise DifftexError(f"{path}: dense geometry not found")
    suffix = path.suffix.lower()
    if suffix == ".ply":
        return DenseSource("mesh" if ply_elements(path).get("face", 0) > 0 else "cloud", path)
    if suffix in MESH_SUFFIXES:
        return DenseSource("mesh", path)
    raise DifftexError(f"{path}: not dense geometry (give a .ply cloud or mesh, an .obj / .glb mesh, or a "
                       "COLMAP dense workspace folder)")


def _search(folder: Path) -> DenseSource | None:
    """The best dense geometry in a folder (CLOUD_NAMES, MESH_NAMES, a workspace, any mesh file)."""
    for name in (*CLOUD_NAMES, *MESH_NAMES):
        if (folder / name).is_file():
            return classify(folder / name)
    if (folder / DEPTH_DIR).is_dir() and any((folder / DEPTH_DIR).glob("*.bin")):
        return DenseSource("depth", folder)
    for suffix in MESH_SUFFIXES:
        files = sorted(folder.glob(f"*{suffix}"))
        if files:
            return classify(files[0])
    return None


def find_source(scene_dir: str | Path, source: str) -> DenseSource | None:
    """The scene's dense geometry.

    Args:
        scene_dir: the scene folder.
        source: ``auto`` (the scene's ``dense/`` folder when it holds any), ``none``, or a path
            (relative to the scene folder, or absolute) to a file or folder.

    Returns:
        The source, or None (``none``, or ``auto`` without a ``dense/`` folder holding geometry).
    """
    if source == "none":
        return None
    if source == "auto":
        folder = Path(scene_dir) / "dense"
        return _search(folder) if folder.is_dir() else None
    path = Path(source)
    return classify(path if path.is_absolute() else Path(scene_dir) / path)


def read_cloud(path: Path) -> np.ndarray:
    """A PLY point cloud's points.

    Returns:
        (N, 3) float64 world coordinates.
    """
    import trimesh

    ply_elements(path)  # one line for a file that is not PLY, before trimesh's own errors
    try:
        geom = trimesh.load(str(path), file_type="ply", process=False)
    except Exception as exc:  # noqa: BLE001 - trimesh raises many kinds on corrupt files
        why = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise DifftexError(f"{path}: unreadable PLY ({why})") from None
    xyz = np.asarray(getattr(geom, "vertices", np.zeros((0, 3))), np.float64)
    return _finite(xyz, path)


def read_mesh(path: Path) -> DenseMesh:
    """A PLY, OBJ or GLB mesh, its scenes' parts merged in world coordinates."""
    import trimesh

    if path.suffix.lower() == ".ply":
        ply_elements(path)
    try:
        mesh = trimesh.load(str(path), force="mesh", process=False)
    except Exception as exc:  # noqa: BLE001 - trimesh raises many kinds on corrupt files
        why = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise DifftexError(f"{path}: unreadable mesh ({why})") from None
    faces = np.asarray(getattr(mesh, "faces", np.zeros((0, 3))), np.int64).reshape(-1, 3)
    if len(faces) == 0:
        raise DifftexError(f"{path}: a mesh without faces")
    vertices = np.asarray(mesh.vertices, np.float64)  # type: ignore[attr-defined]  # force="mesh": a Trimesh
    return DenseMesh(_finite(vertices, path), faces)


def _finite(xyz: np.ndarray, path: Path) -> np.ndarray:
    xyz = xyz.reshape(-1, 3)
    if len(xyz) == 0:
        raise DifftexError(f"{path}: holds no points")
    keep = np.isfinite(xyz).all(1)
    if not keep.any():
        raise DifftexError(f"{path}: no finite point")
    return xyz[keep]


def depth_map_file(workspace: Path, name: str) -> Path | None:
    """The geometric depth map of photo ``name`` (the photometric one where none), or None."""
    for kind in ("geometric", "photometric"):
        f = workspace / DEPTH_DIR / f"{name}.{kind}.bin"
        if f.is_file():
            return f
    return None


def read_depth_maps(workspace: Path, stride: int = 2) -> np.ndarray:
    """A COLMAP dense workspace's depth maps back-projected to world points.

    Depth maps may be smaller than their undistorted photos (PatchMatch's max_image_size): the
    intrinsics are scaled to the map.

    Args:
        workspace: a folder with ``sparse/`` (the undistorted, pinhole model) and ``stereo/depth_maps/``.
        stride: every ``stride``-th pixel in each direction (the maps hold one depth per pixel,
            more than a height field at the photos' resolution needs).

    Returns:
        (N, 3) float64 world points.
    """
    import pycolmap

    from difftex.scene.camera import read_reconstruction

    rec = read_reconstruction(workspace / "sparse")
    out = []
    for image in rec.images.values():
        f = depth_map_file(workspace, image.name)
        if f is None:
            continue
        dm = pycolmap.DepthMap()
        try:
            dm.read(str(f))
        except Exception as exc:  # noqa: BLE001 - pycolmap raises bare errors with C++ context
            raise DifftexError(f"{f}: unreadable COLMAP depth map ({type(exc).__name__})") from None
        depth = np.asarray(dm.to_array(), np.float64)
        cam = rec.cameras[image.camera_id]
        cfw = image.cam_from_world() if callable(image.cam_from_world) else image.cam_from_world
        R, t = np.asarray(cfw.rotation.matrix()), np.asarray(cfw.translation)
        out.append(back_project(depth, np.asarray(cam.calibration_matrix()), (cam.width, cam.height), R, t, stride))
    if not out:
        raise DifftexError(f"{workspace / DEPTH_DIR}: no depth map of a photo of {workspace / 'sparse'}")
    return _finite(np.concatenate(out), workspace / DEPTH_DIR)


def back_project(
    depth: np.ndarray, K: np.ndarray, size: tuple[int, int], R: np.ndarray, t: np.ndarray, stride: int = 1
) -> np.ndarray:
    """World points of a pinhole depth map (COLMAP: depth along the optical axis, 0 for none).

    Args:
        depth: (h, w) depths; K: (3, 3) intrinsics of the photo of ``size`` (width, height)
            pixels (scaled to the map's size here); R, t: cam_from_world.

    Returns:
        (M, 3) float64, the pixels with a positive depth.
    """
    h, w = depth.shape
    sx, sy = w / size[0], h / size[1]
    fx, fy, cx, cy = K[0, 0] * sx, K[1, 1] * sy, K[0, 2] * sx, K[1, 2] * sy
    ys, xs = np.mgrid[0:h:stride, 0:w:stride]
    d = depth[ys, xs]
    ok = np.isfinite(d) & (d > 0)
    x, y, d = xs[ok] + 0.5, ys[ok] + 0.5, d[ok]
    cam = np.stack([(x - cx) / fx * d, (y - cy) / fy * d, d], axis=1)
    return (cam - t) @ R  # R^T (X_cam - t), row-wise


def check_frame(points: np.ndarray, lo: np.ndarray, hi: np.ndarray, path: Path) -> None:
    """Raise when the points are not in the proxy's frame: fewer than MIN_NEAR_SHARE of them
    within its bounding box (``lo``, ``hi``) grown by a tenth of its diagonal.

    Args:
        points: (N, 3) world; lo, hi: (3,) the proxy's bounding box.
    """
    size = float(np.linalg.norm(hi - lo))
    pad = 0.1 * size
    sample = points[:: max(1, len(points) // 200_000)]
    near = np.all((sample >= lo - pad) & (sample <= hi + pad), axis=1)
    if near.mean() >= MIN_NEAR_SHARE:
        return
    gap = np.maximum(np.maximum(lo - sample, sample - hi), 0.0)
    median = float(np.median(np.linalg.norm(gap, axis=1)))
    raise DifftexError(
        f"{path}: not in the proxy's frame: the median distance of its points to the proxy is {median:.4g} scene "
        f"units, the proxy spans {size:.4g} ({100 * near.mean():.2f} % of the points near it); reconstruct it "
        "from the same COLMAP model, or transform it to the proxy's coordinates"
    )
