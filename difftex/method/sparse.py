"""A level's free texels as a flat list: the whole iteration (objective, Adam, activation,
elimination, photo drop, convergence) costs in proportion to the texels that are optimized.

Once the settled texels are fixed at their blend (OptimizeConfig.settle_sigma,
elimination.settled_texels), only the free texels change: on facades most texels settle (82-88 %
of herzjesu-p8's facade at the `balanced` levels) and the free ones are scattered along edges,
where square tiles (the earlier strip of tiles) covered half the level. Here the free texels are
gathered into a sub-level of shape (K, 1, F), on which every per-texel step of the optimizer runs
unchanged (they reduce over the slots only), and L_Para, the one term with neighbours, runs on
explicit edge lists: the up and left neighbour pairs whose two texels are free (L_Para couples
free texels only, so this is the same term). The texel-space gradient on the sub-level equals
the whole level's on the free texels to float rounding (tests/test_sparse.py).

Left out on the sub-level: the render-space loss (its pixel sets are the whole level's; texel
loss only) and elimination on settled texels (they are settled because their photos agree).
"""

from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass

import torch

from difftex.method import losses
from difftex.method.gradient import TexelData, _smooth_abs_grad, texel_data, texel_value_and_grad
from difftex.method.levels import Level
from difftex.method.losses import smooth_abs


@dataclass
class Edges:
    """The neighbour pairs (o, q) along one axis whose texels are both free, as sub-level indices."""

    o: torch.Tensor  # (E,) long
    q: torch.Tensor  # (E,) long, the up (axis 1) or left (axis 2) neighbour of o
    match: torch.Tensor | None  # (K, E) slot of q holding the photo of slot j of o (-1: none); None: fixed
    q_alone: torch.Tensor | None  # (K, E) bool: slots of q whose photo o does not have
    D: torch.Tensor | None = None  # (E,) L_Para's edge weights, refreshed by refresh_edge_weights


@dataclass
class SparseLevel:
    """A level's free texels: the sub-level they form, where they sit, and their edges."""

    sub: Level  # tensors (K, 1, F) / (1, F); its n_tex is F
    src: torch.Tensor  # (F,) long: flat index of each free texel in the level
    edges: dict[int, Edges]
    texel: TexelData  # n_tex the whole level's, so that the gradient is the level's


def gather(x: torch.Tensor, src: torch.Tensor) -> torch.Tensor:
    """(..., h, w) -> (..., 1, F): the level's values at the free texels."""
    return x.flatten(-2)[..., src].unsqueeze(-2)


def scatter_into(full: torch.Tensor, part: torch.Tensor, src: torch.Tensor) -> torch.Tensor:
    """``full`` (..., h, w) with the free texels' values from ``part`` (..., 1, F); in place."""
    full.flatten(-2)[..., src] = part.squeeze(-2)
    return full


def neighbour_edges(free: torch.Tensor, idx_f: torch.Tensor, fixed: bool) -> dict[int, Edges]:
    """The up (axis 1) and left (axis 2) neighbour pairs of free texels, with slot matches.

    Args:
        free: (h, w) bool, the free texels (row-major order gives the sub-level's order).
        idx_f: (K, F) the sub-level's photo per slot.
        fixed: every slot holds one photo everywhere (losses.neighbour_match's ``fixed``).
    """
    h, w = free.shape
    src = free.flatten().nonzero()[:, 0]
    pos = torch.full((h * w,), -1, dtype=torch.long, device=free.device)
    pos[src] = torch.arange(src.numel(), device=free.device)
    out = {}
    for axis, step, ok in ((1, w, src >= w), (2, 1, src % w != 0)):
        o = ok.nonzero()[:, 0]
        q = pos[src[o] - step]
        keep = q >= 0
        o, q = o[keep], q[keep]
        if fixed:
            out[axis] = Edges(o=o, q=q, match=None, q_alone=None)
        else:
            match, q_alone = losses.slot_match(idx_f[:, o], idx_f[:, q])
            out[axis] = Edges(o=o, q=q, match=match, q_alone=q_alone)
    return out


def sparse_level(lv: Level, free: torch.Tensor, Q: torch.Tensor, margin: float) -> SparseLevel:
    """The sub-level of ``lv``'s free texels.

    Args:
        lv: the level.
        free: (h, w) bool, texels inside the polygon whose weights are optimized.
        Q: (K, h, w) the render weights (objective.render_weights).
        margin: the ghost term's margin (objective.ghost_margin).
    """
    src = free.flatten().nonzero()[:, 0]
    sub = dataclasses.replace(
        lv,
        mask=torch.ones((1, src.numel()), dtype=torch.bool, device=free.device),
        idx=gather(lv.idx, src),
        visible=gather(lv.visible, src),
        colours=gather(lv.colours, src),
        Q=gather(lv.Q, src),
        cost=gather(lv.cost, src),
        G=gather(lv.G, src),
        z0=gather(lv.z0, src),
        pixel_sets=None,
    )
    edges = neighbour_edges(free, sub.idx[:, 0], lv.fixed_slots)
    texel = texel_data(sub.colours, gather(Q, src), sub.cost, lv.n_tex, margin)
    return SparseLevel(sub=sub, src=src, edges=edges, texel=texel)


def refresh_edge_weights(sp: SparseLevel, z: torch.Tensor, active: torch.Tensor, mode: str = "softmax") -> None:
    """D = S(|U(o) - U(q)|) (1 + G(o)) on every edge (losses.edge_weights, eq. 9), no gradient;
    ``mode``: OptimizeConfig.weights."""
    with torch.no_grad():
        U = losses.compose(losses.blend_weights(z, active, mode), sp.sub.colours)[:, 0]  # (3, F)
        G = sp.sub.G[0]
        for e in sp.edges.values():
            e.D = torch.sigmoid((U[:, e.o] - U[:, e.q]).norm(dim=0)) * (1.0 + G[e.o])


def para_value_and_grad(
    W: torch.Tensor, active: torch.Tensor, edges: dict[int, Edges], lambda_s: float, eps: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """L_Para (eq. 7-9, times n_tex) on the edge lists and its gradient with respect to W.

    gradient.para_value_and_grad with the neighbour crops replaced by gathers at the edges and
    the scatter of the neighbours' gradient by index_add.

    Shapes: W, active (K, F) -> (), (K, F).
    """
    g = torch.zeros_like(W)
    total = W.new_zeros(())
    overlap = ((active.sum(0, keepdim=True) >= 2) & active).to(W.dtype)  # m_k
    for e in edges.values():
        assert e.D is not None, "refresh_edge_weights first"
        C = overlap[:, e.o] * e.D[None] + lambda_s
        Wo, Wq = W[:, e.o], W[:, e.q]
        if e.match is None:
            d = Wo - Wq
            gd = C * _smooth_abs_grad(d, eps)
            total = total + (C * smooth_abs(d, eps)).sum()
            g.index_add_(1, e.o, gd)
            g.index_add_(1, e.q, -gd)
            continue
        has = (e.match >= 0).to(W.dtype)
        sl = e.match.clamp_min(0)
        d = Wo - torch.gather(Wq, 0, sl) * has
        gd = C * _smooth_abs_grad(d, eps)
        total = total + (C * smooth_abs(d, eps)).sum()
        g.index_add_(1, e.o, gd)
        g.index_add_(1, e.q, torch.zeros_like(Wq).scatter_add_(0, sl, -gd * has))
        alone = e.q_alone.to(W.dtype)  # type: ignore[union-attr]  # set unless fixed
        x = Wq * alone
        total = total + lambda_s * smooth_abs(x, eps).sum()
        g.index_add_(1, e.q, lambda_s * _smooth_abs_grad(x, eps) * alone)
    return total, g


@functools.lru_cache(maxsize=8)
def _without_para(cfg):
    """``cfg`` with L_Para off, for texel_value_and_grad (L_Para runs on the edges here): one
    object per config, so a compiled gradient sees the same argument every iteration."""
    return dataclasses.replace(cfg, use_para=False)


def value_and_grad(
    sp: SparseLevel, z: torch.Tensor, active: torch.Tensor, cfg, refresh: bool, fn=None
) -> tuple[dict[str, torch.Tensor], torch.Tensor]:
    """Every term of L over the free texels and dL/dz on the sub-level, (K, 1, F).

    Args:
        z, active: (K, 1, F) the sub-level's logits and activation.
        cfg: an OptimizeConfig (texel loss).
        refresh: recompute L_Para's edge weights first (every ``eliminate_every`` iterations).
        fn: the compiled gradient.texel_value_and_grad, or None (eager).
    """
    with torch.no_grad():
        terms, grad = (fn or texel_value_and_grad)(z, active, sp.texel, None, {}, _without_para(cfg))
        if cfg.use_para:
            if refresh or any(e.D is None for e in sp.edges.values()):
                refresh_edge_weights(sp, z, active, cfg.weights)
            W = losses.blend_weights(z, active, cfg.weights)[:, 0]
            val, gW = para_value_and_grad(W, active[:, 0], sp.edges, cfg.lambda_s, cfg.para_eps)
            gW = (cfg.omega / sp.texel.n_tex) * gW[:, None]
            grad = grad + losses.weights_vjp(z, active, W[:, None], gW, cfg.weights)  # through the blend
            terms["para"] = val / sp.texel.n_tex
            terms["total"] = terms["total"] + cfg.omega * terms["para"]
    return terms, grad
