"""How much a level trusts each photo (Q = Q_a Q_c, Sec. 4.2, times the project's Q_r) and how noisy its
photos are (sigma_c)."""

from __future__ import annotations

import math

import numpy as np
import torch


def quality(
    cos: torch.Tensor,
    colour: torch.Tensor,
    mu: torch.Tensor,
    msd: torch.Tensor,
    visible: torch.Tensor,
    sigma_min: float,
    frontality_weight: float = 1.0,
) -> torch.Tensor:
    """Q_a Q_c of one photo at every texel (Sec. 4.2), the paper's initial weight Q.

    Q_a is the frontality (cosine between the texel-to-camera direction and the normal); Q_c the
    paper's Gaussian(I_k, mu, sigma) of the colour, mu and sigma the mean and variance of the
    candidates' colours: exp(-|I_k - mu|^2 / (2 sigma)), sigma their mean squared distance to mu
    plus the floor sigma_min^2 (the project's: where every candidate agrees, sigma is 0). Its peak
    is 1 (not the density's normalisation), so Q, and the weights it initialises, lie in [0, 1].
    difftex multiplies it by Q_r (:func:`resolution_factor`) unless resolution_weight is 0.

    Args:
        cos: (h, w) Q_a.
        colour: (3, h, w) the photo's mapped colours.
        mu: (3, h, w) mean colour of the candidates; msd: (h, w) their mean squared distance to it.
        visible: (h, w) bool.
        sigma_min: noise floor of the colour standard deviation.
        frontality_weight: exponent p of Q_a = cos^p (1: the paper's).

    Returns:
        (h, w) Q_a Q_c, zero where the photo does not see the texel.
    """
    d2 = ((colour - mu) ** 2).sum(0)
    qa = cos if frontality_weight == 1.0 else cos.clamp_min(0.0) ** frontality_weight
    q = qa * torch.exp(-0.5 * d2 / (msd + sigma_min**2))
    return torch.where(visible, q, torch.zeros_like(q))


# A polygon whose normal is within this cosine of horizontal (steeper than 60 degrees) is a wall
# for the tilt frontality: its relief's horizontal surfaces face up. Roofs keep Q_a alone: seen
# from above by every photo, their tilt is no sign of relief, and their frontal (nadir) photos
# are often the farthest.
WALL_MAX_UP_COS = 0.5


def wall_tilt_axis(normal: np.ndarray, up: np.ndarray) -> np.ndarray | None:
    """The in-plane vertical axis of a wall: the scene's up with its normal component removed.

    Args:
        normal: (3,) the polygon's unit normal; up: (3,) the scene's unit up.

    Returns:
        (3,) unit axis, or None where the polygon is not a wall (abs(normal . up) >= WALL_MAX_UP_COS).
    """
    n, u = np.asarray(normal, np.float64), np.asarray(up, np.float64)
    if abs(float(n @ u)) >= WALL_MAX_UP_COS:
        return None
    a = u - (u @ n) * n
    return a / np.linalg.norm(a)


def tilt_frontality(view: torch.Tensor, normal: torch.Tensor, axis: torch.Tensor) -> torch.Tensor:
    """The cosine of a view's angle to the normal in the plane of the normal and ``axis``: the
    frontality of its tilt alone (1 for a photo level with the texel, whatever its angle sideways).

    A photo from above sees the tops of a wall's relief (sills, lower reveals, balcony slabs) at
    the proxy's plane, and every drone photo sees them from the same side, so a blend keeps them;
    the side reveals, seen from the left and the right, average out. Weighing Q_a by this cosine
    to a power (``frontality_tilt``) lowers the photos from above where level ones exist, and
    leaves captures taken from one height (all photos tilted alike) nearly as they were.

    Args:
        view: (3, h, w) unit camera-to-texel directions (MappedPhoto.view).
        normal: (3,) the polygon's unit normal; axis: (3,) unit in-plane vertical (wall_tilt_axis).

    Returns:
        (h, w) in [0, 1].
    """
    if view.dim() != 3 or view.shape[0] != 3 or normal.shape != (3,) or axis.shape != (3,):
        raise ValueError(
            f"tilt_frontality: view {tuple(view.shape)} must be (3, h, w), normal {tuple(normal.shape)} "
            f"and axis {tuple(axis.shape)} (3,)"
        )
    cn = -(view * normal[:, None, None]).sum(0)
    ca = (view * axis[:, None, None]).sum(0)
    r = torch.sqrt(cn * cn + ca * ca)
    return torch.where(r > 1e-12, cn.clamp_min(0.0) / r.clamp_min(1e-12), torch.zeros_like(r))


def tilt_factor(tilt: torch.Tensor, best: torch.Tensor, power: float) -> torch.Tensor:
    """The factor of Q_a for the tilt: (tilt / best)^power, ``best`` the most level candidate's
    tilt frontality at the texel, so that texel's most level photo keeps its Q and the others
    fall by how much more they are tilted. Relative, as Q_r is: where every photo is tilted alike
    (street photos looking up at a tall facade) Q keeps its scale, and the activation threshold
    tau, which the weights start against, means what it did.

    Args:
        tilt: (h, w) a photo's tilt_frontality; best: (h, w) the largest over the texel's candidates.
        power: the exponent (``frontality_tilt``, >= 0).

    Returns:
        (h, w) in [0, 1]; 1 where no candidate has a tilt above 0 (best = 0).
    """
    r = torch.where(best > 0, tilt / best.clamp_min(1e-12), torch.ones_like(tilt))
    return r.clamp(0.0, 1.0) ** power


def resolution_factor(footprint: torch.Tensor, weight: float, visible: torch.Tensor) -> torch.Tensor:
    """Q_r = footprint^weight (not in the paper), ``footprint`` the photo's pixels per texel
    relative to the texel's best candidate (:func:`relative_footprint`).

    A photo with fewer pixels per texel than another is blurrier there (its own blur, in texels,
    is larger) and noisier (it averages fewer pixels), so it gets proportionally less weight; the
    best photo keeps Q_r = 1, so the terms that Q weighs keep their scale. ``weight`` 0 gives the
    paper's Q = Q_a Q_c. One function apart from :func:`quality` because a level takes two Q_r of
    the same Q_a Q_c (the blend's and the witnesses', difftex.method.levels).

    Args:
        footprint: (h, w) relative_footprint; weight: exponent of Q_r (``resolution_weight``).
        visible: (h, w) bool; elsewhere the footprint may not be finite.

    Returns:
        (h, w) Q_r, zero where the photo does not see the texel (one everywhere at weight 0).
    """
    if weight <= 0:
        return torch.ones_like(footprint)
    return torch.where(visible, footprint**weight, torch.zeros_like(footprint))


def relative_footprint(footprint: torch.Tensor, best: torch.Tensor | None, knee: float = 1.0) -> torch.Tensor:
    """A photo's pixels per texel over the most that any of the texel's candidates has, or over
    one pixel where none has more: the base of Q_r.

    Where no candidate has one pixel per texel, the footprint itself: every photo there is
    blurrier than the texel, by its own measure. (The earlier Q_r was min(1, footprint): it
    ranked every photo with one pixel per texel or more alike. On the four synthetic buildings
    at `fast`, the relative Q_r in the blend raised SSIM by 0.012-0.036 and lowered Error 95 %
    by 0.026-0.056: docs/optimizer.md.)

    Args:
        footprint: (h, w) the texel's size in the photo's pixels.
        best: (h, w) the largest footprint over the texel's candidates; None: min(1, footprint),
            the earlier Q_r (``resolution_reference: pixel``).
        knee: with ``best``, photos within this factor of it count as fully resolved:
            min(1, knee x footprint / best) (``resolution_knee``; 1: none). A drone photo four
            times coarser than a street photo still falls off, while photos of nearly the same
            resolution are not ranked by differences their blur does not show.

    Returns:
        (h, w) in [0, 1] where footprint <= max(best, 1).
    """
    if best is None:
        return footprint.clamp(max=1.0)
    rel = footprint / best.clamp_min(1.0)
    return (rel * knee).clamp(max=1.0) if knee > 1.0 else rel


def streamed_spread(s1: torch.Tensor, s2: torch.Tensor, count: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The mean colour and the mean squared distance to it of the photos summed into streaming
    statistics (a level's candidates in ``build_level``, or its level photos).

    Args:
        s1: (3, h, w) float64 sum of the photos' colours.
        s2: (h, w) float64 sum of their squared norms.
        count: (h, w) photos per texel.

    Returns:
        (3, h, w) float64 mean, and (h, w) float32 mean squared distance to it (0 where no photo).
    """
    c = count.clamp_min(1.0)
    mu = s1 / c
    return mu, (s2 / c - (mu * mu).sum(0)).clamp_min(0.0).float()


def level_photos_agree(s1: torch.Tensor, s2: torch.Tensor, count: torch.Tensor, noise: float, k: float) -> torch.Tensor:
    """Texels where two or more level photos agree: the RMS distance of their colours to their
    mean is at most ``k`` sigma_c. There they see a recessed window's pane, which photos from
    above see the sill over, and the tilt frontality may weigh the witnesses too
    (``frontality_tilt_witness_agree``); a street occluder far in front of the wall lands on
    different texels in each level photo, so they disagree where it stands.

    Args:
        s1: (3, h, w) float64 sum of the level photos' colours.
        s2: (h, w) float64 sum of their squared norms.
        count: (h, w) level photos per texel.
        noise: sigma_c of the level (:func:`level_noise`).
        k: agreement in units of sigma_c (> 0).

    Returns:
        (h, w) bool.
    """
    if not k > 0:
        raise ValueError(f"k must be > 0, got {k}")
    _, msd = streamed_spread(s1, s2, count)
    return (count >= 2) & (msd <= (k * noise) ** 2)


def level_noise(msd: torch.Tensor, count: torch.Tensor, floor: float) -> float:
    """sigma_c from the streaming statistics: the median over texels seen by two photos or more
    of the RMS distance of their colours to their mean, at least ``floor``.

    The fallback of :func:`robust_noise` where no texel has three candidates. An outlier (an
    occluder in one photo) inflates a texel's RMS distance, so where occluders touch most texels
    in some photo this median measures them, not the noise.
    """
    sel = count >= 2
    if not bool(sel.any()):
        return float(floor)
    return max(float(floor), float(msd[sel].median().sqrt()))


CHI3_MEDIAN = 1.5382  # median of a chi distribution with 3 degrees of freedom
NOISE_SAMPLES = 1 << 16  # texels a level's noise is estimated on (a median: a sample suffices)


def robust_noise(colours: torch.Tensor, visible: torch.Tensor, floor: float) -> float | None:
    """sigma_c: the level's photometric noise, robust to occluders and misregistration.

    Per texel with three candidates or more: the median over its candidates of their colour's
    distance to the per-channel median colour; sigma_c is the median of that over the texels,
    scaled to the RMS distance of Gaussian noise (sqrt(3) / CHI3_MEDIAN), at least ``floor``.
    A photo that disagrees at a texel (an occluder, relief parallax, a misregistered edge) moves
    neither median while the other candidates agree, so sigma_c stays the noise even when
    occluders reach most texels in some photo (the mean-based :func:`level_noise` then grows
    with them, and L_Render's unit and the settling threshold with it). torch.nanquantile, not
    nanmedian: nanmedian returns the lower of the two middle values of an even count, which is
    0 for the distances of two photos.

    Args:
        colours: (K, 3, h, w) the candidates' colours.
        visible: (K, h, w) bool, which candidates see each texel.
        floor: noise floor (OptimizeConfig.sigma_min).
    Returns:
        sigma_c, or None when no texel has three candidates.
    """
    sel = visible.sum(0) >= 3
    n = int(sel.sum())
    if n == 0:
        return None
    flat = sel.flatten().nonzero()[:, 0]
    flat = flat[:: max(1, n // NOISE_SAMPLES)]  # a regular subsample bounds memory and time
    c = colours.flatten(2)[:, :, flat].float()  # (K, 3, n)
    v = visible.flatten(1)[:, flat]
    c = torch.where(v[:, None], c, torch.full_like(c, float("nan")))
    med = torch.nanquantile(c, 0.5, dim=0)  # (3, n)
    d = ((c - med[None]) ** 2).sum(1).sqrt()  # (K, n), NaN where not visible
    s = torch.nanquantile(d, 0.5, dim=0)
    return max(float(floor), float(s.median()) * math.sqrt(3.0) / CHI3_MEDIAN)
