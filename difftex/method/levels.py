"""One resolution level of the method: the candidates mapped into texel space, top-K slots,
the initial weights Q = Q_a Q_c (Sec. 4.2; times Q_r unless resolution_weight is 0), and the
upsampling of weights between levels.

Memory: every texel keeps only its ``top_k`` best candidate photos (slots), so the level's
tensors grow with texels x K, not texels x photos. A level maps each photo once when all its
mapped photos fit in ``MAP_CACHE_BYTES`` (always when the candidates fit in the slots); above
that the photos are mapped a second time for scoring instead of being held (``Level.maps``
counts the mappings).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from difftex.geometry.frames import UVFrame
from difftex.method import losses
from difftex.method.candidate_stats import CandidateStats
from difftex.method.config import OptimizeConfig
from difftex.method.detail import photo_field
from difftex.method.filters import masked_blur
from difftex.method.quality import (
    quality,
    relative_footprint,
    resolution_factor,
    robust_noise,
    tilt_factor,
    tilt_frontality,
    wall_tilt_axis,
)
from difftex.method.regions import Entry, photo_entries
from difftex.method.slots import EMPTY_SCORE, Slots
from difftex.method.witnesses import candidate_footprints, witness_sigma
from difftex.sampling.crops import PolygonInput, seen_from_above
from difftex.sampling.photos import MappedPhoto, PhotoSet
from difftex.sampling.texels import Region, resample_nearest

MAP_CACHE_BYTES = 1 << 30  # mapped photos held at once while a level is built


@dataclass
class Level:
    """The slot layout and fixed data of one resolution level.

    Shapes: K slots over an (h, w) texel grid.
    """

    frame: UVFrame
    mask: torch.Tensor  # (h, w) bool texel mask
    idx: torch.Tensor  # (K, h, w) long photo index per slot, -1 empty
    visible: torch.Tensor  # (K, h, w) bool slot valid (photo sees the texel)
    colours: torch.Tensor  # (K, 3, h, w) what the data terms compare (low-passed: OptimizeConfig.consistency_sigma)
    # (K, h, w) Q_a Q_c Q_r: how much each photo counts as a witness of the texel (L_Render, settling);
    # its Q_r is min(1, px) when Qb, the blend's, holds the relative one
    Q: torch.Tensor
    cost: torch.Tensor  # (K, h, w) |V^ - v~|^2
    G: torch.Tensor  # (h, w) mean gradient magnitude of the mapped photos
    z0: torch.Tensor  # (K, h, w) initial parameters of the weights (losses.init_weights)
    v_tilde: np.ndarray
    n_candidates: int  # photos that see at least one texel at this level
    pixel_sets: losses.PixelBatch | None = None  # render mode
    fixed_slots: bool = False  # slot j holds the same photo at every texel (all candidates fit in K)
    maps: int = 0  # photo mappings made to build the level
    noise: float = 1.0  # typical colour disagreement of the candidates (sigma_c): L_Render's unit
    # (K, 3, h, w) the slots' full-detail colours, composed into the texture, when ``colours`` are
    # low-passed; None: ``colours`` are they. ``detail_noise``: their sigma_c.
    detail: torch.Tensor | None = None
    detail_noise: float | None = None
    Qb: torch.Tensor | None = None  # (K, h, w) Q of the blend (initial and settled weights); None: Q
    compare_sigma: float = 0.0  # texels of the low-pass under which ``colours`` were compared
    # (K, h, w) how well each slot's photo resolves the texel (footprint x cos^2), kept for the
    # detail (difftex.method.detail); None without it
    resolve: torch.Tensor | None = None

    @property
    def blend_Q(self) -> torch.Tensor:
        """(K, h, w) the Q the blend starts from and settled texels keep (:attr:`Qb` or :attr:`Q`)."""
        return self.Q if self.Qb is None else self.Qb

    @property
    def sharp(self) -> torch.Tensor:
        """(K, 3, h, w) the colours the texture is composed of (full detail)."""
        return self.colours if self.detail is None else self.detail

    @property
    def sharp_noise(self) -> float:
        """sigma_c of :attr:`sharp`."""
        return self.noise if self.detail_noise is None else self.detail_noise

    @property
    def n_tex(self) -> float:
        return float(max(int(self.mask.sum()), 1))

    def nbytes(self) -> int:
        ts = [self.idx, self.visible, self.colours, self.Q, self.cost, self.G, self.z0]
        ts += [t for t in (self.detail, self.Qb) if t is not None]
        return int(sum(t.element_size() * t.numel() for t in ts))


def upsample_photo_weight(
    prev_level: Level, prev_W: torch.Tensor, n: int, frame: UVFrame, region: Region | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Bilinear upsampling of photo n's blend weight from the previous level (paper: W upsampled).

    Args:
        prev_level: the coarser level; prev_W: (K, h', w') its blend weights.
        n: photo index; frame: the finer level's frame; region: only that rectangle of it.

    Returns:
        (W (h, w), covered (h, w) bool); only coarse texels where photo n was a candidate
        contribute (mask-normalised bilinear); elsewhere the caller decides.
    """
    vals, has = photo_field(prev_W, prev_level.idx, None, n)
    src = prev_level.frame
    tx, ty = frame.centres()
    if region is not None:
        y0, y1, x0, x1 = region
        tx, ty = tx[y0:y1, x0:x1], ty[y0:y1, x0:x1]
    r = frame.texel_size / src.texel_size
    gx = (tx * r) / src.width * 2 - 1
    gy = (ty * r) / src.height * 2 - 1
    grid = torch.from_numpy(np.stack([gx, gy], -1).astype(np.float32)).to(vals.device)[None]
    stack = torch.stack([vals * has, has.float()])[None]
    up = F.grid_sample(stack, grid, mode="bilinear", padding_mode="border", align_corners=False)[0]
    cov = up[1] > 1e-3
    return up[0] / up[1].clamp_min(1e-3), cov


def upsample_field(field: torch.Tensor, src: UVFrame, frame: UVFrame) -> torch.Tensor:
    """(C, h, w) bilinear resampling of a (C, h', w') field of frame ``src`` at the texel centres of
    ``frame`` (the same rectangle at another resolution)."""
    tx, ty = frame.centres()
    r = frame.texel_size / src.texel_size
    grid = torch.from_numpy(
        np.stack([(tx * r) / src.width * 2 - 1, (ty * r) / src.height * 2 - 1], -1).astype(np.float32)
    )
    return F.grid_sample(
        field[None].float(), grid.to(field.device)[None], mode="bilinear", padding_mode="border", align_corners=False
    )[0]


def upsample_known(prev_level: Level, frame: UVFrame) -> torch.Tensor:
    """(h, w) bool: texels of ``frame`` whose nearest texel at the coarser level, or one of its
    neighbours, had a candidate."""
    known = (prev_level.visible.any(0) & prev_level.mask).float()
    known = F.max_pool2d(known[None, None], 3, stride=1, padding=1)[0, 0]
    src = prev_level.frame
    tx, ty = frame.centres()
    r = frame.texel_size / src.texel_size
    grid = torch.from_numpy(
        np.stack([(tx * r) / src.width * 2 - 1, (ty * r) / src.height * 2 - 1], -1).astype(np.float32)
    )
    up = F.grid_sample(
        known[None, None], grid.to(known.device)[None], mode="nearest", padding_mode="border", align_corners=False
    )
    return up[0, 0] > 0.5


def tilt_axis(inp: PolygonInput, cfg: OptimizeConfig) -> np.ndarray | None:
    """The axis the tilt frontality measures views' tilt about (the wall's in-plane up), or None
    where it is off: ``frontality_tilt`` 0, a roof (quality.wall_tilt_axis), or photos whose
    median elevation is below ``frontality_tilt_min_elevation`` (street photos see the relief
    square on; only photos from above see sills on one side).

    Returns:
        (3,) unit vector, or None.
    """
    if cfg.frontality_tilt <= 0 or not seen_from_above(inp, 0.0, cfg.frontality_tilt_min_elevation):
        return None
    return wall_tilt_axis(inp.frame.normal, inp.up_vector())


def _photo_q(
    mp: MappedPhoto, c: torch.Tensor, sl: tuple[slice, slice], stats: CandidateStats, cfg: OptimizeConfig,
    res_split: bool,
) -> tuple[torch.Tensor, torch.Tensor]:
    """One candidate's witness Q and blend Q over its region ``sl`` of the level (Sec. 4.2:
    Q = Q_a Q_c, times Q_r; the blend's with the tilt frontality).

    Args:
        mp: the photo mapped into the region.
        c: (3, rh, rw) its colours as compared.
        sl: the region's (rows, columns) slices.
        stats: the level's candidate statistics (finished).
        cfg: the optimizer config.
        res_split: whether the witnesses' Q_r is absolute while the blend's is relative.

    Returns:
        (q, qb), each (rh, rw).
    """
    qac = quality(mp.cos, c, stats.mu[:, sl[0], sl[1]], stats.msd[sl], mp.visible, cfg.sigma_min,
                  cfg.frontality_weight)
    # The tilt weighs the blend; as witnesses of what a texel shows (L_Render, elimination,
    # settling) the photos from above keep their votes unless frontality_tilt_witnesses: the
    # street photos' trees are outvoted by the drone photos that see past them, and so are
    # their views of a window's lower pane where the drone photos see the sill. Where the level
    # photos agree (frontality_tilt_witness_agree), the witnesses are tilted too.
    qa_blend = qac
    if stats.tbest is not None:
        assert stats.tilt_axis is not None  # tbest exists only with it
        tilt = tilt_frontality(mp.view, stats.normal, stats.tilt_axis)
        qa_blend = qac * tilt_factor(tilt, stats.tbest[sl], cfg.frontality_tilt)
        if cfg.frontality_tilt_witnesses:
            qac = qa_blend
        elif stats.level_agree is not None:
            qac = torch.where(stats.level_agree[sl], qa_blend, qac)
    best = stats.fpbest[sl] if cfg.resolution_reference == "best" else None
    rw = cfg.resolution_weight
    q_r = resolution_factor(relative_footprint(mp.footprint, best, cfg.resolution_knee), rw, mp.visible)
    qb = qa_blend * q_r
    rw_w = rw if cfg.witness_resolution_weight is None else cfg.witness_resolution_weight
    if res_split:
        return qac * resolution_factor(relative_footprint(mp.footprint, None), rw_w, mp.visible), qb
    return qac * q_r, qb


class _LevelPhotos:
    """A level's candidates as mapped into its texels (``get``) and as compared (``compared``:
    low-passed by ``sigma`` texels when it is above 0), held while ``keep_all`` (they fit in
    MAP_CACHE_BYTES), else mapped again when asked (``maps`` counts the mappings). A candidate is
    an entry, a photo and the rectangle of the level it is mapped over (difftex.method.regions).

    Args:
        photos: the polygon's decoded photos.
        frame: the level's frame.
        mask_np: (h, w) bool, the polygon's texels at this level.
        transfers: per photo brightness transfer (or None).
        mapped: photos already mapped over the whole level by the caller, or None.
        keep_all: hold every mapped photo.
        sigma: the compared colours' low-pass in texels (0: full detail).
    """

    def __init__(
        self, photos: PhotoSet, frame: UVFrame, mask_np: np.ndarray, transfers: list | None,
        mapped: dict[int, MappedPhoto | None] | None, keep_all: bool, sigma: float,
    ) -> None:
        self.photos, self.frame, self.mask_np, self.transfers = photos, frame, mask_np, transfers
        self.keep_all, self.sigma = keep_all, sigma
        h, w = frame.shape
        self.cache: dict[Entry, MappedPhoto | None] = (
            {(n, (0, h, 0, w)): mp for n, mp in mapped.items()} if mapped is not None else {}
        )
        self.low: dict[Entry, torch.Tensor] = {}  # low-passed colours of the entries held in ``cache``
        self.maps = 0

    def get(self, e: Entry) -> MappedPhoto | None:
        if e in self.cache:
            return self.cache[e]
        self.maps += 1
        n, reg = e
        transfer = self.transfers[n] if self.transfers is not None else None
        return self.photos.map(n, self.frame, self.mask_np, transfer, reg)

    def hold(self, e: Entry, mp: MappedPhoto | None) -> None:
        """Keep entry ``e``'s mapping for the second pass (None: it sees nothing there)."""
        if mp is None or self.keep_all:
            self.cache[e] = mp

    def compared(self, e: Entry, mp: MappedPhoto) -> torch.Tensor:
        if self.sigma <= 0:
            return mp.colour
        if e in self.low:
            return self.low[e]
        c = masked_blur(mp.colour, mp.visible, self.sigma)
        if self.keep_all:
            self.low[e] = c
        return c


def _compare_sigma(photos: PhotoSet, frame: UVFrame, order: list[int], cfg: OptimizeConfig) -> float:
    """The low-pass (texels) of the colours the level compares: ``consistency_sigma``, or more at
    the candidates' resolutions (``consistency_px``, difftex.method.witnesses). The render loss
    compares the texture with the photos' own pixels (the paper's L_Render, difftex.method.render):
    its level keeps comparing at full detail (0)."""
    if cfg.loss_mode != "texel":
        return 0.0
    sig = cfg.consistency_sigma
    if cfg.consistency_px > 0:
        sig = max(sig, witness_sigma(candidate_footprints(photos, frame, order), cfg.consistency_px))
    return sig


def _stream_candidates(
    lp: _LevelPhotos, entries: list[Entry], stats: CandidateStats, prev: tuple[Level, torch.Tensor] | None,
) -> tuple[list[Entry], torch.Tensor]:
    """The first pass: every candidate into ``stats`` (finished here). Returns the entries that
    see the level and the guidance direction v~ (the first level's, over all its candidates)."""
    vsum = []
    seen = []
    for e in entries:
        mp = lp.get(e)
        lp.hold(e, mp)
        if mp is None:
            continue
        seen.append(e)
        stats.add(mp, lp.compared(e, mp), e[1])
        vd = (mp.view * mp.visible.float()).sum((1, 2))
        vsum.append(vd / vd.norm().clamp_min(1e-12))
    stats.finish()
    if prev is not None:
        return seen, torch.from_numpy(prev[0].v_tilde).to(stats.normal.device)
    return seen, losses.guidance_direction(torch.stack(vsum), stats.normal) if vsum else -stats.normal


def _fill_slots(
    lp: _LevelPhotos, seen: list[Entry], stats: CandidateStats, v_tilde: torch.Tensor, cfg: OptimizeConfig,
    prev: tuple[Level, torch.Tensor] | None, prev_known: torch.Tensor | None, dropped: set[int], fixed: bool,
) -> Slots:
    """The second pass: each candidate's Q, persp cost and starting weight into the top-K slots
    (``fixed``: every candidate fits, slot j is entry seen[j] over its region)."""
    h, w = lp.frame.shape
    # Q weighs the photos as witnesses (L_Render, ghost, settling); Qb, with the relative Q_r, the
    # blend (initial and settled weights). With one Q for both, the close photos that saw the tree
    # in front of archive's wall00 outvoted the farther ones that saw past it, and it came back.
    res_split = not cfg.resolution_in_consensus and cfg.resolution_reference == "best"
    # the tilt weighs the blend alone unless frontality_tilt_witnesses: that too needs a Qb
    split = res_split or (stats.tbest is not None and not cfg.frontality_tilt_witnesses)
    slots = Slots(max(1, len(seen)) if fixed else cfg.top_k, (h, w), stats.normal.device,
                  detail=lp.sigma > 0, blend_q=split, resolve=cfg.detail == "all")
    for j, e in enumerate(seen):
        mp = lp.get(e)
        assert mp is not None
        n, reg = e
        sl = (slice(reg[0], reg[1]), slice(reg[2], reg[3]))
        c = lp.compared(e, mp)
        q, qb = _photo_q(mp, c, sl, stats, cfg, res_split)
        pc = losses.persp_cost(mp.view[None], v_tilde)[0]
        weight = qb  # as the paper (Sec. 4.2), the weights start at Q (here the blend's, with Q_r)
        if prev is not None:
            assert prev_known is not None  # set with prev
            w_up, cov = upsample_photo_weight(prev[0], prev[1], n, lp.frame, reg)
            # Where the coarser level had candidates but not this photo among its slots, the
            # photo was outranked there: it starts at zero, not at Q (which would bring back
            # the photos the coarser levels left out). Only texels the coarser level did not
            # see at all start from Q.
            weight = torch.where(cov, w_up, torch.where(prev_known[sl], torch.zeros_like(qb), qb))
        # how well the photo resolves the texel, for the detail: pixels per texel times cos^2 (the
        # pixels along the most foreshortened axis, footprint sqrt(cos), times cos^1.5 more: a
        # recess seen obliquely is displaced by depth x tan, so of two photos that resolve a window
        # alike the frontal one shows its mullions where they are)
        resolve = mp.footprint * mp.cos.clamp_min(0.0) ** 2 if cfg.detail == "all" else None
        values = slots.pack(mp.visible, c, q, pc, weight, detail=mp.colour, Qb=qb, resolve=resolve)
        if fixed:
            slots.put(j, n, reg, values)
            continue
        # Rank: upsampled weight (or Q where the coarse level had no data); the small Q term
        # breaks ties between photos that were both deactivated at the coarse level.
        score = weight + 1e-3 * q - (2.0 if n in dropped else 0.0)  # dropped photos only fill empty slots
        score = torch.where(mp.visible, score, torch.full_like(q, EMPTY_SCORE))
        slots.rank(n, reg, score, values, defer=lp.keep_all)
    slots.write_deferred()
    return slots


def build_level(
    photos: PhotoSet,
    frame: UVFrame,
    cfg: OptimizeConfig,
    transfers: list | None = None,
    prev: tuple[Level, torch.Tensor] | None = None,
    dropped: set[int] | None = None,
    mapped: dict[int, MappedPhoto | None] | None = None,
) -> Level:
    """Map the candidates into texel space, compute Q and the persp cost, keep the top-K per texel.

    Args:
        photos: the polygon's decoded photos.
        frame: this level's frame.
        transfers: per photo brightness transfer (or None) applied to the mapped colours.
        prev: (coarser level, its blend weights) to upsample the initial weights from.
        dropped: photos dropped at a coarser level (they only fill otherwise empty slots).
        mapped: this level's photos already mapped (with ``transfers``), e.g. by the caller
            that estimated the transfers on them.

    A streaming pass computes the candidates' statistics (difftex.method.candidate_stats: the
    colours for Q_c, the mean gradient G, the references of Q_r and the tilt) and the mean
    viewing direction (v~); a second pass scores and keeps the top K (difftex.method.slots).
    The mapped photos of the first pass are reused by the second when they fit in MAP_CACHE_BYTES.

    With ``cfg.consistency_sigma`` > 0, Q_c, the statistics and the slots' ``colours`` (which
    L_Render, elimination and settling compare) are the photos' colours low-passed by a Gaussian
    of that many texels (normalised over the photo's visible texels), and ``detail`` keeps the
    full-detail colours for the texture. Relief parallax displaces thin details (mullions, frames)
    by a texel or two between photos: compared at full detail, the one photo that shows a mullion
    where the texture needs it, the most frontal, disagrees with the others there and is
    eliminated or outweighed exactly on the mullion (archive wall00). An occluder, several texels
    across, still disagrees after the low-pass. Texel loss only: with ``loss_mode: render`` the
    photos' pixels are compared at full detail.
    """
    inp = photos.inp
    device = photos.device
    mask_np = resample_nearest(inp.texel_mask, inp.frame, frame)
    mask = torch.from_numpy(mask_np).to(device)
    prev_known = upsample_known(prev[0], frame) if prev is not None else None
    entries = photo_entries(photos, frame, mask_np, prev, prev_known, cfg.tau)
    order = sorted({n for n, _ in entries})
    per_texel = 4 * 12  # colour, view, cos, footprint, visible; Q, persp cost, weight until the slots are written
    area = sum((y1 - y0) * (x1 - x0) for _, (y0, y1, x0, x1) in entries)
    keep_all = mapped is not None or len(entries) <= cfg.top_k or area * per_texel <= MAP_CACHE_BYTES
    sig = _compare_sigma(photos, frame, order, cfg)
    lp = _LevelPhotos(photos, frame, mask_np, transfers, mapped, keep_all, sig)

    normal = torch.tensor(frame.normal, dtype=torch.float32, device=device)
    axis = tilt_axis(inp, cfg)
    axis_t = None if axis is None else torch.tensor(axis, dtype=torch.float32, device=device)
    stats = CandidateStats(frame.shape, device, normal, axis_t, cfg)
    seen, v_tilde = _stream_candidates(lp, entries, stats, prev)
    fixed = len(seen) <= cfg.top_k
    slots = _fill_slots(lp, seen, stats, v_tilde, cfg, prev, prev_known, dropped or set(), fixed)

    vis = slots.visible
    noise = robust_noise(slots.colours, vis & mask, cfg.sigma_min)
    if noise is None:
        noise = stats.noise
    detail_noise = None
    if slots.detail is not None:
        detail_noise = robust_noise(slots.detail, vis & mask, cfg.sigma_min) or noise
    return Level(
        frame=frame,
        mask=mask,
        idx=torch.where(vis, slots.idx, torch.full_like(slots.idx, -1)),
        visible=vis,
        colours=slots.colours,
        Q=slots.Q,
        cost=slots.cost,
        G=stats.G,
        z0=losses.init_weights(slots.w0 * vis, cfg.weights),
        Qb=slots.Qb,
        v_tilde=v_tilde.cpu().numpy(),
        n_candidates=len({n for n, _ in seen}),
        fixed_slots=fixed,
        maps=lp.maps,
        noise=noise,
        detail=slots.detail,
        detail_noise=detail_noise,
        compare_sigma=sig,
        resolve=slots.resolve,
    )
