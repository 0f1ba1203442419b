"""Visibility of proxy polygons in photos: a per-photo polygon-id buffer, texel masks, a_k^i.

The id buffer is made by casting each pixel's ray, through the camera's distortion model,
against the proxy and keeping the nearest hit (difftex.geometry.raycast). A rasteriser's straight edges
could not follow COLMAP's distortion models.

From the id buffer, for polygon i and photo k:
- a_k^i (photo space): pixels whose nearest proxy surface is polygon i, seen from its front;
- texel visibility: texel centre in front of the camera, inside the image, front-facing, and
  its pixel in the id buffer belongs to polygon i (so it is not hidden by another polygon).
"""

from __future__ import annotations

import dataclasses
import math
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from difftex.config import TextureConfig
from difftex.errors import DifftexError
from difftex.geometry.frames import UVFrame, texel_footprint, texel_homography, texel_mask, texel_to_pixel, uv_frame
from difftex.geometry.raycast import NO_POLYGON, ProxyCaster, id_buffer, prepare  # noqa: F401  (id_buffer, prepare: re-exported)
from difftex.scene.camera import Photo
from difftex.scene.proxy import Proxy


@dataclass(frozen=True, eq=False)
class PolygonVisibility:
    """Which texels of one polygon each candidate photo sees, and where (a_k^i) in the photo."""

    polygon_id: str
    frame: UVFrame
    texel_mask: np.ndarray  # (H, W) bool
    photos: list[str]  # candidate photo names, K of them
    texel_visible: np.ndarray  # (K, H, W) bool
    a_bbox: np.ndarray  # (K, 4) int: x0, y0, x1, y1 (exclusive) of a_k^i in photo pixels
    a_masks: list[np.ndarray]  # K crops (y1-y0, x1-x0) bool of a_k^i
    texel_size: dict | None = None  # difftex.geometry.density.TexelSize as a dict: how the texel size was chosen
    rescued: dict | None = None  # photos kept only as the last source of some texels: name -> {"texels", "why"}

    def a_mask_full(self, k: int, width: int, height: int) -> np.ndarray:
        m = np.zeros((height, width), bool)
        x0, y0, x1, y1 = self.a_bbox[k]
        m[y0:y1, x0:x1] = self.a_masks[k]
        return m

    @property
    def coverage(self) -> float:
        """Share of the polygon's texels seen by at least one candidate photo."""
        if not self.texel_mask.any():
            return 0.0
        seen = self.texel_visible.any(axis=0) if len(self.photos) else np.zeros_like(self.texel_mask)
        return float((seen & self.texel_mask).sum() / self.texel_mask.sum())


def save_visibility(path, vis: PolygonVisibility) -> None:
    """Compressed npz; boolean masks are bit-packed (a 2048^2 mask is 512 KiB before zlib)."""
    import json

    from difftex.scene.files import write_npz

    H, W = vis.frame.shape
    sizes = np.array([m.size for m in vis.a_masks], dtype=np.int64)
    a_flat = np.concatenate([m.ravel() for m in vis.a_masks]) if vis.a_masks else np.zeros(0, bool)
    write_npz(
        path,
        polygon_id=np.array(vis.polygon_id),
        frame=np.array(json.dumps(vis.frame.to_dict())),
        texel_mask=np.packbits(vis.texel_mask.ravel()),
        photos=np.array(vis.photos, dtype=str),
        texel_visible=np.packbits(vis.texel_visible.reshape(len(vis.photos), H * W), axis=1),
        a_bbox=vis.a_bbox,
        a_sizes=sizes,
        a_masks=np.packbits(a_flat),
        shape=np.array([H, W]),
        texel_size=np.array(json.dumps(vis.texel_size)),
    )


def load_visibility(path) -> PolygonVisibility:
    import json

    from difftex.scene.files import read_npz

    d = read_npz(path)
    try:
        H, W = (int(x) for x in d["shape"])
        frame = UVFrame.from_dict(json.loads(str(d["frame"])))
        photos = [str(x) for x in d["photos"]]
        K = len(photos)
        tv = (
            np.unpackbits(d["texel_visible"], axis=1, count=H * W).astype(bool).reshape(K, H, W)
            if K
            else np.zeros((0, H, W), bool)
        )
        flat = np.unpackbits(d["a_masks"], count=int(d["a_sizes"].sum())).astype(bool)
        crops, pos = [], 0
        for k in range(K):
            x0, y0, x1, y1 = (int(v) for v in d["a_bbox"][k])
            n = (y1 - y0) * (x1 - x0)
            crops.append(flat[pos : pos + n].reshape(y1 - y0, x1 - x0))
            pos += n
        return PolygonVisibility(
            polygon_id=str(d["polygon_id"]),
            frame=frame,
            texel_mask=np.unpackbits(d["texel_mask"], count=H * W).astype(bool).reshape(H, W),
            photos=photos,
            texel_visible=tv,
            a_bbox=d["a_bbox"].astype(np.int64).reshape(K, 4),
            a_masks=crops,
            texel_size=json.loads(str(d["texel_size"])) if "texel_size" in d else None,
        )
    except (KeyError, ValueError) as exc:
        raise DifftexError(f"{path}: not a difftex visibility file ({exc})") from None


def crop_texel_visibility(frame: UVFrame, photo: Photo, mask: np.ndarray, bbox, crop: np.ndarray) -> np.ndarray:
    """(H, W) bool: texels of ``mask`` whose centre projects onto a pixel of the crop of a_k^i.

    Args:
        bbox: (x0, y0, x1, y1) of ``crop`` in full-resolution pixels.
        crop: (y1 - y0, x1 - x0) bool, the pixels whose nearest proxy surface is the polygon.
    """
    bbox = tuple(int(v) for v in bbox)
    x0, y0, x1, y1 = bbox
    if x1 <= x0 or y1 <= y0:
        return np.zeros(frame.shape, bool)
    if photo.is_pinhole:
        return _crop_texel_visibility_pinhole(frame, photo, mask, bbox, crop)
    return _crop_texel_visibility_projected(frame, photo, mask, bbox, crop)


def _on_crop(u: np.ndarray, v: np.ndarray, ok: np.ndarray, bbox, crop: np.ndarray) -> np.ndarray:
    """Which of the pixel positions (u, v) valid where ``ok`` fall on a True pixel of ``crop``
    (whose box is ``bbox``); the same shape as ``u``."""
    x0, y0, x1, y1 = bbox
    w, h = x1 - x0, y1 - y0
    # exact flat indices past 2^24 pixels; a pixel's column floor(u) is compared with the box's
    # integer edges directly (NaN and inf compare False, so invalid positions need no masking)
    ix, iy = np.floor(np.asarray(u, np.float64)), np.floor(np.asarray(v, np.float64))
    inside = ok & (ix >= x0) & (ix < x1) & (iy >= y0) & (iy < y1)
    with np.errstate(invalid="ignore", over="ignore"):  # the invalid positions' values are not used
        ix -= x0
        iy -= y0
        iy *= w
        iy += ix  # the flat index into the crop (integral, exact in float64)
    # one gather of every position, those outside reading a False past the crop's end: the
    # boolean-mask selections it replaces were most of a polygon's visibility at full density
    at = np.where(inside, iy, h * w).astype(np.int64)
    return np.append(crop.ravel(), False)[at]


def _texel_span_of_box(H: np.ndarray, bbox, rows: tuple[int, int], cols: tuple[int, int]) -> tuple[int, int, int, int]:
    """The rows and columns (r0, r1, c0, c1) of ``rows`` x ``cols`` whose texel centres can project
    into the pixel box ``bbox`` through the texel homography ``H``: the box's corners mapped back
    onto the plane, with a texel of margin for rounding. A photo that sees part of a polygon then
    projects only that part's texels. Where a corner's ray does not meet the plane in front of the
    camera the pixel box's preimage is unbounded, and the span is the whole of rows x cols.

    Args:
        H: (3, 3) texel homography (``frames.texel_homography``).
        bbox: (x0, y0, x1, y1) pixel box, half-open.
        rows, cols: (start, stop) of the texel rows and columns to restrict.

    Returns:
        (r0, r1, c0, c1) within rows x cols (r1 == r0 or c1 == c0 when no texel can reach the box).
    """
    x0, y0, x1, y1 = bbox
    try:
        Hinv = np.linalg.inv(H)
    except np.linalg.LinAlgError:  # the camera centre on the polygon's plane: no bound from it
        return (*rows, *cols)
    q = Hinv @ np.array([[x0, x1, x0, x1], [y0, y0, y1, y1], [1.0, 1.0, 1.0, 1.0]])
    if not (q[2] > 1e-12 * np.abs(q[:2]).max(0)).all():
        return (*rows, *cols)
    t = q[:2] / q[2]  # the corners' texel coordinates (x, y); centres sit at index + 0.5
    c0 = max(cols[0], math.floor(t[0].min() - 0.5) - 1)
    c1 = min(cols[1], math.ceil(t[0].max() - 0.5) + 2)
    r0 = max(rows[0], math.floor(t[1].min() - 0.5) - 1)
    r1 = min(rows[1], math.ceil(t[1].max() - 0.5) + 2)
    return r0, max(r0, r1), c0, max(c0, c1)


def _crop_texel_visibility_projected(
    frame: UVFrame, photo: Photo, mask: np.ndarray, bbox, crop: np.ndarray
) -> np.ndarray:
    """crop_texel_visibility for any camera model: each texel centre of the mask through f_k^i."""
    seen = np.zeros(frame.shape, bool)
    ty, tx = np.nonzero(mask)
    pix, depth = texel_to_pixel(frame, photo, tx + 0.5, ty + 0.5)
    hit = _on_crop(pix[:, 0], pix[:, 1], (depth > 1e-9) & photo.in_image(pix), bbox, crop)
    seen[ty[hit], tx[hit]] = True
    return seen


def _crop_texel_visibility_pinhole(
    frame: UVFrame, photo: Photo, mask: np.ndarray, bbox, crop: np.ndarray
) -> np.ndarray:
    """crop_texel_visibility for a pinhole photo: the homography evaluated by broadcasting on the
    grid of the mask's bounding rows and columns that can reach the crop's box (the same float64
    operations as texel_to_pixel, so the same pixels), instead of on gathered texel lists: 6x
    faster on archive's photos (tests/test_visibility.py compares it with the projected path). A
    texel centre inside the crop's box is inside the image."""
    seen = np.zeros(frame.shape, bool)
    rows, cols = np.flatnonzero(mask.any(1)), np.flatnonzero(mask.any(0))
    if rows.size == 0:
        return seen
    H = texel_homography(frame, photo)
    r0, r1, c0, c1 = _texel_span_of_box(H, bbox, (int(rows[0]), int(rows[-1]) + 1), (int(cols[0]), int(cols[-1]) + 1))
    if r1 == r0 or c1 == c0:
        return seen
    tx = np.arange(c0, c1, dtype=np.float64)[None, :] + 0.5
    ty = np.arange(r0, r1, dtype=np.float64)[:, None] + 0.5
    depth = H[2, 0] * tx + H[2, 1] * ty + H[2, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / depth
        u = (H[0, 0] * tx + H[0, 1] * ty + H[0, 2]) * inv
        v = (H[1, 0] * tx + H[1, 1] * ty + H[1, 2]) * inv
    ok = (depth > 1e-9) & mask[r0:r1, c0:c1] & np.isfinite(u) & np.isfinite(v)
    seen[r0:r1, c0:c1] = _on_crop(u, v, ok, bbox, crop)
    return seen


@dataclass
class _Sighting:
    """What one photo's id buffer says of one polygon (kept until the texel sizes are chosen)."""

    name: str
    bbox: tuple[int, int, int, int]
    crop: np.ndarray  # packed bits of the (y1 - y0, x1 - x0) a_k^i crop
    mean_cos: float
    gsd: np.ndarray | None  # (h, w) at the probe frame (auto density)
    cos: np.ndarray | None


def scene_visibility(
    proxy: Proxy,
    photos: list[Photo],
    up: np.ndarray,
    candidates: dict[str, list[str]],
    texture: TextureConfig | int,
    min_texels: int = 16,
    max_photos: int | None = None,
    progress: bool = True,
    top_k: int = 8,
    fallback: dict[str, dict[str, str]] | None = None,
    texel_candidates: int | None = None,
    threads: int = 1,
    only: list[int] | None = None,
) -> list[PolygonVisibility]:
    """Visibility of every polygon in its candidate photos (photo names per polygon id).

    A photo that sees fewer than ``min_texels`` texels, and one of ``fallback`` (per polygon id:
    photo name -> why the filter left it out, e.g. inclined), joins only where it is the last
    source of some texels: dropping it there would lose their colour for good (paper, Sec. 4.3),
    and the texturing's quality weights and photo drop keep it out of the texels that other
    photos see. ``PolygonVisibility.rescued`` lists those photos. ``texel_candidates``: a
    photo stays a candidate only where it is among that many best of some texel
    (:func:`best_per_texel`), or the last source of some. ``max_photos`` (best Q_a first) is a
    cap the user set, applied last.

    One pass over the photos: each photo's id buffer gives, per polygon it sees, the crop of
    a_k^i and (``density: auto``) the photo's ground sampling distance on a probe grid. Then each
    polygon's texel size is chosen (difftex.geometry.density), and its texel visibility per photo
    is read from the crops. With ``threads`` > 1, the polygons are read side by side, and so are
    the photos when all are pinhole (rasterised; numpy releases the GIL in the array work); one
    full-resolution id buffer per thread is in memory at a time.

    ``texture``: the texture section, or an int long side (tests and tools). ``only``: indices
    of the polygons to compute (a spatial tile of a large scene; the others still occlude them),
    which then decode only their own candidate photos; their results are the same as in a run
    over all polygons.
    """
    from rich.progress import track

    from difftex.geometry.density import PROBE_LONG_SIDE, choose_texel_size, photo_texel_size, probe_gsd

    cfg = texture if isinstance(texture, TextureConfig) else TextureConfig(density=None, long_side=int(texture))
    caster = ProxyCaster.build(proxy)
    fallback = fallback or {}
    todo = list(range(len(proxy.polygons))) if only is None else sorted({int(i) for i in only})
    probes: dict[int, UVFrame] | None = None  # the probe frames of the polygons computed here
    probe_masks: dict[int, np.ndarray] | None = None
    if cfg.mode == "auto":
        probes = {i: uv_frame(proxy.polygons[i], up, long_side=PROBE_LONG_SIDE) for i in todo}
        probe_masks = {i: texel_mask(proxy.polygons[i], probes[i]) for i in todo}
    ids_todo = {proxy.polygons[i].id for i in todo}
    wanted = {
        pid: set(names) | set(fallback.get(pid, ())) for pid, names in candidates.items() if pid in ids_todo
    }
    parts: list[list[_Sighting]] = [[] for _ in proxy.polygons]
    wanted_names = set().union(*wanted.values()) if wanted else set()
    used = [ph for ph in photos if ph.name in wanted_names]

    def sightings(ph: Photo) -> list[tuple[int, _Sighting]]:
        ids, _ = id_buffer(caster, ph)
        # which polygons the photo sees at all: one pass, not one per polygon
        hits = np.bincount(ids.ravel() + 1, minlength=len(proxy.polygons) + 1)[1:]
        found = []
        for i in np.flatnonzero(hits).tolist():  # the polygons it sees, not all of a district's
            poly = proxy.polygons[i]
            if ph.name not in wanted.get(poly.id, ()):
                continue
            if (poly.normal @ (ph.center - poly.centroid)) <= 0:
                continue  # the camera is behind the plane: it sees none of this face's outside
            a = ids == i
            rows, cols = np.flatnonzero(a.any(1)), np.flatnonzero(a.any(0))
            box = (int(cols[0]), int(rows[0]), int(cols[-1]) + 1, int(rows[-1]) + 1)
            crop = a[box[1] : box[3], box[0] : box[2]]
            gsd = cos = None
            if probes is not None and probe_masks is not None:
                seen_p = crop_texel_visibility(probes[i], ph, probe_masks[i], box, crop)
                gsd, cos = probe_gsd(probes[i], ph, seen_p)
            v = ph.center - poly.centroid
            mean_cos = float(v @ poly.normal / np.linalg.norm(v))
            found.append((i, _Sighting(ph.name, box, np.packbits(crop.ravel()), mean_cos, gsd, cos)))
        return found

    # Pinhole photos are rasterised side by side (about 30 B per pixel and thread). Distorted
    # ones are ray-cast, one at a time under the caster's lock, each thread holding its rays
    # (about 90 B per pixel): 2 threads were 8 % faster on sceaux-castle for 1.6x the memory.
    workers = max(1, int(threads))
    cast_workers = workers if all(ph.is_pinhole for ph in used) else 1
    with ThreadPoolExecutor(max_workers=workers) as pool:
        # map keeps the photos' order, so each polygon's sightings are in photo order as before
        found = pool.map(sightings, used) if cast_workers > 1 else map(sightings, used)
        for per_photo in track(found, total=len(used), description="visibility", disable=not progress, transient=True):
            for i, sighting in per_photo:
                parts[i].append(sighting)
    by_name = {p.name: p for p in photos}

    def polygon_visibility(i: int, poly) -> PolygonVisibility:
        items = parts[i]
        rect = uv_frame(poly, up, long_side=PROBE_LONG_SIDE)
        extent = (rect.width * rect.texel_size, rect.height * rect.texel_size)
        photo_size = None
        if probes is not None and items:
            photo_size = photo_texel_size(
                np.stack([it.gsd for it in items]),  # type: ignore[misc]  # set whenever probes are
                np.stack([it.cos for it in items]),  # type: ignore[misc]
                cfg.gsd_percentile,
            )
        size = choose_texel_size(extent, extent[0] * extent[1], photo_size, cfg, min(max(len(items), 1), top_k))
        frame = (
            uv_frame(poly, up, density=1.0 / size.texel_size)
            if cfg.mode != "long_side"
            else uv_frame(poly, up, long_side=int(cfg.long_side))  # type: ignore[arg-type]  # set in long_side mode
        )
        tmask = texel_mask(poly, frame)
        kept, spare = [], []
        later = fallback.get(poly.id, {})
        for it in items:
            h, w = it.bbox[3] - it.bbox[1], it.bbox[2] - it.bbox[0]
            crop = np.unpackbits(it.crop, count=h * w).astype(bool).reshape(h, w)
            seen = crop_texel_visibility(frame, by_name[it.name], tmask, it.bbox, crop)
            if it.name in later:
                spare.append((it, crop, seen, later[it.name]))
            elif seen.sum() >= min_texels:
                kept.append((it, crop, seen))
            elif seen.any():
                spare.append(
                    (it, crop, seen, f"sees {int(seen.sum())} texels (< visibility.min_texels = {min_texels})")
                )
        if texel_candidates and len(kept) > texel_candidates:
            kept, spare_best = best_per_texel(kept, frame, by_name, texel_candidates)
            spare = spare + spare_best
        kept, rescued = last_sources(kept, spare, tmask)
        if max_photos is not None and len(kept) > max_photos:  # a cap the user set: it wins
            kept = sorted(kept, key=lambda k: -k[0].mean_cos)[:max_photos]
            rescued = {n: r for n, r in rescued.items() if n in {k[0].name for k in kept}}
        order = {it.name: n for n, it in enumerate(items)}
        kept = sorted(kept, key=lambda k: order[k[0].name])
        K = len(kept)
        H, W = frame.shape
        vis = PolygonVisibility(
            polygon_id=poly.id,
            frame=frame,
            texel_mask=tmask,
            photos=[k[0].name for k in kept],
            texel_visible=np.stack([k[2] for k in kept]) if K else np.zeros((0, H, W), bool),
            a_bbox=np.asarray([k[0].bbox for k in kept], dtype=np.int64).reshape(K, 4),
            a_masks=[k[1] for k in kept],
        )
        return dataclasses.replace(vis, texel_size=dataclasses.asdict(size), rescued=rescued)

    # the polygons side by side as well (their texel visibility per photo is numpy array work)
    with ThreadPoolExecutor(max_workers=workers) as pool:
        return list(pool.map(polygon_visibility, todo, [proxy.polygons[i] for i in todo]))


def best_per_texel(kept: list[tuple], frame: UVFrame, photos: dict, m: int, grid: int = 64) -> tuple[list, list]:
    """The photos among the ``m`` best of some texel, and the others (as ``last_sources``' spare).

    A texel keeps ``optimize.top_k`` slots, ranked by Q = Q_a Q_c Q_r; a photo outside the best
    few of every texel never wins a slot, yet was decoded, mapped and ranked at every level
    (on a 200-photo building, 54-75 candidates per polygon). Ranked here by the geometric part
    of Q, frontality times resolution (cosine of the viewing angle x min(1, pixels per texel)),
    on a grid of at most ``grid`` x ``grid`` texels of the frame. ``m`` (3 x top_k by default)
    leaves Q_c its consensus: an occluder in a few of the best photos still meets agreeing ones.

    Args:
        kept: (sighting, crop, seen (H, W) bool) per photo, in their order.
        photos: photo name -> Photo.
    Returns:
        (the kept tuples that rank within ``m`` somewhere, in order; the others as (sighting,
        crop, seen, why) for ``last_sources``, which takes back a photo that alone sees texels).
    """
    H, W = frame.shape
    step = max(1, -(-max(H, W) // grid))
    ty, tx = np.mgrid[0:H:step, 0:W:step].astype(np.float64) + 0.5
    X = frame.texel_to_world(tx, ty)
    scores = np.zeros((len(kept), *tx.shape), np.float32)
    for j, (it, _, seen) in enumerate(kept):
        ph = photos[it.name]
        v = ph.center - X
        cos = (v @ frame.normal) / np.linalg.norm(v, axis=-1)
        fp = texel_footprint(frame, ph, texel_to_pixel(frame, ph, tx, ty)[0], tx, ty)
        s = np.nan_to_num(np.clip(cos, 0, 1) * np.minimum(1.0, fp), nan=0.0)
        scores[j] = np.where(seen[::step, ::step], s, -1.0)
    # rank of each photo at each texel (0: best), by score then photo order
    order = np.argsort(-scores, axis=0, kind="stable")
    best = np.zeros(len(kept), bool)
    top = order[: min(m, len(kept))]
    valid = np.take_along_axis(scores, top, axis=0) > 0
    best[np.unique(top[valid])] = True
    return (
        [k for k, b in zip(kept, best) if b],
        [(*k, f"not among the {m} best photos (frontal, resolved) of any texel") for k, b in zip(kept, best) if not b],
    )


def last_sources(kept: list[tuple], spare: list[tuple], mask: np.ndarray) -> tuple[list[tuple], dict]:
    """``kept`` plus the ``spare`` photos that see texels no photo before them sees.

    Args:
        kept: (sighting, crop, seen (H, W) bool) of the photos that passed every test.
        spare: (sighting, crop, seen, why it was left out), tried least oblique first.
        mask: (H, W) texel mask of the polygon.
    Returns:
        (the kept tuples and the rescued ones, {name: {"texels": texels only it sees, "why": why}}).
    """
    covered = np.zeros(mask.shape, bool)
    for k in kept:
        covered |= k[2]
    rescued = {}
    for it, crop, seen, why in sorted(spare, key=lambda s: -s[0].mean_cos):
        new = seen & mask & ~covered
        if new.any():
            kept = [*kept, (it, crop, seen)]
            covered |= seen
            rescued[it.name] = {"texels": int(new.sum()), "why": why}
    return kept, rescued
