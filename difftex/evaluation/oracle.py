"""Upper bounds of texturing by photo selection and blending, given the ground truth (evaluation only).

A method that textures each patch from one of the photos that see it (MRF, texrecon, the most
frontal photo, a sparse difftex) cannot score better than the best choice among those photos.
:func:`patch_oracle` makes that choice with the ground truth in hand: per texel, the photo whose
neighbourhood is closest to the truth. Its score bounds what any selection of patches that size
can reach; a 1-texel patch picks each texel's luckiest noise sample, so the bound is only
meaningful at patch sizes where noise averages out (evaluation/bounds.py reports several). A
blend can score above it by averaging the photos' noise: :func:`blend_oracle` fits each tile's
blend weights to the truth, about the most a blend can reach, and :func:`blend_summary` says what
a blend is made of (photos per texel, their frontality and resolution). :func:`tail_causes`
sorts a texture's worst texels by what the photos hold there. No library offers these (they need
the candidates' texel-space colours, which only the optimizer's photo mapping produces).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from difftex.errors import DifftexError


def _check_candidates(fn: str, colours: torch.Tensor, visible: torch.Tensor, ref: torch.Tensor) -> tuple[int, int, int]:
    """(K, H, W) of candidates (K, 3, H, W) with their visibility (K, H, W) and the truth (3, H, W);
    DifftexError naming ``fn`` otherwise."""
    if colours.ndim != 4 or colours.shape[1] != 3:
        raise DifftexError(f"{fn}: colours must be (K, 3, H, W), got {tuple(colours.shape)}")
    K, _, H, W = colours.shape
    if visible.shape != (K, H, W) or ref.shape != (3, H, W):
        raise DifftexError(
            f"{fn}: visible {tuple(visible.shape)} / ref {tuple(ref.shape)} do not match colours "
            f"{tuple(colours.shape)}"
        )
    return K, H, W


def patch_oracle(
    colours: torch.Tensor, visible: torch.Tensor, ref: torch.Tensor, patch: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """Per texel, the candidate whose ``patch`` x ``patch`` neighbourhood is closest to ``ref``.

    The distance is the mean squared RGB difference over the texels of the neighbourhood that
    the candidate sees; a candidate must see at least half of its neighbourhood (so that one
    lucky texel at the edge of its view does not win), and where none does, the one that sees
    the most of it is taken.

    Args:
        colours: (K, 3, H, W) the candidates' colours in texel space.
        visible: (K, H, W) bool, which candidate sees which texel.
        ref: (3, H, W) the ground truth at the same texels.
        patch: odd neighbourhood side, texels (1: the texel alone).

    Returns:
        texture (3, H, W): the chosen candidate's colour (zero where no candidate sees the texel);
        choice (H, W) long: the chosen candidate, -1 where none sees the texel.
    """
    K, H, W = _check_candidates("patch_oracle", colours, visible, ref)
    if patch < 1 or patch % 2 == 0:
        raise DifftexError(f"patch_oracle: patch must be an odd number >= 1, got {patch}")
    vis = visible.float()
    d2 = ((colours - ref[None]) ** 2).sum(1) * vis  # (K, H, W)
    r = patch // 2
    # box sums over the neighbourhood; count_include_pad keeps the window's area fixed at edges
    ssum = F.avg_pool2d(d2[:, None], patch, 1, r, count_include_pad=True)[:, 0]
    cover = F.avg_pool2d(vis[:, None], patch, 1, r, count_include_pad=True)[:, 0]
    mean = ssum / cover.clamp_min(1e-12)
    enough = cover >= 0.5 * cover.amax(0, keepdim=True).clamp(max=1.0)
    score = torch.where(visible & enough, mean, torch.full_like(mean, float("inf")))
    # where no candidate that sees the texel covers enough of its neighbourhood: the one covering most
    fallback = torch.where(visible, -cover, torch.full_like(cover, float("inf"))).argmin(0)
    choice = torch.where(torch.isfinite(score).any(0), score.argmin(0), fallback)
    seen = visible.any(0)
    tex = torch.gather(colours, 0, choice[None, None].expand(1, 3, H, W))[0] * seen[None]
    return tex, torch.where(seen, choice, torch.full_like(choice, -1))


def blend_oracle(
    colours: torch.Tensor,
    visible: torch.Tensor,
    ref: torch.Tensor,
    tile: int,
    iters: int = 200,
    lr: float = 0.1,
    chunk_values: int = 2**25,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Per ``tile`` x ``tile`` block of texels, the convex blend of the candidates closest to ``ref``.

    Each block gets one weight per candidate (non-negative, summing to one), fitted to the ground
    truth by least squares: T(x) = sum_k w_k v_k(x) c_k(x) / sum_k w_k v_k(x), the weights of the
    candidates that see x renormalised there, as a blend of photos does. With the truth in hand
    this is near the best any blend with block-constant weights can do; it averages noise where
    the candidates agree with the truth, which a selection cannot. Per-texel weights would fit
    each texel's noise (K unknowns for 3 values), so the block must hold many more values than
    there are candidates for the figure to mean anything (tile 15: 675 values). Fitted with Adam
    on the weights' logits from the plain average (scipy's NNLS would need one call per block
    and cannot renormalise per texel); the blocks are independent and batched.

    Args:
        colours: (K, 3, H, W) the candidates' colours in texel space.
        visible: (K, H, W) bool, which candidate sees which texel.
        ref: (3, H, W) the ground truth at the same texels.
        tile: block side, texels (>= 1).
        iters: Adam steps; lr: its step on the logits.
        chunk_values: blocks are fitted in batches of about this many candidate values (memory).

    Returns:
        texture (3, H, W): the blend (zero where no candidate sees the texel);
        weights (K, H, W): each candidate's share of each texel, w_k v_k(x) / sum_j w_j v_j(x)
        (zero where no candidate sees the texel), for :func:`blend_summary`.
    """
    K, H, W = _check_candidates("blend_oracle", colours, visible, ref)
    if tile < 1 or iters < 0:
        raise DifftexError(f"blend_oracle: tile must be >= 1 and iters >= 0, got {tile}, {iters}")
    ny, nx = -(-H // tile), -(-W // tile)
    ph, pw = ny * tile - H, nx * tile - W

    def blocks(t: torch.Tensor) -> torch.Tensor:
        """(..., H, W) -> (ny * nx, ..., tile * tile), padded with zeros (unseen)."""
        t = F.pad(t, (0, pw, 0, ph))
        lead = t.shape[:-2]
        t = t.reshape(*lead, ny, tile, nx, tile).movedim((-4, -2), (0, 1)).reshape(ny * nx, *lead, tile * tile)
        return t

    c = blocks(colours)  # (B, K, 3, P)
    v = blocks(visible.float())  # (B, K, P)
    g = blocks(ref)  # (B, 3, P)
    out = torch.zeros_like(g)
    share = torch.zeros_like(v)
    step = max(1, chunk_values // max(1, K * 3 * tile * tile))
    for b0 in range(0, c.shape[0], step):
        cb, vb, gb = c[b0:b0 + step], v[b0:b0 + step], g[b0:b0 + step]
        sees = vb.sum(-1) > 0  # (b, K)
        # start from the plain average: equal weights over the candidates that see the block
        z = torch.where(sees, 0.0, float("-inf")).requires_grad_(True)
        opt = torch.optim.Adam([z], lr=lr)
        seen = (vb.sum(1) > 0).float()[:, None]  # (b, 1, P)

        def blend(z=z, cb=cb, vb=vb, sees=sees):
            w = torch.softmax(torch.where(sees.any(1, keepdim=True), z, torch.zeros_like(z)), dim=1)
            wv = w[..., None] * vb  # (b, K, P)
            wv = wv / wv.sum(1, keepdim=True).clamp_min(1e-12)
            return (wv[:, :, None] * cb).sum(1), wv

        for _ in range(iters):
            loss = (((blend()[0] - gb) ** 2) * seen).sum()
            opt.zero_grad()
            loss.backward()
            opt.step()
        with torch.no_grad():
            t, wv = blend()
            out[b0:b0 + step] = t * seen
            share[b0:b0 + step] = wv

    def unblock(t: torch.Tensor) -> torch.Tensor:
        """(ny * nx, C, tile * tile) -> (C, H, W), the inverse of ``blocks``."""
        C = t.shape[1]
        return t.reshape(ny, nx, C, tile, tile).permute(2, 0, 3, 1, 4).reshape(C, ny * tile, nx * tile)[:, :H, :W]

    return unblock(out), unblock(share)


def blend_summary(weights: torch.Tensor, mask: torch.Tensor, features: dict[str, torch.Tensor]) -> dict:
    """What a blend is made of, averaged over the texels of ``mask``: the effective number of
    photos per texel, 1 / sum_k w_k^2 (1: one photo; n: n photos equally), and the
    weight-averaged value of each per-photo feature (frontality, pixels per texel ...).

    Args:
        weights: (K, H, W) each photo's share of each texel (summing to one where a photo sees it).
        mask: (H, W) bool texels to average over (texels without weight are left out).
        features: name -> (K, H, W) the photos' values.

    Returns:
        dict: ``photos_per_texel`` and each feature's name -> mean over the texels.
    """
    if weights.ndim != 3 or mask.shape != weights.shape[1:]:
        raise DifftexError(f"blend_summary: weights (K, H, W) {tuple(weights.shape)} / mask {tuple(mask.shape)}")
    total = weights.sum(0)
    m = mask & (total > 0)
    if not bool(m.any()):
        raise DifftexError("blend_summary: no texel of the mask has weight")
    w = weights[:, m] / total[m]
    out = {"photos_per_texel": float((1.0 / (w**2).sum(0)).mean())}
    for name, f in features.items():
        if f.shape != weights.shape:
            raise DifftexError(f"blend_summary: feature {name} {tuple(f.shape)} is not shaped as the weights")
        out[name] = float((w * f[:, m]).sum(0).mean())
    return out


def tail_causes(
    colours: torch.Tensor,
    visible: torch.Tensor,
    cos: torch.Tensor,
    ref: torch.Tensor,
    texture: torch.Tensor,
    mask: torch.Tensor,
    patch: int = 5,
    near: float = 0.15,
    frontal: int = 3,
) -> dict:
    """Why a texture's worst texels (its Error 95 % tail) are wrong, in shares of those texels.

    Args:
        colours: (K, 3, H, W) the candidates' colours; visible: (K, H, W) bool; cos: (K, H, W)
            their frontality (Q_a).
        ref: (3, H, W) the ground truth; texture: (3, H, W) the texture; mask: (H, W) bool texels scored.
        patch: neighbourhood side over which a photo's distance to the truth is averaged.
        near: a photo is "right" where that mean distance is below this (RGB, in [0, sqrt 3]).
        frontal: how many of the texel's most frontal photos the last share looks at.

    Returns:
        dict: ``error95`` of the texture over ``mask``; the shares of its tail (texels at or above
        it) where ``median_photo_worse`` the median candidate's distance to the truth exceeds
        ``error95``, ``no_photo_right`` no candidate is right, ``frontal_right`` one of the
        ``frontal`` most frontal candidates is right; ``tail_texels``.
    """
    K, H, W = _check_candidates("tail_causes", colours, visible, ref)
    if cos.shape != (K, H, W) or texture.shape != (3, H, W) or mask.shape != (H, W):
        raise DifftexError(
            f"tail_causes: cos {tuple(cos.shape)}, texture {tuple(texture.shape)}, mask {tuple(mask.shape)} "
            f"do not match colours {tuple(colours.shape)}"
        )
    seen = visible.any(0) & mask
    err = ((texture - ref) ** 2).sum(0).sqrt()
    if not bool(seen.any()):
        raise DifftexError("tail_causes: no texel is both in the mask and seen by a candidate")
    e95 = float(torch.quantile(err[seen].double(), 0.95))
    tail = seen & (err >= e95)
    d = ((colours - ref[None]) ** 2).sum(1).sqrt()
    med = torch.where(visible, d, torch.full_like(d, float("nan"))).nanmedian(0).values
    r = patch // 2
    vis = visible.float()
    num = F.avg_pool2d((d * vis)[:, None], patch, 1, r, count_include_pad=True)[:, 0]
    den = F.avg_pool2d(vis[:, None], patch, 1, r, count_include_pad=True)[:, 0]
    dp = torch.where(visible, num / den.clamp_min(1e-12), torch.full_like(num, float("inf")))
    right = dp < near
    order = torch.where(visible, cos, torch.full_like(cos, -2.0)).argsort(0, descending=True)[:frontal]
    front_right = torch.gather(right & visible, 0, order).any(0)
    n = float(tail.sum())
    return {
        "error95": e95,
        "tail_texels": int(n),
        "median_photo_worse": float((tail & (med > e95)).sum()) / n,
        "no_photo_right": float((tail & ~right.any(0)).sum()) / n,
        "frontal_right": float((tail & front_right).sum()) / n,
    }
