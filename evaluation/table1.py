"""Table 1 (synthetic scenes): Error 90/95, SSIM, LPIPS and time of difftex and the baselines.

    python evaluation/table1.py                       # tiny synthetic building, preset fast (density auto)
    python evaluation/table1.py --preset balanced --scene data/synth/paper/archive
    python evaluation/table1.py --long-side 512       # every method, every polygon: 512 texels long side

Generates the scene with `difftex synth --preset tiny` when it is missing, runs the photo filter
and visibility once, textures every polygon with each method from the same visibility files,
scores each with `difftex evaluate` against the ground-truth maps (resampled to their size) and
the occluder-free held-out views, and writes evaluation/results/table1.{md,json} plus an HTML
report per method and a comparison page under the work folder.
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from evaluation import common as C  # noqa: E402
from evaluation import peers as P  # noqa: E402


def ensure_synth(scene: Path, preset: str = "tiny") -> float | None:
    if (scene / "ground_truth" / "frames").is_dir() and (scene / "proxy.obj").is_file():
        return None
    return C.difftex("synth", "--preset", preset, "--out", scene, "--quiet")


def relief_row(method: str, scene: Path, work: Path, common: dict) -> dict:
    """difftex mapped through a height field: measured from the scene's dense geometry
    (difftex-dense; its heights stage's time counted) or the synthetic building's true one
    (difftex-true-relief). {"missing": why} where the scene has no such field."""
    if method == "difftex-dense":
        heights, t_heights = C.run_heights(scene, work / "dense-heights", common)
        if heights is None:
            return {"missing": f"{scene} has no dense/ geometry (difftex synth-dense --scene {scene})"}
    else:
        from evaluation.relief_bound import write_true_heights

        heights, t_heights = write_true_heights(scene, common["visibility"], work / "true-heights"), 0.0
    r = C.run_method("difftex", scene, work / method, common, heights=heights)
    r["heights_s"] = t_heights
    r["total_s"] += t_heights
    return r


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="evaluation/out/scenes/tiny", help="synthetic scene (generated if missing)")
    ap.add_argument(
        "--long-side",
        type=int,
        default=None,
        help="texture long side of every polygon and method (default: the preset's density, auto)",
    )
    ap.add_argument(
        "--preset", default="fast", help="difftex preset (config/presets/<name>.yaml; default: the workflow defaults)"
    )
    ap.add_argument(
        "--methods", default="difftex,difftex-dense,difftex-true-relief,difftex-paper,average,frontal,mrf,texrecon,"
        "meshlab-face,meshlab-blend,reprojection",
        help="difftex-paper: preset paper's optimize section (the published method) at the same texel sizes; "
        "difftex-dense: the heights stage on the scene's dense/ geometry first (not run without it); "
        "difftex-true-relief: mapped through the synthetic building's true relief (the bound); "
        "reprojection: texrecon on the scene's dense mesh (dense/), baked onto the proxy (not run without one)",
    )
    ap.add_argument("--optimize", default=None, help="JSON of optimize: overrides (ablations)")
    C.add_table_args(ap, "table1")
    args = ap.parse_args(argv)

    import torch

    torch.set_num_threads(args.threads)
    t_all = time.perf_counter()
    scene, work = Path(args.scene), Path(args.work)
    t_synth = ensure_synth(scene)
    cfg = C.base_config(args.long_side, args.preset, {"optimize": json.loads(args.optimize)} if args.optimize else None)
    common = C.run_common(scene, work, cfg)
    rows = []
    skipped = []
    for m in args.methods.split(","):
        if P.is_peer(m):
            r = P.run_peer(m, scene, work / m, common)
            if r.get("missing"):
                skipped.append(f"{C.LABELS[m]}: not run ({r['missing']})")
                rows.append({"method": m, "run": r, "missing": r["missing"]})
                continue
        elif m in ("difftex-dense", "difftex-true-relief"):
            r = relief_row(m, scene, work, common)
            if r.get("missing"):
                skipped.append(f"{C.LABELS[m]}: not run ({r['missing']})")
                rows.append({"method": m, "run": r, "missing": r["missing"]})
                continue
        elif m == "difftex-paper":  # the published method at the same texel sizes as every other row
            paper = C.base_config(args.long_side, "paper")
            r = C.run_method("difftex", scene, work / m, common, dict(cfg, optimize=paper["optimize"]))
        else:
            r = C.run_method(m, scene, work / m, common)
        ev = C.evaluate(scene, Path(r["results"]), args.lpips)
        rows.append({"method": m, "run": r, "metrics": ev})
        print(f"table1: {m} done in {r['total_s']:.0f} s", flush=True)
    mach = C.machine()
    from difftex.scene.files import read_json

    synth = read_json(scene / "synth.json")
    sc = synth.get("config", {})
    notes = (
        [
            f"Scene: `{scene}` (difftex synth preset `{synth.get('preset')}`, seed {synth.get('seed')}: building "
            f"'{synth['building']['name']}', {len(synth['building']['polygons'])} polygons, {sc.get('views')} photos "
            f"{sc.get('width')}x{sc.get('height')}, exposure range +-{sc.get('exposure_range')} stops, occluders "
            f"{'on' if sc.get('occluders') else 'off'}; ground-truth maps {sc.get('gt_long_side')} texels long side).",
            C.size_note(args.long_side, cfg)
            + f"difftex preset `{args.preset}` ({cfg['optimize'].get('loss_mode')} loss, iteration caps "
            f"{cfg['optimize'].get('max_iters_per_level')}, coarse level {cfg['optimize'].get('long_side_start')}).",
            "Every method textures the same polygons from the same filtered photos and visibility masks; textures are "
            "resampled to the ground-truth map size and scored on the ground-truth texel masks (Error = RGB distance "
            "in "
            "[0, sqrt 3], percentiles pooled over all texels; SSIM/LPIPS texel-weighted over polygons).",
            "`views`: the textured proxy rendered into the scene's occluder-free held-out views and compared on the "
            "proxy's pixels (Table 2's scheme on synthetic data).",
            "Time: texturing only (sum over polygons of the method's per-polygon command; for difftex one "
            "`difftex texture` per polygon, which does the brightness transfers, the weights' initialization and "
            f"optimization and the composition and writes the PNGs); shared filter {common['filter_s']:.0f} s + "
            f"visibility {common['visibility_s']:.0f} s not included.",
            "Lower is better for Error and LPIPS, higher for SSIM, PSNR, Q_front, Q_vc. Sharpness: mean colour "
            "gradient over the ground truth's on the same texels (1 = as sharp; below: blurred; above: noise, seams). "
            "Detail: the ground truth's gradients the texture reproduces, sum(grad T . grad GT) / sum(|grad GT|^2) "
            "(1 = its edges at full contrast and in place; noise, seams and occluders' edges add nothing).",
        ]
        + [n for n in [P.timing_note(rows)] if n]
        + skipped
    )
    lines = [
        C.header(
            "Table 1: synthetic scene, texture maps against ground truth",
            "python evaluation/table1.py " + shlex.join(sys.argv[1:] if argv is None else argv),
            mach,
            notes,
        )
    ]
    lv = next((r["metrics"]["maps"]["overall"]["lpips_variant"] for r in rows if "maps" in r.get("metrics", {})), "n/a")
    lines.append(
        f"| Method | Error (90%) | Error (95%) | SSIM | LPIPS ({lv}) | PSNR | Sharpness vs GT | Detail vs GT | "
        "views SSIM | views LPIPS | Q_front | Q_vc | Time (s) |"
    )
    lines.append("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        if r.get("missing"):
            lines.append(P.missing_line(C.LABELS[r["method"]], r["missing"], 13))
            continue
        mm = r["metrics"]
        o = mm["maps"]["overall"]
        v = mm.get("views", {}).get("overall", {})
        q = mm.get("perspective", {})
        lines.append(
            f"| {C.LABELS.get(r['method'], r['method'])} | {C.fmt(o['error90'])} | {C.fmt(o['error95'])} | "
            f"{C.fmt(o['ssim'])} | {C.fmt(o['lpips'])} | {C.fmt(o['psnr'], 2)} | {C.fmt(o.get('sharpness'), 3)} | "
            f"{C.fmt(o.get('detail'), 3)} | {C.fmt(v.get('ssim'))} | "
            f"{C.fmt(v.get('lpips'))} | {C.fmt(q.get('q_front'))} | {C.fmt(q.get('q_vc'))} | "
            f"{r['run']['total_s']:.0f} |"
        )
    lines.append("")
    lines.append(
        f"Per-polygon values: `{Path(args.out).with_suffix('.json').name}`. Whole command: "
        f"{time.perf_counter() - t_all:.0f} s" + (f" (scene generation {t_synth:.0f} s)" if t_synth else "") + "."
    )
    try:
        from difftex.evaluation.html import comparison_page
        from difftex.evaluation.report import write_report

        done = [r for r in rows if not r.get("missing")]
        for r in done:
            write_report(r["run"]["results"], scene=scene)
        comparison_page(
            work / "index.html",
            "Table 1",
            "\n".join(lines),
            {r["method"]: r["run"]["results"] for r in done},
            scene=scene,
        )
        lines.append(
            f"HTML reports: `{work}/index.html` (one page per method with textures, source/error maps, loss curves)."
        )
    except ImportError:
        pass
    md = "\n".join(lines) + "\n"
    C.write_outputs(
        Path(args.out),
        md,
        {"machine": mach, "args": vars(args), "rows": rows, "common": common, "total_s": time.perf_counter() - t_all},
    )
    print(md)
    return 0


if __name__ == "__main__":
    C.run_script(main)
