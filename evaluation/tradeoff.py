"""Speed/accuracy trade: Error 95% and SSIM against minutes for each difftex preset and resolution.

    python evaluation/tradeoff.py             # fast and balanced presets at 128 and 256 texels, one facade
    python evaluation/tradeoff.py --runs fast@256,fast@512,balanced@512 --polygons all
    python evaluation/tradeoff.py --runs fast@auto,balanced@auto,paper@auto --polygons wall00

Writes evaluation/results/tradeoff.{md,json,png}: one point per preset@resolution (minutes of
texturing, summed over the polygons), with the cheap baselines at the same resolutions as
reference points, so a user can pick a preset from measured evidence.
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


def plot(rows: list[dict], out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from difftex.scene.files import atomic_path

    fig, axes = plt.subplots(1, 2, figsize=(10, 4), dpi=100)
    for ax, key, label in (
        (axes[0], "error95", "Error (95%)  (lower is better)"),
        (axes[1], "ssim", "SSIM  (higher is better)"),
    ):
        for r in rows:
            o = r["metrics"]["maps"]["overall"]
            x = r["run"]["total_s"] / 60
            is_dt = r["method"] == "difftex"
            ax.scatter([x], [o[key]], marker="o" if is_dt else "s", c="C0" if is_dt else "C3", s=30)
            ax.annotate(r["label"], (x, o[key]), fontsize=7, xytext=(3, 3), textcoords="offset points")
        ax.set_xscale("log")
        ax.set_xlabel("minutes of texturing (log)")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    fig.suptitle("difftex presets (circles) and baselines (squares)")
    fig.tight_layout()
    with atomic_path(out) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="evaluation/out/scenes/tiny")
    ap.add_argument(
        "--runs", default="fast@128,fast@256,balanced@128,balanced@256",
        help="comma-separated preset@long_side, or preset@auto for the preset's density from the photos "
        "(preset 'default': no preset, the workflow's defaults)"
    )
    ap.add_argument(
        "--baselines",
        default="average,mrf,texrecon,meshlab-face,meshlab-blend",
        help="run at each resolution as reference points ('' for none)",
    )
    ap.add_argument("--polygons", default="wall00", help="comma-separated ids, or 'all'")
    ap.add_argument("--optimize", default="{}", help="JSON of optimize: overrides for every difftex run")
    C.add_table_args(ap, "tradeoff")
    args = ap.parse_args(argv)

    import torch

    from evaluation.table1 import ensure_synth

    torch.set_num_threads(args.threads)
    t_all = time.perf_counter()
    scene, work = Path(args.scene), Path(args.work)
    ensure_synth(scene)
    only = C.polygon_ids(args.polygons)
    # preset@N: N texels on every map's long side; preset@auto: the preset's own density (texel
    # size from the photos' ground sampling distance, x the preset's density_scale)
    runs = []
    for r in args.runs.split(","):
        preset, res = r.split("@")
        runs.append((preset, None if res == "auto" else int(res)))
    commons, rows = {}, []
    sides: dict[str, str] = {}  # texture section -> the label of the first run with it
    for preset, size in runs:
        # the visibility (texel frames) and the baselines are shared by the runs at one resolution
        # (presets with the same texture section, e.g. paper and the defaults, share them too)
        side = size if size is not None else f"auto-{preset}"
        if size is None:
            key = repr(sorted(C.base_config(None, preset)["texture"].items()))
            side = sides.setdefault(key, side)
        if side not in commons:
            cfg = C.base_config(size, "fast" if size is not None else preset, {"evaluate": {"views": False}})
            commons[side] = C.run_common(scene, work / f"common{side}", cfg, only)
            for b in [b for b in args.baselines.split(",") if b]:
                if P.is_peer(b):
                    r = P.run_peer(b, scene, work / f"{b}@{side}", commons[side])
                    if r.get("missing"):
                        rows.append(
                            {"label": f"{b}@{side}", "method": b, "long_side": side, "run": r, "missing": r["missing"]}
                        )
                        continue
                else:
                    r = C.run_method(b, scene, work / f"{b}@{side}", commons[side])
                ev = C.evaluate(scene, work / f"{b}@{side}", args.lpips, config=commons[side]["config"])
                rows.append(
                    {"label": f"{b}@{side}", "method": b, "preset": None, "long_side": side, "run": r, "metrics": ev}
                )
        cfg = C.base_config(size, preset, {"evaluate": {"views": False}, "optimize": json.loads(args.optimize)})
        r = C.run_method("difftex", scene, work / f"{preset}@{side}", commons[side], cfg)
        ev = C.evaluate(scene, work / f"{preset}@{side}", args.lpips, config=commons[side]["config"])
        rows.append(
            {
                "label": f"{preset}@{'auto' if size is None else size}",
                "method": "difftex",
                "preset": preset,
                "long_side": side,
                "run": r,
                "metrics": ev,
                "optimize": cfg["optimize"],
            }
        )
        print(f"tradeoff: {preset}@{size or 'auto'} done in {r['total_s']:.0f} s", flush=True)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    plot([r for r in rows if not r.get("missing")], out.with_suffix(".png"))
    mach = C.machine()
    notes = [
        f"Scene `{scene}`, polygons {args.polygons}.",
        "Presets from config/presets/<name>.yaml, with the texture long side overridden (preset@N) or at the "
        "preset's own density from the photos (preset@auto, the baselines at the same texel frames); minutes = "
        "texturing time summed over the polygons, on this shared 2-core machine.",
        f"Plot: `{out.with_suffix('.png').name}`.",
    ] + [n for n in [P.timing_note(rows)] if n]
    lines = [
        C.header(
            "Speed/accuracy trade: presets and resolutions",
            "python evaluation/tradeoff.py " + shlex.join(sys.argv[1:] if argv is None else argv),
            mach,
            notes,
        )
    ]
    lv = next((r["metrics"]["maps"]["overall"]["lpips_variant"] for r in rows if r.get("metrics")), "n/a")
    lines.append(f"| Run | loss | iteration caps | Error (95%) | Error (90%) | SSIM | LPIPS ({lv}) | Minutes |")
    lines.append("|---|---|---|---|---|---|---|---|")
    for r in rows:
        if r.get("missing"):
            lines.append(P.missing_line(r["label"], r["missing"], 8))
            continue
        o = r["metrics"]["maps"]["overall"]
        opt = r.get("optimize") or {}
        lines.append(
            f"| {r['label']} | {opt.get('loss_mode', '-')} | {opt.get('max_iters_per_level', '-')} | "
            f"{C.fmt(o['error95'])} | "
            f"{C.fmt(o['error90'])} | {C.fmt(o['ssim'])} | {C.fmt(o['lpips'])} | {r['run']['total_s'] / 60:.2f} |"
        )
    lines.append("")
    lines.append(f"![trade-off]({out.with_suffix('.png').name})")
    C.finish_table(out, lines, t_all, mach, args, rows)
    return 0


if __name__ == "__main__":
    C.run_script(main)
