"""Procedural building shells: the planar proxy polygons and the planar frame of each face.

A building is a stack of extruded footprints ("blocks"). Each footprint edge becomes a wall
polygon, each block top (minus what stands on it) becomes roof polygon(s); a gable block gets
two sloped roof planes and pentagonal gable walls. OBJ n-gons cannot hold holes, so roofs with
a hole (courtyard ring, base around a tower) are cut into hole-free pieces.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from difftex.errors import DifftexError
from difftex.synth.presets import BuildingSpec


@dataclass
class Face:
    """A proxy polygon with an in-plane frame: 2D coords (u, v) = ((X-o).a, (X-o).b), a x b = n.

    For walls ``a`` runs along the wall and ``b`` is +z, so (u, v) are metres along and up.
    ``eave`` is the height (v) below which a wall is a full rectangle (gable walls rise above it).
    """

    id: str
    kind: str  # wall | roof
    outer: np.ndarray  # (n, 3), counter-clockwise seen from outside
    origin: np.ndarray
    a: np.ndarray
    b: np.ndarray
    eave: float = 0.0

    @property
    def normal(self) -> np.ndarray:
        n = np.cross(self.a, self.b)
        return n / np.linalg.norm(n)

    def to2d(self, X: np.ndarray) -> np.ndarray:
        d = np.asarray(X, float) - self.origin
        return np.stack([d @ self.a, d @ self.b], axis=-1)

    def to3d(self, uv: np.ndarray, offset: float = 0.0) -> np.ndarray:
        uv = np.asarray(uv, float)
        return self.origin + uv[..., :1] * self.a + uv[..., 1:2] * self.b + offset * self.normal

    @property
    def poly2d(self) -> np.ndarray:
        return self.to2d(self.outer)

    @property
    def length(self) -> float:
        return float(np.ptp(self.poly2d[:, 0]))


@dataclass
class Building:
    name: str
    spec: BuildingSpec
    faces: list[Face]
    footprint: object  # shapely geometry of the ground footprint (occluders and cameras avoid it)
    top: float  # highest z

    @property
    def walls(self) -> list[Face]:
        return [f for f in self.faces if f.kind == "wall"]

    @property
    def roofs(self) -> list[Face]:
        return [f for f in self.faces if f.kind == "roof"]

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        pts = np.concatenate([f.outer for f in self.faces])
        return pts.min(0), pts.max(0)


def _rect(cx: float, cy: float, w: float, d: float) -> np.ndarray:
    """Axis-aligned rectangle, counter-clockwise from above."""
    return np.array(
        [[cx - w / 2, cy - d / 2], [cx + w / 2, cy - d / 2], [cx + w / 2, cy + d / 2], [cx - w / 2, cy + d / 2]]
    )


def _wall(fid: str, p0, p1, z0: float, z1: float) -> Face:
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    d = p1 - p0
    a = np.array([d[0], d[1], 0.0]) / np.linalg.norm(d)
    outer = np.array([[*p0, z0], [*p1, z0], [*p1, z1], [*p0, z1]])
    return Face(fid, "wall", outer, outer[0].copy(), a, np.array([0.0, 0.0, 1.0]), eave=z1 - z0)


def _flat_roof(fid: str, ring2d: np.ndarray, z: float) -> Face:
    outer = np.column_stack([ring2d, np.full(len(ring2d), z)])
    a = outer[1] - outer[0]
    a /= np.linalg.norm(a)
    b = np.cross([0.0, 0.0, 1.0], a)
    return Face(fid, "roof", outer, outer[0].copy(), a, b)


def _ccw(ring: np.ndarray) -> np.ndarray:
    x, y = ring[:, 0], ring[:, 1]
    area = 0.5 * np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y)
    return ring if area > 0 else ring[::-1]


def _hole_free_pieces(geom) -> list[np.ndarray]:
    """Cut a (multi)polygon with holes into hole-free pieces by vertical lines at hole extents."""
    import shapely
    from shapely.geometry import LineString
    from shapely.ops import split

    polys = list(geom.geoms) if geom.geom_type == "MultiPolygon" else [geom]
    out = []
    for p in polys:
        pieces = [p]
        for hole in p.interiors:
            x0, y0, x1, y1 = shapely.Polygon(hole).bounds
            for x in (x0, x1):
                line = LineString([(x, y0 - 1e4), (x, y1 + 1e4)])
                nxt = []
                for q in pieces:
                    nxt.extend(split(q, line).geoms if q.interiors else [q])
                pieces = nxt
        for q in pieces:
            if q.interiors:
                raise DifftexError(f"roof piece still has a hole after splitting ({q.wkt[:60]})")
            ring = np.asarray(shapely.simplify(q, 1e-6).exterior.coords)[:-1]
            out.append(_ccw(ring))
    # Deterministic order: by centroid x, then y.
    out.sort(key=lambda r: (round(float(r[:, 0].mean()), 3), round(float(r[:, 1].mean()), 3)))
    return out


def _stack(name, spec, blocks) -> Building:
    """blocks: list of (outer ring CCW, [inner rings CW], z0, z1)."""
    import shapely

    faces: list[Face] = []
    for outer, inners, z0, z1 in blocks:
        for ring in [outer, *inners]:
            for i in range(len(ring)):
                faces.append(_wall("", ring[i], ring[(i + 1) % len(ring)], z0, z1))
    for outer, inners, _z0, z1 in blocks:
        region = shapely.Polygon(outer, [r[::-1] for r in inners])
        for other in blocks:
            if abs(other[2] - z1) < 1e-9:
                region = region.difference(shapely.Polygon(other[0]))
        for ring in _hole_free_pieces(region):
            faces.append(_flat_roof("", ring, z1))
    footprint = shapely.Polygon(blocks[0][0], [r[::-1] for r in blocks[0][1]])
    return _finish(name, spec, faces, footprint)


def _finish(name, spec, faces, footprint) -> Building:
    nw = nr = 0
    for f in faces:
        if f.kind == "wall":
            f.id, nw = f"wall{nw:02d}", nw + 1
        else:
            f.id, nr = f"roof{nr:02d}", nr + 1
    top = float(max(f.outer[:, 2].max() for f in faces))
    return Building(name, spec, faces, footprint, top)


def make_building(spec: BuildingSpec, rng: np.random.Generator) -> Building:
    """The shell of ``spec``, centred on the origin, z-up, ground at z = 0."""
    w, d, h = spec.width, spec.depth, spec.height
    if min(w, d, h) <= 0:
        raise DifftexError(f"building '{spec.name}': width, depth and height must be > 0")
    if spec.style == "box":
        # A flat-roofed block with a plant room on the roof (so the roof is not one plain slab).
        pw, pd = w * rng.uniform(0.2, 0.3), d * rng.uniform(0.25, 0.35)
        px, py = rng.uniform(-0.15, 0.15) * w, rng.uniform(-0.1, 0.1) * d
        return _stack(spec.name, spec, [(_rect(0, 0, w, d), [], 0.0, h), (_rect(px, py, pw, pd), [], h, h + 3.5)])
    if spec.style == "tower":
        tw, td = w * rng.uniform(0.45, 0.55), d * rng.uniform(0.45, 0.55)
        tx, ty = rng.uniform(-0.08, 0.08) * w, rng.uniform(-0.08, 0.08) * d
        return _stack(
            spec.name,
            spec,
            [(_rect(0, 0, w, d), [], 0.0, h), (_rect(tx, ty, tw, td), [], h, h * rng.uniform(2.6, 3.2))],
        )
    if spec.style == "lshape":
        fw, fd = w * rng.uniform(0.4, 0.5), d * rng.uniform(0.4, 0.5)
        x0, y0, x1, y1 = -w / 2, -d / 2, w / 2, d / 2
        ring = np.array([[x0, y0], [x1, y0], [x1, y0 + fd], [x0 + fw, y0 + fd], [x0 + fw, y1], [x0, y1]])
        return _stack(spec.name, spec, [(ring, [], 0.0, h)])
    if spec.style == "courtyard":
        cw, cd = w * rng.uniform(0.4, 0.5), d * rng.uniform(0.35, 0.45)
        inner = _rect(0, 0, cw, cd)[::-1]  # clockwise from above: its walls face into the yard
        return _stack(spec.name, spec, [(_rect(0, 0, w, d), [inner], 0.0, h)])
    if spec.style == "gable":
        import shapely

        rise = min(w, d) * rng.uniform(0.3, 0.45)
        x0, y0, x1, y1 = -w / 2, -d / 2, w / 2, d / 2  # ridge along x
        faces = [
            _wall("", (x0, y0), (x1, y0), 0.0, h),
            _wall("", (x1, y1), (x0, y1), 0.0, h),
        ]
        for p0, p1 in (((x1, y0), (x1, y1)), ((x0, y1), (x0, y0))):
            f = _wall("", p0, p1, 0.0, h)
            L = f.length
            f.outer = f.to3d(np.array([[0, 0], [L, 0], [L, h], [L / 2, h + rise], [0, h]]))
            faces.append(f)
        zr = h + rise
        for ring in (
            np.array([[x0, y0, h], [x1, y0, h], [x1, 0, zr], [x0, 0, zr]]),
            np.array([[x1, y1, h], [x0, y1, h], [x0, 0, zr], [x1, 0, zr]]),
        ):
            a = (ring[1] - ring[0]) / np.linalg.norm(ring[1] - ring[0])
            n = np.cross(ring[1] - ring[0], ring[2] - ring[1])
            n /= np.linalg.norm(n)
            faces.append(Face("", "roof", ring, ring[0].copy(), a, np.cross(n, a)))
        return _finish(spec.name, spec, faces, shapely.Polygon(_rect(0, 0, w, d)))
    raise DifftexError(f"building '{spec.name}': unknown style '{spec.style}' (box, gable, lshape, tower, courtyard)")
