"""Where a polygon's texture loses detail: figures written to stats.json and the report.

- effective photos per texel, 1 / sum_k W_k^2 (1: one photo; n: an even blend of n), and the
  largest weight: how much the optimizer selects;
- the share of texels whose dominant photo changed during a level (did the weights move?);
- residual misalignment of each photo against the texture, by masked phase correlation
  (scikit-image), in texels;
- sharpness: mean gradient magnitude of the texture against that of the sharpest single photo
  over the same texels.
"""

from __future__ import annotations

import numpy as np
import torch

from difftex.method.elimination import argmax0


def effective_photos(W: torch.Tensor, mask: torch.Tensor) -> dict:
    """Mean and median of 1 / sum_k W_k^2, and the median largest weight, over textured texels.

    Args:
        W: (K, h, w) blend weights; mask: (h, w) bool polygon texels.
    """
    s2 = (W * W).sum(0)
    sel = mask & (s2 > 0)
    if not bool(sel.any()):
        return {"effective_photos_mean": None, "effective_photos_median": None, "max_weight_median": None}
    n = (1.0 / s2[sel]).float()
    return {"effective_photos_mean": float(n.mean()), "effective_photos_median": float(n.median()),
            "max_weight_median": float(W.amax(0)[sel].float().median())}


def dominant_photo(idx: torch.Tensor, W: torch.Tensor) -> torch.Tensor:
    """(h, w) photo index with the largest weight per texel (-1 where no weight)."""
    j = argmax0(W)
    d = torch.gather(idx, 0, j)[0]
    return torch.where(W.amax(0) > 0, d, torch.full_like(d, -1))


def changed_share(a: torch.Tensor, b: torch.Tensor, mask: torch.Tensor) -> float | None:
    """Share of the polygon's texels (both defined) where two dominant-photo maps differ."""
    sel = mask & (a >= 0) & (b >= 0)
    return float((a != b)[sel].float().mean()) if bool(sel.any()) else None


def mean_gradient(img: torch.Tensor, mask: torch.Tensor) -> float:
    """Mean gradient magnitude (forward differences, mean over channels) over texel pairs inside ``mask``."""
    gx = (img[:, :, 1:] - img[:, :, :-1]).abs().mean(0)
    gy = (img[:, 1:, :] - img[:, :-1, :]).abs().mean(0)
    mx = mask[:, 1:] & mask[:, :-1]
    my = mask[1:, :] & mask[:-1, :]
    n = int(mx.sum() + my.sum())
    return float((gx[mx].sum() + gy[my].sum()) / n) if n else 0.0


def photo_coverage(idx: torch.Tensor, visible: torch.Tensor, W: torch.Tensor | None, mask: torch.Tensor) -> dict:
    """Per photo: the texels of ``mask`` it sees and (with ``W``) its weight summed over them.

    One scatter over the slots instead of a (K, h, w) comparison per photo: a texel's slots hold
    distinct photos, so a photo is counted at most once per texel.

    Returns:
        {photo index: (texels seen, weight sum or 0.0)}.
    """
    sel = visible & mask[None] & (idx >= 0)
    ids = idx[sel]
    if ids.numel() == 0:
        return {}
    n = int(ids.max()) + 1
    seen = torch.bincount(ids, minlength=n)
    wsum = torch.zeros(n, dtype=torch.float64)
    if W is not None:
        wsum = torch.bincount(ids, weights=W[sel].double(), minlength=n)
    return {int(p): (int(seen[p]), float(wsum[p])) for p in torch.nonzero(seen).flatten().tolist()}


def photo_colours(
    colours: torch.Tensor, idx: torch.Tensor, visible: torch.Tensor, n: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """Photo ``n``'s colours (3, h, w) where it holds a visible slot, and that (h, w) mask."""
    at = (idx == n) & visible  # at most one slot per texel: the sum picks it (a gather was slower)
    return torch.where(at[:, None], colours, 0.0).sum(0), at.any(0)


def sharpness(U: torch.Tensor, colours: torch.Tensor, idx: torch.Tensor, visible: torch.Tensor,
              mask: torch.Tensor, min_share: float = 0.25) -> dict:
    """The texture's mean gradient against the sharpest single photo's, on that photo's texels.

    Args:
        U: (3, h, w) texture; colours / idx / visible: the level's slots (K, 3, h, w), (K, h, w).
        min_share: photos seeing less than this share of the polygon are not candidates.

    Returns:
        {"texture": mean gradient of U, "sharpest_photo": the photo's, "ratio": texture / photo on
        the photo's texels, "photo": its index}.
    """
    best = {"texture": mean_gradient(U, mask), "sharpest_photo": None, "ratio": None, "photo": None}
    n_tex = int(mask.sum())
    top = 0.0
    for n, (count, _) in photo_coverage(idx, visible, None, mask).items():
        if count < min_share * n_tex:
            continue
        col, seen = photo_colours(colours, idx, visible, n)
        seen = seen & mask
        g = mean_gradient(col, seen)
        if g > top:
            top = g
            best.update(sharpest_photo=g, photo=int(n), ratio=mean_gradient(U, seen) / max(g, 1e-12))
    return best


def _upsampled_dft(data: np.ndarray, size: int, factor: float, offsets: np.ndarray) -> np.ndarray:
    """The DFT of ``data`` on a ``size`` x ``size`` grid upsampled ``factor`` times, starting at ``offsets``
    (Guizar-Sicairos et al. 2008, matrix-multiply DFT; as scikit-image's ``_upsampled_dft``)."""
    for n_items, offset in list(zip(data.shape, offsets))[::-1]:
        kernel = (np.arange(size) - offset)[:, None] * np.fft.fftfreq(n_items, factor)
        data = np.tensordot(np.exp(-2j * np.pi * kernel), data, axes=(1, -1))
    return data


def phase_shift(reference: np.ndarray, moving: np.ndarray, upsample: int = 10) -> np.ndarray:
    """(dy, dx) that registers ``moving`` to ``reference`` by phase correlation, to 1/``upsample`` pixel.

    scikit-image's ``registration.phase_cross_correlation(..., normalization=None)`` (BSD-3-Clause),
    step for step (tests/test_diagnostics.py compares them): importing it (with scipy.fft) was
    0.4 s of every texture job, more than the measurement itself.

    Args:
        reference, moving: (h, w) real images of one shape.
        upsample: the shift's resolution is 1 / upsample pixel.

    Returns:
        (2,) float shift.
    """
    if reference.shape != moving.shape or reference.ndim != 2:
        raise ValueError(f"need two 2-D images of one shape, got {reference.shape} and {moving.shape}")
    product = np.fft.fft2(reference) * np.fft.fft2(moving).conj()
    corr = np.fft.ifft2(product)
    shape = np.array(corr.shape)
    shifts = np.array(np.unravel_index(np.argmax(np.abs(corr)), corr.shape), dtype=np.float64)
    wrap = shifts > np.trunc(shape / 2)
    shifts[wrap] -= shape[wrap]
    if upsample > 1:
        shifts = np.round(shifts * upsample) / upsample
        region = np.ceil(upsample * 1.5)
        centre = np.trunc(region / 2.0)
        up = _upsampled_dft(product.conj(), int(region), upsample, centre - shifts * upsample).conj()
        peak = np.array(np.unravel_index(np.argmax(np.abs(up)), up.shape), dtype=np.float64)
        shifts = shifts + (peak - centre) / upsample
    shifts[shape == 1] = 0.0
    return shifts


def misalignment(U: torch.Tensor, colours: torch.Tensor, idx: torch.Tensor, visible: torch.Tensor,
                 W: torch.Tensor, mask: torch.Tensor, min_share: float = 0.25, max_side: int = 512,
                 max_photos: int = 8) -> dict:
    """Shift (texels) of each photo's mapped colours against the texture, by phase correlation.

    The ``max_photos`` photos that carry the most weight and see at least ``min_share`` of the
    polygon are measured, in grey, on at most ``max_side`` texels (the shift is scaled back to
    the level's texels), to a tenth of a texel; texels the photo does not see take the
    texture's values, so that the edge of its view adds no false edge (scikit-image's masked
    variant only finds whole texels; :func:`phase_shift` is its unmasked one). The texture
    includes the photo's own contribution, which pulls the figure towards zero.

    Returns:
        {photo index: [dy, dx] in texels, ...} and "median_abs" (the weight-share-weighted median of
        |shift| over the measured photos).
    """
    h, w = mask.shape
    step = max(1, int(np.ceil(max(h, w) / max_side)))
    # everything on the subsampled grid: the shares and coverage are estimates anyway, and the
    # per-photo masks over the full (K, h, w) level cost more than the correlation
    U, colours, idx, visible, W, mask = (
        t[..., ::step, ::step] for t in (U, colours, idx, visible, W, mask)
    )
    grey_u = U.mean(0).cpu().numpy()
    m = mask.cpu().numpy()
    n_tex = int(mask.sum())
    out: dict = {}
    mags, shares = [], []
    cover = photo_coverage(idx, visible, W, mask)
    measured = [n for n, (count, wsum) in cover.items() if count >= min_share * n_tex and wsum > 0]
    # the photos that carry the most weight: the others hardly show in the texture
    measured = sorted(measured, key=lambda n: -cover[n][1])[:max_photos]
    if measured:
        ys, xs = np.nonzero(m)
        box = (slice(ys.min(), ys.max() + 1), slice(xs.min(), xs.max() + 1))
        filled = np.where(m, grey_u, grey_u[m].mean())
        ref = filled[box]
    for n in measured:
        share = cover[n][1] / max(n_tex, 1)
        col_n, seen = photo_colours(colours, idx, visible, n)
        col = col_n.mean(0).cpu().numpy()
        sm = seen.cpu().numpy() & m
        if sm.sum() < 64:
            continue
        mov = np.where(sm, col, filled)[box]
        try:
            shift = phase_shift(ref, mov, upsample=10)
        except (ValueError, RuntimeError):
            continue
        s = np.asarray(shift, float) * step
        out[int(n)] = [round(float(v), 3) for v in s]
        mags.append(float(np.hypot(*s)))
        shares.append(share)
    if mags:
        order = np.argsort(mags)
        cum = np.cumsum(np.asarray(shares)[order])
        out["median_abs"] = float(np.asarray(mags)[order][np.searchsorted(cum, cum[-1] / 2)])
    return out
