"""Z-buffer of the proxy in a pinhole photo: the polygon each pixel's ray meets first, and how far.

For a pinhole camera, casting rays at a planar proxy is rasterising its triangles: a pixel's ray
lies inside a triangle when it is on the inner side of the three planes through the camera
centre and each edge, and its distance to the triangle's plane is a ratio of linear functions
of the normalised pixel coordinates. Both are separable over the pixel grid, so a triangle
costs a few array operations over its projected bounding box, with no ray per pixel. Mitsuba
casts every ray of the grid (about 10 M rays per second on two cores here); this is several
times faster on the proxies difftex textures (tens to a few thousand triangles), with the same
answer up to pixels that graze an edge. GPU rasterisers (nvdiffrast, moderngl, pyrender) need
a GPU or a GL context, which cluster nodes do not promise.

Lens distortion bends the triangles' edges: distorted photos, and triangles that cross the
camera's plane, are left to ray casting (``zbuffer`` returns None).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from difftex.scene.camera import Photo
from difftex.scene.proxy import Proxy, triangulate

NO_POLYGON = -1
# Below this camera depth a vertex is taken to be on the camera's plane (as Photo.project does).
_MIN_DEPTH = 1e-6


@dataclass(frozen=True, eq=False)
class Pieces:
    """The proxy as convex planar pieces: a convex polygon without holes whole, any other
    polygon as its ear-clipped triangles."""

    world: list[np.ndarray]  # (n_j, 3) float64 vertices of piece j, in order around it
    polygon: np.ndarray  # (J,) int32 index into proxy.polygons

    @classmethod
    def of(cls, proxy: Proxy) -> Pieces:
        world: list[np.ndarray] = []
        owner: list[int] = []
        for i, poly in enumerate(proxy.polygons):
            if not poly.holes and _convex(poly.to_plane(poly.outer)):
                world.append(np.asarray(poly.outer, np.float64))
                owner.append(i)
                continue
            v, t = triangulate(poly)
            world.extend(v[t])
            owner.extend([i] * len(t))
        return cls(world, np.asarray(owner, np.int32))

    @cached_property
    def stacked(self) -> tuple[np.ndarray, np.ndarray]:
        """(every piece's vertices (N, 3) in one array, the index of each piece's first vertex (J,)):
        a photo transforms and culls all pieces with a few array operations, not one call per
        piece (a district's thousands of pieces, most outside any one photo)."""
        if not self.world:
            return np.zeros((0, 3)), np.zeros(0, np.int64)
        sizes = np.array([len(w) for w in self.world])
        return np.concatenate(self.world), np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64)


def _convex(xy: np.ndarray) -> bool:
    """Whether a closed 2D outline (n, 2) turns one way only (collinear vertices allowed)."""
    e = np.roll(xy, -1, axis=0) - xy
    turn = e[:, 0] * np.roll(e[:, 1], -1) - e[:, 1] * np.roll(e[:, 0], -1)
    scale = 1e-12 * float(np.abs(e).max() ** 2) if len(e) else 0.0
    return len(xy) >= 3 and ((turn >= -scale).all() or (turn <= scale).all())


def pixel_centres(size: int, stride: int) -> np.ndarray:
    """Pixel-centre coordinates of a photo axis sampled every ``stride`` pixels (as the ray grid)."""
    return np.minimum(np.arange(0, size, stride) + 0.5 * stride, size - 0.5)


def zbuffer(pieces: Pieces, photo: Photo, stride: int = 1) -> tuple[np.ndarray, np.ndarray] | None:
    """Nearest polygon per pixel and the distance along the pixel's unit ray, for a pinhole photo.

    Args:
        pieces: the proxy's convex pieces.
        photo: a pinhole photo (PINHOLE or SIMPLE_PINHOLE).
        stride: sample every ``stride``-th pixel centre (as ``raycast.pixel_rays``).

    Returns:
        (ids (h, w) int32, -1 where no polygon; dist (h, w) float32, inf where none), with
        h = ceil(H / stride), w = ceil(W / stride); or None when the photo is distorted or a
        piece crosses the camera's plane (its image is not a polygon): cast rays then.
    """
    if not photo.is_pinhole:
        return None
    ys, xs = pixel_centres(photo.height, stride), pixel_centres(photo.width, stride)
    ids = np.full((len(ys), len(xs)), NO_POLYGON, np.int32)
    dist = np.full((len(ys), len(xs)), np.inf, np.float32)
    world, starts = pieces.stacked
    if len(starts) == 0:
        return ids, dist
    allc = photo.to_camera(world)  # every piece's vertices in the camera frame, in one product
    ends = np.append(starts[1:], len(allc))
    z = allc[:, 2]
    front = np.minimum.reduceat(z, starts) > _MIN_DEPTH
    if ((np.maximum.reduceat(z, starts) > _MIN_DEPTH) & ~front).any():
        return None  # a piece crosses the camera's plane
    K = photo.K()
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    # normalised image coordinates of the grid: the ray of cell (r, c) is (u[c], v[r], 1)
    u, v = (xs - cx) / fx, (ys - cy) / fy
    # a piece in front of the camera projects inside its vertices' bounding box: one wholly
    # beside the grid meets no ray (the test is conservative by a margin; _rows_inside decides)
    with np.errstate(divide="ignore", invalid="ignore"):
        pu, pv = allc[:, 0] / z, allc[:, 1] / z
    eu, ev = 1e-9 * (1.0 + abs(u[-1] - u[0])), 1e-9 * (1.0 + abs(v[-1] - v[0]))
    seen = front & (np.maximum.reduceat(pu, starts) >= u[0] - eu) & (np.minimum.reduceat(pu, starts) <= u[-1] + eu)
    seen &= (np.maximum.reduceat(pv, starts) >= v[0] - ev) & (np.minimum.reduceat(pv, starts) <= v[-1] + ev)
    norm: np.ndarray | None = None  # |(u, v, 1)| over the grid, made when a piece is in view
    for j in np.flatnonzero(seen):  # a piece wholly behind the camera, or beside it, meets no ray
        span = _rows_inside(allc[starts[j] : ends[j]], u, v)
        if span is None:
            continue
        r0, r1, lo, hi = span
        c0, c1 = int(lo.min()), int(hi.max())
        if norm is None:
            # float32 from the start: a float64 grid of a 24 Mpixel photo is 190 MB
            u32, v32 = u.astype(np.float32), v.astype(np.float32)
            norm = np.sqrt((u32 * u32)[None, :] + (v32 * v32 + np.float32(1.0))[:, None])
        P = allc[starts[j] : ends[j]]
        normal = np.cross(P[1] - P[0], P[2] - P[0])
        h = float(normal @ P[0])  # plane: normal . X = h (camera frame)
        cols = np.arange(c0, c1)
        inside = (cols[None, :] >= lo[:, None]) & (cols[None, :] < hi[:, None])
        denom = (normal[0] * u[c0:c1])[None, :] + (normal[1] * v[r0:r1] + normal[2])[:, None]
        with np.errstate(divide="ignore", invalid="ignore"):
            d = (h * norm[r0:r1, c0:c1]) / denom.astype(np.float32)
        blk = dist[r0:r1, c0:c1]
        closer = inside & (d > 0) & (d < blk)
        # masked copies in place: a boolean index gathers and scatters every selected pixel
        np.copyto(blk, d, where=closer)
        np.copyto(ids[r0:r1, c0:c1], pieces.polygon[j], where=closer)
    return ids, dist


def _rows_inside(P: np.ndarray, u: np.ndarray, v: np.ndarray) -> tuple[int, int, np.ndarray, np.ndarray] | None:
    """The grid cells whose rays pass through a convex piece, as per-row column ranges.

    A ray (u, v, 1) is inside when it is on the inner side of every plane through the camera
    centre and an edge: a e_u + b e_v + c >= 0 per edge, which on a row is a bound on u.

    Args:
        P: (n, 3) the piece's vertices in the camera frame, all in front of it.
        u, v: (w,), (h,) increasing normalised coordinates of the grid's columns and rows.
    Returns:
        (r0, r1, lo (r1 - r0,), hi (r1 - r0,)): rows r0..r1-1, columns lo[r]..hi[r]-1; None if empty.
    """
    edges = np.cross(P, np.roll(P, -1, axis=0))  # (n, 3) normals of the edge planes
    keep = np.linalg.norm(edges, axis=1) > 1e-12 * np.linalg.norm(P, axis=1) ** 2
    if keep.sum() < 3:
        return None
    inner = P.mean(0)
    side = edges @ inner
    if (np.abs(side[keep]) <= 1e-12 * np.linalg.norm(edges[keep], axis=1) * np.linalg.norm(inner)).any():
        return None  # seen edge-on: no ray crosses its interior
    edges = edges[keep] * np.sign(side[keep])[:, None]
    pv = P[:, 1] / P[:, 2]
    r0, r1 = np.searchsorted(v, pv.min() - 1e-12), np.searchsorted(v, pv.max() + 1e-12, side="right")
    if r0 >= r1:
        return None
    vv = v[r0:r1]
    lo_u = np.full(len(vv), -np.inf)
    hi_u = np.full(len(vv), np.inf)
    ok = np.ones(len(vv), bool)
    for a, b, c in edges:
        rest = b * vv + c  # a u + rest >= 0
        if a > 0:
            lo_u = np.maximum(lo_u, -rest / a)
        elif a < 0:
            hi_u = np.minimum(hi_u, -rest / a)
        else:
            ok &= rest >= 0
    lo = np.searchsorted(u, lo_u, side="left")  # first column with u >= lo_u
    hi = np.searchsorted(u, hi_u, side="right")  # past the last column with u <= hi_u
    hi = np.where(ok & (hi > lo), hi, lo)
    rows = np.flatnonzero(hi > lo)
    if len(rows) == 0:
        return None
    a, b = rows[0], rows[-1] + 1
    return int(r0 + a), int(r0 + b), lo[a:b], hi[a:b]
