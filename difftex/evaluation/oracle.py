"""Upper bounds of texturing by photo selection, given the ground truth (evaluation only).

A method that textures a texel with a weighted blend or a selection of the photos that see it
(difftex, averaging, MRF, texrecon, MeshLab) cannot score better than the best choice among
those photos. :func:`patch_oracle` makes that choice with the ground truth in hand: per texel,
the photo whose neighbourhood is closest to the truth. Its score bounds what any selection of
patches that size can reach; a 1-texel patch picks each texel's luckiest noise sample, so the
bound is only meaningful at patch sizes where noise averages out (evaluation/bounds.py reports
several). No library offers this (it needs the candidates' texel-space colours, which only the
optimizer's photo mapping produces).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from difftex.errors import DifftexError


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
    if colours.ndim != 4 or colours.shape[1] != 3:
        raise DifftexError(f"patch_oracle: colours must be (K, 3, H, W), got {tuple(colours.shape)}")
    K, _, H, W = colours.shape
    if visible.shape != (K, H, W) or ref.shape != (3, H, W):
        raise DifftexError(
            f"patch_oracle: visible {tuple(visible.shape)} / ref {tuple(ref.shape)} do not match colours "
            f"{tuple(colours.shape)}"
        )
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
