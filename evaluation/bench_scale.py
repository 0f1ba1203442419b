"""How the whole workflow scales with the scene: generated districts at three sizes (issue #32).

    python evaluation/bench_scale.py --smoke                       # 1, 3, 10 buildings: minutes
    python evaluation/bench_scale.py --buildings 12,36,120 --views 84 --work evaluation/out/bench_scale_10k
        # about 100, 330, 1,100 polygons with 1,000, 3,000, 10,000 photos (evaluation/results/bench_scale.md)

For every size, on the same machine and in this order:

1. ``difftex.synth.district.generate_district`` writes the scene (seconds per photo recorded).
2. ``snakemake -n`` on it: the DAG-building time (up to the visibility checkpoint, as a dry run sees it).
3. ``snakemake --cores N --config scene=S preset=fast 'run={evaluate: false}'`` in a fresh folder,
   as ``evaluation/bench_speed.py`` runs it: wall and CPU seconds of the command; per stage (rule)
   the number of jobs (Snakemake's log), the sum of the jobs' wall seconds and Snakemake's sampled
   ``cpu_time`` (benchmark files), the peak RSS of its largest job; and Snakemake's own overhead,
   the command's wall time during which no job ran (job start and finish times from its log).

Then per quantity a power law ``y = a * work^b`` fitted through the sizes (work: photos for filter
and visibility, polygons for the rest), the extrapolation to a 10,000-polygon city with photos in
the same proportion, and the polygon count at which each limit (``LIMITS``) is first crossed.
Writes <out>.md and <out>.json.
"""

from __future__ import annotations

import argparse
import os
import re
import shlex
import shutil
import subprocess
import sys
import time
from datetime import datetime
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from evaluation import common as C  # noqa: E402
from evaluation.bench_speed import children_cpu, read_benchmarks  # noqa: E402

# the whole-scene stages (their parts and their merges): their work is the photos; every other stage's is the polygons
PHOTO_STAGES = ("filter_part", "filter", "visibility_tile", "visibility")
TARGET_POLYGONS = 10_000
# What "breaks": a limit per quantity, crossed first at the smallest polygon count (the text says why).
LIMITS = {
    "peak_rss_mb": (4000.0, "a job's peak RSS above the SLURM profile's default mem_mb (4,000 MB)"),
    "jobs": (10_000.0, "more than 10,000 jobs in one run (Snakemake's per-job bookkeeping and logs)"),
    "dag_s": (600.0, "DAG building (snakemake -n) over 10 minutes"),
    "serial_s": (3600.0,
                 "one job of the whole-scene stages (filter or visibility, a part or the merge) over 1 hour"),
    "overhead_s": (3600.0, "Snakemake's own overhead (no job running) over 1 hour"),
}
_STAMP = re.compile(r"^\[(\w{3} \w{3} +\d+ \d\d:\d\d:\d\d \d{4})\]$")
_START = re.compile(r"^(?:local)?(?:rule|checkpoint) (\w+):$")
_JOBID = re.compile(r"^\s+jobid: (\d+)$")
_DONE = re.compile(r"^Finished jobid: (\d+) \(Rule: (\w+)\)$")


def parse_log(text: str) -> dict:
    """Jobs per rule and the job intervals from a Snakemake log.

    Args:
        text: the content of ``.snakemake/log/<date>.snakemake.log``.

    Returns:
        {"jobs": {rule: n}, "intervals": [(start, end) in seconds since the first timestamp],
        "seconds": {rule: sum of its jobs' (end - start)}} (1-second timestamps: per job +-1 s).
    """
    stamp = t_first = 0.0
    seen = False
    rule = None
    starts: dict[str, float] = {}
    intervals: list[tuple[float, float]] = []
    jobs: dict[str, int] = {}
    seconds: dict[str, float] = {}
    for line in text.splitlines():
        m = _STAMP.match(line)
        if m:
            stamp = datetime.strptime(m.group(1), "%a %b %d %H:%M:%S %Y").timestamp()
            t_first, seen = (t_first, True) if seen else (stamp, True)
            continue
        if (m := _START.match(line)) and seen:
            rule = m.group(1)
            jobs[rule] = jobs.get(rule, 0) + 1
            continue
        if (m := _JOBID.match(line)) and rule is not None:
            starts[m.group(1)] = stamp - t_first
            rule = None
            continue
        if (m := _DONE.match(line)) and m.group(1) in starts:
            intervals.append((starts.pop(m.group(1)), stamp - t_first))
            seconds[m.group(2)] = seconds.get(m.group(2), 0.0) + intervals[-1][1] - intervals[-1][0]
    return {"jobs": jobs, "intervals": intervals, "seconds": seconds}


def busy_seconds(intervals: list[tuple[float, float]]) -> float:
    """Length of the union of the intervals (time during which at least one job ran)."""
    total, end = 0.0, -np.inf
    for a, b in sorted(intervals):
        if a > end:
            total, end = total + (b - a), b
        elif b > end:
            total, end = total + (b - end), b
    return total


def snakemake_cmd(scene: Path, work: Path, cores: int, dry: bool) -> list[str]:
    bin_dir = Path(sys.executable).parent
    cmd = [str(bin_dir / "snakemake"), "-s", str(ROOT / "Snakefile"), "--directory", str(work), "--cores",
           str(cores), "--config", f"scene={scene.resolve()}", "preset=fast", "run={evaluate: false}"]
    return cmd + (["-n", "--quiet", "all"] if dry else [])


def run_size(buildings: int, views: int, cores: int, work: Path, seed: int) -> dict:
    """Generate one district and run the workflow on it; the figures of one size."""
    from difftex.synth.district import generate_district
    from difftex.workflow.glue import scene_name

    scene = work / "scenes" / f"district{buildings}"
    if scene.exists():
        shutil.rmtree(scene)
    t0 = time.perf_counter()
    m = generate_district(scene, buildings=buildings, views=views, seed=seed)
    gen_s = time.perf_counter() - t0
    run_dir = work / "runs" / scene.name
    if run_dir.exists():
        shutil.rmtree(run_dir)
    run_dir.mkdir(parents=True)
    env = dict(os.environ, PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}")
    t0 = time.perf_counter()
    dry = subprocess.run(snakemake_cmd(scene, run_dir, cores, True), capture_output=True, text=True, env=env)
    dag_s = time.perf_counter() - t0
    if dry.returncode != 0:
        raise RuntimeError(f"snakemake -n failed on {scene}: {(dry.stdout + dry.stderr)[-1500:]}")
    c0, t0 = children_cpu(), time.perf_counter()
    r = subprocess.run(snakemake_cmd(scene, run_dir, cores, False), capture_output=True, text=True, env=env)
    wall, cpu = time.perf_counter() - t0, children_cpu() - c0
    if r.returncode != 0:
        raise RuntimeError(f"workflow failed on {scene}: {(r.stdout + r.stderr)[-1500:]}")
    log = parse_log(sorted((run_dir / ".snakemake" / "log").glob("*.log"))[-1].read_text())
    bench = read_benchmarks(run_dir / "results" / scene_name(scene))
    stages = {}
    for rule in sorted(set(log["jobs"]) | set(bench)):
        b = bench.get(rule, {})
        stages[rule] = {"jobs": log["jobs"].get(rule, b.get("jobs", 0)), "wall_s": b.get("wall_s"),
                        "max_job_s": b.get("max_job_s"),
                        "cpu_s": b.get("cpu_s"), "max_rss_mb": b.get("max_rss_mb"),
                        "log_s": log["seconds"].get(rule)}
    busy = busy_seconds(log["intervals"])
    return {"buildings": buildings, "polygons": m["polygons"], "photos": m["photos"], "views": views,
            "unseen": len(m["unseen_polygons"]), "generate_s": gen_s, "dag_s": dag_s, "wall_s": wall, "cpu_s": cpu,
            "busy_s": busy, "overhead_s": max(0.0, wall - busy), "jobs": sum(log["jobs"].values()),
            "peak_rss_mb": max((d["max_rss_mb"] or 0.0 for d in stages.values()), default=0.0),
            "stages": stages, "load_avg": os.getloadavg()}


def power_fit(x: list[float], y: list[float]) -> tuple[float, float] | None:
    """(a, b) of y = a x^b, least squares in log-log; None with fewer than 2 positive points."""
    pts = [(a, b) for a, b in zip(x, y) if a and b and a > 0 and b > 0]
    if len(pts) < 2 or len({a for a, _ in pts}) < 2:
        return None
    lx, ly = np.log([a for a, _ in pts]), np.log([b for _, b in pts])
    b, la = np.polyfit(lx, ly, 1)
    return float(np.exp(la)), float(b)


def affine_fit(x: list[float], y: list[float]) -> tuple[float, float] | None:
    """(c, k) of y = c + k x, least squares; None with fewer than 2 distinct x."""
    pts = [(a, b) for a, b in zip(x, y) if a is not None and b is not None]
    if len(pts) < 2 or len({a for a, _ in pts}) < 2:
        return None
    k, c = np.polyfit([a for a, _ in pts], [b for _, b in pts], 1)
    return float(c), float(k)


def extrapolate(rows: list[dict]) -> dict:
    """Fits per stage and for the whole run, their value at TARGET_POLYGONS, and where each limit breaks.

    Wall seconds, CPU, DAG time, overhead and RSS get a power law (the exponent says how a cost grows
    with its work); job counts an affine fit (a fixed number of whole-scene jobs plus jobs per polygon).

    Args:
        rows: ``run_size`` results, smallest first.

    Returns:
        {"stages": {rule: {...}}, "run": {...}, "breaks": [(polygons, what, exponent)], "target_photos": n}.
    """
    photos_per_poly = rows[-1]["photos"] / rows[-1]["polygons"]
    target = {"polygons": TARGET_POLYGONS, "photos": TARGET_POLYGONS * photos_per_poly}
    out: dict = {"stages": {}, "run": {}, "breaks": [], "target_photos": round(target["photos"])}

    def fit_at(work_key: str, values: list, affine: bool = False) -> dict:
        work = [r[work_key] for r in rows]
        res: dict = {"work": work_key, "exponent": None, "at_target": None, "affine": affine}
        fit = affine_fit(work, values) if affine else power_fit(work, values)
        if fit and affine:
            res["per_unit"], res["at_target"], res["fit"] = fit[1], fit[0] + fit[1] * target[work_key], fit
        elif fit:
            res["exponent"], res["at_target"], res["fit"] = fit[1], fit[0] * target[work_key] ** fit[1], fit
        return res

    for rule in sorted({k for r in rows for k in r["stages"]}):
        wk = "photos" if rule in PHOTO_STAGES else "polygons"
        st = [r["stages"].get(rule, {}) for r in rows]
        wall = [s.get("wall_s") if s.get("wall_s") is not None else s.get("log_s") for s in st]
        out["stages"][rule] = {"wall_s": fit_at(wk, wall),
                               "jobs": fit_at("polygons", [s.get("jobs") for s in st], affine=True),
                               "max_rss_mb": fit_at(wk, [s.get("max_rss_mb") for s in st]),
                               "max_job_s": fit_at(wk, [s.get("max_job_s") for s in st])}
    for q in ("wall_s", "cpu_s", "dag_s", "overhead_s", "peak_rss_mb"):
        out["run"][q] = fit_at("polygons", [r[q] for r in rows])
    out["run"]["jobs"] = fit_at("polygons", [r["jobs"] for r in rows], affine=True)
    checks = [("jobs", "the run", out["run"]["jobs"]), ("dag_s", "the run", out["run"]["dag_s"]),
              ("overhead_s", "the run", out["run"]["overhead_s"])]
    checks += [("peak_rss_mb", rule, f["max_rss_mb"]) for rule, f in out["stages"].items()]
    checks += [("serial_s", rule, out["stages"][rule]["max_job_s"]) for rule in PHOTO_STAGES if rule in out["stages"]]
    for key, who, f in checks:
        limit, what = LIMITS[key]
        if not f.get("fit"):
            continue
        a, b = f["fit"]
        if f["affine"]:
            if b <= 0:
                continue
            work_at = (limit - a) / b
        else:
            if b <= 0.05:  # flat within the measurement: no crossing to extrapolate
                continue
            work_at = (limit / a) ** (1 / b)
        poly_at = work_at / photos_per_poly if f["work"] == "photos" else work_at
        out["breaks"].append((poly_at, f"{who}: {what}", f.get("exponent") or f.get("per_unit")))
    out["breaks"].sort()
    return out


def _f(x, fmt: str = ".1f") -> str:
    return "-" if x is None else format(x, fmt)


def write(stem: Path, rows: list[dict], ext: dict, mach: dict, args, note: str, command: str | None = None) -> str:
    """<stem>.md and <stem>.json; returns the markdown. ``command``: the one that ran (default: this one)."""
    command = command or "python evaluation/bench_scale.py " + shlex.join(sys.argv[1:])
    lines = [C.header(
        "Scale: the whole workflow on generated districts (issue #32)", command, mach,
        [f"Sizes run: {', '.join(str(r['polygons']) + ' polygons / ' + str(r['photos']) + ' photos' for r in rows)}"
         f" ({note}).",
         f"Scenes: `difftex.synth.district` (seed {args.seed}, {args.views} photos per building, 160x120); "
         f"workflow: `snakemake --cores {args.cores} --config scene=S preset=fast 'run={{evaluate: false}}'`; "
         "the whole-scene stages in parts of `run.filter_photos_per_job` photos and spatial tiles of "
         "`run.visibility_polygons_per_job` polygons (config/config.yaml's defaults), each merged by one job.",
         "Stage wall: the sum of its jobs' wall seconds (benchmark files; jobs run side by side, so it can exceed "
         "the run's wall). CPU: Snakemake's sampled `cpu_time`, a lower bound per job (bench_speed.py says why); "
         "the run's CPU is all child processes' (rusage). Jobs: Snakemake's log, local rules included. "
         "Overhead: the command's wall time during which no job ran (DAG building, checkpoint re-evaluation, "
         "start-up, polling), from the log's 1-second timestamps.",
         "DAG -n: `snakemake -n`, which stops at the visibility checkpoint, so it times the DAG of the "
         "whole-scene stages only; the per-polygon jobs are added to the DAG after the checkpoint, inside the run, "
         "and that time is in the overhead column.",
         "Exponent b of y = a work^b, least squares in log-log over the sizes (work: photos for the filter and "
         "visibility stages, their parts and merges; polygons otherwise); at 10,000 polygons: the fit evaluated "
         "there with photos in the largest "
         "size's proportion. Fixed costs (interpreter and torch start-up) dominate small sizes and pull the "
         "exponents below their asymptotic values: the smoke sizes' extrapolation is a lower bound."])]
    lines += ["## Runs", "", "| polygons | photos | generate (s) | DAG -n (s) | wall (s) | CPU (s) | busy (s) | "
              "overhead (s) | jobs | peak RSS (MB) | unseen polygons | load avg |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['polygons']} | {r['photos']} | {r['generate_s']:.1f} | {r['dag_s']:.1f} | "
                     f"{r['wall_s']:.1f} | {r['cpu_s']:.1f} | {r['busy_s']:.0f} | {r['overhead_s']:.0f} | "
                     f"{r['jobs']} | {r['peak_rss_mb']:.0f} | {r['unseen']} | {r['load_avg'][0]:.1f} |")
    lines += ["", "## Per stage", "", "Per size: jobs / wall s (sum over jobs; in brackets the same from the log's "
              "job start and finish times, which local rules without a benchmark file have too) / the longest "
              "job's wall s / CPU s / peak RSS "
              "MB of its largest job; then the fitted exponent of wall (the log's where there is no benchmark), jobs "
              "and RSS against the stage's work, and wall and peak RSS extrapolated to 10,000 polygons.", "",
              "| stage | " + " | ".join(f"{r['polygons']} polygons" for r in rows) +
              " | b wall | b jobs | b RSS | wall at 10k (s) | jobs at 10k | RSS at 10k (MB) |",
              "|---|" + "---|" * (len(rows) + 6)]
    for rule, fits in ext["stages"].items():
        cells = []
        for r in rows:
            s = r["stages"].get(rule)
            cells.append("-" if s is None else f"{s['jobs']} / {_f(s['wall_s'])} ({_f(s.get('log_s'), '.0f')}) / "
                                               f"{_f(s.get('max_job_s'))} / {_f(s['cpu_s'])} / "
                                               f"{_f(s['max_rss_mb'], '.0f')}")
        fw, fj, fr = fits["wall_s"], fits["jobs"], fits["max_rss_mb"]
        lines.append(f"| {rule} | " + " | ".join(cells) + f" | {_f(fw['exponent'], '.2f')} | "
                     f"{_f(fj.get('per_unit'), '.2f')} | {_f(fr['exponent'], '.2f')} | {_f(fw['at_target'], '.0f')} | "
                     f"{_f(fj['at_target'], '.0f')} | {_f(fr['at_target'], '.0f')} |")
    lines += ["", f"## The whole run at 10,000 polygons ({ext['target_photos']} photos)", "",
              "| quantity | exponent (or slope) | at 10,000 polygons |", "|---|---|---|"]
    for q, f in ext["run"].items():
        slope = f"{_f(f.get('per_unit'), '.2f')} per polygon" if f["affine"] else _f(f["exponent"], ".2f")
        lines.append(f"| {q} | {slope} | {_f(f['at_target'], '.0f')} |")
    lines += ["", "## What breaks first past the largest size", "",
              "Where each fit crosses its limit (job counts: affine, per polygon; the rest: power law); fits "
              "flat within the measurement (exponent <= 0.05) are left out.", ""]
    if ext["breaks"]:
        for poly, what, b in ext["breaks"]:
            where = f"about {poly:,.0f}" if poly < 1e7 else "beyond 10 million (out of the fit's reach)"
            lines.append(f"- at {where} polygons: {what} (slope {b:.2f})")
    else:
        lines.append("- no limit is crossed by any fit with a positive exponent")
    md = "\n".join(lines) + "\n"
    C.write_outputs(stem, md, {"machine": mach, "args": vars(args), "command": command, "rows": rows,
                               "extrapolation": ext})
    return md


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--buildings", default="12,36,120", help="district sizes, buildings (about 9 polygons each)")
    ap.add_argument("--views", type=int, default=10, help="photos per building")
    ap.add_argument("--smoke", action="store_true", help="1, 3 and 10 buildings of 6 photos: minutes on 2 cores")
    ap.add_argument("--cores", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--work", default="evaluation/out/bench_scale")
    ap.add_argument("--out", default="evaluation/results/bench_scale")
    ap.add_argument("--rewrite", action="store_true", help="only rewrite <out>.md from <out>.json's runs")
    args = ap.parse_args(argv)
    if args.rewrite:
        import json

        data = json.loads(Path(args.out).with_suffix(".json").read_text())
        old = argparse.Namespace(**data["args"])
        for r in data["rows"]:
            logs = sorted((Path(old.work) / "runs" / f"district{r['buildings']}" / ".snakemake" / "log").glob("*.log"))
            if logs:
                sec = parse_log(logs[-1].read_text())["seconds"]
                for rule, st in r["stages"].items():
                    st["log_s"] = sec.get(rule)
        print(write(Path(args.out), data["rows"], extrapolate(data["rows"]), data["machine"], old,
                    "smoke" if old.smoke else "full",
                    data.get("command") or "python evaluation/bench_scale.py" + (" --smoke" if old.smoke else "")))
        return 0
    if args.smoke:
        args.buildings, args.views = "1,3,10", 6
    sizes = [int(x) for x in args.buildings.split(",")]
    if len(sizes) < 2 or min(sizes) < 1 or args.views < 1 or args.cores < 1:
        ap.error("--buildings needs at least two sizes >= 1; --views and --cores >= 1")
    mach = C.machine()
    rows = []
    for n in sorted(sizes):
        rows.append(run_size(n, args.views, args.cores, Path(args.work), args.seed))
        r = rows[-1]
        print(f"bench_scale: {r['polygons']} polygons, {r['photos']} photos: {r['wall_s']:.0f} s wall, "
              f"DAG {r['dag_s']:.1f} s, overhead {r['overhead_s']:.0f} s, {r['jobs']} jobs, "
              f"peak {r['peak_rss_mb']:.0f} MB", flush=True)
        if len(rows) >= 2:
            write(Path(args.out), rows, extrapolate(rows), mach, args, "smoke" if args.smoke else "full")
    print(Path(args.out).with_suffix(".md").read_text())
    return 0


if __name__ == "__main__":
    C.run_script(main)
