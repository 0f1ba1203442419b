"""Ablation (paper Fig. 5): difftex with each loss term and each data-quality step off in turn.

    python evaluation/ablation.py                      # tiny synthetic scene, 2 facades, preset fast
    python evaluation/ablation.py --scene data/synth/paper/archive --polygons all --peers ""

Every variant textures the same polygons from the same visibility files and is scored against
the ground-truth maps (Error 90/95, SSIM, LPIPS) and for perspective quality (Q_front, Q_vc).
"""

from __future__ import annotations

import argparse
import shlex
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from evaluation import common as C  # noqa: E402
from evaluation import peers as P  # noqa: E402

VARIANTS = {
    "full": ({}, "all terms and steps on"),
    "no_render": ({"use_render": False}, "without L_Render (and its sparsity term)"),
    "no_ghost": ({"ghost": 0.0}, "without the ghost term beside L_Render (the paper's L_Render alone)"),
    "no_persp": ({"use_persp": False}, "without L_Persp"),
    "no_para": ({"use_para": False}, "without L_Para"),
    "no_elimination": ({"data_elimination": False}, "without photo / pixel elimination"),
    "no_settling": ({"settle_sigma": 0.0}, "every texel optimized (no settled texels)"),
    "with_alignment": ({"align": True}, "with the photos' alignment refinement (off by default)"),
    "histmatch_quantile": (
        {"histmatch_model": "quantile"},
        "brightness by the paper's quantile map (not one gain per photo)",
    ),
    "no_histmatch": ({"histogram_matching": False}, "without HSV histogram matching"),
    "histmatch_best": (
        {"histmatch_reference": "best"},
        "histogram matching to the best photo (not the per-texel median)",
    ),
    "histmatch_pooled": (
        {"histmatch_reference": "pooled"},
        "histogram matching to the pooled histogram (not the per-texel median)",
    ),
    "no_coarse_to_fine": ({"coarse_to_fine": False}, "target level only (no coarse-to-fine)"),
}
# whole presets' optimize sections, at the same texel sizes as the other rows
PRESET_VARIANTS = {
    "paper": ("paper", "**DiffTex as published** (preset `paper`'s optimize section: the paper's terms, "
              "schedule and histogram matching, none of the project's additions)"),
}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="evaluation/out/scenes/tiny")
    ap.add_argument("--polygons", default="wall00,wall01", help="comma-separated ids, or 'all'")
    ap.add_argument("--long-side", type=int, default=None,
                    help="texture long side of every polygon (default: the preset's density, auto)")
    ap.add_argument("--preset", default="fast")
    ap.add_argument("--variants", default=",".join([*VARIANTS, *PRESET_VARIANTS]))
    ap.add_argument("--peers", default=",".join(P.PEERS), help="peer programs as reference rows ('' for none)")
    C.add_table_args(ap, "ablation")
    args = ap.parse_args(argv)

    import torch

    from evaluation.table1 import ensure_synth

    torch.set_num_threads(args.threads)
    t_all = time.perf_counter()
    scene, work = Path(args.scene), Path(args.work)
    ensure_synth(scene)
    only = C.polygon_ids(args.polygons)
    cfg = C.base_config(args.long_side, args.preset, {"evaluate": {"views": False}})
    common = C.run_common(scene, work, cfg, only)
    rows = []
    for v in args.variants.split(","):
        if v in PRESET_VARIANTS:
            preset, what = PRESET_VARIANTS[v]
            over = {"preset": preset}
            vcfg = C.base_config(args.long_side, preset, {"evaluate": {"views": False}})
        else:
            over, what = VARIANTS[v]
            vcfg = C.base_config(args.long_side, args.preset, {"evaluate": {"views": False}, "optimize": over})
        r = C.run_method("difftex", scene, work / v, common, vcfg)
        ev = C.evaluate(scene, work / v, args.lpips, config=common["config"])
        rows.append({"variant": v, "what": what, "optimize": over, "run": r, "metrics": ev})
        print(f"ablation: {v} done in {r['total_s']:.0f} s", flush=True)
    for m in [m for m in args.peers.split(",") if m]:
        r = P.run_peer(m, scene, work / m, common)
        ev = None if r.get("missing") else C.evaluate(scene, work / m, args.lpips, config=common["config"])
        rows.append(
            {"variant": m, "what": f"peer: {C.LABELS[m]}", "run": r, "metrics": ev, "missing": r.get("missing")}
        )
    mach = C.machine()
    notes = [
        f"Scene `{scene}`, polygons: {', '.join(r['id'] for r in common['polygons'])}.",
        C.size_note(args.long_side, cfg) + f"difftex preset `{args.preset}` "
        f"({cfg['optimize'].get('loss_mode')} loss, iteration caps {cfg['optimize'].get('max_iters_per_level')}).",
        "One switch of the `optimize:` section off per row (OptimizeConfig: use_render, ghost, use_persp, "
        "use_para, data_elimination, settle_sigma, align, histogram_matching, coarse_to_fine), or another "
        "histogram-matching reference (histmatch_reference; default median); everything else as in `full`. "
        "The `paper` row replaces the whole `optimize:` section by preset `paper`'s (the published method).",
        "Maps scored against ground truth as in Table 1; time is texturing summed over the polygons (one `difftex "
        "texture` per polygon: decoding, brightness transfers, the weights' optimization, composition).",
        "Peer rows: the peer programs on the same polygons and photos, for reference (not difftex variants).",
    ]
    notes += [n for n in [P.timing_note(rows)] if n]
    lines = [
        C.header(
            "Ablation: each loss term and data-quality step off in turn",
            "python evaluation/ablation.py " + shlex.join(sys.argv[1:] if argv is None else argv),
            mach,
            notes,
        )
    ]
    lv = next((r["metrics"]["maps"]["overall"]["lpips_variant"] for r in rows if r.get("metrics")), "n/a")
    lines.append(
        f"| Variant | Error (90%) | Error (95%) | SSIM | LPIPS ({lv}) | Sharpness vs GT | PSNR | Q_front | Q_vc | "
        "Time (s) |"
    )
    lines.append("|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        if r.get("missing"):
            lines.append(P.missing_line(r["what"], r["missing"], 10))
            continue
        o = r["metrics"]["maps"]["overall"]
        q = r["metrics"].get("perspective", {})
        lines.append(
            f"| {r['what']} | {C.fmt(o['error90'])} | {C.fmt(o['error95'])} | {C.fmt(o['ssim'])} | "
            f"{C.fmt(o['lpips'])} | {C.fmt(o.get('sharpness'), 3)} | "
            f"{C.fmt(o['psnr'], 2)} | {C.fmt(q.get('q_front'))} | {C.fmt(q.get('q_vc'))} | {r['run']['total_s']:.0f} |"
        )
    C.finish_table(Path(args.out), lines, t_all, mach, args, rows)
    return 0


if __name__ == "__main__":
    C.run_script(main)
