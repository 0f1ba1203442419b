"""Optimizer variants on a synthetic building against its ground truth, polygon by polygon, in-process.

    python evaluation/variants.py --scene data/synth/paper/archive --density-scale 0.5 \
        --max-long-side 2048 --out evaluation/results/variants_archive \
        --variants '{"defaults": {}, "raw": {"render_units": "raw"}, "average": null}'

For choosing the optimizer's defaults with evidence: every variant (a dict of ``optimize:``
overrides; null for the plain per-texel average; ``{"baseline": "average" | "frontal",
"supersample": S}`` for a baseline with that photo sampling) textures every polygon from the same
visibility (``texture.density: auto`` at ``--density-scale``), and is scored against the
ground-truth ortho map resampled to the texture's frame: Error 90/95 % and SSIM over the
polygon's texels (difftex.metrics), sharpness = mean colour gradient magnitude over the ground
truth's, detail = the share of the ground truth's gradients reproduced (metrics.detail_gain), LPIPS
(metrics.lpips: piq's classic LPIPS where its weights are on disk, else ST-LPIPS, named in the table),
and the effective number of photos per texel 1 / sum W^2 (mean over texels). Same metric code
as the tables; no held-out views, no assembly. Writes <out>.json and <out>.md.
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from evaluation import common as C  # noqa: E402


def run(
    scene: Path,
    density_scale: float,
    max_long_side: int,
    variants: dict,
    polygons: list[str] | None,
    texel_candidates: int | None = None,
    textures: Path | None = None,
) -> dict:
    import torch

    from difftex.compose.fill import finish_texture
    from difftex.compose.texturing import texture_polygon
    from difftex.evaluation import metrics
    from difftex.evaluation.baselines import baseline_texture
    from difftex.evaluation.evaluate import resample_texture
    from difftex.evaluation.results import EvaluateConfig, _lpips_plan
    from difftex.geometry.frames import UVFrame
    from difftex.method.config import ComputeConfig, OptimizeConfig
    from difftex.sampling import SUPERSAMPLE
    from difftex.sampling.photos import polygon_input_from_visibility
    from difftex.scene.files import read_image, read_json, write_image

    torch.set_num_threads(1)
    # the network resolved once, as Table 1's evaluation does: one fallback note, not one per texture
    lp_kind, lpips_label = _lpips_plan(EvaluateConfig())
    sc, vis = C.scene_polygons(scene, polygons, density_scale, max_long_side, texel_candidates)
    by_name = {p.name: p for p in sc.photos}
    gt = scene / "ground_truth"
    out = {}
    for name, overrides in variants.items():
        errs, ssims, weights, sharp, gsharp, detail, neff, seconds = [], [], [], [], [], [], [], 0.0
        lps: list[float] = []
        for v in vis:
            inp = polygon_input_from_visibility(v, by_name, up=sc.up)
            t0 = time.perf_counter()
            if overrides is None or "baseline" in overrides:
                base = overrides or {}
                U, wsum, _, _ = baseline_texture(
                    inp, base.get("baseline", "average"), "cpu", int(base.get("supersample", SUPERSAMPLE))
                )
                U, _ = finish_texture(U, wsum, inp.texel_mask)
            else:
                tp = texture_polygon(inp, OptimizeConfig(**overrides), ComputeConfig(device="cpu"))
                U = tp.texture
                m = inp.texel_mask & (tp.W.sum(0) > 0)
                neff.append((1.0 / np.maximum((tp.W**2).sum(0), 1e-9))[m])
            seconds += time.perf_counter() - t0
            frame = UVFrame.from_dict(read_json(gt / "frames" / f"{v.polygon_id}.json"))
            ref = resample_texture(read_image(gt / "maps" / f"{v.polygon_id}.png"), frame, v.frame)
            if textures is not None:  # for a person to look at, next to the ground truth in the same frame
                for d in (textures / _slug(name), textures / "ground_truth"):
                    d.mkdir(parents=True, exist_ok=True)
                write_image(textures / _slug(name) / f"{v.polygon_id}.png", U)
                write_image(textures / "ground_truth" / f"{v.polygon_id}.png", ref)
            mk = inp.texel_mask
            errs.append(metrics.texel_error(U, ref)[mk])
            ssims.append(metrics.ssim(U, ref, mk))
            lp = None
            if lp_kind:
                lp, lpips_label = metrics.lpips(np.clip(U, 0, 1), ref, mk, variant=lp_kind)
            lps.append(float("nan") if lp is None else lp)
            weights.append(float(mk.sum()))
            sharp.append(metrics.mean_gradient(U, mk))
            gsharp.append(metrics.mean_gradient(ref, mk))
            detail.append(metrics.detail_gain(U, ref, mk))
        e, w = np.concatenate(errs), np.asarray(weights)
        out[name] = {
            "overrides": overrides,
            "e90": float(np.percentile(e, 90)),
            "e95": float(np.percentile(e, 95)),
            "ssim": float((np.asarray(ssims) * w).sum() / w.sum()),
            "lpips": float((np.asarray(lps) * w).sum() / w.sum()),
            "lpips_variant": lpips_label,
            "sharpness_vs_gt": float((np.asarray(sharp) * w).sum() / (np.asarray(gsharp) * w).sum()),
            "detail_vs_gt": float((np.asarray(detail) * w).sum() / w.sum()),
            "effective_photos": float(np.concatenate(neff).mean()) if neff else None,
            "seconds": seconds,
        }
        r = out[name]
        print(
            f"{scene.name} {name:14s} E90 {r['e90']:.4f} E95 {r['e95']:.4f} SSIM {r['ssim']:.4f} "
            f"LPIPS {r['lpips']:.4f} "
            f"sharpness/gt {r['sharpness_vs_gt']:.3f} detail/gt {r['detail_vs_gt']:.3f} "
            f"photos/texel {r['effective_photos']} {seconds:.0f}s",
            flush=True,
        )
    return {
        "scene": str(scene),
        "polygons": [v.polygon_id for v in vis],
        "texels": int(sum(v.texel_mask.sum() for v in vis)),
        "variants": out,
    }


def _slug(name: str) -> str:
    """A variant's name as a folder name."""
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in name).strip("_") or "variant"


def main(argv=None, command: str | None = None) -> int:
    """``command``: the command line the results file records (default: this script's own)."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", required=True, type=Path)
    ap.add_argument("--density-scale", type=float, default=0.5)
    ap.add_argument("--max-long-side", type=int, default=2048)
    ap.add_argument("--variants", required=True, help="JSON: name -> optimize overrides, or null for the plain average")
    ap.add_argument("--polygons", help="comma-separated polygon ids (default: all)")
    ap.add_argument(
        "--texel-candidates", type=int, help="visibility.texel_candidates (default: every photo that sees a polygon)"
    )
    ap.add_argument("--textures", type=Path, help="also write every variant's textures (and the ground truth, "
                    "resampled to the same frames) as <textures>/<variant>/<polygon>.png")
    ap.add_argument("--out", required=True)
    args = ap.parse_args(argv)
    res = run(
        args.scene,
        args.density_scale,
        args.max_long_side,
        json.loads(args.variants),
        C.polygon_ids(args.polygons) if args.polygons else None,
        args.texel_candidates,
        args.textures,
    )
    mach = C.machine()
    lines = [
        C.header(
            f"Optimizer variants on {args.scene.name}",
            command or "python evaluation/variants.py " + shlex.join(sys.argv[1:] if argv is None else argv),
            mach,
            [
                f"density auto x {args.density_scale} (max {args.max_long_side}), "
                f"visibility.texel_candidates {args.texel_candidates}, "
                f"polygons {', '.join(res['polygons'])}, "
                f"{res['texels']} texels; metrics against the ground-truth maps at each texture's resolution."
            ],
        ),
        f"LPIPS: {next(iter(res['variants'].values()))['lpips_variant']} (mean over the polygons, by texels).",
        "",
        "| variant | overrides | Error 90 % | Error 95 % | SSIM | LPIPS | sharpness / GT | detail / GT | "
        "photos per texel | seconds |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for name, r in res["variants"].items():
        neff = f"{r['effective_photos']:.1f}" if r["effective_photos"] is not None else "(blend of all)"
        lines.append(
            f"| {name} | `{json.dumps(r['overrides'])}` | {r['e90']:.4f} | {r['e95']:.4f} | {r['ssim']:.4f} | "
            f"{r['lpips']:.4f} | "
            f"{r['sharpness_vs_gt']:.3f} | {r['detail_vs_gt']:.3f} | {neff} | {r['seconds']:.0f} |"
        )
    C.write_outputs(
        Path(args.out),
        "\n".join(lines) + "\n",
        {"machine": mach, "args": vars(args) | {"scene": str(args.scene)}, **res},
    )
    return 0


if __name__ == "__main__":
    C.run_script(main)
