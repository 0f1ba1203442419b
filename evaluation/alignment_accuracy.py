"""How far each photo's mapping is from its true pose's, before and after alignment refinement.

    python evaluation/alignment_accuracy.py --scene data/synth/survey/gable \
        --results evaluation/out/table1_survey_gable/difftex --out evaluation/results/alignment_accuracy_gable

`difftex synth` writes each photo's pose with about a pixel of noise and keeps the pose it was
rendered at in synth.json. For every polygon of a finished run (its visibility files and
optimized/<polygon>/stats.json, whose ``corrections`` are the alignment's per-photo affine
corrections in pixels) this measures, per candidate photo, the mean distance in pixels over the
texels the photo sees between where the texels land with the written pose (as given, and with
the correction applied) and where they land with the true pose. The texture is made of the
photos that hold weight, so the summary also weighs each photo by its share of the final blend
weights W (weights.npz). A yardstick for the alignment alone, faster than a table: Table 1 says
whether the texture gained, this says whether the registration did, photo by photo.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from evaluation import common as C  # noqa: E402

MAX_TEXELS = 20000  # per photo, a strided subset of the texels it sees


def true_photos(scene: Path, photos: dict) -> tuple[dict, dict]:
    """The scene's photos by name with their true poses (synth.json ``R_true``, ``t_true``), and
    each view's kind (drone, street) by name."""
    from difftex.errors import DifftexError

    meta_path = scene / "synth.json"
    if not meta_path.is_file():
        raise DifftexError(f"{meta_path}: missing (a difftex synth scene, which keeps the true poses, is needed)")
    views = {v["name"]: v for v in json.loads(meta_path.read_text())["views"] if "R_true" in v}
    if not set(views) & set(photos):
        raise DifftexError(f"{meta_path}: none of its views is a photo of the scene's model")
    out = {}
    for name, ph in photos.items():
        if name in views:
            R = np.asarray(views[name]["R_true"], np.float64)
            out[name] = dataclasses.replace(ph, R=R, t=np.asarray(views[name]["t_true"], np.float64))
    return out, {n: v.get("kind", "") for n, v in views.items()}


def photo_error(frame, given, true, visible: np.ndarray, corr: dict | None) -> tuple[float, float, float]:
    """Mean pixel distance to the true mapping over ``visible`` texels, as written and corrected,
    and the photo's mean pixels per texel there (a misregistration of p pixels blurs the texture
    by p / that many texels)."""
    import torch

    from difftex.geometry.frames import texel_to_pixel
    from difftex.sampling.photos import Correction
    from difftex.sampling.texels import texel_map

    ty, tx = np.nonzero(visible)
    step = max(1, math.ceil(len(tx) / MAX_TEXELS))
    ty, tx = ty[::step], tx[::step]
    pg, _ = texel_to_pixel(frame, given, tx + 0.5, ty + 0.5)
    pt, _ = texel_to_pixel(frame, true, tx + 0.5, ty + 0.5)
    # the texel's footprint in the true photo, as the sampling uses it, over the visible box only
    y0, x0 = int(ty.min()), int(tx.min())
    fp = texel_map(frame, true, "cpu", (y0, int(ty.max()) + 1, x0, int(tx.max()) + 1)).footprint.numpy()
    per_texel = float(fp[ty - y0, tx - x0].mean())
    # texels projected behind a camera (not finite) are left out of the means
    before = float(np.nanmean(np.linalg.norm(pg - pt, axis=1)))
    if corr is None:
        return before, before, per_texel
    c = Correction(torch.tensor(corr["params"], dtype=torch.float64), tuple(corr["centre"]), corr["scale"])
    pc = c.apply(torch.from_numpy(pg)).numpy()
    return before, float(np.nanmean(np.linalg.norm(pc - pt, axis=1))), per_texel


def weight_shares(path: Path) -> dict[str, float]:
    """Each photo's share of the polygon's blend weights W (weights.npz)."""
    z = np.load(path)
    idx, W = z["idx"].astype(np.int64), z["W"].astype(np.float64)
    ok = idx >= 0
    total = np.bincount(idx[ok], W[ok], minlength=len(z["photos"]))
    return {str(n): float(w / max(total.sum(), 1e-12)) for n, w in zip(z["photos"], total)}


def polygon_rows(results: Path, pid: str, photos: dict, true: dict, kinds: dict) -> list[dict]:
    from difftex.errors import DifftexError
    from difftex.geometry.visibility import load_visibility
    from difftex.sampling.crops import polygon_input_from_visibility

    vis = results / "visibility" / f"{pid}.npz"
    if not vis.is_file() and (results / "visibility.txt").is_file():  # an evaluation script's run folder
        vis = Path((results / "visibility.txt").read_text().strip()) / f"{pid}.npz"
    opt = results / "optimized" / pid
    for need in (vis, opt / "stats.json", opt / "weights.npz"):
        if not need.is_file():
            raise DifftexError(f"{need}: missing (polygon '{pid}' of a finished run is needed)")
    inp = polygon_input_from_visibility(load_visibility(vis), photos)
    stats = json.loads((opt / "stats.json").read_text())
    shares = weight_shares(opt / "weights.npz")
    rows = []
    for k, ph in enumerate(inp.photos):
        if ph.name not in true or ph.name not in stats.get("photos_seeing", [ph.name]):
            continue
        visible = inp.texel_visible[k] & inp.texel_mask
        if visible.sum() < 16:
            continue
        corr = stats.get("corrections", {}).get(ph.name)
        before, after, per_texel = photo_error(inp.frame, ph, true[ph.name], visible, corr)
        rows.append({"polygon": pid, "photo": ph.name, "kind": kinds.get(ph.name, ""), "corrected": corr is not None,
                     "before_px": round(before, 3), "after_px": round(after, 3), "px_per_texel": round(per_texel, 3),
                     "weight_share": round(shares.get(ph.name, 0.0), 4)})
    return rows


def summary(rows: list[dict]) -> dict:
    """Medians, W-weighted means and how many photos got closer, over ``rows``."""
    if not rows:
        return {}
    b, a = np.array([r["before_px"] for r in rows]), np.array([r["after_px"] for r in rows])
    w = np.array([r["weight_share"] for r in rows])
    ppt = np.array([r["px_per_texel"] for r in rows])
    wsum = max(w.sum(), 1e-12)
    return {"photos": len(rows), "median_before": float(np.median(b)), "median_after": float(np.median(a)),
            "weighted_before_texels": float((w * b / ppt).sum() / wsum),
            "weighted_after_texels": float((w * a / ppt).sum() / wsum),
            "closer": int((a < b).sum()), "worse_by_0.5px": int((a > b + 0.5).sum())}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", required=True, type=Path, help="a difftex synth scene (synth.json holds the true poses)")
    ap.add_argument("--results", required=True, type=Path, help="a run's results folder (optimized/, visibility/)")
    ap.add_argument("--polygons", default="all", help="comma-separated ids, or all")
    ap.add_argument("--out", required=True, help="output stem (.md, .json)")
    a = ap.parse_args(argv)
    from difftex.errors import DifftexError
    from difftex.scene.loading import load_scene

    t0 = time.perf_counter()
    if not (a.results / "optimized").is_dir():
        raise DifftexError(f"{a.results}: no optimized/ folder (a finished run's results are needed)")
    photos = {p.name: p for p in load_scene(a.scene, check_images=False).photos}
    true, kinds = true_photos(a.scene, photos)
    pids = C.polygon_ids(a.polygons) or sorted(
        p.name for p in (a.results / "optimized").iterdir() if (p / "stats.json").is_file()  # not the jobs/ lists
    )
    rows = [r for pid in pids for r in polygon_rows(a.results, pid, photos, true, kinds)]
    kinds_seen = sorted({r["kind"] for r in rows})
    groups = {"all": rows, **{f"kind {k}": [r for r in rows if r["kind"] == k] for k in kinds_seen}}
    groups.update({f"polygon {p}": [r for r in rows if r["polygon"] == p] for p in pids})
    mach = C.machine()
    lines = [C.header("Registration against the true poses, before and after alignment", "python evaluation/"
                      "alignment_accuracy.py " + " ".join(argv if argv is not None else sys.argv[1:]), mach, [
        "Per photo and polygon: the mean distance (pixels) over the texels the photo sees between the written "
        "pose's mapping (before; after: with the run's alignment correction) and the true pose's.",
        "W-weighted: in texels (each photo's pixels over its pixels per texel there), each photo weighed by its "
        "share of the polygon's final blend weights W: the misregistration of the photos the texture is made of. "
        "After alignment it includes the shift of every photo together, which aligning photos to each other "
        "cannot see.",
    ]).rstrip("\n"), "", "| photos | n | median before (px) | median after (px) | W-weighted before (texels) | "
        "W-weighted after (texels) | closer | worse by > 0.5 px |", "|---|---|---|---|---|---|---|---|"]
    out = {}
    for name, rs in groups.items():
        s = summary(rs)
        if not s:
            continue
        out[name] = s
        lines.append(f"| {name} | {s['photos']} | {s['median_before']:.3f} | {s['median_after']:.3f} | "
                     f"{s['weighted_before_texels']:.3f} | {s['weighted_after_texels']:.3f} | {s['closer']} | "
                     f"{s['worse_by_0.5px']} |")
    worst = sorted(rows, key=lambda r: r["after_px"] - r["before_px"], reverse=True)[:8]
    lines += ["", "Photos the alignment moved furthest from their true pose:", "",
              "| polygon | photo | kind | before (px) | after (px) | pixels per texel | W share |",
              "|---|---|---|---|---|---|---|"]
    lines += [f"| {r['polygon']} | {r['photo']} | {r['kind']} | {r['before_px']} | {r['after_px']} | "
              f"{r['px_per_texel']} | {r['weight_share']} |" for r in worst]
    md = "\n".join(lines) + f"\n\nWhole command: {time.perf_counter() - t0:.0f} s.\n"
    C.write_outputs(Path(a.out), md, {"machine": mach, "args": vars(a), "summary": out, "rows": rows})
    print(md)
    return 0


if __name__ == "__main__":
    C.run_script(main)
