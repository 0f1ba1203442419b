"""Brightness adjustment (paper 4.3): HSV histogram matching of the photos feeding one polygon.

Each candidate photo k gets a monotone transfer per HSV channel (a quantile map), estimated on
the polygon's texels that photo k and the reference both see, so occluders and content seen by
only one photo do not bias it. References:

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

N_KNOTS = 129
MEDIAN_BLOCK_VALUES = 1 << 24  # floats per block of the per-texel median (64 MB)
_Q = np.linspace(0.005, 0.995, N_KNOTS - 2)


def rgb_to_hsv(rgb: torch.Tensor) -> torch.Tensor:
    """(3, ...) RGB in [0, 1] to HSV with H in [0, 1)."""
    r, g, b = rgb[0], rgb[1], rgb[2]
    v, _ = rgb.max(0)
    mn, _ = rgb.min(0)
    c = v - mn
    s = torch.where(v > 0, c / v.clamp_min(1e-12), torch.zeros_like(v))
    cz = c.clamp_min(1e-12)
    h = torch.where(v == r, ((g - b) / cz) % 6, torch.where(v == g, (b - r) / cz + 2, (r - g) / cz + 4))
    h = torch.where(c > 0, h / 6.0, torch.zeros_like(h)) % 1.0
    return torch.stack([h, s, v])


def hsv_to_rgb(hsv: torch.Tensor) -> torch.Tensor:
    h, s, v = hsv[0] % 1.0, hsv[1].clamp(0, 1), hsv[2]
    out = []
    for n in (5.0, 3.0, 1.0):
        k = (n + h * 6.0) % 6.0
        out.append(v - v * s * torch.clamp(torch.minimum(k, 4.0 - k), 0.0, 1.0))
    return torch.stack(out)


def identity_transfer() -> np.ndarray:
    """(3, 2, N_KNOTS) knots (source, reference) per HSV channel that map every value to itself."""
    x = np.concatenate([[0.0], _Q, [1.0]])
    return np.stack([np.stack([x, x])] * 3).astype(np.float32)


def quantile_knots(src: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """(2, N_KNOTS) monotone knots mapping the distribution of ``src`` onto that of ``ref``.

    End knots (0 -> 0, 1 -> 1) make values outside the observed range interpolate towards the
    ends instead of clipping; a tiny ramp keeps the source knots strictly increasing.
    """
    sq = np.quantile(src, _Q)
    rq = np.quantile(ref, _Q)
    xs = np.concatenate([[0.0], sq, [1.0]])
    ys = np.concatenate([[0.0], rq, [1.0]])
    xs = np.maximum.accumulate(xs) + np.linspace(0.0, 1e-6, N_KNOTS)
    ys = np.maximum.accumulate(ys)
    return np.stack([xs, ys]).astype(np.float32)


def _interp(x: torch.Tensor, xs: torch.Tensor, ys: torch.Tensor) -> torch.Tensor:
    """Piecewise-linear map (np.interp for torch, clamped at the ends)."""
    i = torch.searchsorted(xs, x.contiguous().clamp(float(xs[0]), float(xs[-1])), right=True).clamp(1, len(xs) - 1)
    x0, x1, y0, y1 = xs[i - 1], xs[i], ys[i - 1], ys[i]
    t = ((x - x0) / (x1 - x0).clamp_min(1e-12)).clamp(0.0, 1.0)
    return y0 + t * (y1 - y0)


def apply_transfer_torch(rgb: torch.Tensor, transfer: np.ndarray) -> torch.Tensor:
    """Apply a (3, 2, N_KNOTS) HSV transfer to colours (3, ...) in [0, 1]."""
    t = torch.as_tensor(np.asarray(transfer), dtype=rgb.dtype, device=rgb.device)
    hsv = rgb_to_hsv(rgb.clamp(0.0, 1.0))
    chans = [_interp(hsv[c].reshape(-1), t[c, 0], t[c, 1]).reshape(hsv[c].shape) for c in range(3)]
    return hsv_to_rgb(torch.stack(chans))


def apply_transfer(rgb: np.ndarray, transfer: np.ndarray) -> np.ndarray:
    """numpy (..., 3) convenience wrapper of apply_transfer_torch."""
    t = torch.from_numpy(np.moveaxis(np.asarray(rgb, np.float32), -1, 0).copy())
    return np.moveaxis(apply_transfer_torch(t, transfer).numpy(), 0, -1)


def _shares_enough(overlap: int, seen: int, min_overlap: int) -> bool:
    """Whether a photo's texels shared with its reference (>= min_overlap and >= 5 % of what it
    sees) are enough to match on; otherwise whole views are compared."""
    return overlap >= max(min_overlap, 0.05 * seen)


def transfers_from_mapped(colours: dict[int, torch.Tensor], visible: dict[int, torch.Tensor],
                          frontality: dict[int, torch.Tensor], reference: str = "best",
                          channels: str = "sv", min_overlap: int = 64) -> tuple[dict[int, np.ndarray], int | None]:
    """Transfers per photo from their mapped colours (3, h, w) and visibility (h, w) at one level.

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
            if _shares_enough(int(ov.sum()), int(vis[n].sum()), min_overlap):
                ms, mr = ov, ov
            else:  # too little common area: compare each photo's whole view of the polygon
                ms, mr = vis[n], vis[ref]
            if ms.sum() == 0 or mr.sum() == 0:
                continue
            for c in chan_ids:
                out[n][c] = quantile_knots(hsv[n][c][ms], hsv[ref][c][mr])
        return out, ref
    if reference == "median":
        return _median_transfers(hsv, vis, chan_ids, min_overlap), None
    pooled = {c: np.concatenate([hsv[n][c][vis[n]] for n in colours]) for c in chan_ids}
    for n in colours:
        if vis[n].sum() == 0 or any(len(p) == 0 for p in pooled.values()):
            continue
        for c in chan_ids:
            out[n][c] = quantile_knots(hsv[n][c][vis[n]], pooled[c])
    return out, None


def _median_transfers(hsv: dict[int, np.ndarray], vis: dict[int, np.ndarray], chan_ids: list[int],
                      min_overlap: int) -> dict[int, np.ndarray]:
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
        if _shares_enough(int(ov.sum()), int(vis[n].sum()), min_overlap):
            src, ref = hsv[n][:, vis[n] & defined], med[:, ov]
        else:  # the photo sees little of the consensus area: compare whole views
            src, ref = hsv[n][:, vis[n]], med
        if src.shape[1] == 0 or ref.shape[1] == 0:
            continue
        for c in chan_ids:
            out[n][c] = quantile_knots(src[c], ref[c])
    return out


def polygon_transfers(inp, cfg, device, samplers=None, long_side: int | None = None) -> tuple[list, str | None]:
    """Transfers for every candidate of a PolygonInput, estimated at the coarse level.

    Returns (list per photo: (3, 2, N_KNOTS) or None when the photo sees nothing, reference name).
    """
    from difftex.optimize import build_samplers, level_frame, map_photo, resample_nearest

    samplers = samplers if samplers is not None else build_samplers(inp, device)
    frame = level_frame(inp.frame, min(long_side or cfg.long_side_start, max(inp.frame.shape)))
    mask = resample_nearest(inp.texel_mask, inp.frame, frame)
    saved, inp.transfers = inp.transfers, None
    try:
        cols, vis, fr = {}, {}, {}
        for n, smp in samplers.items():
            mp = map_photo(inp, n, frame, smp, mask, device)
            if mp is None:
                continue
            cols[n], vis[n], fr[n] = mp.colour, mp.visible, mp.cos
    finally:
        inp.transfers = saved
    tr, ref = transfers_from_mapped(cols, vis, fr, cfg.histmatch_reference, cfg.histmatch_channels)
    return [tr.get(n) for n in range(len(inp.photos))], (inp.photos[ref].name if ref is not None else None)
