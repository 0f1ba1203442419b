"""The detailed model the photos are rendered from: relief the proxy lacks, and occluders.

Walls get recessed openings (reveals + a back pane carrying the same painted texture),
cornices, string courses and balconies; flat roofs get plant boxes. Occluders (trees, poles,
parked cars) stand in front of walls. Geometry is plain numpy triangle soup, grouped by
material, so the renderer module only has to hand it to Mitsuba.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from difftex.scene.planar import triangulate_rings
from difftex.synth.buildings import Building, Face
from difftex.synth.facades import Bitmap, Layout


@dataclass
class Part:
    """Triangles sharing one material: a bitmap (with per-vertex uv) or a constant albedo."""

    name: str
    vertices: np.ndarray  # (N, 3)
    faces: np.ndarray  # (M, 3) int
    uv: np.ndarray | None = None
    bitmap: np.ndarray | None = None
    color: tuple[float, float, float] | None = None


@dataclass
class Primitive:
    """A Mitsuba built-in shape (occluders): kind sphere|cylinder|cube with its parameters."""

    kind: str
    params: dict
    color: tuple[float, float, float]


@dataclass
class DetailedModel:
    parts: list[Part] = field(default_factory=list)
    occluders: list[Primitive] = field(default_factory=list)
    protrusion: dict[str, float] = field(default_factory=dict)  # face id -> how far relief sticks out


class _Soup:
    def __init__(self):
        self.v, self.f, self.uv = [], [], []
        self.n = 0

    def add(self, verts, tris, uv=None):
        verts = np.asarray(verts, float)
        self.v.append(verts)
        self.f.append(np.asarray(tris, np.int64) + self.n)
        if uv is not None:
            self.uv.append(np.asarray(uv, float))
        self.n += len(verts)

    def quad(self, corners):
        self.add(corners, [[0, 1, 2], [0, 2, 3]])

    def box(self, face: Face, u0, u1, v0, v1, n0, n1):
        """Box in a face's frame: u along, v in-plane up, n outward offsets."""
        c = np.array([[u, v] for v in (v0, v1) for u in (u0, u1)])
        lo, hi = face.to3d(c, n0), face.to3d(c, n1)
        P = np.concatenate([lo, hi])  # 0..3 at n0, 4..7 at n1 ; order (u0v0,u1v0,u0v1,u1v1)
        quads = [(0, 1, 3, 2), (4, 5, 7, 6), (0, 1, 5, 4), (2, 3, 7, 6), (0, 2, 6, 4), (1, 3, 7, 5)]
        tris = [t for a, b, c_, d in quads for t in ((a, b, c_), (a, c_, d))]
        self.add(P, tris)

    def part(self, name, **mat) -> Part | None:
        if not self.v:
            return None
        return Part(name, np.concatenate(self.v), np.concatenate(self.f),
                    np.concatenate(self.uv) if self.uv else None, **mat)


def build_detail(building: Building, layouts: dict[str, Layout], bitmaps: dict[str, Bitmap],
                 relief: float, rng: np.random.Generator, occluders: bool, occluder_count: int) -> DetailedModel:
    model = DetailedModel()
    trim, rail, plant = _Soup(), _Soup(), _Soup()
    bd = float(np.clip(1.5 * relief, 0.0, 0.9))
    for face in building.faces:
        lay, bm = layouts[face.id], bitmaps[face.id]
        soup = _Soup()
        p2 = face.poly2d
        openings = []
        if relief > 0:
            for u0, v0, u1, v1 in lay.openings():
                openings.append((u0, max(v0, 0.02), u1, v1))
        holes = [np.array([[u0, v0], [u0, v1], [u1, v1], [u1, v0]]) for u0, v0, u1, v1 in openings]  # clockwise
        verts2 = np.concatenate([p2, *holes]).astype(np.float64)
        tris = triangulate_rings([p2, *holes])
        soup.add(face.to3d(verts2), tris, bm.uv(verts2))
        prot = 0.0
        for u0, v0, u1, v1 in openings:
            back = np.array([[u0, v0], [u1, v0], [u1, v1], [u0, v1]])
            soup.add(face.to3d(back, -relief), [[0, 1, 2], [0, 2, 3]], bm.uv(back))
            for a, b in ((back[i], back[(i + 1) % 4]) for i in range(4)):
                seg = np.array([a, b])
                trim.quad(np.concatenate([face.to3d(seg, 0.0), face.to3d(seg[::-1], -relief)]))
        if face.kind == "wall" and relief > 0:
            L, He = face.length, face.eave
            if lay.cornice:
                trim.box(face, -relief, L + relief, He - 0.45, He, 0.0, relief)
                prot = max(prot, relief)
            for v in lay.courses:
                trim.box(face, 0.0, L, v - 0.2, v + 0.05, 0.0, 0.5 * relief)
            for u0, u1, v in lay.balconies:
                trim.box(face, u0, u1, v - 0.15, v, 0.0, bd)
                rail.box(face, u0, u1, v, v + 1.0, bd - 0.04, bd)
                rail.box(face, u0, u0 + 0.04, v, v + 1.0, 0.0, bd)
                rail.box(face, u1 - 0.04, u1, v, v + 1.0, 0.0, bd)
                prot = max(prot, bd)
        if face.kind == "roof" and relief > 0 and abs(face.normal[2]) > 0.95:
            prot = max(prot, _plant_boxes(face, plant, rng))
        model.protrusion[face.id] = prot
        model.parts.append(soup.part(f"face_{face.id}", bitmap=bm.pixels))
    st = next(iter(layouts.values())).style
    for soup, name, color in ((trim, "trim", tuple(st["trim_color"])), (rail, "rail", (0.12, 0.12, 0.13)),
                              (plant, "plant", (0.45, 0.46, 0.47))):
        p = soup.part(name, color=color)
        if p is not None:
            model.parts.append(p)
    if occluders:
        model.occluders = place_occluders(building, rng, occluder_count)
    return model


def _plant_boxes(face: Face, soup: _Soup, rng) -> float:
    import shapely

    poly = shapely.Polygon(face.poly2d).buffer(-1.5)
    if poly.is_empty or poly.area < 20:
        return 0.0
    x0, y0, x1, y1 = poly.bounds
    h_max = 0.0
    for _ in range(int(rng.integers(1, 4))):
        w, d, h = rng.uniform(0.8, 2.2), rng.uniform(0.8, 1.6), rng.uniform(0.5, 1.2)
        cu, cv = rng.uniform(x0, x1), rng.uniform(y0, y1)
        if not poly.contains(shapely.box(cu - w / 2, cv - d / 2, cu + w / 2, cv + d / 2)):
            continue
        soup.box(face, cu - w / 2, cu + w / 2, cv - d / 2, cv + d / 2, 0.0, h)
        h_max = max(h_max, h)
    return h_max


def place_occluders(building: Building, rng: np.random.Generator, count: int) -> list[Primitive]:
    """Trees, lamp poles and parked cars in front of ground-floor walls, never inside the footprint."""
    import shapely

    ground_walls = [f for f in building.walls if f.outer[:, 2].min() < 1e-6]
    lengths = np.array([w.length for w in ground_walls])
    if count < 0:
        count = max(2, int(lengths.sum() / 9.0))
    blocked = building.footprint.buffer(1.0)
    placed: list[tuple[np.ndarray, float]] = []
    prims: list[Primitive] = []
    tries = 0
    while len(placed) < count and tries < 40 * count:
        tries += 1
        wall = ground_walls[rng.choice(len(ground_walls), p=lengths / lengths.sum())]
        kind = rng.choice(["tree", "pole", "car"], p=[0.55, 0.2, 0.25])
        dist = {"tree": rng.uniform(2.5, 6.0), "pole": rng.uniform(1.5, 3.0), "car": rng.uniform(2.2, 4.0)}[kind]
        radius = {"tree": 2.2, "pole": 0.3, "car": 2.4}[kind]
        u = rng.uniform(1.0, max(1.01, wall.length - 1.0))
        c = wall.to3d(np.array([[u, 0.0]]), dist)[0]
        c[2] = 0.0
        disk = shapely.Point(c[:2]).buffer(radius if kind != "tree" else 1.0)
        if disk.intersects(blocked) or any(np.linalg.norm(c[:2] - p[:2]) < r + radius for p, r in placed):
            continue
        placed.append((c, radius))
        prims.extend(_occluder(kind, c, wall.a, rng))
    return prims


def _occluder(kind, c, along, rng) -> list[Primitive]:
    x, y = float(c[0]), float(c[1])
    if kind == "tree":
        h = rng.uniform(2.5, 4.0)
        out = [Primitive("cylinder", {"p0": [x, y, 0.0], "p1": [x, y, h + 0.5], "radius": rng.uniform(0.12, 0.2)},
                         (0.2, 0.13, 0.08))]
        green = np.array([0.08, 0.2, 0.05]) * rng.uniform(0.7, 1.3, 3)
        for _ in range(int(rng.integers(3, 6))):
            r = rng.uniform(0.9, 1.8)
            off = rng.uniform(-0.9, 0.9, 3) * [1, 1, 0.6]
            out.append(Primitive("sphere", {"center": [x + off[0], y + off[1], h + r * 0.8 + off[2]], "radius": r},
                                 tuple(np.clip(green * rng.uniform(0.8, 1.2), 0.01, 1).tolist())))
        return out
    if kind == "pole":
        h = rng.uniform(5.0, 7.0)
        return [Primitive("cylinder", {"p0": [x, y, 0.0], "p1": [x, y, h], "radius": 0.08}, (0.15, 0.15, 0.16)),
                Primitive("sphere", {"center": [x, y, h + 0.2], "radius": 0.3}, (0.8, 0.78, 0.7))]
    # car: body and cabin boxes oriented along the wall, four wheels
    a = np.array([along[0], along[1], 0.0])
    b = np.cross([0, 0, 1.0], a)
    base = np.array([0.6, 0.05, 0.05]) if rng.random() < 0.3 else rng.uniform(0.05, 0.7, 3)
    color = tuple(np.clip(base, 0.02, 0.9).tolist())

    def box(cx, cy, cz, sx, sy, sz):
        M = np.eye(4)
        M[:3, 0], M[:3, 1], M[:3, 2] = a * sx / 2, b * sy / 2, [0, 0, sz / 2]
        M[:3, 3] = np.array([x, y, 0.0]) + a * cx + b * cy + [0, 0, cz]
        return {"to_world": M.tolist()}

    out = [
        Primitive("cube", box(0, 0, 0.7, 4.3, 1.8, 0.8), color),
        Primitive("cube", box(-0.2, 0, 1.4, 2.3, 1.6, 0.6), tuple(np.array(color) * 0.8)),
    ]
    for su in (-1.4, 1.4):
        for sv in (-0.9, 0.9):
            p = np.array([x, y, 0.33]) + a * su + b * sv
            out.append(
                Primitive(
                    "cylinder",
                    {"p0": (p - b * 0.12).tolist(), "p1": (p + b * 0.12).tolist(), "radius": 0.33},
                    (0.03, 0.03, 0.03),
                )
            )
    return out
