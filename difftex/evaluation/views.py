"""The textured proxy rendered into held-out cameras and compared with their photos (Table 2's
scheme; synthetic scenes use their occluder-free ``ground_truth/views``). See
difftex.evaluation.evaluate for the whole evaluation of a results folder.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np

from difftex.evaluation.results import EvaluateConfig, PolygonTexture, _lpips_plan
from difftex.layout import view_file

log = logging.getLogger(__name__)


# --------------------------------------------------------------------------------------------
# Rendering the textured proxy into a camera


def scaled_photo(photo, long_side: int):
    """The same camera at another resolution (pycolmap's rescale keeps the pixel-centre convention)."""
    import copy
    import dataclasses

    s = min(1.0, long_side / max(photo.width, photo.height))
    if s >= 1.0:
        return photo, 1.0
    cam = copy.deepcopy(photo.camera)
    w, h = max(1, round(photo.width * s)), max(1, round(photo.height * s))
    cam.rescale(w, h)
    return dataclasses.replace(photo, camera=cam, width=int(cam.width), height=int(cam.height)), s


def render_proxy(
    photo, proxy, textures: dict[str, PolygonTexture], prepared=None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(image (H, W, 3), polygon index per pixel (-1 none), textured (H, W) bool) in ``photo``'s camera.

    Not ``difftex.export.assemble.render_view`` on purpose: that one renders the exported GLB (its
    atlas and UVs, untextured polygons as grey) to check the written file; this one renders the
    per-polygon textures of any results folder (baselines and peers write no GLB), excludes
    untextured polygons from ``textured`` and returns the polygon index per pixel, which the
    scores need. Both use the same ray caster (``id_buffer``) and sampler (``sample_photo``).
    """
    from difftex.geometry.frames import pixel_to_texel, sample_photo
    from difftex.geometry.visibility import id_buffer

    ids, _ = id_buffer(prepared if prepared is not None else proxy, photo)
    H, W = ids.shape
    img = np.zeros((H, W, 3), np.float32)
    textured = np.zeros((H, W), bool)
    for j, poly in enumerate(proxy.polygons):
        pt = textures.get(poly.id)
        sel = ids == j
        if pt is None or not sel.any():
            continue
        ys, xs = np.nonzero(sel)
        pix = np.stack([xs + 0.5, ys + 0.5], -1).astype(np.float64)
        t = pixel_to_texel(pt.frame, photo, pix)
        ok = np.isfinite(t).all(-1)
        vals = sample_photo(pt.texture, np.where(ok[:, None], t, np.nan))
        img[ys[ok], xs[ok]] = vals[ok]
        textured[ys[ok], xs[ok]] = True
    return img, ids, textured


def downscale_image(img: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Antialiased resize to (width, height)."""
    import torch
    import torch.nn.functional as F

    if img.shape[1] == size[0] and img.shape[0] == size[1]:
        return img
    t = torch.from_numpy(np.ascontiguousarray(img, np.float32)).permute(2, 0, 1)[None]
    t = F.interpolate(t, size=(size[1], size[0]), mode="bilinear", antialias=True, align_corners=False)
    return t[0].permute(1, 2, 0).numpy()


def evaluate_views(
    photos: list,
    proxy,
    textures: dict[str, PolygonTexture],
    cfg: EvaluateConfig,
    out_dir: Path | None = None,
    progress: bool = True,
) -> dict:
    """SSIM / LPIPS / PSNR of the textured proxy rendered into each (held-out) photo, on proxy pixels."""
    from rich.progress import track

    from difftex.evaluation import metrics
    from difftex.geometry.visibility import prepare
    from difftex.scene.files import read_image, write_image

    pp = prepare(proxy)
    rows = []
    lp_variant, lp_label = _lpips_plan(cfg)
    for ph in track(photos, description="held-out views", disable=not progress, transient=True):
        sp, _ = scaled_photo(ph, cfg.render_long_side)
        ren, ids, textured = render_proxy(sp, proxy, textures, pp)
        ref = downscale_image(read_image(ph.image_path, expected_size=(ph.width, ph.height)), (sp.width, sp.height))
        # Metrics take [0, 1] images; textures are stored in [0, 1], so an HDR photo's values
        # above 1 are clipped as the texture's were.
        ref = np.clip(ref, 0.0, 1.0)
        mask = textured
        row = {
            "photo": ph.name,
            "size": [sp.width, sp.height],
            "proxy_pixels": int((ids >= 0).sum()),
            "compared_pixels": int(mask.sum()),
        }
        if mask.sum() < 64:
            row["skipped"] = "the textured proxy covers fewer than 64 pixels"
            rows.append(row)
            continue
        row["ssim"] = metrics.ssim(ren, ref, mask)
        row["psnr"] = metrics.psnr(ren, ref, mask)
        if lp_variant:
            row["lpips"], lp_label = metrics.lpips(
                ren, ref, mask, variant=lp_variant, weights_dir=cfg.lpips_weights, device=cfg.device
            )
        else:
            row["lpips"] = None
        if out_dir is not None:
            shown = np.where(mask[..., None], ren, ref * 0.25)
            write_image(view_file(out_dir, ph.name, "render"), shown)
            write_image(view_file(out_dir, ph.name, "photo"), ref)
            err = np.clip(metrics.texel_error(ren, ref) / math.sqrt(3) * 3, 0, 1)
            err[~mask] = 0
            write_image(view_file(out_dir, ph.name, "error"), err)
        rows.append(row)
    scored = [r for r in rows if "ssim" in r]

    def wmean(key):
        vals = [(r[key], r["compared_pixels"]) for r in scored if r.get(key) is not None]
        return sum(v * n for v, n in vals) / sum(n for _, n in vals) if vals else None

    overall = {
        "ssim": wmean("ssim"),
        "lpips": wmean("lpips"),
        "psnr": wmean("psnr"),
        "views": len(scored),
        "lpips_variant": lp_label or "unavailable: no held-out view was scored",
        "render_long_side": cfg.render_long_side,
        "aggregation": "pixel-weighted means over the held-out views of the per-view values",
    }
    return {"overall": overall, "views": rows}
