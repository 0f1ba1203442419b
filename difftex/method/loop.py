"""The coarse-to-fine optimization of one polygon's blend weights W (Sec. 4.2-4.3).

For each level, from ``long_side_start`` times ``level_step`` (the paper: from 256, doubling) up
to the target: build the level (top-K candidates, Q init or the coarser level's weights
upsampled), then Adam steps on L with the activation update, pixel elimination and photo drop
between them, until the weights stop changing or the level's iteration cap.
"""

from __future__ import annotations

import functools
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from rich.console import Console
from rich.progress import MofNCompleteColumn, Progress

from difftex.geometry.frames import level_sides
from difftex.method import alignment, detail, diagnostics, losses, parallax, selection
from difftex.method.config import ComputeConfig, OptimizeConfig
from difftex.method.elimination import (
    settled_texels,
)
from difftex.method.level_run import run_level
from difftex.method.levels import Level, build_level, tilt_axis, upsample_field
from difftex.method.objective import (
    LevelState,
)
from difftex.method.render import build_pixel_sets
from difftex.sampling.crops import PolygonInput, median_elevation
from difftex.sampling.photos import MappedPhoto, PhotoSet
from difftex.sampling.texels import level_frame, resample_nearest


@dataclass
class Result:
    """Optimized weights at the target level, the composed texture and the run's statistics."""

    idx: np.ndarray  # (K, H, W) int, photo index into PolygonInput.photos, -1 empty
    W: np.ndarray  # (K, H, W) float32 normalised blend weights (0 where inactive)
    U: np.ndarray  # (H, W, 3) the composed texture at the target level
    stats: dict


def _no_progress(n: float) -> None:
    pass


def optimize_polygon(
    photos: PhotoSet,
    cfg: OptimizeConfig,
    compute: ComputeConfig = ComputeConfig(),
    transfers: list | None = None,
    first: dict[int, MappedPhoto | None] | None = None,
    progress: bool = False,
) -> Result:
    """Run DiffTex for one polygon; returns weights and texture at the target resolution.

    Args:
        photos: the polygon's decoded candidate photos.
        transfers: per photo brightness transfer (or None), applied to every mapped colour.
        first: the first level's photos already mapped with ``transfers`` (reused, not re-mapped).
    """
    torch.manual_seed(cfg.seed)
    inp, device = photos.inp, photos.device
    t_start = time.perf_counter()
    stats = _start_stats(inp, cfg, device)
    sides = level_sides(max(inp.frame.shape), cfg.long_side_start, cfg.coarse_to_fine, cfg.level_step)
    dropped: set[int] = set()
    prev: LevelState | None = None
    # Iterations against the levels' caps, on stderr, gone when done, and only on a terminal (a
    # transient rich bar still writes an empty line to a log). Without it, advancing costs nothing.
    console = Console(stderr=True)
    show = progress and console.is_terminal
    bar = Progress(*Progress.get_default_columns(), MofNCompleteColumn(), console=console, transient=True,
                   disable=not show)
    advance: Callable[[float], None] = _no_progress
    if show:
        total = sum(cfg.cap(i) for i in range(len(sides)))
        advance = functools.partial(bar.advance, bar.add_task(f"optimize {inp.polygon_id}", total=total))
    bar.start()
    stats["alignment"] = []
    aligning, first_fit = cfg.align, True
    try:
        for li, side in enumerate(sides):
            tl = time.perf_counter()
            frame = level_frame(inp.frame, side)
            aligned = False
            if aligning and cfg.align_min_long_side <= side <= cfg.align_max_long_side:
                rep = _align(photos, frame, transfers, prev, cfg, first=first_fit)
                stats["alignment"].append(rep)
                aligned = "skipped" not in rep
                # Converged: the corrections no longer move at this resolution; finer levels
                # would refit the same ones at the cost of mapping every photo again.
                aligning = first_fit or rep["max_update_px"] > cfg.align_tol_px
                first_fit = False
            lv = build_level(
                photos,
                frame,
                cfg,
                transfers,
                dropped=dropped,
                mapped=first if li == 0 and not aligned else None,
                # the normalised blend W, whatever the parameters: every level starts from weights
                # that sum to one per texel (the paper upsamples "the parameter field")
                prev=(prev.level, losses.blend_weights(prev.z, prev.active, cfg.weights)) if prev is not None else None,
            )
            if cfg.use_render and cfg.loss_mode == "render":
                lv.pixel_sets = build_pixel_sets(photos, lv, transfers, cfg.render_scale)
            t_setup = time.perf_counter() - tl
            st, lvl_stats = run_level(lv, li, cfg, compute, dropped, stats, advance)
            lvl_stats.update(
                {"long_side": side, "time_setup_s": t_setup, "time_s": time.perf_counter() - tl, "photo_maps": lv.maps}
            )
            stats["levels"].append(lvl_stats)
            prev = st
    finally:
        bar.stop()
    assert prev is not None
    lv = prev.level
    W, U = _final_weights(prev, cfg, stats, len(inp.photos))
    _final_diagnostics(stats, inp, lv, W, U)
    stats["time_total_s"] = time.perf_counter() - t_start
    if device.type == "cuda":
        stats["cuda_peak_bytes"] = int(torch.cuda.max_memory_allocated(device))
    return Result(
        idx=lv.idx.cpu().numpy().astype(np.int32),
        W=W.cpu().numpy().astype(np.float32),
        U=U.permute(1, 2, 0).cpu().numpy(),
        stats=stats,
    )


def _start_stats(inp: PolygonInput, cfg: OptimizeConfig, device: torch.device) -> dict:
    """A polygon's stats.json before its levels run: what ran, on what, from which photos."""
    return {
        "polygon_id": inp.polygon_id,
        "device": str(device),
        "photos": [p.name for p in inp.photos],
        "levels": [],
        "dropped": [],
        "config": cfg.to_dict(),
        # which method ran: the keys where it is not the published one (config.PUBLISHED; none
        # with preset paper), and the weights' parametrisation
        "departures_from_paper": cfg.departures(),
        "weights": cfg.weights,
        # the photos' median elevation (degrees, photos in front, seen from the centre) and
        # whether the tilt frontality weighs this polygon's blend: it does only above its limit
        "photo_elevation_deg": median_elevation(inp, 0.0),
        "frontality_tilt_on": tilt_axis(inp, cfg) is not None,
    }


def _final_weights(
    prev: LevelState, cfg: OptimizeConfig, stats: dict, n_photos: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """The finest level's blend weights W and texture U (3, h, w), after the optional parallax
    gate and view-coherent selection (with its detail band); their reports go into ``stats``."""
    lv = prev.level
    with torch.no_grad():
        W = losses.blend_weights(prev.z, prev.active, cfg.weights)
        if cfg.parallax_sigma > 0:
            W, stats["parallax"] = parallax.parallax_weights(
                W, lv.sharp, lv.cost, lv.sharp_noise, cfg.parallax_sigma, cfg.parallax_gate, lv.idx
            )
        blend = W
        if cfg.select:
            free = None  # select_scope "all": every texel
            if cfg.select_scope == "disagree":
                free = lv.mask & ~settled_texels(lv, prev.active, prev.active, cfg.settle_sigma)[0]
            W, stats["selection"] = selection.select_weights(
                W, lv.Q, lv.idx, lv.mask, n_photos, cfg.select_patch, cfg.select_smoothness,
                cfg.select_feather, free=free,
            )
        U = losses.compose(W, lv.sharp)
        if cfg.select and cfg.select_band > 0:
            # the band's low-pass over the texels some photo sees: the unseen ones (filled later)
            # would pull both low-passes towards zero and leave part of the selected photo's exposure
            seen = lv.mask & (blend.sum(0) > 0)
            U = selection.detail_band(losses.compose(blend, lv.sharp), U, seen, cfg.select_band)
        if cfg.detail == "all":  # "mixed" is "all" on a mixed-resolution polygon (OptimizeConfig.for_spread)
            assert lv.resolve is not None  # the level keeps it with cfg.detail
            seen = lv.mask & (blend.sum(0) > 0)
            U, _, stats["detail"] = detail.detail_texture(
                U, lv.sharp, lv.idx, lv.visible, lv.resolve, seen, lv.sharp_noise, cfg.detail_settings()
            )
    return W, U


def _final_diagnostics(stats: dict, inp: PolygonInput, lv: Level, W: torch.Tensor, U: torch.Tensor) -> None:
    """The texture's diagnostics (effective photos, sharpness, misalignment; photo names, not
    indices), coverage, texel count and the photos it uses, into ``stats``."""
    lmask = lv.mask
    stats["diagnostics"] = {
        **diagnostics.effective_photos(W, lmask),
        "sharpness": diagnostics.sharpness(U, lv.sharp, lv.idx, lv.visible, lmask),
        "misalignment_texels": diagnostics.misalignment(U, lv.sharp, lv.idx, lv.visible, W, lmask),
    }
    for key in ("sharpness", "misalignment_texels"):  # photo indices to names
        d = stats["diagnostics"][key]
        if key == "sharpness" and d.get("photo") is not None:
            d["photo"] = inp.photos[d["photo"]].name
        if key == "misalignment_texels":
            stats["diagnostics"][key] = {(inp.photos[k].name if isinstance(k, int) else k): v for k, v in d.items()}
    mask = inp.texel_mask
    has = (W.sum(0) > 0).cpu().numpy() & mask
    stats["coverage"] = float(has.sum() / max(mask.sum(), 1))
    stats["texels"] = int(mask.sum())
    stats["used_photos"] = sorted({inp.photos[int(n)].name for n in torch.unique(lv.idx[(W > 0)]).tolist() if n >= 0})


def _align(
    photos: PhotoSet, frame, transfers, prev: LevelState | None, cfg: OptimizeConfig, first: bool = True
) -> dict:
    """Refine the photos' mapping corrections at this level against the consensus texture: the
    per-texel median of every candidate at the first aligned level (``first``: the first level,
    or the first from ``align_min_long_side``); after it, by ``align_consensus``, the previous
    level's texture upsampled, its blend of the photos mapped at this level, or their median.

    After the first aligned level only the photos that hold weight somewhere (> tau) are refined:
    the others do not appear in the texture, and a photo that comes back keeps its last correction.
    """
    t0 = time.perf_counter()
    inp = photos.inp
    mask = resample_nearest(inp.texel_mask, inp.frame, frame)
    which = None
    if prev is not None and not first:
        W = losses.blend_weights(prev.z, prev.active, cfg.weights)
        which = set(torch.unique(prev.level.idx[(W > cfg.tau) & prev.level.visible]).tolist()) - {-1}
    refined = len(photos.samplers) if which is None else len(which)
    if refined < cfg.align_min_photos:  # too few to tell pose errors from relief: registration kept
        return {"long_side": max(frame.shape), "photos": {}, "aligned": 0, "max_update_px": 0.0,
                "skipped": f"{refined} photos to refine, fewer than align_min_photos", "time_s": 0.0}
    if first or cfg.align_consensus == "median":
        consensus, defined = alignment.consensus_median(photos, frame, mask, transfers)
        noise = 0.05 if prev is None else prev.level.sharp_noise
    else:
        assert prev is not None  # only the first aligned level can have none
        plv = prev.level
        defined = upsample_field((plv.visible.sum(0) >= 2).float()[None], plv.frame, frame)[0] > 0.99
        noise = plv.sharp_noise
        if cfg.align_consensus == "blend":
            def weight_of(n: int) -> torch.Tensor:  # one photo's W, upsampled: one (h, w) map at a time
                return upsample_field((W * (plv.idx == n)).sum(0)[None], plv.frame, frame)[0]

            held = [n for n in torch.unique(plv.idx[W > 0]).tolist() if n >= 0]
            consensus, seen = alignment.consensus_blend(photos, frame, mask, transfers, held, weight_of)
            defined = defined & seen
        else:
            U = losses.compose(W, plv.sharp)  # registration needs the full detail
            consensus = upsample_field(U, plv.frame, frame)
    st = alignment.AlignSettings(
        cfg.align_model, cfg.align_iterations, cfg.align_prior_px, cfg.align_max_px, max(noise, cfg.sigma_min),
        cfg.align_gauge, cfg.align_robust, cfg.align_points,
    )
    report = alignment.align_level(
        photos, frame, mask, transfers, consensus, defined & torch.from_numpy(mask).to(defined.device), st, which
    )
    moved = [r["update_px"] for r in report.values()]
    return {"long_side": max(frame.shape), "photos": report, "aligned": len(report),
            "max_update_px": max(moved, default=0.0), "time_s": time.perf_counter() - t0}


def photo_weight(idx: np.ndarray, W: np.ndarray, n: int) -> np.ndarray:
    """Photo n's blend weight per texel (H, W) from the slot layout."""
    return (W * (idx == n)).sum(0)
