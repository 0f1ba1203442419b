"""The DiffTex objective for one polygon (paper eq. 3-9), on a slot layout of the weights.

Layout: each texel keeps ``K`` candidate *slots*; slot ``j`` of texel ``t`` refers to photo
``idx[j, t]`` (or -1). The parameters ``z`` (K, H, W) are, by ``OptimizeConfig.weights``, logits
whose softmax over the active slots is the blend W (``softmax``, the project's), or the paper's
weights w in [0, 1], normalised per texel over the active slots (``normalised``, Sec. 4.1);
``active`` is the activation mask a_k^i mapped to texel space. Every sum over texels is divided
by the polygon's texel count ``n_tex``: the same factor for every term, so the balance alpha :
beta : omega is the paper's and a level's loss values compare with another level's.

Render loss comes in two forms: the texel-space form compares U with every photo mapped into
texel space (fast); the render-space form renders the textured polygon into each photo's pixels
(what the paper does with nvdiffrast) by bilinear lookup of U at each pixel's texel coordinate.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

WEIGHT_MODES = ("softmax", "normalised")  # OptimizeConfig.weights


def _check_mode(mode: str) -> None:
    if mode not in WEIGHT_MODES:
        raise ValueError(f"weights mode must be one of {', '.join(WEIGHT_MODES)}, got {mode!r}")


def blend_weights(z: torch.Tensor, active: torch.Tensor, mode: str = "softmax") -> torch.Tensor:
    """W (K, H, W), the blend weights of the parameters z over each texel's active slots.

    ``mode`` "softmax": the softmax of the logits z (zero where no slot is active); "normalised":
    :func:`normalised_weights`. Logits are the project's default: with normalised weights the
    gradient of a photo is proportional to how far its cost is from the texel's weighted mean,
    which vanishes for the runners-up as a texel narrows down to a few photos, so they linger
    for hundreds of iterations; Adam on logits lowers every losing photo's log-weight at its
    step size until the activation threshold tau removes it.
    """
    _check_mode(mode)
    if mode == "normalised":
        return normalised_weights(z, active)
    x = torch.where(active, z, torch.full_like(z, float("-inf")))
    zm = x.amax(0, keepdim=True).detach()
    zm = torch.where(torch.isfinite(zm), zm, torch.zeros_like(zm))  # texels with nothing active
    e = torch.exp(x - zm)
    return e / e.sum(0, keepdim=True).clamp_min(1e-30)


def normalised_weights(w: torch.Tensor, active: torch.Tensor) -> torch.Tensor:
    """W_k = a_k w_k / sum_j a_j w_j: the paper's weights w in [0, 1] as a normalised vector per
    texel (Sec. 4.1), over the active slots.

    Where every active weight is zero (L1 sparsity can take them there) the texel keeps an even
    blend of its active slots, which the activation update reduces to its strongest photo
    (elimination.update_activation); the paper does not say what such a texel shows. Where no
    slot is active, W is zero. Finite everywhere, its gradient too (no 0 / 0 in either branch).

    Args:
        w: (K, H, W) weights, >= 0.
        active: (K, H, W) bool.

    Returns:
        (K, H, W) W, summing to one over the active slots of every texel that has one.
    """
    a = active.to(w.dtype)
    aw = a * w
    s = aw.sum(0, keepdim=True)
    pos = s > 0
    even = a / a.sum(0, keepdim=True).clamp_min(1.0)
    return torch.where(pos, aw / torch.where(pos, s, torch.ones_like(s)), even)


def selection_weights(z: torch.Tensor, base: torch.Tensor, mode: str = "softmax") -> torch.Tensor:
    """What the activation threshold tau and the photo drop's "zero weight" read, (K, H, W).

    "softmax": the blend weights over the slots that may carry weight (``base``); "normalised":
    the weights w themselves (the paper selects a pixel "with w_k greater than ... tau", and its
    L1 term shrinks w, not the normalised W).
    """
    if mode == "normalised":
        return torch.where(base, z, torch.zeros_like(z))
    return blend_weights(z, base)


def weights_vjp(z: torch.Tensor, active: torch.Tensor, W: torch.Tensor, gW: torch.Tensor, mode: str = "softmax"):
    """dL/dz from dL/dW through :func:`blend_weights`; all (K, H, W).

    softmax: dW_j/dz_i = W_i (delta_ij - W_j); normalised: dW_j/dw_i = a_i (delta_ij - W_j) / S,
    S = sum_k a_k w_k, and zero where S = 0 (the even blend does not depend on w).
    """
    c = gW - (W * gW).sum(0, keepdim=True)
    if mode != "normalised":
        return W * c
    a = active.to(z.dtype)
    s = (a * z).sum(0, keepdim=True)
    pos = s > 0
    return torch.where(pos, a * c / torch.where(pos, s, torch.ones_like(s)), torch.zeros_like(c))


def init_weights(weights: torch.Tensor, mode: str = "softmax") -> torch.Tensor:
    """Parameters whose blend is proportional to ``weights`` (>= 0): their logits (softmax;
    a zero weight gets the logit of 1e-6) or the weights clipped to [0, 1] (normalised: the paper
    initialises w_k to Q, Sec. 4.2)."""
    if mode == "normalised":
        return weights.clamp(0.0, 1.0)
    return torch.log(weights.clamp_min(1e-6))


def project_weights(z: torch.Tensor, mode: str = "softmax") -> None:
    """In place, after an optimizer step: the paper's weights back into [0, 1] (normalised;
    logits need nothing)."""
    if mode == "normalised":
        z.clamp_(0.0, 1.0)


def sparsity_loss(w: torch.Tensor, active: torch.Tensor, n_tex: float) -> torch.Tensor:
    """The L1 term of L_Render (eq. 4), sum_k sum_o |W_k(t_o)|, on the weights in use.

    On the un-normalised weights w (weights "normalised"): on the normalised W it would be one
    per texel, a constant. Shrinking every w by the same step, it lowers the smallest ones to
    zero first, which the activation threshold then deselects: sparsity. Slots outside
    ``active`` carry no weight (their w is frozen) and are not counted.

    Shapes: w, active (K, H, W) -> ().
    """
    return (active.to(w.dtype) * w).abs().sum() / n_tex


def sparsity_grad(w: torch.Tensor, active: torch.Tensor, n_tex: float) -> torch.Tensor:
    """d sparsity_loss / dw, (K, H, W): a_k sign(w_k) / n_tex (0 at w = 0, as autograd's |.|)."""
    return active.to(w.dtype) * torch.sign(w) / n_tex


def compose(W: torch.Tensor, colours: torch.Tensor) -> torch.Tensor:
    """U_i(t) = sum_k W_k(t) I_k(f_k(t)); colours (K, 3, H, W) -> (3, H, W)."""
    return (W[:, None] * colours).sum(0)


def render_loss_texel(U, colours, active, Q, n_tex: float) -> torch.Tensor:
    """Texel-space L_Render data term: sum_k ||a_k Q_k (U - I^_k)||^2 over texels."""
    r = (active.to(U.dtype) * Q)[:, None] * (U[None] - colours)
    return (r * r).sum() / n_tex


def para_edge_cost(active: torch.Tensor, D: torch.Tensor, axis: int, lambda_s: float) -> torch.Tensor:
    """C(t_o, t_q) = m_k(t_o) D(t_o, t_q) + lambda_s per slot (eq. 8), with m_k the overlap mask:
    one where slot k is active at t_o and another slot is too (the paper: another mapped photo
    overlaps photo k's, whose selected pixels a_k marks)."""
    overlap = (active.sum(0, keepdim=True) >= 2) & active  # m_k: another selected photo overlaps
    return crop_pair(overlap, axis, "o").to(D.dtype) * D[None] + lambda_s


def render_quality(active: torch.Tensor, Q: torch.Tensor) -> torch.Tensor:
    """q_k = (a_k Q_k)^2, each photo's weight in the squared norm of L_Render (eq. 4); (K, H, W)."""
    aq = active.to(Q.dtype) * Q
    return aq * aq


def ghost_spread(d2: torch.Tensor, margin: float) -> torch.Tensor:
    """psi(d^2) = d^4 / (d^2 + margin): a photo's squared distance to the blend, discounted
    below ``margin`` (the photometric noise: blending photos that differ by noise only averages
    the noise away, which is wanted), equal to d^2 - margin + O(margin^2 / d^2) above it."""
    return d2 if margin <= 0 else d2 * d2 / (d2 + margin)


def ghost_loss(W, U, colours, active, Q, n_tex: float, margin: float = 0.0) -> torch.Tensor:
    """The spread of the blend: sum_t A(t) sum_k W_k(t) psi(|I^_k(t) - U(t)|^2), A = sum_k q_k.

    Not in the paper. L_Render alone is minimised by the q-weighted mean of the photos (the mean
    minimises a sum of squared distances), so it pulls every texel towards a blend, and ghosts
    where the photos disagree. By the bias-variance decomposition (sum_k W_k = 1)

        L_Render + ghost = sum_t sum_k W_k(t) sum_j q_j(t) |I^_k(t) - I^_j(t)|^2,

    the expected render error of using one photo, drawn with probability W: linear in W, so
    its minimum selects photos, and blending photos that agree costs nothing while blending
    photos that disagree (relief parallax, misalignment, an occluder) costs their spread. With
    ``margin`` > 0 (psi, ghost_spread) differences at the noise level cost next to nothing, so
    photos that agree up to noise are blended (the noise averages out) and the others selected.

    Shapes: W (K, H, W), U (3, H, W), colours (K, 3, H, W), active / Q (K, H, W).
    """
    A = render_quality(active, Q).sum(0)
    spread = (W * ghost_spread(((colours - U[None]) ** 2).sum(1), margin)).sum(0)
    return (A * spread).sum() / n_tex


@dataclass
class PixelSet:
    """Render-mode data of one photo at one level: its a_k^i pixels (downscaled to texel size)."""

    grid: torch.Tensor  # (1, n, 1, 2) texel coordinates normalised for grid_sample
    colour: torch.Tensor  # (n, 3) photo colours at those pixels
    texel: torch.Tensor  # (n,) flat index of the nearest texel
    slot: torch.Tensor  # (n,) slot of this photo at that texel, -1 if it is not a candidate there
    scale: float  # what each pixel counts in L_Render (pixel_weight)


@dataclass
class PixelBatch:
    """All photos' PixelSets concatenated, so one grid_sample renders every view."""

    grid: torch.Tensor  # (1, P, 1, 2)
    colour: torch.Tensor  # (P, 3)
    texel: torch.Tensor  # (P,)
    slot: torch.Tensor  # (P,)
    scale: torch.Tensor  # (P,) the photo's scale per pixel
    den: torch.Tensor | None = None  # (P,) sampled support, fixed per level (see render_view)

    @property
    def n(self) -> int:
        return int(self.colour.shape[0])


def pixel_weight(mode: str, texels: int, pixels: int, step: int) -> float:
    """How much one of a photo's rendered pixels counts in L_Render's sum (PixelSet.scale).

    Args:
        mode: ``render_scale``. "texels" (the project's): texels / pixels, so that every photo's
            pixel sum sits on the texel-sum scale of the other terms, however large the photo
            sees the polygon. "pixels" (eq. 4): a sum over the photo's pixels at its own
            resolution; rendered at a pyramid level whose pixel is ``step`` x ``step`` of them,
            each counts for step^2.
        texels: the polygon's texels the photo sees at this level; pixels: its rendered pixels.
        step: full-resolution pixels per rendered pixel along an axis (2^level).
    """
    if mode not in ("texels", "pixels"):
        raise ValueError(f"render_scale must be texels or pixels, got {mode!r}")
    if mode == "pixels":
        return float(step * step)
    return texels / max(pixels, 1)


def batch_pixel_sets(sets: list[PixelSet], support: torch.Tensor, device) -> PixelBatch:
    if not sets:
        z = torch.zeros(0, device=device)
        return PixelBatch(
            grid=torch.zeros(1, 0, 1, 2, device=device),
            colour=torch.zeros(0, 3, device=device),
            texel=z.long(),
            slot=z.long(),
            scale=z,
            den=z,
        )
    b = PixelBatch(
        grid=torch.cat([s.grid for s in sets], 1),
        colour=torch.cat([s.colour for s in sets]),
        texel=torch.cat([s.texel for s in sets]),
        slot=torch.cat([s.slot for s in sets]),
        scale=torch.cat([torch.full((s.colour.shape[0],), float(s.scale), device=device) for s in sets]),
    )
    s_ = support.float()[None, None]
    b.den = F.grid_sample(s_, b.grid, mode="bilinear", padding_mode="zeros", align_corners=False)[0, 0, :, 0]
    return b


def render_view(
    U: torch.Tensor, support: torch.Tensor, grid: torch.Tensor, den: torch.Tensor | None = None
) -> torch.Tensor:
    """R_k at the given pixels: bilinear lookup of U (3, H, W), normalised by the support.

    Texels outside the polygon (or with no source) carry no colour; dividing by the bilinearly
    sampled support keeps pixels at the polygon's border from blending with black. The support
    does not depend on the weights, so its samples ``den`` can be computed once.
    """
    s = support.to(U.dtype)[None]
    num = F.grid_sample((U * s)[None], grid, mode="bilinear", padding_mode="zeros", align_corners=False)[0, :, :, 0]
    if den is None:
        den = F.grid_sample(s[None], grid, mode="bilinear", padding_mode="zeros", align_corners=False)[0, 0, :, 0]
    return (num / den.clamp_min(1e-6)[None]).T  # (n, 3)


def render_loss_pixels(U, support, batch: PixelBatch, active, Q, n_tex: float) -> torch.Tensor:
    """Render-space L_Render data term (eq. 4): sum_k ||a_k Q (R_k - I_k)||^2 over a_k^i pixels.

    Each pixel counts ``batch.scale`` times (pixel_weight); a and Q are the values at the texel
    the pixel falls on (the paper: "each element in Q^i is equal to Q(t_o)").

    Shapes: U (3, H, W), support (H, W), active / Q (K, H, W) -> ().
    """
    if batch.n == 0:
        return U.new_zeros(())
    K = active.shape[0]
    a_flat = active.reshape(K, -1).to(U.dtype)
    q_flat = Q.reshape(K, -1)
    ok = batch.slot >= 0
    j = batch.slot.clamp_min(0)
    wq = a_flat[j, batch.texel] * q_flat[j, batch.texel] * ok.to(U.dtype)
    R = render_view(U, support, batch.grid, batch.den)
    r = wq[:, None] * (R - batch.colour)
    return (batch.scale[:, None] * r * r).sum() / n_tex


def guidance_direction(view_dirs: torch.Tensor, normal: torch.Tensor) -> torch.Tensor:
    """v~_i = 0.5 sum v_k / |sum v_k| - 0.5 n_i (Sec. 4.2, the text before eq. 5).

    v_k are the photos' viewing directions.
    """
    s = view_dirs.sum(0)
    return 0.5 * s / s.norm().clamp_min(1e-12) - 0.5 * normal


def persp_cost(view_field: torch.Tensor, v_tilde: torch.Tensor) -> torch.Tensor:
    """|V^_k - v~_i|^2 per slot and texel; view_field (K, 3, H, W) camera-to-texel unit vectors."""
    d = view_field - v_tilde.view(1, 3, 1, 1)
    return (d * d).sum(1)


def persp_loss(W, cost, n_tex: float) -> torch.Tensor:
    """L_Persp = sum_k ||W_k . V_k . V_k||_1 with V_k = a^_k (V^_k - v~) (eq. 5-6); a is inside W."""
    return (W * cost).sum() / n_tex


@dataclass
class NeighbourMatch:
    """Slot correspondence between texel o and its neighbour q (up or left) for L_Para.

    ``match[j]`` at o is the slot of q holding the same photo as slot j of o (-1: none);
    ``q_alone[l]`` at o marks slots of q whose photo is not among o's slots.
    Arrays are cropped so that o and q line up: o = [:, 1:, :], q = [:, :-1, :] for "up".
    """

    match: torch.Tensor | None  # (K, h', w') long; None: slot j is the same photo everywhere
    q_alone: torch.Tensor | None  # (K, h', w') bool
    pair_ok: torch.Tensor  # (h', w') bool: both texels inside the polygon


def neighbour_match(idx: torch.Tensor, mask: torch.Tensor, axis: int, fixed: bool = False) -> NeighbourMatch:
    """Build the slot correspondence for the up (axis=1) or left (axis=2) neighbour.

    ``fixed``: every slot holds one photo at all texels (weights of photos that do not see a
    texel are 0 there), so slots correspond directly and no gather is needed.
    """
    if axis == 1:
        io, iq = idx[:, 1:, :], idx[:, :-1, :]
        ok = mask[1:, :] & mask[:-1, :]
    else:
        io, iq = idx[:, :, 1:], idx[:, :, :-1]
        ok = mask[:, 1:] & mask[:, :-1]
    if fixed:
        return NeighbourMatch(match=None, q_alone=None, pair_ok=ok)
    match, q_alone = slot_match(io, iq)
    return NeighbourMatch(match=match, q_alone=q_alone, pair_ok=ok)


def slot_match(io: torch.Tensor, iq: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """For texels o and their neighbours q (photo per slot, -1 empty, same shape (K, ...)):
    ``match[j]``, the slot of q holding the photo of slot j of o (-1: none), and ``q_alone[l]``,
    the slots of q whose photo is not among o's."""
    K = io.shape[0]
    match = torch.full_like(io, -1)
    q_in_o = torch.zeros(io.shape, dtype=torch.bool, device=io.device)
    # K x K comparisons, done slot by slot to keep the temporary at the texels' size.
    for slot in range(K):
        same = (io == iq[slot : slot + 1]) & (io >= 0)
        match = torch.where(same & (match < 0), torch.full_like(match, slot), match)
        q_in_o[slot] = same.any(0)
    return match, (~q_in_o) & (iq >= 0)


def crop_pair(x: torch.Tensor, axis: int, which: str) -> torch.Tensor:
    """The texels o (``which`` "o") or their neighbours q ("q") along ``axis`` (1: up, 2: left)."""
    if axis == 1:
        return x[..., 1:, :] if which == "o" else x[..., :-1, :]
    return x[..., :, 1:] if which == "o" else x[..., :, :-1]


def smooth_abs(x: torch.Tensor, eps: float) -> torch.Tensor:
    """|x|, smoothed near 0 (Charbonnier) when eps > 0.

    The exact |x| has a gradient of constant size whose sign flips with every tiny
    difference; with Adam's per-parameter normalisation that noise swamps the other terms.
    """
    return (x * x + eps * eps).sqrt() - eps if eps > 0 else x.abs()


def edge_weights(U: torch.Tensor, G: torch.Tensor, axes=(1, 2), detach: bool = True) -> dict[int, torch.Tensor]:
    """D(t_o, t_q) = S(|U(t_o) - U(t_q)|) (1 + G(t_o)) per neighbour direction (eq. 9).

    ``detach`` (para_edges "fixed", the project's): D is a constant of L_Para. It says where a
    change of source is expensive; letting its gradient act would blur U instead of moving the
    seams. It changes slowly with U, so the optimizer refreshes it every few iterations. Not
    detached ("live"): eq. 9 as written, a function of the current U, differentiated.

    Shapes: U (3, H, W), G (H, W) -> {axis: (H - 1, W) or (H, W - 1)}.
    """
    if detach:
        U = U.detach()
    return {
        a: torch.sigmoid((crop_pair(U, a, "o") - crop_pair(U, a, "q")).norm(dim=0)) * (1.0 + crop_pair(G, a, "o"))
        for a in axes
    }


def para_loss(
    W,
    U,
    active,
    G,
    matches: dict[int, NeighbourMatch],
    lambda_s: float,
    n_tex: float,
    eps: float = 0.0,
    D: dict[int, torch.Tensor] | None = None,
) -> torch.Tensor:
    """L_Para (eq. 7-9) over up and left neighbours, summed over photos.

    C = m_k(t_o) D(t_o, t_q) + lambda_s with D from ``edge_weights`` (computed here if not given).
    """
    if D is None:
        D = edge_weights(U, G, tuple(matches))
    total = W.new_zeros(())
    for axis, nm in matches.items():
        Wo, Wq = crop_pair(W, axis, "o"), crop_pair(W, axis, "q")
        C = para_edge_cost(active, D[axis], axis, lambda_s)
        if nm.match is None:
            term = (C * smooth_abs(Wo - Wq, eps)).sum(0)
        else:
            Wq_same = torch.gather(Wq, 0, nm.match.clamp_min(0)) * (nm.match >= 0).to(W.dtype)
            alone = nm.q_alone.to(W.dtype)  # type: ignore[union-attr]  # set unless fixed
            term = (C * smooth_abs(Wo - Wq_same, eps)).sum(0) + lambda_s * smooth_abs(Wq * alone, eps).sum(0)
        total = total + (term * nm.pair_ok.to(W.dtype)).sum()
    return total / n_tex
