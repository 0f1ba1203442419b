"""The per-texel statistics of a level's candidate photos, streamed one photo at a time: their
colours' mean and spread (for Q_c), mean gradient (G), the most pixels per texel of any
candidate (Q_r's reference), the most level candidate's tilt frontality (the tilt's reference)
and, with ``frontality_tilt_witness_agree``, where two or more level photos agree.

A level holds at most its top-K candidates per texel, so the statistics over all candidates
are accumulated as each photo is mapped and then dropped (difftex.method.levels.build_level).
"""

from __future__ import annotations

import math

import torch

from difftex.method.config import OptimizeConfig
from difftex.method.quality import level_noise, level_photos_agree, streamed_spread, tilt_frontality
from difftex.sampling.photos import MappedPhoto
from difftex.sampling.texels import Region

# a photo is level (a street photo) within this tilt where frontality_tilt_min_elevation is not
# above 0 degrees and cannot say where photos from above begin
LEVEL_TILT_DEG = 20.0


def gradient_magnitude(col: torch.Tensor, vis: torch.Tensor) -> torch.Tensor:
    """Mean-over-channels colour gradient magnitude (h, w), zero across visibility borders.

    Args:
        col: (3, h, w) colours.
        vis: (h, w) bool, where the colours are defined.
    """
    gx = torch.zeros_like(col)
    gy = torch.zeros_like(col)
    okx = (vis[:, 1:] & vis[:, :-1])[None]
    oky = (vis[1:, :] & vis[:-1, :])[None]
    gx[:, :, 1:] = (col[:, :, 1:] - col[:, :, :-1]) * okx
    gy[:, 1:, :] = (col[:, 1:, :] - col[:, :-1, :]) * oky
    return (gx * gx + gy * gy).sqrt().mean(0)


_Sums = tuple[torch.Tensor, torch.Tensor, torch.Tensor]  # colour sum, squared-norm sum, count


def _zero_sums(shape: tuple[int, int], device) -> _Sums:
    h, w = shape
    return (torch.zeros(3, h, w, device=device, dtype=torch.float64),
            torch.zeros(h, w, device=device, dtype=torch.float64),
            torch.zeros(h, w, device=device))


def _add_sums(sums: _Sums, c: torch.Tensor, sq: torch.Tensor, weight: torch.Tensor, reg: Region) -> None:
    """Add colours ``c`` (3, rh, rw) float64 and their squared norms ``sq`` where ``weight``
    (rh, rw, 0 or 1) is 1, over ``reg`` of the level."""
    y0, y1, x0, x1 = reg
    sums[0][:, y0:y1, x0:x1] += c * weight
    sums[1][y0:y1, x0:x1] += sq * weight
    sums[2][y0:y1, x0:x1] += weight


class CandidateStats:
    """Sums over the candidates of one level, added photo by photo (``add``), then reduced
    (``finish``) to the fields the level's Q needs.

    Args:
        shape: the level's (h, w).
        device: the torch device of the sums.
        normal: (3,) the polygon's normal.
        tilt_axis: (3,) the wall's in-plane up when the tilt frontality is on, else None.
        cfg: the optimizer config (sigma_min, the tilt's elevation limit and witness agreement).

    After ``finish``: ``mu`` (3, h, w) and ``msd`` (h, w) the candidates' mean colour and mean
    squared distance to it, ``G`` (h, w) their mean gradient magnitude, ``fpbest`` (h, w) the most
    pixels per texel of any, ``tbest`` (h, w) the most level one's tilt frontality (None without
    the tilt), ``noise`` the level's sigma_c floor, ``level_agree`` (h, w) bool where the level
    photos agree (None unless the witness agreement is on).
    """

    def __init__(
        self, shape: tuple[int, int], device, normal: torch.Tensor, tilt_axis: torch.Tensor | None,
        cfg: OptimizeConfig,
    ) -> None:
        h, w = shape
        self.cfg = cfg
        self.normal = normal
        self.tilt_axis = tilt_axis
        # float64 sums: msd = s2 / n - |mu|^2 cancels where the candidates agree, and in float32 its
        # rounding (~1e-7) would swamp a small sigma_min^2 (the paper preset's 1e-6) in Q_c
        self.sums = _zero_sums(shape, device)
        self.gsum = torch.zeros(h, w, device=device)
        self.fpbest = torch.zeros(h, w, device=device)
        self.tbest = torch.zeros(h, w, device=device) if tilt_axis is not None else None
        # the level photos' (tilted less than the elevation limit) colour statistics: where two or
        # more agree, the tilt may weigh the witnesses too (frontality_tilt_witness_agree)
        self.agree_k = (
            cfg.frontality_tilt_witness_agree if self.tbest is not None and not cfg.frontality_tilt_witnesses else 0.0
        )
        self.level_cos = math.cos(math.radians(max(cfg.frontality_tilt_min_elevation, 0.0) or LEVEL_TILT_DEG))
        self.level_sums = _zero_sums(shape, device) if self.agree_k > 0 else None

    def add(self, mp: MappedPhoto, compared: torch.Tensor, reg: Region) -> None:
        """Add one mapped photo over its region ``reg`` of the level.

        Args:
            mp: the photo mapped into the region's texels.
            compared: (3, rh, rw) its colours as the level compares them (low-passed or not).
            reg: (y0, y1, x0, x1) the region.
        """
        y0, y1, x0, x1 = reg
        c = compared.double()
        sq = (c * c).sum(0)
        _add_sums(self.sums, c, sq, mp.visible.float(), reg)
        self.gsum[y0:y1, x0:x1] += gradient_magnitude(mp.colour, mp.visible) * mp.visible.float()
        self.fpbest[y0:y1, x0:x1] = torch.maximum(self.fpbest[y0:y1, x0:x1], torch.where(mp.visible, mp.footprint, 0.0))
        if self.tbest is None:
            return
        assert self.tilt_axis is not None  # tbest exists only with it
        tf = torch.where(mp.visible, tilt_frontality(mp.view, self.normal, self.tilt_axis), 0.0)
        self.tbest[y0:y1, x0:x1] = torch.maximum(self.tbest[y0:y1, x0:x1], tf)
        if self.level_sums is not None:
            _add_sums(self.level_sums, c, sq, (tf >= self.level_cos).float(), reg)

    def finish(self) -> None:
        """Reduce the sums to ``mu``, ``msd``, ``G``, ``noise`` and ``level_agree``."""
        mu64, self.msd = streamed_spread(*self.sums)  # msd: mean squared distance to the mean
        self.mu = mu64.float()
        count = self.sums[2]
        self.G = self.gsum / count.clamp_min(1.0)
        self.noise = level_noise(self.msd, count, self.cfg.sigma_min)
        self.level_agree = (
            level_photos_agree(*self.level_sums, self.noise, self.agree_k) if self.level_sums is not None else None
        )
