"""Data quality optimization (Sec. 4.3): the activation masks a_k (Sec. 4.2), pixel elimination
and photo drop.

All functions work on one level's slot layout: (K, h, w) tensors, slot j of texel t holding
photo ``idx[j, t]``.
"""

from __future__ import annotations

import torch

from difftex.method import losses
from difftex.method.config import OptimizeConfig
from difftex.method.levels import Level


def argmax0(x: torch.Tensor) -> torch.Tensor:
    """Index of the largest entry along dim 0, as (1, ...) (first one on ties).

    torch's argmax over the leading dimension of a (K, H, W) tensor is a strided reduction that
    ran ~100x slower on CPU than this loop over the few slots.
    """
    best = x[0].clone()
    idx = torch.zeros(x.shape[1:], dtype=torch.long, device=x.device)
    for j in range(1, x.shape[0]):
        better = x[j] > best
        best = torch.where(better, x[j], best)
        idx = torch.where(better, torch.full_like(idx, j), idx)
    return idx[None]


def base_mask(lv: Level, eliminated: torch.Tensor, dropped_slots: torch.Tensor) -> torch.Tensor:
    """Slots that may carry weight: visible, not eliminated, not of a dropped photo."""
    return lv.visible & ~eliminated & ~dropped_slots


def update_activation(
    z: torch.Tensor, base: torch.Tensor, tau: float, mode: str = "softmax", prev: torch.Tensor | None = None
) -> torch.Tensor:
    """a = base & (selected weight > tau); the best one always stays (Sec. 4.2's a_k update).

    The selected weight is losses.selection_weights: W normalised over the base candidates
    (softmax), or the weights w themselves (normalised: the paper's "w_k greater than ... tau").
    Keeping each texel's strongest candidate avoids holes when every weight is below tau; with
    normalised weights it is the strongest of the slots active before (``prev``, where any is
    left in ``base``): a slot frozen below tau must not take over from the photo whose weight the
    L1 term is taking to zero.

    Shapes: z, base, prev (K, h, w) -> (K, h, w) bool.
    """
    W = losses.selection_weights(z, base, mode)
    act = base & (W > tau)
    pool = base
    if mode == "normalised" and prev is not None:
        left = prev & base
        pool = torch.where(left.any(0, keepdim=True), left, base)
    best = argmax0(torch.where(pool, W, torch.full_like(W, -1.0)))
    keep = torch.zeros_like(act).scatter_(0, best, True) & pool
    return act | keep


def eliminate_pixels(lv: Level, active: torch.Tensor, W: torch.Tensor, cfg: OptimizeConfig) -> torch.Tensor:
    """Slots whose colour lies beyond sigma_k standard deviations of the texel's selected colours.

    "paper" (Sec. 4.3, Data Elimination): per texel the mean and standard deviation of its
    selected (active) colours; every selected slot further than sigma_k standard deviations from
    the mean goes. The colours are points in RGB: the standard deviation is their RMS distance to
    the mean, sqrt(var) with var the mean squared distance. With the mean and deviation including
    the pixel tested, a pixel lies at most sqrt(n - 1) deviations away, so at sigma_k 3 the test
    needs 11 selected photos or more to remove any.

    "loo" (the project's default): mean/std of the *other* selected colours, with a noise floor
    sigma_min, which catches a lone occluded pixel among three or more; at most one slot per
    texel per pass, never the texel's highest-weight one (``W``), and only with >= 3 selected.

    Shapes: active, W (K, h, w); lv.colours (K, 3, h, w) -> (K, h, w) bool.
    """
    a = active.to(lv.colours.dtype)
    n = a.sum(0)
    c = lv.colours
    s1 = (c * a[:, None]).sum(0)
    if cfg.elimination_test == "paper":
        mu = s1 / n.clamp_min(1)
        d2 = ((c - mu[None]) ** 2).sum(1)
        # two passes, so that equal colours give var = d2 = 0 (to rounding, on both sides)
        var = (d2 * a).sum(0) / n.clamp_min(1)
        return active & (d2 > cfg.sigma_k**2 * var[None])
    s2 = ((c * c).sum(1) * a).sum(0)
    m = (n[None] - a).clamp_min(1)
    mu = (s1[None] - c * a[:, None]) / m[:, None]
    var = ((s2[None] - (c * c).sum(1) * a) / m - (mu * mu).sum(1)).clamp_min(0)
    d2 = ((c - mu) ** 2).sum(1)
    z2 = d2 / (var + cfg.sigma_min**2)
    # var is a mean squared distance over 3 channels; a 1-D k-sigma test on it reads k^2
    out = active & (z2 > cfg.sigma_k**2) & (n >= 3)[None]
    best = argmax0(torch.where(active, W, torch.full_like(W, -1.0)))
    out.scatter_(0, best, False)
    worst = argmax0(torch.where(out, z2, torch.full_like(z2, -1.0)))
    one = torch.zeros_like(out).scatter_(0, worst, True)
    return out & one


def _photo_counts(idx: torch.Tensor, base: torch.Tensor, W: torch.Tensor, tau: float, n_photos: int):
    """Per photo: (texels it could serve, those where its weight is zero), float64 (n_photos,)."""
    i = idx.clamp_min(0).reshape(-1)
    tot = torch.bincount(i, weights=base.reshape(-1).double(), minlength=n_photos)
    zero = torch.bincount(i, weights=(base & (W <= tau)).reshape(-1).double(), minlength=n_photos)
    return tot, zero


def settled_counts(
    lv: Level, base: torch.Tensor, W: torch.Tensor, tau: float, n_photos: int, settled: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """photo_zero_share's counts over the settled texels alone ((h, w) bool ``settled``): the
    constant part of the counts while the free texels are optimized on their own."""
    keep = settled[None]
    return _photo_counts(lv.idx, base & keep, W, tau, n_photos)


def photo_zero_share(
    lv: Level, base: torch.Tensor, W: torch.Tensor, tau: float, n_photos: int, extra: tuple | None = None
) -> torch.Tensor:
    """Per photo: share of the texels it could serve (base) where its weight is zero (<= tau); -1 if none.

    ``extra``: counts (served, zero) of texels outside ``lv`` to add (settled_counts).
    """
    tot, zero = _photo_counts(lv.idx, base, W, tau, n_photos)
    if extra is not None:
        tot, zero = tot + extra[0], zero + extra[1]
    return torch.where(tot > 0, zero / tot.clamp_min(1), torch.full_like(tot, -1.0))


def photos_to_drop(
    lv: Level, base: torch.Tensor, W: torch.Tensor, tau: float, tau_w: float, n_photos: int, extra: tuple | None = None
) -> list[int]:
    """Photos whose weight is zero (<= tau) on more than tau_w of the texels they could serve
    (Sec. 4.3 i): "the portion of zero value weight in W_k (regarding the mask) exceeds tau_w").

    ``W``: losses.selection_weights, what the activation threshold reads.
    """
    share = photo_zero_share(lv, base, W, tau, n_photos, extra)
    return [int(k) for k in torch.nonzero(share > tau_w).flatten().tolist()]


def dropped_slot_mask(
    lv: Level, eliminated: torch.Tensor, dropped: set[int], W: torch.Tensor | None = None
) -> torch.Tensor:
    """Slots of dropped photos, except the best one of a texel that no other photo serves.

    Removing a texel's last source would leave a hole the optimization cannot fill (the paper,
    Sec. 4.3: "improper photo or pixel removal can cause irreversible color loss"; it names no
    remedy, this one is the project's).
    """
    base = lv.visible & ~eliminated
    if not dropped:
        return torch.zeros_like(base)
    dset = torch.tensor(sorted(dropped), device=lv.idx.device)
    ds = torch.isin(lv.idx, dset) & base
    need = base.any(0) & ~(base & ~ds).any(0)
    score = W if W is not None else lv.z0
    best = argmax0(torch.where(base, score, torch.full_like(score, -1.0)))
    keep = torch.zeros_like(ds).scatter_(0, best, True) & need[None]
    return ds & ~keep


def settled_texels(
    lv: Level, active: torch.Tensor, base: torch.Tensor, k: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """Texels whose active candidates all agree, within ``k`` times the level's photometric
    noise sigma_c (Level.noise) of their Q-weighted mean, and the candidates that agree there.

    There the objective has nothing to decide: no occluder to reject, no misregistration or
    relief to choose between, and a blend averages the photos' noise away. The optimization
    leaves these texels at the Q-proportional blend of every candidate (``base``: active or not)
    within the same distance of that mean, and spends its iterations on the others (a level
    where every texel is settled runs none). Candidates that were left out and disagree (an
    occluder the coarser level or the elimination removed) stay out.

    Shapes: active, base (K, h, w) bool (active within base, as update_activation makes it)
    -> settled (h, w) bool, agree (K, h, w) bool.
    """
    a = active.to(lv.Q.dtype) * lv.Q
    wsum = a.sum(0)
    mu = (a[:, None] * lv.colours).sum(0) / wsum.clamp_min(1e-12)
    d2 = ((lv.colours - mu[None]) ** 2).sum(1)
    near = d2 <= (k * lv.noise) ** 2
    worst_ok = (near | ~active).all(0)
    settled = lv.mask & (wsum > 0) & worst_ok
    return settled, base & near & settled[None]
