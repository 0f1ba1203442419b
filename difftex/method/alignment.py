"""Alignment refinement: a small affine correction of each photo's mapping f_k^i, per polygon.

Registered photos are off by a pixel or more (pose noise, residual distortion, rolling shutter),
so their mapped colours disagree at edges: blends ghost and seams break. Before the weights of
each level are optimized, every candidate photo's mapping is corrected in its own pixels,

    f_k^i(t) -> f_k^i(t) + d + M (f_k^i(t) - c) / s,

six parameters (translation d, affine part M normalised to the polygon's extent s in the photo)
found by Gauss-Newton (Lucas-Kanade) against the consensus texture: at the first aligned level
the per-texel median of the photos, after it (``align_consensus``) the previous level's optimized
texture upsampled, its blend of the photos mapped at this level (consensus_blend), or their median. The photo is
sampled through the same trilinear pyramid sampling as everywhere (difftex.sampling.photos); its
gradient by central differences. A robust (Cauchy) weight ignores occluded texels, and a
Gaussian prior of ``align_prior_px`` keeps corrections small where the texture says little
(flat walls). The corrections accumulate from coarse to fine levels. What the consensus cannot
tell (every photo moved together, or the plane moved along its normal) is taken out of the
corrections after each level: their median, or with ``align_gauge: plane`` a common shift and
height fitted over the photos (plane_gauge), so that relief does not pull them off the plane.

Why per polygon and not a pose update shared by a photo's polygons: a homography per plane is
exactly what a small pose error does to a planar polygon, and per-polygon parameters absorb
residual lens distortion and rolling shutter too, which a rigid pose cannot; small polygons,
where the per-polygon fit is poorly conditioned, are held near zero by the prior.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch

from difftex.geometry.frames import UVFrame
from difftex.method.config import OptimizeConfig
from difftex.sampling.colour import apply_transfer_torch
from difftex.sampling.photos import Correction, PhotoSet
from difftex.sampling.texels import resample_nearest, texel_map

# Photos refined together below which the plane gauge falls back to the median: it fits four
# parameters from two equations per photo, and with few photos a chance correlation of their pose
# errors with their parallax is taken for height (docs/optimizer.md, "Alignment refinement").
PLANE_GAUGE_MIN_PHOTOS = 12
PLANE_GAUGE_T = 3.0  # a fitted height is kept beyond this many of its standard errors


@dataclass(frozen=True)
class AlignSettings:
    model: str  # "translation" (2 parameters) or "affine" (6)
    iterations: int  # Gauss-Newton steps per level
    prior_px: float  # standard deviation of the prior on every parameter, pixels
    max_px: float  # corrections larger than this (at the polygon's edge) are rejected
    noise: float  # colour noise (sigma_c): the prior's and the robust weight's scale
    gauge: str = "median"  # what is taken out of the corrections: their median, or plane_gauge's fit
    robust: float = 3.0  # Cauchy scale, robust standard deviations of a photo's residuals
    points: int = OptimizeConfig.align_points  # texels per photo and step, at most (a strided subset above it)


def _basis(pix: torch.Tensor, centre: tuple[float, float], scale: float) -> torch.Tensor:
    """(n, 2, 6) derivative of the correction's displacement with respect to its parameters."""
    u = (pix[:, 0] - centre[0]) / scale
    v = (pix[:, 1] - centre[1]) / scale
    one, zero = torch.ones_like(u), torch.zeros_like(u)
    row_x = torch.stack([one, zero, u, v, zero, zero], -1)
    row_y = torch.stack([zero, one, zero, zero, u, v], -1)
    return torch.stack([row_x, row_y], 1)


def _sample(photos: PhotoSet, n: int, pix: torch.Tensor, fp: torch.Tensor, transfer) -> torch.Tensor:
    """(3, m) colours of photo n at pixels (m, 2), through its brightness transfer."""
    col = photos.samplers[n].sample(pix.float()[None], fp.float()[None])[:, 0]
    return apply_transfer_torch(col[:, :, None], transfer)[:, :, 0] if transfer is not None else col


def gauss_newton(
    photos: PhotoSet,
    n: int,
    pix0: torch.Tensor,
    fp: torch.Tensor,
    target: torch.Tensor,
    weight: torch.Tensor,
    corr: Correction,
    transfer,
    st: AlignSettings,
) -> Correction:
    """``st.iterations`` Gauss-Newton steps of photo n's correction against ``target``.

    Args:
        pix0: (m, 2) uncorrected pixel positions of the texels; fp: (m,) their footprints.
        target: (3, m) consensus colours; weight: (m,) confidence of each texel (the robust
            weight multiplies it).
    """
    B = _basis(pix0.double(), corr.centre, corr.scale)  # (m, 2, 6)
    # The affine part is held four times closer to zero than the translation: a small pose error
    # moves a polygon's image mostly as a whole, while differences of blur between photos (their
    # footprints differ) would otherwise leak into the scale and shear terms.
    affine_sd = 0.25 if st.model == "affine" else 1e-6  # "translation": the affine part held at zero
    sd = torch.tensor([1.0, 1.0] + [affine_sd] * 4, dtype=torch.float64) * st.prior_px
    prior = torch.diag(1.0 / sd**2)
    inv_var = 1.0 / (3 * st.noise**2)  # per texel, over the three channels
    params = corr.params.clone()
    for _ in range(st.iterations):
        cur = Correction(params, corr.centre, corr.scale)
        pix = cur.apply(pix0)
        h = (0.5 * fp).clamp_min(0.5)[:, None]  # half a texel, at least half a pixel
        ex = torch.zeros_like(pix)
        ex[:, 0] = 1.0
        ey = torch.zeros_like(pix)
        ey[:, 1] = 1.0
        # the five samples in one call: the pyramid levels are read (and widened from float16) once
        at = torch.cat([pix, pix + h * ex, pix - h * ex, pix + h * ey, pix - h * ey])
        col, xp, xm, yp, ym = _sample(photos, n, at, fp.repeat(5), transfer).chunk(5, dim=1)
        gx = (xp - xm) / (2 * h.T)
        gy = (yp - ym) / (2 * h.T)
        r = (col - target).double()  # (3, m)
        grad = torch.stack([gx, gy], -1).double()  # (3, m, 2)
        J = torch.einsum("cmk,mkp->cmp", grad, B)  # (3, m, 6)
        # Cauchy weights at st.robust robust standard deviations of this photo's residuals (its
        # median squared residual), at least the noise: an occluded texel hardly counts, and at
        # one deviation neither does relief that the photo sees displaced by parallax.
        e2 = (r * r).sum(0)
        k2 = st.robust**2
        c2 = max(k2 * 2.2 * float(e2.median()), k2 * st.noise**2)
        w = weight.double() / (1.0 + e2 / c2)
        # the 6x6 system on the CPU, where the parameters live (the sums run on the photos' device)
        Hm = torch.einsum("cmp,m,cmq->pq", J, w, J).cpu() * inv_var + prior
        g = torch.einsum("cmp,m,cm->p", J, w, r).cpu() * inv_var + prior @ params
        try:
            step = -torch.linalg.solve(Hm, g)
        except RuntimeError:  # singular: nothing to align on
            break
        params = params + step
        if float(step.abs().max()) < 1e-3:
            break
    return Correction(params, corr.centre, corr.scale)


def consensus_median(
    photos: PhotoSet, frame: UVFrame, mask: np.ndarray, transfers: list | None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-texel median of the mapped photos ((3, h, w)) and where two or more define it."""
    mapped = {n: photos.map(n, frame, mask, transfers[n] if transfers else None) for n in sorted(photos.samplers)}
    maps = {n: mp for n, mp in mapped.items() if mp is not None}
    if not maps:
        h, w = frame.shape
        return torch.zeros(3, h, w, device=photos.device), torch.zeros(h, w, dtype=torch.bool, device=photos.device)
    col = torch.stack([mp.colour for mp in maps.values()])
    vis = torch.stack([mp.visible for mp in maps.values()])
    x = torch.where(vis[:, None], col, torch.full_like(col, float("nan")))
    med = torch.nanmedian(x, dim=0).values
    return torch.nan_to_num(med), vis.sum(0) >= 2


def consensus_blend(
    photos: PhotoSet,
    frame: UVFrame,
    mask: np.ndarray,
    transfers: list | None,
    held: list[int],
    weight_of: Callable[[int], torch.Tensor],
) -> tuple[torch.Tensor, torch.Tensor]:
    """The previous level's blend at this level's detail ((3, h, w)) and where it is defined.

    Args:
        held: the photos that hold blend weight; weight_of(n): photo n's weight (h, w) on this
            level's frame (the coarser level's optimized W, upsampled), asked for one photo at a
            time. Each photo is mapped at this level with its current correction and blended by
            those weights: the texture the optimizer chose, with this level's detail, where the
            upsampled texture would be a level blurrier.

    Returns:
        (consensus, defined): defined where the photos mapped hold at least half of the weight.
    """
    h, w = frame.shape
    num = torch.zeros(3, h, w, device=photos.device)
    den = torch.zeros(h, w, device=photos.device)
    total = torch.zeros(h, w, device=photos.device)
    for n in sorted(held):
        wn = weight_of(n)
        total += wn
        mp = photos.map(n, frame, mask, transfers[n] if transfers else None)
        if mp is None:
            continue
        v = wn * mp.visible.float()
        num += mp.colour * v
        den += v
    return num / den.clamp_min(1e-6), (den > 0.5 * total) & (den > 1e-3)


def align_level(
    photos: PhotoSet,
    frame: UVFrame,
    mask: np.ndarray,
    transfers: list | None,
    consensus: torch.Tensor,
    defined: torch.Tensor,
    st: AlignSettings,
    which: set[int] | None = None,
) -> dict:
    """Refine the candidate photos' corrections against ``consensus`` (3, h, w) at ``frame``.

    Args:
        which: the photos to refine (None: every candidate); the others keep their correction
            (up to the common shift that _fix_gauge removes).

    Returns per photo name: the correction's largest displacement at the polygon's extent
    (pixels), how far this call moved it (``update_px``), its parameters, and whether it was
    kept (one beyond ``max_px`` is discarded).
    """
    inp = photos.inp
    report = {}
    # Not the polygon's border texels: their footprint reaches past the polygon's edge, where
    # photos see other surfaces (and the consensus blends them), which would pull the fit.
    outside = torch.nn.functional.pad((~defined).float()[None, None], (2, 2, 2, 2), value=1.0)
    inner = torch.nn.functional.max_pool2d(outside, 5, stride=1)[0, 0] == 0
    defined = defined & inner
    before = dict(photos.corrections)
    geometry: dict[int, tuple[torch.Tensor, torch.Tensor, torch.Tensor]] = {}
    for n in sorted(photos.samplers):
        if which is not None and n not in which:
            continue
        ph = inp.photos[n]
        tm = texel_map(frame, ph, photos.device)
        vis = resample_nearest(inp.texel_visible[n], inp.frame, frame) & mask
        sel = tm.valid & torch.from_numpy(np.ascontiguousarray(vis)).to(photos.device) & defined
        if int(sel.sum()) < 64:
            continue
        idx = torch.nonzero(sel.flatten()).flatten()
        if len(idx) > st.points:
            idx = idx[:: math.ceil(len(idx) / st.points)]
        pix0 = tm.pix.reshape(-1, 2)[idx].double()
        fp = tm.footprint.reshape(-1)[idx]
        corr = photos.corrections.get(n)
        if corr is None:
            lo, hi = pix0.min(0).values, pix0.max(0).values
            centre = (float((lo[0] + hi[0]) / 2), float((lo[1] + hi[1]) / 2))
            corr = Correction(torch.zeros(6, dtype=torch.float64), centre, max(float((hi - lo).max()) / 2, 1.0))
        if st.gauge == "plane":
            geometry[n] = (*texel_jacobian_and_parallax(tm, frame, idx), pix0)
        target = consensus.reshape(3, -1)[:, idx]
        weight = torch.ones(len(idx), device=pix0.device)
        new = gauss_newton(photos, n, pix0, fp, target, weight, corr, transfers[n] if transfers else None, st)
        if bool(torch.isfinite(new.params).all()):
            photos.corrections[n] = new
        report[ph.name] = n
    if st.gauge == "plane" and len(geometry) >= PLANE_GAUGE_MIN_PHOTOS:
        plane_gauge(photos, geometry)
    else:
        _fix_gauge(photos)
    out = {}
    for name, n in report.items():
        c = photos.corrections.get(n)
        edge = max_shift(c) if c is not None else 0.0
        old = before.get(n)  # a photo with a correction before keeps one (only finite ones are set)
        moved = max_shift(Correction(c.params - old.params, c.centre, c.scale)) if c and old else edge
        out[name] = {
            "max_shift_px": round(edge, 3),
            "update_px": round(moved, 3),
            "kept": c is not None and edge <= st.max_px,
            "params": [round(float(v), 4) for v in c.params] if c is not None else None,
        }
        if c is not None and edge > st.max_px:
            del photos.corrections[n]
    return out


def max_shift(c: Correction) -> float:
    """The correction's largest displacement at the corners of the polygon's extent, pixels."""
    s = c.scale
    corners = torch.tensor(
        [[c.centre[0] + a * s, c.centre[1] + b * s] for a in (-1, 1) for b in (-1, 1)], dtype=torch.float64
    )
    return float(c.displacement(corners).norm(dim=1).max())


def _fix_gauge(photos: PhotoSet) -> None:
    """Remove the corrections' common part (their median): shifting every photo together changes
    no agreement between them, so the consensus alone does not fix it, and a photo that is off
    pulls the consensus, and with it the others, towards itself over the levels. The median
    photo stays where its registration put it."""
    if len(photos.corrections) < 3:
        return
    med = torch.stack([c.params for c in photos.corrections.values()]).median(0).values
    for n, c in photos.corrections.items():
        photos.corrections[n] = Correction(c.params - med, c.centre, c.scale)


def texel_jacobian_and_parallax(tm, frame: UVFrame, idx: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """At the texels ``idx`` (flat indices) of ``tm``'s frame: the photo's pixels per texel and
    where a point one scene unit in front of the plane is seen on it.

    A point at height h along the normal n, seen along the unit direction v (camera to texel), is
    seen on the plane at h (n - v / (v . n)) from its foot: the parallax per unit height.

    Returns:
        J (m, 2, 2): columns d pixel / d texel x and y (finite differences of the texel map);
        P (m, 2): parallax per unit height, texels.
    """
    h, w = tm.pix.shape[:2]
    flat = tm.pix.reshape(-1, 2)

    def difference(along: torch.Tensor, size: int, stride: int) -> torch.Tensor:
        """Forward difference to the next texel along an axis (backward at its last texel), only
        at ``idx``: the whole frame's differences would be computed for a few thousand texels."""
        if size < 2:
            return torch.zeros(len(idx), 2, dtype=torch.float64, device=flat.device)
        a = torch.where(along == size - 1, idx - stride, idx)
        return flat[a + stride].double() - flat[a].double()

    J = torch.stack([difference(idx % w, w, 1), difference(idx // w, h, w)], -1)
    v = tm.view.double().reshape(3, -1)[:, idx].cpu()
    n = torch.tensor(np.asarray(frame.normal), dtype=torch.float64)
    vn = (v * n[:, None]).sum(0).clamp(max=-1e-3)  # front-facing texels look against the normal
    p3 = n[:, None] - v / vn[None]
    axes = torch.tensor(np.stack([frame.e_u, frame.e_v]), dtype=torch.float64)  # (2, 3)
    return J.cpu(), (axes @ p3).T / frame.texel_size


def _huber_fit(A: torch.Tensor, b: torch.Tensor, iterations: int = 5) -> torch.Tensor:
    """(t_x, t_y, h_x, h_y) of plane_gauge: least squares with Huber weights (1.345 robust
    deviations, so a photo far off does not set the gauge); a height within PLANE_GAUGE_T robust
    standard errors of zero is set to zero and the shift refitted without it: the pose errors of
    a few dozen photos correlate with their parallax by that much by chance, and taking that
    out would misalign photos that agree on a flat surface."""
    cols = list(range(A.shape[1]))
    for _ in range(2):
        As = A[:, cols]
        w = torch.ones(len(b), dtype=torch.float64)
        for _ in range(iterations):
            xs = torch.linalg.lstsq(As * w.sqrt()[:, None], b * w.sqrt()).solution
            r = (b - As @ xs).abs()
            s = 1.4826 * float(r.median()) + 1e-9
            w = (1.345 * s / r.clamp_min(1e-12)).clamp(max=1.0)
        cov = s**2 * torch.linalg.pinv((As * w[:, None]).T @ As)
        x = torch.zeros(A.shape[1], dtype=torch.float64)
        x[cols] = xs
        weak = [c for j, c in enumerate(cols) if c >= 2 and abs(float(xs[j])) < PLANE_GAUGE_T * float(cov[j, j].sqrt())]
        if not weak:
            break
        cols = [c for c in cols if c not in weak]
    return x


def plane_gauge(photos: PhotoSet, geometry: dict) -> None:
    """Take out of the refined photos' corrections what a common in-plane shift t and a common
    height h_x, h_y per texel axis explain.

    Aligning photos to their consensus cannot see either: every photo moved together, or the
    plane moved along its normal (each photo then shifts by its parallax). Relief decides both:
    the fit follows the layer with the most contrast (window frames, reveals), not the plane the
    texture lies in, and vertical and horizontal edges can sit at different depths. With photo k's
    correction moving its samples by e_k texels on average and P_k its parallax per unit height,

        e_k = t + diag(h_x, h_y) P_k + (the photo's own pose error),

    fitted over the photos by least squares with Huber weights; the fitted part is removed.

    Args:
        geometry: photo index -> (J (m, 2, 2), P (m, 2), pix0 (m, 2)) at its fitted texels.
    """
    names, E, P, J = [], [], [], []
    for n, (Jn, Pn, pix0) in geometry.items():
        c = photos.corrections.get(n)
        if c is None:
            continue
        # texels whose finite differences reach past the photo's edge or fold are left out
        ok = torch.isfinite(Jn).all((1, 2)) & (torch.linalg.det(Jn).abs() > 1e-9) & torch.isfinite(Pn).all(1)
        if not bool(ok.any()):
            continue
        d = c.displacement(pix0.cpu()[ok]).double()
        e = torch.linalg.solve(Jn[ok], d[..., None])[..., 0]  # texels, per fitted texel
        names.append(n)
        E.append(e.mean(0))
        P.append(Pn[ok].mean(0))
        J.append(Jn[ok].mean(0))
    if len(names) < PLANE_GAUGE_MIN_PHOTOS:
        _fix_gauge(photos)
        return
    Em, Pm = torch.stack(E), torch.stack(P)
    k = len(names)
    A = torch.zeros(2 * k, 4, dtype=torch.float64)
    A[0::2, 0] = 1.0
    A[1::2, 1] = 1.0
    A[0::2, 2] = Pm[:, 0]
    A[1::2, 3] = Pm[:, 1]
    x = _huber_fit(A, Em.reshape(-1))
    for i, n in enumerate(names):
        g = J[i] @ (x[:2] + x[2:] * Pm[i])  # pixels
        c = photos.corrections[n]
        p = c.params.clone()
        p[:2] -= g.to(p.dtype)
        photos.corrections[n] = Correction(p, c.centre, c.scale)
