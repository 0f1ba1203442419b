"""Relief of a polygon from its photos: a plane sweep of photo consistency along the normal.

The proxy is a plane; the facade has recessed windows and balconies that the photos see from
different directions, so at the plane they disagree and any blend of them smears (the relief
issue; the paper's L_Persp only chooses which photos to trust). Mapped through the right height
h(t) along the normal (difftex.sampling.relief), they agree. h(t) is found by sweeping planes:

1. candidate photos: the polygon's photos seen within ``min_cos`` of the normal (oblique photos
   hide the recesses behind their reveals and see glass at grazing angles), the most frontal
   ``max_photos`` of them;
2. for each height h_d of the sweep (the proxy plane h = 0 among them), every photo is mapped
   through the plane shifted by h_d; their per-texel median M_d is the consensus, and each photo's
   zero-normalised cross-correlation with M_d over a window of ``window`` texels (grey values)
   scores how well it agrees there: ZNCC ignores each photo's gain and offset, and a window
   wider than a mullion's displacement sees the structure, not one texel's noise;
3. the cost of h_d at a texel is the mean over photos of 1 - ZNCC (:func:`sweep_cost`);
4. the height field (:func:`height_field`) takes per texel the height of least cost, keeps it
   only where it beats the plane by ``margin`` (where the photos agree at h = 0, or the wall is
   featureless, the plane stays), and flattens it with a mode filter of ``smooth`` texels, so
   recesses and balconies come out as flat steps (the facade's relief is made of planes);
5. a sweep is trusted only with at least MIN_PHOTOS photos and at most MAX_STEPS steps off the
   plane: otherwise the polygon keeps its plane (``stats["reason"]`` says why).

Options for photos that all see the wall from one side (drone surveys; docs/optimizer.md, "A sweep
for drone photos"): ``structure="parallax"`` compares each photo's differences along its own
parallax direction instead of its grey values (:func:`sweep_cost` says why), ``share`` < 1 the best
agreeing photos only, and ``regularise="semiglobal"`` replaces step 4's per-texel choice and mode
filter by semi-global matching (difftex.method.semiglobal, :func:`height_field_semiglobal`), and
``openings`` completes each step to a rectangle (difftex.method.openings).

The field is estimated at a frame of at most ``long_side`` texels and used at every level of
the polygon (its steps are resampled nearest). Where the sweep finds nothing (too few photos,
a flat wall), the field is 0 and texturing is exactly as without relief.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import torch
import torch.nn.functional as F

from difftex.geometry.frames import UVFrame
from difftex.method.config import ReliefSettings  # noqa: F401  (defined beside OptimizeConfig, re-exported)
from difftex.method.openings import fill_openings
from difftex.method.semiglobal import aggregate, best_share_mean
from difftex.sampling.crops import elevation_reaches, median_elevation
from difftex.sampling.photos import PhotoSet
from difftex.sampling.relief import GreySweep, Relief, relief_visibility
from difftex.sampling.texels import level_frame, resample_nearest, texel_map

GREY = (0.299, 0.587, 0.114)  # Rec. 601 luma: ZNCC compares structure, not colour
# Fewer photos than this within the angle give a median and a mean cost too noisy to tell a
# recess from chance (lund-door's archivolts, 3-10 photos, took heights all over the range).
MIN_PHOTOS = 5
# A field with more flat steps than this off the plane is not a facade's relief (recesses,
# balconies, a cornice) but the sweep following noise or a curved surface: the plane is kept.
MAX_STEPS = 4


def sweep_photos(photos: PhotoSet, frame: UVFrame, mask: np.ndarray, min_cos: float, max_photos: int) -> list[int]:
    """The photos the sweep compares: seen within arccos(``min_cos``) of the normal on at least a
    quarter of the polygon's texels, the most frontal ``max_photos`` of them (median cos).

    Returns:
        Photo indices, most frontal first (estimate_relief keeps the plane with fewer than MIN_PHOTOS).
    """
    scored = []
    n_mask = max(int(mask.sum()), 1)
    for n in sorted(photos.samplers):
        tm = texel_map(frame, photos.inp.photos[n], "cpu")  # the plane's: which photos see the polygon
        vis = resample_nearest(photos.inp.texel_visible[n], photos.inp.frame, frame) & mask & tm.valid.numpy()
        if vis.sum() < 0.25 * n_mask:
            continue
        scored.append((float(np.median(tm.cos.numpy()[vis])), n))
    scored.sort(reverse=True)
    return [n for c, n in scored if c >= min_cos][:max_photos]


def photo_parallax(photos: PhotoSet, which: list[int], frame: UVFrame) -> np.ndarray:
    """Each photo's parallax at the polygon's centre: a point at height h appears on the plane
    displaced by h (v_u / v_n, v_v / v_n) texel units (times 1 / texel size) for a photo seen along v.

    Returns:
        (len(which), 2) the displacement per unit height along e_u and e_v.
    """
    centre = frame.texel_to_world(np.array(frame.width / 2), np.array(frame.height / 2))
    out = []
    for n in which:
        v = photos.inp.photos[n].center - centre
        vn = max(float(v @ frame.normal), 1e-6)
        out.append([float(v @ frame.e_u) / vn, float(v @ frame.e_v) / vn])
    return np.asarray(out, np.float64).reshape(-1, 2)


def sweep_heights(photos: PhotoSet, which: list[int], frame: UVFrame, s: ReliefSettings) -> np.ndarray:
    """The swept heights: from ``lo`` to ``hi`` in steps that move the photos' parallax relative to
    each other by about one texel (finer steps tell nothing new), at most ``max_heights``, 0 among them.

    The largest difference of :func:`photo_parallax` between two photos sets the step.
    """
    d = photo_parallax(photos, which, frame)
    spread = float(np.max(np.linalg.norm(d[:, None] - d[None], axis=-1))) if len(d) > 1 else 0.0
    step = frame.texel_size / max(spread, 1e-6)
    step = max(step, (s.hi - s.lo) / (s.max_heights - 1))
    below = -np.arange(0.0, -s.lo + 1e-9, step)[::-1]
    above = np.arange(step, s.hi + 1e-9, step)
    return np.concatenate([below, above]).astype(np.float64)


def parallax_directions(parallax: np.ndarray) -> np.ndarray:
    """Per photo, the unit direction (e_u, e_v) in which a wrong height moves it against the
    consensus: its parallax minus the photos' median parallax (the consensus is their median).

    Args:
        parallax: (P, 2) from :func:`photo_parallax`.

    Returns:
        (P, 2) unit vectors; (1, 0) for a photo at the median itself (no direction of its own).
    """
    off = parallax - np.median(parallax, 0)
    norm = np.linalg.norm(off, axis=1, keepdims=True)
    return np.where(norm > 1e-9, off / np.maximum(norm, 1e-9), np.array([[1.0, 0.0]]))


def directional_difference(
    x: torch.Tensor, valid: torch.Tensor, direction: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Forward differences of ``x`` along a direction per image: d_u dx/du + d_v dx/dv.

    Args:
        x: (B, h, w), or (1, h, w) to difference one image along B directions; valid: bool, as ``x``;
        direction: (B, 2) unit (d_u, d_v).

    Returns:
        ((B, h, w) the difference, 0 on the last row and column; bool, as ``valid``, where it and
        its two neighbours are valid).
    """
    du = F.pad(x[..., 1:] - x[..., :-1], (0, 1))
    dv = F.pad(x[..., 1:, :] - x[..., :-1, :], (0, 0, 0, 1))
    ok = valid & F.pad(valid[..., 1:], (0, 1)) & F.pad(valid[..., 1:, :], (0, 0, 0, 1))
    a, b = direction[:, 0].view(-1, 1, 1).to(x), direction[:, 1].view(-1, 1, 1).to(x)
    return a * du + b * dv, ok


def box_filter(x: torch.Tensor, window: int) -> torch.Tensor:
    """Mean over ``window`` x ``window`` texels (zero padded), from running sums along each axis:
    O(1) per texel whatever the window, which the sweep's dozens of windowed moments per height
    need (torch's avg_pool2d costs O(window) per texel and pass on a CPU).

    Args:
        x: (B, h, w).

    Returns:
        (B, h, w).
    """
    r = window // 2
    y = x.double()  # running sums over a whole row would lose float32's precision
    for dim in (-1, -2):
        pad = [0, 0, 0, 0]
        pad[0 if dim == -1 else 2], pad[1 if dim == -1 else 3] = r + 1, r
        c = torch.cumsum(F.pad(y, pad), dim)
        n = c.shape[dim]
        y = (c.narrow(dim, window, n - window) - c.narrow(dim, 0, n - window)) / window
    return y.to(x.dtype)


def zncc(a: torch.Tensor, b: torch.Tensor, valid: torch.Tensor, window: int, eps: float = 1e-4) -> torch.Tensor:
    """Zero-normalised cross-correlation of ``a`` with ``b`` over windows, counting valid texels only.

    Args:
        a: (B, h, w) grey values; b: (h, w) or (B, h, w) the reference; valid: (B, h, w) bool.
        eps: variance floor, so flat windows (noise only) correlate to about 0, not to +-1.

    Returns:
        (B, h, w) ZNCC in [-1, 1]; 0 where fewer than half a window's texels are valid.
    """
    w = valid.float()
    b = b.expand_as(a)
    share = box_filter(w, window)
    inv = 1.0 / share.clamp_min(1e-12)
    ma, mb = box_filter(w * a, window) * inv, box_filter(w * b, window) * inv
    va = (box_filter(w * a * a, window) * inv - ma * ma).clamp_min(0)
    vb = (box_filter(w * b * b, window) * inv - mb * mb).clamp_min(0)
    cab = box_filter(w * a * b, window) * inv - ma * mb
    r = cab / torch.sqrt((va + eps) * (vb + eps))
    return torch.where(share >= 0.5, r.clamp(-1, 1), torch.zeros_like(r))


def sweep_cost(
    photos: PhotoSet, which: list[int], frame: UVFrame, mask: np.ndarray, heights: np.ndarray, window: int,
    share: float = 1.0, structure: str = "grey",
) -> tuple[torch.Tensor, torch.Tensor]:
    """The plane sweep's cost volume: per height and texel, the mean of 1 - ZNCC(photo, median)
    over the ``share`` of the photos that agree best (difftex.method.semiglobal.best_share_mean).

    ``structure``: "grey" compares the grey values; "parallax" compares each photo's and the
    median's differences along that photo's :func:`parallax_directions`, the only direction in
    which a wrong height moves it against the others. Grey values also agree at a wrong height
    wherever the structure is uniform along that direction (drone photos, all from above, move
    alike up and down the wall: a cornice or a sill line brought into the window by a wrong height
    matches in all of them), and that pulls plain plaster to the height that shows it an edge.

    Each photo is sampled once per height, grey, at the pyramid level of the sweep frame's texels
    (difftex.sampling.relief.GreySweep), where it saw the plane at h = 0 and lands in its crop.

    Returns:
        ((D, h, w) cost, inf where fewer than 3 photos compare; (D, h, w) how many photos do).
    """
    dev = photos.device
    m = torch.from_numpy(mask).to(dev)
    sweeps, seen = [], []
    dirs = torch.from_numpy(parallax_directions(photo_parallax(photos, which, frame))).to(dev)
    for n in which:
        ok, fp = photos.footprint_on(n, frame, m)
        sweeps.append(GreySweep(photos.samplers[n], frame, photos.inp.photos[n], 1.0 if fp is None else fp))
        seen.append(ok)
    costs, counts = [], []
    for h in heights:
        cols, inside = [], []
        for sw, ok in zip(sweeps, seen):
            g, within = sw.sample(float(h))
            cols.append(g)
            inside.append(ok & within)
        g, v = torch.stack(cols), torch.stack(inside)
        med = torch.nanmedian(torch.where(v, g, torch.full_like(g, math.nan)), 0).values.nan_to_num(0.0)
        if structure == "parallax":
            g, v = directional_difference(g, v, dirs)
            # the median's differences once, combined along every photo's direction by broadcasting
            med = directional_difference(med[None], torch.ones_like(v[:1]), dirs)[0]
        r = zncc(g, med, v, window)
        both = v & (r != 0)
        cnt = both.sum(0).float()
        c = best_share_mean(1.0 - r, both, share)
        costs.append(torch.where(cnt >= 3, c, torch.full_like(c, math.inf)))
        counts.append(cnt)
    return torch.stack(costs), torch.stack(counts)


def mode_filter(labels: torch.Tensor, n_labels: int, size: int, keep: torch.Tensor) -> torch.Tensor:
    """The most frequent label of each ``size`` x ``size`` window among the texels of ``keep``.

    Args:
        labels: (h, w) long in [0, n_labels); keep: (h, w) bool texels that vote.

    Returns:
        (h, w) long; a texel with no voter around keeps its label.
    """
    if size <= 1:
        return labels
    votes = torch.stack([((labels == k) & keep).float() for k in range(n_labels)])
    votes = F.avg_pool2d(votes[:, None], size, 1, size // 2)[:, 0]
    best = votes.argmax(0)
    return torch.where(votes.amax(0) > 0, best, labels)


def merge_steps(h: np.ndarray, mask: np.ndarray, tol: float, min_share: float) -> np.ndarray:
    """Snap a height field to a few flat steps: heights within ``tol`` of a more frequent one, or held
    by less than ``min_share`` of the texels, take the nearest kept height (0 is always kept).

    Args:
        h: (h, w) heights; mask: (h, w) bool texels counted; tol: scene units; min_share: in [0, 1).

    Returns:
        (h, w) float32 heights holding only the kept values.
    """
    vals, counts = np.unique(h[mask], return_counts=True)
    if vals.size <= 1:
        return h.astype(np.float32)
    share = counts / counts.sum()
    kept = [0.0]
    for i in np.argsort(-counts, kind="stable"):
        v = float(vals[i])
        if share[i] >= min_share and all(abs(v - k) > tol for k in kept):
            kept.append(v)
    k = np.asarray(kept)
    snapped = k[np.abs(h[..., None] - k).argmin(-1)]
    return np.where(mask, snapped, 0.0).astype(np.float32)


def plane_label(heights: np.ndarray) -> int:
    """The index of the plane (h = 0) among the swept heights; a sweep without it is an error."""
    zero = int(np.argmin(np.abs(heights)))
    if abs(heights[zero]) > 1e-12:
        raise ValueError("the swept heights must include 0")
    return zero


def steps_of(label: torch.Tensor, heights: np.ndarray, mask: np.ndarray, smooth: int) -> np.ndarray:
    """A label map as a field of flat steps: mode-filtered over ``smooth`` texels, the labels' heights,
    merged by :func:`merge_steps` (within 2 sweep steps, at least 0.5 % of texels).

    Args:
        label: (h, w) long indices into ``heights``; mask: (h, w) bool.

    Returns:
        (h, w) float32 heights, 0 outside ``mask``.
    """
    m = torch.from_numpy(mask).to(label.device)
    label = mode_filter(label, len(heights), smooth, m)
    out_t = torch.from_numpy(heights.astype(np.float32)).to(label.device)[label]
    out = torch.where(m, out_t, torch.zeros_like(out_t)).cpu().numpy()
    step = float(np.min(np.diff(np.sort(heights)))) if len(heights) > 1 else 0.0
    return merge_steps(out, mask, 2.0 * step + 1e-9, 0.005)


def height_field(cost: torch.Tensor, heights: np.ndarray, mask: np.ndarray, margin: float, smooth: int) -> np.ndarray:
    """Per texel the swept height of least cost, where it beats the plane by ``margin``, as flat
    steps (:func:`steps_of`).

    Args:
        cost: (D, h, w) the sweep's cost; heights: (D,) its heights, 0 among them; mask: (h, w) bool.

    Returns:
        (h, w) float32 heights, 0 outside ``mask`` and where no height beats the plane.
    """
    zero = plane_label(heights)
    m = torch.from_numpy(mask).to(cost.device)
    best_cost, label = cost.min(0)
    plane = cost[zero]
    gain = torch.where(torch.isfinite(plane), plane - best_cost, torch.zeros_like(plane))
    label = torch.where((gain > margin) & m, label, torch.full_like(label, zero))
    return steps_of(label, heights, mask, smooth)


def height_field_semiglobal(
    cost: torch.Tensor, heights: np.ndarray, mask: np.ndarray, margin: float, p1: float, p2: float, smooth: int
) -> np.ndarray:
    """The height field of least semi-globally aggregated cost (difftex.method.semiglobal), the
    plane favoured by ``margin`` at every texel, as flat steps (:func:`steps_of`).

    Args:
        cost: (D, h, w) the sweep's cost, heights in order; heights: (D,) 0 among them; mask: (h, w) bool.

    Returns:
        (h, w) float32 heights, 0 outside ``mask``.
    """
    zero = plane_label(heights)
    m = torch.from_numpy(mask).to(cost.device)
    c = cost.clone()
    c[zero] -= margin
    # outside the polygon no evidence: every height costs the same, so paths pass through unchanged
    c = torch.where(m[None], c, torch.zeros_like(c))
    label = aggregate(c, p1, p2).argmin(0)
    label = torch.where(m, label, torch.full_like(label, zero))
    return steps_of(label, heights, mask, smooth)


def estimate_relief(photos: PhotoSet, s: ReliefSettings, max_steps: int = MAX_STEPS) -> tuple[Relief, dict]:
    """The polygon's height field and each candidate photo's self-occlusion through it.

    ``max_steps``: a field with more steps off the plane is rejected (the plane is kept); a
    yardstick of the sweep itself (evaluation/relief_bound.py --accuracy) lifts it.

    Returns:
        (the Relief at the sweep's frame, statistics for stats.json).
    """
    inp = photos.inp
    frame = level_frame(inp.frame, min(s.long_side, max(inp.frame.shape)))
    mask = resample_nearest(inp.texel_mask, inp.frame, frame)
    flat = Relief(frame, np.zeros(frame.shape, np.float32))
    elevation = median_elevation(inp, s.min_cos)  # the test of crops.seen_from_above, on its value
    if not elevation_reaches(elevation, s.min_elevation):
        why = ("no photo within the angle" if elevation is None else
               f"photos' median elevation {elevation:.0f} deg, below {s.min_elevation:g} (not from above)")
        return flat, {"photos": [], "long_side": max(frame.shape), "elevation": elevation, "heights": [],
                      "relief_share": 0.0, "reason": why}
    which = sweep_photos(photos, frame, mask, s.min_cos, s.max_photos)
    stats: dict = {"photos": [inp.photos[n].name for n in which], "long_side": max(frame.shape),
                   "elevation": elevation}
    if len(which) < MIN_PHOTOS:
        return flat, {**stats, "heights": [], "relief_share": 0.0, "reason": f"fewer than {MIN_PHOTOS} photos"}
    short = min(frame.width, frame.height) * frame.texel_size
    s = dataclasses.replace(s, lo=max(s.lo, -s.max_share * short), hi=min(s.hi, s.max_share * short))
    stats["range"] = [s.lo, s.hi]
    heights = sweep_heights(photos, which, frame, s)
    with torch.no_grad():
        cost, _ = sweep_cost(photos, which, frame, mask, heights, s.window, s.share, s.structure)
        if s.regularise == "semiglobal":
            h = height_field_semiglobal(cost, heights, mask, s.margin, s.p1, s.p2, s.smooth)
        else:
            h = height_field(cost, heights, mask, s.margin, s.smooth)
        if s.openings != "none":
            # a component below a quarter of the ZNCC window's area is finer than the window resolves
            h = fill_openings(h, mask, cost.cpu().numpy(), heights, s.openings, min_texels=s.window**2 // 4,
                              tol=s.openings_tol)
    steps = len(np.unique(h[mask])) - int(bool((h[mask] == 0).any()))
    if steps > max_steps:
        stats.update({"heights": [float(x) for x in heights], "relief_share": 0.0, "steps": steps,
                      "reason": f"{steps} steps off the plane (more than {max_steps}): not a facade's relief"})
        return flat, stats
    stats.update(
        {
            "heights": [float(x) for x in heights],
            "steps": steps,
            "relief_share": float((h[mask] != 0).mean()) if mask.any() else 0.0,
            "levels": {f"{v:.4g}": float((h[mask] == v).mean()) for v in np.unique(h[mask])},
        }
    )
    return occluding_relief(photos, frame, h, mask), stats


def occluding_relief(photos: PhotoSet, frame: UVFrame, heights: np.ndarray, mask: np.ndarray) -> Relief:
    """The Relief of a height field at ``frame``, with each candidate photo's self-occlusion
    through it (the texels of ``mask`` that the relief hides from the photo).

    Args:
        heights: (h, w) scene units along the normal, at ``frame``; mask: (h, w) bool.
    """
    relief = Relief(frame, heights)
    if not relief.flat:
        none = np.zeros(frame.shape, bool)
        relief.hidden = np.stack(
            [
                ~relief_visibility(frame, ph, heights, mask) & mask if n in photos.samplers else none
                for n, ph in enumerate(photos.inp.photos)
            ]
        )
    return relief
