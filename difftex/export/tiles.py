"""The textured model as a 3D Tiles 1.1 tileset: ``tileset.json`` and one GLB tile per building.

Layout (``out_dir`` is usually ``R/model/tileset``)::

    tileset.json            asset.version "1.1"; root: a box around the whole model, no content,
                            refine ADD, one child per building (geometricError 0: full detail)
    tiles/<building>.glb    the building's polygons, textured from its own atlas pages

Buildings are the proxy's CityJSON buildings (``Polygon.building``) when it has them, else the
connected components of the proxy: polygons touching within ``TOUCH_TOL`` of the model's size
(a vertex on another polygon's edge or face counts).

Axes: bounding volumes are in the scene frame, which 3D Tiles takes as z-up. glTF is y-up, and a
3D Tiles runtime turns tile content from y-up to z-up with the fixed rotation (x, y, z) -> (x, -z, y)
(3D Tiles 1.1, "glTF transforms"); so each tile's glTF nodes carry the inverse rotation
``Z_UP_TO_Y_UP`` and its content lands in the scene frame, where its bounding box is.

Geo-reference (``AssembleConfig.tileset_georef``): None leaves the root in the local scene frame,
turned about the origin so that the scene's up (the photos' up, as the texturing takes it) is +z
when ``up`` is given (a COLMAP frame points anywhere; a 3D Tiles viewer shows +z up);
``{lon, lat, height}`` (degrees, degrees, metres above the WGS84 ellipsoid) takes the scene frame as
east-north-up metres at that point and gives the root that frame's ECEF transform; ``{ecef: [16
numbers]}`` is any column-major 4 x 4 scene-to-ECEF transform (with a rotation and a scale for a
frame that is not east-north-up metres).

Atlases: each tile is packed with difftex.export.assemble's ``build_atlas`` and written with its
``write_glb``, so ``assemble.max_page_size`` and ``padding`` hold per tile as for the whole model.
"""

from __future__ import annotations

import math
import re
import tempfile
from pathlib import Path

import numpy as np

from difftex.errors import DifftexError
from difftex.export.assemble import AssembleConfig, PolygonTexture, build_atlas, write_glb
from difftex.layout import TILES_DIR, TILESET
from difftex.scene.proxy import Polygon

TILESET_VERSION = "1.1"
TOUCH_TOL = 1e-3  # polygons closer than this times the model's diagonal are one building
MIN_HALF_AXIS = 1e-3  # a box's thinnest half axis, relative to its largest (a flat tile is no box)
Z_UP_TO_Y_UP = np.array([[1.0, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0], [0, 0, 0, 1]])
WGS84_A = 6378137.0
WGS84_F = 1.0 / 298.257223563
_SAFE = re.compile(r"[^A-Za-z0-9_.-]+")


# ---------------------------------------------------------------------------------------------
# Buildings


def _touching(a: Polygon, b: Polygon, tol: float) -> bool:
    """Whether a vertex of one polygon lies within ``tol`` of the other polygon (edge or face)."""
    from difftex.scene.loading import distance_to_proxy
    from difftex.scene.proxy import Proxy

    for p, q in ((a, b), (b, a)):
        pts = np.concatenate([p.outer, *p.holes])
        if float(distance_to_proxy(Proxy([q], Path(q.id)), pts).min()) <= tol:
            return True
    return False


def building_groups(polygons: list[Polygon], tol_rel: float = TOUCH_TOL) -> dict[str, list[int]]:
    """The polygons' buildings: {tile name: polygon indices}, in the order of their first polygon.

    Args:
        polygons: the proxy's polygons.
        tol_rel: touching distance relative to the model's diagonal (connected components only).

    Returns:
        Names are the CityJSON building ids made filename-safe when every polygon has one, else
        ``building<k>`` for the connected components; each index is in exactly one group.
    """
    if not polygons:
        raise DifftexError("no polygons to group into tiles")
    if all(p.building for p in polygons):
        keys = [p.building for p in polygons]
    else:
        allv = np.concatenate([p.outer for p in polygons])
        tol = tol_rel * float(np.linalg.norm(np.ptp(allv, axis=0)))
        lo = np.array([p.outer.min(axis=0) for p in polygons]) - tol
        hi = np.array([p.outer.max(axis=0) for p in polygons]) + tol
        parent = list(range(len(polygons)))

        def find(i: int) -> int:
            while parent[i] != i:
                parent[i] = parent[parent[i]]
                i = parent[i]
            return i

        for i in range(len(polygons)):
            near = np.nonzero(((lo[i] <= hi[i + 1 :]) & (lo[i + 1 :] <= hi[i])).all(axis=1))[0] + i + 1
            for j in near:
                if find(i) != find(int(j)) and _touching(polygons[i], polygons[int(j)], tol):
                    parent[find(int(j))] = find(i)
        roots = [find(i) for i in range(len(polygons))]
        order = {r: k for k, r in enumerate(dict.fromkeys(roots))}
        keys = [f"building{order[r]:03d}" for r in roots]
    groups: dict[str, list[int]] = {}
    names: dict[str, str] = {}
    for i, key in enumerate(keys):
        if key not in names:
            safe = _SAFE.sub("_", key).strip("_.") or "building"
            name, k = safe, 1
            while name in groups:  # two ids that differ only in unsafe characters
                name, k = f"{safe}_{k}", k + 1
            names[key] = name
            groups[name] = []
        groups[names[key]].append(i)
    return groups


# ---------------------------------------------------------------------------------------------
# Frames and bounding volumes


def enu_to_ecef(lon_deg: float, lat_deg: float, height: float) -> np.ndarray:
    """4 x 4 transform from east-north-up metres at a WGS84 point to Earth-centred, Earth-fixed.

    Args:
        lon_deg, lat_deg: the point's longitude and geodetic latitude, degrees.
        height: metres above the WGS84 ellipsoid.

    Returns:
        Columns: east, north, up (unit vectors in ECEF) and the point's ECEF position.
    """
    lon, lat = math.radians(lon_deg), math.radians(lat_deg)
    e2 = WGS84_F * (2 - WGS84_F)
    n = WGS84_A / math.sqrt(1 - e2 * math.sin(lat) ** 2)
    origin = [
        (n + height) * math.cos(lat) * math.cos(lon),
        (n + height) * math.cos(lat) * math.sin(lon),
        (n * (1 - e2) + height) * math.sin(lat),
    ]
    east = [-math.sin(lon), math.cos(lon), 0.0]
    north = [-math.sin(lat) * math.cos(lon), -math.sin(lat) * math.sin(lon), math.cos(lat)]
    up = [math.cos(lat) * math.cos(lon), math.cos(lat) * math.sin(lon), math.sin(lat)]
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = east, north, up, origin
    return m


def _number(georef: dict, key: str, lo: float, hi: float) -> float:
    v = georef.get(key, 0.0 if key == "height" else None)
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not lo <= v <= hi:
        raise DifftexError(f"assemble.tileset_georef: {key} must be a number in [{lo:g}, {hi:g}], got {v!r}")
    return float(v)


def root_transform(georef: dict | None) -> list[float] | None:
    """The root tile's ``transform`` (16 numbers, column-major) for a geo-reference, or None.

    Args:
        georef: None; ``{lon, lat, height}`` (height defaults to 0); or ``{ecef: [16 numbers]}``.

    Returns:
        None for the local frame, else the scene-to-ECEF transform.
    """
    if georef is None:
        return None
    if not isinstance(georef, dict):
        raise DifftexError(f"assemble.tileset_georef: must be null, {{lon, lat, height}} or {{ecef}}, got {georef!r}")
    if set(georef) == {"ecef"}:
        try:
            m = np.asarray(georef["ecef"], dtype=np.float64).reshape(4, 4).T  # column-major
        except (TypeError, ValueError):
            m = np.full((4, 4), np.nan)
        if not np.isfinite(m).all() or not np.allclose(m[3], [0, 0, 0, 1]) or abs(np.linalg.det(m[:3, :3])) < 1e-12:
            raise DifftexError(
                "assemble.tileset_georef: ecef must be 16 numbers, a column-major affine 4 x 4 matrix "
                "(last row 0 0 0 1) with an invertible 3 x 3 part"
            )
        return m.T.reshape(-1).tolist()
    if not set(georef) <= {"lon", "lat", "height"} or not {"lon", "lat"} <= set(georef):
        raise DifftexError(
            f"assemble.tileset_georef: give lon, lat (and height) or ecef, got keys {', '.join(sorted(georef))}"
        )
    m = enu_to_ecef(
        _number(georef, "lon", -180, 360), _number(georef, "lat", -90, 90), _number(georef, "height", -1e5, 1e7)
    )
    return m.T.reshape(-1).tolist()


def level_rotation(up: np.ndarray) -> np.ndarray:
    """4 x 4 rotation about the origin taking the unit vector ``up`` to +z (the shortest turn)."""
    u = np.asarray(up, dtype=np.float64)
    u = u / np.linalg.norm(u)
    z = np.array([0.0, 0.0, 1.0])
    axis, c = np.cross(u, z), float(u @ z)
    m = np.eye(4)
    if c < -1 + 1e-12:  # upside down: half a turn about x
        m[:3, :3] = np.diag([1.0, -1.0, -1.0])
        return m
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    m[:3, :3] = np.eye(3) + k + k @ k / (1 + c)  # Rodrigues for unit vectors
    return m


def box_of(points: np.ndarray) -> list[float]:
    """A 3D Tiles ``box`` (centre, then three half axes) around points, along the frame's axes;
    a flat extent gets a thickness of MIN_HALF_AXIS of the largest one."""
    lo, hi = points.min(axis=0), points.max(axis=0)
    centre, half = (lo + hi) / 2, (hi - lo) / 2
    half = np.maximum(half, MIN_HALF_AXIS * max(float(half.max()), 1e-9))
    return [*centre.tolist(), half[0], 0.0, 0.0, 0.0, half[1], 0.0, 0.0, 0.0, half[2]]


# ---------------------------------------------------------------------------------------------
# Writer


def _write_tile(path: Path, items: list[PolygonTexture], cfg: AssembleConfig) -> int:
    """One tile's GLB (its own atlas, nodes z-up -> y-up); returns its atlas page count."""
    from difftex.scene.files import write_image

    atlas = build_atlas(items, cfg)
    with tempfile.TemporaryDirectory(prefix=".pages-", dir=path.parent) as tmp:
        pages = []
        for k, page in enumerate(atlas.pages):
            pages.append(Path(tmp) / f"atlas{k}.png")
            write_image(pages[-1], page, bits=8)  # glTF viewers read 8-bit textures
        write_glb(path, items, atlas, pages, int(cfg.padding), transform=Z_UP_TO_Y_UP)
    return len(atlas.pages)


def _points(items: list[PolygonTexture]) -> np.ndarray:
    return np.concatenate([it.polygon.outer for it in items])


def write_tileset(
    items: list[PolygonTexture],
    out_dir: str | Path,
    cfg: AssembleConfig,
    generator: str = "",
    up: np.ndarray | None = None,
) -> dict:
    """Write ``out_dir``/tileset.json and ``out_dir``/tiles/<building>.glb, each file atomically,
    tileset.json last (tiles of an earlier run that are no longer listed are removed after it).

    Args:
        items: every polygon with its texture (as for ``assemble``).
        out_dir: the tileset's folder.
        cfg: atlas settings (``max_page_size``, ``padding``, colours) and ``tileset_georef``.
        generator: ``asset.generator`` (e.g. "difftex 0.1.0").
        up: the scene's up; without a geo-reference the root turns it to +z (None: no turn).

    Returns:
        A summary: the tileset file, georeferenced or not, per tile its name, file, polygons and
        atlas pages.
    """
    from difftex.scene.files import write_json

    if not items:
        raise DifftexError(f"{out_dir}: no polygons to write as tiles")
    transform = root_transform(cfg.tileset_georef)
    if transform is None and up is not None:
        transform = level_rotation(up).T.reshape(-1).tolist()
    out_dir = Path(out_dir)
    (out_dir / TILES_DIR).mkdir(parents=True, exist_ok=True)
    groups = building_groups([it.polygon for it in items])
    children, rows = [], []
    for name, idx in groups.items():
        sub = [items[i] for i in idx]
        uri = f"{TILES_DIR}/{name}.glb"
        pages = _write_tile(out_dir / uri, sub, cfg)
        polys = {it.polygon.id: it.polygon.semantic for it in sub}
        children.append(
            {"boundingVolume": {"box": box_of(_points(sub))}, "geometricError": 0.0, "content": {"uri": uri}}
        )
        if any(polys.values()):
            children[-1]["extras"] = {"semantics": polys}
        rows.append({"name": name, "file": uri, "polygons": sorted(polys), "atlas_pages": pages})
    pts = _points(items)
    error = float(np.linalg.norm(np.ptp(pts, axis=0)))
    root: dict = {"boundingVolume": {"box": box_of(pts)}, "geometricError": error, "refine": "ADD"}
    if transform is not None:
        root["transform"] = transform
    root["children"] = children
    asset = {"version": TILESET_VERSION, **({"generator": generator} if generator else {})}
    write_json(out_dir / TILESET, {"asset": asset, "geometricError": error, "root": root})
    listed = {out_dir / r["file"] for r in rows}
    for stale in (out_dir / TILES_DIR).glob("*.glb"):
        if stale not in listed:
            stale.unlink()
    georef = cfg.tileset_georef is not None
    return {"file": TILESET, "georeferenced": georef, "levelled": not georef and up is not None, "tiles": rows}
