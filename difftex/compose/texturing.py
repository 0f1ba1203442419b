"""The per-polygon texturing stage: one pass over the photos, from candidates to texture maps.

For one polygon: decode its candidate photos once (difftex.sampling.photos.PhotoSet), map them at the
first level, estimate their brightness transfers there (histogram matching, Sec. 4.3), run the
coarse-to-fine optimization of the blend weights (difftex.method.loop), and compose the final
texture from the last level's slots (no second pass over the photos). ``texture_polygon`` is
the importable stage; the ``difftex texture`` command and the workflow's ``texture`` rule call it.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from difftex.compose.composite import dominant_from_slots, finish_texture
from difftex.compose.histmatch import mapped_transfers
from difftex.compose.outputs import write_composite
from difftex.geometry.frames import UVFrame, level_sides
from difftex.method.config import ComputeConfig, OptimizeConfig
from difftex.method.loop import optimize_polygon
from difftex.method.relief import estimate_relief
from difftex.sampling.photos import PhotoSet, PolygonInput, pick_device, with_transfer
from difftex.sampling.texels import level_frame, resample_nearest
from difftex.scene.files import decode_photo


@dataclass
class TexturedPolygon:
    """Everything the texturing of one polygon produced (arrays at the target frame)."""

    inp: PolygonInput
    texture: np.ndarray  # (H, W, 3) float, unseen texels filled
    seen: np.ndarray  # (H, W) bool texels some photo coloured
    dominant: np.ndarray  # (H, W) int photo index with the largest weight, -1 none
    idx: np.ndarray  # (K, H, W) slot photo indices
    W: np.ndarray  # (K, H, W) blend weights
    transfers: list | None  # per photo (3, 2, N_KNOTS) or None
    stats: dict  # optimization statistics (levels, losses, times)
    heights: np.ndarray | None = None  # (H, W) relief height field at the target frame, scene units
    report: dict = field(default_factory=dict)  # fill and summary figures


def polygon_transfers(photos: PhotoSet, cfg: OptimizeConfig) -> tuple[UVFrame, dict, list | None, str | None]:
    """The polygon's brightness transfers, estimated on its photos mapped at the coarse level.

    Returns:
        (the coarse level's frame, {photo index: MappedPhoto or None} there before any transfer,
        per photo transfers or None without histogram matching, the reference photo's name or None).
    """
    inp = photos.inp
    match_frame = level_frame(inp.frame, min(cfg.long_side_start, max(inp.frame.shape)))
    mask = resample_nearest(inp.texel_mask, inp.frame, match_frame)
    raw = {n: photos.map(n, match_frame, mask) for n in sorted(photos.samplers)}
    transfers, ref = None, None
    if cfg.histogram_matching:
        transfers, ref = mapped_transfers(
            raw, len(inp.photos), cfg.histmatch_reference, cfg.histmatch_channels, names=[p.name for p in inp.photos],
            model=cfg.histmatch_model,
        )
    return match_frame, raw, transfers, ref


def texture_polygon(
    inp: PolygonInput,
    cfg: OptimizeConfig,
    compute: ComputeConfig = ComputeConfig(),
    progress: bool = False,
    decode: Callable[..., np.ndarray] = decode_photo,
) -> TexturedPolygon:
    """Texture one polygon: transfers, optimization and composition from one decode per photo
    (``decode``: ``decode_photo``, or a DecodeCache that several polygons of a job share)."""
    t0 = time.perf_counter()
    device = pick_device(compute.device)
    photos = PhotoSet.load(
        inp, device, exact_decode=cfg.exact_decode, decode=decode, supersample=cfg.supersample,
        relief_range=cfg.relief_range if cfg.relief else (0.0, 0.0),
    )
    t_read = time.perf_counter() - t0
    relief_stats = None
    if cfg.relief:
        photos.relief, relief_stats = estimate_relief(photos, cfg.relief_settings())
        relief_stats["time_s"] = time.perf_counter() - t0 - t_read
    sides = level_sides(max(inp.frame.shape), cfg.long_side_start, cfg.coarse_to_fine, cfg.level_step)
    match_frame, raw, transfers, ref = polygon_transfers(photos, cfg)
    first = None
    if match_frame.shape == level_frame(inp.frame, sides[0]).shape:
        first = {
            n: (with_transfer(mp, transfers[n] if transfers else None) if mp is not None else None)
            for n, mp in raw.items()
        }
    t_match = time.perf_counter() - t0 - t_read - (relief_stats["time_s"] if relief_stats else 0.0)
    res = optimize_polygon(photos, cfg, compute, transfers, first=first, progress=progress)
    wsum = res.W.sum(0)
    U, fill = finish_texture(res.U, wsum, inp.texel_mask)
    seen = (wsum > 0) & inp.texel_mask
    stats = dict(res.stats)
    stats.update(
        {
            "histmatch": transfers is not None,
            "histmatch_reference": ref,
            "histmatch_mode": cfg.histmatch_reference if cfg.histogram_matching else None,
            "photos_seeing": [inp.photos[n].name for n in sorted(photos.samplers)],
            "photo_reads": photos.reads,
            "decode_scale": {inp.photos[n].name: s for n, s in photos.decode_scale.items()},
            "photo_bytes": photos.nbytes(),
            "time_read_photos_s": t_read,
            "time_histmatch_s": t_match,
            "corrections": {
                inp.photos[n].name: {"params": c.params.tolist(), "centre": list(c.centre), "scale": c.scale}
                for n, c in photos.corrections.items()
            },
            "time_stage_s": time.perf_counter() - t0,
            "relief": relief_stats,
        }
    )
    report = {"polygon_id": inp.polygon_id, "method": "difftex", "histogram_matching": transfers is not None, **fill}
    return TexturedPolygon(
        inp=inp,
        texture=U,
        seen=seen,
        dominant=dominant_from_slots(res.idx, res.W),
        idx=res.idx,
        W=res.W,
        transfers=transfers,
        stats=stats,
        report=report,
        heights=photos.relief.at(inp.frame) * inp.texel_mask if photos.relief is not None else None,
    )


def write_polygon(tp: TexturedPolygon, optimized_dir: str | Path) -> None:
    """weights.npz (slots, weights, transfers), stats.json and composite.npz (the float texture,
    its source map and report; assembly writes the PNGs from it), each written atomically."""
    import json

    from difftex.sampling.colour import N_KNOTS, identity_transfer
    from difftex.scene.files import write_json, write_npz

    inp = tp.inp
    H, W = inp.frame.shape
    names = [p.name for p in inp.photos]
    extra = {}
    if tp.transfers is not None:
        arr = (
            np.stack([t if t is not None else identity_transfer() for t in tp.transfers])
            if names
            else np.zeros((0, 3, 2, N_KNOTS), np.float32)
        )
        extra = {
            "transfers": arr.astype(np.float32),
            "has_transfer": np.array([t is not None for t in tp.transfers], bool),
        }
    write_npz(
        Path(optimized_dir) / "weights.npz",
        polygon_id=np.array(inp.polygon_id),
        photos=np.array(names, dtype=str),
        frame=np.array(json.dumps(inp.frame.to_dict())),
        shape=np.array([H, W]),
        texel_mask=np.packbits(inp.texel_mask.ravel()),
        idx=tp.idx.astype(np.int16),
        W=tp.W.astype(np.float16),
        **extra,
    )
    write_json(Path(optimized_dir) / "stats.json", tp.stats)
    write_composite(
        Path(optimized_dir) / "composite.npz",
        tp.texture,
        inp.texel_mask,
        tp.seen,
        tp.dominant,
        names,
        dict(tp.report, optimize=tp.stats),
        relief=(tp.heights, inp.frame.texel_size) if tp.heights is not None else None,
    )
