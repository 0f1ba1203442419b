"""One level's iterations (Sec. 4.3): Adam on the weights with activation updates (tau), pixel
elimination and photo drop (tau_w), the settled texels kept at their blend and the iterations
run on the free texels' sub-level when few are left (difftex.method.sparse), until the weights
stop moving (``conv_tol``, ``conv_colour``) or the level's cap. difftex.method.loop runs the
levels of a polygon.
"""

from __future__ import annotations

import time
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import torch

from difftex.method import diagnostics, losses, sparse
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
from difftex.method.levels import Level
from difftex.method.objective import (
    LevelState,
    compiled_objective,
    ghost_margin,
    objective,
    render_weights,
    value_and_grad,
)

LOSS_KEYS = ("total", "render", "ghost", "sparsity", "persp", "para")
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


def _evaluate(cur: LevelState, sp: sparse.SparseLevel | None, cfg: OptimizeConfig, fn, refresh: bool):
    """The terms of L and dL/dz on the level, or on its free texels' sub-level ``sp``."""
    if sp is not None:
        return sparse.value_and_grad(sp, cur.z, cur.active, cfg, refresh, fn)
    return value_and_grad(cur, cfg, fn)


@dataclass
class _Run:
    """What one level's run records as it goes, for its stats."""

    cap: int
    iterations: int = 0
    converged: bool = False
    eliminated: int = 0  # pixels eliminated
    dropped: list[str] = field(default_factory=list)  # photos dropped at this level
    loss: dict[str, list] = field(default_factory=lambda: {k: [] for k in LOSS_KEYS})
    iter_times: list[float] = field(default_factory=list)
    changes: list[float] = field(default_factory=list)  # weight change per convergence window
    colour_moves: list[float] = field(default_factory=list)  # the blend's colour change per window, in sigma_c
    compiled: bool = False


def _eliminate_first(lv: Level, st: LevelState, cfg: OptimizeConfig, dropped: set[int], run: _Run):
    """Pixel elimination before the first iteration, on the initial weights. Returns the drop
    slots and the base mask after it."""
    mode = cfg.weights
    with torch.no_grad():
        e = eliminate_pixels(lv, st.active, losses.blend_weights(st.z, st.active, mode), cfg)
        st.eliminated |= e
        run.eliminated += int(e.sum())
        drop_slots = dropped_slot_mask(lv, st.eliminated, dropped)
        base = base_mask(lv, st.eliminated, drop_slots)
        st.active = update_activation(st.z, base, cfg.tau, mode, st.active)
    return drop_slots, base


def _settle(lv: Level, st: LevelState, base: torch.Tensor, cfg: OptimizeConfig):
    """Settle the texels whose candidates agree (``settle_sigma``) at their Q blend. Returns the
    settled texels (h, w) bool, the free texels as (1, h, w) float and the mask L_Para couples."""
    mode = cfg.weights
    with torch.no_grad():
        settled, agree = settled_texels(lv, st.active, base, cfg.settle_sigma)
        # the Q blend of the candidates that agree: Q x base would bring back the photos the
        # coarser level or the first elimination left out for disagreeing (an occluder)
        st.z = torch.where(settled[None], losses.init_weights(lv.blend_Q * agree, mode), st.z)
        st.active = update_activation(st.z, base, cfg.tau, mode, st.active)
    # L_Para couples free texels only: a seam against a settled texel, whose photos agree, shows
    # nothing, so the free texels choose as if their settled neighbours were any of their photos
    # (not the blend the settled texels keep)
    return settled, (~settled).to(st.z.dtype)[None], lv.mask & ~settled


def _drop_and_eliminate(
    lvc: Level, cur: LevelState, base: torch.Tensor, W: torch.Tensor, it: int, cfg: OptimizeConfig,
    dropped: set[int], extra, drop_slots: torch.Tensor, run: _Run, li: int, stats: dict,
) -> torch.Tensor:
    """After iteration ``it``: drop the worst photo that tau_w says to (one per check: dropping
    changes everyone's weights), and every ``eliminate_every`` iterations eliminate pixels.
    Returns the drop slots."""
    photos = stats["photos"]
    N = len(photos)
    if it >= cfg.min_iters_per_level // 2:
        cand = [n for n in photos_to_drop(lvc, base, W, cfg.tau, cfg.tau_w, N, extra) if n not in dropped]
        if cand:
            shares = photo_zero_share(lvc, base, W, cfg.tau, N, extra)
            n = max(cand, key=lambda k: (float(shares[k]), -k))
            dropped.add(n)
            run.dropped.append(photos[n])
            stats["dropped"].append({"photo": photos[n], "level": li, "iteration": it})
            drop_slots = dropped_slot_mask(lvc, cur.eliminated, dropped, W)
    if it % max(cfg.eliminate_every, 1) == 0:
        elim = eliminate_pixels(lvc, cur.active, losses.blend_weights(cur.z, cur.active, cfg.weights), cfg)
        cur.eliminated |= elim
        run.eliminated += int(elim.sum())
        if dropped:
            drop_slots = dropped_slot_mask(lvc, cur.eliminated, dropped, W)
    return drop_slots


def _sparse_sublevel(
    lv: Level, st: LevelState, cfg: OptimizeConfig, free_mask: torch.Tensor, settled: torch.Tensor,
    drop_slots: torch.Tensor, base: torch.Tensor, N: int,
):
    """The free texels' sub-level (difftex.method.sparse) and its state, gathered from the
    level's. Returns (sub-level, its state, the settled texels' counts for the photo drop, the
    drop slots and base mask on the sub-level)."""
    with torch.no_grad():
        sp = sparse.sparse_level(lv, free_mask, render_weights(lv, cfg), ghost_margin(lv, cfg))
        cur = LevelState(level=sp.sub, z=sparse.gather(st.z, sp.src), active=sparse.gather(st.active, sp.src),
                         eliminated=sparse.gather(st.eliminated, sp.src))
        # the photo drop counts the settled texels as they stand (they do not change)
        extra = settled_counts(lv, base, losses.selection_weights(st.z, base, cfg.weights), cfg.tau, N, settled)
        return sp, cur, extra, sparse.gather(drop_slots, sp.src), sparse.gather(base, sp.src)


def _still_moving(
    W_now: torch.Tensor, W_check: torch.Tensor, lvc: Level, cfg: OptimizeConfig, fixed_share: float, run: _Run,
) -> bool:
    """Whether the weights still move over the last convergence window (recorded in ``run``):
    converged when almost every texel (99 %) moved less than ``conv_tol`` of its weight, or its
    blended colour less than ``conv_colour`` sigma_c."""
    run.changes.append(weight_change(W_now, W_check, lvc.mask, fixed_share=fixed_share))
    if cfg.conv_colour > 0:
        moved = colour_change(W_now, W_check, lvc.colours, lvc.mask, fixed_share=fixed_share)
        run.colour_moves.append(moved / max(lvc.noise, 1e-12))
    return run.changes[-1] >= cfg.conv_tol and not (run.colour_moves and run.colour_moves[-1] < cfg.conv_colour)


def _level_record(
    lv: Level, li: int, st: LevelState, cfg: OptimizeConfig, run: _Run, anything: bool, settled_share: float,
    sp: sparse.SparseLevel | None, dominant_start: torch.Tensor,
) -> dict:
    """The level's entry in stats.json."""
    final_terms = {k: float(v) for k, v in value_and_grad(st, cfg)[0].items()}
    W_end = losses.blend_weights(st.z, st.active, cfg.weights)
    times = run.iter_times
    rec = {
        "level": li,
        "shape": list(lv.frame.shape),
        "top_k": lv.idx.shape[0],
        "candidates": lv.n_candidates,
        "iterations": run.iterations if anything else 0,
        "cap": run.cap,
        "converged": run.converged,
        # the first iteration carries torch.compile's cost; the median of the rest is the steady rate
        "time_first_iter_s": times[0] if times else 0.0,
        "time_per_iter_s": float(np.median(times[1:])) if len(times) > 1 else (times[0] if times else 0.0),
        "eliminated_pixels": run.eliminated,
        "dropped_photos": run.dropped,
        "settled_share": settled_share,
        "noise": lv.noise,  # sigma_c: L_Render's unit and the settling threshold's
        "compare_sigma": lv.compare_sigma,  # the comparisons' low-pass, texels (consistency_sigma / _px)
        # texels the iterations ran on against the level's (1: the whole level, not the sub-level)
        "evaluated_share": sp.src.numel() / lv.mask.numel() if sp is not None else 1.0,
        "active_slots_mean": float(st.active.sum(0).float()[lv.mask].mean()) if bool(lv.mask.any()) else 0.0,
        "tensor_bytes": lv.nbytes(),
        "final": final_terms,
        "loss": run.loss,
        "v_tilde": lv.v_tilde.tolist(),
        "compiled": run.compiled,
        "weight_change": run.changes,
        **({"colour_change_sigma": run.colour_moves} if cfg.conv_colour > 0 else {}),
        **diagnostics.effective_photos(W_end, lv.mask),
        "dominant_changed": diagnostics.changed_share(
            dominant_start, diagnostics.dominant_photo(lv.idx, W_end), lv.mask
        ),
    }
    if lv.pixel_sets is not None:
        rec["render_pixels"] = lv.pixel_sets.n
        rec["render_bytes"] = int(
            sum(t.element_size() * t.numel() for t in vars(lv.pixel_sets).values() if isinstance(t, torch.Tensor))
        )
    return rec


def run_level(
    lv: Level, li: int, cfg: OptimizeConfig, compute: ComputeConfig, dropped: set[int], stats: dict,
    advance: Callable[[float], None],
) -> tuple[LevelState, dict]:
    """Adam iterations at one level with activation updates, pixel elimination and photo drop.

    Args:
        lv: the level.
        li: its index (0: the coarsest).
        cfg: the optimizer config; ``compute``: the device and compilation settings.
        dropped: the photos dropped so far (updated in place).
        stats: the polygon's stats (its ``photos``; ``dropped`` and ``compile_failed`` are added to).
        advance: the progress bar's step, called once per iteration of the cap.

    Returns:
        The level's final state and its stats.json entry.
    """
    N = len(stats["photos"])
    mode = cfg.weights  # the parameters: logits (softmax) or the paper's weights (normalised)
    eliminated = torch.zeros_like(lv.visible)
    drop_slots = dropped_slot_mask(lv, eliminated, dropped)
    z = lv.z0.clone()
    base = base_mask(lv, eliminated, drop_slots)
    st = LevelState(level=lv, z=z, active=update_activation(z, base, cfg.tau, mode), eliminated=eliminated)
    adam = Adam(lr=cfg.lr, betas=cfg.betas)
    run = _Run(cap=cfg.cap(li))
    if cfg.data_elimination:
        drop_slots, base = _eliminate_first(lv, st, cfg, dropped, run)
    free = None  # (1, h, w) float: 1 where the weights are optimized (None: everywhere)
    free_mask = lv.mask  # the texels L_Para couples
    settled_share = 0.0
    if cfg.settle_sigma > 0:
        settled, free, free_mask = _settle(lv, st, base, cfg)
        settled_share = float(settled.sum()) / lv.n_tex
    if cfg.use_para:
        st.matches = {a: losses.neighbour_match(lv.idx, free_mask, a, fixed=lv.fixed_slots) for a in (1, 2)}
    anything = (cfg.use_render or cfg.use_persp or cfg.use_para) and settled_share < 1.0
    # every texel settled: the weights are final, nothing is left to iterate (a level that
    # converges without an iteration, not one cut at its cap)
    run.converged = settled_share >= 1.0
    # The iterations run on ``cur``: the level, or the sub-level of its free texels
    # (difftex.method.sparse) when most texels are settled and the loss is the texel one.
    sp = None
    cur, lvc, extra = st, lv, None
    if free is not None and anything and not cfg.autograd and 1.0 - settled_share <= SPARSE_MAX_SHARE:
        sp, cur, extra, drop_slots, base = _sparse_sublevel(lv, st, cfg, free_mask, settled, drop_slots, base, N)
        lvc, free = sp.sub, None
    fn = compiled_objective(lvc, cfg, compute)
    if fn is None and cfg.autograd:
        fn = objective  # autograd needs the function; the texel loss has its own gradient
    W_check = losses.blend_weights(st.z, st.active, mode)
    dominant_start = diagnostics.dominant_photo(lv.idx, W_check)
    if sp is not None:
        W_check = losses.blend_weights(cur.z, cur.active, mode)
    fixed_share = settled_share if sp is not None else 0.0  # texels outside ``cur`` that do not move
    it = 0
    for it in range(1, run.cap + 1 if anything else 1):
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
        for k in run.loss:
            run.loss[k].append(float(terms[k]) if k in terms else 0.0)
        with torch.no_grad():
            assert grad is not None  # fn is set, so the gradient is
            if free is not None:
                grad = grad * free  # settled texels keep their blend
            adam.step(cur.z, grad)
            losses.project_weights(cur.z, mode)  # the paper's weights stay in [0, 1]
            W = losses.selection_weights(cur.z, base, mode)
            if cfg.data_elimination:
                drop_slots = _drop_and_eliminate(lvc, cur, base, W, it, cfg, dropped, extra, drop_slots, run, li, stats)
            base = base_mask(lvc, cur.eliminated, drop_slots)
            cur.active = update_activation(cur.z, base, cfg.tau, mode, cur.active)
        run.iter_times.append(time.perf_counter() - t_it)
        advance(1)
        if it % cfg.conv_window == 0:
            W_now = losses.blend_weights(cur.z, cur.active, mode)
            still = _still_moving(W_now, W_check, lvc, cfg, fixed_share, run)
            W_check = W_now
            if it >= cfg.min_iters_per_level and not still:
                run.converged = True
                break
    run.iterations = it
    if it < run.cap:
        advance(run.cap - it)
    if sp is not None:
        with torch.no_grad():  # the free texels back into the level; drops reach the settled ones too
            sparse.scatter_into(st.z, cur.z, sp.src)
            sparse.scatter_into(st.eliminated, cur.eliminated, sp.src)
            W_full = losses.blend_weights(st.z, st.active, mode)
            full_drop = dropped_slot_mask(lv, st.eliminated, dropped, W_full)
            st.active = update_activation(st.z, base_mask(lv, st.eliminated, full_drop), cfg.tau, mode, st.active)
    run.compiled = fn is not None and fn is not objective
    return st, _level_record(lv, li, st, cfg, run, anything, settled_share, sp, dominant_start)
