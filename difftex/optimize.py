"""Per-polygon DiffTex optimization: candidate photos, Q = Q_a * Q_c, top-K slots, coarse-to-fine Adam.

For one polygon P_i the problem is: a target UV frame and texel mask, the candidate photos with
their texel visibility (and photo-space masks a_k^i for the render-space loss), and a loader of
photo pixels. Everything here takes plain arrays and dataclasses; files are read by the CLI.

Memory: photos are cropped to the polygon and kept as a box-filtered pyramid (float16); at each
level every texel keeps only its ``top_k`` best candidate photos (slots), so the optimized
tensors grow with texels x K, not texels x photos. Each photo is mapped into texel space at each
level from the pyramid level whose pixel size matches the texel footprint (trilinear), so a
256-texel level never touches full-resolution pixels.
"""

from __future__ import annotations

import dataclasses
import math
import time
import warnings
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import torch
import torch.nn.functional as F

from difftex import losses
from difftex.camera import Photo
from difftex.errors import DifftexError
from difftex.mapping import UVFrame, map_texels, pixel_to_texel, texel_to_pixel


# --------------------------------------------------------------------------------------------
# Configuration


@dataclass(frozen=True)
class OptimizeConfig:
    """Parameters of the ``optimize:`` config section (paper defaults where the paper gives one)."""

    long_side_start: int = 256  # coarse-to-fine: first level's long side (paper: 256)
    top_k: int = 8  # candidate slots kept per texel
    loss_mode: str = "texel"  # "texel" (mapped photos in texel space) or "render" (rendered into photo pixels)
    alpha: float = 1.0  # L_Render
    beta: float = 2.0  # L_Persp
    omega: float = 10.0  # L_Para
    lambda_s: float = 0.5
    para_eps: float = 0.01  # Charbonnier smoothing of |.| in L_Para (0: exact L1)
    sparsity: float = 1.0  # weight of the L1 term inside L_Render (paper: 1; see docs/optimizer.md)
    lr: float = 0.005
    betas: tuple[float, float] = (0.9, 0.99)
    tau: float = 0.01  # activation threshold on normalised weights
    tau_w: float = 0.95  # drop a photo when this share of its texels has zero weight
    sigma_k: float = 3.0  # pixel elimination: standard deviations
    sigma_min: float = 0.02  # noise floor of colour standard deviations (Q_c and elimination)
    elimination_test: str = "loo"  # "loo": leave-one-out mean/std; "paper": mean/std including the pixel
    eliminate_every: int = 10  # iterations between pixel-elimination passes
    max_iters_per_level: tuple[int, ...] = (300, 150, 80, 40)  # caps, last value repeats
    min_iters_per_level: int = 20
    conv_rel_tol: float = 1e-3  # converged when the loss fell by less than this share ...
    conv_window: int = 20  # ... over this many iterations
    device: str = "auto"  # auto | cpu | cuda
    use_render: bool = True
    use_persp: bool = True
    use_para: bool = True
    use_sparsity: bool = True
    data_elimination: bool = True
    coarse_to_fine: bool = True
    histogram_matching: bool = True
    histmatch_reference: str = "median"  # per-texel "median" of the candidates, the "best" photo, or the "pooled" histogram
    histmatch_channels: str = "sv"  # HSV channels matched; hue is circular and left alone by default
    compile: str = "auto"  # torch.compile the objective: auto (large levels only) | on | off
    compile_min_slots: int = 4_194_304  # auto: compile levels with at least this many K x H x W slot entries
    output_bits: int = 8  # texture.png bit depth (8 or 16)
    write_exr: bool = False  # also texture.exr (half float)
    seed: int = 0

    def __post_init__(self):
        def bad(msg):
            raise ValueError(msg)

        if self.loss_mode not in ("texel", "render"):
            bad(f"loss_mode must be 'texel' or 'render', got {self.loss_mode!r}")
        if self.device not in ("auto", "cpu", "cuda"):
            bad(f"device must be auto, cpu or cuda, got {self.device!r}")
        if self.elimination_test not in ("loo", "paper"):
            bad(f"elimination_test must be 'loo' or 'paper', got {self.elimination_test!r}")
        if self.histmatch_reference not in ("best", "median", "pooled"):
            bad(f"histmatch_reference must be 'best', 'median' or 'pooled', got {self.histmatch_reference!r}")
        if not set(self.histmatch_channels) <= set("hsv") or not self.histmatch_channels:
            bad(f"histmatch_channels must be letters of 'hsv', got {self.histmatch_channels!r}")
        if self.compile not in ("auto", "on", "off"):
            bad(f"compile must be auto, on or off, got {self.compile!r}")
        if self.output_bits not in (8, 16):
            bad(f"output_bits must be 8 or 16, got {self.output_bits}")
        if self.top_k < 1 or self.long_side_start < 1:
            bad("top_k and long_side_start must be >= 1")
        if not 0 <= self.tau < 1 or not 0 < self.tau_w <= 1:
            bad("tau must be in [0, 1) and tau_w in (0, 1]")
        if self.lr <= 0 or len(tuple(self.betas)) != 2:
            bad("lr must be > 0 and betas a pair")
        caps = tuple(int(c) for c in (self.max_iters_per_level if isinstance(self.max_iters_per_level, (list, tuple)) else [self.max_iters_per_level]))
        if not caps or min(caps) < 0:
            bad("max_iters_per_level must be a non-empty list of counts >= 0")
        object.__setattr__(self, "max_iters_per_level", caps)
        object.__setattr__(self, "betas", tuple(float(b) for b in self.betas))

    @classmethod
    def from_dict(cls, data: dict | None, where: str = "optimize") -> "OptimizeConfig":
        from difftex.config import from_dict

        return from_dict(cls, data, where=where)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    def cap(self, level: int) -> int:
        caps = self.max_iters_per_level
        return caps[min(level, len(caps) - 1)]


def pick_device(name: str) -> torch.device:
    if name == "cuda" and not torch.cuda.is_available():
        raise DifftexError("optimize: device 'cuda' requested but torch sees no CUDA device")
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


# --------------------------------------------------------------------------------------------
# Inputs


@dataclass(eq=False)
class PolygonInput:
    """What one polygon's optimization needs (built from a visibility file or by a test)."""

    polygon_id: str
    frame: UVFrame  # target resolution
    texel_mask: np.ndarray  # (H, W) bool
    photos: list[Photo]  # candidate photos
    texel_visible: np.ndarray  # (N, H, W) bool
    load_image: Callable[[Photo], np.ndarray]  # float32 RGB (h, w, 3) in [0, 1]
    a_bbox: np.ndarray | None = None  # (N, 4) x0, y0, x1, y1 of a_k^i (render mode)
    a_masks: list[np.ndarray] | None = None  # N crops of a_k^i
    transfers: list | None = None  # per photo HSV transfer (difftex.histmatch) or None

    def __post_init__(self):
        N = len(self.photos)
        if self.texel_visible.shape != (N, *self.frame.shape):
            raise DifftexError(
                f"polygon '{self.polygon_id}': visibility is {self.texel_visible.shape}, expected {(N, *self.frame.shape)}"
            )
        if self.texel_mask.shape != self.frame.shape:
            raise DifftexError(f"polygon '{self.polygon_id}': texel mask shape {self.texel_mask.shape} != frame {self.frame.shape}")


def polygon_input_from_visibility(vis, scene_photos: dict[str, Photo], load_image=None) -> PolygonInput:
    """PolygonInput from a difftex.visibility.PolygonVisibility and the scene's photos by name."""
    from difftex.io import read_image

    missing = [n for n in vis.photos if n not in scene_photos]
    if missing:
        raise DifftexError(f"polygon '{vis.polygon_id}': visibility names photo(s) not in the scene: {', '.join(missing[:3])}")
    photos = [scene_photos[n] for n in vis.photos]
    loader = load_image or (lambda ph: read_image(ph.image_path, expected_size=(ph.width, ph.height)))
    return PolygonInput(
        polygon_id=vis.polygon_id,
        frame=vis.frame,
        texel_mask=vis.texel_mask,
        photos=photos,
        texel_visible=vis.texel_visible,
        load_image=loader,
        a_bbox=vis.a_bbox,
        a_masks=vis.a_masks,
    )


def level_sides(target_long: int, start: int, coarse_to_fine: bool) -> list[int]:
    """Long sides of the levels: start, 2 start, ... then the target (paper: 256 -> 2048)."""
    if not coarse_to_fine or target_long <= start:
        return [target_long]
    sides = []
    s = start
    while s < target_long:
        sides.append(s)
        s *= 2
    sides.append(target_long)
    return sides


def level_frame(frame: UVFrame, long_side: int) -> UVFrame:
    return frame if long_side == max(frame.shape) else frame.resized(long_side)


def resample_nearest(arr: np.ndarray, src: UVFrame, dst: UVFrame) -> np.ndarray:
    """(..., H, W) array of ``src`` to ``dst`` texel centres (same rectangle), nearest texel."""
    if src.shape == dst.shape and src.texel_size == dst.texel_size:
        return arr
    tx, ty = dst.centres()
    r = dst.texel_size / src.texel_size
    ix = np.clip(np.floor(tx[0] * r).astype(int), 0, src.width - 1)
    iy = np.clip(np.floor(ty[:, 0] * r).astype(int), 0, src.height - 1)
    return arr[..., iy[:, None], ix[None, :]]


# --------------------------------------------------------------------------------------------
# Photo sampling


class PhotoSampler:
    """A photo cropped to the polygon, as a 2x box-filtered pyramid, sampled at pixel positions.

    Level L pixel (i, j) covers full-resolution pixels [x0 + j 2^L, x0 + (j+1) 2^L); with COLMAP
    pixel centres at +0.5 a full-resolution coordinate p maps to (p - x0) / 2^L at level L.
    """

    def __init__(self, image: np.ndarray, box: tuple[int, int, int, int], device: torch.device, min_side: int = 4):
        x0, y0, x1, y1 = box
        self.x0, self.y0 = int(x0), int(y0)
        crop = torch.from_numpy(np.ascontiguousarray(image[y0:y1, x0:x1], dtype=np.float32)).permute(2, 0, 1)
        self.device = device
        levels = [crop.to(device=device, dtype=torch.float16)]
        cur = crop.to(device)
        while min(cur.shape[1:]) >= 2 * min_side and len(levels) < 10:
            h, w = cur.shape[1] // 2 * 2, cur.shape[2] // 2 * 2
            cur = F.avg_pool2d(cur[None, :, :h, :w], 2)[0]
            levels.append(cur.to(torch.float16))
        self.levels = levels

    @property
    def n_levels(self) -> int:
        return len(self.levels)

    def level_image(self, L: int) -> torch.Tensor:
        return self.levels[L].float()

    def sample(self, pix: np.ndarray, footprint: np.ndarray) -> torch.Tensor:
        """Colours (3, h, w) at full-resolution pixels (h, w, 2), trilinear over pyramid levels.

        ``footprint`` (h, w) is the texel's size in full-resolution pixels; the pyramid level is
        log2 of it, so a texel averages about one level pixel (no aliasing, no extra blur).
        """
        h, w = pix.shape[:2]
        lam = np.log2(np.maximum(np.nan_to_num(footprint, nan=1.0), 1.0))
        lam = np.clip(lam, 0, self.n_levels - 1).astype(np.float32)
        out = torch.zeros(3, h, w, device=self.device)
        lam_t = torch.from_numpy(lam).to(self.device)
        p = np.nan_to_num(pix, nan=-1e6).astype(np.float64)
        for L in range(int(np.floor(lam.min())), min(int(np.ceil(lam.max())), self.n_levels - 1) + 1):
            wL = (1.0 - (lam_t - L).abs()).clamp_min(0.0)
            if not bool((wL > 0).any()):
                continue
            img = self.level_image(L)
            s = 2.0**L
            gx = ((p[..., 0] - self.x0) / s) / img.shape[2] * 2 - 1
            gy = ((p[..., 1] - self.y0) / s) / img.shape[1] * 2 - 1
            grid = torch.from_numpy(np.stack([gx, gy], -1).astype(np.float32)).to(self.device)[None]
            # border padding: pixels of a texel near the crop edge still get the nearest colour
            smp = F.grid_sample(img[None], grid, mode="bilinear", padding_mode="border", align_corners=False)[0]
            out += wL[None] * smp
        return out


def texel_footprint(frame: UVFrame, photo: Photo, pix: np.ndarray) -> np.ndarray:
    """Texel size in pixels, sqrt(|det J|) of f_k^i by forward differences (h, w)."""
    tx, ty = frame.centres()
    px, _ = texel_to_pixel(frame, photo, tx + 1.0, ty)
    py, _ = texel_to_pixel(frame, photo, tx, ty + 1.0)
    dx, dy = px - pix, py - pix
    with np.errstate(invalid="ignore"):
        area = np.abs(dx[..., 0] * dy[..., 1] - dx[..., 1] * dy[..., 0])
    return np.sqrt(area)


def crop_box(photo: Photo, pix_valid: np.ndarray, a_box=None, pad: int = 16) -> tuple[int, int, int, int] | None:
    """Pixel box holding the polygon's visible texels (and a_k^i), padded, inside the image."""
    boxes = []
    if len(pix_valid):
        boxes.append((pix_valid[:, 0].min(), pix_valid[:, 1].min(), pix_valid[:, 0].max(), pix_valid[:, 1].max()))
    if a_box is not None and a_box[2] > a_box[0] and a_box[3] > a_box[1]:
        boxes.append(tuple(float(v) for v in a_box))
    if not boxes:
        return None
    b = np.array(boxes)
    x0 = max(0, int(math.floor(b[:, 0].min())) - pad)
    y0 = max(0, int(math.floor(b[:, 1].min())) - pad)
    x1 = min(photo.width, int(math.ceil(b[:, 2].max())) + pad)
    y1 = min(photo.height, int(math.ceil(b[:, 3].max())) + pad)
    if x1 <= x0 or y1 <= y0:
        return None
    return x0, y0, x1, y1


def build_samplers(inp: PolygonInput, device: torch.device, progress=None) -> dict[int, PhotoSampler]:
    """One sampler per candidate photo that sees any texel (images are read once each)."""
    samplers = {}
    for n, ph in enumerate(inp.photos):
        vis = inp.texel_visible[n] & inp.texel_mask
        if not vis.any():
            continue
        ty, tx = np.nonzero(vis)
        pix, _ = texel_to_pixel(inp.frame, ph, tx + 0.5, ty + 0.5)
        pix = pix[np.isfinite(pix).all(-1)]
        a_box = inp.a_bbox[n] if inp.a_bbox is not None and len(inp.a_bbox) > n else None
        box = crop_box(ph, pix, a_box)
        if box is None:
            continue
        img = inp.load_image(ph)
        if img.shape[:2] != (ph.height, ph.width):
            raise DifftexError(f"{ph.image_path}: image is {img.shape[1]}x{img.shape[0]}, camera says {ph.width}x{ph.height}")
        samplers[n] = PhotoSampler(img, box, device)
        del img
        if progress is not None:
            progress()
    return samplers


# --------------------------------------------------------------------------------------------
# One level's data


@dataclass
class MappedPhoto:
    """Photo n mapped into texel space at one level."""

    colour: torch.Tensor  # (3, h, w), brightness-adjusted when a transfer is given
    visible: torch.Tensor  # (h, w) bool
    view: torch.Tensor  # (3, h, w) unit camera-to-texel direction (V^_k)
    cos: torch.Tensor  # (h, w) frontality (Q_a)


def map_photo(inp: PolygonInput, n: int, frame: UVFrame, sampler: PhotoSampler, mask: np.ndarray, device) -> MappedPhoto | None:
    ph = inp.photos[n]
    m = map_texels(frame, ph)
    vis = resample_nearest(inp.texel_visible[n], inp.frame, frame) & m.valid & mask
    if not vis.any():
        return None
    fp = texel_footprint(frame, ph, m.pix)
    col = sampler.sample(m.pix, fp)
    if inp.transfers is not None and inp.transfers[n] is not None:
        from difftex.histmatch import apply_transfer_torch

        col = apply_transfer_torch(col, inp.transfers[n])
    vis_t = torch.from_numpy(vis).to(device)
    col = col * vis_t[None]
    view = torch.from_numpy(-m.view_dir.transpose(2, 0, 1).astype(np.float32)).to(device)
    cos = torch.from_numpy(np.clip(np.nan_to_num(m.cos_angle), 0.0, 1.0).astype(np.float32)).to(device)
    return MappedPhoto(colour=col, visible=vis_t, view=view, cos=cos)


def gradient_magnitude(col: torch.Tensor, vis: torch.Tensor) -> torch.Tensor:
    """Mean-over-channels colour gradient magnitude (h, w), zero across visibility borders."""
    gx = torch.zeros_like(col)
    gy = torch.zeros_like(col)
    okx = (vis[:, 1:] & vis[:, :-1])[None]
    oky = (vis[1:, :] & vis[:-1, :])[None]
    gx[:, :, 1:] = (col[:, :, 1:] - col[:, :, :-1]) * okx
    gy[:, 1:, :] = (col[:, 1:, :] - col[:, :-1, :]) * oky
    return (gx * gx + gy * gy).sqrt().mean(0)


@dataclass
class Level:
    """The slot layout and fixed data of one resolution level."""

    frame: UVFrame
    mask: torch.Tensor  # (h, w) bool texel mask
    idx: torch.Tensor  # (K, h, w) long photo index per slot, -1 empty
    visible: torch.Tensor  # (K, h, w) bool slot valid (photo sees the texel)
    colours: torch.Tensor  # (K, 3, h, w)
    Q: torch.Tensor  # (K, h, w) Q_a * Q_c
    cost: torch.Tensor  # (K, h, w) |V^ - v~|^2
    G: torch.Tensor  # (h, w) mean gradient magnitude of the mapped photos
    theta0: torch.Tensor  # (K, h, w) initial raw weights
    v_tilde: np.ndarray
    n_candidates: int  # photos that see at least one texel at this level
    pixel_sets: "losses.PixelBatch | None" = None  # render mode
    fixed_slots: bool = False  # slot j holds the same photo at every texel (all candidates fit in K)

    @property
    def n_tex(self) -> float:
        return float(max(int(self.mask.sum()), 1))

    def nbytes(self) -> int:
        ts = [self.idx, self.visible, self.colours, self.Q, self.cost, self.G, self.theta0]
        return int(sum(t.element_size() * t.numel() for t in ts))


def _scatter_photo_field(idx: torch.Tensor, values: torch.Tensor, n: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Photo n's dense (h, w) field from the slot layout, and where photo n has a slot."""
    sel = idx == n
    return (values * sel).sum(0), sel.any(0)


def upsample_photo_theta(prev: "LevelState", n: int, frame: UVFrame) -> tuple[torch.Tensor, torch.Tensor]:
    """Bilinear upsampling of photo n's active raw weight from the previous level (paper: W upsampled).

    Returns (theta (h, w), covered (h, w) bool); only coarse texels where photo n was a
    candidate contribute (mask-normalised bilinear), elsewhere the caller falls back to Q.
    """
    lv = prev.level
    vals, has = _scatter_photo_field(lv.idx, (prev.theta.detach() * prev.active), n)
    src = lv.frame
    tx, ty = frame.centres()
    r = frame.texel_size / src.texel_size
    gx = (tx * r) / src.width * 2 - 1
    gy = (ty * r) / src.height * 2 - 1
    grid = torch.from_numpy(np.stack([gx, gy], -1).astype(np.float32)).to(vals.device)[None]
    stack = torch.stack([vals * has, has.float()])[None]
    up = F.grid_sample(stack, grid, mode="bilinear", padding_mode="border", align_corners=False)[0]
    cov = up[1] > 1e-3
    return up[0] / up[1].clamp_min(1e-3), cov


def build_level(inp: PolygonInput, frame: UVFrame, samplers: dict[int, PhotoSampler], cfg: OptimizeConfig,
                device, prev: "LevelState | None" = None, dropped: set[int] | None = None) -> Level:
    """Map the candidates into texel space, compute Q and the persp cost, keep the top-K per texel.

    Two streaming passes over the photos (statistics, then scoring) keep memory at K slots;
    pass-1 results are cached when all candidates fit in the slots anyway.
    """
    mask_np = resample_nearest(inp.texel_mask, inp.frame, frame)
    mask = torch.from_numpy(mask_np).to(device)
    h, w = frame.shape
    K = cfg.top_k
    dropped = dropped or set()
    photos = sorted(samplers)
    cache: dict[int, MappedPhoto | None] = {}
    keep_all = len(photos) <= K
    s1 = torch.zeros(3, h, w, device=device)
    s2 = torch.zeros(h, w, device=device)
    cnt = torch.zeros(h, w, device=device)
    gsum = torch.zeros(h, w, device=device)
    vsum = []
    for n in photos:
        mp = map_photo(inp, n, frame, samplers[n], mask_np, device)
        if mp is None:
            cache[n] = None
            continue
        v = mp.visible.float()
        s1 += mp.colour * v
        s2 += (mp.colour * mp.colour).sum(0) * v
        cnt += v
        gsum += gradient_magnitude(mp.colour, mp.visible) * v
        vd = (mp.view * v).sum((1, 2))
        vsum.append(vd / vd.norm().clamp_min(1e-12))
        if keep_all:
            cache[n] = mp
        else:
            cache[n] = "seen"  # type: ignore[assignment]
    seen = [n for n in photos if cache.get(n) is not None]
    c = cnt.clamp_min(1.0)
    mu = s1 / c
    msd = (s2 / c - (mu * mu).sum(0)).clamp_min(0.0)  # mean squared distance to the mean
    G = gsum / c
    normal = torch.tensor(frame.normal, dtype=torch.float32, device=device)
    v_tilde = losses.guidance_direction(torch.stack(vsum), normal) if vsum else -normal

    fixed = keep_all  # every candidate fits: slot j is photo seen[j] at every texel
    if fixed:
        K = max(1, len(seen))
    best_score = torch.full((K, h, w), -10.0, device=device)
    idx = torch.full((K, h, w), -1, dtype=torch.long, device=device)
    vis = torch.zeros((K, h, w), dtype=torch.bool, device=device)
    cols = torch.zeros((K, 3, h, w), device=device)
    Q = torch.zeros((K, h, w), device=device)
    cost = torch.zeros((K, h, w), device=device)
    th0 = torch.zeros((K, h, w), device=device)
    for j, n in enumerate(seen):
        mp = cache[n] if keep_all else map_photo(inp, n, frame, samplers[n], mask_np, device)
        if mp is None:
            continue
        d2 = ((mp.colour - mu) ** 2).sum(0)
        q = mp.cos * torch.exp(-0.5 * d2 / (msd + cfg.sigma_min**2))
        q = torch.where(mp.visible, q, torch.zeros_like(q))
        pc = losses.persp_cost(mp.view[None], v_tilde)[0]
        theta = q
        if prev is not None:
            t_up, cov = upsample_photo_theta(prev, n, frame)
            theta = torch.where(cov, t_up, q)
        if fixed:
            idx[j] = n
            vis[j], cols[j], Q[j], cost[j], th0[j] = mp.visible, mp.colour, q, pc, theta
            continue
        # Rank: upsampled weight (or Q where the coarse level had no data); the small Q term
        # breaks ties between photos that were both deactivated at the coarse level.
        score = theta + 1e-3 * q - (2.0 if n in dropped else 0.0)  # dropped photos only fill empty slots
        score = torch.where(mp.visible, score, torch.full_like(q, -10.0))
        all_score = torch.cat([best_score, score[None]])
        top = torch.topk(all_score, K, dim=0)
        sel = top.indices

        def pick(old, new):
            allv = torch.cat([old, new[None]])
            if allv.dim() == 4:
                return torch.gather(allv, 0, sel[:, None].expand(-1, allv.shape[1], -1, -1))
            return torch.gather(allv, 0, sel)

        best_score = top.values
        idx = pick(idx, torch.full((h, w), n, dtype=torch.long, device=device))
        vis = pick(vis, mp.visible)
        cols = pick(cols, mp.colour)
        Q = pick(Q, q)
        cost = pick(cost, pc)
        th0 = pick(th0, theta)
        del mp
    idx = torch.where(vis, idx, torch.full_like(idx, -1))
    th0 = th0.clamp(0.0, 1.0) * vis
    th0 = gauge(th0, vis)
    return Level(frame=frame, mask=mask, idx=idx, visible=vis, colours=cols, Q=Q, cost=cost, G=G, theta0=th0,
                 v_tilde=v_tilde.cpu().numpy(), n_candidates=len(seen), fixed_slots=fixed)


def gauge(theta: torch.Tensor, active: torch.Tensor) -> torch.Tensor:
    """Rescale each texel's raw weights so the largest active one is 1.

    W is invariant to this scale; fixing it stops the L1 term from shrinking all weights of a
    texel together (which would end in the uniform blend) and makes it act on the ratios.
    """
    mx = (theta * active).amax(0, keepdim=True)
    return torch.where(mx > 0, theta / mx.clamp_min(1e-12), theta).clamp(0.0, 1.0)


# --------------------------------------------------------------------------------------------
# Render-space data


def build_pixel_sets(inp: PolygonInput, lv: Level, samplers: dict[int, PhotoSampler], device) -> "losses.PixelBatch":
    """Per photo: its a_k^i pixels at the pyramid level matching the texel size, their texel coords.

    The rasterisation (pixel -> texel coordinate) is computed once per photo and level; the
    rendering itself is then a differentiable bilinear lookup of U (losses.render_view).
    """
    if inp.a_bbox is None or inp.a_masks is None:
        raise DifftexError(f"polygon '{inp.polygon_id}': loss_mode 'render' needs the photo-space masks a_k^i (visibility file)")
    frame = lv.frame
    h, w = frame.shape
    K = lv.idx.shape[0]
    idx_flat = lv.idx.reshape(K, -1)
    mask_flat = lv.mask.reshape(-1)
    sets = []
    for n, smp in samplers.items():
        x0, y0, x1, y1 = (int(v) for v in inp.a_bbox[n])
        a = inp.a_masks[n]
        n_tex = int((lv.idx == n).any(0).sum())
        if a.size == 0 or not a.any() or n_tex == 0:
            continue
        ratio = math.sqrt(a.sum() / n_tex)
        L = int(np.clip(math.floor(math.log2(max(ratio, 1.0))), 0, smp.n_levels - 1))
        s = 2**L
        img = smp.level_image(L)
        hh, ww = img.shape[1:]
        # a_k^i in the sampler crop's frame, then box-averaged to level L (majority vote)
        full = torch.zeros(hh * s, ww * s, dtype=torch.float32)
        cx0, cy0 = smp.x0, smp.y0
        ax0, ay0 = max(x0, cx0), max(y0, cy0)
        ax1, ay1 = min(x1, cx0 + ww * s), min(y1, cy0 + hh * s)
        if ax1 <= ax0 or ay1 <= ay0:
            continue
        full[ay0 - cy0 : ay1 - cy0, ax0 - cx0 : ax1 - cx0] = torch.from_numpy(a[ay0 - y0 : ay1 - y0, ax0 - x0 : ax1 - x0].astype(np.float32))
        m = (F.avg_pool2d(full[None, None], s)[0, 0] > 0.5) if s > 1 else full > 0.5
        rows, cols_ = torch.nonzero(m, as_tuple=True)
        if len(rows) == 0:
            continue
        px = cx0 + (cols_.numpy() + 0.5) * s
        py = cy0 + (rows.numpy() + 0.5) * s
        t = pixel_to_texel(frame, inp.photos[n], np.stack([px, py], -1))
        ok = np.isfinite(t).all(-1) & (t[:, 0] >= 0) & (t[:, 0] < w) & (t[:, 1] >= 0) & (t[:, 1] < h)
        if not ok.any():
            continue
        t = t[ok]
        rows_d, cols_d = rows[ok].to(device), cols_[ok].to(device)
        colour = img[:, rows_d, cols_d].T.contiguous()
        if inp.transfers is not None and inp.transfers[n] is not None:
            from difftex.histmatch import apply_transfer_torch

            colour = apply_transfer_torch(colour.T[:, :, None], inp.transfers[n])[:, :, 0].T.contiguous()
        tex = torch.from_numpy(np.floor(t[:, 1]).astype(np.int64) * w + np.floor(t[:, 0]).astype(np.int64)).to(device)
        inside = mask_flat[tex]
        tex, colour, t = tex[inside], colour[inside], t[inside.cpu().numpy()]
        if len(tex) == 0:
            continue
        slots = idx_flat[:, tex] == n
        slot = torch.where(slots.any(0), slots.float().argmax(0), torch.full_like(tex, -1))
        g = np.stack([t[:, 0] / w * 2 - 1, t[:, 1] / h * 2 - 1], -1).astype(np.float32)
        grid = torch.from_numpy(g).to(device)[None, :, None, :]
        sets.append(losses.PixelSet(grid=grid, colour=colour, texel=tex, slot=slot, scale=n_tex / len(tex)))
    return losses.batch_pixel_sets(sets, render_support(lv), device)


def render_support(lv: Level) -> torch.Tensor:
    """Texels that carry colour in the render-mode lookup: inside the polygon and seen by a photo.

    The activation update always keeps a texel's strongest candidate, so this does not change
    during a level.
    """
    return lv.mask & lv.visible.any(0)


# --------------------------------------------------------------------------------------------
# Optimization state and loop


@dataclass
class LevelState:
    level: Level
    theta: torch.Tensor
    active: torch.Tensor  # (K, h, w) bool a^_k
    eliminated: torch.Tensor  # (K, h, w) bool
    history: dict = field(default_factory=dict)
    it: int = 0
    D: dict | None = None  # L_Para edge weights, refreshed every eliminate_every iterations


def argmax0(x: torch.Tensor) -> torch.Tensor:
    """Index of the largest entry along dim 0, as (1, ...) (first one on ties).

    torch's argmax over the leading dimension of a (K, H, W) tensor is a strided reduction that
    ran ~100x slower on CPU than this loop over the few slots.
    """
    best = x[0].clone()
    idx = torch.zeros(x.shape[1:], dtype=torch.long, device=x.device)
    for j in range(1, x.shape[0]):
        better = x[j] > best
        best = torch.where(better, x[j], best)
        idx = torch.where(better, torch.full_like(idx, j), idx)
    return idx[None]


def base_mask(lv: Level, eliminated: torch.Tensor, dropped_slots: torch.Tensor) -> torch.Tensor:
    return lv.visible & ~eliminated & ~dropped_slots


def update_activation(theta, base, tau: float) -> torch.Tensor:
    """a = base & (W > tau), W normalised over the base candidates; the best one always stays.

    Keeping each texel's strongest candidate avoids holes when every weight is below tau.
    """
    W = losses.blend_weights(theta, base)
    act = base & (W > tau)
    best = argmax0(torch.where(base, W, torch.full_like(W, -1.0)))
    keep = torch.zeros_like(act).scatter_(0, best, True) & base
    return act | keep


def eliminate_pixels(lv: Level, active: torch.Tensor, W: torch.Tensor, cfg: OptimizeConfig) -> torch.Tensor:
    """Slots whose colour lies beyond sigma_k standard deviations of the texel's selected colours.

    "paper": mean/std of all selected colours (a pixel can then be at most sqrt(n-1) std away,
    so this needs n >= 11 to fire); "loo": mean/std of the *other* selected colours, with a noise
    floor sigma_min, which catches a lone occluded pixel among three or more. At most one slot
    per texel per pass, never the texel's highest-weight one, and only with >= 3 selected.
    """
    a = active.float()
    n = a.sum(0)
    c = lv.colours
    s1 = (c * a[:, None]).sum(0)
    s2 = ((c * c).sum(1) * a).sum(0)
    if cfg.elimination_test == "paper":
        mu = s1 / n.clamp_min(1)
        var = (s2 / n.clamp_min(1) - (mu * mu).sum(0)).clamp_min(0)
        d2 = ((c - mu[None]) ** 2).sum(1)
        z2 = d2 / (var + cfg.sigma_min**2)[None]
    else:
        m = (n[None] - a).clamp_min(1)
        mu = (s1[None] - c * a[:, None]) / m[:, None]
        var = ((s2[None] - (c * c).sum(1) * a) / m - (mu * mu).sum(1)).clamp_min(0)
        d2 = ((c - mu) ** 2).sum(1)
        z2 = d2 / (var + cfg.sigma_min**2)
    # var is a mean squared distance over 3 channels; a 1-D k-sigma test on it reads k^2
    out = active & (z2 > cfg.sigma_k**2) & (n >= 3)[None]
    best = argmax0(torch.where(active, W, torch.full_like(W, -1.0)))
    out.scatter_(0, best, False)
    worst = argmax0(torch.where(out, z2, torch.full_like(z2, -1.0)))
    one = torch.zeros_like(out).scatter_(0, worst, True)
    return out & one


def photo_zero_share(lv: Level, base: torch.Tensor, W: torch.Tensor, tau: float, n_photos: int) -> torch.Tensor:
    """Per photo: share of the texels it could serve (base) where its weight is zero (<= tau); -1 if none."""
    idx = lv.idx.clamp_min(0).reshape(-1)
    b = base.reshape(-1).double()
    z = (base & (W <= tau)).reshape(-1).double()
    tot = torch.bincount(idx, weights=b, minlength=n_photos)
    zero = torch.bincount(idx, weights=z, minlength=n_photos)
    return torch.where(tot > 0, zero / tot.clamp_min(1), torch.full_like(tot, -1.0))


def photos_to_drop(lv: Level, base: torch.Tensor, W: torch.Tensor, tau: float, tau_w: float, n_photos: int) -> list[int]:
    """Photos whose weight is zero (<= tau) on more than tau_w of the texels they could serve."""
    share = photo_zero_share(lv, base, W, tau, n_photos)
    return [int(k) for k in torch.nonzero(share > tau_w).flatten().tolist()]


def dropped_slot_mask(lv: Level, eliminated: torch.Tensor, dropped: set[int], W: torch.Tensor | None = None) -> torch.Tensor:
    """Slots of dropped photos, except the best one of a texel that no other photo serves.

    Removing a texel's last source would leave a hole the optimization cannot fill (paper:
    "improper photo or pixel removal can cause irreversible color loss").
    """
    base = lv.visible & ~eliminated
    if not dropped:
        return torch.zeros_like(base)
    dset = torch.tensor(sorted(dropped), device=lv.idx.device)
    ds = torch.isin(lv.idx, dset) & base
    need = base.any(0) & ~(base & ~ds).any(0)
    score = W if W is not None else lv.theta0
    best = argmax0(torch.where(base, score, torch.full_like(score, -1.0)))
    keep = torch.zeros_like(ds).scatter_(0, best, True) & need[None]
    return ds & ~keep


def objective(theta, active, colours, Q, cost, D, matches, pixel_sets, support, n_tex: float,
              cfg: OptimizeConfig) -> dict[str, torch.Tensor]:
    """Every term of L for one level and its weighted total: a pure function of tensors, so
    torch.compile can fuse it (``OptimizeConfig.compile``)."""
    W = losses.blend_weights(theta, active)
    U = losses.compose(W, colours)
    terms = {}
    zero = theta.new_zeros(())
    if cfg.use_render:
        if cfg.loss_mode == "render":
            terms["render"] = losses.render_loss_pixels(U, support, pixel_sets, active, Q, n_tex)
        else:
            terms["render"] = losses.render_loss_texel(U, colours, active, Q, n_tex)
        terms["sparsity"] = losses.sparsity_loss(theta, active, n_tex) if cfg.use_sparsity else zero
    terms["persp"] = losses.persp_loss(W, cost, n_tex) if cfg.use_persp else zero
    if cfg.use_para:
        terms["para"] = losses.para_loss(W, U, active, None, matches, cfg.lambda_s, n_tex, cfg.para_eps, D)
    else:
        terms["para"] = zero
    total = zero
    if cfg.use_render:
        total = total + cfg.alpha * (terms["render"] + cfg.sparsity * terms["sparsity"])
    total = total + cfg.beta * terms["persp"] + cfg.omega * terms["para"]
    terms["total"] = total
    return terms


def loss_terms(lv: Level, st: LevelState, cfg: OptimizeConfig, matches, fn=objective) -> dict[str, torch.Tensor]:
    """The terms at the current weights; refreshes L_Para's edge weights D when they are due."""
    if cfg.use_para and (st.D is None or st.it % max(cfg.eliminate_every, 1) == 0):
        with torch.no_grad():
            U = losses.compose(losses.blend_weights(st.theta, st.active), lv.colours)
            st.D = losses.edge_weights(U, lv.G, tuple(matches))
    support = render_support(lv) if cfg.use_render and cfg.loss_mode == "render" else None
    return fn(st.theta, st.active, lv.colours, lv.Q, lv.cost, st.D, matches, lv.pixel_sets, support, lv.n_tex, cfg)


def _gradient_step(lv: Level, st: LevelState, cfg: OptimizeConfig, matches, fn, opt) -> dict[str, torch.Tensor]:
    """Evaluate the terms with ``fn``, backpropagate and take one Adam step; returns the terms."""
    terms = loss_terms(lv, st, cfg, matches, fn)
    opt.zero_grad(set_to_none=True)
    terms["total"].backward()
    opt.step()
    return terms


def compiled_objective(lv: Level, cfg: OptimizeConfig):
    """torch.compile'd ``objective`` for this level, or None to run eagerly.

    On the CPU, eager L costs some 30 elementwise passes over (K, H, W) tensors per iteration;
    inductor fuses them into a few loops. Measured on one thread (evaluation/bench_optimize.md):
    at a 19.8 M-slot level 4.3-5.7 s eager vs 2.3 s compiled per iteration, after 13-15 s of
    cold compilation. Saving ~0.1 us per slot and iteration repays that at about 130 M
    slot-iterations, i.e. from ~4 M slots at the finer levels' 40-80 iteration caps: ``auto``
    compiles levels with at least ``compile_min_slots`` slot entries.
    """
    mode = cfg.compile
    if mode == "off" or (mode == "auto" and lv.idx.numel() < cfg.compile_min_slots):
        return None
    return torch.compile(objective, dynamic=False)


@dataclass
class Result:
    """Optimized weights at the target level and the run's statistics."""

    frame: UVFrame
    texel_mask: np.ndarray
    idx: np.ndarray  # (K, H, W) int, photo index into PolygonInput.photos, -1 empty
    W: np.ndarray  # (K, H, W) float32 normalised blend weights (0 where inactive)
    stats: dict
    U: np.ndarray | None = None  # (H, W, 3) the composed texture at the target level


def optimize_polygon(inp: PolygonInput, cfg: OptimizeConfig, progress: bool = False, init_theta=None) -> Result:
    """Run DiffTex for one polygon; returns weights at the target resolution and statistics."""
    torch.manual_seed(cfg.seed)
    device = pick_device(cfg.device)
    t_start = time.perf_counter()
    N = len(inp.photos)
    stats: dict = {"polygon_id": inp.polygon_id, "device": str(device), "photos": [p.name for p in inp.photos],
                   "levels": [], "dropped": [], "config": cfg.to_dict()}
    target_long = max(inp.frame.shape)
    sides = level_sides(target_long, cfg.long_side_start, cfg.coarse_to_fine)
    t0 = time.perf_counter()
    samplers = build_samplers(inp, device)
    stats["time_read_photos_s"] = time.perf_counter() - t0
    dropped: set[int] = set()
    prev: LevelState | None = None
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=sum(cfg.cap(i) for i in range(len(sides))), desc=f"optimize {inp.polygon_id}", leave=False)
    for li, side in enumerate(sides):
        tl = time.perf_counter()
        frame = level_frame(inp.frame, side)
        lv = build_level(inp, frame, samplers, cfg, device, prev=prev, dropped=dropped)
        if cfg.use_render and cfg.loss_mode == "render":
            lv.pixel_sets = build_pixel_sets(inp, lv, samplers, device)
        t_setup = time.perf_counter() - tl
        K = lv.idx.shape[0]
        eliminated = torch.zeros_like(lv.visible)
        drop_slots = dropped_slot_mask(lv, eliminated, dropped)
        theta = lv.theta0.clone()
        base = base_mask(lv, eliminated, drop_slots)
        active = update_activation(theta, base, cfg.tau)
        st = LevelState(level=lv, theta=theta.requires_grad_(True), active=active, eliminated=eliminated)
        matches = {a: losses.neighbour_match(lv.idx, lv.mask, a, fixed=lv.fixed_slots) for a in (1, 2)} if cfg.use_para else {}
        opt = torch.optim.Adam([st.theta], lr=cfg.lr, betas=cfg.betas)
        fn = compiled_objective(lv, cfg) or objective
        hist: dict[str, list] = {k: [] for k in ("total", "render", "sparsity", "persp", "para")}
        n_elim = 0
        dropped_here = []
        converged = False
        cap = cfg.cap(li)
        it = 0
        if cfg.data_elimination:
            with torch.no_grad():
                W0 = losses.blend_weights(st.theta, st.active)
                e = eliminate_pixels(lv, st.active, W0, cfg)
                st.eliminated |= e
                n_elim += int(e.sum())
                drop_slots = dropped_slot_mask(lv, st.eliminated, dropped)
                base = base_mask(lv, st.eliminated, drop_slots)
                st.active = update_activation(st.theta.detach(), base, cfg.tau)
        anything = cfg.use_render or cfg.use_persp or cfg.use_para
        iter_times: list[float] = []
        for it in range(1, cap + 1 if anything else 1):
            st.it = it
            t_it = time.perf_counter()
            try:
                terms = _gradient_step(lv, st, cfg, matches, fn, opt)
            except Exception as e:  # noqa: BLE001 - compilation needs a C++ toolchain; eager always works
                if fn is objective:
                    raise
                reason = f"{type(e).__name__}: {str(e).splitlines()[0][:200]}"
                warnings.warn(f"torch.compile failed ({reason}); running eagerly")
                stats["compile_failed"] = reason
                fn = objective
                terms = _gradient_step(lv, st, cfg, matches, fn, opt)
            for k in hist:
                hist[k].append(float(terms[k].detach()) if k in terms else 0.0)
            with torch.no_grad():
                st.theta.data = gauge(st.theta.data.clamp(0.0, 1.0), base)
                W = losses.blend_weights(st.theta, base)
                if cfg.data_elimination:
                    if it >= cfg.min_iters_per_level // 2:
                        cand = [n for n in photos_to_drop(lv, base, W, cfg.tau, cfg.tau_w, N) if n not in dropped]
                        if cand:
                            # one photo per check (the worst): dropping changes everyone's weights
                            shares = photo_zero_share(lv, base, W, cfg.tau, N)
                            n = max(cand, key=lambda k: (float(shares[k]), -k))
                            dropped.add(n)
                            dropped_here.append(inp.photos[n].name)
                            stats["dropped"].append({"photo": inp.photos[n].name, "level": li, "iteration": it})
                            drop_slots = dropped_slot_mask(lv, st.eliminated, dropped, W)
                    if it % max(cfg.eliminate_every, 1) == 0:
                        e = eliminate_pixels(lv, st.active, losses.blend_weights(st.theta, st.active), cfg)
                        st.eliminated |= e
                        n_elim += int(e.sum())
                        if dropped:
                            drop_slots = dropped_slot_mask(lv, st.eliminated, dropped, W)
                base = base_mask(lv, st.eliminated, drop_slots)
                st.active = update_activation(st.theta.detach(), base, cfg.tau)
            iter_times.append(time.perf_counter() - t_it)
            if bar is not None:
                bar.update(1)
            w_ = cfg.conv_window
            if it >= max(cfg.min_iters_per_level, w_ + 1):
                old, new = hist["total"][-1 - w_], hist["total"][-1]
                if abs(old - new) <= cfg.conv_rel_tol * max(abs(old), 1e-12):
                    converged = True
                    break
        if bar is not None and it < cap:
            bar.update(cap - it)
        with torch.no_grad():
            final_terms = {k: float(v) for k, v in loss_terms(lv, st, cfg, matches).items()}
        st.history = hist
        lvl_stats = {
            "level": li, "long_side": side, "shape": list(frame.shape), "top_k": K,
            "candidates": lv.n_candidates, "iterations": it if anything else 0, "cap": cap,
            "converged": converged, "time_setup_s": t_setup, "time_s": time.perf_counter() - tl,
            # the first iteration carries torch.compile's cost; the median of the rest is the steady rate
            "time_first_iter_s": iter_times[0] if iter_times else 0.0,
            "time_per_iter_s": float(np.median(iter_times[1:])) if len(iter_times) > 1 else (iter_times[0] if iter_times else 0.0),
            "eliminated_pixels": n_elim, "dropped_photos": dropped_here,
            "active_slots_mean": float(st.active.sum(0).float()[lv.mask].mean()) if bool(lv.mask.any()) else 0.0,
            "tensor_bytes": lv.nbytes(), "final": final_terms, "loss": hist,
            "v_tilde": lv.v_tilde.tolist(), "compiled": fn is not objective,
        }
        if lv.pixel_sets is not None:
            lvl_stats["render_pixels"] = lv.pixel_sets.n
        stats["levels"].append(lvl_stats)
        prev = st
    if bar is not None:
        bar.close()
    assert prev is not None
    lv = prev.level
    with torch.no_grad():
        W = losses.blend_weights(prev.theta, prev.active)
        U = losses.compose(W, lv.colours)
    mask = inp.texel_mask
    has = (W.sum(0) > 0).cpu().numpy() & mask
    stats["coverage"] = float(has.sum() / max(mask.sum(), 1))
    stats["texels"] = int(mask.sum())
    stats["used_photos"] = sorted({inp.photos[int(n)].name for n in torch.unique(lv.idx[(W > 0)]).tolist() if n >= 0})
    stats["time_total_s"] = time.perf_counter() - t_start
    if device.type == "cuda":
        stats["cuda_peak_bytes"] = int(torch.cuda.max_memory_allocated(device))
    return Result(frame=inp.frame, texel_mask=mask, idx=lv.idx.cpu().numpy().astype(np.int32),
                  W=W.cpu().numpy().astype(np.float32), stats=stats, U=U.permute(1, 2, 0).cpu().numpy())


def photo_weight(idx: np.ndarray, W: np.ndarray, n: int) -> np.ndarray:
    """Photo n's blend weight per texel (H, W) from the slot layout."""
    return (W * (idx == n)).sum(0)
