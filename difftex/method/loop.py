"""The coarse-to-fine optimization of one polygon's blend weights W (Sec. 4.2-4.3).

For each level, from ``long_side_start`` times ``level_step`` (the paper: from 256, doubling) up
to the target: build the level (top-K candidates, Q init or the coarser level's weights
upsampled), then Adam steps on L with the activation update, pixel elimination and photo drop
between them, until the weights stop changing or the level's iteration cap.
"""

from __future__ import annotations

import functools
import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from rich.console import Console
from rich.progress import MofNCompleteColumn, Progress

from difftex.geometry.frames import level_sides
from difftex.method import alignment, diagnostics, losses, parallax, selection, sparse
from difftex.method.config import ComputeConfig, OptimizeConfig
from difftex.method.elimination import (
    base_mask,
    dropped_slot_mask,
    eliminate_pixels,
    photo_zero_share,
    photos_to_drop,
    settled_counts,
    settled_texels,
    update_activation,
)
from difftex.method.gradient import Adam
from difftex.method.levels import Level, build_level, tilt_axis, upsample_field
from difftex.method.objective import (
    LevelState,
    compiled_objective,
    ghost_margin,
    objective,
    render_weights,
    value_and_grad,
)
from difftex.method.render import build_pixel_sets
from difftex.sampling.crops import median_elevation
from difftex.sampling.photos import MappedPhoto, PhotoSet
from difftex.sampling.texels import level_frame, resample_nearest

LOSS_KEYS = ("total", "render", "ghost", "sparsity", "persp", "para")


@dataclass
class Result:
    """Optimized weights at the target level, the composed texture and the run's statistics."""

    idx: np.ndarray  # (K, H, W) int, photo index into PolygonInput.photos, -1 empty
    W: np.ndarray  # (K, H, W) float32 normalised blend weights (0 where inactive)
    U: np.ndarray  # (H, W, 3) the composed texture at the target level
    stats: dict


SPARSE_MAX_SHARE = 0.5  # iterate on the free texels' sub-level when they are at most this share


def weight_change(
    W: torch.Tensor, W_old: torch.Tensor, mask: torch.Tensor, q: float = 0.99, fixed_share: float = 0.0
) -> float:
    """The ``q`` quantile over the polygon's texels of the total-variation distance between two
    sets of blend weights: sum_k |W_k - W'_k| / 2 is the share of a texel's weight that moved.

    ``fixed_share``: the share of the polygon's texels that are not in ``mask`` and did not move
    (the settled texels when W is the free texels' sub-level): the quantile is the polygon's.
    """
    return _quantile(0.5 * (W - W_old).abs().sum(0), mask, q, fixed_share)


def colour_change(
    W: torch.Tensor, W_old: torch.Tensor, colours: torch.Tensor, mask: torch.Tensor, q: float = 0.99,
    fixed_share: float = 0.0,
) -> float:
    """The ``q`` quantile over the polygon's texels of how far the blended colour moved (RGB
    distance) between two sets of blend weights over the same slots' colours (K, 3, h, w)."""
    dU = ((W - W_old)[:, None] * colours).sum(0)
    return _quantile(dU.norm(dim=0), mask, q, fixed_share)


def _quantile(d: torch.Tensor, mask: torch.Tensor, q: float, fixed_share: float) -> float:
    """The ``q`` quantile of ``d`` over ``mask``, counting ``fixed_share`` of the polygon's texels
    outside ``mask`` as zeros."""
    if fixed_share > 0.0:
        if q <= fixed_share:
            return 0.0
        q = (q - fixed_share) / (1.0 - fixed_share)
    d = d[mask]
    if d.numel() == 0:
        return 0.0
    if d.numel() > 1 << 20:  # torch.quantile's input limit: a strided sample is as good
        d = d[:: d.numel() // (1 << 20) + 1]
    return float(torch.quantile(d.float(), q))


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
    stats: dict = {
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
            st, lvl_stats = _run_level(lv, li, cfg, compute, dropped, stats, advance)
            lvl_stats.update(
                {"long_side": side, "time_setup_s": t_setup, "time_s": time.perf_counter() - tl, "photo_maps": lv.maps}
            )
            stats["levels"].append(lvl_stats)
            prev = st
    finally:
        bar.stop()
    assert prev is not None
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
                W, lv.Q, lv.idx, lv.mask, len(inp.photos), cfg.select_patch, cfg.select_smoothness,
                cfg.select_feather, free=free,
            )
        U = losses.compose(W, lv.sharp)
        if cfg.select and cfg.select_band > 0:
            # the band's low-pass over the texels some photo sees: the unseen ones (filled later)
            # would pull both low-passes towards zero and leave part of the selected photo's exposure
            seen = lv.mask & (blend.sum(0) > 0)
            U = selection.detail_band(losses.compose(blend, lv.sharp), U, seen, cfg.select_band)
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
    stats["time_total_s"] = time.perf_counter() - t_start
    if device.type == "cuda":
        stats["cuda_peak_bytes"] = int(torch.cuda.max_memory_allocated(device))
    return Result(
        idx=lv.idx.cpu().numpy().astype(np.int32),
        W=W.cpu().numpy().astype(np.float32),
        U=U.permute(1, 2, 0).cpu().numpy(),
        stats=stats,
    )


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


def _evaluate(cur: LevelState, sp: sparse.SparseLevel | None, cfg: OptimizeConfig, fn, refresh: bool):
    """The terms of L and dL/dz on the level, or on its free texels' sub-level ``sp``."""
    if sp is not None:
        return sparse.value_and_grad(sp, cur.z, cur.active, cfg, refresh, fn)
    return value_and_grad(cur, cfg, fn)


def _run_level(
    lv: Level, li: int, cfg: OptimizeConfig, compute: ComputeConfig, dropped: set[int], stats: dict,
    advance: Callable[[float], None],
) -> tuple[LevelState, dict]:
    """Adam iterations at one level with activation updates, pixel elimination and photo drop."""
    N = len(stats["photos"])
    mode = cfg.weights  # the parameters: logits (softmax) or the paper's weights (normalised)
    eliminated = torch.zeros_like(lv.visible)
    drop_slots = dropped_slot_mask(lv, eliminated, dropped)
    z = lv.z0.clone()
    base = base_mask(lv, eliminated, drop_slots)
    st = LevelState(level=lv, z=z, active=update_activation(z, base, cfg.tau, mode), eliminated=eliminated)
    adam = Adam(lr=cfg.lr, betas=cfg.betas)
    hist: dict[str, list] = {k: [] for k in LOSS_KEYS}
    n_elim = 0
    dropped_here: list[str] = []
    converged = False
    cap = cfg.cap(li)
    it = 0
    if cfg.data_elimination:
        with torch.no_grad():
            e = eliminate_pixels(lv, st.active, losses.blend_weights(st.z, st.active, mode), cfg)
            st.eliminated |= e
            n_elim += int(e.sum())
            drop_slots = dropped_slot_mask(lv, st.eliminated, dropped)
            base = base_mask(lv, st.eliminated, drop_slots)
            st.active = update_activation(st.z, base, cfg.tau, mode, st.active)
    free = None  # (1, h, w) float: 1 where the weights are optimized (None: everywhere)
    free_mask = lv.mask  # the texels L_Para couples
    settled_share = 0.0
    if cfg.settle_sigma > 0:
        with torch.no_grad():
            settled, agree = settled_texels(lv, st.active, base, cfg.settle_sigma)
            # the Q blend of the candidates that agree: Q x base would bring back the photos the
            # coarser level or the first elimination left out for disagreeing (an occluder)
            st.z = torch.where(settled[None], losses.init_weights(lv.blend_Q * agree, mode), st.z)
            st.active = update_activation(st.z, base, cfg.tau, mode, st.active)
            free = (~settled).to(st.z.dtype)[None]
            settled_share = float(settled.sum()) / lv.n_tex
            # L_Para couples free texels only: a seam against a settled texel, whose photos
            # agree, shows nothing, so the free texels choose as if their settled neighbours
            # were any of their photos (not the blend the settled texels keep)
            free_mask = lv.mask & ~settled
    if cfg.use_para:
        st.matches = {a: losses.neighbour_match(lv.idx, free_mask, a, fixed=lv.fixed_slots) for a in (1, 2)}
    anything = (cfg.use_render or cfg.use_persp or cfg.use_para) and settled_share < 1.0
    # every texel settled: the weights are final, nothing is left to iterate (a level that
    # converges without an iteration, not one cut at its cap)
    converged = settled_share >= 1.0
    # The iterations run on ``cur``: the level, or the sub-level of its free texels
    # (difftex.method.sparse) when most texels are settled and the loss is the texel one.
    sp = None
    cur, lvc, extra = st, lv, None
    if free is not None and anything and not cfg.autograd and 1.0 - settled_share <= SPARSE_MAX_SHARE:
        with torch.no_grad():
            sp = sparse.sparse_level(lv, free_mask, render_weights(lv, cfg), ghost_margin(lv, cfg))
            lvc = sp.sub
            cur = LevelState(level=lvc, z=sparse.gather(st.z, sp.src), active=sparse.gather(st.active, sp.src),
                             eliminated=sparse.gather(st.eliminated, sp.src))
            # the photo drop counts the settled texels as they stand (they do not change)
            extra = settled_counts(lv, base, losses.selection_weights(st.z, base, mode), cfg.tau, N, settled)
            drop_slots = sparse.gather(drop_slots, sp.src)
            base = sparse.gather(base, sp.src)
            free = None
    fn = compiled_objective(lvc, cfg, compute)
    if fn is None and cfg.autograd:
        fn = objective  # autograd needs the function; the texel loss has its own gradient
    iter_times: list[float] = []
    W_check = losses.blend_weights(st.z, st.active, mode)
    dominant_start = diagnostics.dominant_photo(lv.idx, W_check)
    if sp is not None:
        W_check = losses.blend_weights(cur.z, cur.active, mode)
    fixed_share = settled_share if sp is not None else 0.0  # texels outside ``cur`` that do not move
    changes: list[float] = []
    colour_moves: list[float] = []  # conv_colour: the blend's colour change per window, in sigma_c
    for it in range(1, cap + 1 if anything else 1):
        cur.it = it
        t_it = time.perf_counter()
        due = it % max(cfg.eliminate_every, 1) == 0  # L_Para's edge weights are refreshed
        try:
            terms, grad = _evaluate(cur, sp, cfg, fn, due)
        except Exception as e:  # noqa: BLE001 - compilation needs a C++ toolchain; eager always works
            if fn is None or fn is objective:
                raise
            reason = f"{type(e).__name__}: {str(e).splitlines()[0][:200]}"
            warnings.warn(f"torch.compile failed ({reason}); running eagerly", stacklevel=2)
            stats["compile_failed"] = reason
            fn = objective if cfg.autograd else None
            terms, grad = _evaluate(cur, sp, cfg, fn, True)
        for k in hist:
            hist[k].append(float(terms[k]) if k in terms else 0.0)
        with torch.no_grad():
            assert grad is not None  # fn is set, so the gradient is
            if free is not None:
                grad = grad * free  # settled texels keep their blend
            adam.step(cur.z, grad)
            losses.project_weights(cur.z, mode)  # the paper's weights stay in [0, 1]
            W = losses.selection_weights(cur.z, base, mode)
            if cfg.data_elimination:
                if it >= cfg.min_iters_per_level // 2:
                    cand = [n for n in photos_to_drop(lvc, base, W, cfg.tau, cfg.tau_w, N, extra) if n not in dropped]
                    if cand:
                        # one photo per check (the worst): dropping changes everyone's weights
                        shares = photo_zero_share(lvc, base, W, cfg.tau, N, extra)
                        n = max(cand, key=lambda k: (float(shares[k]), -k))
                        dropped.add(n)
                        dropped_here.append(stats["photos"][n])
                        stats["dropped"].append({"photo": stats["photos"][n], "level": li, "iteration": it})
                        drop_slots = dropped_slot_mask(lvc, cur.eliminated, dropped, W)
                if it % max(cfg.eliminate_every, 1) == 0:
                    elim = eliminate_pixels(lvc, cur.active, losses.blend_weights(cur.z, cur.active, mode), cfg)
                    cur.eliminated |= elim
                    n_elim += int(elim.sum())
                    if dropped:
                        drop_slots = dropped_slot_mask(lvc, cur.eliminated, dropped, W)
            base = base_mask(lvc, cur.eliminated, drop_slots)
            cur.active = update_activation(cur.z, base, cfg.tau, mode, cur.active)
        iter_times.append(time.perf_counter() - t_it)
        advance(1)
        if it % cfg.conv_window == 0:
            # Converged: over the last conv_window iterations almost every texel (99 %) moved
            # less than conv_tol of its weight.
            W_now = losses.blend_weights(cur.z, cur.active, mode)
            changes.append(weight_change(W_now, W_check, lvc.mask, fixed_share=fixed_share))
            if cfg.conv_colour > 0:
                moved = colour_change(W_now, W_check, lvc.colours, lvc.mask, fixed_share=fixed_share)
                colour_moves.append(moved / max(lvc.noise, 1e-12))
            W_check = W_now
            still = changes[-1] >= cfg.conv_tol and not (colour_moves and colour_moves[-1] < cfg.conv_colour)
            if it >= cfg.min_iters_per_level and not still:
                converged = True
                break
    if it < cap:
        advance(cap - it)
    if sp is not None:
        with torch.no_grad():  # the free texels back into the level; drops reach the settled ones too
            sparse.scatter_into(st.z, cur.z, sp.src)
            sparse.scatter_into(st.eliminated, cur.eliminated, sp.src)
            W_full = losses.blend_weights(st.z, st.active, mode)
            full_drop = dropped_slot_mask(lv, st.eliminated, dropped, W_full)
            st.active = update_activation(st.z, base_mask(lv, st.eliminated, full_drop), cfg.tau, mode, st.active)
    final_terms = {k: float(v) for k, v in value_and_grad(st, cfg)[0].items()}
    W_end = losses.blend_weights(st.z, st.active, mode)
    lvl_stats = {
        "level": li,
        "shape": list(lv.frame.shape),
        "top_k": lv.idx.shape[0],
        "candidates": lv.n_candidates,
        "iterations": it if anything else 0,
        "cap": cap,
        "converged": converged,
        # the first iteration carries torch.compile's cost; the median of the rest is the steady rate
        "time_first_iter_s": iter_times[0] if iter_times else 0.0,
        "time_per_iter_s": float(np.median(iter_times[1:]))
        if len(iter_times) > 1
        else (iter_times[0] if iter_times else 0.0),
        "eliminated_pixels": n_elim,
        "dropped_photos": dropped_here,
        "settled_share": settled_share,
        "noise": lv.noise,  # sigma_c: L_Render's unit and the settling threshold's
        "compare_sigma": lv.compare_sigma,  # the comparisons' low-pass, texels (consistency_sigma / _px)
        # texels the iterations ran on against the level's (1: the whole level, not the sub-level)
        "evaluated_share": sp.src.numel() / lv.mask.numel() if sp is not None else 1.0,
        "active_slots_mean": float(st.active.sum(0).float()[lv.mask].mean()) if bool(lv.mask.any()) else 0.0,
        "tensor_bytes": lv.nbytes(),
        "final": final_terms,
        "loss": hist,
        "v_tilde": lv.v_tilde.tolist(),
        "compiled": fn is not None and fn is not objective,
        "weight_change": changes,
        **({"colour_change_sigma": colour_moves} if cfg.conv_colour > 0 else {}),
        **diagnostics.effective_photos(W_end, lv.mask),
        "dominant_changed": diagnostics.changed_share(
            dominant_start, diagnostics.dominant_photo(lv.idx, W_end), lv.mask
        ),
    }
    if lv.pixel_sets is not None:
        lvl_stats["render_pixels"] = lv.pixel_sets.n
        lvl_stats["render_bytes"] = int(
            sum(t.element_size() * t.numel() for t in vars(lv.pixel_sets).values() if isinstance(t, torch.Tensor))
        )
    return st, lvl_stats


def photo_weight(idx: np.ndarray, W: np.ndarray, n: int) -> np.ndarray:
    """Photo n's blend weight per texel (H, W) from the slot layout."""
    return (W * (idx == n)).sum(0)
