"""Ray casting against the proxy: which polygon each ray hits first, and how far.

Mitsuba 3 (a dependency already, for the synthetic scenes) intersects the ear-clipped proxy
with its LLVM backend, vectorised and multi-threaded: some 10 M rays per second here, where the
exact per-polygon ray-plane and point-in-polygon casting of ``_cast_numpy`` does about 0.5 M.
``_cast_numpy`` is kept for machines without LLVM (Mitsuba's scalar variants intersect one ray
per Python call): it gives the same answer (tests compare the two).

Rays are in world coordinates; both backends work relative to the proxy's centre so that float32
keeps its precision in large (e.g. UTM) coordinates.
"""

from __future__ import annotations

import functools
import logging
import threading
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from difftex.geometry.zbuffer import NO_POLYGON, Pieces, pixel_centres, zbuffer
from difftex.scene.camera import Photo
from difftex.scene.proxy import Proxy, triangulate

log = logging.getLogger(__name__)

MITSUBA_VARIANT = "llvm_ad_rgb"


def mitsuba_scene(vertices: np.ndarray, faces: np.ndarray):
    """A Mitsuba scene (LLVM variant) of one triangle mesh, for ray queries.

    Args:
        vertices: (V, 3), already relative to a nearby centre (they are cast to float32);
        faces: (F, 3) vertex indices.
    """
    import drjit as dr
    import mitsuba as mi

    mi.set_variant(MITSUBA_VARIANT)
    V = np.asarray(vertices, np.float32)
    mesh = mi.Mesh("mesh", len(V), len(faces))
    params = mi.traverse(mesh)
    params["vertex_positions"] = dr.ravel(mi.Point3f(V[:, 0], V[:, 1], V[:, 2]))
    params["faces"] = np.asarray(faces, np.uint32).ravel()
    params.update()
    return mi.load_dict({"type": "scene", "mesh": mesh})


@functools.lru_cache(maxsize=1)
def mitsuba_available() -> bool:
    """Whether Mitsuba's LLVM variant loads (it needs libLLVM, Debian's libllvm19)."""
    try:
        import mitsuba as mi

        mi.set_variant(MITSUBA_VARIANT)
        return True
    except Exception as exc:  # noqa: BLE001 - ImportError, or the variant cannot find libLLVM
        log.info("Mitsuba %s unavailable (%s): ray casting in numpy", MITSUBA_VARIANT, exc)
        return False


@dataclass(eq=False)
class ProxyCaster:
    """The proxy prepared for casting; ``cast`` returns (polygon index, distance) per ray."""

    proxy: Proxy
    centre: np.ndarray  # (3,) origin of the float32 frame
    backend: str  # "mitsuba" or "numpy": how rays are cast ("auto": chosen at the first cast)
    # pinhole photos rasterised instead of cast (backend "auto"): the same answer, faster
    pieces: Pieces | None = None
    _scene: Any = None  # mitsuba.Scene (mitsuba ships no type information)
    _tri_polygon: Any = None  # (T,) polygon index of each triangle
    _planes: Any = None  # numpy backend: visibility._PlanarPolygons
    # one thread at a time prepares the backend and casts with Mitsuba (its scene is not shared
    # across threads here) or numpy (shapely builds its prepared polygons' indices on first
    # use); rasterising needs no lock
    _lock: Any = field(default_factory=threading.RLock, repr=False)

    @classmethod
    def build(cls, proxy: Proxy, backend: str = "auto") -> ProxyCaster:
        """``backend``: "auto" (pinhole photos rasterised, :mod:`difftex.geometry.zbuffer`; other
        rays cast by Mitsuba when its LLVM variant loads, else in numpy), "mitsuba" or "numpy"
        (every ray cast by that backend)."""
        allv = np.concatenate([p.outer for p in proxy.polygons]) if proxy.polygons else np.zeros((1, 3))
        centre = allv.mean(0)
        pieces = Pieces.of(proxy) if backend == "auto" else None
        caster = cls(proxy=proxy, centre=centre, backend=backend, pieces=pieces)
        if backend != "auto":
            caster._ready()
        return caster

    def _ready(self) -> None:
        """Prepare the ray backend. "auto" waits for the first ray that rasterising cannot answer
        (a distorted photo, a polygon across the camera plane): with pinhole photos, loading
        Mitsuba (0.26 s per process) and its scene would be for nothing."""
        with self._lock:
            if self._scene is not None or self._planes is not None:
                return
            if self.backend == "auto":
                self.backend = "mitsuba" if mitsuba_available() else "numpy"
            if self.backend == "mitsuba":
                self._build_mitsuba()
            else:
                self._planes = _planar(self.proxy)

    def _build_mitsuba(self) -> None:
        Vs: list[np.ndarray] = []
        Fs: list[np.ndarray] = []
        owner: list[np.ndarray] = []
        n = 0
        for i, poly in enumerate(self.proxy.polygons):
            v, t = triangulate(poly)
            Vs.append(v - self.centre)
            Fs.append(t + n)
            owner.append(np.full(len(t), i, np.int32))
            n += len(v)
        self._scene = mitsuba_scene(np.concatenate(Vs), np.concatenate(Fs))
        self._tri_polygon = np.concatenate(owner)

    def cast(self, origin: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """First hit of rays from ``origin`` (3,) along unit ``dirs`` (..., 3).

        Returns:
            (polygon index (...) int32, -1 for none; distance along the ray (...) float32, inf for none).
        """
        self._ready()
        shape = dirs.shape[:-1]
        d = np.ascontiguousarray(dirs.reshape(-1, 3), dtype=np.float32)
        o = np.asarray(origin, np.float64) - self.centre
        if self.backend == "mitsuba":
            with self._lock:
                ids, dist = self._cast_mitsuba(o, d)
        else:
            ids, dist = self._cast_numpy(o, d)
        return ids.reshape(shape), dist.reshape(shape)

    def _cast_mitsuba(self, o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        import mitsuba as mi

        n = len(d)
        if n == 0:
            return np.zeros(0, np.int32), np.zeros(0, np.float32)
        org = mi.Point3f(np.full(n, o[0], np.float32), np.full(n, o[1], np.float32), np.full(n, o[2], np.float32))
        ray = mi.Ray3f(org, mi.Vector3f(d[:, 0], d[:, 1], d[:, 2]))
        pi = self._scene.ray_intersect_preliminary(ray)
        t = np.asarray(pi.t, np.float32)
        prim = np.asarray(pi.prim_index, np.int64)
        hit = np.isfinite(t)
        ids = np.full(n, NO_POLYGON, np.int32)
        ids[hit] = self._tri_polygon[prim[hit]]
        return ids, np.where(hit, t, np.inf).astype(np.float32)

    def _cast_numpy(self, o: np.ndarray, d: np.ndarray, chunk: int = 1 << 18) -> tuple[np.ndarray, np.ndarray]:
        """Exact casting: per polygon, ray-plane distance and a point-in-polygon test (shapely)."""
        import shapely

        pp = self._planes
        n = len(d)
        ids = np.full(n, NO_POLYGON, np.int32)
        dist = np.full(n, np.inf, np.float32)
        C = o + self.centre
        for j in range(len(pp.shapes)):
            nrm = pp.normals[j].astype(np.float32)
            h = np.float32(pp.offsets[j] - pp.normals[j] @ C)  # signed distance of the plane from the origin
            for a in range(0, n, chunk):
                rays = d[a : a + chunk]
                with np.errstate(divide="ignore", invalid="ignore"):
                    lam = h / (rays @ nrm)
                hit = (lam > 0) & np.isfinite(lam) & (lam < dist[a : a + chunk])
                if not hit.any():
                    continue
                (hr,) = np.nonzero(hit)
                lh = lam[hr].astype(np.float64)
                X = C + lh[:, None] * rays[hr].astype(np.float64) - pp.origins[j]
                inside = shapely.contains_xy(pp.shapes[j], X @ pp.b1[j], X @ pp.b2[j])
                ids[a + hr[inside]] = j
                dist[a + hr[inside]] = lh[inside]
        return ids, dist


@functools.lru_cache(maxsize=8)
def _camera_rays(model: str, width: int, height: int, params: tuple[float, ...], stride: int) -> np.ndarray:
    """Unit camera-frame ray directions (h, w, 3) of a camera's pixel centres (memoised: photos
    of one camera share them, and unprojecting through a distortion model is the costly part)."""
    ys, xs = pixel_centres(height, stride), pixel_centres(width, stride)
    if model in ("SIMPLE_PINHOLE", "PINHOLE"):
        # separable: a row and a column of normalised coordinates broadcast into the grid (a
        # meshgrid of float64 pixels was 0.9 s of a 6-Mpixel photo's 1.0 s here)
        f = (params[0], params[0]) if model == "SIMPLE_PINHOLE" else params[:2]
        c = params[1:3] if model == "SIMPLE_PINHOLE" else params[2:4]
        x = ((xs - c[0]) / f[0])[None, :]
        y = ((ys - c[1]) / f[1])[:, None]
        inv = 1.0 / np.sqrt(x * x + y * y + 1.0)
        d = np.empty((len(ys), len(xs), 3), np.float32)
        d[..., 0] = x * inv
        d[..., 1] = y * inv
        d[..., 2] = inv
        d.setflags(write=False)  # shared by every caller of the cache
        return d
    import pycolmap

    gx, gy = np.meshgrid(xs, ys)
    pix = np.stack([gx, gy], -1).reshape(-1, 2)
    cam = pycolmap.Camera(model=model, width=width, height=height, params=list(params))
    xy = np.asarray(cam.cam_from_img(pix), dtype=np.float64).reshape(-1, 2)
    d = np.concatenate([xy, np.ones((len(xy), 1))], axis=1)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    out = d.reshape(len(ys), len(xs), 3).astype(np.float32)
    out.setflags(write=False)  # shared by every caller of the cache
    return out


def camera_rays(photo: Photo, stride: int = 1) -> np.ndarray:
    """Camera-frame unit ray directions (h, w, 3) float32 through ``photo``'s pixel centres (every
    ``stride``-th; memoised per camera: read-only)."""
    params = tuple(float(v) for v in np.asarray(photo.camera.params, np.float64))
    return _camera_rays(photo.model, photo.width, photo.height, params, int(stride))


def pixel_rays(photo: Photo, stride: int = 1, window: tuple[int, int, int, int] | None = None) -> np.ndarray:
    """World-frame unit ray directions (h, w, 3) through the pixel centres of ``photo`` (every
    ``stride``-th pixel: h = ceil(H / stride)); ``window`` (y0, y1, x0, x1): only that block of
    the grid."""
    cam = camera_rays(photo, stride)
    if window is not None:
        y0, y1, x0, x1 = window
        cam = cam[y0:y1, x0:x1]
    return (cam.reshape(-1, 3) @ photo.R.astype(np.float32)).reshape(cam.shape)


def proxy_window(proxy: Proxy, photo: Photo, stride: int = 1) -> tuple[int, int, int, int] | None:
    """(y0, y1, x0, x1) block of the photo's ``stride`` grid that holds every ray that can hit the
    proxy, or None (the whole grid) when that is not known.

    For a pinhole camera with every proxy vertex in front of it, a polygon's image lies in the
    bounding box of its projected vertices (lines stay lines); other rays hit nothing. With lens
    distortion, edges bend beyond their vertices, and a vertex behind the camera has no image.
    """
    if not photo.is_pinhole or not proxy.polygons:
        return None
    V = np.concatenate([p.outer for p in proxy.polygons])
    pix, depth = photo.project(V)
    if not (depth > 1e-6).all() or not np.isfinite(pix).all():
        return None
    hgrid, wgrid = -(-photo.height // stride), -(-photo.width // stride)
    # grid cell j's ray passes through pixel (j + 0.5) stride: keep one cell of margin either side
    x0 = int(np.clip(np.floor(pix[:, 0].min() / stride) - 1, 0, wgrid))
    x1 = int(np.clip(np.ceil(pix[:, 0].max() / stride) + 1, 0, wgrid))
    y0 = int(np.clip(np.floor(pix[:, 1].min() / stride) - 1, 0, hgrid))
    y1 = int(np.clip(np.ceil(pix[:, 1].max() / stride) + 1, 0, hgrid))
    return y0, max(y0, y1), x0, max(x0, x1)


def id_buffer(proxy: Proxy | ProxyCaster, photo: Photo, stride: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Nearest proxy polygon per pixel (index into proxy.polygons, or -1) and its ray distance.

    ``stride`` > 1 samples every stride-th pixel centre (for cheap photo filtering); the result
    then has shape (ceil(H/stride), ceil(W/stride)). Build a ProxyCaster once to cast many photos.
    """
    caster = proxy if isinstance(proxy, ProxyCaster) else ProxyCaster.build(proxy)
    if caster.pieces is not None:
        raster = zbuffer(caster.pieces, photo, stride)
        if raster is not None:
            return raster
    caster._ready()
    if caster.backend == "numpy":
        # under the caster's lock: shapely builds its prepared polygons' indices on first use
        with caster._lock:
            return _id_buffer_numpy(caster._planes, photo, stride)
    win = proxy_window(caster.proxy, photo, stride)
    if win is None:
        return caster.cast(photo.center, pixel_rays(photo, stride))
    # only the rays that can hit the proxy (a building often fills a part of the frame)
    h, w = -(-photo.height // stride), -(-photo.width // stride)
    ids = np.full((h, w), NO_POLYGON, np.int32)
    dist = np.full((h, w), np.inf, np.float32)
    y0, y1, x0, x1 = win
    if y1 > y0 and x1 > x0:
        ids[y0:y1, x0:x1], dist[y0:y1, x0:x1] = caster.cast(photo.center, pixel_rays(photo, stride, win))
    return ids, dist


# ---------------------------------------------------------------------------------------------
# numpy backend


@dataclass(frozen=True, eq=False)
class _PlanarPolygons:
    """Polygons prepared for ray casting: planes, in-plane bases and shapely outlines."""

    normals: np.ndarray  # (P, 3)
    offsets: np.ndarray  # (P,)
    origins: np.ndarray  # (P, 3)
    b1: np.ndarray  # (P, 3)
    b2: np.ndarray  # (P, 3)
    shapes: list  # shapely Polygons in (b1, b2) coordinates
    vertices: list  # (n, 3) arrays, outer + holes, for projected bounding boxes


def prepare(proxy: Proxy) -> ProxyCaster:
    """The proxy prepared once for casting many photos (id_buffer)."""
    return ProxyCaster.build(proxy)


def _planar(proxy: Proxy) -> _PlanarPolygons:
    import shapely

    normals, offsets, origins, b1s, b2s, shapes, verts = [], [], [], [], [], [], []
    for p in proxy.polygons:
        o, b1, b2 = p.plane_basis()
        outer = p.to_plane(p.outer)
        holes = [p.to_plane(h) for h in p.holes]
        shp = shapely.Polygon(outer, holes)
        if not shp.is_valid:
            shp = shapely.make_valid(shp)
        shapely.prepare(shp)
        normals.append(p.normal)
        offsets.append(p.offset)
        origins.append(o)
        b1s.append(b1)
        b2s.append(b2)
        shapes.append(shp)
        verts.append(np.concatenate([p.outer, *p.holes]) if p.holes else p.outer)
    return _PlanarPolygons(
        np.array(normals), np.array(offsets), np.array(origins), np.array(b1s), np.array(b2s), shapes, verts
    )


def _candidate_box(photo: Photo, verts: np.ndarray, pad: float) -> tuple[int, int, int, int] | None:
    """Image-space box that can contain the polygon, or None if it cannot be in the photo.

    A polygon crossing the camera plane can cover any pixel, so it gets the whole image.
    """
    pix, depth = photo.project(verts)
    if (depth <= 0).all():
        return None
    if (depth <= 0).any():
        return 0, 0, photo.width, photo.height
    x0, y0 = np.floor(pix.min(axis=0) - pad).astype(int)
    x1, y1 = np.ceil(pix.max(axis=0) + pad).astype(int)
    x0, y0 = max(x0, 0), max(y0, 0)
    x1, y1 = min(x1, photo.width), min(y1, photo.height)
    if x0 >= x1 or y0 >= y1:
        return None
    return int(x0), int(y0), int(x1), int(y1)


def _id_buffer_numpy(
    proxy: Proxy | _PlanarPolygons,
    photo: Photo,
    stride: int = 1,
    chunk: int = 1 << 18,
) -> tuple[np.ndarray, np.ndarray]:
    """id_buffer by exact casting in numpy: per polygon, only the pixels of its projected box."""
    import shapely

    pp = proxy if isinstance(proxy, _PlanarPolygons) else _planar(proxy)
    ys, xs = pixel_centres(photo.height, stride), pixel_centres(photo.width, stride)
    H, W = len(ys), len(xs)
    ids = np.full((H, W), NO_POLYGON, dtype=np.int32)
    dist = np.full((H, W), np.inf, dtype=np.float32)
    C = photo.center
    # One ray per pixel, shared by all polygons (unprojecting is the costly part with distortion).
    gx, gy = np.meshgrid(xs, ys)
    all_rays = photo.unproject(np.stack([gx, gy], axis=-1)).astype(np.float32)
    del gx, gy
    # Distortion can bend a straight polygon edge outwards by a few pixels; pad the boxes.
    pad = 0.02 * max(photo.width, photo.height) if not photo.is_pinhole else 2.0
    for j in range(len(pp.shapes)):
        box = _candidate_box(photo, pp.vertices[j], pad)
        if box is None:
            continue
        x0, y0, x1, y1 = box
        c0, c1 = np.searchsorted(xs, x0), np.searchsorted(xs, x1, side="right")
        r0, r1 = np.searchsorted(ys, y0), np.searchsorted(ys, y1, side="right")
        if c0 >= c1 or r0 >= r1:
            continue
        n, d = pp.normals[j].astype(np.float32), pp.offsets[j]
        h_cam = np.float32(d - pp.normals[j] @ C)  # signed distance of the plane from the camera centre
        step = max(1, int(chunk // (c1 - c0)))
        for ra in range(int(r0), int(r1), step):
            rb = min(r1, ra + step)
            rays = all_rays[ra:rb, c0:c1]
            with np.errstate(divide="ignore", invalid="ignore"):
                lam = h_cam / (rays @ n)
            hit = (lam > 0) & np.isfinite(lam) & (lam < dist[ra:rb, c0:c1])
            if not hit.any():
                continue
            hr, hc = np.nonzero(hit)
            lh = lam[hr, hc].astype(np.float64)
            X = C + lh[:, None] * rays[hr, hc].astype(np.float64) - pp.origins[j]
            inside = shapely.contains_xy(pp.shapes[j], X @ pp.b1[j], X @ pp.b2[j])
            hr, hc = hr[inside] + ra, hc[inside] + c0
            ids[hr, hc] = j
            dist[hr, hc] = lh[inside]
    return ids, dist
