"""Parallax-aware composition: where the kept photos disagree beyond noise, the ones seen closest
to the polygon's guidance direction carry the texel.

A texel's optimized weights W spread over every photo that is consistent enough to keep (3-7 on
facades): none of them is an outlier to drop, so elimination and L_Render leave the blend alone.
Where the photos agree, that blend averages their noise away. Where they disagree by more than
noise without any of them being an occluder, the cause is relief parallax: a recessed window's
mullions are displaced by depth x tan(angle) in each photo, and the blend of several viewpoints
smears them out (archive wall00 at `fast`: no vertical mullion left, where the most frontal
photo shows it crisply).

Photos seen from nearly the same direction show relief at nearly the same place, so a blend of
those stays sharp. The composition therefore, at texels that disagree, reweights the kept slots
by how close their viewing direction is to the best slot's, measured against the polygon's
guidance direction v~ of L_Persp (eq. 5): with d_k = |V^_k - v~| (the persp cost's square root,
about the angle in radians between V^_k and v~),

    W'_k = W_k g_k / sum_j W_j g_j,   g_k = exp(-(d_k - min_j d_j)^2 / (2 s^2)),

where min runs over the texel's slots holding weight. Only slots whose photo holds weight all
around the texel (2 texels, :func:`interior_slots`) may carry it: the rim of an occluder that
elimination left in a photo would otherwise take the texel whole where that photo is the most
frontal (a tree's edge on archive wall00). d_k varies smoothly over the polygon for a
given photo, so the chosen photo changes along smooth lines, cross-faded where two photos are
within s of each other: the seams are few and soft. Where the photos agree the weights do not
change: there the gate

    gamma = clamp(r / sigma_c - gate, 0, 1),   r = sqrt(sum_k W_k |I_k - U|^2),

is 0 (r: the weighted RMS distance of the kept colours to their blend U; sigma_c the level's
noise, in the same RMS unit: agreeing photos spread about sqrt(1 - 1/K) sigma_c), and it is
dilated and blurred by one texel so that a thin detail is reweighted whole and the switch
between blend and selection does not itself draw a seam. The result is gamma W' + (1 - gamma) W.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from difftex.method.filters import blur

MIN_WEIGHT = 0.01  # slots below this weight (the activation threshold tau's default) do not set min d
BORDER_TEXELS = 2  # a photo must hold weight this far around a texel to carry it alone (interior_slots)


def blend_spread(W: torch.Tensor, colours: torch.Tensor) -> torch.Tensor:
    """r = sqrt(sum_k W_k |I_k - U|^2): the weighted RMS distance of the slots' colours to their blend.

    Args:
        W: (K, h, w) blend weights (summing to 1 or 0 per texel).
        colours: (K, 3, h, w) the slots' colours I_k.

    Returns:
        (h, w) r, 0 where no slot holds weight.
    """
    if colours.shape[0] != W.shape[0] or colours.shape[2:] != W.shape[1:]:
        raise ValueError(f"colours {tuple(colours.shape)} does not match W {tuple(W.shape)}")
    U = (W[:, None] * colours).sum(0)
    return (W * ((colours - U[None]) ** 2).sum(1)).sum(0).clamp_min(0.0).sqrt()


def interior_slots(W: torch.Tensor, idx: torch.Tensor, radius: int = BORDER_TEXELS) -> torch.Tensor:
    """Slots whose photo holds weight (> MIN_WEIGHT) at every texel within ``radius`` of theirs.

    An occluder's outline survives elimination in a rim of texels (thin branches, the edge of a
    tree blurred by the mapping); in the blend it is a faint tint, but the view-coherent
    weights would give it the whole texel when its photo is the most frontal. A photo that lost
    its weight next to a texel is not trusted to carry that texel alone.

    Args:
        W: (K, h, w) blend weights; idx: (K, h, w) photo index of each slot (-1: empty).
        radius: texels (Chebyshev distance).

    Returns:
        (K, h, w) bool.
    """
    if idx.shape != W.shape:
        raise ValueError(f"idx {tuple(idx.shape)} does not match W {tuple(W.shape)}")
    held = (W > MIN_WEIGHT) & (idx >= 0)
    out = torch.zeros_like(held)
    if radius <= 0:
        return held
    for n in torch.unique(idx[held]).tolist():
        at = idx == n
        has = (at & held).any(0).float()
        # erosion: a texel keeps the photo when no texel within radius lacks it
        inner = -F.max_pool2d(-has[None, None], 2 * radius + 1, stride=1, padding=radius)[0, 0] > 0.5
        out |= at & inner[None]
    return out & held


def view_coherent_weights(
    W: torch.Tensor, cost: torch.Tensor, sigma: float, eligible: torch.Tensor | None = None
) -> torch.Tensor:
    """W' = W g / sum W g with g = exp(-(d - d_min)^2 / (2 s^2)), d = sqrt(persp cost).

    Args:
        W: (K, h, w) blend weights.
        cost: (K, h, w) the slots' persp cost |V^_k - v~|^2 (Level.cost).
        sigma: s, in units of d (about radians).
        eligible: (K, h, w) bool, the slots that may carry the texel (:func:`interior_slots`);
            the others get g = 0. A texel without an eligible slot keeps W. None: all.

    Returns:
        (K, h, w) weights, normalised where any slot holds weight (the best slot's g is 1, so
        the sum never vanishes there), zero elsewhere.
    """
    if sigma <= 0:
        raise ValueError(f"sigma must be > 0, got {sigma}")
    if cost.shape != W.shape:
        raise ValueError(f"cost {tuple(cost.shape)} does not match W {tuple(W.shape)}")
    d = cost.clamp_min(0.0).sqrt()
    held = W > MIN_WEIGHT
    # a texel whose weights are all below MIN_WEIGHT (many equal photos) takes its largest one
    held = held | ((W > 0) & (W >= W.amax(0, keepdim=True)))
    if eligible is not None:
        held = held & eligible
    d_min = torch.where(held, d, torch.full_like(d, float("inf"))).amin(0, keepdim=True)
    d_min = torch.where(torch.isfinite(d_min), d_min, torch.zeros_like(d_min))
    g = torch.exp(-0.5 * ((d - d_min) / sigma) ** 2)
    if eligible is not None:
        g = torch.where(eligible, g, torch.zeros_like(g))
    Wg = W * g
    s = Wg.sum(0, keepdim=True)
    return torch.where(s > 0, Wg / s.clamp_min(1e-30), W)


def parallax_gate(W: torch.Tensor, colours: torch.Tensor, noise: float, gate: float) -> torch.Tensor:
    """gamma = clamp(r / sigma_c - gate, 0, 1), dilated and blurred by one texel: where the blend disagrees.

    Args:
        W: (K, h, w) blend weights; colours: (K, 3, h, w).
        noise: sigma_c, the level's photometric noise (> 0).
        gate: spread, in sigma_c, below which the blend is kept (it reaches full selection at gate + 1).

    Returns:
        (h, w) gamma in [0, 1].
    """
    if noise <= 0:
        raise ValueError(f"noise must be > 0, got {noise}")
    r = blend_spread(W, colours)
    gamma = (r / noise - gate).clamp(0.0, 1.0)
    # dilated by one texel, then blurred: a one-texel mullion is reweighted whole, and the
    # switch to the blend around it is gradual
    gamma = F.max_pool2d(gamma[None, None], 3, stride=1, padding=1)[0]
    return blur(gamma, 1.0)[0].clamp(0.0, 1.0)


def parallax_weights(
    W: torch.Tensor,
    colours: torch.Tensor,
    cost: torch.Tensor,
    noise: float,
    sigma: float,
    gate: float,
    idx: torch.Tensor | None = None,
) -> tuple[torch.Tensor, dict]:
    """gamma W' + (1 - gamma) W: view-coherent weights where the kept photos disagree, the blend elsewhere.

    Args:
        W: (K, h, w) optimized weights; colours: (K, 3, h, w) slot colours; cost: (K, h, w) persp cost.
        noise: sigma_c; sigma: s of :func:`view_coherent_weights`; gate: of :func:`parallax_gate`.
        idx: (K, h, w) the slots' photos: only :func:`interior_slots` may carry a texel (None: any).

    Returns:
        (K, h, w) weights and statistics: the share of weighted texels that were reweighted
        (gamma > 0.5) and the effective photos per texel (1 / sum W^2) before and after.
    """
    gamma = parallax_gate(W, colours, noise, gate)
    eligible = interior_slots(W, idx) if idx is not None else None
    out = gamma[None] * view_coherent_weights(W, cost, sigma, eligible) + (1.0 - gamma[None]) * W
    has = W.sum(0) > 0
    n = max(int(has.sum()), 1)

    def neff(x: torch.Tensor) -> float:
        return float((1.0 / (x * x).sum(0).clamp_min(1e-12))[has].sum()) / n

    stats = {
        "reweighted_share": float(((gamma > 0.5) & has).sum()) / n,
        "effective_photos_before": neff(W),
        "effective_photos_after": neff(out),
    }
    return out, stats
