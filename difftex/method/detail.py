"""Detail from one photo per facade element (not in the paper).

A blend of photos is never sharper than its photos: where they disagree by parallax (recessed
windows seen from several heights) or by resolution (a drone survey's few close photos), the
optimized W spreads over several of them and the mullions smear. The paper's L_Persp and its
sparsity want few, frontal photos per texel; switching photos per texel or per small patch
(difftex.method.selection) breaks a window into a patchwork of photos.

Here the blend keeps what it does well (occluders removed, exposure, the low frequencies, no
seams) and only the detail above a band comes from photos, one photo per region the size of a
facade element:

    U = G_b * U_blend + sum_l e_l (I_l - G_b * I_l)

with G_b a Gaussian of ``band`` texels, I_l photo l's colours and e_l its share of a texel (its
region's indicator, cross-faded over ``feather`` texels at the seams). The regions are a labelling
of patches by graph cuts (alpha-expansion, PyMaxflow's max-flow):

    E(l) = sum_p D_p(l_p) + sum_{p~q} s_pq [l_p != l_q]

- the data cost D_p(l) of photo l is how far it falls short of the sharpest photo of the texel
  (1 - r_l / max r; r = pixels per texel x cos^2, resolution and frontality in one figure),
  plus its disagreement with the blend below the band (an occluder, a misregistration): a photo
  more than ``agree`` times the second-closest photo's distance off the blend there is no
  candidate. The blend's own detail is a
  label too, of cost 1: it stays where no photo agrees.
- the seam cost s_pq grows with how much the candidates disagree on the patches' texels (their
  colours' spread, in sigma_c): seams are cheap where the photos agree (plain wall, where a change
  of photo does not show) and dear across a window, whose parallax makes the photos disagree, so
  a window comes from one photo.

PyMaxflow's ``aexpansion_grid`` takes one label-pair cost for every edge; the seam cost here
varies per edge, so the expansion moves are built here on PyMaxflow's graph (Boykov, Veksler,
Zabih 2001, the Potts construction of Kolmogorov and Zabih 2004).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from difftex.method.filters import masked_blur
from difftex.method.selection import patch_costs

UNSEEN_COST = 4.0  # a photo that does not see a texel, or disagrees with the blend there
BLEND_COST = 1.0  # the blend's own detail: the fallback where no photo agrees
AGREE_WEIGHT = 0.25  # weight of a candidate's distance to the blend in its data cost


@dataclass(frozen=True)
class DetailSettings:
    """How the detail photos are chosen and composed (``OptimizeConfig.detail_*``)."""

    band: float = 8.0  # sigma of the band, texels: the blend below, one photo's detail above
    patch: int = 8  # graph node side, texels
    smoothness: float = 2.0  # seam cost per texel of seam where the photos agree (units of the data cost)
    feather: float = 1.0  # cross-fade of the seams, texels
    agree: float = 3.0  # a candidate is within this many times the second-closest photo's distance to the blend
    max_labels: int = 24  # at most this many photos compete (the most preferred first)
    cycles: int = 3  # alpha-expansion sweeps

    def __post_init__(self) -> None:
        if self.band <= 0 or self.patch < 1 or self.smoothness < 0 or self.feather < 0 or self.agree <= 0:
            raise ValueError("detail: band and agree must be > 0, patch >= 1, smoothness and feather >= 0")
        if self.max_labels < 1 or self.cycles < 1:
            raise ValueError("detail: max_labels and cycles must be >= 1")


def photo_field(
    values: torch.Tensor, idx: torch.Tensor, present: torch.Tensor | None, n: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """Photo n's dense field out of the slot layout.

    Args:
        values: (K, [C,] h, w) per-slot values.
        idx: (K, h, w) photo index of each slot (-1 empty).
        present: (K, h, w) bool slots that hold a value (the photo sees the texel); None: every slot.
        n: the photo.

    Returns:
        (field ([C,] h, w), where (h, w) bool): zero where photo n has no slot.
    """
    sel = idx == n if present is None else (idx == n) & present
    m = sel if values.dim() == 3 else sel[:, None]
    return (values * m).sum(0), sel.any(0)


def texel_costs(
    resolve: torch.Tensor, low_dist: torch.Tensor, where: torch.Tensor, agree: float
) -> torch.Tensor:
    """Per label and texel, the data cost of taking the detail from it (label 0: the blend).

    A photo's distance to the blend is measured against the second-closest photo's: where the
    blend is a mix of photos that all differ from it a little (parallax smears a recessed pane in
    every one of them), the closest ones set the scale and none is singled out; where the blend
    follows the photos that see past an occluder, those are close and the ones that see the
    occluder stand out by far.

    Args:
        resolve: (L, h, w) how well each photo resolves the texel (0 where it has none).
        low_dist: (L, h, w) distance of each photo's low band to the blend's, in sigma_c.
        where: (L, h, w) bool where each photo has colours.
        agree: a photo is a candidate within this many times the scale (at least 1 sigma_c).

    Returns:
        (L + 1, h, w): the blend's BLEND_COST, then 1 - r / max r + AGREE_WEIGHT (d / (agree scale))^2 for the
        photos, UNSEEN_COST where a photo has no colours or disagrees.
    """
    if resolve.shape != low_dist.shape or resolve.shape != where.shape:
        raise ValueError(f"resolve, low_dist and where must have one shape, got {tuple(resolve.shape)}, "
                         f"{tuple(low_dist.shape)}, {tuple(where.shape)}")
    d = torch.where(where, low_dist, torch.full_like(low_dist, float("inf")))
    second = d.topk(min(2, d.shape[0]), dim=0, largest=False).values[-1]
    scale = agree * torch.where(torch.isfinite(second), second, torch.zeros_like(second)).clamp_min(1.0)
    ok = where & (low_dist <= scale)
    best = torch.where(ok, resolve, torch.zeros_like(resolve)).max(0).values.clamp_min(1e-6)
    # within the gate, the sharpest photo wins; its agreement only breaks near-ties
    cost = 1.0 - resolve / best + AGREE_WEIGHT * (low_dist / scale) ** 2
    cost = torch.where(ok, cost, torch.full_like(cost, UNSEEN_COST))
    blend = torch.full_like(cost[:1], BLEND_COST)
    return torch.cat([blend, cost])


def seam_costs(
    spread: torch.Tensor, mask: torch.Tensor, patch: int, smoothness: float
) -> tuple[np.ndarray, np.ndarray]:
    """The seam cost between each patch and its right and lower neighbour.

        s_pq = smoothness * patch * (1 + (spread_p + spread_q) / 2)

    with spread_p the mean over patch p's texels of the candidates' colour spread in sigma_c
    (capped at 4: a tree or a window is dear enough). Plain wall where the photos agree within
    noise costs about two seam units per texel of seam, a window several.

    Args:
        spread: (h, w) the candidates' colour spread per texel, sigma_c.
        mask: (h, w) bool polygon texels.
        patch: patch side, texels.
        smoothness: cost per texel of seam.

    Returns:
        (right (ph, pw), down (ph, pw)): the cost of a seam to the right / lower neighbour
        (the last column / row unused).
    """
    sums = patch_costs(torch.stack([spread.clamp(0, 4) * mask, mask.float()]).cpu().numpy(), patch)
    sp = sums[..., 0] / np.maximum(sums[..., 1], 1.0)
    right = np.zeros_like(sp)
    down = np.zeros_like(sp)
    right[:, :-1] = 0.5 * (sp[:, :-1] + sp[:, 1:])
    down[:-1] = 0.5 * (sp[:-1] + sp[1:])
    scale = smoothness * patch
    return scale * (1.0 + right), scale * (1.0 + down)


def energy(labels: np.ndarray, unary: np.ndarray, right: np.ndarray, down: np.ndarray) -> float:
    """E(l) of a labelling (ph, pw) under unary (ph, pw, L) and the seam costs."""
    d = np.take_along_axis(unary, labels[..., None], -1).sum()
    s = (right[:, :-1] * (labels[:, :-1] != labels[:, 1:])).sum() + (down[:-1] * (labels[:-1] != labels[1:])).sum()
    return float(d + s)


def _expand(labels: np.ndarray, alpha: int, unary: np.ndarray, right: np.ndarray, down: np.ndarray) -> np.ndarray:
    """One alpha-expansion move: each node keeps its label (x = 0) or takes ``alpha`` (x = 1),
    whichever minimises E, by one max-flow (Kolmogorov-Zabih construction).

    A pair term E(x_p, x_q) with E00 = A, E01 = B, E10 = C, E11 = 0 is A + (C - A) x_p - C x_q
    + (B + C - A) (1 - x_p) x_q; the last is an edge p -> q (paid when p stays with the source
    and q goes to the sink), non-negative because Potts is a metric.
    """
    import maxflow

    ph, pw, _ = unary.shape
    lin = np.take_along_axis(unary, np.full((ph, pw, 1), alpha), -1)[..., 0] - np.take_along_axis(
        unary, labels[..., None], -1
    )[..., 0]
    g = maxflow.Graph[float]()
    nodes = g.add_grid_nodes((ph, pw))
    src, dst, caps = [], [], []
    for cost, p_sl, q_sl in (
        (right, (slice(None), slice(0, -1)), (slice(None), slice(1, None))),
        (down, (slice(0, -1), slice(None)), (slice(1, None), slice(None))),
    ):
        w = cost[p_sl]
        lp, lq = labels[p_sl], labels[q_sl]
        A = w * (lp != lq)
        B = w * (lp != alpha)
        C = w * (lq != alpha)
        lin[p_sl] += C - A
        lin[q_sl] -= C
        src.append(nodes[p_sl].ravel())
        dst.append(nodes[q_sl].ravel())
        caps.append((B + C - A).ravel())
    i, j, c = np.concatenate(src), np.concatenate(dst), np.concatenate(caps)
    keep = c > 0
    g.add_edges(i[keep], j[keep], c[keep], np.zeros(int(keep.sum())))
    g.add_grid_tedges(nodes, np.maximum(lin, 0.0), np.maximum(-lin, 0.0))
    g.maxflow()
    switch = g.get_grid_segments(nodes)
    return np.where(switch, alpha, labels)


def solve_labels(unary: np.ndarray, right: np.ndarray, down: np.ndarray, cycles: int = 3) -> np.ndarray:
    """Labels (ph, pw) minimising sum D_p(l_p) + sum s_pq [l_p != l_q] by alpha-expansion.

    Args:
        unary: (ph, pw, L) data costs.
        right, down: (ph, pw) seam costs to the right / lower neighbour (:func:`seam_costs`).
        cycles: sweeps over the labels (stops early when a sweep changes nothing).

    Returns:
        (ph, pw) int64 labels, within a factor 2 of the optimum (Boykov et al.); exact for two.
    """
    if unary.ndim != 3 or right.shape != unary.shape[:2] or down.shape != unary.shape[:2]:
        raise ValueError(f"unary (ph, pw, L) and seam costs (ph, pw) must match, got {unary.shape}, "
                         f"{right.shape}, {down.shape}")
    labels = np.argmin(unary, -1).astype(np.int64)
    if unary.shape[-1] == 1:
        return labels
    e = energy(labels, unary, right, down)
    for _ in range(cycles):
        changed = False
        for alpha in range(unary.shape[-1]):
            new = _expand(labels, alpha, unary, right, down)
            e_new = energy(new, unary, right, down)
            if e_new < e - 1e-9:
                labels, e, changed = new, e_new, True
        if not changed:
            break
    return labels


def candidate_spread(colours: torch.Tensor, present: torch.Tensor, noise: float) -> torch.Tensor:
    """(h, w) the RMS distance of the texel's candidate colours to their mean, in units of
    ``noise`` (0 where fewer than two photos see it).

    Args:
        colours: (K, 3, h, w) the slots' colours; present: (K, h, w) bool slots that hold one.
        noise: sigma_c.
    """
    v = present.float()[:, None]
    n = v.sum(0).clamp_min(1.0)
    mean = (colours * v).sum(0) / n
    var = (((colours - mean) ** 2) * v).sum((0, 1)) / n[0]
    spread = var.sqrt() / max(noise, 1e-6)
    return torch.where(present.sum(0) >= 2, spread, torch.zeros_like(spread))


def compose_detail(
    blended: torch.Tensor, photos: list[tuple[torch.Tensor, torch.Tensor]], labels: torch.Tensor,
    seen: torch.Tensor, band: float, feather: float,
) -> torch.Tensor:
    """U = G_b * U_blend + sum_l e_l (I_l - G_b * I_l): the blend's low band, each region's photo's
    detail, cross-faded over ``feather`` texels at the seams.

    Args:
        blended: (3, h, w) the blend's texture.
        photos: per photo label 1..L, (colours (3, h, w), where (h, w) bool it has them).
        labels: (h, w) long, 0 the blend's own detail, l the photo ``photos[l - 1]``.
        seen: (h, w) bool texels some photo sees (the band's low-pass is normalised over them).
        band: Gaussian sigma of the band, texels (> 0).
        feather: Gaussian sigma of the seams' cross-fade, texels (0: hard seams).

    Returns:
        (3, h, w) colours in [0, 1]; the blend's outside ``seen``.
    """
    from difftex.method.filters import blur

    if blended.shape[1:] != labels.shape or labels.shape != seen.shape:
        raise ValueError(f"blended (3, h, w), labels and seen (h, w) must match, got {tuple(blended.shape)}, "
                         f"{tuple(labels.shape)}, {tuple(seen.shape)}")
    low = masked_blur(blended, seen, band)
    own = blended - low
    share = blur((labels == 0).float()[None], feather)[0]
    out = low + share * own
    for lab, (col, where) in enumerate(photos, start=1):
        ind = labels == lab
        if not bool(ind.any()):
            continue
        e = blur(ind.float()[None], feather)[0]
        hp = col - masked_blur(col, where, band)
        # where the region's photo has no colours (its edge), the blend's own detail stands in
        out = out + e * torch.where(where[None], hp, own)
    # the sum of a band and a detail can leave the colours' range next to strong edges
    return torch.where(seen[None], out.clamp(0.0, 1.0), blended)


def detail_texture(
    blended: torch.Tensor, sharp: torch.Tensor, idx: torch.Tensor, present: torch.Tensor, resolve: torch.Tensor,
    seen: torch.Tensor, noise: float, st: DetailSettings,
) -> tuple[torch.Tensor, torch.Tensor, dict]:
    """The blend's texture with its detail taken, per facade element, from the sharpest photo that
    agrees with it (module docstring).

    Args:
        blended: (3, h, w) the optimized blend U = sum_k w_k I_k.
        sharp: (K, 3, h, w) the slots' full-detail colours; idx: (K, h, w) their photos (-1 empty);
            present: (K, h, w) bool slots whose photo sees the texel.
        resolve: (K, h, w) how well each slot's photo resolves the texel (pixels per texel x cos^2).
        seen: (h, w) bool polygon texels some photo sees.
        noise: sigma_c of the full-detail colours.
        st: the settings.

    Returns:
        (U (3, h, w), the photo whose detail each texel takes ((h, w) long, -1: the blend's own),
        stats: the photos that competed, the regions, the share of texels left to the blend).
    """
    if sharp.shape[0] != idx.shape[0] or sharp.shape[2:] != idx.shape[1:] or resolve.shape != idx.shape:
        raise ValueError(f"sharp (K, 3, h, w), idx and resolve (K, h, w) must match, got {tuple(sharp.shape)}, "
                         f"{tuple(idx.shape)}, {tuple(resolve.shape)}")
    present = present & (idx >= 0) & seen[None]
    noise = max(float(noise), 1e-3)
    low_blend = masked_blur(blended, seen, st.band)
    photos = [int(n) for n in torch.unique(idx[present]).tolist()]
    fields, dists, res, wheres = [], [], [], []
    for n in photos:
        col, where = photo_field(sharp, idx, present, n)
        r, _ = photo_field(resolve, idx, present, n)
        low = masked_blur(col, where, st.band)
        fields.append(col)
        wheres.append(where)
        res.append(r)
        dists.append(torch.where(where, (low - low_blend).norm(dim=0) / noise, torch.full_like(r, 1e6)))
    if not photos:
        return blended, torch.zeros(seen.shape, dtype=torch.long, device=seen.device), {"photos": 0}
    spread = candidate_spread(sharp, present, noise)
    cost = texel_costs(torch.stack(res), torch.stack(dists), torch.stack(wheres), st.agree)
    cost = torch.where(seen[None], cost, torch.zeros_like(cost))
    # the photos that are cheapest somewhere compete, the most often cheapest first
    wins = torch.bincount(cost.argmin(0)[seen].flatten(), minlength=cost.shape[0])[1:]
    order = [i for i in torch.argsort(wins, descending=True).tolist() if int(wins[i]) > 0][: st.max_labels]
    keep = [0] + [i + 1 for i in order]
    unary = patch_costs(cost[keep].cpu().numpy(), st.patch)
    right, down = seam_costs(spread, seen, st.patch, st.smoothness)
    lab = solve_labels(unary, right, down, st.cycles)
    h, w = seen.shape
    lab_t = torch.from_numpy(lab).to(seen.device).repeat_interleave(st.patch, 0).repeat_interleave(st.patch, 1)[:h, :w]
    chosen = [(fields[i], wheres[i]) for i in order]
    U = compose_detail(blended, chosen, lab_t, seen, st.band, st.feather)
    texel_photo = torch.tensor([-1] + [photos[i] for i in order], device=seen.device)[lab_t]
    used = lab_t[seen]
    stats = {
        "photos": len(order),
        "regions": int(_count_regions(lab)),
        "blend_share": float((used == 0).float().mean()) if used.numel() else 1.0,
        "patch": st.patch,
        "band": st.band,
    }
    return U, texel_photo, stats


def _count_regions(labels: np.ndarray) -> int:
    """Connected regions (4-neighbours) of equal label in a (ph, pw) labelling."""
    from scipy import ndimage

    total = 0
    for lab in np.unique(labels):
        total += int(ndimage.label(labels == lab)[1])
    return total
