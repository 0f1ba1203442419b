"""The files the per-polygon stages hand on: initialization -> histogram matching ->
optimization -> composition.

``R/init/<pid>/crops.npz`` (initialization): each candidate photo as decoded and cropped to the
polygon (``PhotoCrop``), uncompressed, and the decode's figures. The histogram matching and the
optimization build their pyramids from these crops, so no photo is decoded twice for a polygon.

``R/histmatch/<pid>/transfers.npz`` (histogram matching): the photos' brightness transfers
(``Brightness``) and the relief height field they were estimated through, which the
optimization maps the photos through as well.

``R/optimized/<pid>/weights.npz`` and ``optimized.npz`` (optimization): the slots, weights and
brightness transfers, and the composition's inputs (U before the fill, sum_k W_k, the dominant
photo, the height field). ``stats.json`` beside them. Composition writes ``composite.npz``
(difftex.compose.outputs.write_composite) from them, the same bytes as the one-process
``texture`` stage writes.

``initialize_polygon`` is the initialization stage itself. Nothing here imports torch (the
transfers' module is imported where it is used): the initialization and composition jobs run
without it.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from difftex.compose.fill import finish_texture
from difftex.compose.outputs import write_composite
from difftex.errors import DifftexError
from difftex.geometry.frames import UVFrame
from difftex.layout import OPTIMIZED, STATS, WEIGHTS
from difftex.scene.files import decode_photo, read_json, read_npz, write_json, write_npz, write_npz_stored

if TYPE_CHECKING:
    from difftex.method.config import OptimizeConfig
    from difftex.sampling.crops import PhotoCrop, PolygonInput
    from difftex.sampling.relief import Relief

INIT_VERSION = 1
HISTMATCH_VERSION = 1


@dataclass
class Brightness:
    """What histogram matching hands the optimization (``texturing.match_brightness``).

    The transfers are estimated on the photos mapped at the coarse level through the polygon's
    relief (when ``optimize.relief`` sweeps one), so the relief is found here and handed on: the
    optimization maps through the same one. ``mapped`` (the coarse level's photos before any
    transfer, and their frame) is kept in memory only, for the one-process stage to reuse.
    """

    transfers: list | None  # per photo (3, 2, N_KNOTS) float32, None where it sees nothing; None: no matching
    reference: str | None  # the reference photo's name (``histmatch_reference: best``), else None
    relief: Relief | None = None
    relief_stats: dict | None = None  # the sweep's statistics (stats.json's ``relief``)
    time_s: float = 0.0  # the transfers' time, the sweep's excluded
    mapped: tuple | None = None


@dataclass
class OptimizedPolygon:
    """What the optimization stage hands to composition (arrays at the target frame).

    ``U``: sum_k W_k sharp_k before the unseen texels are filled; ``idx``, ``W`` and ``transfers``
    are kept in memory only (the stage writes them to weights.npz, composition does not read them).
    """

    polygon_id: str
    names: list[str]  # the polygon's candidate photos, as indexed by ``dominant``
    mask: np.ndarray  # (H, W) bool texels inside the polygon
    frame: UVFrame  # the target frame
    U: np.ndarray  # (H, W, 3) float32
    weight_sum: np.ndarray  # (H, W) sum_k W_k
    dominant: np.ndarray  # (H, W) int photo index with the largest weight, -1 none
    stats: dict
    histmatch: bool
    heights: np.ndarray | None = None
    idx: np.ndarray | None = None
    W: np.ndarray | None = None
    transfers: list | None = None


def compose_polygon(opt: OptimizedPolygon) -> tuple[np.ndarray, np.ndarray, dict]:
    """The composition stage: the texture with its unseen texels filled, the seen texels, and
    the polygon's report (fill figures; the optimization's statistics under ``optimize``)."""
    U, fill = finish_texture(opt.U, opt.weight_sum, opt.mask)
    seen = (opt.weight_sum > 0) & opt.mask
    report = {"polygon_id": opt.polygon_id, "method": "difftex", "histogram_matching": opt.histmatch, **fill}
    return U, seen, report


def initialize_polygon(
    inp: PolygonInput, cfg: OptimizeConfig, decode: Callable[..., np.ndarray] = decode_photo
) -> tuple[dict[int, PhotoCrop], dict]:
    """The initialization stage: every candidate photo decoded once and cropped to the polygon.

    Returns:
        ({photo index: crop}, {"photo_reads", "time_read_photos_s"}); ``PhotoSet.from_crops``
        turns the crops into the photo set that ``PhotoSet.load`` would have built.
    """
    t0 = time.perf_counter()
    from difftex.sampling.crops import photo_crops

    crops = dict(photo_crops(inp, None, cfg.exact_decode, decode, cfg.supersample, crop_relief_range(cfg, inp)))
    return crops, {"photo_reads": len(crops), "time_read_photos_s": time.perf_counter() - t0}


def crop_relief_range(cfg: OptimizeConfig, inp: PolygonInput) -> tuple[float, float]:
    """The heights along the normal that the photos' crops must hold: the measured field's
    (``inp.dense``), else the relief sweep's range where the sweep runs on the polygon
    (difftex.sampling.crops.seen_from_above), else none."""
    from difftex.sampling.crops import seen_from_above

    if inp.dense is not None:  # the measured field's heights (the plane among them)
        heights = inp.dense[1]
        return (min(0.0, float(heights.min())), max(0.0, float(heights.max())))
    if not cfg.relief or not seen_from_above(inp, cfg.relief_min_cos, cfg.relief_min_elevation):
        return (0.0, 0.0)
    return cfg.relief_range


def write_init(path: str | Path, polygon_id: str, names: list[str], crops: dict[int, PhotoCrop], stats: dict) -> None:
    """The initialization's file: ``crops`` (photo index -> crop), the photos' names (so a reader
    can check it pairs the file with the right polygon) and ``stats`` (JSON-able)."""
    arrays: dict[str, np.ndarray] = {
        "version": np.array(INIT_VERSION),
        "polygon_id": np.array(polygon_id),
        "photos": np.array(names, dtype=str),
        "stats": np.array(json.dumps(stats)),
    }
    for n, c in crops.items():
        arrays[f"crop_{n}"] = c.pixels
        arrays[f"box_{n}"] = np.array([c.x0, c.y0, c.base], np.int64)
    write_npz_stored(path, **arrays)


def read_init(path: str | Path, polygon_id: str, names: list[str]) -> tuple[dict[int, PhotoCrop], dict]:
    """(crops, stats) of ``write_init``'s file; a file of another polygon or photo list is refused."""
    d = read_npz(path)
    _meta(path, d, INIT_VERSION, "initialization", polygon_id, names)
    from difftex.sampling.crops import PhotoCrop

    crops = {}
    for key in d:
        if key.startswith("crop_"):
            n = int(key[5:])
            x0, y0, base = (int(v) for v in d[f"box_{n}"])
            crops[n] = PhotoCrop(d[key], x0, y0, base)
    return crops, json.loads(str(d["stats"]))


def _meta(path: str | Path, d: dict, version: int, what: str, polygon_id: str, names: list[str]) -> None:
    """Refuse a stage file of another version, polygon or photo list, in one line naming it."""
    if int(d.get("version", -1)) != version:
        article = "an" if what[0] in "aeiou" else "a"
        raise DifftexError(f"{path}: not {article} {what} file of this difftex (version {d.get('version')})")
    if str(d["polygon_id"]) != polygon_id or list(d["photos"]) != list(names):
        raise DifftexError(f"{path}: made for polygon {d['polygon_id']} and other photos; rerun the {what}")


def write_histmatch(path: str | Path, polygon_id: str, names: list[str], b: Brightness) -> None:
    """The histogram-matching stage's file: transfers, reference, the relief and its statistics."""
    from difftex.sampling.colour import N_KNOTS, identity_transfer

    meta = {"reference": b.reference, "relief_stats": b.relief_stats, "time_s": b.time_s,
            "matched": b.transfers is not None}
    arrays: dict[str, np.ndarray] = {
        "version": np.array(HISTMATCH_VERSION),
        "polygon_id": np.array(polygon_id),
        "photos": np.array(names, dtype=str),
        "meta": np.array(json.dumps(meta, default=_json_value)),
    }
    if b.transfers is not None:
        arrays["transfers"] = (np.stack([t if t is not None else identity_transfer() for t in b.transfers])
                               if b.transfers else np.zeros((0, 3, 2, N_KNOTS), np.float32))
        arrays["has_transfer"] = np.array([t is not None for t in b.transfers], bool)
    if b.relief is not None:
        arrays["relief_frame"] = np.array(json.dumps(b.relief.frame.to_dict()))
        arrays["relief_heights"] = b.relief.heights
        if b.relief.hidden is not None:
            arrays["relief_hidden"] = b.relief.hidden
    write_npz(path, **arrays)


def read_histmatch(path: str | Path, polygon_id: str, names: list[str]) -> Brightness:
    """``write_histmatch``'s file; one of another polygon or photo list is refused."""
    d = read_npz(path)
    _meta(path, d, HISTMATCH_VERSION, "histogram matching", polygon_id, names)
    meta = json.loads(str(d["meta"]))
    transfers = None
    if meta["matched"]:
        transfers = [t if ok else None for t, ok in zip(d["transfers"], d["has_transfer"])]
    relief = None
    if "relief_heights" in d:
        from difftex.sampling.relief import Relief

        relief = Relief(UVFrame.from_dict(json.loads(str(d["relief_frame"]))), d["relief_heights"],
                        d.get("relief_hidden"))
    return Brightness(transfers, meta["reference"], relief, meta["relief_stats"], float(meta["time_s"]))


def _json_value(obj):
    """numpy scalars and arrays as JSON values (the relief's statistics may hold them)."""
    return obj.item() if isinstance(obj, np.generic) else np.asarray(obj).tolist()


def write_weights(
    path: str | Path,
    polygon_id: str,
    names: list[str],
    frame: UVFrame,
    mask: np.ndarray,
    idx: np.ndarray,
    W: np.ndarray,
    transfers: list | None,
) -> None:
    """weights.npz: the last level's slots and weights (float16) and the brightness transfers."""
    from difftex.sampling.colour import N_KNOTS, identity_transfer

    H, Wd = frame.shape
    extra = {}
    if transfers is not None:
        arr = (
            np.stack([t if t is not None else identity_transfer() for t in transfers])
            if names
            else np.zeros((0, 3, 2, N_KNOTS), np.float32)
        )
        extra = {
            "transfers": arr.astype(np.float32),
            "has_transfer": np.array([t is not None for t in transfers], bool),
        }
    write_npz(
        path,
        polygon_id=np.array(polygon_id),
        photos=np.array(names, dtype=str),
        frame=np.array(json.dumps(frame.to_dict())),
        shape=np.array([H, Wd]),
        texel_mask=np.packbits(mask.ravel()),
        idx=idx.astype(np.int16),
        W=W.astype(np.float16),
        **extra,
    )


def write_weights_and_stats(out_dir: str | Path, opt: OptimizedPolygon) -> None:
    """weights.npz and stats.json of the optimization, each atomically (both texturing paths)."""
    out_dir = Path(out_dir)
    assert opt.idx is not None and opt.W is not None
    write_weights(out_dir / WEIGHTS, opt.polygon_id, opt.names, opt.frame, opt.mask, opt.idx, opt.W,
                  opt.transfers)
    write_json(out_dir / STATS, opt.stats)


def write_optimized(out_dir: str | Path, opt: OptimizedPolygon) -> None:
    """The optimization stage's files: weights.npz, optimized.npz (composition's inputs) and
    stats.json, each atomically."""
    out_dir = Path(out_dir)
    extra = {"heights": np.asarray(opt.heights, np.float32)} if opt.heights is not None else {}
    write_npz(
        out_dir / OPTIMIZED,
        U=np.asarray(opt.U, np.float32),
        weight_sum=np.asarray(opt.weight_sum, np.float32),
        dominant=opt.dominant.astype(np.int32),
        histmatch=np.array(opt.histmatch),
        **extra,
    )
    write_weights_and_stats(out_dir, opt)


def read_optimized(out_dir: str | Path) -> OptimizedPolygon:
    """``write_optimized``'s files, as composition needs them (no slots or weights)."""
    out_dir = Path(out_dir)
    meta = read_npz(out_dir / WEIGHTS)
    shape = tuple(int(v) for v in meta["shape"])
    mask = np.unpackbits(meta["texel_mask"])[: shape[0] * shape[1]].reshape(shape).astype(bool)
    d = read_npz(out_dir / OPTIMIZED)
    return OptimizedPolygon(
        polygon_id=str(meta["polygon_id"]),
        names=[str(n) for n in meta["photos"]],
        mask=mask,
        frame=UVFrame.from_dict(json.loads(str(meta["frame"]))),
        U=d["U"],
        weight_sum=d["weight_sum"],
        dominant=d["dominant"],
        stats=read_json(out_dir / STATS),
        histmatch=bool(d["histmatch"]),
        heights=d.get("heights"),
    )


def write_composite_of(path: str | Path, opt: OptimizedPolygon, U: np.ndarray, seen: np.ndarray, report: dict) -> None:
    """composite.npz of a polygon: its composed texture ``U``, ``seen`` texels and ``report``
    (``compose_polygon``'s), with the optimization's dominant photo, statistics and heights."""
    write_composite(
        path,
        U,
        opt.mask,
        seen,
        opt.dominant,
        opt.names,
        dict(report, optimize=opt.stats),
        relief=(opt.heights, opt.frame.texel_size) if opt.heights is not None else None,
    )


def write_composed(path: str | Path, opt: OptimizedPolygon) -> dict:
    """The composition stage's file, composite.npz; returns the polygon's report."""
    U, seen, report = compose_polygon(opt)
    write_composite_of(path, opt, U, seen, report)
    return report
