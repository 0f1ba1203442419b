"""Photo sampling: a polygon's candidate photos, decoded once, mapped into its texel space.

For one polygon P_i, every candidate photo I_k is

1. decoded once (``decode_photo``), at the coarsest power-of-two scale that still holds the
   detail the polygon's finest texture level needs (a JPEG is decoded at 1/2, 1/4 or 1/8 in the
   DCT domain, which is several times faster than a full decode);
2. cropped to the polygon and kept as a 2x box-filtered pyramid (``PhotoSampler``);
3. mapped into texel space at any resolution level (``PhotoSet.map``): f_k^i evaluated at the
   texel centres (``texel_map``), the pyramid level matched to each texel's footprint
   (trilinear), so a coarse level never touches full-resolution pixels.

Layer: scene input and geometry below, the method (initialisation, losses, the loop),
composition and the baselines above; they all sample photos through this module.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import torch
import torch.nn.functional as F

from difftex.errors import DifftexError
from difftex.geometry.frames import UVFrame
from difftex.sampling import SUPERSAMPLE
from difftex.sampling.colour import apply_transfer_torch

# the torch-free part (the initialization stage's), re-exported: callers import the polygon's input here
from difftex.sampling.crops import (  # noqa: F401
    CROP_ALIGN,
    PROBE_LONG_SIDE,
    PhotoCrop,
    PolygonInput,
    crop_box,
    photo_crops,
    polygon_input_from_visibility,
)
from difftex.sampling.relief import Relief, texel_map_relief
from difftex.sampling.texels import Region, resample_nearest, texel_map
from difftex.scene.files import decode_photo, to_float


def pick_device(name: str | torch.device) -> torch.device:
    """The torch device for a config value: "auto" (CUDA when torch sees it), "cpu" or "cuda"."""
    if isinstance(name, torch.device):
        return name
    if name == "cuda" and not torch.cuda.is_available():
        raise DifftexError("device 'cuda' requested but torch sees no CUDA device")
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


# --------------------------------------------------------------------------------------------
# One polygon's input


# --------------------------------------------------------------------------------------------
# Decoding and pyramids


def box_halve(x: torch.Tensor) -> torch.Tensor:
    """The 2x2 box average of (C, h, w) maps: (C, h // 2, w // 2), an odd last row or column dropped.

    The same values as ``F.avg_pool2d(x[None], 2)[0]`` (its sum order, ((a + b) + c) + d, then
    a quarter), written out over strided views: on a CPU the pooling kernel took several times
    as long, and every decoded photo gets a pyramid.

    Args:
        x: (C, h, w) float maps, h and w at least 2.

    Returns:
        (C, h // 2, w // 2) maps.
    """
    h, w = x.shape[-2] // 2 * 2, x.shape[-1] // 2 * 2
    x = x[..., :h, :w]
    s = x[..., 0::2, 0::2] + x[..., 0::2, 1::2]
    s += x[..., 1::2, 0::2]
    s += x[..., 1::2, 1::2]
    return s.mul_(0.25)


class PhotoSampler:
    """A photo cropped to the polygon, as a 2x box-filtered pyramid, sampled at pixel positions.

    Level L pixel (i, j) covers full-resolution pixels [x0 + j 2^L, x0 + (j+1) 2^L); with COLMAP
    pixel centres at +0.5 a full-resolution coordinate p maps to (p - x0) / 2^L at level L.
    ``image`` is the photo decoded at 1/2^``base`` (levels below ``base`` do not exist) and
    ``box`` the crop in full-resolution pixels, a multiple of 2^``base``.
    """

    def __init__(
        self, image: np.ndarray, box: tuple[int, int, int, int], device: torch.device, base: int = 0, min_side: int = 4
    ):
        x0, y0, x1, y1 = box
        s = 2**base
        if x0 % s or y0 % s:
            raise ValueError("the crop box must start on a multiple of the decode scale")
        self.x0, self.y0, self.base = int(x0), int(y0), int(base)
        # (an image as stored, 8/16-bit, is converted here: only the crop)
        crop = torch.from_numpy(
            np.ascontiguousarray(to_float(image[y0 // s : -(-y1 // s), x0 // s : -(-x1 // s)]))
        ).permute(2, 0, 1)
        self._build(crop, device, min_side)

    @classmethod
    def from_crop(cls, crop: PhotoCrop, device: torch.device, min_side: int = 4) -> PhotoSampler:
        """The sampler of a crop as ``photo_crops`` made it (the same pyramid, bit for bit, as
        the constructor's on the whole decoded photo and the crop's box)."""
        self = cls.__new__(cls)
        self.x0, self.y0, self.base = int(crop.x0), int(crop.y0), int(crop.base)
        self._build(torch.from_numpy(np.ascontiguousarray(to_float(crop.pixels))).permute(2, 0, 1), device, min_side)
        return self

    def _build(self, crop: torch.Tensor, device: torch.device, min_side: int) -> None:
        """The 2x box pyramid of ``crop`` (3, h, w) float32."""
        self.device = device
        levels = [crop.to(device=device, dtype=torch.float16)]
        cur = crop.to(device)
        while min(cur.shape[1:]) >= 2 * min_side and len(levels) < 12:
            cur = box_halve(cur)
            levels.append(cur.to(torch.float16))
        self.levels = levels  # levels[i] is pyramid level base + i

    @property
    def top(self) -> int:
        """The coarsest level's index."""
        return self.base + len(self.levels) - 1

    def level_image(self, L: int) -> torch.Tensor:
        return self.levels[L - self.base].float()

    def nbytes(self) -> int:
        return int(sum(t.numel() * t.element_size() for t in self.levels))

    def sample(self, pix: torch.Tensor, footprint: torch.Tensor, supersample: int = 1) -> torch.Tensor:
        """Colours (3, h, w) of the texels centred at full-resolution pixels ``pix`` (h, w, 2).

        ``footprint`` (h, w) is the texel's size in full-resolution pixels. With ``supersample``
        S = 1, one trilinear sample at pyramid level log2(footprint): the box of the level's pixel
        convolved with the bilinear tent of the same width, a blur of standard deviation 0.5
        footprint where the texel's own box is 0.29. With S > 1, the mean of S x S samples spread
        over the texel (along the grid's axes in the photo, :func:`texel_axes`), each at level
        log2(footprint / S): the blur falls towards the texel's box (0.35 footprint at S = 2),
        so a texture holds the detail of its texel size, as a peer that textures at the photos'
        resolution and area-averages does, for S^2 times the sampling.
        """
        if supersample <= 1:
            return self._sample(pix, footprint)
        ax, ay = texel_axes(pix)
        offsets = [(j + 0.5) / supersample - 0.5 for j in range(supersample)]
        out = torch.zeros(3, *pix.shape[:2], device=self.device)
        for oy in offsets:
            for ox in offsets:
                out += self._sample(pix + ox * ax + oy * ay, footprint / supersample)
        return out / supersample**2

    def _sample(self, pix: torch.Tensor, footprint: torch.Tensor) -> torch.Tensor:
        """One trilinear sample per pixel position, at pyramid level log2(footprint)."""
        h, w = pix.shape[:2]
        lam = torch.log2(footprint.clamp_min(1.0)).clamp(self.base, self.top)
        out = torch.zeros(3, h, w, device=self.device)
        p = torch.nan_to_num(pix, nan=-1e6)
        lo, hi = int(math.floor(float(lam.min()))), int(math.ceil(float(lam.max())))
        for L in range(lo, min(hi, self.top) + 1):
            wL = (1.0 - (lam - L).abs()).clamp_min(0.0)
            if not bool((wL > 0).any()):
                continue
            img = self.level_image(L)
            s = 2.0**L
            gx = ((p[..., 0] - self.x0) / s) / img.shape[2] * 2 - 1
            gy = ((p[..., 1] - self.y0) / s) / img.shape[1] * 2 - 1
            grid = torch.stack([gx, gy], -1)[None]
            # border padding: pixels of a texel near the crop edge still get the nearest colour
            smp = F.grid_sample(img[None], grid, mode="bilinear", padding_mode="border", align_corners=False)[0]
            out += wL[None] * smp
        return out


def texel_axes(pix: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The photo-space steps (h, w, 2) of one texel along the grid's x and y: central differences
    of ``pix`` (h, w, 2), one-sided at the edges; zero where a neighbour is not finite (behind the
    camera), so that such texels' sub-samples fall on their centre.

    Differences of the mapped positions rather than the homography's Jacobian: the positions
    already hold the lens distortion and an alignment correction, and f_k^i is smooth at the
    scale of a texel.
    """
    if pix.shape[0] < 2 or pix.shape[1] < 2:
        return torch.zeros_like(pix), torch.zeros_like(pix)
    gy, gx = torch.gradient(pix, dim=(0, 1))
    return torch.nan_to_num(gx, nan=0.0, posinf=0.0, neginf=0.0), torch.nan_to_num(gy, nan=0.0, posinf=0.0, neginf=0.0)


# --------------------------------------------------------------------------------------------
# A polygon's photos, decoded once


@dataclass
class MappedPhoto:
    """Photo n mapped into texel space at one level."""

    colour: torch.Tensor  # (3, h, w), through the photo's brightness transfer when one is given
    visible: torch.Tensor  # (h, w) bool
    view: torch.Tensor  # (3, h, w) unit camera-to-texel direction (V^_k)
    cos: torch.Tensor  # (h, w) frontality (Q_a)
    footprint: torch.Tensor  # (h, w) texel size in full-resolution pixels


@dataclass
class Correction:
    """An affine correction of a photo's mapping in its pixels: p -> p + d + M (p - c) / s.

    ``params`` = (dx, dy, m11, m12, m21, m22) in pixels; ``centre`` c and ``scale`` s normalise
    the affine part to the polygon's extent in the photo, so all six parameters are in pixels
    of displacement at the polygon's edge.
    """

    params: torch.Tensor  # (6,) float64
    centre: tuple[float, float]
    scale: float

    def displacement(self, pix: torch.Tensor) -> torch.Tensor:
        """(..., 2) pixel displacement at ``pix`` (..., 2)."""
        p = self.params.to(pix.device, pix.dtype)
        u = (pix[..., 0] - self.centre[0]) / self.scale
        v = (pix[..., 1] - self.centre[1]) / self.scale
        return torch.stack([p[0] + p[2] * u + p[3] * v, p[1] + p[4] * u + p[5] * v], -1)

    def apply(self, pix: torch.Tensor) -> torch.Tensor:
        return pix + self.displacement(pix)




@dataclass
class PhotoSet:
    """The candidate photos of one polygon, each decoded once and kept as a cropped pyramid.

    ``samplers`` maps the index of a photo in ``inp.photos`` to its sampler; photos that see no
    texel of the polygon have none. ``reads`` counts image decodes (one per photo).
    """

    inp: PolygonInput
    device: torch.device
    samplers: dict[int, PhotoSampler]
    reads: int = 0
    decode_scale: dict[int, int] = field(default_factory=dict)
    # Per photo, a small affine correction of f_k^i in pixels (difftex.method.alignment):
    # p -> p + d + M (p - c) / s, parameters (dx, dy, m11, m12, m21, m22), centre c, scale s.
    corrections: dict[int, Correction] = field(default_factory=dict)
    supersample: int = SUPERSAMPLE  # S x S samples per texel of the polygon's own frame (PhotoSampler.sample)
    # the polygon's height field (difftex.sampling.relief): photos are mapped through the displaced
    # surface and lose the texels it hides from them; None: the proxy's plane
    relief: Relief | None = None
    # each photo's median footprint on the polygon's coarse probe grid (None: it sees none there),
    # filled by difftex.method.witnesses.candidate_footprints: it depends only on the photo's
    # pose and the polygon, and is read once per level and once for the mixed-resolution decision
    probe_footprints: dict[int, float | None] = field(default_factory=dict)

    @classmethod
    def load(
        cls,
        inp: PolygonInput,
        device,
        finest: UVFrame | None = None,
        exact_decode: bool = False,
        progress: Callable[[], None] | None = None,
        decode: Callable[..., np.ndarray] = decode_photo,
        supersample: int = SUPERSAMPLE,
        relief_range: tuple[float, float] = (0.0, 0.0),
    ) -> PhotoSet:
        """Decode, crop and pyramid every candidate photo that sees a texel of ``inp``.

        ``finest``: the finest frame that will be sampled (default ``inp.frame``); each photo is
        decoded at the largest power-of-two reduction r with r <= the smallest texel footprint
        (in pixels) over the texels it sees, so no sampled pyramid level is lost. ``exact_decode``
        decodes every photo at full size (a JPEG's DCT-scaled decode differs from box-averaging
        the full decode by about one 8-bit step). ``decode``: ``decode_photo`` or a cache around
        it (difftex.scene.files.DecodeCache) shared by the polygons of one job. ``supersample``:
        S x S samples per texel of ``inp.frame`` (the texture's own resolution), each at 1/S of
        the texel's footprint (so decoded at up to S times finer). ``relief_range``: the lowest
        and highest heights along the normal that the photos may be mapped through (a relief
        sweep's range): each crop also holds the polygon's rectangle shifted to both.
        """
        ps = cls(inp=inp, device=pick_device(device), samplers={}, supersample=max(1, int(supersample)))
        for n, crop in photo_crops(inp, finest, exact_decode, decode, ps.supersample, relief_range):
            ps.reads += 1
            ps.add(n, crop)
            if progress is not None:
                progress()
        return ps

    @classmethod
    def from_crops(
        cls, inp: PolygonInput, crops: dict[int, PhotoCrop], device, supersample: int = SUPERSAMPLE
    ) -> PhotoSet:
        """The photo set of crops decoded earlier (``photo_crops``): no photo is decoded."""
        ps = cls(inp=inp, device=pick_device(device), samplers={}, supersample=max(1, int(supersample)))
        for n in sorted(crops):
            ps.add(n, crops[n])
        return ps

    def add(self, n: int, crop: PhotoCrop) -> None:
        """Photo ``n``'s sampler, from its crop."""
        self.samplers[n] = PhotoSampler.from_crop(crop, self.device)
        self.decode_scale[n] = 2**crop.base

    def nbytes(self) -> int:
        return int(sum(s.nbytes() for s in self.samplers.values()))

    def footprint_on(self, n: int, frame: UVFrame, mask: torch.Tensor) -> tuple[torch.Tensor, float | None]:
        """Where photo n sees ``frame`` (on the plane, within ``mask``), and its median footprint
        there (pixels per texel; None where it sees none).

        Args:
            n: the photo's index; frame: any frame of the polygon; mask: (h, w) bool on ``frame``'s device.

        Returns:
            ((h, w) bool texels seen, median footprint or None).
        """
        inp = self.inp
        tm = texel_map(frame, inp.photos[n], self.device)
        seen = torch.from_numpy(resample_nearest(inp.texel_visible[n], inp.frame, frame)).to(self.device)
        seen &= mask & tm.valid
        return seen, (float(tm.footprint[seen].median()) if bool(seen.any()) else None)

    def map(
        self, n: int, frame: UVFrame, mask: np.ndarray, transfer: np.ndarray | None = None, region: Region | None = None
    ) -> MappedPhoto | None:
        """Photo n mapped into ``frame`` over the texels of ``mask``; None if it sees none.

        ``transfer``: its brightness transfer (difftex.sampling.colour), applied to the colours;
        ``region``: only that rectangle of the frame (the MappedPhoto is that size; ``mask`` is
        the whole frame's).
        """
        inp, ph = self.inp, self.inp.photos[n]
        visible = resample_nearest(inp.texel_visible[n], inp.frame, frame, region)
        if region is not None:
            y0, y1, x0, x1 = region
            mask = mask[y0:y1, x0:x1]
        relief = self.relief if self.relief is not None and not self.relief.flat else None
        if relief is not None:
            tm = texel_map_relief(frame, ph, relief.at(frame, region), self.device, region)
            seen = relief.seen(n, frame, region)
            if seen is not None:
                visible = visible & seen
        else:
            tm = texel_map(frame, ph, self.device, region)
        if n in self.corrections:
            tm.pix = self.corrections[n].apply(tm.pix)
        vis = tm.valid & torch.from_numpy(np.ascontiguousarray(visible & mask)).to(self.device)
        if not bool(vis.any()):
            return None
        # The texture's own texels are supersampled; coarser levels, which only steer the weights,
        # take one sample and skip the S^2 cost
        final = frame.shape == inp.frame.shape and frame.texel_size == inp.frame.texel_size
        col = self.samplers[n].sample(tm.pix, tm.footprint, self.supersample if final else 1) * vis[None]
        mp = MappedPhoto(colour=col, visible=vis, view=tm.view, cos=tm.cos, footprint=tm.footprint)
        return with_transfer(mp, transfer)


def with_transfer(mp: MappedPhoto, transfer: np.ndarray | None) -> MappedPhoto:
    """The mapped photo with its colours through a brightness transfer (difftex.sampling.colour)."""
    if transfer is None:
        return mp
    col = apply_transfer_torch(mp.colour, transfer) * mp.visible[None]
    return MappedPhoto(colour=col, visible=mp.visible, view=mp.view, cos=mp.cos, footprint=mp.footprint)


