"""Photo filtering: drop photos that see nothing, blurry photos, and per polygon extreme inclinations.

Sharpness is the variance of the Laplacian of the grey image at a common size, judged relative
to the set's median so that the threshold does not depend on the camera or the scene.

The per-polygon tests (``max_angle_deg``, ``min_pixels``) never take a polygon's last photos
(paper, Sec. 4.3: improper photo removal causes irreversible colour loss). A polygon that every
sharp photo sees beyond ``max_angle_deg`` keeps all of those oblique photos (``textured_from_oblique``);
one that no photo sees with ``min_pixels`` pixels keeps the sharp photos in which some of it is
visible at all (``textured_from_glimpses``). Only a polygon that no sharp photo sees stays
untextured, and the table says why (:func:`unseen_reason`).
"""

from __future__ import annotations

import logging
import time
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from math import ceil

import numpy as np

from difftex.config import FilterConfig, job_threads
from difftex.errors import DifftexError
from difftex.geometry.raycast import ProxyCaster, camera_rays
from difftex.geometry.visibility import id_buffer, prepare
from difftex.scene.camera import Photo
from difftex.scene.files import decode_photo
from difftex.scene.proxy import Proxy

log = logging.getLogger(__name__)


_LUMA = np.array([0.299, 0.587, 0.114], dtype=np.float32)


def luminance(image: np.ndarray) -> np.ndarray:
    """Rec. 601 luma in [0, 1], float32 (h, w), of an RGB(A) image as floats in [0, 1] or as its
    stored 8/16-bit values (``decode_photo(..., as_stored=True)``).

    Integer channels are converted one at a time: a float copy of the whole photo, made only to
    be reduced to one channel, was most of the filter's time (fresh pages for every photo).
    """
    top = {np.dtype(np.uint8): 255.0, np.dtype(np.uint16): 65535.0}.get(image.dtype)
    if top is None:
        return image[..., :3] @ _LUMA
    grey = image[..., 0].astype(np.float32)
    grey *= _LUMA[0]
    for c in (1, 2):
        part = image[..., c].astype(np.float32)
        part *= _LUMA[c]
        grey += part
    grey *= np.float32(1.0 / top)
    return grey


def sharpness(image: np.ndarray, long_side: int = 1024) -> float:
    """Variance of the Laplacian of the luminance, after area-downscaling to ``long_side``.

    ``image``: RGB(A) as floats in [0, 1], or as its stored 8/16-bit values.
    """
    grey = luminance(image)
    h, w = grey.shape
    scale = long_side / max(h, w)
    if scale < 1:
        from skimage.transform import resize  # imported only here: 0.3 s that photos at that size never need

        grey = resize(grey, (max(1, round(h * scale)), max(1, round(w * scale))), anti_aliasing=True)
    # scipy.ndimage.laplace (kernel [1, -2, 1] per axis, mode "reflect" = numpy's "symmetric")
    # from slices: the same values, four times faster than its two correlate1d passes
    # in float32 (the image's precision; half the memory traffic), the variance summed in float64
    # (summed in place, in the same order: the same values with two temporaries instead of five)
    grey = grey.astype(np.float32, copy=False)
    p = np.pad(grey, 1, mode="symmetric")
    lap = p[:-2, 1:-1] + p[2:, 1:-1]
    lap += p[1:-1, :-2]
    lap += p[1:-1, 2:]
    lap -= 4.0 * grey
    return float(lap.var(dtype=np.float64))


@dataclass
class PhotoRecord:
    name: str
    sharpness: float = 0.0
    sharpness_rel: float = 0.0
    polygons: dict | None = None  # polygon id -> {"pixels": int, "angle_deg": float}
    kept: bool = True
    reason: str = ""
    # when it sees no polygon with min_pixels pixels: the most pixels it sees of one (0: none at all)
    largest_view: int = 0


def viewing_angles(proxy: Proxy, photo: Photo, ids: np.ndarray, dist: np.ndarray, stride: int, min_pixels: int) -> dict:
    """Per seen polygon: visible pixel count (at analysis size) and the median viewing angle (deg)."""
    out: dict = {}
    flat = np.flatnonzero(ids >= 0)
    if flat.size == 0:
        return out
    # the rays of the id buffer's grid (memoised per camera), not an unprojection per pixel; the
    # normals are turned into the camera frame (P rotations), not every pixel's ray into the world
    # (a (N, 3) @ (3, 3) product per photo, most of this function's time)
    pid = ids.ravel()[flat]
    normals = np.array([p.normal for p in proxy.polygons], np.float32) @ photo.R.astype(np.float32).T
    rays = camera_rays(photo, stride).reshape(-1, 3)[flat]
    cos = -np.einsum("ij,ij->i", rays, normals[pid])  # rays point at the surface
    # per polygon, its front-facing pixels in one sort: counts from a bincount (not np.unique, a
    # second sort), and 16-bit keys, which numpy's stable sort orders by radix, in linear time
    front = cos > 0
    pid, cos = pid[front], cos[front]
    counts = np.bincount(pid, minlength=len(proxy.polygons))
    cos = cos[np.argsort(pid.astype(np.int16) if len(proxy.polygons) < 2**15 else pid, kind="stable")]
    starts = np.cumsum(counts) - counts
    for j in np.flatnonzero(counts >= max(min_pixels, 1)):
        a, n = starts[j], counts[j]
        angle = np.degrees(np.arccos(np.clip(np.median(cos[a : a + n]), -1, 1)))
        out[proxy.polygons[j].id] = {"pixels": int(n), "angle_deg": round(float(angle), 2)}
    return out


def _names(names: list[str]) -> str:
    return ", ".join(names[:3]) + (", ..." if len(names) > 3 else "")


def check_kept(records: list[PhotoRecord], cfg: FilterConfig, images_dir) -> None:
    """Stop when no photo is left at all, saying which test dropped them and what to change.

    A photo that sees nothing is normal (a view of the street); every photo seeing nothing is
    not: the proxy and the photos do not meet (wrong frame or units), and continuing would
    write an all-grey model. Photos that do see the proxy, but none of its polygons with
    ``filter.min_pixels`` pixels, point at that setting instead.
    """
    if any(r.kept for r in records):
        return
    reasons: dict[str, int] = {}
    for r in records:
        key = r.reason.split(" (")[0]
        reasons[key] = reasons.get(key, 0) + 1
    detail = "; ".join(f"{why}: {n} of {len(records)}" for why, n in sorted(reasons.items(), key=lambda kv: -kv[1]))
    largest = max((r.largest_view for r in records if not r.polygons), default=0)
    hint = ""
    if all(not r.polygons for r in records):
        if largest == 0:
            hint = " Is the proxy in the COLMAP model's frame and units?"
        else:
            hint = (
                f" The photos see at most {largest} pixels of a polygon at the filter's analysis size "
                f"(filter.analysis_long_side = {cfg.analysis_long_side}): set filter.min_pixels to {largest} "
                "or less."
            )
    raise DifftexError(f"{images_dir}: every photo was filtered out ({detail}); nothing to texture.{hint}")


def warn_dropped(records: list[PhotoRecord], cfg: FilterConfig, images_dir) -> None:
    """One warning line per reason for the photos that stay dropped: seeing no polygon at all,
    none with ``min_pixels`` pixels, or blurry (photos.csv has every photo's reason)."""
    dropped = [r for r in records if not r.kept]
    blind = [r.name for r in dropped if not r.polygons and r.largest_view == 0]
    small = [r for r in dropped if not r.polygons and r.largest_view > 0]
    blurry = [r for r in dropped if _blurry(r)]
    if blind:
        log.warning(
            "%s: %d photo%s no proxy polygon, dropped (%s)",
            images_dir,
            len(blind),
            "s see" if len(blind) > 1 else " sees",
            _names(blind),
        )
    if small:
        log.warning(
            "%s: %d photo%s no polygon with filter.min_pixels = %d pixels (at most %d), dropped (%s)",
            images_dir,
            len(small),
            "s see" if len(small) > 1 else " sees",
            cfg.min_pixels,
            max(r.largest_view for r in small),
            _names([r.name for r in small]),
        )
    if blurry:
        blurry.sort(key=lambda r: r.sharpness_rel)
        log.warning(
            "%s: %d photo%s dropped as blurry (sharpness below filter.blur_ratio = %g x the median): %s",
            images_dir,
            len(blurry),
            "s" if len(blurry) > 1 else "",
            cfg.blur_ratio,
            _names([f"{r.name} ({r.sharpness_rel:.2g})" for r in blurry]),
        )


def _blurry(r: PhotoRecord) -> bool:
    return not r.kept and r.reason.startswith("blurry")


def _join(a: str, b: str) -> str:
    return f"{a}; {b}" if a else b


def polygon_photos(pid: str, records: list[PhotoRecord], cfg: FilterConfig) -> dict:
    """The photos one polygon keeps, and those it drops with the reason.

    Photos that see it within ``max_angle_deg`` are kept. When there are none, every sharp
    photo that sees it is kept, however oblique: all of them rather than the least oblique few,
    because oblique views of one polygon usually see different parts of it (a side wall from
    either end), and the texturing's quality weights (Q_a, L_Persp) already prefer, per texel,
    the least oblique photo that sees it -- a choice per polygon here could only lose texels.

    Returns:
        {"kept": [names], "dropped": {name: reason}, "inclined": {name: angle} (dropped as
        inclined; the visibility stage takes one back for texels no kept photo sees),
        "textured_from_oblique": bool, and when true "oblique_angles": {name: angle}, least oblique first}.
    """
    kept, dropped, inclined = [], {}, {}
    for r in records:
        seen = (r.polygons or {}).get(pid)
        if seen is None:
            continue
        if not r.kept:
            dropped[r.name] = r.reason
        elif seen["angle_deg"] > cfg.max_angle_deg:
            dropped[r.name] = f"inclined ({seen['angle_deg']:.1f} deg > {cfg.max_angle_deg})"
            inclined[r.name] = seen["angle_deg"]
        else:
            kept.append(r.name)
    out = {"kept": kept, "dropped": dropped, "inclined": inclined, "textured_from_oblique": False}
    if not kept and inclined:
        out.update(
            kept=sorted(inclined),
            dropped={n: w for n, w in dropped.items() if n not in inclined},
            inclined={},
            textured_from_oblique=True,
            oblique_angles=dict(sorted(inclined.items(), key=lambda kv: kv[1])),
        )
    return out


def polygon_points(poly, long_side: int = 32) -> np.ndarray:
    """(N, 3) points spread over a polygon: its texel centres at ``long_side`` and its centroid."""
    from difftex.geometry.frames import texel_mask, uv_frame

    frame = uv_frame(poly, np.array([0.0, 0.0, 1.0]), long_side=long_side)
    ty, tx = np.nonzero(texel_mask(poly, frame))
    return np.concatenate([frame.texel_to_world(tx + 0.5, ty + 0.5), poly.centroid[None]])


def sight_line(caster: ProxyCaster, index: int, photo: Photo, points: np.ndarray) -> dict:
    """How ``photo`` sees polygon ``index``, from ``points`` on it (:func:`polygon_points`)
    rather than from the photo's pixels, so that a polygon too small for the filter's analysis
    size is still found.

    Returns:
        {"state": "back-facing" (the camera is behind its plane) | "outside" (no point of it in
        the image) | "hidden" (every point in the image is behind another polygon) | "visible",
        "points": visible points, "angle_deg": median viewing angle of those (visible only)}.
    """
    poly = caster.proxy.polygons[index]
    if float(poly.normal @ (photo.center - poly.centroid)) <= 0:
        return {"state": "back-facing", "points": 0}
    pix, depth = photo.project(points)
    inside = (depth > 0) & photo.in_image(pix)
    if not inside.any():
        return {"state": "outside", "points": 0}
    rays = points[inside] - photo.center
    dist = np.linalg.norm(rays, axis=1)
    ids, _ = caster.cast(photo.center, rays / dist[:, None])
    seen = ids == index  # a ray meets the polygon's plane once: a hit on it is a hit at the point
    if not seen.any():
        return {"state": "hidden", "points": 0}
    cos = -(rays[seen] / dist[seen, None]) @ poly.normal
    return {
        "state": "visible",
        "points": int(seen.sum()),
        "angle_deg": round(float(np.degrees(np.arccos(np.clip(np.median(cos), -1, 1)))), 2),
    }


def unseen_reason(sight: dict[str, dict], blurry: list[str]) -> str:
    """Why no photo textures a polygon, from :func:`sight_line` of every photo.

    ``blurry``: photos in which it is visible but that were dropped as blurry.
    """
    n = len(sight)
    count = {state: sum(s["state"] == state for s in sight.values()) for state in ("back-facing", "outside", "hidden")}
    if blurry:
        return (
            "every photo that sees it was dropped as blurry "
            f"({', '.join(blurry[:3])}{', ...' if len(blurry) > 3 else ''})"
        )
    if count["hidden"]:
        return f"hidden behind other polygons in the {count['hidden']} photo(s) that have it in view"
    if count["outside"]:
        return f"outside every photo (in front of {count['outside']} of {n} cameras, in none of their images)"
    return f"back-facing to every camera (all {n})"


def photo_records(proxy: Proxy, photos: list[Photo], cfg: FilterConfig, progress: bool = True) -> list[PhotoRecord]:
    """Each photo's own tests: its sharpness, and the polygons it sees with their pixel counts and
    viewing angles (an id buffer at ``cfg.analysis_long_side`` against the whole proxy). Nothing
    here depends on the other photos, so a large scene's photos are measured in chunks by
    separate jobs and :func:`decide_photos` merges them.

    Args:
        proxy: the whole proxy (every polygon may hide another).
        photos: the photos to measure (all of the scene's, or one chunk).
    Returns:
        One PhotoRecord per photo, in order, with ``kept`` and ``reason`` still undecided.
    """
    from rich.progress import track

    pp = prepare(proxy)
    records = []

    def photo_sharpness(ph: Photo) -> float:
        # Sharpness is measured at sharpness_long_side: a JPEG decodes straight to about that size.
        reduce = 2 ** int(np.floor(np.log2(max(1.0, max(ph.width, ph.height) / cfg.sharpness_long_side))))
        image = decode_photo(ph.image_path, (ph.width, ph.height), reduce, as_stored=True)
        return sharpness(image, cfg.sharpness_long_side)

    def photo_record(ph: Photo) -> PhotoRecord:
        stride = max(1, ceil(max(ph.width, ph.height) / cfg.analysis_long_side))
        ids, dist = id_buffer(pp, ph, stride=stride)
        rec = PhotoRecord(name=ph.name)
        rec.polygons = viewing_angles(proxy, ph, ids, dist, stride, cfg.min_pixels)
        if not rec.polygons and cfg.min_pixels > 1:  # below min_pixels, or nothing at all?
            rec.largest_view = max(
                (v["pixels"] for v in viewing_angles(proxy, ph, ids, dist, stride, 1).values()), default=0
            )
        return rec

    # Decoding, sharpness and id buffers run ahead in worker threads, one per thread of the job
    # (OMP_NUM_THREADS, as the workflow sets it): image codecs and numpy's rasterising release
    # the GIL, and the photos that must be ray-cast take the caster's lock one at a time.
    workers = job_threads()
    with ThreadPoolExecutor(max_workers=workers) as pool:
        sharp = deque(pool.submit(photo_sharpness, ph) for ph in photos[:workers])
        ahead = deque(pool.submit(photo_record, ph) for ph in photos[:workers])
        it = track(range(len(photos)), description="filtering photos", disable=not progress, transient=True)
        for i in it:
            if i + workers < len(photos):
                sharp.append(pool.submit(photo_sharpness, photos[i + workers]))
                ahead.append(pool.submit(photo_record, photos[i + workers]))
            rec = ahead.popleft().result()
            rec.sharpness = sharp.popleft().result()  # a decode error surfaces here, in photo order
            records.append(rec)
    return records


def record_from_dict(d: dict) -> PhotoRecord:
    """A PhotoRecord from its JSON form (``PhotoRecord.__dict__``, as a chunk's job writes it)."""
    try:
        return PhotoRecord(**d)
    except TypeError as exc:
        raise DifftexError(f"not a difftex photo record ({exc})") from None


def filter_photos(proxy: Proxy, photos: list[Photo], cfg: FilterConfig, progress: bool = True) -> dict:
    """Decide which photos to keep, globally and per polygon; returns the table as a dict."""
    t0 = time.perf_counter()
    records = photo_records(proxy, photos, cfg, progress)
    result = decide_photos(proxy, photos, records, cfg)
    result["seconds"] = round(time.perf_counter() - t0, 3)
    return result


def decide_photos(proxy: Proxy, photos: list[Photo], records: list[PhotoRecord], cfg: FilterConfig) -> dict:
    """The filter's decisions from every photo's record (:func:`photo_records`): blur relative
    to the set's median, per polygon the kept photos (:func:`polygon_photos`), and for polygons
    no kept photo sees, the glimpses found by casting rays at the polygon itself (the cameras
    only: no photo is decoded here).

    Args:
        photos: every photo of the scene, in the records' order.
        records: one per photo.
    Returns:
        The filter table (``write_table``); its ``seconds`` are the decisions' own.
    """
    if [r.name for r in records] != [ph.name for ph in photos]:
        raise DifftexError("the photo records do not match the scene's photos (a stale chunk of the filter stage?)")
    t0 = time.perf_counter()
    pp = None  # the caster, built for the first polygon that needs its glimpses (most scenes: none)
    med = float(np.median([r.sharpness for r in records])) if records else 0.0
    for r in records:
        r.sharpness_rel = r.sharpness / med if med > 0 else 1.0
        if not r.polygons and r.largest_view > 0:
            r.kept, r.reason = False, (
                f"sees no polygon with filter.min_pixels = {cfg.min_pixels} pixels (at most {r.largest_view})"
            )
        elif not r.polygons:
            r.kept, r.reason = False, "sees no proxy polygon"
        elif r.sharpness_rel < cfg.blur_ratio:
            r.kept, r.reason = False, f"blurry (sharpness {r.sharpness_rel:.2f} x median < {cfg.blur_ratio})"
    images_dir = photos[0].image_path.parent if photos else None
    check_kept(records, cfg, images_dir)
    per_polygon = {poly.id: polygon_photos(poly.id, records, cfg) for poly in proxy.polygons}
    by_name = {r.name: r for r in records}
    for i, poly in enumerate(proxy.polygons):
        d = per_polygon[poly.id]
        if d["kept"]:
            continue
        # no sharp photo sees it with min_pixels pixels: look at the polygon itself in every photo
        points = polygon_points(poly)
        pp = pp or prepare(proxy)
        sight = {ph.name: sight_line(pp, i, ph, points) for ph in photos}
        usable = {n: s for n, s in sight.items() if s["state"] == "visible" and not _blurry(by_name[n])}
        if usable:
            d["kept"] = sorted(usable)
            d["textured_from_glimpses"] = True
            d["glimpses"] = {n: {"points": s["points"], "angle_deg": s["angle_deg"]} for n, s in sorted(usable.items())}
            for n in usable:
                r = by_name[n]
                if not r.kept:  # it saw no polygon with min_pixels pixels: kept for this one
                    r.kept, r.reason = True, ""
                r.reason = _join(r.reason, f"kept for {poly.id}, which no other photo sees")
        else:
            blurry = sorted(n for n, s in sight.items() if s["state"] == "visible")
            d["untextured_reason"] = unseen_reason(sight, blurry)
            d["sight"] = {
                state: sum(s["state"] == state for s in sight.values())
                for state in ("back-facing", "outside", "hidden", "visible")
            }
    warn_dropped(records, cfg, images_dir)  # after the glimpses, which may take a photo back
    oblique = {pid: d for pid, d in per_polygon.items() if d["textured_from_oblique"]}
    if oblique:
        log.warning(
            "%s: textured from oblique photos only (every photo sees them beyond filter.max_angle_deg = %g): %s",
            proxy.path,
            cfg.max_angle_deg,
            ", ".join(f"{pid} ({min(d['oblique_angles'].values()):.0f} deg)" for pid, d in oblique.items()),
        )
    unseen = {pid: d["untextured_reason"] for pid, d in per_polygon.items() if not d["kept"]}
    if unseen:
        log.warning(
            "%s: no photo sees %d of %d polygons, untextured (grey): %s",
            proxy.path,
            len(unseen),
            len(per_polygon),
            "; ".join(f"{pid} ({why})" for pid, why in unseen.items()),
        )
    return {
        "config": cfg.__dict__,
        "median_sharpness": med,
        "photos": [r.__dict__ for r in records],
        "polygons": per_polygon,
        "seconds": round(time.perf_counter() - t0, 3),
    }


def write_table(result: dict, json_path, csv_path=None) -> None:
    """The filter table as JSON (complete) and CSV (one row per photo, for a spreadsheet)."""
    from difftex.scene.files import write_json, write_text

    write_json(json_path, result)
    if csv_path is not None:
        rows = ["photo,kept,reason,sharpness,sharpness_rel,polygons_seen,candidate_for"]
        used: dict[str, list[str]] = {}
        for pid, d in result["polygons"].items():
            for name in d["kept"]:
                used.setdefault(name, []).append(pid)
        for r in result["photos"]:
            seen = ";".join(f"{k}:{v['angle_deg']:.1f}deg" for k, v in (r["polygons"] or {}).items())
            reason = r["reason"].replace('"', "'")
            rows.append(
                f'{r["name"]},{int(r["kept"])},"{reason}",{r["sharpness"]:.6g},{r["sharpness_rel"]:.3f},"{seen}",'
                f'"{";".join(used.get(r["name"], []))}"'
            )
        write_text(csv_path, "\n".join(rows) + "\n")
