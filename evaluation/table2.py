"""Table 2 (real scenes): Q_front, Q_vc, and held-out-photo SSIM / LPIPS / PSNR, time per method.

    python evaluation/table2.py                                   # the shared real scenes, 128-texel maps
    python evaluation/table2.py --scenes ../shared/data/lund-door --holdout 2 --long-side 512

The paper's scheme: per scene, some photos are held out (``--holdout N``: N photos spread evenly
over the sorted names, or ``--holdout-names a.jpg,b.jpg``), the scene is copied without them
(`difftex.evaluation.holdout.prepare_holdout`: images symlinked, COLMAP model rewritten), every method
textures the proxy from the remaining photos, and the textured proxy is rendered into each
held-out camera and compared with the held-out photo on the proxy's pixels. Q_front / Q_vc are
computed on the texture maps from the view directions of the pixels that coloured each texel.
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

SHARED = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default=",".join(str(p) for p in sorted(SHARED.glob("*")) if (p / "sparse").is_dir()),
                    help="comma-separated scene folders (default: every scene in ../shared/data)")
    ap.add_argument("--holdout", type=int, default=2, help="held-out photos per scene (evenly spread)")
    ap.add_argument("--holdout-names", default=None, help="comma-separated names instead (one scene only)")
    ap.add_argument("--long-side", type=int, default=None,
                    help="texture long side of every polygon and method (default: the preset's density, auto)")
    ap.add_argument("--preset", default="fast")
    ap.add_argument("--render-long-side", type=int, default=768, help="held-out views are compared at this size")
    ap.add_argument("--methods", default="difftex,average,frontal,mrf,texrecon,meshlab-face,meshlab-blend")
    ap.add_argument("--optimize", default=None, help="JSON of optimize: overrides (ablations)")
    C.add_table_args(ap, "table2")
    args = ap.parse_args(argv)

    import torch

    from difftex.evaluation.holdout import prepare_holdout
    from difftex.evaluation.html import comparison_page
    from difftex.evaluation.report import write_report

    torch.set_num_threads(args.threads)
    t_all = time.perf_counter()
    over = {"evaluate": {"render_long_side": args.render_long_side}}
    if args.optimize:
        over["optimize"] = json.loads(args.optimize)
    cfg = C.base_config(args.long_side, args.preset, over)
    scenes = [Path(s) for s in args.scenes.split(",") if s]
    results, skipped, per_scene = [], [], {}
    for sc in scenes:
        work = Path(args.work) / sc.name
        hold = args.holdout_names.split(",") if args.holdout_names else args.holdout
        info = prepare_holdout(sc, hold, work / "scene")
        copy = work / "scene"
        common = C.run_common(copy, work, cfg)
        per_scene[sc.name] = {"held_out": info["held_out"], "kept": len(info["kept"]),
                              "filter_s": common["filter_s"], "visibility_s": common["visibility_s"],
                              "polygons": len(common["polygons"])}
        runs = {}
        for m in args.methods.split(","):
            if P.is_peer(m):
                r = P.run_peer(m, copy, work / m, common)
                if r.get("missing"):
                    if not any(C.LABELS[m] in s for s in skipped):
                        skipped.append(f"{C.LABELS[m]}: not run ({r['missing']})")
                    results.append({"scene": sc.name, "method": m, "run": r, "missing": r["missing"]})
                    continue
            else:
                r = C.run_method(m, copy, work / m, common)
            ev = C.evaluate(copy, Path(r["results"]), args.lpips, config=common["config"])
            results.append({"scene": sc.name, "method": m, "run": r, "metrics": ev})
            runs[m] = r["results"]
            write_report(r["results"], scene=copy)
            print(f"table2: {sc.name} {m} done in {r['total_s']:.0f} s", flush=True)
        per_scene[sc.name]["runs"] = runs
    mach = C.machine()
    notes = (
        [
            "Scenes: "
            + ", ".join(
                f"`{s.name}` ({per_scene[s.name]['kept']} photos kept, held out: "
                + ", ".join(per_scene[s.name]["held_out"])
                + ")"
                for s in scenes
            )
            + ".",
            C.size_note(args.long_side, cfg)
            + f"difftex preset `{args.preset}` ({cfg['optimize'].get('loss_mode')} loss, iteration caps "
            f"{cfg['optimize'].get('max_iters_per_level')}); held-out views compared at {args.render_long_side} px "
            "long side.",
            "SSIM / LPIPS / PSNR: the textured proxy rendered into each held-out camera against the held-out photo, "
            "on the "
            "pixels where a textured proxy polygon is the nearest surface (pixel-weighted mean over views). The photos "
            "contain what the proxy does not model (statues, columns, people) and exposure differs per photo, so these "
            "numbers are far from 1 for every method; compare methods within a scene.",
            "Q_front / Q_vc (docs/metrics.md): from the per-texel view directions of the pixels that coloured each "
            "texel "
            "(difftex: optimized blend weights; averaging: all visible photos equally; frontal, MRF: the chosen "
            "photo), "
            "texel-weighted over polygons.",
            "Time: texturing only (sum over polygons); filter + visibility are shared: "
            + ", ".join(f"{n} {d['filter_s'] + d['visibility_s']:.0f} s" for n, d in per_scene.items())
            + ".",
            "Lower is better for LPIPS, higher for the rest.",
        ]
        + [n for n in [P.timing_note(results)] if n]
        + skipped
    )
    lines = [
        C.header(
            "Table 2: real scenes, held-out photos and perspective quality",
            "python evaluation/table2.py " + shlex.join(sys.argv[1:] if argv is None else argv),
            mach,
            notes,
        )
    ]
    lv = next(
        (r["metrics"]["views"]["overall"]["lpips_variant"] for r in results if "views" in r.get("metrics", {})), "n/a"
    )
    lines.append(f"| Scene | Method | Q_front | Q_vc | SSIM | LPIPS ({lv}) | PSNR | Time (s) |")
    lines.append("|---|---|---|---|---|---|---|---|")
    for r in results:
        if r.get("missing"):
            lines.append(P.missing_line(C.LABELS[r["method"]], r["missing"], 8, [r["scene"]]))
            continue
        mm = r["metrics"]
        v = mm.get("views", {}).get("overall", {})
        q = mm.get("perspective", {})
        lines.append(
            f"| {r['scene']} | {C.LABELS.get(r['method'], r['method'])} | {C.fmt(q.get('q_front'))} | "
            f"{C.fmt(q.get('q_vc'))} | {C.fmt(v.get('ssim'))} | {C.fmt(v.get('lpips'))} | {C.fmt(v.get('psnr'), 2)} | "
            f"{r['run']['total_s']:.0f} |"
        )
    # mean over scenes per method
    methods = list(dict.fromkeys(r["method"] for r in results))
    if len(scenes) > 1:
        for m in methods:
            rs = [r for r in results if r["method"] == m and not r.get("missing")]
            if not rs:
                continue

            def mean(get, rs=rs):
                vals = [get(r) for r in rs if get(r) is not None]
                return sum(vals) / len(vals) if vals else None

            lines.append(
                f"| **mean** | {C.LABELS.get(m, m)} | "
                f"{C.fmt(mean(lambda r: r['metrics'].get('perspective', {}).get('q_front')))} | "
                f"{C.fmt(mean(lambda r: r['metrics'].get('perspective', {}).get('q_vc')))} | "
                f"{C.fmt(mean(lambda r: r['metrics'].get('views', {}).get('overall', {}).get('ssim')))} | "
                f"{C.fmt(mean(lambda r: r['metrics'].get('views', {}).get('overall', {}).get('lpips')))} | "
                f"{C.fmt(mean(lambda r: r['metrics'].get('views', {}).get('overall', {}).get('psnr')), 2)} | "
                f"{mean(lambda r: r['run']['total_s']):.0f} |"
            )
    lines.append("")
    lines.append(
        f"Per-view and per-polygon values: `{Path(args.out).with_suffix('.json').name}`. Whole command: "
        f"{time.perf_counter() - t_all:.0f} s. HTML: `{args.work}/<scene>/index.html`."
    )
    md = "\n".join(lines) + "\n"
    for sc in scenes:
        comparison_page(Path(args.work) / sc.name / "index.html", f"Table 2: {sc.name}", md, per_scene[sc.name]["runs"])
    C.write_outputs(
        Path(args.out),
        md,
        {
            "machine": mach,
            "args": vars(args),
            "scenes": per_scene,
            "rows": results,
            "total_s": time.perf_counter() - t_all,
        },
    )
    print(md)
    return 0


if __name__ == "__main__":
    C.run_script(main)
