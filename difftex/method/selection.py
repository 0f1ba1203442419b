"""Selection: the optimized weights turned into one photo per region, feathered across seams.

The optimized W of a texel where the photos disagree only by parallax (recessed windows,
reveals) stays spread over 3-5 photos: every one of them is consistent enough to keep, none is
an outlier to drop, so the blend is blurred. Selection keeps what the optimization learnt (which
photos are occluded or inconsistent where: their W is ~0) and picks, per patch of texels, the
single photo with the best score W x Q (Q = Q_a Q_c Q_r: frontal, consistent, resolved), with a
Potts cost on label changes between neighbouring patches so seams are few and short:

    E(l) = sum_p sum_{t in p} (1 - s_t(l_p) / max_n s_t(n)) + lambda * patch * sum_{p~q} [l_p != l_q]

solved by alpha-expansion graph cuts (PyMaxflow, as the MRF baseline). The selected photo's
indicator is blurred by a Gaussian of ``select_feather`` texels, so a seam is a short cross-fade;
a texel whose selected photo does not see it keeps its optimized W. Where the photos agree
within noise (the settled texels, difftex.method.elimination.settled_texels) the blend stays and
the data cost is zero, so the seams run there.
"""

from __future__ import annotations

import numpy as np
import torch

from difftex.method.filters import blur, masked_blur

UNSEEN_COST = 2.0  # a photo that does not see a texel (or holds no weight there) costs more than any that does


def texel_costs(W: torch.Tensor, Q: torch.Tensor, idx: torch.Tensor, n_photos: int) -> torch.Tensor:
    """Per texel and photo, the data cost 1 - s / max s with the score s = W Q.

    Args:
        W: (K, h, w) optimized weights; Q: (K, h, w) quality of each slot; idx: (K, h, w) photo
            index of each slot (-1 empty).
        n_photos: number of photos (labels).

    Returns:
        (n_photos, h, w) costs in [0, 1], ``UNSEEN_COST`` where the photo holds no weight.
    """
    if W.shape != Q.shape or W.shape != idx.shape:
        raise ValueError(f"W, Q and idx must have one shape, got {W.shape}, {Q.shape}, {idx.shape}")
    score = (W * Q.clamp_min(0)).float()
    best = score.max(0).values.clamp_min(1e-12)
    rel = score / best
    cost = torch.full((n_photos, *W.shape[1:]), UNSEEN_COST, dtype=torch.float32, device=W.device)
    ok = (idx >= 0) & (W > 0)
    flat = cost.view(n_photos, -1)
    for j in range(W.shape[0]):  # a texel's slots hold distinct photos: no two writes collide
        m = ok[j].reshape(-1)
        flat[idx[j].reshape(-1)[m], torch.nonzero(m).flatten()] = (1.0 - rel[j]).reshape(-1)[m]
    return cost


def patch_costs(cost: np.ndarray, patch: int) -> np.ndarray:
    """(L, h, w) texel costs summed over patch x patch blocks: (ph, pw, L) (the last blocks partial)."""
    L, h, w = cost.shape
    ph, pw = -(-h // patch), -(-w // patch)
    pad = np.zeros((L, ph * patch, pw * patch), np.float64)
    pad[:, :h, :w] = cost
    return pad.reshape(L, ph, patch, pw, patch).sum((2, 4)).transpose(1, 2, 0)


def solve_potts(unary: np.ndarray, smooth: float, max_cycles: int = 5) -> np.ndarray:
    """Labels (ph, pw) minimising unary (ph, pw, L) + Potts ``smooth`` over 4-neighbours
    (alpha-expansion; PyMaxflow's aexpansion_grid)."""
    import maxflow.fastmin as fm

    init = np.argmin(unary, axis=-1).astype(np.int64)
    if unary.shape[-1] == 1 or smooth == 0:
        return init
    V = smooth * (1.0 - np.eye(unary.shape[-1]))
    return np.asarray(fm.aexpansion_grid(unary.astype(np.float64), V, max_cycles=max_cycles, labels=init), np.int64)


def select_weights(
    W: torch.Tensor,
    Q: torch.Tensor,
    idx: torch.Tensor,
    mask: torch.Tensor,
    n_photos: int,
    patch: int = 4,
    smoothness: float = 1.0,
    feather: float = 1.0,
    free: torch.Tensor | None = None,
) -> tuple[torch.Tensor, dict]:
    """Weights of one selected photo per patch, feathered across seams.

    Args:
        W, Q, idx: (K, h, w) optimized weights, quality and photo index of the slots.
        mask: (h, w) bool texels of the polygon.
        n_photos: number of photos (labels).
        patch: patch side in texels (the graph's nodes).
        smoothness: Potts cost per texel of seam, in units of the per-texel data cost.
        feather: Gaussian sigma of the cross-fade at seams, texels (0: hard seams).
        free: (h, w) bool texels where the photos disagree (None: all). Elsewhere the photos
            agree within noise: the optimized blend stays (it averages their noise away), their
            data cost is zero, so seams go there, where a change of photo does not show.

    Returns:
        (K, h, w) weights (normalised where any photo is selected; the input W elsewhere) and
        statistics: the patches, the labels used, the share of texels that kept their W.
    """
    if patch < 1 or smoothness < 0 or feather < 0:
        raise ValueError("patch must be >= 1, smoothness and feather >= 0")
    K, h, w = W.shape
    cost = texel_costs(W, Q, idx, n_photos)
    chosen = mask if free is None else mask & free
    cost = torch.where(chosen[None], cost, torch.zeros_like(cost))
    used = [n for n in range(n_photos) if bool((cost[n] < UNSEEN_COST).any())]
    if len(used) <= 1:
        return W, {"patches": 0, "labels": len(used), "kept_share": 1.0}
    unary = patch_costs(cost[used].cpu().numpy(), patch)
    labels = solve_potts(unary, smoothness * patch)
    # per-texel label maps of the used photos, blurred into cross-fades at the seams
    lab = torch.from_numpy(labels).to(W.device)
    lab = lab.repeat_interleave(patch, 0).repeat_interleave(patch, 1)[:h, :w]
    ind = blur(torch.stack([(lab == i).float() for i in range(len(used))]), feather)  # (L, h, w)
    pos = torch.full((n_photos,), -1, dtype=torch.long, device=W.device)
    pos[torch.tensor(used, device=W.device)] = torch.arange(len(used), device=W.device)
    slot_label = pos[idx.clamp_min(0)]  # (K, h, w) label index of each slot's photo, -1 if unused
    ok = (idx >= 0) & (W > 0) & (slot_label >= 0)
    sel = torch.where(ok, torch.gather(ind, 0, slot_label.clamp_min(0)), torch.zeros_like(W))
    total = sel.sum(0, keepdim=True)
    # a texel whose selected photo(s) hold no weight there keeps the optimized blend
    has = total[0] > 0.05
    out = torch.where(has[None], sel / total.clamp_min(1e-12), W)
    if free is not None:  # selection where the photos disagree, cross-faded into the blend
        alpha = blur(free.float()[None], feather)[0]
        out = alpha[None] * out + (1.0 - alpha[None]) * W
    n_mask = int(mask.sum())
    stats = {
        "patches": int(labels.size),
        "labels": len(np.unique(labels)),
        "kept_share": float((~has & mask).sum()) / max(n_mask, 1),
        "selected_share": float((chosen & has).sum()) / max(n_mask, 1),
    }
    return out, stats


def detail_band(blended: torch.Tensor, selected: torch.Tensor, mask: torch.Tensor, sigma: float) -> torch.Tensor:
    """The blend's colours below a Gaussian of ``sigma`` texels plus the selection's detail above it:

        U = G * U_blend + (U_sel - G * U_sel)

    as in multi-band blending: the selected photo keeps its edges (mullions, carvings) where the
    blend of photos that disagree by parallax smears them, while its noise and exposure below the
    band are averaged with the other photos'. The low-pass is normalised over ``mask``.

    Args:
        blended: (3, h, w) the optimized blend's colours.
        selected: (3, h, w) the selection's colours.
        mask: (h, w) bool texels to filter over and change: the polygon's texels that a photo sees.
        sigma: Gaussian sigma of the band's edge, texels (> 0).

    Returns:
        (3, h, w) colours in [0, 1], the blend's outside the mask.
    """
    if blended.shape != selected.shape or blended.shape[1:] != mask.shape:
        raise ValueError(f"blended, selected (3, h, w) and mask (h, w) must match, got "
                         f"{tuple(blended.shape)}, {tuple(selected.shape)}, {tuple(mask.shape)}")
    if sigma <= 0:
        raise ValueError(f"sigma must be > 0, got {sigma}")
    out = masked_blur(blended, mask, sigma) + selected - masked_blur(selected, mask, sigma)
    # the sum of a band and a detail can leave the colours' range next to strong edges
    return torch.where(mask[None], out.clamp(0.0, 1.0), blended)
