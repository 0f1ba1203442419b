"""Semi-global aggregation of a plane sweep's cost volume (Hirschmueller, "Stereo processing by
semiglobal matching and mutual information", PAMI 2008), and the occlusion-robust per-texel cost
it aggregates.

A facade's relief is made of flat steps (recessed panes, balconies, a cornice) on a wall whose
plaster, seen through a camera's noise, gives every height about the same cost. Taking each
texel's cheapest height on its own follows that noise (false relief over the plaster) and, near
an opening, the strongest edge within the matching window (halos). Semi-global matching adds, along
straight paths through the texel grid, a penalty ``p1`` for a change of one height step between
neighbours and ``p2`` for a larger jump, and sums the paths' costs (eq. 13 of the paper):

    L_r(p, d) = C(p, d) + min(L_r(p - r, d), L_r(p - r, d +- 1) + p1, min_i L_r(p - r, i) + p2)
                - min_i L_r(p - r, i),        S(p, d) = sum_r L_r(p, d).

The result is a field of flat regions with edges where the photos' evidence is, in a time linear
in the volume. OpenCV's StereoSGBM implements this only for a rectified image pair (its own
cost); a sweep over several photos needs it on an arbitrary volume, so it is written out here
(one vectorised step per row or column, in torch, on the sweep's device).

Occlusion: at a recess's true height, the photos from one side do not see the texels behind the
reveal on that side, and they disagree with the others there. The cost of a height at a texel is
therefore the mean over the ``share`` of photos that agree best (Kang, Szeliski and Chai,
"Handling occlusions in dense multi-view stereo", CVPR 2001), not over all of them.

Layer: method (difftex.method.relief builds the volume).
"""

from __future__ import annotations

import math

import torch

# the four paths along the grid's rows and columns, each way, and the four diagonals: (dy, dx)
DIRECTIONS_4 = ((0, 1), (0, -1), (1, 0), (-1, 0))
DIRECTIONS_8 = DIRECTIONS_4 + ((1, 1), (1, -1), (-1, 1), (-1, -1))


def best_share_mean(costs: torch.Tensor, valid: torch.Tensor, share: float, least: int = 3) -> torch.Tensor:
    """Per texel, the mean of the lowest costs: those of the best ``share`` of the valid photos (at
    least ``least`` of them, or all there are).

    Args:
        costs: (P, h, w) per-photo costs; valid: (P, h, w) bool photos that compare there.
        share: in (0, 1]; 1 is the plain mean over the valid photos.

    Returns:
        (h, w) the mean of the kept costs; inf where no photo is valid.
    """
    if costs.shape != valid.shape:
        raise ValueError(f"costs {tuple(costs.shape)} and valid {tuple(valid.shape)} must match")
    if not 0 < share <= 1:
        raise ValueError(f"share must be in (0, 1], got {share}")
    n = valid.sum(0)
    if share == 1:  # every valid photo: no sort needed (the sort is most of this function's time)
        total = torch.where(valid, costs, torch.zeros_like(costs)).sum(0)
        return torch.where(n > 0, total / n.clamp_min(1).float(), torch.full_like(total, math.inf))
    k = torch.minimum(torch.clamp((n.float() * share).ceil().long(), min=least), n)
    srt = torch.where(valid, costs, torch.full_like(costs, math.inf)).sort(0).values
    rank = torch.arange(costs.shape[0], device=costs.device).view(-1, 1, 1)
    kept = rank < k
    total = torch.where(kept, srt, torch.zeros_like(srt)).sum(0)
    return torch.where(k > 0, total / k.clamp_min(1).float(), torch.full_like(total, math.inf))


def path_cost(cost: torch.Tensor, direction: tuple[int, int], p1: float, p2: float) -> torch.Tensor:
    """L_r of one path direction over the whole volume.

    Args:
        cost: (D, h, w) finite costs, the labels in order (label d and d + 1 are neighbouring heights).
        direction: (dy, dx), each in {-1, 0, 1}, not both 0: the step from a texel's predecessor to it.
        p1: penalty of a one-label change between neighbours; p2 (>= p1): of a larger one.

    Returns:
        (D, h, w) the path's aggregated cost.

    A diagonal path steps one column at a time and one row, so it runs over the columns with the
    previous column's costs shifted by a row; texels whose predecessor lies outside the grid start
    a new path (their L is their own cost).
    """
    dy, dx = direction
    if (dy, dx) == (0, 0) or max(abs(dy), abs(dx)) != 1:
        raise ValueError(f"direction must be a unit grid step, got {direction}")
    c = cost
    if dx == 0:  # a vertical path is a horizontal one on the transposed grid
        c, dx, dy = c.transpose(1, 2), dy, 0
    if dx < 0:
        c, dy_flip = c.flip(2), dy
    else:
        dy_flip = dy
    out = torch.empty_like(c)
    prev = c[:, :, 0]
    out[:, :, 0] = prev
    inf = torch.full_like(prev[:1], math.inf)
    for x in range(1, c.shape[2]):
        p = prev
        if dy_flip:  # the predecessor of row y is row y - dy: shift, a new path at the edge
            zero = torch.zeros_like(p[:, :1])
            p = torch.cat([zero, p[:, :-1]], 1) if dy_flip > 0 else torch.cat([p[:, 1:], zero], 1)
        m = p.min(0, keepdim=True).values
        near = torch.minimum(torch.cat([p[1:], inf]), torch.cat([inf, p[:-1]])) + p1
        prev = c[:, :, x] + torch.minimum(torch.minimum(p, near), m + p2) - m
        out[:, :, x] = prev
    if direction[1] < 0 or (direction[1] == 0 and direction[0] < 0):
        out = out.flip(2)
    return out.transpose(1, 2) if direction[1] == 0 else out


def aggregate(cost: torch.Tensor, p1: float, p2: float, directions=DIRECTIONS_8) -> torch.Tensor:
    """S = sum over the path directions of L_r (semi-global matching).

    Args:
        cost: (D, h, w) costs; inf (no photo compares) is replaced by the largest finite cost, so
            those texels carry no preference and pass their neighbours' on.
        p1, p2: the penalties of :func:`path_cost` (0 <= p1 <= p2).

    Returns:
        (D, h, w) the aggregated cost; its argmin over D is the regularised label.
    """
    if cost.dim() != 3:
        raise ValueError(f"cost must be (D, h, w), got {tuple(cost.shape)}")
    if not 0 <= p1 <= p2:
        raise ValueError(f"penalties must satisfy 0 <= p1 <= p2, got {p1}, {p2}")
    finite = torch.isfinite(cost)
    top = float(cost[finite].max()) if bool(finite.any()) else 0.0
    c = torch.where(finite, cost, torch.full_like(cost, top))
    total = torch.zeros_like(c)
    for d in directions:
        total += path_cost(c, d, p1, p2)
    return total

