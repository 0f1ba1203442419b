"""Render-space data of one level (loss_mode "render"): each photo's a_k^i pixels and where they
fall on the texture, so that L_Render renders the textured polygon into the photos.

The rasterisation (pixel -> texel coordinate) is computed once per photo and level; the
rendering itself is then a differentiable bilinear lookup of U (losses.render_view).
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F

from difftex.errors import DifftexError
from difftex.geometry.frames import pixel_to_texel
from difftex.method import losses
from difftex.method.levels import Level
from difftex.sampling.colour import apply_transfer_torch
from difftex.sampling.photos import PhotoSet


def render_support(lv: Level) -> torch.Tensor:
    """Texels that carry colour in the render-mode lookup: inside the polygon and seen by a photo.

    The activation update always keeps a texel's strongest candidate, so this does not change
    during a level.
    """
    return lv.mask & lv.visible.any(0)


def build_pixel_sets(
    photos: PhotoSet, lv: Level, transfers: list | None, scale: str = "texels"
) -> losses.PixelBatch:
    """Per photo: its a_k^i pixels at the pyramid level matching the texel size, their texel
    coords, and what each counts in L_Render (``scale``: OptimizeConfig.render_scale,
    losses.pixel_weight)."""
    inp, device = photos.inp, photos.device
    if inp.a_bbox is None or inp.a_masks is None:
        raise DifftexError(
            f"polygon '{inp.polygon_id}': loss_mode 'render' needs the photo-space masks a_k^i (visibility file)"
        )
    frame = lv.frame
    h, w = frame.shape
    K = lv.idx.shape[0]
    idx_flat = lv.idx.reshape(K, -1)
    mask_flat = lv.mask.reshape(-1)
    sets = []
    for n, smp in photos.samplers.items():
        x0, y0, x1, y1 = (int(v) for v in inp.a_bbox[n])
        a = inp.a_masks[n]
        n_tex = int((lv.idx == n).any(0).sum())
        if a.size == 0 or not a.any() or n_tex == 0:
            continue
        ratio = math.sqrt(a.sum() / n_tex)
        L = int(np.clip(math.floor(math.log2(max(ratio, 1.0))), smp.base, smp.top))
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
        full[ay0 - cy0 : ay1 - cy0, ax0 - cx0 : ax1 - cx0] = torch.from_numpy(
            a[ay0 - y0 : ay1 - y0, ax0 - x0 : ax1 - x0].astype(np.float32)
        )
        m = (F.avg_pool2d(full[None, None], s)[0, 0] > 0.5) if s > 1 else full > 0.5
        rows, cols_ = torch.nonzero(m, as_tuple=True)
        if len(rows) == 0:
            continue
        px = cx0 + (cols_.numpy() + 0.5) * s
        py = cy0 + (rows.numpy() + 0.5) * s
        pix = np.stack([px, py], -1)
        if n in photos.corrections:
            # the alignment moved f_k^i to p + d(p); its inverse, to first order in the (small,
            # smooth) displacement, takes photo pixel p back through p - d(p)
            d = photos.corrections[n].displacement(torch.from_numpy(pix).double()).numpy()
            pix = pix - d
        t = pixel_to_texel(frame, inp.photos[n], pix)
        ok = np.isfinite(t).all(-1) & (t[:, 0] >= 0) & (t[:, 0] < w) & (t[:, 1] >= 0) & (t[:, 1] < h)
        if not ok.any():
            continue
        t = t[ok]
        rows_d, cols_d = rows[ok].to(device), cols_[ok].to(device)
        colour = img[:, rows_d, cols_d].T.contiguous()
        if transfers is not None and transfers[n] is not None:
            colour = apply_transfer_torch(colour.T[:, :, None], transfers[n])[:, :, 0].T.contiguous()
        tex = torch.from_numpy(np.floor(t[:, 1]).astype(np.int64) * w + np.floor(t[:, 0]).astype(np.int64)).to(device)
        inside = mask_flat[tex]
        tex, colour, t = tex[inside], colour[inside], t[inside.cpu().numpy()]
        if len(tex) == 0:
            continue
        slots = idx_flat[:, tex] == n
        slot = torch.where(slots.any(0), slots.float().argmax(0), torch.full_like(tex, -1))
        g = np.stack([t[:, 0] / w * 2 - 1, t[:, 1] / h * 2 - 1], -1).astype(np.float32)
        grid = torch.from_numpy(g).to(device)[None, :, None, :]
        weight = losses.pixel_weight(scale, n_tex, len(tex), s)
        sets.append(losses.PixelSet(grid=grid, colour=colour, texel=tex, slot=slot, scale=weight))
    return losses.batch_pixel_sets(sets, render_support(lv), device)
