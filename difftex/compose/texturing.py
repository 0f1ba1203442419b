"""The per-polygon stages: one pass over the photos, from candidates to texture maps.

For one polygon:

1. initialization (``initialize_polygon`` in difftex.compose.stage_files, no torch): decode its
   candidate photos once and crop them to the polygon (difftex.sampling.crops.photo_crops);
2. histogram matching (``match_brightness``): sweep the relief when asked, map the photos at the
   first level through it and estimate their brightness transfers there (Sec. 4.3). The losses
   compare matched colours, so the transfers are an input of the optimization, not a step
   after it;
3. optimization (``optimize_photos``): decide whether the polygon is a mixed-resolution one
   (its candidates' resolution spread, ``optimize.mixed_spread``: then the ``mixed_*`` values
   apply), build the crops' pyramids, run the coarse-to-fine optimization of the blend weights
   (difftex.method.loop) on the matched photos and sum U from the last level's slots (no second
   pass over the photos);
4. composition (``compose_polygon``): fill the unseen texels, the report.

``texture_polygon`` runs the four in one process (the workflow's ``texture`` rule with
``run.split: false``, the baselines and benchmarks); the workflow's ``initialize``,
``histmatch``, ``optimize`` and ``compose`` rules run them as four jobs that exchange the files
of difftex.compose.stage_files. Both run the same functions, so both give the same textures.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from difftex.compose.fill import dominant_from_slots
from difftex.compose.histmatch import mapped_transfers
from difftex.compose.stage_files import Brightness, OptimizedPolygon, compose_polygon, crop_relief_range
from difftex.geometry.frames import UVFrame, level_sides
from difftex.layout import COMPOSITE
from difftex.method.config import ComputeConfig, OptimizeConfig
from difftex.method.loop import optimize_polygon
from difftex.method.relief import estimate_relief, occluding_relief
from difftex.method.witnesses import candidate_footprints, resolution_spread
from difftex.sampling.photos import PhotoSet, PolygonInput, pick_device, with_transfer
from difftex.sampling.relief import Relief
from difftex.sampling.texels import level_frame, resample_nearest
from difftex.scene.files import decode_photo


@dataclass
class TexturedPolygon:
    """Everything the texturing of one polygon produced (arrays at the target frame): the
    optimization's result and the composed texture."""

    inp: PolygonInput
    texture: np.ndarray  # (H, W, 3) float, unseen texels filled
    seen: np.ndarray  # (H, W) bool texels some photo coloured
    optimized: OptimizedPolygon  # slots, weights, transfers, dominant photo, heights, statistics
    report: dict = field(default_factory=dict)  # fill and summary figures

    @property
    def dominant(self) -> np.ndarray:
        """(H, W) int photo index with the largest weight, -1 none."""
        return self.optimized.dominant

    @property
    def idx(self) -> np.ndarray:
        """(K, H, W) slot photo indices."""
        assert self.optimized.idx is not None
        return self.optimized.idx

    @property
    def W(self) -> np.ndarray:
        """(K, H, W) blend weights."""
        assert self.optimized.W is not None
        return self.optimized.W

    @property
    def transfers(self) -> list | None:
        """Per photo (3, 2, N_KNOTS) brightness transfers, or None."""
        return self.optimized.transfers

    @property
    def stats(self) -> dict:
        """Optimization statistics (levels, losses, times)."""
        return self.optimized.stats

    @property
    def heights(self) -> np.ndarray | None:
        """(H, W) relief height field at the target frame, scene units, or None."""
        return self.optimized.heights


def coarse_frame(frame: UVFrame, cfg: OptimizeConfig) -> UVFrame:
    """The level the transfers are estimated at: the first level's long side, or the polygon's."""
    return level_frame(frame, min(cfg.long_side_start, max(frame.shape)))


def coarse_maps(photos: PhotoSet, cfg: OptimizeConfig) -> tuple[UVFrame, dict]:
    """The photos mapped at the coarse level (``coarse_frame``) before any transfer: (its frame,
    {photo index: MappedPhoto or None})."""
    inp = photos.inp
    match_frame = coarse_frame(inp.frame, cfg)
    mask = resample_nearest(inp.texel_mask, inp.frame, match_frame)
    return match_frame, {n: photos.map(n, match_frame, mask) for n in sorted(photos.samplers)}


def polygon_transfers(photos: PhotoSet, cfg: OptimizeConfig) -> tuple[UVFrame, dict, list | None, str | None]:
    """The polygon's brightness transfers, estimated on its photos mapped at the coarse level.

    Returns:
        (the coarse level's frame, {photo index: MappedPhoto or None} there before any transfer,
        per photo transfers or None without histogram matching, the reference photo's name or None).
    """
    inp = photos.inp
    match_frame, raw = coarse_maps(photos, cfg)
    transfers, ref = None, None
    if cfg.histogram_matching:
        transfers, ref = mapped_transfers(
            raw, len(inp.photos), cfg.histmatch_reference, cfg.histmatch_channels, names=[p.name for p in inp.photos],
            model=cfg.histmatch_model,
        )
    return match_frame, raw, transfers, ref


def match_brightness(photos: PhotoSet, cfg: OptimizeConfig) -> Brightness:
    """The histogram-matching stage on decoded photos: the relief sweep when ``optimize.relief``
    asks for one (``photos.relief`` is set to it: the photos are mapped through it from here on),
    then the brightness transfers at the coarse level (``polygon_transfers``)."""
    t0 = time.perf_counter()
    relief_stats = None
    if photos.inp.dense is not None:  # measured: the sweep has nothing to add
        photos.relief, relief_stats = dense_relief(photos)
    elif cfg.relief:
        photos.relief, relief_stats = estimate_relief(photos, cfg.relief_settings())
    if relief_stats is not None:
        relief_stats["time_s"] = time.perf_counter() - t0
    t1 = time.perf_counter()
    match_frame, raw, transfers, ref = polygon_transfers(photos, cfg)
    return Brightness(transfers, ref, photos.relief if relief_stats is not None else None, relief_stats,
                      time.perf_counter() - t1, mapped=(match_frame, raw))


def dense_relief(photos: PhotoSet) -> tuple[Relief, dict]:
    """The Relief of the height field the heights stage measured (``photos.inp.dense``), with
    each photo's self-occlusion through it, and its statistics for stats.json."""
    inp = photos.inp
    frame, heights = inp.dense
    mask = resample_nearest(inp.texel_mask, inp.frame, frame)
    h = np.where(mask, heights, 0.0).astype(np.float32)
    levels = {f"{v:.4g}": float((h[mask] == v).mean()) for v in np.unique(h[mask])} if mask.any() else {}
    stats = {"source": "dense", "long_side": max(frame.shape), "levels": levels,
             "relief_share": float((h[mask] != 0).mean()) if mask.any() else 0.0}
    return occluding_relief(photos, frame, h, mask), stats


def optimize_photos(
    photos: PhotoSet,
    cfg: OptimizeConfig,
    compute: ComputeConfig = ComputeConfig(),
    progress: bool = False,
    read_stats: dict | None = None,
    brightness: Brightness | None = None,
) -> OptimizedPolygon:
    """The optimization stage on decoded photos: the mixed-resolution switch (``cfg.for_spread``
    on the candidates' resolution spread; stats ``resolution_spread``, ``mixed_resolution``),
    then the coarse-to-fine optimization of W and U = sum_k W_k sharp_k on the photos matched by
    ``brightness`` (the histogram-matching stage's; None: ``match_brightness`` runs here).

    ``read_stats``: ``photo_reads``, ``time_read_photos_s`` of the stage that decoded the photos
    (``PhotoSet.load`` in this process, or the initialization stage's file).
    """
    t0 = time.perf_counter()
    inp = photos.inp
    spread, mixed = None, False
    if cfg.mixed_spread > 0:  # decided once per polygon, on all its candidates (before the relief)
        spread = resolution_spread(candidate_footprints(photos, inp.frame, sorted(photos.samplers)))
        switched = cfg.for_spread(spread)
        mixed, cfg = switched is not cfg, switched
    if brightness is None:
        brightness = match_brightness(photos, cfg)
    else:  # matched in another process: map through the relief the transfers were estimated on
        photos.relief = brightness.relief
    transfers = brightness.transfers
    sides = level_sides(max(inp.frame.shape), cfg.long_side_start, cfg.coarse_to_fine, cfg.level_step)
    first = None
    if coarse_frame(inp.frame, cfg).shape == level_frame(inp.frame, sides[0]).shape:
        # the first level is the transfers' level: its photos are mapped once (in this process
        # by match_brightness, else here), and the optimization's first level reuses them
        _, raw = brightness.mapped if brightness.mapped is not None else coarse_maps(photos, cfg)
        first = {
            n: (with_transfer(mp, transfers[n] if transfers else None) if mp is not None else None)
            for n, mp in raw.items()
        }
    res = optimize_polygon(photos, cfg, compute, transfers, first=first, progress=progress)
    read = {"photo_reads": photos.reads, "time_read_photos_s": 0.0, **(read_stats or {})}
    stats = dict(res.stats)
    stats.update(
        {
            "histmatch": transfers is not None,
            "histmatch_reference": brightness.reference,
            "histmatch_mode": cfg.histmatch_reference if cfg.histogram_matching else None,
            "photos_seeing": [inp.photos[n].name for n in sorted(photos.samplers)],
            "photo_reads": read["photo_reads"],
            "decode_scale": {inp.photos[n].name: s for n, s in photos.decode_scale.items()},
            "photo_bytes": photos.nbytes(),
            "time_read_photos_s": read["time_read_photos_s"],
            "time_histmatch_s": brightness.time_s,
            "corrections": {
                inp.photos[n].name: {"params": c.params.tolist(), "centre": list(c.centre), "scale": c.scale}
                for n, c in photos.corrections.items()
            },
            "time_stage_s": time.perf_counter() - t0 + read["time_read_photos_s"],
            "relief": brightness.relief_stats,
            "resolution_spread": spread,
            "mixed_resolution": mixed,
        }
    )
    return OptimizedPolygon(
        polygon_id=inp.polygon_id,
        names=[p.name for p in inp.photos],
        mask=inp.texel_mask,
        frame=inp.frame,
        U=res.U,
        weight_sum=res.W.sum(0),
        dominant=dominant_from_slots(res.idx, res.W),
        stats=stats,
        histmatch=transfers is not None,
        heights=photos.relief.at(inp.frame) * inp.texel_mask if photos.relief is not None else None,
        idx=res.idx,
        W=res.W,
        transfers=transfers,
    )


def texture_polygon(
    inp: PolygonInput,
    cfg: OptimizeConfig,
    compute: ComputeConfig = ComputeConfig(),
    progress: bool = False,
    decode: Callable[..., np.ndarray] = decode_photo,
) -> TexturedPolygon:
    """Texture one polygon: the initialization (one decode per photo), optimization and
    composition stages in one process (``decode``: ``decode_photo``, or a DecodeCache that several
    polygons of a job share)."""
    t0 = time.perf_counter()
    photos = PhotoSet.load(
        inp, pick_device(compute.device), exact_decode=cfg.exact_decode, decode=decode, supersample=cfg.supersample,
        relief_range=crop_relief_range(cfg, inp),
    )
    read = {"photo_reads": photos.reads, "time_read_photos_s": time.perf_counter() - t0}
    opt = optimize_photos(photos, cfg, compute, progress=progress, read_stats=read)
    U, seen, report = compose_polygon(opt)
    return TexturedPolygon(inp=inp, texture=U, seen=seen, optimized=opt, report=report)


def write_polygon(tp: TexturedPolygon, optimized_dir: str | Path) -> None:
    """weights.npz (slots, weights, transfers), stats.json and composite.npz (the float texture,
    its source map and report; the finish stage writes the PNGs from it), each written atomically:
    the split stages' files but optimized.npz, whose content composite.npz holds."""
    from difftex.compose.stage_files import write_composite_of, write_weights_and_stats

    out_dir = Path(optimized_dir)
    write_weights_and_stats(out_dir, tp.optimized)
    write_composite_of(out_dir / COMPOSITE, tp.optimized, tp.texture, tp.seen, tp.report)
