"""How far selecting or blending the photos can go on a synthetic building: upper bounds, beside difftex.

    python evaluation/bounds.py --scene data/synth/paper/archive --density-scale 1.0 \
        --preset default --out evaluation/results/bounds_archive

Scores, in Table 1's scheme (each texture resampled to the ground-truth map and compared on its
texels: Error 95 % pooled over texels, SSIM texel-weighted over polygons), per polygon at the
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
- ``difftex``: texture_polygon with the preset's ``optimize:`` section (``--preset none``: skip).

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
        polygons: list[str] | None, tiles: tuple[int, ...] = ()) -> dict:
    import torch

    from difftex.compose.fill import finish_texture
    from difftex.compose.texturing import texture_polygon
    from difftex.evaluation import metrics
    from difftex.evaluation.evaluate import resample_texture
    from difftex.evaluation.oracle import blend_oracle, blend_summary, patch_oracle, tail_causes
    from difftex.geometry.frames import UVFrame
    from difftex.method.config import ComputeConfig, OptimizeConfig
    from difftex.method.loop import photo_weight
    from difftex.sampling.photos import PhotoSet, polygon_input_from_visibility
    from difftex.scene.files import read_image, read_json

    torch.set_num_threads(1)
    cfg = OptimizeConfig.from_dict(C.base_config(None, preset if preset != "none" else "default")["optimize"])
    sc, vis = C.scene_polygons(scene, polygons, density_scale, max_long_side)
    by_name = {p.name: p for p in sc.photos}
    gt = scene / "ground_truth"
    names = ["ground truth at the texture's texel size", "average"] + [f"oracle, {p}x{p} patches" for p in patches]
    names += [f"blend oracle, {t}x{t} tiles" for t in tiles]
    if preset != "none":
        names.append(f"difftex ({preset})")
    per: dict[str, list[dict]] = {n: [] for n in names}
    errs: dict[str, list[np.ndarray]] = {n: [] for n in names}
    tails: list[dict] = []
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
            per[name].append({
                "polygon_id": v.polygon_id, "texels": int(gmask.sum()), "frame": list(v.frame.shape),
                "error95": float(np.percentile(e, 95)), "ssim": metrics.ssim(out, ref, gmask),
            })
        short = {names[0]: "truth", **{f"oracle, {p}x{p} patches": f"oracle {p}x{p}" for p in patches},
                 **{f"blend oracle, {t}x{t} tiles": f"blend {t}x{t}" for t in tiles}}
        print(f"{scene.name} {v.polygon_id} {v.frame.width}x{v.frame.height} texels, {len(photos.samplers)} photos, "
              "SSIM: " + ", ".join(f"{short.get(n, n)} {per[n][-1]['ssim']:.3f}" for n in names)
              + f" ({time.perf_counter() - t0:.0f} s)", flush=True)
    rows = {}
    for n in names:
        w = np.array([r["texels"] for r in per[n]], float)
        rows[n] = {
            "error95": float(np.percentile(np.concatenate(errs[n]), 95)),
            "ssim": float((np.array([r["ssim"] for r in per[n]]) * w).sum() / w.sum()),
            "polygons": per[n],
        }
        if n in made_of:  # what the blend is made of, texel-weighted over polygons
            tot = sum(b for _, b in made_of[n])
            rows[n]["made_of"] = {k: sum(s[k] * b for s, b in made_of[n]) / max(1, tot) for k in made_of[n][0][0]}
    return {"scene": str(scene), "polygons": [v.polygon_id for v in vis], "rows": rows, "difftex_tail": tails}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", required=True, type=Path)
    ap.add_argument("--density-scale", type=float, default=1.0)
    ap.add_argument("--max-long-side", type=int, default=2048)
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
              tiles)
    mach = C.machine()
    lines = [
        C.header(
            f"Upper bounds of photo selection and blending on {args.scene.name}",
            "python evaluation/bounds.py " + shlex.join(sys.argv[1:] if argv is None else argv),
            mach,
            [
                f"Polygons {', '.join(res['polygons'])}; frames of `density: auto` x {args.density_scale} "
                f"(max long side {args.max_long_side}); every photo that sees a polygon is a candidate, through "
                "the brightness transfers difftex estimates.",
                "Scored as Table 1: textures resampled to the ground-truth maps, Error 95 % pooled over their "
                "texels, SSIM texel-weighted over polygons.",
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
        "| texture | Error 95 % | SSIM | photos per texel | frontality | texel (px) | SSIM per polygon |",
        "|---|---|---|---|---|---|---|",
    ]
    for n, r in res["rows"].items():
        pp = ", ".join(f"{p['polygon_id']} {p['ssim']:.3f}" for p in r["polygons"])
        mo = r.get("made_of")
        made = f"{mo['photos_per_texel']:.1f} | {mo['cos']:.3f} | {mo['texel_px']:.2f}" if mo else " | | "
        lines.append(f"| {n} | {r['error95']:.4f} | {r['ssim']:.4f} | {made} | {pp} |")
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
