"""Brightness adjustment (paper 4.3): matching the photos feeding one polygon, per HSV channel.

Each candidate photo k gets a monotone transfer per HSV channel, estimated on the polygon's
texels that photo k and the reference both see, so occluders and content seen by only one photo
do not bias it: one gain (``gain``, the default, :func:`gain_knots`) or the paper's histogram
matching, a quantile map (``quantile``, :func:`quantile_knots`). References:

- ``median`` (default): the per-texel median of the photos that see the texel (the consensus
  image). A minority of outliers (an occluder, one badly exposed photo) does not move it, and
  its exposure is the median photo exposure, so no single photo sets the texture's brightness.
- ``best``: the photo with the largest sum of frontality over its visible texels (most
  frontal x most coverage): the photo the optimizer leans on most, so matching the others to it
  changes the final texture least; but its exposure error spreads over the whole texture.
- ``pooled``: the histogram of all candidates together, which occluders and content seen by
  only some photos also pull.

Hue is circular and a quantile map on it produces false colours, so by default only S and V are
matched (``histmatch_channels: sv``). skimage.exposure.match_histograms matches whole images and
does not return the transfer function, which we need to apply the same map to the photo at
every resolution level and in the final composition; hence this small implementation.
"""

from __future__ import annotations

import numpy as np
import torch

from difftex.sampling.colour import N_KNOTS, QUANTILES, identity_transfer, rgb_to_hsv

MEDIAN_BLOCK_VALUES = 1 << 24  # floats per block of the per-texel median (64 MB)


def quantile_knots(src: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """(2, N_KNOTS) monotone knots mapping the distribution of ``src`` onto that of ``ref``.

    End knots (0 -> 0, 1 -> 1) make values outside the observed range interpolate towards the
    ends instead of clipping; a tiny ramp keeps the source knots strictly increasing.
    """
    sq = np.quantile(src, QUANTILES)
    rq = np.quantile(ref, QUANTILES)
    xs = np.concatenate([[0.0], sq, [1.0]])
    ys = np.concatenate([[0.0], rq, [1.0]])
    xs = np.maximum.accumulate(xs) + np.linspace(0.0, 1e-6, N_KNOTS)
    ys = np.maximum.accumulate(ys)
    return np.stack([xs, ys]).astype(np.float32)


GAIN_MIN_VALUE = 0.02  # texels darker or greyer than this carry no ratio (noise over nothing)
GAIN_RANGE = (0.25, 4.0)  # two stops either way: beyond it the pairing is wrong, not the exposure


def gain_knots(src: np.ndarray, ref: np.ndarray, paired: bool) -> np.ndarray:
    """(2, N_KNOTS) knots of y = min(1, g x): one gain g that takes ``src`` to ``ref``.

    g is the median of the per-texel ratios ref / src where the two are paired (the same
    texels, in the same order), else the ratio of their medians. An exposure change is a gain on
    the photo's values before the tone curve, and on V after a gamma-like curve too
    ((g L)^(1/2.2) = g^(1/2.2) L^(1/2.2)); a white-balance change moves S by about a gain.

    Why not the quantile map (``quantile_knots``) by default: matching a single photo onto the
    per-texel median, which has averaged its noise away, makes a staircase. Where the median's
    values bunch into modes (the tiles of a facade, each a flat colour), the photo's noisier
    values spread between them; the map is flat at the modes and steep between them, so each
    texel's noise throws it to one mode or the other, and the texture shows salt-and-pepper on
    the tiles whose values fall on a steep step (archive wall00 at `balanced`).
    """
    if paired:
        ok = (src > GAIN_MIN_VALUE) & (ref > GAIN_MIN_VALUE)
        g = float(np.median(ref[ok] / src[ok])) if ok.any() else 1.0
    else:
        ms = float(np.median(src)) if src.size else 0.0
        g = float(np.median(ref)) / ms if ms > GAIN_MIN_VALUE else 1.0
    g = float(np.clip(g, *GAIN_RANGE))
    x = identity_transfer()[0, 0]
    return np.stack([x, np.minimum(1.0, g * x)]).astype(np.float32)


def _knots(src: np.ndarray, ref: np.ndarray, model: str, paired: bool) -> np.ndarray:
    """The transfer knots of one channel under ``model`` (quantile | gain)."""
    return quantile_knots(src, ref) if model == "quantile" else gain_knots(src, ref, paired)


def _shares_enough(overlap: int, seen: int, min_overlap: int) -> bool:
    """Whether a photo's texels shared with its reference (>= min_overlap and >= 5 % of what it
    sees) are enough to match on; otherwise whole views are compared."""
    return overlap >= max(min_overlap, 0.05 * seen)


def transfers_from_mapped(
    colours: dict[int, torch.Tensor],
    visible: dict[int, torch.Tensor],
    frontality: dict[int, torch.Tensor],
    reference: str = "best",
    channels: str = "sv",
    min_overlap: int = 64,
    model: str = "gain",
) -> tuple[dict[int, np.ndarray], int | None]:
    """Transfers per photo from their mapped colours (3, h, w) and visibility (h, w) at one level.

    ``model``: quantile (a monotone quantile map per channel, the paper's histogram matching) or
    gain (one gain per channel, :func:`gain_knots`).

    Returns ({photo: (3, 2, N_KNOTS)}, reference photo, or None for median and pooled).
    """
    chan_ids = ["hsv".index(c) for c in channels]
    hsv = {n: rgb_to_hsv(c.clamp(0, 1)).cpu().numpy() for n, c in colours.items()}
    vis = {n: v.cpu().numpy().astype(bool) for n, v in visible.items()}
    out = {n: identity_transfer() for n in colours}
    if not colours:
        return out, None
    if reference == "best":
        ref = max(colours, key=lambda n: (float((frontality[n] * visible[n]).sum()), -n))
        for n in colours:
            if n == ref:
                continue
            ov = vis[n] & vis[ref]
            paired = _shares_enough(int(ov.sum()), int(vis[n].sum()), min_overlap)
            # too little common area: compare each photo's whole view of the polygon
            ms, mr = (ov, ov) if paired else (vis[n], vis[ref])
            if ms.sum() == 0 or mr.sum() == 0:
                continue
            for c in chan_ids:
                out[n][c] = _knots(hsv[n][c][ms], hsv[ref][c][mr], model, paired)
        return out, ref
    if reference == "median":
        return _median_transfers(hsv, vis, chan_ids, min_overlap, model), None
    pooled = {c: np.concatenate([hsv[n][c][vis[n]] for n in colours]) for c in chan_ids}
    for n in colours:
        if vis[n].sum() == 0 or any(len(p) == 0 for p in pooled.values()):
            continue
        for c in chan_ids:
            out[n][c] = _knots(hsv[n][c][vis[n]], pooled[c], model, False)
    return out, None


def _median_transfers(
    hsv: dict[int, np.ndarray], vis: dict[int, np.ndarray], chan_ids: list[int], min_overlap: int,
    model: str = "gain",
) -> dict[int, np.ndarray]:
    """Match every photo to the per-texel median of all photos (the consensus image).

    The median over the photos that see a texel ignores a minority of outliers (an occluder in
    one photo, a badly exposed photo), and the consensus exposure is the median photo exposure,
    so no single dark or bright photo sets the texture's brightness. Each photo is matched on
    the texels it sees where at least two photos define the median: the same content on both
    sides, unlike the pooled histogram, which mixes content only some photos see.
    """
    names = list(hsv)
    out = {n: identity_transfer() for n in names}
    count = np.sum([vis[n] for n in names], axis=0)
    defined = count >= 2
    if not defined.any():
        return out  # one photo per texel: nothing to agree on
    flat = np.flatnonzero(defined)
    med = np.empty((3, flat.size), np.float32)
    # In blocks of texels: the (photos, 3, texels) stack of a polygon seen by hundreds of photos
    # would not fit in memory at once.
    block = max(1, MEDIAN_BLOCK_VALUES // (3 * len(names)))
    for b0 in range(0, flat.size, block):
        sel = flat[b0 : b0 + block]
        stack = np.stack([np.where(vis[n].ravel()[sel][None], hsv[n].reshape(3, -1)[:, sel], np.nan) for n in names])
        with np.errstate(all="ignore"):
            med[:, b0 : b0 + block] = np.nanmedian(stack, axis=0)
    for n in names:
        ov = vis[n][defined]
        paired = _shares_enough(int(ov.sum()), int(vis[n].sum()), min_overlap)
        if paired:  # the same texels in the same (flat) order on both sides
            src, ref = hsv[n][:, vis[n] & defined], med[:, ov]
        else:  # the photo sees little of the consensus area: compare whole views
            src, ref = hsv[n][:, vis[n]], med
        if src.shape[1] == 0 or ref.shape[1] == 0:
            continue
        for c in chan_ids:
            out[n][c] = _knots(src[c], ref[c], model, paired)
    return out


def mapped_transfers(
    mapped: dict, n_photos: int, reference: str = "median", channels: str = "sv", names: list[str] | None = None,
    model: str = "gain",
) -> tuple[list, str | None]:
    """Transfers of every candidate from its raw mapped photo at one (coarse) level.

    Args:
        mapped: {photo index: difftex.sampling.photos.MappedPhoto or None} without transfers.
        n_photos: number of candidates (the list's length).

    Returns:
        (list per photo: (3, 2, N_KNOTS), or None when the photo sees nothing; the reference
        photo's name for "best", else None).
    """
    cols = {n: mp.colour for n, mp in mapped.items() if mp is not None}
    vis = {n: mp.visible for n, mp in mapped.items() if mp is not None}
    fr = {n: mp.cos for n, mp in mapped.items() if mp is not None}
    tr, ref = transfers_from_mapped(cols, vis, fr, reference, channels, model=model)
    name = names[ref] if (ref is not None and names is not None) else None
    return [tr.get(n) for n in range(n_photos)], name
