"""The heights stage: each polygon's height field from the scene's dense geometry, one file per polygon.

A tile of polygons (the visibility stage's tiles, so a district fans out as visibility does)
reads the dense geometry once (difftex.geometry.dense), keeps what lies near its polygons, and
writes per polygon ``<out>/<polygon>.npz``: the field's frame, its heights and statistics
(difftex.geometry.heightfield). The texturing stages map the photos through it
(difftex.compose.texturing); a polygon without a file keeps its plane.

No torch here: the initialization stage reads these files and must not import it.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from difftex.errors import DifftexError
from difftex.geometry.dense import DenseMesh, DenseSource, check_frame, read_cloud, read_depth_maps, read_mesh
from difftex.geometry.frames import UVFrame, level_frame, resample_nearest
from difftex.geometry.heightfield import HeightFieldConfig, height_field

log = logging.getLogger(__name__)

HEIGHTS_VERSION = 1


def read_geometry(source: DenseSource, box: tuple[np.ndarray, np.ndarray], pad: float) -> np.ndarray | DenseMesh:
    """The source's points (a cloud, or depth maps back-projected) or mesh, checked to be in the
    proxy's frame (``box``: the proxy's bounding box) and, for points, cut to ``box`` grown by ``pad``.

    Returns:
        (N, 3) float64 points, or a DenseMesh.
    """
    lo, hi = box
    if source.kind == "mesh":
        mesh = read_mesh(source.path)
        check_frame(mesh.vertices, lo, hi, source.path)
        return mesh
    points = read_cloud(source.path) if source.kind == "cloud" else read_depth_maps(source.path)
    check_frame(points, lo, hi, source.path)
    return points[np.all((points >= lo - pad) & (points <= hi + pad), axis=1)]


def polygon_box(frame: UVFrame, lo: float, hi: float) -> tuple[np.ndarray, np.ndarray]:
    """The world box of a polygon's rectangle swept from ``lo`` to ``hi`` along its normal."""
    s = frame.texel_size
    u, v = frame.width * s * frame.e_u, frame.height * s * frame.e_v
    corners = np.array([frame.origin + a * u + b * v + h * frame.normal
                        for a in (0, 1) for b in (0, 1) for h in (lo, hi)])
    return corners.min(0), corners.max(0)


def polygon_field(
    geometry, frame: UVFrame, mask: np.ndarray, cfg: HeightFieldConfig
) -> tuple[UVFrame, np.ndarray, dict]:
    """One polygon's field from the tile's geometry (points are cut to the polygon's box first).

    Args:
        frame: the polygon's texture frame; mask: (H, W) bool at ``frame``.

    Returns:
        (the field's frame, (h, w) float32 heights, statistics).
    """
    small = level_frame(frame, min(cfg.long_side, max(frame.shape)))
    m = resample_nearest(mask, frame, small)
    if isinstance(geometry, DenseMesh):
        return small, *height_field(small, m, cfg, mesh=geometry)
    lo, hi = cfg.bounds(small)
    blo, bhi = polygon_box(small, lo, hi)
    near = geometry[np.all((geometry >= blo) & (geometry <= bhi), axis=1)]
    return small, *height_field(small, m, cfg, points=near)


def write_heights(path: Path, polygon_id: str, frame: UVFrame, heights: np.ndarray, stats: dict) -> None:
    """One polygon's field file (atomically)."""
    from difftex.scene.files import write_npz

    write_npz(path, version=np.array(HEIGHTS_VERSION), polygon_id=np.array(polygon_id),
              frame=np.array(json.dumps(frame.to_dict())), heights=heights.astype(np.float32),
              stats=np.array(json.dumps(stats)))


def read_heights(path: Path, polygon_id: str) -> tuple[UVFrame, np.ndarray, dict]:
    """A field file's (frame, (h, w) heights, statistics), checked to be ``polygon_id``'s."""
    from difftex.scene.files import read_npz

    d = read_npz(path)
    try:
        if int(d["version"]) != HEIGHTS_VERSION or str(d["polygon_id"]) != polygon_id:
            raise DifftexError(f"{path}: a height field of another polygon or version (run the heights stage again)")
        frame = UVFrame.from_dict(json.loads(str(d["frame"])))
        heights = np.asarray(d["heights"], np.float32)
        if heights.shape != frame.shape or not np.isfinite(heights).all():
            raise DifftexError(f"{path}: heights do not match their frame, or are not finite")
        return frame, heights, json.loads(str(d["stats"]))
    except KeyError as exc:
        raise DifftexError(f"{path}: not a height-field file (no {exc.args[0]!r})") from None


def tile_heights(
    scene_dir: Path, source: DenseSource, visibility: list[Path], cfg: HeightFieldConfig, out: list[Path]
) -> list[dict]:
    """The heights stage on a tile: the geometry read once, each polygon's field written to its
    ``out`` file (a polygon with no dense geometry near it gets one warning line and keeps its plane).

    Args:
        visibility: the polygons' visibility files (their frames and texel masks); out: a file each.

    Returns:
        Per polygon {polygon, out, layers, evidence_share, relief_share, seconds}.
    """
    import time

    from difftex.geometry.visibility import load_visibility
    from difftex.scene.loading import find_proxy
    from difftex.scene.proxy import load_proxy

    proxy = load_proxy(find_proxy(Path(scene_dir)))
    allv = np.concatenate([p.outer for p in proxy.polygons])
    reach = max(abs(cfg.range[0]), abs(cfg.range[1]))
    geometry = read_geometry(source, (allv.min(0), allv.max(0)), reach)
    done = []
    for vis_file, out_file in zip(visibility, out, strict=True):
        t0 = time.perf_counter()
        vis = load_visibility(vis_file)
        frame, heights, stats = polygon_field(geometry, vis.frame, vis.texel_mask, cfg)
        stats["source"] = str(source.path)
        if stats["evidence_share"] == 0:
            log.warning("%s: no dense geometry near polygon '%s' (it keeps its plane)", source.path, vis.polygon_id)
        write_heights(out_file, vis.polygon_id, frame, heights, stats)
        done.append({"polygon": vis.polygon_id, "out": str(out_file), "layers": stats.get("layers"),
                     "evidence_share": round(stats["evidence_share"], 4),
                     "relief_share": round(stats.get("relief_share", 0.0), 4),
                     "seconds": round(time.perf_counter() - t0, 3)})
    return done
