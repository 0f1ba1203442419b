"""Parameters of the method (the ``optimize:`` config section) and of how it runs (``compute:``).

``OptimizeConfig`` holds what changes the result; ``ComputeConfig`` holds what only changes
how fast it is computed (device, torch.compile), so that the workflow does not rerun texturing
when only those change.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Literal

from difftex.sampling import SUPERSAMPLE

LossMode = Literal["texel", "render"]
EliminationTest = Literal["loo", "paper"]
HistmatchReference = Literal["median", "best", "pooled"]
HistmatchModel = Literal["gain", "quantile"]
Device = Literal["auto", "cpu", "cuda"]
CompileMode = Literal["auto", "on", "off"]
RenderUnits = Literal["noise", "raw"]
AlignModel = Literal["translation", "affine"]
AlignGauge = Literal["median", "plane"]
AlignConsensus = Literal["texture", "median", "blend"]
ResolutionReference = Literal["best", "pixel"]
# the parameters: "softmax" (the project's): logits, W their softmax over the active slots;
# "normalised" (the paper's, Sec. 4.1): weights w in [0, 1], W = w normalised per texel
WeightParam = Literal["softmax", "normalised"]
# how much a rendered pixel counts in L_Render: "texels" (the project's): a photo's pixel sum put
# on the texel-sum scale; "pixels" (the paper's eq. 4): a sum over the photo's pixels
RenderScale = Literal["texels", "pixels"]
# L_Para's D (eq. 9): "fixed" (the project's): a constant refreshed every eliminate_every
# iterations; "live" (eq. 9 as written): a function of the current texture, differentiated
ParaEdges = Literal["fixed", "live"]


def _check_choice(name: str, value, choices: tuple) -> None:
    if value not in choices:
        raise ValueError(f"{name} must be one of {', '.join(map(str, choices))}, got {value!r}")


@dataclass(frozen=True)
class ReliefSettings:
    """How the sweep runs (the ``optimize.relief_*`` keys)."""

    lo: float  # lowest height (scene units, < 0: into the facade)
    hi: float  # highest height (> 0: out of it)
    long_side: int = 512  # texels of the sweep's frame, at most
    window: int = 15  # ZNCC window, texels of that frame (odd)
    max_photos: int = 16
    min_cos: float = 0.5  # photos seen within arccos(min_cos) of the normal
    margin: float = 0.15  # least cost gain over the plane for a height to be kept
    smooth: int = 9  # mode filter, texels (odd; 1: off)
    max_heights: int = 49  # most planes swept
    # heights beyond this share of the polygon's shorter side are not swept: a scene in other units
    # than metres (COLMAP's are arbitrary unless scaled), or a small polygon, gets a range in scale
    max_share: float = 0.2
    # per texel and height, the mean cost of this share of the photos that agree best (1: of all):
    # the photos that a reveal hides the texel from disagree at the true height (semiglobal.py)
    share: float = 1.0
    # "mode": each texel's cheapest height where it beats the plane by ``margin``, mode-filtered;
    # "semiglobal": the cost volume aggregated along 8 paths (semi-global matching) with the
    # penalties p1 (one height step) and p2 (a larger jump), the plane favoured by ``margin``
    regularise: Literal["mode", "semiglobal"] = "mode"
    # what the ZNCC compares: grey values, or differences along each photo's parallax direction
    # (difftex.method.relief.sweep_cost says why)
    structure: Literal["grey", "parallax"] = "grey"
    p1: float = 0.05
    p2: float = 0.5
    # "box": each step completed to its bounding box, "grow": grown first while the photos agree
    # (difftex.method.openings); accepted where the box agrees at the step's height by ``openings_tol``
    openings: Literal["none", "box", "grow"] = "none"
    openings_tol: float = 0.0
    # the sweep runs where its photos' median elevation seen from the polygon (degrees above the
    # horizontal) is at least this: -90 everywhere, > 0 only photos from above (relief.median_elevation)
    min_elevation: float = -90.0

    def __post_init__(self):
        if self.openings not in ("none", "box", "grow"):
            raise ValueError(f"relief openings none|box|grow, got {self.openings!r}")
        if not -90 <= self.min_elevation <= 90:
            raise ValueError(f"relief min_elevation in [-90, 90] degrees, got {self.min_elevation}")
        if not 0 < self.share <= 1 or not 0 <= self.p1 <= self.p2 or self.regularise not in ("mode", "semiglobal") \
                or self.structure not in ("grey", "parallax"):
            raise ValueError(f"relief share in (0, 1], 0 <= p1 <= p2, regularise mode|semiglobal; got {self.share}, "
                             f"{self.p1}, {self.p2}, {self.regularise!r}, structure {self.structure!r}")
        if not self.lo <= 0 <= self.hi or self.lo == self.hi:
            raise ValueError(f"relief range must hold 0 and not be empty, got [{self.lo}, {self.hi}]")
        if self.window < 3 or self.window % 2 == 0 or self.smooth < 1 or self.smooth % 2 == 0:
            raise ValueError("relief window must be odd and >= 3, smooth odd and >= 1")
        if self.max_photos < 2 or not 0 <= self.min_cos < 1 or self.margin < 0 or self.max_heights < 3:
            raise ValueError("relief max_photos >= 2, min_cos in [0, 1), margin >= 0, max_heights >= 3")
        if self.max_share <= 0:
            raise ValueError(f"relief max_share must be > 0, got {self.max_share}")


@dataclass(frozen=True)
class OptimizeConfig:
    """Parameters of the ``optimize:`` config section: the project's defaults. The published
    method's values are :data:`PUBLISHED` (``config/presets/paper.yaml``); :meth:`departures`
    lists the keys where a configuration differs from them."""

    # the schedule measured better than the paper's start and doubling (256, x2; with the caps
    # 300/150/80/40, which are the project's: the paper gives none) at every density tried, in
    # less time: docs/optimizer.md "The schedule"
    long_side_start: int = 64  # coarse-to-fine: first level's long side (paper: 256)
    level_step: float = 4.0  # coarse-to-fine: ratio of a level's long side to the previous one's (paper: 2)
    top_k: int = 8  # candidate slots kept per texel
    loss_mode: LossMode = "texel"  # "texel" (mapped photos in texel space) or "render" (rendered into photo pixels)
    render_scale: RenderScale = "texels"  # render loss: a photo's pixel sum on the texel scale, or per pixel (paper)
    weights: WeightParam = "softmax"  # logits and their softmax, or weights in [0, 1] normalised per texel (paper)
    # weight of the L1 term sum_k sum_o |w_k(t_o)| inside L_Render (eq. 4; paper: 1). It acts on
    # the un-normalised weights, so only with weights "normalised"; 0: off
    sparsity: float = 0.0
    alpha: float = 1.0  # L_Render
    beta: float = 2.0  # L_Persp
    omega: float = 10.0  # L_Para
    lambda_s: float = 0.5
    para_eps: float = 0.01  # Charbonnier smoothing of |.| in L_Para (0: exact L1, the paper's)
    para_edges: ParaEdges = "fixed"  # L_Para's D: constant between refreshes, or live and differentiated (paper)
    render_units: RenderUnits = "noise"
    ghost_margin: float = 1.0  # squared differences below this many sigma_c^2 cost little in the ghost term (0: all)
    ghost: float = 1.0
    lr: float = 0.1  # Adam step on the parameters: here the logits (paper: 0.005 on the weights)
    betas: tuple[float, float] = (0.9, 0.99)
    tau: float = 0.01  # activation threshold: on W (softmax) or on the weights w (normalised); paper: "very small"
    tau_w: float = 0.95  # drop a photo when this share of its texels has zero weight
    sigma_k: float = 3.0  # pixel elimination: standard deviations
    # exponent of Q_r in Q = Q_a Q_c Q_r, Q_r = a photo's pixels per texel over the most of the texel's
    # candidates (or over 1 where none has one): 0 gives the paper's Q = Q_a Q_c
    resolution_weight: float = 1.0
    # "best": Q_r relative to the texel's best candidate; "pixel": min(1, pixels per texel), the
    # earlier Q_r, which ranks every photo with a pixel per texel or more alike
    resolution_reference: ResolutionReference = "best"
    # with "best": photos within this factor of the texel's best candidate's pixels per texel count
    # as fully resolved (Q_r = min(1, knee x footprint / best)^resolution_weight); 1: no knee
    resolution_knee: float = 1.0
    # the relative Q_r also weighs the photos as witnesses of what a texel shows (L_Render and its
    # ghost term, the settling test): off, they count by Q_a Q_c min(1, px), so a close photo with
    # an occluder does not outvote the farther photos that see past it
    resolution_in_consensus: bool = False
    # exponent of the witnesses' Q_r, min(1, px)^this (None: resolution_weight). A steep blend
    # exponent would otherwise silence the far witnesses too (0.6 pixels per texel, to the 8th:
    # 0.017), and a close photo's occluder would no longer be outvoted
    witness_resolution_weight: float | None = None
    # exponent of Q_a in Q: cos^this of the angle between the normal and the direction to the
    # camera (1: the paper's Q_a). Steeper, frontal photos outrank oblique ones more: the relief a
    # proxy lacks (reveals, sills) shows most in oblique views
    frontality_weight: float = 1.0
    # exponent of the tilt frontality on walls (difftex.method.quality.tilt_frontality): the
    # cosine of a view's angle to the normal in the wall's vertical plane, to this power, times
    # Q_a. Photos from above see the tops of the relief a proxy lacks (sills, the lower reveals
    # of recessed windows, balcony slabs) on one side only, so a blend cannot average them away
    # as it does the side reveals that photos from the left and the right show; 0: off. The
    # default, 3 above 20 degrees, gained Error 95 %, SSIM and LPIPS on every survey building and
    # left Table 2's real scenes (street photos, below the limit) unchanged (docs/optimizer.md)
    frontality_tilt: float = 3.0
    # the tilt also weighs the photos as witnesses (L_Render, elimination, settling): the sills
    # go, but the level (street) photos then outvote the photos from above, their occluders too
    frontality_tilt_witnesses: bool = False
    # > 0: the tilt also weighs the witnesses at the texels where two or more level photos (tilted
    # less than frontality_tilt_min_elevation, or 20 degrees) agree within this many sigma_c: they
    # see the pane where the photos from above see the sill, while a street occluder, far in front
    # of the wall, lands on different texels in each and is left to the photos from above. The
    # default gained all three metrics on every survey building over the blend-only tilt
    # (docs/optimizer.md, "Tilt frontality"); it acts only where the tilt does
    frontality_tilt_witness_agree: float = 1.0
    # the tilt only where the median elevation of the photos in front of the polygon, seen from its
    # centre, is at least this (degrees; difftex.sampling.crops.median_elevation); -90: everywhere.
    # Street photos see the relief square on; only drone photos see sills on one side
    frontality_tilt_min_elevation: float = 20.0
    sigma_min: float = 0.02  # noise floor of colour standard deviations (Q_c and elimination)
    # "loo": leave-one-out mean/std with a noise floor, one slot per texel and pass; "paper": the
    # paper's test (Sec. 4.3), every selected pixel beyond sigma_k std of all selected ones
    elimination_test: EliminationTest = "loo"
    eliminate_every: int = 10  # iterations between pixel-elimination passes
    # caps, the last value repeats (the paper stops a level "after convergence" and gives no count)
    max_iters_per_level: tuple[int, ...] = (40, 20, 10)
    min_iters_per_level: int = 20
    conv_tol: float = 0.02  # converged when 99 % of the texels moved less than this share of their weight ...
    conv_window: int = 10  # ... over the last conv_window iterations
    # ... or (when > 0) when 99 % of the texels' blended colour moved less than this many sigma_c
    # over the window: weights that trade between agreeing photos change nothing (0: off)
    conv_colour: float = 0.0
    use_render: bool = True
    use_persp: bool = True
    use_para: bool = True
    data_elimination: bool = True
    # selection (difftex.method.selection): one photo per patch of the final level, by W x Q,
    # with a Potts cost on seams, cross-faded over select_feather texels
    select: bool = False
    select_patch: int = 4  # patch side, texels
    select_smoothness: float = 1.0  # Potts cost per texel of seam, in units of a texel's data cost
    select_feather: float = 1.0  # Gaussian sigma of the cross-fade at seams, texels
    # where: "disagree", the texels whose kept photos disagree (the settled ones keep the blend,
    # which averages the photos' noise away); "all", every texel (one photo per patch everywhere)
    select_scope: Literal["disagree", "all"] = "disagree"
    # > 0: the selection gives only the detail finer than a Gaussian of this sigma (texels); the
    # colours below it stay the blend's, which averages the photos' noise and exposure (0: the
    # selected colours whole)
    select_band: float = 0.0
    # detail from one photo per facade element (difftex.method.detail): the blend below a Gaussian
    # of detail_band texels, above it the sharpest photo that agrees with the blend, one photo per
    # region of patches labelled by graph cuts whose seams run where the photos agree. "mixed": on
    # the polygons whose photos' resolutions spread by mixed_spread or more (drone surveys with
    # street photos), where the blend is softer than its finest photos; "all": every polygon
    detail: Literal["off", "mixed", "all"] = "mixed"
    detail_band: float = 8.0  # sigma of the band, texels
    detail_patch: int = 8  # side of the labelling's patches, texels
    detail_smoothness: float = 2.0  # seam cost per texel of seam where the photos agree (units of a texel's data cost)
    detail_feather: float = 1.0  # Gaussian sigma of the seams' cross-fade, texels
    # a photo is a candidate within this many times the second-closest photo's distance to the blend (low band)
    detail_agree: float = 3.0
    # parallax-aware composition (difftex.method.parallax): where the kept photos disagree by more
    # than parallax_gate sigma_c, the slots seen from nearly the best slot's direction carry the
    # texel (within parallax_sigma, about radians, of it; 0: off)
    parallax_sigma: float = 0.0
    parallax_gate: float = 2.0
    # relief-compensated mapping (difftex.method.relief): a plane sweep of photo consistency along
    # the normal gives each texel a height, and the photos are mapped through that displaced surface
    relief: bool = False
    relief_range: tuple[float, float] = (-0.6, 0.6)  # heights swept, scene units (< 0: into the facade)
    relief_max_share: float = 0.2  # ... at most this share of the polygon's shorter side (scale-free)
    relief_long_side: int = 512  # texels of the sweep's frame, at most
    relief_window: int = 15  # ZNCC window of the sweep, texels of its frame (odd)
    relief_photos: int = 16  # most photos compared by the sweep, most frontal first
    relief_min_cos: float = 0.5  # ... among those seen within arccos of this of the normal
    relief_margin: float = 0.15  # least gain in mean 1 - ZNCC over the plane for a height to be kept
    relief_smooth: int = 9  # mode filter of the height field, texels of the sweep's frame (odd; 1: off)
    relief_share: float = 1.0  # per texel and height, the mean cost of this share of the best-agreeing photos
    relief_regularise: Literal["mode", "semiglobal"] = "mode"  # the field's regulariser (difftex.method.semiglobal)
    relief_structure: Literal["grey", "parallax"] = "grey"  # what the sweep's ZNCC compares (relief.sweep_cost)
    relief_p1: float = 0.05  # semiglobal: penalty of one height step between neighbouring texels (cost units)
    relief_p2: float = 0.5  # semiglobal: penalty of a larger jump
    relief_openings: Literal["none", "box", "grow"] = "none"  # steps completed to rectangles (method.openings)
    relief_openings_tol: float = 0.0  # ... where the box's cost gain over the plane is at most this
    relief_min_elevation: float = -90.0  # sweep only where the photos' median elevation is this high (degrees)
    coarse_to_fine: bool = True
    histogram_matching: bool = True
    # refine each photo's mapping (affine, pixels) against the consensus texture, where at least
    # align_min_photos photos are refined: drone surveys' poses are off by about a pixel, and
    # their blends lost the bricks and mullions to it (docs/optimizer.md, "Alignment refinement")
    align: bool = True
    align_model: AlignModel = "affine"  # correction per photo: translation (2 parameters) or affine (6)
    align_iterations: int = 3  # Gauss-Newton steps per level
    align_prior_px: float = 0.5  # prior standard deviation of a correction, pixels
    align_max_px: float = 8.0  # a correction moving the polygon's edge further than this is rejected
    align_max_long_side: int = 1024  # align at levels up to this long side
    # ... and from this long side (0: from the first level): on coarser levels a texel spans
    # several of the photos' pixels, so their pose errors are a fraction of a texel there
    align_min_long_side: int = 0
    # texels per photo and Gauss-Newton step (a strided subset above it): a 2- or 6-parameter fit
    # from 16 k texels is limited by the texture's blur and the pose error's non-affine part, not
    # by the number of points: 64 k gave corrections within 0.02 px of these on the analytic wall,
    # at four times the cost (alignment was 85-90 % of a `fast` polygon's time with 64 k)
    align_points: int = 16384
    # what the photos are aligned to after the first level: the previous level's texture,
    # upsampled (texture: a level blurrier than the photos), the per-texel median of the photos
    # at this level (median), or the previous level's blend of the photos mapped at this level
    # (blend); median and blend have this level's detail
    align_consensus: AlignConsensus = "texture"
    # what the corrections cannot tell apart and is taken out of them: the median correction
    # (median), or a common in-plane shift and a common depth along the normal per texel axis (plane:
    # relief pulls the fit to the layer with the most contrast; difftex.method.alignment)
    align_gauge: AlignGauge = "plane"
    align_robust: float = 1.0  # Cauchy scale of the fit's residuals, robust standard deviations
    # a level is aligned only with at least this many photos to refine: the plane gauge fits four
    # parameters over them, and with fewer photos alignment never measured better (Table 2's scenes)
    align_min_photos: int = 12
    # Gaussian sigma, texels, of the low-pass under which photos are compared (Q_c, L_Render,
    # elimination, settling): relief parallax of thin details is not disagreement (0: full detail)
    consistency_sigma: float = 0.0
    # ... or, when larger, the low-pass that brings the finest candidate to the median candidate's
    # misfit, each photo taken to blur and misregister by this many of its own pixels
    # (difftex.method.witnesses; 0: off)
    consistency_px: float = 0.0
    # Mixed-resolution captures (a drone survey with a few close street photos): where the finest
    # candidate has at least this many times the median candidate's pixels per texel
    # (difftex.method.witnesses.resolution_spread, per polygon; scale-free), the polygon is textured
    # with the mixed_* values in place of consistency_px, resolution_weight, resolution_knee and
    # witness_resolution_weight, so the close photos' detail carries the blend (0: never; 1: always).
    # It replaces those four keys there, whatever they are set to: a variant of them on a drone
    # survey wants mixed_spread: 0. With two candidates the median is their mean, so the spread
    # stays below 2 and the switch off
    mixed_spread: float = 3.0
    mixed_consistency_px: float = 1.0
    mixed_resolution_weight: float = 8.0
    mixed_resolution_knee: float = 1.5
    mixed_witness_resolution_weight: float = 1.0
    settle_sigma: float = 3.0  # texels whose candidates agree within this many sigma_c keep their Q blend (0: off)
    align_tol_px: float = 0.1  # stop aligning once no weighted photo's correction moved more than this, pixels
    histmatch_reference: HistmatchReference = "median"  # per-texel median of the candidates, the best photo, or pooled
    # transfer per photo and channel: one gain (gain) or a quantile map (quantile: the paper's
    # histogram matching, which turns noise on flat-coloured tiles into salt-and-pepper)
    histmatch_model: HistmatchModel = "gain"
    histmatch_channels: str = "sv"  # HSV channels matched; hue is circular and left alone by default
    exact_decode: bool = False  # decode every photo at full size (default: JPEG DCT scaling where levels allow)
    supersample: int = SUPERSAMPLE  # S x S photo samples per texel, each at 1/S of its footprint
    seed: int = 0

    def __post_init__(self):
        _check_choice("loss_mode", self.loss_mode, ("texel", "render"))
        _check_choice("render_scale", self.render_scale, ("texels", "pixels"))
        _check_choice("weights", self.weights, ("softmax", "normalised"))
        _check_choice("para_edges", self.para_edges, ("fixed", "live"))
        if self.sparsity < 0:
            raise ValueError(f"sparsity must be >= 0, got {self.sparsity}")
        if self.sparsity > 0 and self.weights != "normalised":
            # the L1 norm of weights that sum to one is one per texel: a constant
            raise ValueError("sparsity needs weights: normalised (softmax weights have an L1 norm of 1 per texel)")
        _check_choice("elimination_test", self.elimination_test, ("loo", "paper"))
        _check_choice("render_units", self.render_units, ("noise", "raw"))
        _check_choice("align_model", self.align_model, ("translation", "affine"))
        _check_choice("align_gauge", self.align_gauge, ("median", "plane"))
        _check_choice("align_consensus", self.align_consensus, ("texture", "median", "blend"))
        if not 0 <= self.align_min_long_side <= self.align_max_long_side:
            raise ValueError(
                f"align_min_long_side must be in [0, align_max_long_side = {self.align_max_long_side}], "
                f"got {self.align_min_long_side}"
            )
        if self.align_points < 64:
            raise ValueError(f"align_points must be >= 64, got {self.align_points}")
        if self.align_min_photos < 0:
            raise ValueError(f"align_min_photos must be >= 0, got {self.align_min_photos}")
        if not self.align_robust > 0:
            raise ValueError(f"align_robust must be > 0, got {self.align_robust}")
        _check_choice("resolution_reference", self.resolution_reference, ("best", "pixel"))
        if self.resolution_weight < 0:
            raise ValueError(f"resolution_weight must be >= 0, got {self.resolution_weight}")
        if not self.frontality_weight >= 0:
            raise ValueError(f"frontality_weight must be >= 0, got {self.frontality_weight}")
        if not self.frontality_tilt >= 0:
            raise ValueError(f"frontality_tilt must be >= 0, got {self.frontality_tilt}")
        if not self.frontality_tilt_witness_agree >= 0:
            raise ValueError(f"frontality_tilt_witness_agree must be >= 0, got {self.frontality_tilt_witness_agree}")
        if not -90 <= self.frontality_tilt_min_elevation <= 90:
            raise ValueError(f"frontality_tilt_min_elevation in [-90, 90], got {self.frontality_tilt_min_elevation}")
        if not self.resolution_knee >= 1.0:
            raise ValueError(f"resolution_knee must be >= 1, got {self.resolution_knee}")
        _check_choice("histmatch_reference", self.histmatch_reference, ("best", "median", "pooled"))
        _check_choice("histmatch_model", self.histmatch_model, ("gain", "quantile"))
        if not set(self.histmatch_channels) <= set("hsv") or not self.histmatch_channels:
            raise ValueError(f"histmatch_channels must be letters of 'hsv', got {self.histmatch_channels!r}")
        if not 1.0 < float(self.level_step) <= 16.0:
            raise ValueError(f"level_step must be in (1, 16], got {self.level_step}")
        if self.top_k < 1 or self.long_side_start < 1 or self.supersample < 1:
            raise ValueError("top_k, long_side_start and supersample must be >= 1")
        if not 0 <= self.tau < 1 or not 0 < self.tau_w <= 1:
            raise ValueError("tau must be in [0, 1) and tau_w in (0, 1]")
        if self.ghost < 0:
            raise ValueError(f"ghost must be >= 0, got {self.ghost}")
        if self.select_patch < 1 or self.select_smoothness < 0 or self.select_feather < 0:
            raise ValueError("select_patch must be >= 1, select_smoothness and select_feather >= 0")
        _check_choice("detail", self.detail, ("off", "mixed", "all"))
        # checked here, not by building DetailSettings: its module imports torch, which the
        # initialization stage does not load
        if self.detail_band <= 0 or self.detail_agree <= 0 or self.detail_patch < 1:
            raise ValueError("detail_band and detail_agree must be > 0, detail_patch >= 1")
        if self.detail_smoothness < 0 or self.detail_feather < 0:
            raise ValueError("detail_smoothness and detail_feather must be >= 0")
        if self.select_band < 0:
            raise ValueError(f"select_band must be >= 0, got {self.select_band}")
        if self.select_scope not in ("disagree", "all"):
            raise ValueError(f"select_scope must be 'disagree' or 'all', got {self.select_scope!r}")
        if self.parallax_sigma < 0 or self.parallax_gate < 0 or self.consistency_sigma < 0:
            raise ValueError("parallax_sigma, parallax_gate and consistency_sigma must be >= 0")
        if self.witness_resolution_weight is not None and not self.witness_resolution_weight >= 0:
            raise ValueError(f"witness_resolution_weight must be >= 0 or null, got {self.witness_resolution_weight}")
        if not (self.mixed_spread == 0 or self.mixed_spread >= 1.0):
            raise ValueError(f"mixed_spread must be 0 (never) or >= 1, got {self.mixed_spread}")
        mixed = (self.mixed_consistency_px, self.mixed_resolution_weight, self.mixed_witness_resolution_weight)
        if any(not isinstance(v, (int, float)) or isinstance(v, bool) for v in mixed):
            raise ValueError(
                "mixed_consistency_px, mixed_resolution_weight and mixed_witness_resolution_weight must be numbers, "
                f"got {mixed}"
            )
        if min(mixed) < 0:
            raise ValueError(
                "mixed_consistency_px, mixed_resolution_weight and mixed_witness_resolution_weight must be >= 0"
            )
        if not self.mixed_resolution_knee >= 1.0:
            raise ValueError(f"mixed_resolution_knee must be >= 1, got {self.mixed_resolution_knee}")
        if self.consistency_px < 0:
            raise ValueError(f"consistency_px must be >= 0, got {self.consistency_px}")
        if self.conv_window < 1 or self.conv_tol < 0 or self.conv_colour < 0:
            raise ValueError("conv_window must be >= 1, conv_tol and conv_colour >= 0")
        if self.lr <= 0 or len(tuple(self.betas)) != 2:
            raise ValueError("lr must be > 0 and betas a pair")
        caps_in = self.max_iters_per_level
        caps = tuple(int(c) for c in (caps_in if isinstance(caps_in, (list, tuple)) else [caps_in]))
        if not caps or min(caps) < 0:
            raise ValueError("max_iters_per_level must be a non-empty list of counts >= 0")
        object.__setattr__(self, "max_iters_per_level", caps)
        object.__setattr__(self, "relief_range", tuple(float(b) for b in self.relief_range))
        self.relief_settings()  # checks the relief keys
        object.__setattr__(self, "betas", tuple(float(b) for b in self.betas))

    @classmethod
    def from_dict(cls, data: dict | None, where: str = "optimize") -> OptimizeConfig:
        from difftex.config import from_dict

        return from_dict(cls, data, where=where)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @property
    def autograd(self) -> bool:
        """Whether L's gradient comes from autograd (difftex.method.objective.objective): the
        render loss, and L_Para's live edge weights, have no written-out gradient."""
        return self.loss_mode == "render" or self.para_edges == "live"

    def for_spread(self, spread: float) -> OptimizeConfig:
        """This configuration for a polygon whose candidates' resolutions spread by ``spread``
        (the finest's pixels per texel over the median's): with the mixed_* values where it
        reaches ``mixed_spread``, else unchanged."""
        if self.mixed_spread <= 0 or spread < self.mixed_spread:
            return self
        return dataclasses.replace(
            self,
            consistency_px=self.mixed_consistency_px,
            resolution_weight=self.mixed_resolution_weight,
            resolution_knee=self.mixed_resolution_knee,
            witness_resolution_weight=self.mixed_witness_resolution_weight,
            detail="all" if self.detail == "mixed" else self.detail,
        )

    def departures(self) -> list[str]:
        """The keys of :data:`PUBLISHED` where this configuration is not the published method."""
        return [k for k, v in PUBLISHED.items() if getattr(self, k) != v]

    def detail_settings(self):
        """The detail's settings (difftex.method.detail.DetailSettings)."""
        from difftex.method.detail import DetailSettings

        return DetailSettings(band=self.detail_band, patch=self.detail_patch, smoothness=self.detail_smoothness,
                              feather=self.detail_feather, agree=self.detail_agree)

    def relief_settings(self):
        """The relief sweep's settings (:class:`ReliefSettings`)."""
        lo, hi = self.relief_range
        return ReliefSettings(
            lo=lo, hi=hi, long_side=self.relief_long_side, window=self.relief_window, max_photos=self.relief_photos,
            min_cos=self.relief_min_cos, margin=self.relief_margin, smooth=self.relief_smooth,
            max_share=self.relief_max_share, share=self.relief_share, regularise=self.relief_regularise,
            p1=self.relief_p1, p2=self.relief_p2, structure=self.relief_structure,
            openings=self.relief_openings, openings_tol=self.relief_openings_tol,
            min_elevation=self.relief_min_elevation,
        )

    def cap(self, level: int) -> int:
        caps = self.max_iters_per_level
        return caps[min(level, len(caps) - 1)]


# The published method (DiffTex, ACM TOG 2025; sections and equations of its text): the values
# of the ``optimize:`` keys that the paper states, and the project's additions switched off.
# config/presets/paper.yaml sets them (tests/test_paper_method.py checks that it does); keys the
# paper leaves open (tau, top_k, the caps and the convergence test, sigma_min, the histogram
# matching's reference) are set there with a note, not listed here.
PUBLISHED: dict = {
    "weights": "normalised",  # Sec. 4.1: a normalised vector of weights w_k in [0, 1] per texel
    "sparsity": 1.0,  # eq. 4: + sum_o |W_k(t_o)|, no coefficient of its own
    "loss_mode": "render",  # Sec. 3, eq. 4: the textured proxy rendered into the photos (nvdiffrast)
    "render_scale": "pixels",  # eq. 4: a sum over the photos' pixels
    "render_units": "raw",  # eq. 4: ||a Q (R - I)||^2 in colour units
    "ghost": 0.0,  # eq. 4 has no further term
    "alpha": 1.0,  # eq. 3 and the text after it: alpha, beta, omega = 1, 2, 10
    "beta": 2.0,
    "omega": 10.0,
    "lambda_s": 0.5,  # eq. 8 and the text after eq. 9
    "para_eps": 0.0,  # eq. 7: |.|
    "para_edges": "live",  # eq. 9: D from the current texture
    "resolution_weight": 0.0,  # Sec. 4.2: Q = Q_a Q_c
    "lr": 0.005,  # Sec. 5, Implementation: Adam, alpha = 0.005, beta_1 = 0.9, beta_2 = 0.99, constant
    "betas": (0.9, 0.99),
    "long_side_start": 256,  # Sec. 4.3, Coarse-to-Fine Resolution: from 256, doubled up to the target
    "level_step": 2.0,
    "coarse_to_fine": True,
    "data_elimination": True,  # Sec. 4.3, Data Elimination
    "elimination_test": "paper",  # ... beyond three standard deviations of the texel's selected pixels
    "sigma_k": 3.0,
    "tau_w": 0.95,  # Sec. 4.3 i) and Sec. 5: a photo whose weights are zero on this share is excluded
    "histogram_matching": True,  # Sec. 4.3, Brightness Adjustment: histogram matching in HSV
    "histmatch_model": "quantile",
    "histmatch_channels": "hsv",
    "use_render": True,  # eq. 3: all three terms
    "use_persp": True,
    "use_para": True,
    # the project's additions, off
    "settle_sigma": 0.0,
    "conv_colour": 0.0,
    "align": False,
    "consistency_sigma": 0.0,
    "consistency_px": 0.0,
    "mixed_spread": 0.0,
    "parallax_sigma": 0.0,
    "select": False,
    "detail": "off",
    "relief": False,
    "frontality_tilt": 0.0,
    "supersample": 1,  # eq. 2: one lookup I_k(f_k(t_o)) per texel
}


@dataclass(frozen=True)
class ComputeConfig:
    """The ``compute:`` section: where and how the method runs; results do not depend on it
    beyond float tolerance (tests compare compiled with eager, CUDA with CPU)."""

    device: Device = "auto"  # auto (CUDA when torch sees it) | cpu | cuda
    compile: CompileMode = "auto"  # torch.compile the objective: auto (large levels on a CPU) | on | off
    compile_min_slots: int = 4_194_304  # auto: compile levels with at least this many K x H x W slot entries

    def __post_init__(self):
        _check_choice("device", self.device, ("auto", "cpu", "cuda"))
        _check_choice("compile", self.compile, ("auto", "on", "off"))
        if self.compile_min_slots < 0:
            raise ValueError("compile_min_slots must be >= 0")

    @classmethod
    def from_dict(cls, data: dict | None, where: str = "compute") -> ComputeConfig:
        from difftex.config import from_dict

        return from_dict(cls, data, where=where)
