"""The objective L = alpha L_Render + beta L_Persp + omega L_Para of one level (eq. 3) and its
gradient. The terms themselves are in difftex.method.losses, one function per equation.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

from difftex.method import losses
from difftex.method.config import ComputeConfig, OptimizeConfig
from difftex.method.gradient import TexelData, texel_data, texel_value_and_grad
from difftex.method.levels import Level
from difftex.method.render import render_support


@dataclass
class LevelState:
    """The optimization variables of one level and what changes with them."""

    level: Level
    z: torch.Tensor  # (K, h, w) parameters of the blend weights: logits or weights (losses.blend_weights)
    active: torch.Tensor  # (K, h, w) bool a^_k
    eliminated: torch.Tensor  # (K, h, w) bool
    it: int = 0
    D: dict | None = None  # L_Para edge weights, refreshed every eliminate_every iterations (para_edges "fixed")
    matches: dict = field(default_factory=dict)  # L_Para slot correspondences per neighbour axis
    texel: TexelData | None = None  # texel-space data of the written-out gradient


def objective(z, active, colours, Q, cost, D, matches, pixel_sets, support, n_tex: float,
              cfg: OptimizeConfig, ghost_margin: float = 0.0, G=None) -> dict[str, torch.Tensor]:
    """Every term of L for one level and its weighted total: a pure function of tensors, so
    torch.compile can fuse it (``ComputeConfig.compile``).

    L = alpha (L_Render + sparsity x L1 + ghost x spread) + beta L_Persp + omega L_Para (eq. 3,
    with eq. 4's L1 term and the project's ghost term). ``D``: L_Para's edge weights (para_edges
    "fixed"); with "live" they are computed here from U and ``G`` (eq. 9) and differentiated.
    """
    W = losses.blend_weights(z, active, cfg.weights)
    U = losses.compose(W, colours)
    terms = {}
    zero = z.new_zeros(())
    if cfg.use_render:
        if cfg.loss_mode == "render":
            terms["render"] = losses.render_loss_pixels(U, support, pixel_sets, active, Q, n_tex)
        else:
            terms["render"] = losses.render_loss_texel(U, colours, active, Q, n_tex)
        terms["ghost"] = losses.ghost_loss(W, U, colours, active, Q, n_tex, ghost_margin) if cfg.ghost > 0 else zero
        terms["sparsity"] = losses.sparsity_loss(z, active, n_tex) if cfg.sparsity > 0 else zero
    terms["persp"] = losses.persp_loss(W, cost, n_tex) if cfg.use_persp else zero
    if cfg.use_para:
        if cfg.para_edges == "live":
            D = losses.edge_weights(U, G, tuple(matches), detach=False)
        terms["para"] = losses.para_loss(W, U, active, G, matches, cfg.lambda_s, n_tex, cfg.para_eps, D)
    else:
        terms["para"] = zero
    total = zero
    if cfg.use_render:
        total = total + cfg.alpha * (terms["render"] + cfg.ghost * terms["ghost"] + cfg.sparsity * terms["sparsity"])
    total = total + cfg.beta * terms["persp"] + cfg.omega * terms["para"]
    terms["total"] = total
    return terms


def render_weights(lv: Level, cfg: OptimizeConfig) -> torch.Tensor:
    """Q as L_Render weighs the photos: Q / sigma_c with render_units "noise" (so that L_Render
    and the ghost term count squared colour differences in units of the level's photometric
    noise, quality.level_noise), Q itself with "raw" (the paper)."""
    return lv.Q / lv.noise if cfg.render_units == "noise" else lv.Q


def ghost_margin(lv: Level, cfg: OptimizeConfig) -> float:
    """The ghost term's noise margin in squared colour units: ghost_margin x sigma_c^2."""
    return cfg.ghost_margin * lv.noise**2


def refresh_edge_weights(st: LevelState, cfg: OptimizeConfig) -> None:
    """Recompute L_Para's edge weights D from the current texture when they are due (every
    ``eliminate_every`` iterations): D is a constant of the term between refreshes."""
    lv = st.level
    if cfg.use_para and cfg.para_edges == "fixed" and (st.D is None or st.it % max(cfg.eliminate_every, 1) == 0):
        with torch.no_grad():
            U = losses.compose(losses.blend_weights(st.z, st.active, cfg.weights), lv.colours)
            st.D = losses.edge_weights(U, lv.G, tuple(st.matches))


def value_and_grad(st: LevelState, cfg: OptimizeConfig, fn=None) -> tuple[dict[str, torch.Tensor], torch.Tensor | None]:
    """The terms of L at the current weights and dL/dz (None when ``fn`` is None and the
    terms are only evaluated).

    Texel space with fixed L_Para edges: the gradient written out (difftex.method.gradient).
    Otherwise (``cfg.autograd``: the render loss, live edges): autograd through ``fn``
    (``objective`` or its torch.compile'd version).
    """
    lv = st.level
    refresh_edge_weights(st, cfg)
    Q = render_weights(lv, cfg)
    if not cfg.autograd:
        if st.texel is None:
            st.texel = texel_data(lv.colours, Q, lv.cost, lv.n_tex, ghost_margin(lv, cfg))
        with torch.no_grad():
            return (fn or texel_value_and_grad)(st.z, st.active, st.texel, st.D, st.matches, cfg)
    support = render_support(lv) if cfg.use_render and cfg.loss_mode == "render" else None
    args = (lv.colours, Q, lv.cost, st.D, st.matches, lv.pixel_sets, support, lv.n_tex, cfg, ghost_margin(lv, cfg),
            lv.G)
    if fn is None:
        with torch.no_grad():
            return objective(st.z, st.active, *args), None
    z = st.z.detach().requires_grad_(True)
    terms = fn(z, st.active, *args)
    terms["total"].backward()
    return {k: v.detach() for k, v in terms.items()}, z.grad


def compiled_objective(lv: Level, cfg: OptimizeConfig, compute: ComputeConfig):
    """The level's loss function torch.compile'd, or None to run it eagerly: ``objective``
    (autograd through it) for the render loss and live L_Para edges (``cfg.autograd``),
    ``texel_value_and_grad`` otherwise.

    On the CPU, eager L costs some 30 elementwise passes over (K, H, W) tensors per iteration,
    and the written-out texel gradient some 80 over (K, 3, H, W) and (K, H, W) tensors, each a
    trip through memory; inductor fuses them into a few loops. Measured on one thread
    (evaluation/bench_optimize.md): render loss at a 19.8 M-slot level 4.3-5.7 s eager vs 2.3 s
    compiled per iteration, after 13-15 s of cold compilation; texel loss at 1024 texels
    0.70 vs 0.34 s (evaluation/bench_optimize_texel_compile.md). Saving ~0.1 us per slot and
    iteration repays the compilation at about 130 M slot-iterations, i.e. from ~4 M slots at the
    finer levels' 40-80 iteration caps: ``auto`` compiles levels with at least
    ``compile_min_slots`` slot entries (a sub-level of free texels counts its own).

    On CUDA ``auto`` runs eagerly: there an iteration is milliseconds and the compilation is
    not. On an H200 (evaluation/results/bench_texture_stage_h200.md, the paper preset on a
    2048-texel wall) compiling took 17.7 and 11.4 s at the first iteration of the two finest
    levels, whose 80 and 40 compiled iterations then took 0.7 and 1.3 s.
    """
    mode = compute.compile
    if mode == "off":
        return None
    if mode == "auto" and (lv.idx.is_cuda or lv.idx.numel() < compute.compile_min_slots):
        return None
    return torch.compile(objective if cfg.autograd else texel_value_and_grad, dynamic=False)
