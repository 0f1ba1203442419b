"""The gradient of L with respect to the parameters z of the weights in texel space, written out, and Adam.

Autograd records some 40 intermediate (K, H, W) tensors per iteration of L and replays them
backwards; every term of the texel-space objective has a short closed-form derivative, so this
computes L and dL/dz in one forward sweep over the slots (about a fifth of the memory
traffic; tests check it against autograd to float tolerance). The render-space L_Render
(loss_mode "render") keeps autograd, through difftex.method.objective.

Notation (per texel, K slots): W = the blend of the parameters z over the active slots (losses.
blend_weights: softmax of logits, or the paper's normalised weights), U = sum_j W_j I_j,
q_j = (a_j Q_j)^2, A = sum_j q_j. L_Para with live edge weights (para_edges "live") has no
written-out gradient; it runs through autograd (OptimizeConfig.autograd).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from difftex.method import losses
from difftex.method.losses import NeighbourMatch, crop_pair, para_edge_cost, smooth_abs


@dataclass
class TexelData:
    """What the texel-space terms read of one level (fixed during a level)."""

    colours: torch.Tensor  # (K, 3, H, W)
    sq: torch.Tensor  # (K, H, W) |I_j|^2
    Q: torch.Tensor  # (K, H, W)
    cost: torch.Tensor  # (K, H, W) |V^ - v~|^2 (L_Persp)
    n_tex: float
    ghost_margin: float = 0.0  # losses.ghost_spread's margin, squared colour units


def texel_data(colours: torch.Tensor, Q: torch.Tensor, cost: torch.Tensor, n_tex: float,
               ghost_margin: float = 0.0) -> TexelData:
    return TexelData(colours=colours, sq=(colours * colours).sum(1), Q=Q, cost=cost, n_tex=n_tex,
                     ghost_margin=ghost_margin)


def _smooth_abs_grad(x: torch.Tensor, eps: float) -> torch.Tensor:
    """d smooth_abs(x) / dx."""
    return x / (x * x + eps * eps).sqrt() if eps > 0 else torch.sign(x)


def para_value_and_grad(
    W: torch.Tensor,
    active: torch.Tensor,
    D: dict[int, torch.Tensor],
    matches: dict[int, NeighbourMatch],
    lambda_s: float,
    eps: float,
) -> tuple[torch.Tensor, torch.Tensor]:
    """L_Para (eq. 7-9, times n_tex) and its gradient with respect to W, (K, H, W).

    Mirrors losses.para_loss: the slot j of texel o meets the slot of its neighbour q that holds
    the same photo (``match``; all slots correspond when the layout is fixed), and photos of q
    that o does not have pay lambda_s |W|.
    """
    g = torch.zeros_like(W)
    total = W.new_zeros(())
    for axis, nm in matches.items():
        Wo, Wq = crop_pair(W, axis, "o"), crop_pair(W, axis, "q")
        go, gq = crop_pair(g, axis, "o"), crop_pair(g, axis, "q")  # views into g
        C = para_edge_cost(active, D[axis], axis, lambda_s) * nm.pair_ok.to(W.dtype)
        if nm.match is None:
            d = Wo - Wq
            total = total + (C * smooth_abs(d, eps)).sum()
            gd = C * _smooth_abs_grad(d, eps)
            go += gd
            gq -= gd
        else:
            has = (nm.match >= 0).to(W.dtype)
            idx = nm.match.clamp_min(0)
            d = Wo - torch.gather(Wq, 0, idx) * has
            total = total + (C * smooth_abs(d, eps)).sum()
            gd = C * _smooth_abs_grad(d, eps)
            go += gd
            gq.scatter_add_(0, idx, -gd * has)
            alone = nm.q_alone.to(W.dtype) * nm.pair_ok.to(W.dtype)  # type: ignore[union-attr]  # set unless fixed
            x = Wq * alone
            total = total + lambda_s * smooth_abs(x, eps).sum()
            gq += lambda_s * _smooth_abs_grad(x, eps) * alone
    return total, g


def texel_value_and_grad(
    z: torch.Tensor, active: torch.Tensor, data: TexelData, D: dict | None, matches: dict, cfg
) -> tuple[dict[str, torch.Tensor], torch.Tensor]:
    """Every term of L in texel space (as difftex.method.objective.objective computes them) and
    dL/dz, (K, H, W). ``cfg``: an OptimizeConfig with para_edges "fixed"."""
    W = losses.blend_weights(z, active, cfg.weights)
    n = data.n_tex
    zero = z.new_zeros(())
    terms: dict[str, torch.Tensor] = {"render": zero, "persp": zero, "para": zero, "ghost": zero, "sparsity": zero}
    gW = torch.zeros_like(W)
    if cfg.use_render:
        U = (W[:, None] * data.colours).sum(0)
    if cfg.use_render:
        q = losses.render_quality(active, data.Q)
        A = q.sum(0)
        M = (q[:, None] * data.colours).sum(0)
        UC = (U[None] * data.colours).sum(1)  # (K, H, W) U . I_j
        UU = (U * U).sum(0)
        qsq = (q * data.sq).sum(0)
        # sum_k q_k |U - I_k|^2 = A |U|^2 - 2 U.M + sum_k q_k |I_k|^2
        terms["render"] = (A * UU - 2 * (U * M).sum(0) + qsq).sum() / n
        MC = (M[None] * data.colours).sum(1)  # (K, H, W) M . I_j
        gW += cfg.alpha * 2 * (A[None] * UC - MC) / n
        if cfg.ghost > 0:
            m = data.ghost_margin
            if m <= 0:
                spread = (W * data.sq).sum(0) - UU  # sum_k W_k |I_k - U|^2
                terms["ghost"] = (A * spread).sum() / n
                gW += cfg.alpha * cfg.ghost * A[None] * (data.sq - 2 * UC) / n
            else:
                # sum_k W_k psi(d_k), d_k = |I_k - U|^2: d/dW_k = psi(d_k) - 2 R . I_k with
                # R = sum_j W_j psi'(d_j) (I_j - U)
                diff = data.colours - U[None]
                d2 = (diff * diff).sum(1)
                psi = losses.ghost_spread(d2, m)
                dpsi = d2 * (d2 + 2 * m) / (d2 + m) ** 2
                R = ((W * dpsi)[:, None] * diff).sum(0)
                terms["ghost"] = (A * (W * psi).sum(0)).sum() / n
                gW += cfg.alpha * cfg.ghost * A[None] * (psi - 2 * (R[None] * data.colours).sum(1)) / n
    if cfg.use_persp:
        terms["persp"] = (W * data.cost).sum() / n
        gW += cfg.beta * data.cost / n
    if cfg.use_para:
        assert D is not None, "L_Para needs its edge weights D (losses.edge_weights)"
        val, g = para_value_and_grad(W, active, D, matches, cfg.lambda_s, cfg.para_eps)
        terms["para"] = val / n
        gW += cfg.omega * g / n
    total = zero
    if cfg.use_render:
        total = total + cfg.alpha * (terms["render"] + cfg.ghost * terms["ghost"])
    total = total + cfg.beta * terms["persp"] + cfg.omega * terms["para"]
    grad = losses.weights_vjp(z, active, W, gW, cfg.weights)
    if cfg.use_render and cfg.sparsity > 0:  # eq. 4's L1 term, on the weights themselves
        terms["sparsity"] = losses.sparsity_loss(z, active, n)
        total = total + cfg.alpha * cfg.sparsity * terms["sparsity"]
        grad = grad + cfg.alpha * cfg.sparsity * losses.sparsity_grad(z, active, n)
    terms["total"] = total
    return terms, grad


@dataclass
class Adam:
    """torch.optim.Adam's update (amsgrad off, no weight decay), in place on one tensor.

    torch.optim imports torch._dynamo on first use (2.4 s per process here); this is the same
    arithmetic on the one parameter tensor the method has.
    """

    lr: float
    betas: tuple[float, float]
    eps: float = 1e-8
    step_count: int = 0
    m: torch.Tensor | None = None
    v: torch.Tensor | None = None

    def step(self, param: torch.Tensor, grad: torch.Tensor) -> None:
        if self.m is None:
            self.m = torch.zeros_like(param)
            self.v = torch.zeros_like(param)
        b1, b2 = self.betas
        assert self.m is not None and self.v is not None  # set above on the first step
        self.step_count += 1
        self.m.lerp_(grad, 1 - b1)
        self.v.mul_(b2).addcmul_(grad, grad, value=1 - b2)
        bc1 = 1 - b1**self.step_count
        bc2 = 1 - b2**self.step_count
        denom = (self.v.sqrt() / bc2**0.5).add_(self.eps)
        param.addcdiv_(self.m, denom, value=-self.lr / bc1)
