"""Speed of the whole workflow per preset against texrecon and a plain average, in one run.

    python evaluation/bench_speed.py --scene data/synth/paper/archive --scene ../shared/data/herzjesu-p8
    python evaluation/bench_speed.py --scene data/synth/paper/archive --subset 50   # + a 50-photo copy

For every scene, in rounds (``--repeats``), on the same machine:

1. The workflow, once per preset, as a user runs it: ``snakemake --cores N --config scene=S
   preset=P 'run={evaluate: false}'`` in a fresh folder; wall seconds of the command, CPU seconds
   and peak RSS of every job (Snakemake's benchmark files), texels and K x texels per polygon,
   iterations per level.
2. texrecon (mvs-texturing) at the end of every round: in the first, through difftex's peer runner
   (``difftex peer``) on the photos the first run kept, with difftex's preparation (photos
   resampled as centred pinhole cameras, the proxy meshed) and the import of its atlas reported
   apart; in the later rounds its program alone again on the same prepared input. Each workflow
   run's ratio is against the texrecon of its own round: a shared machine's speed drifts over
   minutes (other tenants), so a texrecon timed once minutes away from a run is no yardstick.
   Not run if texrecon is not found (``DIFFTEX_TEXRECON`` or PATH;
   ``../shared/peers/build_texrecon.sh`` builds it).
3. The floor: a plain per-texel average (``difftex baseline --method average``) of every polygon
   at the first preset's texel sizes, in-process (no interpreter start-up per polygon).

``--subset N`` adds a copy of each scene with N of its photos (evenly spread), to show how the
time grows with the photos at the same texels. ``--split both`` runs each preset with the
per-polygon work as one ``texture`` job per polygon group (``run.split: false``) and as
initialize/optimize/compose jobs (``run.split: true``), alternating, ``--repeats`` times each, and
gives the split's wall against the one job's. Writes JSON and markdown with the machine.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shlex
import shutil
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from evaluation import common as C  # noqa: E402


def children_cpu() -> float:
    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    return ru.ru_utime + ru.ru_stime


def read_benchmarks(results: Path) -> dict[str, dict]:
    """{rule: {"jobs", "wall_s", "cpu_s", "max_rss_mb"}} from Snakemake's benchmark files
    (difftex.evaluation.report.stage_benchmarks, under this benchmark's JSON keys)."""
    from difftex.evaluation.report import stage_benchmarks

    return {
        rule: {"jobs": d["jobs"], "wall_s": d["seconds"], "max_job_s": d["max_s"], "cpu_s": d["cpu_s"],
               "max_rss_mb": d["max_rss_mb"]}
        for rule, d in stage_benchmarks(results).items()
    }


def stage_lines(rows: list[dict]) -> list[str]:
    """Markdown: each run's wall seconds per stage, summed over the stage's jobs."""
    lines = [
        "Wall seconds per stage (sum over the stage's jobs; /n: n jobs, which run side by side). Snakemake's "
        "`cpu_time` per job is in the JSON (`cpu_s`), but it samples the job's processes and misses most of a "
        "long texture job's CPU, so it is not summed here.",
        "",
    ]
    for row in rows:
        for run in row["runs"]:
            parts = ", ".join(
                f"{k} {d['wall_s']:.1f}" + (f"/{d['jobs']}" if d["jobs"] > 1 else "") for k, d in run["stages"].items()
            )
            lines.append(f"- {Path(row['scene']).name} {run['preset']}: {parts}")
    return lines


def split_lines(rows: list[dict]) -> list[str]:
    """Markdown: per scene and preset run both ways, the split's wall and CPU against the one job's
    (medians over the repeats)."""
    import statistics

    lines = []
    for row in rows:
        by: dict[tuple[str, str], list[dict]] = {}
        for run in row["runs"]:
            by.setdefault((run["preset"].split(",")[0], run.get("split", "auto")), []).append(run)
        for (preset, sp), runs in sorted(by.items()):
            if sp != "true" or (preset, "false") not in by:
                continue
            one = by[(preset, "false")]
            w1, w2 = (statistics.median(r["wall_s"] for r in rr) for rr in (one, runs))
            c1, c2 = (statistics.median(r["cpu_s"] for r in rr) for rr in (one, runs))
            lines.append(
                f"- {Path(row['scene']).name} {preset}: split {w2:.1f} s against one job {w1:.1f} s wall "
                f"({100 * (w2 / w1 - 1):+.0f} %), CPU {c2:.1f} s against {c1:.1f} s ({100 * (c2 / c1 - 1):+.0f} %); "
                f"medians of {len(runs)} and {len(one)} runs"
            )
    return lines + [""] if lines else []


def polygon_work(results: Path) -> dict:
    """Texels, slots and iterations of the run's texture stage (visibility summary, stats.json)."""
    from difftex.scene.files import read_json

    vis = read_json(results / "visibility" / "summary.json")["polygons"]
    texels = sum(int(p["texels"]) for p in vis if p.get("photos"))
    slots = iters = caps = converged = n_levels = 0
    levels = []
    for p in vis:
        st = results / "optimized" / p["id"] / "stats.json"
        if not st.is_file():
            continue
        s = read_json(st)
        last = s["levels"][-1]
        slots += int(last["top_k"]) * int(s.get("texels", 0))
        iters += sum(int(lv["iterations"]) for lv in s["levels"])
        caps += sum(int(lv["cap"]) for lv in s["levels"])
        converged += sum(bool(lv["converged"]) for lv in s["levels"])
        n_levels += len(s["levels"])
        levels.append([int(lv["iterations"]) for lv in s["levels"]])
    return {"polygons": len(vis), "textured": sum(1 for p in vis if p.get("photos")), "texels": texels,
            "slot_texels": slots, "iterations": iters, "iterations_per_level": levels,
            "iteration_caps": caps, "levels_converged": converged, "levels": n_levels,
            "map_sizes": {p["id"]: [p["width"], p["height"]] for p in vis},
            "texel_sizes": {p["id"]: p.get("texel_size") for p in vis}}


def run_workflow(scene: Path, work: Path, preset: str, cores: int, split: str = "auto") -> dict:
    work.mkdir(parents=True, exist_ok=True)
    bin_dir = Path(sys.executable).parent
    cmd = [str(bin_dir / "snakemake"), "-s", str(ROOT / "Snakefile"), "--directory", str(work), "--cores", str(cores),
           "--config", f"scene={scene.resolve()}", f"run={{evaluate: false, split: {split}}}"]
    if preset != "default":  # "default": no preset, the configuration's defaults (full density)
        cmd.append(f"preset={preset}")
    env = dict(os.environ, PATH=f"{bin_dir}{os.pathsep}{os.environ.get('PATH', '')}")
    c0, t0 = children_cpu(), time.perf_counter()
    r = subprocess.run(cmd, capture_output=True, text=True, env=env)
    wall, cpu = time.perf_counter() - t0, children_cpu() - c0
    if r.returncode != 0:
        raise RuntimeError(f"workflow failed on {scene} ({preset}): {(r.stdout + r.stderr)[-1500:]}")
    from difftex.workflow.glue import scene_name

    results = work / "results" / scene_name(scene)
    stages = read_benchmarks(results)
    label = preset + {"true": ", split", "false": ", one job"}.get(split, "")
    return {"preset": label, "split": split, "wall_s": wall, "cpu_s": cpu, "stages": stages,
            "peak_rss_mb": max((d["max_rss_mb"] for d in stages.values()), default=0.0),
            **polygon_work(results), "results": str(results)}


def run_texrecon(scene: Path, work: Path, results: Path) -> dict:
    """texrecon on the scene's photos the workflow kept, imported into the workflow's frames."""
    from evaluation import peers

    why = peers.unavailable("texrecon")
    if why:
        return {"missing": why}
    common = {
        "visibility": results / "visibility",
        "config": results / "config" / "x.yaml",
        "polygons": [
            p for p in json.loads((results / "visibility" / "summary.json").read_text())["polygons"] if p["photos"]
        ],
    }
    (results / "config" / "x.yaml").parent.mkdir(exist_ok=True)
    shutil.copyfile(results / "photos.json", results / "config" / "photos.json")
    # the resampled photos are kept so that later rounds time the program again on the same input
    return peers.run_peer("texrecon", scene, work / "texrecon", common, keep_inputs=True)


def rerun_texrecon(first: dict) -> dict:
    """texrecon's program again, on the input the first round prepared.

    Args:
        first: the first round's ``run_texrecon`` result (its command as recorded, shell-quoted).

    Returns:
        {"wall_s", "cpu_s", "peak_rss_mib"}, or {"error": the one-line reason} when it failed
        (the other rounds are kept).
    """
    from difftex.errors import DifftexError
    from difftex.evaluation.peers.measure import run_measured

    rec = first["peer_record"]
    cmd = shlex.split(rec["peer_program"]["command"])
    log = Path(first["results"]) / "work" / "rerun.log"
    try:
        phase = run_measured(cmd, log, float(rec["config"]["timeout_s"]), what="texrecon")
    except DifftexError as e:
        return {"error": str(e)}
    return {"wall_s": phase.wall_s, "cpu_s": phase.cpu_s, "peak_rss_mib": phase.peak_rss_mib}


def run_average(scene: Path, results: Path) -> dict:
    """The plain per-texel average of every textured polygon at the run's texel sizes, in-process."""
    from difftex.evaluation.baselines import baseline_texture
    from difftex.geometry.visibility import load_visibility
    from difftex.sampling.photos import polygon_input_from_visibility
    from difftex.scene.loading import load_scene

    t0, c0 = time.perf_counter(), time.process_time()
    sc = load_scene(scene, check_images=False)
    by = {p.name: p for p in sc.photos}
    n = 0
    for npz in sorted((results / "visibility").glob("*.npz")):
        vis = load_visibility(npz)
        if vis.photos:
            baseline_texture(polygon_input_from_visibility(vis, by), "average", "cpu")
            n += 1
    return {"wall_s": time.perf_counter() - t0, "cpu_s": time.process_time() - c0, "polygons": n}


def subset_scene(scene: Path, n: int, out: Path) -> Path | None:
    from difftex.evaluation.holdout import prepare_holdout
    from difftex.scene.camera import load_photos
    from difftex.scene.loading import find_sparse

    names = [p.name for p in load_photos(find_sparse(scene), scene / "images", check_images=False)]
    if len(names) <= n:
        return None  # no smaller copy to make
    step = max(1, len(names) // n)
    dst = out / f"{scene.name}-{n}"
    if not (dst / "sparse").is_dir():
        prepare_holdout(scene, 0, dst, keep=names[::step][:n])
    return dst


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", action="append", required=True)
    ap.add_argument("--presets", default="fast,balanced", help="comma-separated; 'default' is no preset")
    ap.add_argument("--subset", type=int, default=0, help="also a copy of each scene with this many photos")
    ap.add_argument("--cores", type=int, default=2)
    ap.add_argument("--split", default="auto", choices=["auto", "true", "false", "both"],
                    help="run.split of the workflow runs; both: each preset both ways, alternating")
    ap.add_argument("--repeats", type=int, default=1, help="runs of each preset (and split), alternating")
    ap.add_argument("--work", default="evaluation/out/bench_speed")
    ap.add_argument("--out", default="evaluation/results/bench_speed")
    args = ap.parse_args(argv)

    work = Path(args.work)
    scenes = [Path(s) for s in args.scene]
    if args.subset:
        subsets = [subset_scene(s, args.subset, work / "scenes") for s in list(scenes)]
        scenes += [s for s in subsets if s is not None]
    mach = C.machine()
    rows = []
    for scene in scenes:
        row: dict = {"scene": str(scene), "load_avg_start": os.getloadavg()}
        splits = ["false", "true"] if args.split == "both" else [args.split]
        variants = [(p, sp) for p in args.presets.split(",") for sp in splits]
        row["runs"] = []
        for rep in range(args.repeats):
            for p, sp in variants:
                wd = work / scene.name / "-".join([p] + ([f"split_{sp}"] if sp != "auto" else []) + [str(rep)])
                if wd.exists():
                    shutil.rmtree(wd)
                run = run_workflow(scene, wd, p, args.cores, sp)
                run["repeat"] = rep
                row["runs"].append(run)
                print(
                    f"bench_speed: {scene.name} {run['preset']}: {run['wall_s']:.0f} s wall, {run['cpu_s']:.0f} s CPU, "
                    f"peak {run['peak_rss_mb']:.0f} MB, {run['texels'] / 1e6:.2f} M texels",
                    flush=True,
                )
            if rep == 0:
                row["texrecon"] = run_texrecon(scene, work / scene.name, Path(row["runs"][0]["results"]))
                if "peer_s" in row["texrecon"]:
                    tr = row["texrecon"]
                    row["texrecon_rounds"] = [
                        {"wall_s": tr["peer_s"], "cpu_s": tr["peer_cpu_s"], "peak_rss_mib": tr["peer_peak_rss_mib"]}
                    ]
            elif "peer_s" in row["texrecon"]:
                row["texrecon_rounds"].append(rerun_texrecon(row["texrecon"]))
            if row.get("texrecon_rounds"):
                last = row["texrecon_rounds"][-1]
                done = f"{last['wall_s']:.1f} s wall" if "wall_s" in last else f"failed: {last['error']}"
                print(f"bench_speed: {scene.name} texrecon: {done}", flush=True)
        first = Path(row["runs"][0]["results"])
        row["average"] = run_average(scene, first)
        row["load_avg_end"] = os.getloadavg()
        rows.append(row)
        write(Path(args.out), rows, mach, args)
    print(Path(args.out).with_suffix(".md").read_text())
    return 0


def table_lines(row: dict, n_ph: int) -> list[str]:
    """Markdown rows of one scene: per round, its workflow runs and then its texrecon; each run's
    ratio is against its round's texrecon, the average's against the last round's."""
    name, rounds = Path(row["scene"]).name, row.get("texrecon_rounds", [])
    lines = []
    for rep in range(1 + max((r.get("repeat", 0) for r in row["runs"]), default=0)):
        tw = rounds[rep].get("wall_s") if rounds else None
        for run in (r for r in row["runs"] if r.get("repeat", 0) == rep):
            ratio = f"{run['wall_s'] / tw:.2f}" if tw else "n/a"
            lines.append(
                f"| {name} | {n_ph} | {rep + 1} | difftex {run['preset']} | {run['wall_s']:.1f} | {run['cpu_s']:.1f} | "
                f"{run['peak_rss_mb']:.0f} | {run['texels'] / 1e6:.2f} | {run['slot_texels'] / 1e6:.2f} | "
                f"{run['iterations']} of {run.get('iteration_caps', '?')} "
                f"({run.get('levels_converged', '?')}/{run.get('levels', '?')} levels converged) | {ratio} |"
            )
        if rounds and "error" in rounds[rep]:
            lines.append(f"| {name} | {n_ph} | {rep + 1} | texrecon | failed: {rounds[rep]['error']} | | | | | | |")
        elif rounds:
            t = rounds[rep]
            lines.append(f"| {name} | {n_ph} | {rep + 1} | texrecon | {t['wall_s']:.1f} | {t['cpu_s']:.1f} | "
                         f"{t['peak_rss_mib']:.0f} | | | | 1.00 |")
        else:
            lines.append(f"| {name} | {n_ph} | {rep + 1} | texrecon | not run: "
                         f"{row.get('texrecon', {}).get('missing', '?')} | | | | | | |")
    av, tw = row["average"], rounds[-1].get("wall_s") if rounds else None
    ratio = f"{av['wall_s'] / tw:.2f}" if tw else "n/a"
    lines.append(f"| {name} | {n_ph} | | plain average | {av['wall_s']:.1f} | {av['cpu_s']:.1f} | | | | | {ratio} |")
    return lines


def ratio_lines(rows: list[dict]) -> list[str]:
    """Markdown: per scene and preset, the median (and range) over the rounds of its ratio to the
    texrecon of the same round."""
    import statistics

    lines = []
    for row in rows:
        rounds = row.get("texrecon_rounds", [])
        if not rounds:
            continue
        by: dict[str, list[float]] = {}
        for run in row["runs"]:
            tw = rounds[run.get("repeat", 0)].get("wall_s")
            if tw:
                by.setdefault(run["preset"], []).append(run["wall_s"] / tw)
        for preset, ratios in by.items():
            lines.append(
                f"- {Path(row['scene']).name} {preset}: {statistics.median(ratios):.2f}x texrecon, median of "
                f"{len(ratios)} rounds (range {min(ratios):.2f}-{max(ratios):.2f})"
            )
    return lines + [""] if lines else []


def write(stem: Path, rows: list[dict], mach: dict, args) -> None:
    lines = [
        C.header(
            "Speed: the workflow per preset against texrecon and a plain average",
            "python evaluation/bench_speed.py " + shlex.join(sys.argv[1:]),
            mach,
            [
                "Rows in the order they ran: per round, the presets and then texrecon (in the first round "
                "on the first preset's photos, through difftex's preparation of its input; in later rounds "
                "its program alone on that input); then the average. Wall seconds of the whole command, "
                f"Snakemake with --cores {args.cores}, evaluation off (the workflow's other stages all on).",
                "texrecon: the program's own wall time (difftex's preparation of its input and the import of "
                "its atlas apart, in the JSON). Average: every polygon's plain per-texel average at the first "
                "preset's texel sizes, in one process.",
                "Ratio = workflow wall / the wall of its round's texrecon (the average: the last round's). "
                "CPU: all jobs of the run; RSS: the largest job.",
            ],
        )
    ]
    lines.append(
        "| scene | photos | round | method | wall (s) | CPU (s) | peak RSS (MB) | texels (M) | K x texels (M) | "
        "iterations | vs texrecon |"
    )
    lines.append("|---|---|---|---|---|---|---|---|---|---|---|")
    from difftex.scene.camera import load_photos
    from difftex.scene.loading import find_sparse

    for row in rows:
        sc = Path(row["scene"])
        lines += table_lines(row, len(load_photos(find_sparse(sc), sc / "images", check_images=False)))
    lines += ["", *ratio_lines(rows), *split_lines(rows), *stage_lines(rows)]
    C.write_outputs(stem, "\n".join(lines) + "\n", {"machine": mach, "args": vars(args), "rows": rows})


if __name__ == "__main__":
    C.run_script(main)
