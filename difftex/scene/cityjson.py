"""CityJSON proxies: the surfaces of LOD2 building models (CityJSON 1.0, 1.1, 2.0) as planar loops.

A CityJSON file holds CityObjects (buildings, building parts...), each with geometries at one or
more levels of detail. Per object the geometry of the highest LOD from ``MIN_LOD`` (1: an LOD0
footprint has no walls) up to ``MAX_LOD`` (2.2) is taken, and a building whose parts have such a
geometry is left to its parts;
each of its surfaces (an outer ring and optional hole rings, as indices into the file's shared
``vertices``, which ``transform`` scales and translates) becomes one surface here, named
``<cityobject id>_<semantic type>_<n>`` with n counted per object and type in file order, so the
names stay the same across reruns. The semantic type (WallSurface, RoofSurface...) is kept.

GroundSurface (the footprint, facing down into the ground) and ClosureSurface (a virtual surface
that closes an open part of a solid) are never seen by a camera: they are skipped with one
warning. Objects other than buildings, bridges, tunnels and other constructions (terrain, roads,
vegetation...) are skipped with one warning too.

This module only reads: difftex.scene.proxy turns the surfaces into the proxy's polygons and
checks them (planarity, degenerate loops) like those of any other format.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from difftex.errors import DifftexError
from difftex.scene.planar import newell_normal

log = logging.getLogger(__name__)

MAX_LOD = 2.2
MIN_LOD = 1.0  # LOD0 is a footprint or roof outline: no walls to texture
SKIPPED_SEMANTICS = {
    "GroundSurface": "they face down into the ground, no photo sees them",
    "ClosureSurface": "they are virtual surfaces closing an open part of a solid",
}
BUILDING_TYPES = ("Building", "Bridge", "Tunnel", "OtherConstruction")  # prefixes: BuildingPart too
SURFACE_DEPTH = {"MultiSurface": 0, "CompositeSurface": 0, "Solid": 1, "MultiSolid": 2, "CompositeSolid": 2}


@dataclass(frozen=True, eq=False)
class Surface:
    """One CityJSON surface: its loops in the file's real coordinates and where it came from."""

    name: str  # <cityobject id>_<semantic>_<n>
    outer: np.ndarray  # (n, 3)
    holes: tuple[np.ndarray, ...]
    semantic: str  # the semantic surface type, "Surface" where the file gives none
    building: str  # the id of the object's topmost parent (a building for its parts)


def _load_json(path: Path) -> dict:
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except UnicodeDecodeError:
        raise DifftexError(f"{path}: not a CityJSON file (not UTF-8 text)") from None
    except json.JSONDecodeError as exc:
        raise DifftexError(f"{path}: not valid JSON ({exc.msg} at line {exc.lineno}, column {exc.colno})") from None
    if not isinstance(data, dict) or data.get("type") != "CityJSON":
        what = data.get("type") if isinstance(data, dict) else type(data).__name__
        hint = " (CityJSON Lines features are not supported: give the whole file)" if what == "CityJSONFeature" else ""
        raise DifftexError(f"{path}: not a CityJSON file (its \"type\" is {what!r}, not \"CityJSON\"){hint}")
    version = str(data.get("version", ""))
    if version.split(".")[0] not in ("1", "2"):
        log.warning("%s: CityJSON version %r; read as 2.0", path, version)
    return data


def read_vertices(data: dict, path: Path) -> np.ndarray:
    """The file's vertices (V, 3) in real coordinates: ``vertices`` x ``transform.scale`` +
    ``transform.translate`` (CityJSON 1.1 and 2.0 store integers; 1.0 files may have no transform).

    Args:
        data: the parsed CityJSON object.
        path: the file, for messages.

    Returns:
        (V, 3) float64 array.
    """
    raw = data.get("vertices")
    if not isinstance(raw, list) or not raw:
        raise DifftexError(f"{path}: CityJSON has no \"vertices\" array (or it is empty)")
    try:
        verts = np.asarray(raw, dtype=np.float64)
    except (TypeError, ValueError):
        verts = np.zeros((0, 0))
    if verts.ndim != 2 or verts.shape[1] != 3:
        raise DifftexError(f"{path}: CityJSON \"vertices\" must be a list of [x, y, z] numbers")
    tf = data.get("transform")
    if tf is not None:
        try:
            scale = np.asarray(tf["scale"], dtype=np.float64).reshape(3)
            translate = np.asarray(tf["translate"], dtype=np.float64).reshape(3)
        except (KeyError, TypeError, ValueError):
            raise DifftexError(
                f"{path}: CityJSON \"transform\" must hold \"scale\" and \"translate\", three numbers each"
            ) from None
        verts = verts * scale + translate
    if not np.isfinite(verts).all():
        raise DifftexError(f"{path}: CityJSON has non-finite vertex coordinates")
    return verts


def _lod(geom: dict) -> float:
    try:
        return float(geom.get("lod", "nan"))
    except (TypeError, ValueError):
        return float("nan")


def pick_geometry(obj: dict) -> dict | None:
    """The object's geometry of the highest LOD in [MIN_LOD, MAX_LOD] among the surface types, or None."""
    best: dict | None = None
    for geom in obj.get("geometry") or []:
        if not isinstance(geom, dict) or geom.get("type") not in SURFACE_DEPTH:
            continue
        lod = _lod(geom)
        if MIN_LOD <= lod <= MAX_LOD and (best is None or lod > _lod(best)):
            best = geom
    return best


def _pair(bounds: Any, values: Any, depth: int, out: list) -> None:
    """Append (surface, semantic value) pairs of ``bounds`` nested ``depth`` levels above the
    surfaces; a null value stands for all surfaces under it. TypeError: bounds nested wrongly;
    ValueError: values not nested like the bounds."""
    if not isinstance(bounds, list):
        raise TypeError
    if values is not None and (not isinstance(values, list) or len(values) != len(bounds)):
        raise ValueError
    for i, b in enumerate(bounds):
        v = None if values is None else values[i]
        if depth == 0:
            if not isinstance(b, list) or not all(isinstance(ring, list) for ring in b):
                raise TypeError
            out.append((b, v))
        else:
            _pair(b, v, depth - 1, out)


def _surfaces_of(geom: dict, where: str) -> list[tuple[list, Any]]:
    """(rings, semantic index) per surface of a geometry, flattening shells and solids."""
    depth = SURFACE_DEPTH[geom["type"]]
    out: list[tuple[list, Any]] = []
    try:
        _pair(geom.get("boundaries"), None, depth, out)
    except TypeError:
        raise DifftexError(
            f"{where}: \"boundaries\" are not nested as a {geom['type']}'s (down to surfaces, rings, vertex indices)"
        ) from None
    values = (geom.get("semantics") or {}).get("values")
    out = []
    try:
        _pair(geom["boundaries"], values, depth, out)
    except ValueError:
        raise DifftexError(
            f"{where}: \"semantics.values\" do not match the boundaries (one value per surface, nested like them)"
        ) from None
    return out


def _rings(surface: Any, verts: np.ndarray, where: str) -> list[np.ndarray]:
    if not isinstance(surface, list) or not surface:
        raise DifftexError(f"{where}: a surface must be a list of rings (lists of vertex indices)")
    out = []
    for ring in surface:
        if not isinstance(ring, list) or not all(isinstance(i, int) and not isinstance(i, bool) for i in ring):
            raise DifftexError(f"{where}: a ring must be a list of vertex indices (integers)")
        bad = [i for i in ring if i < 0 or i >= len(verts)]
        if bad:
            raise DifftexError(
                f"{where}: refers to vertex {bad[0]} but the file has {len(verts)} vertices (0..{len(verts) - 1})"
            )
        idx = [i for k, i in enumerate(ring) if k == 0 or i != ring[k - 1]]
        if len(idx) > 1 and idx[-1] == idx[0]:
            idx = idx[:-1]  # a closed ring (first vertex repeated), which CityJSON does not want
        out.append(verts[np.asarray(idx, dtype=np.int64)] if idx else np.zeros((0, 3)))
    return out


def _orient_holes(outer: np.ndarray, holes: list[np.ndarray]) -> tuple[np.ndarray, ...]:
    """Holes clockwise seen from outside (the proxy's convention), whatever the file's order."""
    n = newell_normal(outer)
    return tuple(h[::-1].copy() if len(h) >= 3 and newell_normal(h) @ n > 0 else h for h in holes)


def _root(oid: str, objects: dict) -> str:
    seen = {oid}
    while True:
        parents = objects.get(oid, {}).get("parents") or []
        if not parents or parents[0] in seen or parents[0] not in objects:
            return oid
        oid = parents[0]
        seen.add(oid)


def _object_surfaces(oid: str, geom: dict, verts: np.ndarray, path: Path, building: str) -> list[Surface]:
    where = f"{path}: CityObject '{oid}' ({geom['type']}, LOD {geom.get('lod')})"
    types = [
        s.get("type", "Surface") if isinstance(s, dict) else "Surface"
        for s in (geom.get("semantics") or {}).get("surfaces") or []
    ]
    counts: dict[str, int] = {}
    out = []
    for k, (surface, sem) in enumerate(_surfaces_of(geom, where)):
        rings = _rings(surface, verts, f"{where}: surface {k}")
        if isinstance(sem, int) and not isinstance(sem, bool) and 0 <= sem < len(types):
            kind = str(types[sem])
        elif sem is None:
            kind = "Surface"
        else:
            raise DifftexError(
                f"{where}: surface {k} has semantic value {sem!r}, but \"semantics.surfaces\" has {len(types)} entries"
            )
        n = counts.get(kind, 0)
        counts[kind] = n + 1
        out.append(Surface(f"{oid}_{kind}_{n}", rings[0], _orient_holes(rings[0], rings[1:]), kind, building))
    return out


def read_cityjson(path: str | Path) -> list[Surface]:
    """Every textured-able surface of a CityJSON file's buildings, in file order.

    Args:
        path: a CityJSON 1.0 / 1.1 / 2.0 file.

    Returns:
        The surfaces, GroundSurface and ClosureSurface ones left out (with one warning).

    Raises:
        DifftexError: one line naming the file and the problem (not JSON, not CityJSON, no
            vertices, a ring referring to a vertex that does not exist, boundaries nested wrongly,
            no building geometry of LOD <= 2.2).
    """
    path = Path(path)
    data = _load_json(path)
    objects = data.get("CityObjects")
    if not isinstance(objects, dict) or not objects:
        raise DifftexError(f"{path}: CityJSON has no \"CityObjects\"")
    verts = read_vertices(data, path)
    surfaces: list[Surface] = []
    other_types: set[str] = set()
    above_lod: list[str] = []
    if not all(isinstance(obj, dict) for obj in objects.values()):
        oid = next(k for k, v in objects.items() if not isinstance(v, dict))
        raise DifftexError(f"{path}: CityObject '{oid}' is not a JSON object")
    # a building whose parts have geometry: the parts hold the detail, the building's own
    # geometry (3D BAG: a footprint, an LOD1 block) would duplicate them
    with_parts = {p for obj in objects.values() if pick_geometry(obj) for p in obj.get("parents") or []}
    for oid, obj in objects.items():
        if oid in with_parts:
            continue
        if not str(obj.get("type", "")).lstrip("+").startswith(BUILDING_TYPES):
            other_types.add(str(obj.get("type")))
            continue
        geom = pick_geometry(obj)
        if geom is None:
            if obj.get("geometry"):
                above_lod.append(str(oid))
            continue
        surfaces.extend(_object_surfaces(str(oid), geom, verts, path, _root(str(oid), objects)))
    if other_types:
        log.warning("%s: CityObjects of type %s skipped (not buildings)", path, ", ".join(sorted(other_types)))
    if above_lod:
        log.warning(
            "%s: %d CityObject(s) have no surface geometry of LOD %s to %s, skipped: %s",
            path,
            len(above_lod),
            MIN_LOD,
            MAX_LOD,
            ", ".join(above_lod[:5]) + (" ..." if len(above_lod) > 5 else ""),
        )
    kept = _drop_unseen(surfaces, path)
    if not kept:
        raise DifftexError(f"{path}: CityJSON has no building surface of LOD {MIN_LOD:g} to {MAX_LOD} to texture")
    return kept


def _drop_unseen(surfaces: list[Surface], path: Path) -> list[Surface]:
    """The surfaces a camera can see; one warning per skipped semantic type, naming a few."""
    for kind, why in SKIPPED_SEMANTICS.items():
        names = [s.name for s in surfaces if s.semantic == kind]
        if names:
            shown = ", ".join(names[:3]) + (f" and {len(names) - 3} more" if len(names) > 3 else "")
            log.warning("%s: %d %s polygon(s) skipped (%s): %s", path, len(names), kind, why, shown)
    return [s for s in surfaces if s.semantic not in SKIPPED_SEMANTICS]
