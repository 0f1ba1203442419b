"""A polygon's candidate photos decoded once and cropped to it, in numpy (no torch).

What the initialization stage does (difftex.compose.stage_files.initialize_polygon): for every
candidate photo, a probe level of the polygon's frame is mapped into the photo (exactly, through
the camera model) to find the pixels that the polygon's visible texels cover and the coarsest
decode scale that keeps the detail the finest texture level needs; the photo is decoded at that
scale and cropped. ``PhotoSet.from_crops`` (difftex.sampling.photos) builds the pyramids from
the crops. No torch here: the initialization job would spend more time importing it than
cropping a small polygon's photos.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np

from difftex.errors import DifftexError
from difftex.geometry.frames import (
    UVFrame,
    level_frame,
    shifted_frame,
    texel_footprint,
    texel_homography,
    texel_to_pixel,
)
from difftex.sampling import SUPERSAMPLE
from difftex.scene.camera import Photo, scene_up
from difftex.scene.files import decode_photo

PROBE_LONG_SIDE = 64  # texels of the probe level that sizes crops and decode scales
# Crop origins are multiples of 2^CROP_ALIGN pixels, so the box-filter pyramid's pixels fall on
# the same image blocks whatever the crop (for levels <= CROP_ALIGN): sampled colours then do
# not depend on how far the polygon's visible region happens to extend.
CROP_ALIGN = 7


@dataclass(eq=False)
class PolygonInput:
    """What texturing one polygon needs (built from a visibility file or by a test)."""

    polygon_id: str
    frame: UVFrame  # target resolution
    texel_mask: np.ndarray  # (H, W) bool
    photos: list[Photo]  # candidate photos
    texel_visible: np.ndarray  # (N, H, W) bool
    load_image: Callable[[Photo], np.ndarray] | None = None  # float32 RGB (h, w, 3); None: decode_photo
    a_bbox: np.ndarray | None = None  # (N, 4) x0, y0, x1, y1 of a_k^i (render mode)
    a_masks: list[np.ndarray] | None = None  # N crops of a_k^i
    up: np.ndarray | None = None  # (3,) the scene's unit up (None: estimated from the candidates)
    # the height field measured from the scene's dense geometry (difftex.compose.heights), at its
    # own frame over the polygon's rectangle; None: the plane, or the sweep of optimize.relief
    dense: tuple[UVFrame, np.ndarray] | None = None

    def up_vector(self) -> np.ndarray:
        """The scene's unit up: ``up`` where given, else estimated from the candidate photos
        (difftex.scene.camera.scene_up; photos all on one side tilt that estimate)."""
        up = np.asarray(self.up if self.up is not None else scene_up(self.photos), np.float64)
        return up / np.linalg.norm(up)

    def __post_init__(self):
        N = len(self.photos)
        if self.texel_visible.shape != (N, *self.frame.shape):
            raise DifftexError(
                f"polygon '{self.polygon_id}': visibility is {self.texel_visible.shape}, expected "
                f"{(N, *self.frame.shape)}"
            )
        if self.texel_mask.shape != self.frame.shape:
            raise DifftexError(
                f"polygon '{self.polygon_id}': texel mask shape {self.texel_mask.shape} != frame {self.frame.shape}"
            )


def median_elevation(inp: PolygonInput, min_cos: float) -> float | None:
    """The median elevation of the polygon's photos seen from its centre within arccos(``min_cos``)
    of its normal: the angle of the ray to each photo above the horizontal (degrees; > 0 from
    above, as a drone's). The relief sweep runs only above ``optimize.relief_min_elevation``, and
    the initialization then crops the photos for it; both ask this, from the polygon input alone.

    Returns:
        degrees, or None where no photo is within the angle.
    """
    fr = inp.frame
    up = inp.up_vector()
    centre = fr.texel_to_world(np.array(fr.width / 2), np.array(fr.height / 2))
    el = []
    for ph in inp.photos:
        v = ph.center - centre
        v = v / max(float(np.linalg.norm(v)), 1e-12)
        if float(v @ fr.normal) >= min_cos:
            el.append(math.degrees(math.asin(float(np.clip(v @ up, -1.0, 1.0)))))
    return float(np.median(el)) if el else None


def elevation_reaches(elevation: float | None, min_elevation: float) -> bool:
    """Whether a :func:`median_elevation` reaches ``min_elevation`` (always at -90, even with no
    photo within the angle)."""
    return min_elevation <= -90 or (elevation is not None and elevation >= min_elevation)


def seen_from_above(inp: PolygonInput, min_cos: float, min_elevation: float) -> bool:
    """Whether the polygon's :func:`median_elevation` reaches ``min_elevation``: the relief sweep
    and the tilt frontality run only there, when asked. The initialization asks the same to crop
    the photos for the sweep's heights, so a polygon the sweep skips is textured exactly as
    without relief."""
    return elevation_reaches(median_elevation(inp, min_cos), min_elevation)


def polygon_input_from_visibility(
    vis, scene_photos: dict[str, Photo], load_image=None, up: np.ndarray | None = None
) -> PolygonInput:
    """PolygonInput from a difftex.geometry.visibility.PolygonVisibility and the scene's photos by
    name; ``up``: the scene's up (difftex.scene.loading.Scene.up)."""
    missing = [n for n in vis.photos if n not in scene_photos]
    if missing:
        raise DifftexError(
            f"polygon '{vis.polygon_id}': visibility names photo(s) not in the scene: {', '.join(missing[:3])}"
        )
    return PolygonInput(
        polygon_id=vis.polygon_id,
        frame=vis.frame,
        texel_mask=vis.texel_mask,
        photos=[scene_photos[n] for n in vis.photos],
        texel_visible=vis.texel_visible,
        load_image=load_image,
        a_bbox=vis.a_bbox,
        a_masks=vis.a_masks,
        up=up,
    )


@dataclass
class PhotoCrop:
    """One candidate photo as decoded and cropped to a polygon: what the initialization stage
    writes and the optimization stage builds its pyramid from (no photo is decoded twice).

    ``pixels`` (h, w, 3) as the file stores them (uint8 or uint16), decoded at 1/2^``base``;
    (``x0``, ``y0``): the crop's corner in full-resolution pixels, a multiple of 2^``base``.
    """

    pixels: np.ndarray
    x0: int
    y0: int
    base: int


def probe_map(frame: UVFrame, photo: Photo) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """f_k^i at the texel centres of a small frame (the probe), in numpy.

    Pinhole cameras: the homography, in the same float64 operations as ``texel_map``, so the
    pixels and footprints are those of the optimization's mapping. Other camera models: every
    texel projected exactly through the model (a probe has a few thousand texels), the footprint
    by forward differences.

    Returns:
        pix (H, W, 2) float32 full-resolution pixels, NaN behind the camera; footprint (H, W)
        float32 pixels per texel; valid (H, W) bool: in front, inside the image, front-facing.
    """
    tx = np.arange(frame.width, dtype=np.float64) + 0.5
    ty = np.arange(frame.height, dtype=np.float64) + 0.5
    if photo.is_pinhole:
        Hm = texel_homography(frame, photo)

        def affine(a: float, b: float, c: float) -> np.ndarray:  # as texel_map's, term for term
            return (a * tx)[None, :] + (b * ty + c)[:, None]

        depth = affine(*Hm[2])
        front = depth > 1e-9
        inv = 1.0 / np.where(front, depth, 1.0)
        pix = np.stack([affine(*Hm[0]) * inv, affine(*Hm[1]) * inv], -1)
        a = np.abs(inv)
        footprint = np.sqrt(abs(float(np.linalg.det(Hm))) * (a * a * a))
    else:
        TX, TY = np.meshgrid(tx, ty)
        pix, depth = texel_to_pixel(frame, photo, TX, TY)
        front = np.isfinite(pix).all(-1) & (depth > 1e-9)
        footprint = texel_footprint(frame, photo, pix, TX, TY)
    s = frame.texel_size
    c = np.asarray(photo.center - frame.origin, np.float64)
    eu, ev, nrm = (np.asarray(v, np.float64) for v in (frame.e_u, frame.e_v, frame.normal))
    a_u, a_v, cn = float(c @ eu) - s * tx, float(c @ ev) - s * ty, float(c @ nrm)
    cos = cn / np.maximum(np.sqrt((a_u * a_u)[None, :] + (a_v * a_v + cn * cn)[:, None]), 1e-30)
    with np.errstate(invalid="ignore"):
        inside = (pix[..., 0] >= 0) & (pix[..., 0] <= photo.width) & (pix[..., 1] >= 0) & (pix[..., 1] <= photo.height)
    valid = front & inside & (cos > 0) & np.isfinite(pix).all(-1)
    pix = np.where(front[..., None], pix, np.nan)
    return pix.astype(np.float32), np.nan_to_num(footprint, nan=1.0).astype(np.float32), valid


def any_pool(masks: np.ndarray, src: UVFrame, dst: UVFrame) -> np.ndarray:
    """(N, h, w) bool: a texel of ``dst`` is set when any texel of ``src`` it covers is set
    (torch's adaptive max pooling bins; nearest neighbour where ``dst`` is the finer).

    Shape: (N, H, W) at ``src`` -> (N, h, w) at ``dst``.
    """
    if masks.shape[-2:] == dst.shape:
        return masks
    out = np.asarray(masks, bool)
    for axis, (n_in, n_out) in ((1, (src.height, dst.height)), (2, (src.width, dst.width))):
        if n_out <= n_in:  # adaptive bins [floor(i n_in / n_out), ceil((i + 1) n_in / n_out))
            lo = [i * n_in // n_out for i in range(n_out)]
            hi = [-(-(i + 1) * n_in // n_out) for i in range(n_out)]
            out = np.stack([np.take(out, range(a, b), axis=axis).any(axis) for a, b in zip(lo, hi)], axis)
        else:  # nearest: source index floor(i n_in / n_out)
            out = np.take(out, [int(i * (n_in / n_out)) for i in range(n_out)], axis=axis)
    return out


def photo_crops(
    inp: PolygonInput,
    finest: UVFrame | None = None,
    exact_decode: bool = False,
    decode: Callable[..., np.ndarray] = decode_photo,
    supersample: int = SUPERSAMPLE,
    relief_range: tuple[float, float] = (0.0, 0.0),
) -> Iterator[tuple[int, PhotoCrop]]:
    """(photo index, crop) of every candidate photo that sees a texel of ``inp``, one decode each,
    one photo at a time (so one decoded photo is held at once). Arguments as ``PhotoSet.load``'s."""
    finest = finest or inp.frame
    supersample = max(1, int(supersample))
    probe = level_frame(inp.frame, min(PROBE_LONG_SIDE, max(inp.frame.shape)))
    vis_probe = any_pool(inp.texel_visible & inp.texel_mask[None], inp.frame, probe)
    for n, ph in enumerate(inp.photos):
        if not vis_probe[n].any():
            continue
        t_pix, t_fp, t_valid = probe_map(probe, ph)
        ok = vis_probe[n] & t_valid
        if not ok.any():
            continue
        scale = probe.texel_size / finest.texel_size  # probe texel -> finest texels
        fp_fine = t_fp[ok] / scale
        pix, fp = [t_pix[ok]], [t_fp[ok]]
        for h in {float(x) for x in relief_range} - {0.0}:
            h_pix, h_fp, h_valid = probe_map(shifted_frame(probe, h), ph)
            okh = vis_probe[n] & h_valid
            pix.append(h_pix[okh])
            fp.append(h_fp[okh])
        box = crop_box(
            ph,
            np.concatenate(pix),
            np.concatenate(fp),
            inp.a_bbox[n] if inp.a_bbox is not None and len(inp.a_bbox) > n else None,
        )
        if box is None:
            continue
        reduce = 1
        if not exact_decode and inp.load_image is None:
            finest_px = float(fp_fine.min()) / supersample  # a sub-sample's footprint
            reduce = 2 ** int(np.clip(np.floor(np.log2(max(finest_px, 1.0))), 0, 3))
        s = reduce
        x0, y0, x1, y1 = box[0] // s * s, box[1] // s * s, box[2], box[3]
        if inp.load_image is not None:
            img = inp.load_image(ph)
            if img.shape[:2] != (ph.height, ph.width):
                raise DifftexError(
                    f"{ph.image_path}: image is {img.shape[1]}x{img.shape[0]}, camera says {ph.width}x{ph.height}"
                )
        else:
            img = decode(ph.image_path, (ph.width, ph.height), reduce, as_stored=True)
        # a copy, so the whole decoded photo is freed here (a cache may keep it)
        pixels = img[y0 // s : -(-y1 // s), x0 // s : -(-x1 // s)].copy()
        del img
        yield n, PhotoCrop(pixels, int(x0), int(y0), int(math.log2(reduce)))


def crop_box(
    photo: Photo, pix: np.ndarray, footprint: np.ndarray, a_box=None, pad: int = 16
) -> tuple[int, int, int, int] | None:
    """Pixel box holding the polygon's visible (probe) texels and a_k^i, padded, inside the image.

    A probe texel covers ``footprint`` pixels around its centre: the box grows by that much.
    """
    boxes: list[tuple[float, ...]] = []
    if len(pix):
        r = footprint[:, None]
        lo, hi = pix - r, pix + r
        boxes.append((lo[:, 0].min(), lo[:, 1].min(), hi[:, 0].max(), hi[:, 1].max()))
    if a_box is not None and a_box[2] > a_box[0] and a_box[3] > a_box[1]:
        boxes.append(tuple(float(v) for v in a_box))
    if not boxes:
        return None
    b = np.array(boxes)
    a = 2**CROP_ALIGN
    x0 = max(0, int(math.floor(b[:, 0].min())) - pad) // a * a
    y0 = max(0, int(math.floor(b[:, 1].min())) - pad) // a * a
    x1 = min(photo.width, int(math.ceil(b[:, 2].max())) + pad)
    y1 = min(photo.height, int(math.ceil(b[:, 3].max())) + pad)
    if x1 <= x0 or y1 <= y0:
        return None
    return x0, y0, x1, y1
