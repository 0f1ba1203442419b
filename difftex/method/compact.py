"""The texel-space objective evaluated only where the candidates disagree.

Once the settled texels are fixed at their blend (OptimizeConfig.settle_sigma,
elimination.settled_texels), the gradient is zero there and L_Render, the ghost term and L_Persp
of those texels are constants; only the free texels and their neighbours (through L_Para) matter.
On facades most texels are settled (82-88 % of herzjesu-p8's facade at the `balanced` levels), so
the free texels are cut out in square tiles, each with a one-texel ring of its neighbours (the
halo), stacked in a strip, and the objective runs on the strip:

    strip rows: [halo | T tile rows | halo | separator] per tile, T + 2 columns

Every term is local (a texel and its up/left neighbour), so on the tiles' interiors the strip's
gradient equals the full level's, to float rounding: the halo carries the neighbours' current
weights (gathered every iteration from the level's logits), and a separator row outside the
polygon's mask (pair_ok false) keeps stacked tiles from meeting. The optimizer's other steps
(Adam, activation, elimination, photo drop, convergence) stay on the whole level. Tile size:
the one of 8, 16 and 32 texels with the smallest strip; none when the strip would not be
smaller than ``max_share`` of the level.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from difftex.method import losses
from difftex.method.gradient import TexelData, texel_data, texel_value_and_grad


@dataclass
class TileLayout:
    """Where each strip position reads the level: flat texel index, -1 outside the level."""

    src: torch.Tensor  # (hc, wc) long, index into the level's h * w texels, -1 pad or separator
    interior: torch.Tensor  # (hc, wc) bool: free texels of a tile's interior (the gradient is kept)
    tile: int

    @property
    def shape(self) -> tuple[int, int]:
        return int(self.src.shape[0]), int(self.src.shape[1])


def tile_layout(free: torch.Tensor, max_share: float = 0.35, tiles: tuple[int, ...] = (8, 16, 32)) -> TileLayout | None:
    """The strip of tiles that covers every free texel, or None when it would not pay.

    Args:
        free: (h, w) bool, the texels whose weights are optimized.
        max_share: return None when the strip has more than this share of the level's texels.

    Returns:
        The layout; its strip has (T + 3) rows per active tile and T + 2 columns.
    """
    h, w = free.shape
    if not bool(free.any()):
        return None
    grids = {T: _tiles_with_free(free, T) for T in tiles}
    T = min(tiles, key=lambda t: int(grids[t].sum()) * (t + 3) * (t + 2))
    if int(grids[T].sum()) * (T + 3) * (T + 2) > max_share * h * w:
        return None
    act = torch.nonzero(grids[T])  # (n, 2) tile row, column
    dev = free.device
    dy = torch.arange(-1, T + 2, device=dev)  # halo, T rows, halo, separator
    dx = torch.arange(-1, T + 1, device=dev)
    Y = act[:, 0, None, None] * T + dy[None, :, None]
    X = act[:, 1, None, None] * T + dx[None, None, :]
    valid = (Y >= 0) & (Y < h) & (X >= 0) & (X < w) & (dy != T + 1)[None, :, None]
    src = torch.where(valid, Y * w + X, torch.full_like(Y, -1))
    inner = ((dy >= 0) & (dy < T))[None, :, None] & ((dx >= 0) & (dx < T))[None, None, :] & valid
    interior = inner & free.reshape(-1)[src.clamp_min(0)]
    n = act.shape[0]
    return TileLayout(src=src.reshape(n * (T + 3), T + 2), interior=interior.reshape(n * (T + 3), T + 2), tile=T)


def _tiles_with_free(free: torch.Tensor, T: int) -> torch.Tensor:
    """(ceil(h / T), ceil(w / T)) bool: the T x T tiles that hold a free texel."""
    h, w = free.shape
    ty, tx = -(-h // T), -(-w // T)
    fp = torch.zeros(ty * T, tx * T, dtype=torch.bool, device=free.device)
    fp[:h, :w] = free
    return fp.reshape(ty, T, tx, T).any(3).any(1)


def gather(x: torch.Tensor, lay: TileLayout) -> torch.Tensor:
    """(..., h, w) -> (..., hc, wc): the level's values at the strip's positions, 0 (False) at pads."""
    flat = x.flatten(-2)[..., lay.src.clamp_min(0)]
    keep = lay.src >= 0
    return flat & keep if flat.dtype == torch.bool else flat * keep.to(flat.dtype)


def scatter(xc: torch.Tensor, lay: TileLayout, shape: tuple[int, ...]) -> torch.Tensor:
    """(..., hc, wc) -> (..., h, w): the strip's interior values at their texels, 0 elsewhere."""
    out = torch.zeros(shape, dtype=xc.dtype, device=xc.device)
    sel = lay.interior
    out.flatten(-2)[..., lay.src[sel]] = xc[..., sel]
    return out


@dataclass
class CompactObjective:
    """The strip's fixed data for one level (TexelData, L_Para's G and slot correspondences)."""

    layout: TileLayout
    data: TexelData
    G: torch.Tensor  # (hc, wc)
    matches: dict
    D: dict | None = None

    @property
    def slots(self) -> int:
        return int(self.data.Q.numel())


def compact_objective(
    lay: TileLayout, colours, Q, cost, G, idx, mask, n_tex: float, ghost_margin: float, fixed: bool, use_para: bool
) -> CompactObjective:
    """Gather a level's fixed tensors (shapes as difftex.method.levels.Level) onto the strip.
    ``n_tex`` stays the level's texel count, so the strip's gradient is the level's."""
    idx_c = torch.where(gather(idx >= 0, lay), gather(idx, lay), torch.full(lay.shape, -1, device=idx.device))
    mask_c = gather(mask, lay)
    data = texel_data(gather(colours, lay), gather(Q, lay), gather(cost, lay), n_tex, ghost_margin)
    matches = {a: losses.neighbour_match(idx_c, mask_c, a, fixed=fixed) for a in (1, 2)} if use_para else {}
    return CompactObjective(layout=lay, data=data, G=gather(G, lay), matches=matches)


def value_and_grad(z: torch.Tensor, active: torch.Tensor, co: CompactObjective, cfg, refresh_D: bool, fn=None):
    """The terms of L over the strip and dL/dz on the whole level (zero outside the free texels).

    Args:
        z, active: (K, h, w) the level's logits and activation.
        refresh_D: recompute L_Para's edge weights from the current strip (as
            objective.refresh_edge_weights does on the level).
        fn: the compiled texel_value_and_grad, or None (eager).
    """
    lay = co.layout
    z_c, a_c = gather(z, lay), gather(active, lay)
    if cfg.use_para and (co.D is None or refresh_D):
        U = losses.compose(losses.blend_weights(z_c, a_c), co.data.colours)
        co.D = losses.edge_weights(U, co.G, tuple(co.matches))
    terms, g_c = (fn or texel_value_and_grad)(z_c, a_c, co.data, co.D, co.matches, cfg)
    return terms, scatter(g_c, lay, tuple(z.shape))
