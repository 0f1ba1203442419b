"""How far selecting or blending the photos can go on a synthetic building: upper bounds, beside difftex.

    python evaluation/bounds.py --scene data/synth/paper/archive --density-scale 1.0 \
        --preset default --out evaluation/results/bounds_archive

Scores, in Table 1's scheme (each texture resampled to the ground-truth map and compared on its
texels: Error 95 % pooled over texels, SSIM and LPIPS texel-weighted over polygons), per polygon at the
frames of ``texture.density: auto`` x ``--density-scale``:

- ``ground truth at the texture's texel size``: the truth resampled to the texture's frame and
  back, what a texture that was exactly the truth at that texel size scores (the resolution
  ceiling; a texture can score slightly above it, as the round trip resamples twice).
- ``oracle, P x P patches``: per texel, the photo (through difftex's brightness transfers) whose
  P x P neighbourhood is closest to the truth (difftex.evaluation.oracle). A bound on what a
  per-patch selection of these photos can reach; at small P it also picks lucky noise.
- ``blend oracle, T x T tiles``: per T x T block, the convex blend of the photos closest to the
  truth (difftex.evaluation.oracle.blend_oracle): about what a blend with block-constant weights
  can reach. A blend beats selection by averaging noise; this measures how far that goes.
- ``average``: every photo that sees a texel, equal weights, the same transfers.
- ``MRF`` (``--mrf``): the LTBC-style baseline (difftex.evaluation.mrf), Table 1's best peer on
  LPIPS, on the same photos and frames, so the bounds and the target "LPIPS at most 0.8x the best
  peer's" are read in one run.
- ``difftex``: texture_polygon with the preset's ``optimize:`` section (``--preset none``: skip).

``--long-side L`` gives every map L texels on its long side, as Table 1's ``--long-side``.

Every photo that sees a polygon is a candidate (no photo filter, as evaluation/variants.py).
Writes <out>.json (per polygon too) and <out>.md.
"""

from __future__ import annotations

import argparse
import shlex
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from evaluation import common as C  # noqa: E402

MRF_ROW = C.LABELS["mrf"]  # Table 1's label of the same baseline


def candidates(photos, cfg):
    """(colours (K, 3, H, W), visible (K, H, W), cos (K, H, W), footprint (K, H, W), photo indices)
    of every photo that sees the polygon, at its frame, through the brightness transfers
    texture_polygon would estimate."""
    import torch

    from difftex.compose.texturing import polygon_transfers
    from difftex.sampling.photos import with_transfer

    transfers = polygon_transfers(photos, cfg)[2]
    cols, vis, cos, fp, ids = [], [], [], [], []
    for n in sorted(photos.samplers):
        mp = photos.map(n, photos.inp.frame, photos.inp.texel_mask)
        if mp is None:
            continue
        mp = with_transfer(mp, transfers[n] if transfers else None)
        cols.append(mp.colour)
        vis.append(mp.visible)
        cos.append(mp.cos)
        fp.append(torch.where(mp.visible, mp.footprint, torch.zeros_like(mp.footprint)))
        ids.append(n)
    return torch.stack(cols), torch.stack(vis), torch.stack(cos), torch.stack(fp), ids



def run(scene: Path, density_scale: float, max_long_side: int, preset: str, patches: list[int],
        polygons: list[str] | None, tiles: tuple[int, ...] = (), long_side: int | None = None,
        mrf: bool = False, lpips: bool = True) -> dict:
    import torch

    from difftex.compose.fill import finish_texture
    from difftex.compose.texturing import texture_polygon
    from difftex.evaluation import metrics
    from difftex.evaluation.evaluate import resample_texture
    from difftex.evaluation.mrf import MRFConfig, mrf_texture
    from difftex.evaluation.oracle import blend_oracle, blend_summary, patch_oracle, tail_causes
    from difftex.evaluation.results import EvaluateConfig, _lpips_plan
    from difftex.geometry.frames import UVFrame
    from difftex.method.config import ComputeConfig, OptimizeConfig
    from difftex.method.loop import photo_weight
    from difftex.sampling.photos import PhotoSet, polygon_input_from_visibility
    from difftex.scene.files import read_image, read_json

    torch.set_num_threads(1)
    cfg = OptimizeConfig.from_dict(C.base_config(None, preset if preset != "none" else "default")["optimize"])
    sc, vis = C.scene_polygons(scene, polygons, density_scale, max_long_side, long_side=long_side)
    by_name = {p.name: p for p in sc.photos}
    gt = scene / "ground_truth"
    names = ["ground truth at the texture's texel size", "average"] + [f"oracle, {p}x{p} patches" for p in patches]
    names += [f"blend oracle, {t}x{t} tiles" for t in tiles]
    if mrf:
        names.append(MRF_ROW)
    if preset != "none":
        names.append(f"difftex ({preset})")
    per: dict[str, list[dict]] = {n: [] for n in names}
    errs: dict[str, list[np.ndarray]] = {n: [] for n in names}
    tails: list[dict] = []
    # the network resolved once, as Table 1's evaluation does: one fallback note, not one per texture
    lp_kind = _lpips_plan(EvaluateConfig())[0] if lpips else None
    lp_label = "not computed"
    made_of: dict[str, list[tuple[dict, int]]] = {}  # row -> per polygon (blend_summary, texels)
    for v in vis:
        t0 = time.perf_counter()
        inp = polygon_input_from_visibility(v, by_name, up=sc.up)
        gframe = UVFrame.from_dict(read_json(gt / "frames" / f"{v.polygon_id}.json"))
        ref = read_image(gt / "maps" / f"{v.polygon_id}.png")
        gmask = read_image(gt / "masks" / f"{v.polygon_id}.png")[..., 0] > 0.5
        ref_here = resample_texture(ref, gframe, v.frame)
        maps = {names[0]: ref_here}
        if preset != "none":
            tp = texture_polygon(inp, cfg, ComputeConfig(device="cpu"))
            maps[f"difftex ({preset})"] = tp.texture
        photos = PhotoSet.load(inp, torch.device("cpu"), supersample=cfg.supersample)
        cols, seen, cos, fp, ids = candidates(photos, cfg)
        mask_t = torch.from_numpy(inp.texel_mask)

        def made(name, weights, cos=cos, fp=fp, mask_t=mask_t):
            s = blend_summary(weights, mask_t, {"cos": cos, "texel_px": fp})
            made_of.setdefault(name, []).append((s, int((mask_t & (weights.sum(0) > 0)).sum())))

        if preset != "none":
            made(f"difftex ({preset})", torch.from_numpy(np.stack([photo_weight(tp.idx, tp.W, n) for n in ids])))
            del tp
        wsum = seen.sum(0).float()
        avg = (cols * seen[:, None]).sum(0) / wsum.clamp_min(1)
        maps["average"] = finish_texture(avg.permute(1, 2, 0).numpy(), wsum.numpy(), inp.texel_mask)[0]
        ref_t = torch.from_numpy(np.ascontiguousarray(ref_here.transpose(2, 0, 1)))
        for p in patches:
            t, _ = patch_oracle(cols, seen, ref_t, p)
            t = t.permute(1, 2, 0).numpy()
            maps[f"oracle, {p}x{p} patches"] = finish_texture(t, wsum.numpy(), inp.texel_mask)[0]
        for t in tiles:
            b, share = blend_oracle(cols, seen, ref_t, t)
            maps[f"blend oracle, {t}x{t} tiles"] = finish_texture(b.permute(1, 2, 0).numpy(), wsum.numpy(),
                                                                  inp.texel_mask)[0]
            made(f"blend oracle, {t}x{t} tiles", share)
            del share
        if mrf:  # the best peer on LPIPS in Table 1, on the same photos and frame
            U, mw = mrf_texture(inp, MRFConfig(supersample=cfg.supersample))[:2]
            maps[MRF_ROW] = finish_texture(U, mw, inp.texel_mask)[0]
        made("average", seen.float())
        if preset != "none":  # why difftex's worst texels are wrong, at its own frame
            tex_t = torch.from_numpy(np.ascontiguousarray(maps[f"difftex ({preset})"].transpose(2, 0, 1)))
            tails.append(tail_causes(cols, seen, cos, ref_t, tex_t, torch.from_numpy(inp.texel_mask)))
            tails[-1]["polygon_id"] = v.polygon_id
        del cols, seen, cos, fp
        for name, img in maps.items():
            out = resample_texture(img, v.frame, gframe)
            e = metrics.texel_error(out, ref)[gmask]
            errs[name].append(e)
            lp = None
            if lp_kind and min(gmask.shape) >= metrics.LPIPS_MIN_SIDE:
                lp, lp_label = metrics.lpips(out, ref, gmask, variant=lp_kind)
            per[name].append({
                "polygon_id": v.polygon_id, "texels": int(gmask.sum()), "frame": list(v.frame.shape),
                "error95": float(np.percentile(e, 95)), "ssim": metrics.ssim(out, ref, gmask), "lpips": lp,
            })
        short = {names[0]: "truth", **{f"oracle, {p}x{p} patches": f"oracle {p}x{p}" for p in patches},
                 **{f"blend oracle, {t}x{t} tiles": f"blend {t}x{t}" for t in tiles}}
        print(f"{scene.name} {v.polygon_id} {v.frame.width}x{v.frame.height} texels, {len(photos.samplers)} photos, "
              "SSIM: " + ", ".join(f"{short.get(n, n)} {per[n][-1]['ssim']:.3f}" for n in names)
              + f" ({time.perf_counter() - t0:.0f} s)", flush=True)
    rows = {}
    for n in names:
        w = np.array([r["texels"] for r in per[n]], float)
        lw = [(r["lpips"], r["texels"]) for r in per[n] if r["lpips"] is not None]
        rows[n] = {
            "error95": float(np.percentile(np.concatenate(errs[n]), 95)),
            "ssim": float((np.array([r["ssim"] for r in per[n]]) * w).sum() / w.sum()),
            "lpips": sum(x * t for x, t in lw) / sum(t for _, t in lw) if lw else None,
            "polygons": per[n],
        }
        if n in made_of:  # what the blend is made of, texel-weighted over polygons
            tot = sum(b for _, b in made_of[n])
            rows[n]["made_of"] = {k: sum(s[k] * b for s, b in made_of[n]) / max(1, tot) for k in made_of[n][0][0]}
    return {"scene": str(scene), "polygons": [v.polygon_id for v in vis], "rows": rows, "difftex_tail": tails,
            "lpips_variant": lp_label}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", required=True, type=Path)
    ap.add_argument("--density-scale", type=float, default=1.0)
    ap.add_argument("--max-long-side", type=int, default=2048)
    ap.add_argument("--long-side", type=int, help="every map this many texels long, as Table 1's --long-side "
                    "(instead of density auto)")
    ap.add_argument("--mrf", action="store_true", help="add the MRF baseline's row (Table 1's best peer on LPIPS)")
    ap.add_argument("--no-lpips", action="store_true", help="skip the LPIPS column")
    ap.add_argument(
        "--preset", default="default", help="difftex's preset for its row (default: config.yaml; none: no row)"
    )
    ap.add_argument("--patches", default="5,15,31", help="oracle patch sides, odd, comma-separated")
    ap.add_argument("--blend-tiles", default="15", help="blend oracle tile sides, comma-separated (empty: none)")
    ap.add_argument("--polygons", default="all", help="comma-separated polygon ids, or all")
    ap.add_argument("--out", required=True)
    args = ap.parse_args(argv)
    t_all = time.perf_counter()
    patches = [int(p) for p in args.patches.split(",")]
    tiles = tuple(int(t) for t in args.blend_tiles.split(",") if t.strip())
    res = run(args.scene, args.density_scale, args.max_long_side, args.preset, patches, C.polygon_ids(args.polygons),
              tiles, long_side=args.long_side, mrf=args.mrf, lpips=not args.no_lpips)
    mach = C.machine()
    lines = [
        C.header(
            f"Upper bounds of photo selection and blending on {args.scene.name}",
            "python evaluation/bounds.py " + shlex.join(sys.argv[1:] if argv is None else argv),
            mach,
            [
                f"Polygons {', '.join(res['polygons'])}; "
                + (f"every map {args.long_side} texels long (Table 1's --long-side)" if args.long_side else
                   f"frames of `density: auto` x {args.density_scale} (max long side {args.max_long_side})")
                + "; every photo that sees a polygon is a candidate, through the brightness transfers difftex "
                "estimates (MRF: the photos as they are, as in Table 1).",
                "Scored as Table 1: textures resampled to the ground-truth maps, Error 95 % pooled over their "
                f"texels, SSIM and LPIPS ({res['lpips_variant']}) texel-weighted over polygons.",
                "The oracle rows choose photos with the ground truth in hand (difftex.evaluation.oracle): no "
                "method that selects among these photos at that patch size scores better. At 5x5 it also picks "
                "each patch's luckiest noise. The blend oracle fits each tile's convex weights to the truth: "
                "about the most a blend with tile-constant weights reaches.",
                "What each blend is made of (difftex.evaluation.oracle.blend_summary; difftex: its final "
                "weights, the blend oracle its tiles' weights, the average equal weights), mean over the "
                "textured texels: photos per texel 1 / sum W^2; frontality, the weighted cosine between the "
                "view and the normal (Q_a); texel (px), the weighted size of a texel in the photos' pixels "
                "(larger: the photos hold more detail there).",
            ],
        ),
        "| texture | Error 95 % | SSIM | LPIPS | photos per texel | frontality | texel (px) | SSIM per polygon |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for n, r in res["rows"].items():
        pp = ", ".join(f"{p['polygon_id']} {p['ssim']:.3f}" for p in r["polygons"])
        mo = r.get("made_of")
        made = f"{mo['photos_per_texel']:.1f} | {mo['cos']:.3f} | {mo['texel_px']:.2f}" if mo else " | | "
        lp = "n/a" if r["lpips"] is None else f"{r['lpips']:.4f}"
        lines.append(f"| {n} | {r['error95']:.4f} | {r['ssim']:.4f} | {lp} | {made} | {pp} |")
    if res["difftex_tail"]:
        lines += [
            "",
            "difftex's worst texels (at or above its Error 95 %, per polygon at its own frame; "
            "difftex.evaluation.oracle.tail_causes): share where the median photo is further from the truth "
            "than that, where no photo is within 0.15 of it (mean over 5x5 texels: shadows of occluders the "
            "truth lacks, relief every photo sees), where one of the 3 most frontal photos is.",
            "",
            "| polygon | Error 95 % | median photo worse | no photo right | a frontal photo right |",
            "|---|---|---|---|---|",
        ]
        for t in res["difftex_tail"]:
            lines.append(f"| {t['polygon_id']} | {t['error95']:.4f} | {t['median_photo_worse']:.2f} | "
                         f"{t['no_photo_right']:.2f} | {t['frontal_right']:.2f} |")
    lines += ["", f"Whole command: {time.perf_counter() - t_all:.0f} s."]
    data = {"machine": mach, "args": vars(args) | {"scene": str(args.scene)}, **res}
    C.write_outputs(Path(args.out), "\n".join(lines) + "\n", data)
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    C.run_script(main)
