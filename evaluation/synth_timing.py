"""Generation time of the synthetic data set, per view, on this machine.

    python evaluation/synth_timing.py --preset paper --building hall --out data/synth/paper

generates the named buildings (all of the preset when none is named) with the preset's settings
(or the given overrides) and writes evaluation/synth_timing.json and .md: per building the number
of photos, their size and samples per pixel, seconds per photo, seconds for the ground-truth maps
and held-out views, and the total, with the machine it ran on. Results of earlier runs for other
buildings are kept, so buildings can be timed one at a time.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from evaluation import common as C  # noqa: E402

HERE = Path(__file__).resolve().parent


def machine() -> dict:
    """The shared machine description (evaluation/common.py) plus what this benchmark adds."""
    m = C.machine()
    import mitsuba

    from difftex.synth.render import choose_variant

    m.update(mitsuba=mitsuba.__version__, mitsuba_variant=choose_variant("auto"))
    return m


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="paper")
    ap.add_argument("--building", action="append", help="building to generate and time (repeatable)")
    ap.add_argument("--out", default=None, help="scene output folder (default data/synth/<preset>)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--views", type=int, help="override the number of photos (default: the preset's)")
    ap.add_argument("--result", default=str(HERE / "synth_timing"), help="result path without extension")
    ap.add_argument("--note", help="free text stored with the rows timed now (e.g. what else loaded the machine)")
    ap.add_argument("--markdown-only", action="store_true", help="rewrite the markdown from the JSON, generate nothing")
    args = ap.parse_args(argv)

    from difftex.scene.files import write_json, write_text
    from difftex.synth import generate, get_preset

    cfg = get_preset(args.preset)
    names = args.building or [b.name for b in cfg.buildings]
    out = Path(args.out or f"data/synth/{args.preset}")
    ov = {"views": args.views} if args.views else {}
    result_json = Path(args.result + ".json")
    old = json.loads(result_json.read_text()) if result_json.is_file() else {}
    rows = {r["building"]: r for r in old.get("buildings", []) if old.get("preset") == args.preset}
    mach = machine()
    for name in ([] if args.markdown_only else names):
        load0 = os.getloadavg()
        t0 = time.perf_counter()
        generate(cfg, out, seed=args.seed, buildings=[name], progress=True, **ov)
        wall = time.perf_counter() - t0
        scene = out if len(cfg.buildings) == 1 else out / name
        tm = json.loads((scene / "synth_timing.json").read_text())
        man = json.loads((scene / "synth.json").read_text())
        c = man["config"]
        rows[name] = {
            "building": name, "style": man["building"]["style"], "polygons": len(man["building"]["polygons"]),
            "views": tm["views"], "width": c["width"], "height": c["height"], "spp": c["spp"],
            "gt_long_side": c["gt_long_side"], "gt_spp": c["gt_spp"], "held_out_views": c["held_out_views"],
            "seconds_per_view": tm["timing"]["per_photo_s"], "photos_s": tm["timing"]["photos_s"],
            "model_s": tm["timing"]["model_s"], "gt_maps_s": tm["timing"]["gt_maps_s"],
            "held_out_s": tm["timing"]["held_out_s"], "total_s": round(wall, 1),
            "total_per_view_s": round(wall / tm["views"], 3), "machine": mach,
            "command": " ".join([Path(sys.executable).name, "evaluation/synth_timing.py", *(argv or sys.argv[1:])]),
            # 1-minute load averages before and after: other work on the machine slows the renders
            "load_before_after": [round(load0[0], 2), round(os.getloadavg()[0], 2)],
            "note": args.note or "",
        }
    if args.markdown_only and args.note:
        for r in rows.values():
            r["note"] = args.note
    res = {"preset": args.preset, "seed": args.seed, "buildings": [rows[k] for k in sorted(rows)]}
    write_json(result_json, res)
    lines = [
        f"# Synthetic data set generation time (`{args.preset}` preset)",
        "",
        "Written by `evaluation/synth_timing.py`; one row per building generated, on the machine named in it.",
        "",
        "| building | style | polygons | photos | size | spp | s / photo | GT maps (s) | held-out (s) | total (s) | "
        "total / photo (s) |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in res["buildings"]:
        lines.append(
            f"| {r['building']} | {r['style']} | {r['polygons']} | {r['views']} | {r['width']}x{r['height']} | "
            f"{r['spp']} | "
            f"{r['seconds_per_view']:.2f} | {r['gt_maps_s']:.0f} | {r['held_out_s']:.0f} | {r['total_s']:.0f} | "
            f"{r['total_per_view_s']:.2f} |"
        )
    notes = [f"- {r['building']}: {r['note']}" for r in res["buildings"] if r.get("note")]
    if notes:
        lines += ["", "Notes:", ""] + notes
    lines += ["", "Machines:", ""]
    for m in {json.dumps(r["machine"], sort_keys=True) for r in res["buildings"]}:
        m = json.loads(m)
        lines.append(
            f"- {m['cpu']}, {m['cores']} cores, {m['ram_gib']} GiB RAM; Python {m['python']}, torch {m['torch']}, "
            f"Mitsuba {m['mitsuba']} ({m['mitsuba_variant']}); {m['platform']}"
        )
    lines += ["", "Commands:", ""] + sorted({f"- `{r['command']}`" for r in res["buildings"]}) + [""]
    write_text(Path(args.result + ".md"), "\n".join(lines))
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    C.run_script(main)
