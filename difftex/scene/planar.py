"""Planar loops: a loop's normal, area and planarity; the one triangulator (``triangulate_rings``,
earcut); and a triangle mesh's coplanar regions as planar polygons with holes (how a triangulated proxy
file becomes polygons): vertices welded, triangles grouped by shared edges and a common plane, each group's
boundary loops traced along triangle orientation and cleared of collinear vertices.

Why not trimesh's ``facets``: it returns only groups of two or more faces (a polygon made of one
triangle would be lost) and joins neighbours pairwise by their angle, so a slowly curving surface
chains into one facet; here every triangle of a group is tested against the plane of the group's
first triangle, within both an angle and a distance tolerance.
"""

from __future__ import annotations

import numpy as np


def newell_normal(loop: np.ndarray) -> np.ndarray:
    """Unit normal of a (possibly non-convex) loop; right-hand rule on the vertex order."""
    v = np.asarray(loop, dtype=np.float64)
    w = np.roll(v, -1, axis=0)
    n = np.array(
        [
            np.sum((v[:, 1] - w[:, 1]) * (v[:, 2] + w[:, 2])),
            np.sum((v[:, 2] - w[:, 2]) * (v[:, 0] + w[:, 0])),
            np.sum((v[:, 0] - w[:, 0]) * (v[:, 1] + w[:, 1])),
        ]
    )
    norm = np.linalg.norm(n)
    return n / norm if norm > 0 else n


def polygon_area(loop: np.ndarray) -> float:
    v = np.asarray(loop, dtype=np.float64)
    w = np.roll(v, -1, axis=0)
    return 0.5 * float(np.linalg.norm(np.cross(v, w).sum(axis=0)))


def triangulate_rings(rings: list[np.ndarray]) -> np.ndarray:
    """Triangles (m, 3) of a 2D outline with holes, ``rings`` = [outer, *holes], as indices into the
    rings' concatenated vertices (mapbox earcut: holes handled robustly, no Delaunay needed)."""
    import mapbox_earcut

    verts = np.concatenate(rings).astype(np.float64)
    ends = np.cumsum([len(r) for r in rings]).astype(np.uint32)
    return np.asarray(mapbox_earcut.triangulate_float64(verts, ends), dtype=np.int64).reshape(-1, 3)


def planarity_deviation(points: np.ndarray) -> float:
    """Largest distance of a point from the least-squares plane."""
    p = np.asarray(points, dtype=np.float64)
    c = p - p.mean(axis=0)
    if len(p) < 4:
        return 0.0
    n = np.linalg.svd(c, full_matrices=False)[2][-1]
    return float(np.abs(c @ n).max())


def _group_triangles(verts, tris, angle_tol_deg, dist_tol_rel):
    """Connected components of triangles whose normals and planes agree; returns lists of tri ids."""
    tris = np.asarray(tris, dtype=np.int64)
    p = verts[tris]
    n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    area2 = np.linalg.norm(n, axis=1)
    ok = area2 > 1e-14 * max(1.0, float(np.ptp(verts, axis=0).max()) ** 2)
    n[ok] /= area2[ok, None]
    # shared-edge adjacency
    edges = {}
    for t, tri in enumerate(tris):
        if not ok[t]:
            continue
        for a, b in ((tri[0], tri[1]), (tri[1], tri[2]), (tri[2], tri[0])):
            edges.setdefault((min(a, b), max(a, b)), []).append(t)
    neigh = [[] for _ in range(len(tris))]
    for ts in edges.values():
        for a in ts:
            for b in ts:
                if a != b:
                    neigh[a].append(b)
    cos_tol = np.cos(np.radians(angle_tol_deg))
    scale = float(np.linalg.norm(np.ptp(verts, axis=0))) or 1.0
    dist_tol = dist_tol_rel * scale
    seen = np.zeros(len(tris), bool)
    groups = []
    for seed in range(len(tris)):
        if seen[seed] or not ok[seed]:
            continue
        n0, d0 = n[seed], float(n[seed] @ p[seed, 0])
        stack, group = [seed], []
        seen[seed] = True
        while stack:
            t = stack.pop()
            group.append(t)
            for u in neigh[t]:
                if seen[u] or n[u] @ n0 < cos_tol or np.abs(p[u] @ n0 - d0).max() > dist_tol:
                    continue
                seen[u] = True
                stack.append(u)
        groups.append(sorted(group))
    return groups


def _boundary_loops(tris: np.ndarray) -> list[list[int]]:
    """Closed loops of edges used by exactly one triangle, following triangle orientation."""
    count = {}
    for tri in tris:
        for a, b in ((tri[0], tri[1]), (tri[1], tri[2]), (tri[2], tri[0])):
            count[(a, b)] = count.get((a, b), 0) + 1
    nxt = {}
    for (a, b) in count:
        if (b, a) not in count:
            nxt.setdefault(a, []).append(b)
    loops, used = [], set()
    for start in sorted(nxt):
        for first in nxt[start]:
            if (start, first) in used:
                continue
            loop, a, b = [start], start, first
            used.add((a, b))
            while b != start and len(loop) <= len(count):
                loop.append(b)
                cands = [c for c in nxt.get(b, []) if (b, c) not in used]
                if not cands:
                    break
                a, b = b, cands[0]
                used.add((a, b))
            if b == start and len(loop) >= 3:
                loops.append(loop)
    return loops


def _simplify_loop(loop: np.ndarray, tol: float) -> np.ndarray:
    """Drop vertices that lie on the straight line through their neighbours (triangulation leftovers)."""
    pts = list(loop)
    changed = True
    while changed and len(pts) > 3:
        changed = False
        for i in range(len(pts)):
            a, b, c = pts[i - 1], pts[i], pts[(i + 1) % len(pts)]
            ac = c - a
            L = np.linalg.norm(ac)
            if L == 0 or np.linalg.norm(np.cross(b - a, ac)) / L < tol:
                del pts[i]
                changed = True
                break
    return np.asarray(pts)


def _weld(verts: np.ndarray, tris: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Merge vertices at the same position so triangle soups (one vertex per corner) connect."""
    scale = float(np.linalg.norm(np.ptp(verts, axis=0))) or 1.0
    key = np.round(verts / (1e-9 * scale)).astype(np.int64)
    uniq, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    return verts[first], inverse.reshape(-1)[tris]


def polygons_from_triangles(verts, tris, angle_tol_deg, dist_tol_rel):
    """[(outer loop, holes, first triangle id)] of the coplanar groups of a triangle mesh."""
    verts, tris = _weld(verts, np.asarray(tris, dtype=np.int64))
    out = []
    for group in _group_triangles(verts, tris, angle_tol_deg, dist_tol_rel):
        gt = np.asarray(tris, dtype=np.int64)[group]
        loops = [verts[np.asarray(lp)] for lp in _boundary_loops(gt)]
        if not loops:
            continue
        pn = np.cross(verts[gt[:, 1]] - verts[gt[:, 0]], verts[gt[:, 2]] - verts[gt[:, 0]]).sum(axis=0)
        pn /= np.linalg.norm(pn) or 1.0
        scale = float(np.linalg.norm(np.ptp(verts[gt.ravel()], axis=0)))
        loops = [_simplify_loop(lp, 1e-9 * max(scale, 1e-12)) for lp in loops]
        areas = [polygon_area(lp) for lp in loops]
        k = int(np.argmax(areas))
        outer = loops[k]
        if newell_normal(outer) @ pn < 0:
            outer = outer[::-1]
        holes = []
        for i, lp in enumerate(loops):
            if i != k:
                holes.append(lp if newell_normal(lp) @ pn < 0 else lp[::-1])
        out.append((outer, tuple(holes), group[0]))
    return out
