"""Proxy models as planar polygons: loading OBJ/PLY/OFF/GLB/CityJSON, coplanar grouping of triangle meshes.

OBJ and OFF are parsed here because trimesh triangulates n-gons on load and the polygons are
the unit of work; PLY and glTF/GLB go through trimesh and their triangles are grouped back
into planar polygons (connected, coplanar within an angle and a distance tolerance). CityJSON
surfaces are polygons with holes already (difftex.scene.cityjson reads them).
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np

from difftex.errors import DifftexError
from difftex.scene.planar import (
    newell_normal,
    planarity_deviation,
    polygon_area,
    polygons_from_triangles,
    triangulate_rings,
)

log = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class Polygon:
    """A planar polygon: outer boundary counter-clockwise seen from outside, holes clockwise."""

    id: str
    outer: np.ndarray  # (n, 3)
    holes: tuple[np.ndarray, ...] = field(default=())
    semantic: str = ""  # CityJSON proxies: the surface's semantic type (WallSurface, RoofSurface...)
    building: str = ""  # CityJSON proxies: the building (topmost CityObject) the polygon belongs to

    # Computed once per polygon (the stages ask for every polygon's normal per photo: with a
    # district's thousands of polygons, recomputing it was most of the photo filter's time), and
    # read-only, so that no caller can change the cached value in place.
    @cached_property
    def normal(self) -> np.ndarray:
        n = np.array(newell_normal(self.outer), dtype=np.float64)
        n.flags.writeable = False
        return n

    @cached_property
    def centroid(self) -> np.ndarray:
        c = np.array(self.outer.mean(axis=0), dtype=np.float64)
        c.flags.writeable = False
        return c

    @property
    def offset(self) -> float:
        """d in the plane equation n . X = d."""
        return float(self.normal @ self.outer.mean(axis=0))

    @property
    def area(self) -> float:
        a = polygon_area(self.outer)
        return a - sum(polygon_area(h) for h in self.holes)

    @property
    def diameter(self) -> float:
        return float(np.linalg.norm(np.ptp(self.outer, axis=0)))

    def plane_basis(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(origin, b1, b2): an orthonormal in-plane basis with b1 x b2 = normal."""
        n = self.normal
        a = np.eye(3)[int(np.argmin(np.abs(n)))]
        b1 = np.cross(a, n)
        b1 /= np.linalg.norm(b1)
        b2 = np.cross(n, b1)
        return self.outer[0], b1, b2

    def to_plane(self, X: np.ndarray) -> np.ndarray:
        o, b1, b2 = self.plane_basis()
        d = np.asarray(X, dtype=np.float64) - o
        return np.stack([d @ b1, d @ b2], axis=-1)


@dataclass(frozen=True, eq=False)
class Proxy:
    polygons: list[Polygon]
    path: Path

    def __len__(self) -> int:
        return len(self.polygons)

    def by_id(self, pid: str) -> Polygon:
        for p in self.polygons:
            if p.id == pid:
                return p
        raise DifftexError(f"{self.path}: no polygon with id '{pid}'")

    @property
    def ids(self) -> list[str]:
        return [p.id for p in self.polygons]


_SAFE = re.compile(r"[^A-Za-z0-9_-]+")


def _safe_id(name: str) -> str:
    return _SAFE.sub("_", name).strip("_")


# ---------------------------------------------------------------------------------------------
# Readers: each returns (vertices (V,3), faces [list of index lists], names [group per face])


def _read_obj(path: Path):
    verts, faces, names, lines = [], [], [], []
    group = ""
    for lineno, raw in enumerate(path.read_text(errors="replace").splitlines(), 1):
        parts = raw.split("#", 1)[0].split()
        if not parts:
            continue
        key = parts[0]
        try:
            if key == "v":
                verts.append([float(x) for x in parts[1:4]])
            elif key in ("g", "o"):
                group = " ".join(parts[1:])
            elif key == "f":
                idx = []
                for tok in parts[1:]:
                    i = int(tok.split("/")[0])
                    idx.append(i - 1 if i > 0 else len(verts) + i)
                faces.append(idx)
                names.append(group)
                lines.append(lineno)
        except (ValueError, IndexError):
            raise DifftexError(f"{path}:{lineno}: malformed OBJ line '{raw.strip()}'") from None
    if any(len(v) != 3 for v in verts):
        raise DifftexError(f"{path}: a vertex line ('v') has fewer than 3 coordinates")
    return np.asarray(verts, dtype=np.float64).reshape(-1, 3), faces, names, lines


def _read_off(path: Path):
    tokens = []
    for raw in path.read_text(errors="replace").splitlines():
        tokens.extend(raw.split("#", 1)[0].split())
    try:
        if not tokens or not tokens[0].endswith("OFF"):
            raise ValueError("missing OFF header")
        nv, nf = int(tokens[1]), int(tokens[2])
        pos = 4
        verts = np.array(tokens[pos : pos + 3 * nv], dtype=np.float64).reshape(nv, 3)
        pos += 3 * nv
        faces = []
        for _ in range(nf):
            k = int(tokens[pos])
            faces.append([int(x) for x in tokens[pos + 1 : pos + 1 + k]])
            pos += 1 + k  # colour values after the indices are not supported (rare in proxies)
    except (ValueError, IndexError) as exc:
        raise DifftexError(f"{path}: malformed OFF file ({exc})") from None
    return verts, faces, [""] * len(faces), [None] * len(faces)


def _read_trimesh(path: Path):
    import trimesh

    try:
        scene = trimesh.load(str(path), force="scene", process=False)
    except Exception as exc:
        raise DifftexError(
            f"{path}: cannot read mesh ({str(exc).splitlines()[0] if str(exc) else type(exc).__name__})"
        ) from None
    verts, faces, names = [], [], []
    offset = 0
    # dump() applies the scene graph transforms, so glTF nodes land in the world frame.
    for name, geom in zip(scene.graph.nodes_geometry, scene.dump()):
        if not hasattr(geom, "faces"):
            continue
        verts.append(np.asarray(geom.vertices, dtype=np.float64))
        faces.extend((np.asarray(geom.faces) + offset).tolist())
        names.extend([str(name)] * len(geom.faces))
        offset += len(geom.vertices)
    if not verts:
        return np.zeros((0, 3)), [], [], []
    return np.concatenate(verts), faces, names, [None] * len(faces)


# ---------------------------------------------------------------------------------------------


def degenerate_reason(outer: np.ndarray, holes: tuple = ()) -> str | None:
    """Why a polygon cannot be textured as a surface, or None.

    Zero area (collinear or coincident vertices) is degenerate, and so is a sliver thinner than a
    millionth of its size: its texture map would be one texel high, and the model is written with
    float32 positions (glTF), in which its area does not survive (assembly then finds the
    reloaded polygon smaller than the proxy's). So the area is also checked after rounding the
    vertices to float32, against a tenth of the assembly check's tolerance (1e-4).

    Args:
        outer: (n, 3) boundary loop.
        holes: (m, 3) loops.

    Returns:
        A short phrase, or None for a usable polygon.
    """
    if len(outer) < 3:
        return f"{len(outer)} vertices"
    diam = float(np.linalg.norm(np.ptp(outer, axis=0)))
    area = polygon_area(outer) - sum(polygon_area(h) for h in holes)
    if diam == 0 or area <= 1e-6 * diam * diam:
        return f"zero area: collinear or coincident vertices; area {area:.3g} for a size of {diam:.3g}"
    rounded = polygon_area(outer.astype(np.float32).astype(np.float64)) - sum(
        polygon_area(h.astype(np.float32).astype(np.float64)) for h in holes
    )
    if abs(rounded - area) > 1e-5 * area:
        return f"too thin to store: its area {area:.3g} changes by {abs(rounded - area) / area:.1e} in float32"
    return None


def assign_ids(names: list[str], path: Path) -> list[str]:
    """Unique polygon ids from group names, deterministic across runs.

    A name used by one polygon is its id (made filename-safe). A name shared by several polygons
    (two OBJ groups with the same name, a triangle group that splits into several planes, or
    names that become equal once made safe) gets suffixes ``_1``, ``_2``... in file order, with one
    warning listing them. Unnamed polygons are ``poly<index>``.
    """
    safe = [_safe_id(n) for n in names]
    counts: dict[str, int] = {}
    for n in safe:
        counts[n] = counts.get(n, 0) + 1
    taken = {n for n in safe if n and counts[n] == 1}
    ids: list[str] = []
    shared: dict[str, list[str]] = {}
    next_suffix: dict[str, int] = {}
    for i, n in enumerate(safe):
        if n and counts[n] == 1:
            ids.append(n)
            continue
        while True:
            if n:
                next_suffix[n] = next_suffix.get(n, 0) + 1
                cand = f"{n}_{next_suffix[n]}"
            else:
                cand = f"poly{i:04d}" if f"poly{i:04d}" not in taken else f"poly{i:04d}_{len(taken)}"
            if cand not in taken:
                break
        taken.add(cand)
        ids.append(cand)
        if n:
            shared.setdefault(n, []).append(cand)
    if shared:
        shown = "; ".join(f"'{n}' -> {', '.join(v)}" for n, v in list(shared.items())[:3])
        more = f"; and {len(shared) - 3} more names" if len(shared) > 3 else ""
        log.warning(
            "%s: %d polygon name%s shared by several polygons, so their ids get suffixes: %s%s",
            path,
            len(shared),
            "s are" if len(shared) > 1 else " is",
            shown,
            more,
        )
    return ids


def load_proxy(
    path: str | Path,
    angle_tol_deg: float = 1.0,
    dist_tol_rel: float = 1e-3,
) -> Proxy:
    """Planar polygons of a proxy model.

    n-gon faces are kept as they are; triangles are grouped into coplanar connected polygons.
    A non-planar n-gon (deviation above ``dist_tol_rel`` of its diameter) is an error naming it;
    faces with fewer than 3 vertices and degenerate polygons (zero area, collinear, slivers; see
    ``degenerate_reason``) are skipped with a warning naming them. Ids are unique (``assign_ids``).
    """
    path = Path(path)
    if not path.is_file():
        raise DifftexError(f"{path}: proxy file not found")
    suffix = path.suffix.lower()
    if suffix == ".obj":
        verts, faces, names, lines = _read_obj(path)
    elif suffix == ".off":
        verts, faces, names, lines = _read_off(path)
    elif suffix in (".ply", ".glb", ".gltf", ".stl"):
        verts, faces, names, lines = _read_trimesh(path)
    elif suffix == ".json":
        return _cityjson_proxy(path, dist_tol_rel)
    else:
        raise DifftexError(f"{path}: unsupported proxy format '{suffix}' (use OBJ, PLY, OFF, GLB, glTF or CityJSON)")
    if not np.isfinite(verts).all():
        raise DifftexError(f"{path}: proxy has non-finite vertex coordinates")
    for f, ln in zip(faces, lines):
        bad = [i for i in f if i < 0 or i >= len(verts)]
        if bad:
            where = f"{path}:{ln}" if ln else str(path)
            raise DifftexError(f"{where}: face refers to vertex {bad[0] + 1} but the file has {len(verts)} vertices")

    # (outer, holes, name, order key)
    raw: list[tuple[np.ndarray, tuple, str, int]] = []
    tri_by_group: dict[str, list[tuple[int, list[int]]]] = {}
    for fi, (face, name, ln) in enumerate(zip(faces, names, lines)):
        if len(face) == 3:
            tri_by_group.setdefault(name, []).append((fi, face))
        elif len(face) > 3:
            raw.append((verts[np.asarray(face)], (), name, fi))
        else:
            where = f"{path}:{ln}" if ln else f"{path}: face {fi}"
            label = f"'{name}'" if name else "an unnamed group"
            log.warning("%s: face of %s has %d vertices (a polygon needs 3), skipped", where, label, len(face))
    for name, items in tri_by_group.items():
        fids = [fi for fi, _ in items]
        groups = polygons_from_triangles(verts, [f for _, f in items], angle_tol_deg, dist_tol_rel)
        if not groups:
            log.warning(
                "%s: the triangles of '%s' are all degenerate (zero area), skipped", path, name or "an unnamed group"
            )
        for outer, holes, first in groups:
            raw.append((outer, holes, name, fids[first]))
    raw.sort(key=lambda r: r[3])
    return _checked_proxy(path, [(o, h, n, {}) for o, h, n, _ in raw], dist_tol_rel)


def _cityjson_proxy(path: Path, dist_tol_rel: float) -> Proxy:
    """The proxy of a CityJSON file: one polygon per surface, keeping its semantic type and building."""
    from difftex.scene.cityjson import read_cityjson

    surfaces = read_cityjson(path)
    raw = [(s.outer, s.holes, s.name, {"semantic": s.semantic, "building": s.building}) for s in surfaces]
    proxy = _checked_proxy(path, raw, dist_tol_rel)
    kinds: dict[str, int] = {}
    for p in proxy.polygons:
        kinds[p.semantic] = kinds.get(p.semantic, 0) + 1
    log.info(
        "%s: %d polygons of %d building(s): %s",
        path,
        len(proxy),
        len({p.building for p in proxy.polygons}),
        ", ".join(f"{n} {k}" for k, n in sorted(kinds.items())),
    )
    return proxy


def _checked_proxy(path: Path, raw: list[tuple[np.ndarray, tuple, str, dict]], dist_tol_rel: float) -> Proxy:
    """The proxy of loops (outer, holes, name, extra Polygon fields) in file order: degenerate ones
    skipped with a warning, a non-planar one an error naming it, ids assigned (``assign_ids``)."""
    kept, thin = [], 0
    for i, (outer, holes, name, extra) in enumerate(raw):
        label = name or f"face {i}"
        why = degenerate_reason(outer, holes)
        if why:
            log.warning("%s: polygon '%s' is degenerate (%s); skipped", path, label, why)
            thin += why.startswith("too thin")
            continue
        diam = float(np.linalg.norm(np.ptp(outer, axis=0)))
        dev = planarity_deviation(np.concatenate([outer, *holes]) if holes else outer)
        if dev > dist_tol_rel * diam:
            raise DifftexError(
                f"{path}: polygon '{label}' is not planar (max deviation {dev:.4g} from its plane, "
                f"tolerance {dist_tol_rel * diam:.4g})"
            )
        kept.append((outer, holes, name, extra))
    if not kept:
        hint = ""
        if raw and thin == len(raw):  # every polygon tiny next to its distance from the origin
            v = np.concatenate([r[0] for r in raw])
            hint = (
                f" (it is {np.linalg.norm(np.ptp(v, axis=0)):.3g} across, "
                f"{np.linalg.norm(v.mean(axis=0)):.3g} from the origin: wrong units?)"
            )
        raise DifftexError(f"{path}: proxy has no usable polygons{hint}")

    ids = assign_ids([n for _, _, n, _ in kept], path)
    polys = [Polygon(id=pid, outer=o, holes=h, **extra) for pid, (o, h, _, extra) in zip(ids, kept)]
    return Proxy(polygons=polys, path=path)


def write_proxy_obj(path: str | Path, polygons: list[Polygon], header: str = "") -> None:
    """One ``g <id>`` group and one n-gon face per polygon (holes cannot be expressed in OBJ)."""
    from difftex.scene.files import write_text

    lines = [f"# {line}" for line in header.splitlines()] if header else []
    lines.append(f"# {len(polygons)} planar polygons; vertex order counter-clockwise seen from outside")
    faces, nv = [], 0
    for p in polygons:
        if p.holes:
            raise DifftexError(f"{path}: polygon '{p.id}' has holes, which OBJ n-gons cannot hold")
        for v in p.outer:
            lines.append(f"v {v[0]:.9g} {v[1]:.9g} {v[2]:.9g}")
        faces.append((p.id, list(range(nv + 1, nv + 1 + len(p.outer)))))
        nv += len(p.outer)
    for pid, idx in faces:
        lines.append(f"g {pid}")
        lines.append("f " + " ".join(map(str, idx)))
    write_text(path, "\n".join(lines) + "\n")


def triangulate(polygon: Polygon) -> tuple[np.ndarray, np.ndarray]:
    """(vertices (n, 3), triangles (m, 3)) of a planar polygon with holes, counter-clockwise seen
    from outside (earcut in the polygon's plane)."""
    loops = [polygon.outer, *polygon.holes]
    verts = np.concatenate(loops).astype(np.float64)
    ends = np.cumsum([len(lp) for lp in loops])[:-1]
    tris = triangulate_rings(np.split(polygon.to_plane(verts), ends))
    if len(tris) == 0:
        raise DifftexError(f"polygon '{polygon.id}' could not be triangulated (degenerate outline)")
    a, b, c = verts[tris[:, 0]], verts[tris[:, 1]], verts[tris[:, 2]]
    flip = np.cross(b - a, c - a) @ polygon.normal < 0
    tris[flip] = tris[flip][:, ::-1]
    return verts, tris
