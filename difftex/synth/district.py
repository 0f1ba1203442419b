"""A district for scale tests: a street grid of simple buildings, drone and street photos.

``generate_district(out_dir, buildings=N, ...)`` lays N shells of ``difftex.synth.buildings``
(styles box, gable, lshape, tower: 6-11 planar polygons each) on a street grid, places drone
orbits and street-level cameras per building (``cameras.make_views``) and writes a scene in the
project's layout: images/, sparse/0/ (COLMAP text), proxy.obj, synth.json (deterministic) and
synth_timing.json. It measures the pipeline, not texture quality, so there is no ground truth
and the photos are small flat-shaded renders of the proxy itself, ray cast per pixel in numpy
(float64; the same bytes on every CPU): a painted window grid on the walls, stripes on the
roofs, a checker ground, a sun and a sky term, a gain per photo. docs/synth.md (*Districts*) has
why this renderer and not Mitsuba, and what it costs per photo.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from difftex.errors import DifftexError
from difftex.synth.buildings import Building, make_building
from difftex.synth.presets import BuildingSpec

STYLES = ("box", "gable", "lshape", "tower")  # 11, 6, 7, 11 polygons
SUN = np.array([0.45, -0.35, 0.82]) / np.linalg.norm([0.45, -0.35, 0.82])  # towards the sun
SKY = np.array([0.62, 0.72, 0.86])
DRONE_RINGS = ((1.3, 1.5), (1.6, 2.4))  # (distance factor, height factor): looking 20-45 degrees down


@dataclass(frozen=True)
class DistrictConfig:
    """Every parameter of a district; written verbatim into synth.json."""

    buildings: int = 12  # N, laid on a grid of ceil(sqrt N) columns
    views: int = 10  # photos per building
    street_fraction: float = 0.3  # share of street-level photos among them
    width: int = 160
    height: int = 120
    street: float = 24.0  # street width between lots, metres (street cameras stand 7-14 m from a wall)
    exposure_range: float = 0.2  # max |log2 gain| of a photo
    points_per_building: int = 12  # COLMAP points sampled on the walls

    def __post_init__(self) -> None:
        if self.buildings < 1 or self.views < 1:
            raise DifftexError(f"a district needs >= 1 building and >= 1 view per building, got {self.buildings}, "
                               f"{self.views}")
        if min(self.width, self.height) < 16:
            raise DifftexError(f"district photos must be at least 16x16 pixels, got {self.width}x{self.height}")
        if not 0 <= self.street_fraction <= 1 or self.street < 16 or self.exposure_range < 0:
            raise DifftexError("street_fraction must be in [0, 1], street >= 16 m and exposure_range >= 0")

    def replace(self, **changes) -> DistrictConfig:
        names = {f.name for f in dataclasses.fields(self)}
        bad = sorted(set(changes) - names)
        if bad:
            raise DifftexError(f"unknown district setting(s): {', '.join(bad)} (known: {', '.join(sorted(names))})")
        return dataclasses.replace(self, **changes)


def _translate(b: Building, dx: float, dy: float, prefix: str) -> Building:
    """``b`` moved by (dx, dy), its face ids prefixed (``b007_wall02``)."""
    import shapely.affinity

    off = np.array([dx, dy, 0.0])
    for f in b.faces:
        f.outer = f.outer + off
        f.origin = f.origin + off
        f.id = f"{prefix}{f.id}"
    b.footprint = shapely.affinity.translate(b.footprint, dx, dy)
    return b


def layout(cfg: DistrictConfig, seed: int) -> list[Building]:
    """The district's shells on a street grid, each drawn from its own generator.

    Args:
        cfg: the district's settings.
        seed: everything is drawn from it.

    Returns:
        ``cfg.buildings`` buildings, ids ``b000_...``, centred in lots of pitch 34 m + street.
    """
    cols = int(np.ceil(np.sqrt(cfg.buildings)))
    pitch = 34.0 + cfg.street  # the largest footprint is 34 m across
    digits = max(3, len(str(cfg.buildings - 1)))
    out = []
    for i in range(cfg.buildings):
        rng = np.random.default_rng([seed, i, 1])
        style = STYLES[int(rng.integers(len(STYLES)))]
        w, d = float(rng.uniform(14.0, 34.0)), float(rng.uniform(12.0, 26.0))
        h = float(rng.uniform(6.0, 10.0) if style == "tower" else rng.uniform(7.0, 24.0))
        name = f"b{i:0{digits}d}"
        spec = BuildingSpec(name, style, round(w, 2), round(d, 2), round(h, 2), "office")
        b = make_building(spec, rng)
        out.append(_translate(b, (i % cols) * pitch, (i // cols) * pitch, name + "_"))
    return out


@dataclass
class Faces:
    """The proxy as flat arrays for the rasteriser: per polygon its plane frame, ring and colour."""

    ids: list[str]
    rings2d: list[np.ndarray]
    outer: list[np.ndarray]
    origin: np.ndarray  # (P, 3)
    a: np.ndarray
    b: np.ndarray
    normal: np.ndarray
    roof: np.ndarray  # (P,) bool
    eave: np.ndarray  # (P,)
    albedo: np.ndarray  # (P, 3) base colour
    phase: np.ndarray  # (P, 2) window grid offset, metres


def flatten(buildings: list[Building], seed: int) -> Faces:
    """Rasteriser arrays of every face, with a colour per building (walls) and per roof."""
    rows = []
    for i, b in enumerate(buildings):
        rng = np.random.default_rng([seed, i, 2])
        wall = rng.uniform(0.35, 0.75, 3) * np.array([1.0, 0.92, 0.82])
        roof = rng.uniform(0.2, 0.45) * np.array([1.0, 0.8, 0.7]) + rng.uniform(0.0, 0.1, 3)
        for f in b.faces:
            rows.append((f, roof if f.kind == "roof" else wall, rng.uniform(0.0, 3.0, 2)))
    return Faces(
        ids=[f.id for f, _, _ in rows], rings2d=[f.poly2d for f, _, _ in rows], outer=[f.outer for f, _, _ in rows],
        origin=np.array([f.origin for f, _, _ in rows]), a=np.array([f.a for f, _, _ in rows]),
        b=np.array([f.b for f, _, _ in rows]), normal=np.array([f.normal for f, _, _ in rows]),
        roof=np.array([f.kind == "roof" for f, _, _ in rows]), eave=np.array([f.eave for f, _, _ in rows]),
        albedo=np.array([c for _, c, _ in rows]), phase=np.array([p for _, _, p in rows]))


def _inside(uv: np.ndarray, ring: np.ndarray) -> np.ndarray:
    """Even-odd point-in-polygon of (M, 2) points against a ring (n, 2)."""
    x, y = uv[:, 0], uv[:, 1]
    inside = np.zeros(len(uv), bool)
    for (x0, y0), (x1, y1) in zip(ring, np.roll(ring, -1, 0)):
        cross = (y0 > y) != (y1 > y)
        with np.errstate(divide="ignore", invalid="ignore"):
            xs = x0 + (y - y0) * (x1 - x0) / (y1 - y0)
        inside ^= cross & (x < xs)
    return inside


def _candidates(faces: Faces, R, t, f, W, H) -> list[tuple[int, tuple[int, int, int, int]]]:
    """Polygons facing the camera with their pixel bounding boxes (x0, x1, y0, y1) in the image
    (the whole image for one that crosses the camera plane), all polygons projected at once."""
    C = -R.T @ t
    verts = np.concatenate(faces.outer)
    start = np.cumsum([0] + [len(r) for r in faces.outer[:-1]])
    Xc = verts @ R.T + t
    z = Xc[:, 2]
    zs = np.maximum(z, 0.05)
    px, py = f * Xc[:, 0] / zs + W / 2, f * Xc[:, 1] / zs + H / 2
    zmin, zmax = np.minimum.reduceat(z, start), np.maximum.reduceat(z, start)
    crosses = zmin <= 0.05
    x0 = np.where(crosses, 0, np.clip(np.floor(np.minimum.reduceat(px, start)), 0, W)).astype(int)
    x1 = np.where(crosses, W, np.clip(np.ceil(np.maximum.reduceat(px, start)) + 1, 0, W)).astype(int)
    y0 = np.where(crosses, 0, np.clip(np.floor(np.minimum.reduceat(py, start)), 0, H)).astype(int)
    y1 = np.where(crosses, H, np.clip(np.ceil(np.maximum.reduceat(py, start)) + 1, 0, H)).astype(int)
    facing = np.einsum("ij,ij->i", C - faces.origin, faces.normal) > 1e-6
    keep = facing & (zmax > 0.05) & (x0 < x1) & (y0 < y1)
    return [(int(k), (int(x0[k]), int(x1[k]), int(y0[k]), int(y1[k]))) for k in np.nonzero(keep)[0]]


def raycast(faces: Faces, R, t, f: float, W: int, H: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """First polygon hit by each pixel's ray of a pinhole camera (pixel centres).

    Args:
        faces: the proxy (``flatten``).
        R, t: cam_from_world (COLMAP).
        f: focal length in pixels; the principal point is the image centre.
        W, H: image size.

    Returns:
        ids (H, W) int32 polygon index or -1, depth (H, W) camera z (inf where none), and
        uv (H, W, 2) the hit's plane coordinates in its face frame (metres).
    """
    C = -R.T @ t
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float64) + 0.5
    d = np.stack([(xx - W / 2) / f, (yy - H / 2) / f, np.ones_like(xx)], -1) @ R  # world, camera z = 1
    depth = np.full((H, W), np.inf)
    ids = np.full((H, W), -1, np.int32)
    uv = np.zeros((H, W, 2))
    for k, (x0, x1, y0, y1) in _candidates(faces, R, t, f, W, H):
        dd = d[y0:y1, x0:x1].reshape(-1, 3)
        n = faces.normal[k]
        den = dd @ n
        with np.errstate(divide="ignore", invalid="ignore"):
            s = np.where(np.abs(den) > 1e-12, ((faces.origin[k] - C) @ n) / den, np.inf)
        zb = depth[y0:y1, x0:x1].reshape(-1)
        near = (s > 0.05) & (s < zb)
        if not near.any():
            continue
        X = C + s[near, None] * dd[near]
        p = np.stack([(X - faces.origin[k]) @ faces.a[k], (X - faces.origin[k]) @ faces.b[k]], -1)
        inside = _inside(p, faces.rings2d[k])
        hit = np.nonzero(near)[0][inside]
        if len(hit) == 0:
            continue
        rows, cols = y0 + hit // (x1 - x0), x0 + hit % (x1 - x0)
        depth[rows, cols] = s[hit]
        ids[rows, cols] = k
        uv[rows, cols] = p[inside]
    return ids, depth, uv


def shade(faces: Faces, ids, uv, R, t, f: float, gain: float) -> np.ndarray:
    """Linear RGB of a raycast: windows and stripes on the polygons, checker ground, sky.

    Args:
        faces, ids, uv: the proxy and ``raycast``'s hit buffers.
        R, t, f: the camera (for the ground and sky of pixels without a polygon).
        gain: the photo's exposure.

    Returns:
        (H, W, 3) float64 linear radiance times ``gain``.
    """
    H, W = ids.shape
    img = np.empty((H, W, 3))
    hit = ids >= 0
    k = ids[hit]
    u, v = uv[hit, 0] + faces.phase[k, 0], uv[hit, 1]
    alb = faces.albedo[k].copy()
    wall = ~faces.roof[k]
    window = wall & ((u % 3.0) > 0.9) & ((u % 3.0) < 2.2) & ((v % 3.2) > 1.0) & ((v % 3.2) < 2.4) & (
        v < faces.eave[k] - 0.4)
    alb[window] = [0.1, 0.13, 0.18]
    fine = 0.9 + 0.1 * ((np.floor(u / 0.5) + np.floor((v + faces.phase[k, 1]) / 0.5)) % 2)
    alb[~wall] *= (0.85 + 0.15 * (np.floor(u[~wall]) % 2))[:, None]
    light = 0.35 + 0.9 * np.clip(faces.normal[k] @ SUN, 0.0, None)
    img[hit] = alb * (fine * light)[:, None]
    C = -R.T @ t
    yy, xx = np.nonzero(~hit)
    d = np.stack([(xx + 0.5 - W / 2) / f, (yy + 0.5 - H / 2) / f, np.ones(len(xx))], -1) @ R
    down = d[:, 2] < -1e-9
    g = C[:2] + (-C[2] / np.where(down, d[:, 2], -1.0))[:, None] * d[:, :2]
    checker = 0.28 + 0.06 * ((np.floor(g[:, 0] / 4.0) + np.floor(g[:, 1] / 4.0)) % 2)
    ground = checker[:, None] * np.array([1.0, 0.97, 0.9]) * (0.35 + 0.9 * SUN[2])
    img[yy, xx] = np.where(down[:, None], ground, SKY)
    return img * gain


def _srgb8(linear: np.ndarray) -> np.ndarray:
    x = np.clip(linear, 0.0, 1.0)
    s = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    return np.round(s * 255.0) / 255.0


def _points(buildings: list[Building], faces: Faces, n: int, seed: int):
    """``n`` points per building on its walls (on the proxy), with their polygon index."""
    index = {fid: k for k, fid in enumerate(faces.ids)}
    xyz, owner = [], []
    for i, b in enumerate(buildings):
        rng = np.random.default_rng([seed, i, 3])
        walls = b.walls
        for _ in range(n):
            w = walls[int(rng.integers(len(walls)))]
            uv = np.array([[rng.uniform(0.1, 0.9) * w.length, rng.uniform(0.1, 0.9) * w.eave]])
            xyz.append(w.to3d(uv)[0])
            owner.append(index[w.id])
    return np.array(xyz).reshape(-1, 3), np.array(owner, int)


def _observe(X, owner, ids, depth, R, t, f, W, H) -> list[tuple[int, list[float]]]:
    """The points a photo sees: in the image, on the polygon its pixel shows, at its depth."""
    if len(X) == 0:
        return []
    Xc = X @ R.T + t
    z = np.where(Xc[:, 2] > 0.05, Xc[:, 2], np.nan)
    px, py = f * Xc[:, 0] / z + W / 2, f * Xc[:, 1] / z + H / 2
    ok = np.isfinite(px) & (px > 0) & (px < W) & (py > 0) & (py < H)
    out = []
    for p in np.nonzero(ok)[0]:
        c, r = int(px[p]), int(py[p])
        if ids[r, c] == owner[p] and abs(depth[r, c] - Xc[p, 2]) < 0.02 * Xc[p, 2] + 0.05:
            out.append((int(p), [float(px[p]), float(py[p])]))
    return out


def make_views(cfg: DistrictConfig, buildings: list[Building], seed: int) -> list:
    """Per building ``cfg.views`` photos: drone orbits around it and street views at its walls.

    Args:
        cfg: the district's settings.
        buildings: ``layout``'s shells.
        seed: the cameras' and gains' seed.

    Returns:
        ``cameras.View`` list, names ``<building>_<nnnn>.png``, gains drawn per photo.
    """
    from difftex.synth import cameras as cams

    views = []
    for i, b in enumerate(buildings):
        rng = np.random.default_rng([seed, i, 4])
        vs = cams.make_views(b, cfg.views, cfg.street_fraction, rng, prefix=b.name + "_", rings=DRONE_RINGS)
        for v in vs:
            v.gain = float(2.0 ** rng.uniform(-cfg.exposure_range, cfg.exposure_range))
        views += vs
    return views


def generate_district(out_dir: str | Path, cfg: DistrictConfig | None = None, seed: int = 0,
                      progress: bool = False, **overrides) -> dict:
    """Write a district scene (images/, sparse/0/, proxy.obj, synth.json, synth_timing.json).

    Args:
        out_dir: the scene folder (created).
        cfg: settings (default ``DistrictConfig()``); ``overrides`` replace fields of it.
        seed: everything is drawn from it: same seed, same bytes.
        progress: print a line every 500 photos.

    Returns:
        The manifest written as synth.json (timing apart, in synth_timing.json).
    """
    from difftex.scene.files import write_image, write_json
    from difftex.scene.proxy import Polygon, write_proxy_obj
    from difftex.synth import cameras as cams

    cfg = (cfg or DistrictConfig()).replace(**overrides)
    out = Path(out_dir)
    t0 = time.perf_counter()
    buildings = layout(cfg, seed)
    faces = flatten(buildings, seed)
    views = make_views(cfg, buildings, seed)
    intr = [cams.Intrinsics(1, cfg.width, cfg.height, cfg.width / 2 / np.tan(np.deg2rad(65) / 2), 0.0),
            cams.Intrinsics(2, cfg.width, cfg.height, cfg.width / 2 / np.tan(np.deg2rad(75) / 2), 0.0)]
    focal = {c.camera_id: c.f for c in intr}
    X, owner = _points(buildings, faces, cfg.points_per_building, seed)
    t1 = time.perf_counter()
    pixels = np.zeros(len(faces.ids), np.int64)
    photos = np.zeros(len(faces.ids), np.int64)
    obs = {}
    for i, v in enumerate(views):
        f = focal[v.camera_id]
        ids, depth, uv = raycast(faces, v.R, v.t, f, cfg.width, cfg.height)
        write_image(out / "images" / v.name, _srgb8(shade(faces, ids, uv, v.R, v.t, f, v.gain)))
        counts = np.bincount(ids[ids >= 0], minlength=len(faces.ids))
        pixels += counts
        photos += counts > 0
        obs[i] = _observe(X, owner, ids, depth, v.R, v.t, f, cfg.width, cfg.height)
        if progress and (i + 1) % 500 == 0:
            print(f"district: {i + 1}/{len(views)} photos", flush=True)
    t2 = time.perf_counter()
    rgb = (_srgb8(faces.albedo[owner] * 0.8) * 255).round().astype(np.uint8).reshape(-1, 3)
    cams.write_colmap(out / "sparse" / "0", intr, views, (X, rgb, obs) if len(X) else None)
    polygons = [Polygon(id=fid, outer=ring.copy()) for fid, ring in zip(faces.ids, faces.outer)]
    write_proxy_obj(out / "proxy.obj", polygons, header=f"difftex synth district: {len(buildings)} buildings, "
                                                        f"seed {seed}")
    unseen = [fid for fid, n in zip(faces.ids, photos) if n == 0]
    manifest = {
        "generator": "difftex synth district", "seed": int(seed), "config": dataclasses.asdict(cfg),
        "renderer": "numpy flat-shaded ray casting of the proxy (difftex.synth.district), 1 sample per pixel",
        "polygons": len(faces.ids), "photos": len(views), "unseen_polygons": unseen,
        "buildings": [{"name": b.name, "style": b.spec.style, "width": b.spec.width, "depth": b.spec.depth,
                       "height": b.spec.height, "polygons": [f.id for f in b.faces]} for b in buildings],
        "coverage": {fid: {"photos": int(n), "pixels": int(p)} for fid, n, p in zip(faces.ids, photos, pixels)},
        "views": [{"name": v.name, "kind": v.kind, "camera_id": v.camera_id, "gain": v.gain} for v in views],
    }
    write_json(out / "synth.json", manifest)
    write_json(out / "synth_timing.json", {"layout_s": round(t1 - t0, 3), "photos_s": round(t2 - t1, 3),
                                           "per_photo_s": round((t2 - t1) / len(views), 4),
                                           "total_s": round(time.perf_counter() - t0, 3)})
    if unseen:
        import logging

        logging.getLogger(__name__).warning("district: %d polygon(s) seen by no photo: %s", len(unseen),
                                            ", ".join(unseen[:10]))
    return manifest
