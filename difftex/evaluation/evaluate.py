"""Evaluation of a textured proxy (paper Tables 1 and 2), for difftex and every baseline alike.

Two schemes, both reading only a results folder ``R`` (``R/textures/<pid>/texture.png``,
``source.npz``, ``report.json`` and the frames in ``R/visibility/<pid>.npz``):

- **Synthetic** (scene has ``ground_truth/``): every texture is resampled into its polygon's
  ground-truth frame (``ground_truth/frames/<pid>.json``) through world points, so a texture
  at any resolution, or in a frame whose axes differ, lands on the right ground-truth texels;
  the frames' planes must agree (checked) and then Error 90/95, SSIM, PSNR and LPIPS are
  computed on the ground-truth texel mask (the paper resamples every method to the GT size).
- **Held-out photos** (real scenes): the scene was copied by
  :func:`difftex.evaluation.holdout.prepare_holdout` with some photos removed from its COLMAP
  model (``holdout.json`` in the copy names them and the original scene); the textured proxy is
  rendered into each held-out camera (an id buffer says which polygon a pixel sees, the pixel's
  ray meets that polygon's plane at a texel, the texture is sampled bilinearly there) and
  compared with the photo on the proxy's pixels. Synthetic scenes get the same with their
  occluder-free ``ground_truth/views``.

Q_front / Q_vc (perspective quality) need per-texel view directions of the source pixels:
difftex's optimized blend weights (``R/optimized/<pid>/weights.npz``), the equal weights of the
averaging baseline, or otherwise the dominant photo per texel (``R/textures/<pid>/source.npz``).
"""

from __future__ import annotations

import json
import logging
import math
import time
from pathlib import Path

import numpy as np

from difftex.errors import DifftexError
from difftex.evaluation.results import (  # noqa: F401  (re-exported)
    EvaluateConfig,
    PolygonTexture,
    _lpips_plan,
    load_textures,
    visibility_dir,
)
from difftex.geometry.frames import UVFrame
from difftex.layout import ERROR_MAPS, SOURCE_NPZ, VIEWS, Results, error_map_file, visibility_file

log = logging.getLogger(__name__)


# The config, reading a results folder and the LPIPS plan live in difftex.evaluation.results
# (shared with difftex.evaluation.views); imported here for the callers of this module.


# --------------------------------------------------------------------------------------------
# Resampling between frames of the same plane


def check_same_plane(a: UVFrame, b: UVFrame, what: str, tol: float = 1e-3) -> None:
    """Raise unless the two frames lie on the same plane with the same outward normal."""
    scale = max(a.width * a.texel_size, a.height * a.texel_size, 1e-9)
    if float(a.normal @ b.normal) < 1 - 1e-4:
        raise DifftexError(
            f"{what}: ground-truth frame normal {np.round(b.normal, 4).tolist()} differs from "
            f"difftex's {np.round(a.normal, 4).tolist()}"
        )
    if abs(float((b.origin - a.origin) @ a.normal)) > tol * scale:
        raise DifftexError(
            f"{what}: ground-truth frame is off difftex's plane by "
            f"{abs(float((b.origin - a.origin) @ a.normal)):.4g} scene units"
        )


def frame_offsets(a: UVFrame, b: UVFrame) -> dict:
    """How frame b differs from a (axes and origin), for the evaluation record."""
    return {
        "axes_dot": [float(a.e_u @ b.e_u), float(a.e_v @ b.e_v)],
        "origin_offset_texels": float(np.linalg.norm(b.origin - a.origin) / b.texel_size),
        "texel_size_ratio": float(b.texel_size / a.texel_size),
    }


def resample_texture(tex: np.ndarray, src: UVFrame, dst: UVFrame) -> np.ndarray:
    """The texture of frame ``src`` seen at the texel centres of frame ``dst`` (same plane).

    Downsampling first low-passes the texture (antialiased resize to about the destination
    texel size) so that a 2048 map compared at 512 is not aliased, then samples bilinearly at
    the exact world positions of the destination texel centres (edge texels clamp).
    """
    import torch
    import torch.nn.functional as F

    img = torch.from_numpy(np.ascontiguousarray(tex, np.float32)).permute(2, 0, 1)[None]
    r = dst.texel_size / src.texel_size  # > 1: destination texels are larger
    sx = sy = 1.0
    if r > 1.01:
        h, w = max(1, round(src.height / r)), max(1, round(src.width / r))
        sy, sx = src.height / h, src.width / w
        img = F.interpolate(img, size=(h, w), mode="bilinear", antialias=True, align_corners=False)
    tx, ty = dst.centres()
    t = src.world_to_texel(dst.texel_to_world(tx, ty))
    H, W = img.shape[-2:]
    gx = (t[..., 0] / sx) / W * 2 - 1
    gy = (t[..., 1] / sy) / H * 2 - 1
    grid = torch.from_numpy(np.stack([gx, gy], -1).astype(np.float32))[None]
    out = F.grid_sample(img, grid, mode="bilinear", padding_mode="border", align_corners=False)
    return out[0].permute(1, 2, 0).numpy()


# --------------------------------------------------------------------------------------------
# Per-texel view directions (Q_front, Q_vc)


def view_weights(pt: PolygonTexture, results: Path) -> tuple[list[str], np.ndarray, str]:
    """(photo names, per-photo weights (K, H, W), how) of the pixels that coloured each texel."""
    from difftex.geometry.visibility import load_visibility
    from difftex.scene.files import read_npz

    method = pt.report.get("method", "")
    wpath = Results(results).weights(pt.polygon_id)
    if method == "difftex" and wpath.is_file():
        wz = read_npz(wpath)
        names = [str(x) for x in wz["photos"]]
        idx, W = wz["idx"].astype(np.int64), wz["W"].astype(np.float32)
        if idx.shape[1:] == pt.frame.shape:
            dense = (
                np.stack([(W * (idx == n)).sum(0) for n in range(len(names))])
                if names
                else np.zeros((0, *pt.frame.shape))
            )
            return names, dense, "blend weights"
    if method == "average":
        vis = load_visibility(visibility_file(visibility_dir(results), pt.polygon_id))
        return list(vis.photos), vis.texel_visible.astype(np.float32), "equal weights of visible photos"
    src = pt.folder / SOURCE_NPZ
    if not src.is_file():  # a results folder written before source.npz: its source.png is only colours
        return [], np.zeros((0, *pt.frame.shape), np.float32), "none"
    d = read_npz(src)
    try:
        names, dom = [str(x) for x in d["photos"]], d["dominant"].astype(np.int64)
    except KeyError as exc:
        raise DifftexError(f"{src}: not a difftex source file (no {exc})") from None
    if dom.shape != pt.frame.shape:
        raise DifftexError(
            f"{src}: {dom.shape[1]}x{dom.shape[0]} texels, its frame says {pt.frame.width}x{pt.frame.height}"
        )
    w = (dom[None] == np.arange(len(names))[:, None, None]).astype(np.float32)  # (K, H, W), K may be 0
    return names, w, "dominant photo (source.npz)" if names else "none"


def perspective_quality(pt: PolygonTexture, results: Path, centres: dict[str, np.ndarray]) -> dict | None:
    from difftex.evaluation import metrics

    names, w, how = view_weights(pt, results)
    keep = [i for i, n in enumerate(names) if n in centres]
    if not keep:
        return None
    w = w[keep] * pt.mask[None]
    if not (w.sum(0) > 0).any():
        return None
    tx, ty = pt.frame.centres()
    pts = pt.frame.texel_to_world(tx, ty)
    dirs = metrics.view_directions(pts, np.stack([centres[names[i]] for i in keep]), w, mode="blend")
    cov = (w.sum(0) > 0) & pt.mask
    return {
        "q_front": metrics.q_front(dirs, pt.frame.normal, cov),
        "q_vc": metrics.q_vc(dirs, cov),
        "q_texels": int(cov.sum()),
        "q_source": how,
    }


# --------------------------------------------------------------------------------------------
# Synthetic: against ground-truth maps


def evaluate_maps(
    scene: Path,
    textures: dict[str, PolygonTexture],
    cfg: EvaluateConfig,
    error_dir: Path | None = None,
    progress: bool = True,
) -> dict:
    """Table 1 metrics per polygon and pooled over the building."""
    from difftex.evaluation import metrics
    from difftex.scene.files import read_image, read_json, write_image

    gt = scene / "ground_truth"
    rows, errs, sq, n_tex = [], [], 0.0, 0
    lp_variant, lp_label = _lpips_plan(cfg)
    for pid, pt in textures.items():
        fpath = gt / "frames" / f"{pid}.json"
        if not fpath.is_file():
            continue
        gframe = UVFrame.from_dict(read_json(fpath))
        check_same_plane(pt.frame, gframe, str(fpath))
        ref = read_image(gt / "maps" / f"{pid}.png")
        gmask = read_image(gt / "masks" / f"{pid}.png")[..., 0] > 0.5
        if ref.shape[:2] != gframe.shape:
            raise DifftexError(
                f"{gt / 'maps' / (pid + '.png')}: size differs from its frame {gframe.width}x{gframe.height}"
            )
        img = resample_texture(pt.texture, pt.frame, gframe)
        row = {
            "polygon_id": pid,
            "texels": int(gmask.sum()),
            "coverage": pt.report.get("coverage"),
            "frame": frame_offsets(pt.frame, gframe),
        }
        e = metrics.texel_error(img, ref)
        errs.append(e[gmask])
        sq += float(((img - ref)[gmask] ** 2).sum())
        n_tex += int(gmask.sum())
        pe = metrics.error_percentiles(img, ref, gmask)
        row.update(error90=pe[90.0], error95=pe[95.0], psnr=metrics.psnr(img, ref, gmask))
        row["ssim"] = metrics.ssim(img, ref, gmask) if min(gmask.shape) >= 11 else None
        # Sharpness against the ground truth's: below 1 blurred, above 1 noise or seams.
        pairs = bool((gmask[:, 1:] & gmask[:, :-1]).any() or (gmask[1:] & gmask[:-1]).any())
        g_ref = metrics.mean_gradient(ref, gmask) if pairs else 0.0
        row["sharpness"] = metrics.mean_gradient(img, gmask) / g_ref if g_ref > 0 else None
        # the ground truth's detail the texture reproduces (noise does not count, metrics.detail_gain)
        row["detail"] = metrics.detail_gain(img, ref, gmask) if g_ref > 0 else None
        if lp_variant and min(gmask.shape) >= metrics.LPIPS_MIN_SIDE:
            row["lpips"], lp_label = metrics.lpips(
                img, ref, gmask, variant=lp_variant, weights_dir=cfg.lpips_weights, device=cfg.device
            )
        else:
            row["lpips"] = None
        if error_dir is not None and cfg.error_maps:
            em = np.clip(e / math.sqrt(3.0) * 3.0, 0, 1)  # x3 so that typical errors are visible
            em[~gmask] = 0
            write_image(error_map_file(error_dir, pid), em)
        rows.append(row)
    if not rows:
        raise DifftexError(f"{gt}: no ground-truth frame matches a textured polygon")
    allerr = np.concatenate(errs)
    tot = float(sum(r["texels"] for r in rows))

    def wmean(key):
        vals = [(r[key], r["texels"]) for r in rows if r.get(key) is not None]
        return sum(v * n for v, n in vals) / sum(n for _, n in vals) if vals else None

    mse = sq / max(3 * n_tex, 1)
    overall = {
        "error90": float(np.percentile(allerr, 90)),
        "error95": float(np.percentile(allerr, 95)),
        "ssim": wmean("ssim"),
        "lpips": wmean("lpips"),
        "sharpness": wmean("sharpness"),
        "detail": wmean("detail"),
        "psnr": metrics.psnr_from_mse(mse),
        "lpips_variant": lp_label or "unavailable: no polygon has 32x32 ground-truth texels",
        "texels": int(tot),
        "polygons": len(rows),
        "aggregation": "Error percentiles over all ground-truth texels of all polygons; SSIM/LPIPS/sharpness "
        "texel-weighted means of the per-polygon values",
    }
    return {"overall": overall, "polygons": rows}


# --------------------------------------------------------------------------------------------
# Everything for one results folder


def evaluate_results(
    scene: str | Path,
    results: str | Path,
    cfg: EvaluateConfig = EvaluateConfig(),
    out_dir: str | Path | None = None,
    progress: bool = True,
) -> dict:
    """All applicable metrics of one results folder; images (error maps, renders) under ``out_dir``."""
    from difftex.scene.camera import load_photos
    from difftex.scene.files import read_json
    from difftex.scene.loading import load_scene

    t0 = time.perf_counter()
    scene, results = Path(scene), Path(results)
    out_dir = Path(out_dir) if out_dir is not None else None
    textures = load_textures(results)
    sc = load_scene(scene, check_images=False)
    methods = sorted({pt.report.get("method", "?") for pt in textures.values()})
    res: dict = {
        "scene": str(scene),
        "results": str(results),
        "method": methods[0] if len(methods) == 1 else methods,
        "config": cfg.__dict__,
        "textured_polygons": len(textures),
        "proxy_polygons": len(sc.proxy.polygons),
    }
    # Perspective quality: over the photos the scene copy had (they are the only possible sources).
    centres = {p.name: p.center for p in sc.photos}
    qrows = {}
    for pid, pt in textures.items():
        q = perspective_quality(pt, results, centres)
        if q is not None:
            qrows[pid] = q
    if qrows:
        n = {pid: q["q_texels"] for pid, q in qrows.items()}
        tot = sum(n.values())
        res["perspective"] = {
            "q_front": sum(q["q_front"] * n[p] for p, q in qrows.items()) / tot,
            "q_vc": sum(q["q_vc"] * n[p] for p, q in qrows.items()) / tot,
            "polygons": qrows,
            "aggregation": "texel-weighted mean over polygons",
        }
    if (scene / "ground_truth" / "frames").is_dir():
        res["maps"] = evaluate_maps(scene, textures, cfg, out_dir / ERROR_MAPS if out_dir else None, progress)
    if cfg.views:
        from difftex.evaluation.views import evaluate_views  # it imports this module's types

        hold = scene / "holdout.json"
        if hold.is_file() and read_json(hold)["held_out"]:
            info = read_json(hold)
            orig = load_scene(info["original_scene"], check_images=False)
            photos = [p for p in orig.photos if p.name in set(info["held_out"])]
            res["views"] = evaluate_views(
                photos, sc.proxy, textures, cfg, out_dir / VIEWS if out_dir else None, progress
            )
            res["views"]["held_out"] = info["held_out"]
        elif (scene / "ground_truth" / "views" / "sparse" / "0").is_dir():
            vdir = scene / "ground_truth" / "views"
            photos = load_photos(vdir / "sparse" / "0", vdir / "images")
            res["views"] = evaluate_views(
                photos, sc.proxy, textures, cfg, out_dir / VIEWS if out_dir else None, progress
            )
    res["time_s"] = time.perf_counter() - t0
    return res


def summary_line(res: dict) -> str:
    parts = [f"{res['textured_polygons']}/{res['proxy_polygons']} polygons textured"]
    if "maps" in res:
        o = res["maps"]["overall"]
        parts.append(
            f"maps: E90 {o['error90']:.4f} E95 {o['error95']:.4f} SSIM {o['ssim']:.4f} "
            f"LPIPS {o['lpips'] if o['lpips'] is None else round(o['lpips'], 4)} ({o['lpips_variant']})"
        )
    if "views" in res:
        o = res["views"]["overall"]
        if o["ssim"] is not None:
            parts.append(
                f"views ({o['views']}): SSIM {o['ssim']:.4f} PSNR {o['psnr']:.2f} "
                f"LPIPS {o['lpips'] if o['lpips'] is None else round(o['lpips'], 4)}"
            )
    if "perspective" in res:
        parts.append(f"Q_front {res['perspective']['q_front']:.4f} Q_vc {res['perspective']['q_vc']:.4f}")
    return "; ".join(parts)


def to_json(obj):
    return json.loads(json.dumps(obj, default=lambda o: o.tolist() if hasattr(o, "tolist") else str(o)))
