"""Photo filtering: drop photos that see nothing, blurry photos, and per polygon extreme inclinations.

Sharpness is the variance of the Laplacian of the grey image at a common size, judged relative
to the set's median so that the threshold does not depend on the camera or the scene.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from math import ceil

import numpy as np

from difftex.camera import Photo
from difftex.config import FilterConfig
from difftex.errors import DifftexError
from difftex.io import decode_photo
from difftex.proxy import Proxy
from difftex.visibility import id_buffer, prepare

log = logging.getLogger(__name__)


def sharpness(image: np.ndarray, long_side: int = 1024) -> float:
    """Variance of the Laplacian of the luminance, after area-downscaling to ``long_side``."""
    from scipy.ndimage import laplace
    from skimage.transform import resize

    grey = image[..., :3] @ np.array([0.299, 0.587, 0.114], dtype=np.float32)
    h, w = grey.shape
    scale = long_side / max(h, w)
    if scale < 1:
        grey = resize(grey, (max(1, round(h * scale)), max(1, round(w * scale))), anti_aliasing=True)
    return float(laplace(grey.astype(np.float64)).var())


@dataclass
class PhotoRecord:
    name: str
    sharpness: float = 0.0
    sharpness_rel: float = 0.0
    polygons: dict | None = None  # polygon id -> {"pixels": int, "angle_deg": float}
    kept: bool = True
    reason: str = ""


def viewing_angles(proxy: Proxy, photo: Photo, ids: np.ndarray, dist: np.ndarray, stride: int, min_pixels: int) -> dict:
    """Per seen polygon: visible pixel count (at analysis size) and the median viewing angle (deg)."""
    out = {}
    ys, xs = np.nonzero(ids >= 0)
    if len(ys) == 0:
        return out
    pix = np.stack([(xs + 0.5) * stride, (ys + 0.5) * stride], axis=-1)
    pix = np.minimum(pix, [photo.width - 0.5, photo.height - 0.5])
    rays = photo.unproject(pix)
    pid = ids[ys, xs]
    for j in np.unique(pid):
        sel = pid == j
        n = proxy.polygons[j].normal
        cos = -(rays[sel] @ n)  # ray points from the camera to the surface
        front = cos > 0
        if front.sum() < min_pixels:
            continue
        angle = np.degrees(np.arccos(np.clip(np.median(cos[front]), -1, 1)))
        out[proxy.polygons[j].id] = {"pixels": int(front.sum()), "angle_deg": round(float(angle), 2)}
    return out


def check_kept(records: list[PhotoRecord], proxy: Proxy, images_dir) -> None:
    """Warn about photos that see no polygon; stop when no photo is left at all.

    A photo that sees nothing is normal (a view of the street); every photo seeing nothing is
    not: the proxy and the photos do not meet (wrong frame or units), and continuing would
    write an all-grey model.
    """
    blind = [r.name for r in records if not r.polygons]
    kept = [r for r in records if r.kept]
    if not kept:
        reasons: dict[str, int] = {}
        for r in records:
            key = r.reason.split(" (")[0]
            reasons[key] = reasons.get(key, 0) + 1
        detail = "; ".join(f"{why}: {n} of {len(records)}" for why, n in sorted(reasons.items(), key=lambda kv: -kv[1]))
        hint = " Is the proxy in the COLMAP model's frame and units?" if len(blind) == len(records) else ""
        raise DifftexError(f"{images_dir}: every photo was filtered out ({detail}); nothing to texture.{hint}")
    if blind:
        shown = ", ".join(blind[:3]) + (", ..." if len(blind) > 3 else "")
        log.warning("%s: %d photo%s no proxy polygon, dropped (%s)", images_dir, len(blind), "s see" if len(blind) > 1 else " sees", shown)


def filter_photos(proxy: Proxy, photos: list[Photo], cfg: FilterConfig, progress: bool = True) -> dict:
    """Decide which photos to keep, globally and per polygon; returns the table as a dict."""
    from rich.progress import track

    t0 = time.perf_counter()
    pp = prepare(proxy)
    records = []
    it = track(photos, description="filtering photos", disable=not progress, transient=True)
    for ph in it:
        # Sharpness is measured at sharpness_long_side: a JPEG decodes straight to about that size.
        reduce = 2 ** int(np.floor(np.log2(max(1.0, max(ph.width, ph.height) / cfg.sharpness_long_side))))
        img = decode_photo(ph.image_path, (ph.width, ph.height), reduce)
        stride = max(1, ceil(max(ph.width, ph.height) / cfg.analysis_long_side))
        ids, dist = id_buffer(pp, ph, stride=stride)
        rec = PhotoRecord(name=ph.name, sharpness=sharpness(img, cfg.sharpness_long_side))
        rec.polygons = viewing_angles(proxy, ph, ids, dist, stride, cfg.min_pixels)
        records.append(rec)
    med = float(np.median([r.sharpness for r in records])) if records else 0.0
    for r in records:
        r.sharpness_rel = r.sharpness / med if med > 0 else 1.0
        if not r.polygons:
            r.kept, r.reason = False, "sees no proxy polygon"
        elif r.sharpness_rel < cfg.blur_ratio:
            r.kept, r.reason = False, f"blurry (sharpness {r.sharpness_rel:.2f} x median < {cfg.blur_ratio})"
    check_kept(records, proxy, photos[0].image_path.parent if photos else None)
    per_polygon = {}
    for poly in proxy.polygons:
        kept, dropped = [], {}
        for r in records:
            seen = (r.polygons or {}).get(poly.id)
            if seen is None:
                continue
            if not r.kept:
                dropped[r.name] = r.reason
            elif seen["angle_deg"] > cfg.max_angle_deg:
                dropped[r.name] = f"inclined ({seen['angle_deg']:.1f} deg > {cfg.max_angle_deg})"
            else:
                kept.append(r.name)
        per_polygon[poly.id] = {"kept": kept, "dropped": dropped}
    unseen = [pid for pid, d in per_polygon.items() if not d["kept"]]
    if len(unseen) == len(per_polygon):
        raise DifftexError(
            f"{proxy.path}: no polygon keeps a photo after filtering (every view is inclined beyond "
            f"filter.max_angle_deg = {cfg.max_angle_deg:g} or dropped); nothing to texture"
        )
    if unseen:
        log.warning(
            "%s: seen by no kept photo, so untextured (grey): %s (%d of %d polygons)",
            proxy.path, ", ".join(unseen), len(unseen), len(per_polygon),
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
    from difftex.io import write_json, write_text

    write_json(json_path, result)
    if csv_path is not None:
        rows = ["photo,kept,reason,sharpness,sharpness_rel,polygons_seen"]
        for r in result["photos"]:
            seen = ";".join(f"{k}:{v['angle_deg']:.1f}deg" for k, v in (r["polygons"] or {}).items())
            reason = r["reason"].replace('"', "'")
            rows.append(f'{r["name"]},{int(r["kept"])},"{reason}",{r["sharpness"]:.6g},{r["sharpness_rel"]:.3f},"{seen}"')
        write_text(csv_path, "\n".join(rows) + "\n")
