"""A polygon's height field along its normal from dense geometry (difftex.geometry.dense).

The relief the proxy lacks, h(t) per texel along the polygon's outward normal (h < 0 in a recess,
h > 0 on a balcony), is what difftex.sampling.relief maps the photos through. From the user's
dense reconstruction it is measured, not guessed:

1. evidence per texel (:func:`cloud_evidence`, :func:`mesh_evidence`): a cloud's points within
   the polygon's rectangle and the swept range of heights give, per texel, the median of their
   heights (robust to the odd outlier); a mesh is hit by one ray per texel cast along -n from the
   top of the range, the front-most surface as an orthographic view along the normal sees it;
2. layers (:func:`find_layers`): a facade's relief is made of planes (the wall, the openings'
   back panes, a cornice, balconies), so the heights the texels hold cluster; the clusters'
   centres, a few at most, are the layers;
3. snapping (:func:`snap_to_layers`): each texel takes one layer by a graph cut (alpha-expansion
   on PyMaxflow's ``fastmin``): the data term is the texel's distance to the layer in units of
   the evidence's noise, the Potts term keeps regions whole. Texels without evidence (glass,
   which dense matching does not reconstruct; parts no two photos saw) cost the same for every
   layer, so they take their surroundings' layer (a window's pane is filled from its frame); a
   region without evidence on any side keeps the plane.

The field is computed at a frame of at most ``long_side`` texels over the polygon's rectangle and
resampled (nearest) to every level, like the sweep's (difftex.method.relief).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from difftex.errors import DifftexError
from difftex.geometry.dense import DenseMesh
from difftex.geometry.frames import UVFrame, resample_nearest

# A layer must hold this share of the texels with evidence (and MIN_LAYER_TEXELS): smaller
# clusters are a sill, a lamp, noise, not a plane of the facade worth its own mapping.
MIN_LAYER_SHARE = 0.005
MIN_LAYER_TEXELS = 16
# Texels whose points are fewer than this are weighed down (a lone point is often an outlier).
FULL_EVIDENCE = 3
# Coarse texels of this many times the points' spacing hold about its square of points: enough
# for a median, and for a texel of plain wall to hold two points (the noise estimate).
POINTS_PER_SIDE = 2.0
# What leaving the coarse labelling costs a fine texel: less than one point's third (a texel with
# evidence moves the edge), more than nothing (a texel without follows the coarse region).
PRIOR_COST = 0.1
# A hole takes the layer its points vote for with at least this many points, and this many per
# texel of the hole (a window's frame and mullions give far more; a large unseen patch of wall
# with a stray point does not), at this weight (below a measured texel's, above the prior's).
MIN_HOLE_POINTS = 3
HOLE_DENSITY = 0.1
HOLE_WEIGHT = 0.5


@dataclass(frozen=True)
class HeightFieldConfig:
    """How a polygon's height field is made from dense geometry (the ``dense:`` keys)."""

    source: str = "auto"
    """``auto``: the scene's ``dense/`` folder when it holds a cloud, a mesh or COLMAP depth maps;
    ``none``: no dense geometry (the plane, or the sweep of ``optimize.relief``); or a path."""
    range: tuple[float, float] = (-1.0, 1.0)
    """Heights along the normal that count as the polygon's relief, scene units (< 0: into the facade)."""
    max_share: float = 0.2
    """... at most this share of the polygon's shorter side (a small polygon has no metre-deep relief)."""
    long_side: int = 512
    """Texels of the field's frame along the polygon's longer side, at most."""
    layers: int = 4
    """Layers besides the wall, at most (recesses, cornice, balconies)."""
    smoothness: float = 0.5
    """Potts weight of a layer change between neighbouring texels, against a data cost of at most 1."""

    def __post_init__(self):
        object.__setattr__(self, "range", tuple(float(b) for b in self.range))
        lo, hi = self.range
        if not lo <= 0.0 <= hi or lo == hi:
            raise DifftexError(f"dense range must hold 0 and not be empty, got [{lo}, {hi}]")
        if not (self.max_share > 0 and self.long_side >= 8 and self.layers >= 0 and self.smoothness >= 0):
            raise DifftexError("dense: max_share > 0, long_side >= 8, layers >= 0, smoothness >= 0")

    def bounds(self, frame: UVFrame) -> tuple[float, float]:
        """The range on this polygon: ``range`` clipped to ``max_share`` of its shorter side."""
        short = min(frame.width, frame.height) * frame.texel_size
        return max(self.range[0], -self.max_share * short), min(self.range[1], self.max_share * short)


def plane_coordinates(points: np.ndarray, frame: UVFrame) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Texel column, row and height along the normal of world points.

    Args:
        points: (N, 3) world.

    Returns:
        ((N,) tx, (N,) ty in texels of ``frame``, (N,) h in scene units).
    """
    d = points - frame.origin
    return d @ frame.e_u / frame.texel_size, d @ frame.e_v / frame.texel_size, d @ frame.normal


def cloud_evidence(points: np.ndarray, frame: UVFrame, lo: float, hi: float) -> tuple[np.ndarray, np.ndarray, float]:
    """Per texel the median height of the points over it within [lo, hi], and how much it counts.

    A texel whose points spread over more than 4 sigma of the noise (and a texel's size) lies
    across an edge (a reveal, a balcony's side) or holds an outlier: its median is between two
    surfaces, so it is no evidence; the graph cut gives it its neighbours' layer.

    Returns:
        ((H, W) float32 median, NaN without points; (H, W) weight in [0, 1]: min(points,
        FULL_EVIDENCE) / FULL_EVIDENCE, 0 where none or mixed; the points' noise sigma, scene units).
    """
    tx, ty, h = plane_coordinates(points, frame)
    keep = (tx >= 0) & (tx < frame.width) & (ty >= 0) & (ty < frame.height) & (h >= lo) & (h <= hi)
    idx = ty[keep].astype(np.int64) * frame.width + tx[keep].astype(np.int64)
    h = h[keep]
    med = np.full(frame.height * frame.width, np.nan, np.float32)
    count = np.bincount(idx, minlength=med.size).astype(np.int32)
    if len(idx) == 0:
        return med.reshape(frame.shape), np.zeros(frame.shape), 0.0
    start = np.concatenate([[0], np.cumsum(count)[:-1]])
    # the noise: in each texel of two points or more, the difference of two of its points (in
    # the file's order, not sorted: adjacent sorted heights are closer than chance) is
    # N(0, 2 sigma^2) on a plane; the median over texels ignores those across an edge
    by_texel = h[np.argsort(idx, kind="stable")]
    two = start[count >= 2]
    noise = 1.4826 * float(np.median(np.abs(by_texel[two + 1] - by_texel[two]))) / np.sqrt(2) if len(two) else 0.0
    h = h[np.lexsort((h, idx))]  # by texel, then height: each texel's heights sorted in a run
    has = count > 0
    med[has] = h[start[has] + (count[has] - 1) // 2]  # the lower median: a height that exists
    spread = np.zeros(med.size)
    spread[has] = h[start[has] + count[has] - 1] - h[start[has]]
    weight = np.minimum(count, FULL_EVIDENCE) / FULL_EVIDENCE * (spread <= max(4.0 * noise, frame.texel_size))
    return med.reshape(frame.shape), weight.reshape(frame.shape), noise


def mesh_evidence(mesh: DenseMesh, frame: UVFrame, lo: float, hi: float) -> np.ndarray:
    """Per texel the height of the mesh's front-most surface within [lo, hi] along the normal.

    One ray per texel centre from height ``hi`` along -n (Mitsuba, as difftex.geometry.raycast);
    a ray that meets nothing before ``lo`` leaves the texel without evidence.

    Returns:
        (H, W) float32 heights, NaN where the ray misses.
    """
    import mitsuba as mi

    scene = mesh.scene()
    centre = mesh.centre
    tx, ty = frame.centres()
    o = (frame.texel_to_world(tx, ty) - centre + hi * frame.normal).reshape(-1, 3).astype(np.float32)
    d = np.broadcast_to(-frame.normal, o.shape).astype(np.float32)
    ray = mi.Ray3f(mi.Point3f(o[:, 0], o[:, 1], o[:, 2]), mi.Vector3f(d[:, 0], d[:, 1], d[:, 2]))
    ray.maxt = mi.Float(float(hi - lo))  # type: ignore[assignment]  # mitsuba's Float is drjit's
    t = np.asarray(scene.ray_intersect_preliminary(ray).t, np.float64)
    h = np.where(np.isfinite(t) & (t <= hi - lo), hi - t, np.nan)
    return h.reshape(frame.shape).astype(np.float32)


def find_layers(values: np.ndarray, tol: float, max_layers: int, lo: float, hi: float) -> np.ndarray:
    """The heights the texels cluster at: peaks of their histogram, the most populated first,
    at least 2 ``tol`` apart, each refined to the median of the values within ``tol``.

    Args:
        values: (M,) heights of the texels with evidence; tol: the evidence's uncertainty.

    Returns:
        (L,) sorted heights, 0 among them (the plane: what a texel without evidence keeps),
        at most ``max_layers`` besides the one nearest 0.
    """
    if len(values) == 0:
        return np.zeros(1)
    width = tol / 2
    edges = np.arange(lo, hi + width, width)
    hist, _ = np.histogram(values, bins=edges)
    smooth = np.convolve(hist, [1, 2, 1], mode="same")
    peaks = [i for i in range(len(smooth)) if smooth[i] > 0 and smooth[i] >= smooth[max(i - 1, 0)]
             and smooth[i] >= smooth[min(i + 1, len(smooth) - 1)]]
    centres = 0.5 * (edges[:-1] + edges[1:])
    least = max(MIN_LAYER_TEXELS, MIN_LAYER_SHARE * len(values))
    picked: list[float] = []
    for i in sorted(peaks, key=lambda i: -smooth[i]):
        near = values[np.abs(values - centres[i]) <= tol]
        if len(near) < least or any(abs(centres[i] - p) < 2 * tol for p in picked):
            continue
        picked.append(float(np.median(near)))
        if len(picked) > max_layers:
            break
    layers = np.array(sorted(picked)) if picked else np.zeros(1)
    near = int(np.argmin(np.abs(layers)))
    if abs(layers[near]) <= tol / 2:  # the proxy on the wall within the noise: exactly the plane
        layers[near] = 0.0
    else:  # no layer is the plane: add it, for the texels without evidence
        layers = np.sort(np.append(layers, 0.0))
    return layers


def snap_to_layers(
    evidence: np.ndarray, weight: np.ndarray, layers: np.ndarray, tol: float, smoothness: float,
    prior: np.ndarray | None = None,
) -> np.ndarray:
    """Each texel's layer by alpha-expansion: data cost min(((e - layer) / 2 tol)^2, 1) x weight,
    plus PRIOR_COST off the ``prior`` label where one is given, Potts cost ``smoothness`` between
    4-neighbours of different layers.

    Args:
        evidence: (H, W) heights, NaN without evidence; weight: (H, W) in [0, 1] (0: none);
        layers: (L,) from :func:`find_layers`; prior: (H, W) int labels (a coarser labelling) or None.

    Returns:
        (H, W) int layer index.
    """
    from maxflow import fastmin

    plane = int(np.argmin(np.abs(layers)))
    if len(layers) == 1:
        return np.full(evidence.shape, plane, np.int64)
    e = np.nan_to_num(evidence, nan=0.0)[..., None]
    D = np.minimum(((e - layers) / (2 * tol)) ** 2, 1.0) * weight[..., None]
    # without evidence every layer costs the same but for a hair on the plane: a region cut off
    # from all evidence keeps the plane, one bordered by evidence takes its border's layer
    D += np.where(np.arange(len(layers)) == plane, 0.0, 1e-4)
    if prior is not None:
        D += PRIOR_COST * (np.arange(len(layers)) != prior[..., None])
    V = smoothness * (1.0 - np.eye(len(layers)))
    init = np.argmin(D, axis=-1) if prior is None else prior
    return np.asarray(fastmin.aexpansion_grid(D.astype(np.float64), V, max_cycles=5, labels=init), np.int64)


def cloud_spacing(points: np.ndarray, frame: UVFrame, mask: np.ndarray, lo: float, hi: float) -> float:
    """The mean distance between the cloud's points over the polygon: sqrt(its area / their number).

    Args:
        points: (N, 3) world; mask: (H, W) bool at ``frame``.

    Returns:
        Scene units; inf without points.
    """
    tx, ty, h = plane_coordinates(points, frame)
    inside = (tx >= 0) & (tx < frame.width) & (ty >= 0) & (ty < frame.height) & (h >= lo) & (h <= hi)
    n = int(mask[ty[inside].astype(np.int64), tx[inside].astype(np.int64)].sum())
    area = float(mask.sum()) * frame.texel_size**2
    return float(np.sqrt(area / n)) if n else float("inf")


def cloud_field(points: np.ndarray, frame: UVFrame, mask: np.ndarray, cfg: HeightFieldConfig, lo: float, hi: float):
    """The labelling from a cloud, coarse to fine: where the points are sparser than the texels,
    the layers and the regions are found at texels of POINTS_PER_SIDE x the points' spacing
    (enough points per texel for a median and a noise estimate, and windows whose glass has
    no points are a few texels wide, not a sieve), then the regions' edges are placed at
    ``frame`` by the points there, the coarse labels a prior where a texel has none.

    Returns:
        ((L,) layers, (H, W) int labels at ``frame``, the noise, the share of coarse texels with evidence).
    """
    spacing = cloud_spacing(points, frame, mask, lo, hi)
    side = max(frame.width, frame.height) * frame.texel_size
    coarse = frame
    if POINTS_PER_SIDE * spacing > frame.texel_size and np.isfinite(spacing):
        coarse = frame.resized(max(4, int(np.ceil(side / (POINTS_PER_SIDE * spacing)))))
    cmask = resample_nearest(mask, frame, coarse)
    evidence, weight, noise = cloud_evidence(points, coarse, lo, hi)
    weight = np.where(cmask & np.isfinite(evidence), weight, 0.0)
    tol = max(3.0 * noise, 0.5 * coarse.texel_size)
    has = weight > 0
    share = float(has[cmask].mean()) if cmask.any() else 0.0
    if not has.any():
        return np.zeros(1), np.zeros(frame.shape, np.int64), noise, share
    layers = find_layers(evidence[has], tol, cfg.layers, lo, hi)
    evidence, weight = hole_evidence(points, coarse, cmask, evidence, weight, layers, tol, lo, hi)
    label = snap_to_layers(np.where(cmask, evidence, np.nan), weight, layers, tol, cfg.smoothness)
    if coarse is frame:
        return layers, label, noise, share
    prior = resample_nearest(label, coarse, frame)
    evidence, weight, _ = cloud_evidence(points, frame, lo, hi)
    weight = np.where(mask & np.isfinite(evidence), weight, 0.0)
    fine_tol = max(3.0 * noise, 0.5 * frame.texel_size)
    return layers, snap_to_layers(evidence, weight, layers, fine_tol, cfg.smoothness, prior), noise, share


def hole_evidence(
    points: np.ndarray, frame: UVFrame, mask: np.ndarray, evidence: np.ndarray, weight: np.ndarray,
    layers: np.ndarray, tol: float, lo: float, hi: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Evidence for the holes: a region of texels without evidence amid a wall the cloud covers
    is surface dense matching could not reconstruct (a window's glass). Its height is what the
    few points inside it and on its rim say behind the wall (its frame and mullions, the deep end
    of its reveals): the layer behind the plane with the most points there, given HOLE_WEIGHT, where
    they are at least MIN_HOLE_POINTS and HOLE_DENSITY per texel of the hole. Without it the
    hole would take the wall around it, which holds far more points.

    Args:
        evidence, weight: (H, W) from :func:`cloud_evidence` (weight 0 outside ``mask``).

    Returns:
        (evidence, weight) with the holes' texels given their layer.
    """
    from scipy import ndimage

    holes, n = ndimage.label(mask & (weight == 0))
    if n == 0 or len(layers) < 2:
        return evidence, weight
    rim = ndimage.grey_dilation(holes, size=3)  # a hole's id on its texels and on the ring around them
    tx, ty, h = plane_coordinates(points, frame)
    inside = (tx >= 0) & (tx < frame.width) & (ty >= 0) & (ty < frame.height) & (h >= lo) & (h <= hi)
    hole = rim[ty[inside].astype(np.int64), tx[inside].astype(np.int64)]
    near = np.abs(h[inside][:, None] - layers[None]) <= tol
    layer = np.where(near.any(1), near.argmax(1), -1)
    plane = int(np.argmin(np.abs(layers)))
    # only layers behind the wall: glass sits in openings, and what stands out of a facade
    # (a balcony, a cornice) is solid surface that dense matching reconstructs; points in front
    # of a hole are an occluder's (a tree before a door)
    use = (hole > 0) & (layer >= 0) & (layer != plane) & (layers[np.maximum(layer, 0)] < layers[plane])
    votes = np.zeros((n + 1, len(layers)))
    np.add.at(votes, (hole[use], layer[use]), 1.0)
    size = np.bincount(holes.ravel(), minlength=n + 1)
    best = votes.argmax(1)
    ok = (votes.max(1) >= np.maximum(MIN_HOLE_POINTS, HOLE_DENSITY * size)) & (np.arange(n + 1) > 0)
    fill = ok[holes] & (holes > 0)
    evidence = np.where(fill, layers[best[holes]], evidence)
    weight = np.where(fill, HOLE_WEIGHT, weight)
    return evidence, weight


def height_field(
    frame: UVFrame, mask: np.ndarray, cfg: HeightFieldConfig, points: np.ndarray | None = None,
    mesh: DenseMesh | None = None,
) -> tuple[np.ndarray, dict]:
    """A polygon's height field at ``frame`` from a cloud (``points``, :func:`cloud_field`) or a ``mesh``.

    Args:
        frame: the field's texel grid (a level of the polygon's frame); mask: (H, W) bool, the
            polygon's texels.

    Returns:
        ((H, W) float32 heights, 0 outside ``mask`` and on the plane; statistics for stats.json:
        the layers and their shares, the share of texels with evidence, the noise).
    """
    lo, hi = cfg.bounds(frame)
    if (points is None) == (mesh is None):
        raise ValueError("give points or a mesh")
    stats: dict = {"range": [lo, hi], "long_side": max(frame.shape)}
    if points is not None:
        layers, label, noise, share = cloud_field(points, frame, mask, cfg, lo, hi)
    else:
        assert mesh is not None
        evidence = np.where(mask, mesh_evidence(mesh, frame, lo, hi), np.nan)
        weight = np.isfinite(evidence).astype(np.float64)
        noise, share = 0.0, float(weight[mask].mean()) if mask.any() else 0.0
        # a mesh has no noise: its layers are told apart at half a texel (a smaller height
        # difference moves no photo by half a texel under 45 degrees)
        tol = 0.5 * frame.texel_size
        layers = find_layers(evidence[weight > 0], tol, cfg.layers, lo, hi) if share else np.zeros(1)
        label = snap_to_layers(evidence, weight, layers, tol, cfg.smoothness) if share else np.zeros(frame.shape, int)
    stats.update({"evidence_share": share, "noise": noise})
    if share == 0:
        return np.zeros(frame.shape, np.float32), {**stats, "layers": {}, "reason": "no dense geometry near it"}
    h = np.where(mask, layers[label], 0.0).astype(np.float32)
    stats["layers"] = {f"{v:.4g}": float((h[mask] == np.float32(v)).mean()) for v in layers}
    stats["relief_share"] = float((h[mask] != 0).mean()) if mask.any() else 0.0
    return h, stats
