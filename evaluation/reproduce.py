"""Re-make the headline results in one command, each table with its peers in the same run, stamped.

    python evaluation/reproduce.py                    # every table in full: many hours on 2 cores
    python evaluation/reproduce.py --smoke            # a tiny version of every table: minutes
    python evaluation/reproduce.py --only table1,speed
    python evaluation/reproduce.py --smoke --dry-run  # the commands, without running them
    python evaluation/reproduce.py --smoke --rewrite  # only rebuild the combined markdown

The tables (``--only`` takes their names): ``table1`` (the survey synthetic buildings against
ground truth), ``table2`` (the shared real scenes, held-out photos), ``ablation``, ``tradeoff``
(the speed/quality curve: several resolutions per preset), ``speed`` (the workflow per preset
against texrecon) and ``scale`` (generated districts). Each is one or more calls of the existing
script (evaluation/table1.py, ...), run as a child process so that one failing table does not
stop the others; its log goes to ``<work>/logs/``.

Where the results go:

- full run: ``evaluation/results/<table>/<name>.{md,json}`` (the trade-off's curve as .png
  beside them) and the combined ``docs/results.md``;
- ``--smoke``: ``evaluation/results/smoke/<table>/...`` and ``evaluation/results/smoke/results.md``;
  it never touches ``docs/results.md`` or the full run's tables.

Every .md and .json written is stamped (evaluation/stamp.py) with the difftex version and the hash
of the defaults it was made with; tests/test_results_stamp.py fails once a default changes and a
stamped result is not re-made. The combined markdown is rebuilt from whatever tables the output
folder holds, so ``--only`` re-makes one table and keeps the others' sections as they were.
"""

from __future__ import annotations

import argparse
import datetime as _dt
import os
import shlex
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from evaluation import stamp as S  # noqa: E402
from evaluation.common import run_script  # noqa: E402
from evaluation.reproduce_summary import TITLES, write_summary  # noqa: E402

TABLES = tuple(TITLES)
SURVEY = ("gable", "lblock", "courtyard")
REAL = ("herzjesu-p8", "lund-door", "sceaux-castle")
SHARED = Path("../shared/data")  # relative to the repository root, where every command runs
# the published method (difftex-paper: the render loss, long caps) wants a GPU at full density; the
# trade-off curve holds its row at 512 texels
# with and without the survey scene's dense cloud (difftex synth-dense), the true-relief bound,
# and the reprojection peer (texrecon on the dense mesh, baked)
ALL_METHODS = ("difftex,difftex-dense,difftex-true-relief,average,frontal,mrf,texrecon,meshlab-blend,meshlab-face,"
               "reprojection")


@dataclass
class Job:
    """One call of an evaluation script; its outputs are ``<out>/<table>/<name>.*``."""

    table: str
    name: str
    script: str
    args: list[str]
    needs: list[str] = field(default_factory=list)  # scene folders that must exist first

    def argv(self, out: Path, work: Path) -> list[str]:
        stem = out / self.table / self.name
        return [sys.executable, f"evaluation/{self.script}.py", *self.args,
                "--work", str(work / self.table / self.name), "--out", str(stem)]


def full_plan(threads: int, survey: tuple[str, ...] = SURVEY) -> list[Job]:
    """The headline tables: the defaults at the photos' full texel density (the density a user
    gets without a preset), every method and peer at the same texels; the speed bench on a
    200-photo survey building against texrecon."""
    t = ["--threads", str(threads)]
    jobs = [Job("table1", f"survey_{b}", "table1",
                ["--scene", f"data/synth/survey/{b}", "--preset", "default",
                 "--methods", ALL_METHODS, *t], [f"data/synth/survey/{b}"]) for b in survey]
    for b in survey:  # the field the dense cloud gives, and the sweep from the photos alone
        scene = f"data/synth/survey/{b}"
        jobs.append(Job("relief", f"dense_{b}", "relief_bound", ["--accuracy", "--dense", "auto", "--scene", scene],
                        [scene]))
        jobs.append(Job("relief", f"sweep_{b}", "relief_bound", ["--accuracy", "--scene", f"data/synth/survey/{b}"],
                        [f"data/synth/survey/{b}"]))
    jobs.append(Job("table2", "real_scenes", "table2",
                    ["--scenes", ",".join(str(SHARED / s) for s in REAL),
                     "--preset", "default", "--holdout", "2", *t], [str(SHARED / s) for s in REAL]))
    jobs.append(Job("ablation", "survey_gable", "ablation",
                    ["--scene", "data/synth/survey/gable", "--polygons", "all", "--long-side", "256",
                     "--preset", "default", *t], ["data/synth/survey/gable"]))
    runs = ",".join(f"{p}@{s}" for p in ("fast", "balanced", "default") for s in ("256", "512", "auto"))
    jobs.append(Job("tradeoff", "survey_gable", "tradeoff",
                    ["--scene", "data/synth/survey/gable", "--runs", runs + ",paper@512",
                     "--baselines", "average,mrf,texrecon,meshlab-blend", "--polygons", "all", *t],
                    ["data/synth/survey/gable"]))
    jobs.append(Job("speed", f"survey_{survey[0]}", "bench_speed",
                    ["--scene", f"data/synth/survey/{survey[0]}", "--presets", "fast,balanced,default",
                     "--repeats", "2", "--cores", str(threads)], [f"data/synth/survey/{survey[0]}"]))
    jobs.append(Job("scale", "districts_smoke", "bench_scale", ["--smoke", "--cores", str(threads)]))
    return jobs


def smoke_plan(threads: int, tiny: str) -> list[Job]:
    """A tiny version of every table: the survey-tiny building, one small real scene, few methods
    (a peer in each), small maps; the same scripts and code paths as the full run."""
    t = ["--threads", str(threads)]
    door = str(SHARED / "lund-door")  # the shared scene with the smallest photos
    return [
        Job("table1", "survey_tiny", "table1",
            ["--scene", tiny, "--long-side", "128", "--preset", "default",
             "--methods", "difftex,difftex-dense,average,mrf,texrecon,meshlab-blend,reprojection", *t], [tiny]),
        Job("relief", "dense_tiny", "relief_bound", ["--accuracy", "--dense", "auto", "--scene", tiny], [tiny]),
        Job("table2", "lund_door", "table2",
            ["--scenes", door, "--long-side", "96", "--preset", "default", "--holdout", "1",
             "--render-long-side", "256", "--methods", "difftex,average,texrecon", *t], [door]),
        Job("ablation", "survey_tiny", "ablation",
            ["--scene", tiny, "--polygons", "all", "--long-side", "64", "--preset", "default",
             "--variants", "full,no_persp,paper", "--peers", "texrecon", *t], [tiny]),
        Job("tradeoff", "survey_tiny", "tradeoff",
            ["--scene", tiny, "--runs", "fast@64,fast@128,default@64,default@128",
             "--baselines", "average,texrecon", "--polygons", "all", *t], [tiny]),
        Job("speed", "survey_tiny", "bench_speed",
            ["--scene", tiny, "--presets", "fast", "--repeats", "1", "--cores", str(threads)], [tiny]),
        Job("scale", "districts_tiny", "bench_scale",
            ["--buildings", "1,2", "--views", "4", "--cores", str(threads)]),
    ]


def scene_commands(jobs: list[Job], tiny: str) -> list[list[str]]:
    """``difftex synth`` for every synthetic scene a job needs that is not there yet (the shared
    real scenes cannot be made: a job that needs a missing one is reported, not run)."""
    cmds = []
    for need in dict.fromkeys(n for j in jobs for n in j.needs):
        if _scene_ready(Path(need)) or not (need == tiny or need.startswith("data/synth/survey/")):
            continue
        if need == tiny:
            cmds.append(["synth", "--preset", "survey-tiny", "--out", tiny, "--dense"])
        else:  # one building of the survey at a time: another run may be rendering the others
            cmds.append(["synth", "--preset", "survey", "--out", "data/synth/survey", "--building", Path(need).name,
                         "--dense"])
    for need in dict.fromkeys(n for j in jobs for n in j.needs):  # a scene made before synth wrote its cloud
        synthetic = need == tiny or need.startswith("data/synth/survey/")
        if synthetic and _scene_ready(Path(need)) and not (ROOT / need / "dense").is_dir():
            cmds.append(["synth-dense", "--scene", need])
    return [[sys.executable, "-m", "difftex", *c, "--quiet"] for c in cmds]


def _scene_ready(scene: Path) -> bool:
    path = ROOT / scene
    synthetic = (path / "ground_truth").exists() or "synth" in scene.parts or scene.name == "survey-tiny"
    if synthetic:  # what table1.ensure_synth checks: else it would generate the *tiny* preset there
        return (path / "ground_truth" / "frames").is_dir() and (path / "proxy.obj").is_file()
    return (path / "proxy.obj").is_file() and (path / "images").is_dir()


def run_logged(argv: list[str], log: Path, env: dict) -> tuple[int, float]:
    """Run ``argv`` in the repository root with its output in ``log``; (exit status, wall s)."""
    log.parent.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    with open(log, "w") as fh:
        rc = subprocess.run(argv, cwd=ROOT, env=env, stdout=fh, stderr=subprocess.STDOUT).returncode
    return rc, time.perf_counter() - t0


def _last_line(log: Path) -> str:
    try:
        lines = [ln for ln in log.read_text(errors="replace").splitlines() if ln.strip()]
    except OSError:
        return ""
    return lines[-1][:300] if lines else ""


def run_job(job: Job, out: Path, work: Path, env: dict, rerun: str) -> dict:
    """Run one job and stamp what it wrote; returns its record for the summary."""
    argv = job.argv(out, work)
    log = work / "logs" / f"{job.table}_{job.name}.log"
    missing = [n for n in job.needs if not _scene_ready(Path(n))]
    rec = {"table": job.table, "name": job.name, "command": shlex.join(["python", *argv[1:]]), "log": str(log)}
    if missing:
        print(f"reproduce: {job.table}/{job.name}: not run, missing {', '.join(missing)}", flush=True)
        return dict(rec, rc=None, error=f"missing {', '.join(missing)}")
    before = S.current_stamp()
    print(f"reproduce: {job.table}/{job.name} ...", flush=True)
    rc, wall = run_logged(argv, log, env)
    rec.update(rc=rc, wall_s=round(wall, 1))
    if rc != 0:
        print(f"reproduce: {job.table}/{job.name} FAILED (exit {rc}) after {wall:.0f} s: {_last_line(log)} "
              f"(log: {log})", flush=True)
        return dict(rec, error=_last_line(log))
    if S.current_stamp() != before:
        # another change to the defaults landed while the job ran: stamp what it started with, so
        # the stamp check calls the result stale instead of vouching for defaults it never saw
        print(f"reproduce: warning: the defaults changed while {job.table}/{job.name} ran; "
              "its stamp names the ones it started with", flush=True)
    stamp = dict(before, wall_s=rec["wall_s"],
                 date_utc=_dt.datetime.now(_dt.UTC).strftime("%Y-%m-%d %H:%M UTC"))
    files = sorted(f for f in (out / job.table).glob(f"{job.name}.*") if f.suffix in (".md", ".json"))
    for f in files:
        S.stamp_file(f, stamp, rerun)
    print(f"reproduce: {job.table}/{job.name} done in {wall:.0f} s ({len(files)} files stamped)", flush=True)
    return rec


def child_env(texrecon: str | None) -> dict:
    """The scripts' environment: the venv's commands first on PATH (snakemake, difftex), texrecon
    where ``--texrecon`` says (else DIFFTEX_TEXRECON or PATH, as the peer runner looks)."""
    env = dict(os.environ, PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}")
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    if texrecon:
        env["DIFFTEX_TEXRECON"] = str(Path(texrecon).resolve())
    return env


def parse_args(argv):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--smoke", action="store_true", help="a tiny version of every table (minutes on 2 cores)")
    ap.add_argument("--only", default="", help=f"comma-separated subset of: {', '.join(TABLES)}")
    ap.add_argument("--out", default=None, help="results folder (default: evaluation/results, "
                    "or evaluation/results/smoke with --smoke)")
    ap.add_argument("--summary", default=None, help="combined markdown (default: docs/results.md, "
                    "or <out>/results.md with --smoke or --out)")
    ap.add_argument("--work", default=None, help="work folder (default: evaluation/out/reproduce[_smoke])")
    ap.add_argument("--survey", default=",".join(SURVEY),
                    help=f"comma-separated survey buildings of Table 1 (default: {','.join(SURVEY)}); the "
                    "speed bench runs on the first")
    ap.add_argument("--threads", type=int, default=2, help="torch threads per table; Snakemake cores")
    ap.add_argument("--texrecon", default=None, help="texrecon program (default: DIFFTEX_TEXRECON or PATH)")
    ap.add_argument("--dry-run", action="store_true", help="print the commands, run nothing")
    ap.add_argument("--rewrite", action="store_true",
                    help="run nothing: only rebuild the combined markdown from the tables in --out")
    args = ap.parse_args(argv)
    only = [n for n in args.only.split(",") if n]
    bad = [n for n in only if n not in TABLES]
    if bad:
        ap.error(f"--only: unknown table {', '.join(bad)} (known: {', '.join(TABLES)})")
    if args.threads < 1:
        ap.error("--threads must be at least 1")
    args.survey = tuple(b for b in args.survey.split(",") if b)
    unknown = [b for b in args.survey if b not in SURVEY]
    if unknown or not args.survey:
        ap.error(f"--survey: unknown building {', '.join(unknown) or '(none)'} (known: {', '.join(SURVEY)})")
    if args.texrecon and not Path(args.texrecon).is_file():
        ap.error(f"--texrecon: {args.texrecon} is not a file")
    args.only = only or list(TABLES)
    default_out = args.out is None
    args.out = Path(args.out or ("evaluation/results/smoke" if args.smoke else "evaluation/results"))
    if args.summary is None:
        args.summary = "docs/results.md" if default_out and not args.smoke else str(args.out / "results.md")
    args.summary = Path(args.summary)
    args.work = Path(args.work or ("evaluation/out/reproduce_smoke" if args.smoke else "evaluation/out/reproduce"))
    return args


def rerun_command(args, table: str) -> str:
    """The command that re-makes one table as this run made it (the stamp check prints it)."""
    parts = ["python", "evaluation/reproduce.py"] + (["--smoke"] if args.smoke else []) + ["--only", table]
    if not args.smoke and args.survey != SURVEY and table in ("table1", "speed"):
        parts += ["--survey", ",".join(args.survey)]
    if args.out != Path("evaluation/results/smoke" if args.smoke else "evaluation/results"):
        parts += ["--out", str(args.out)]
    return shlex.join(parts)


def main(argv=None) -> int:
    args = parse_args(argv)
    os.chdir(ROOT)  # every path in the plan is relative to the repository root
    tiny = str(args.work / "scenes" / "survey-tiny")
    plan = smoke_plan(args.threads, tiny) if args.smoke else full_plan(args.threads, args.survey)
    jobs = [j for j in plan if j.table in args.only]
    env = child_env(args.texrecon)
    synth = scene_commands(jobs, tiny)
    if args.rewrite:
        write_summary(args.summary, args.out, smoke=args.smoke, records=[])
        print(f"reproduce: rewrote {args.summary} from {args.out}")
        return 0
    if args.dry_run:
        for c in synth + [j.argv(args.out, args.work) for j in jobs]:
            print(shlex.join(["python", *c[1:]]))
        return 0
    t0 = time.perf_counter()
    print(f"reproduce: {'smoke' if args.smoke else 'full'} run of {', '.join(args.only)}; load average "
          f"{os.getloadavg()[0]:.1f}; {S.stamp_line(S.current_stamp())}", flush=True)
    for i, c in enumerate(synth):
        rc, wall = run_logged(c, args.work / "logs" / f"synth_{i}.log", env)
        print(f"reproduce: {shlex.join(['difftex', *c[3:]])}: exit {rc} in {wall:.0f} s", flush=True)
    records = [run_job(j, args.out, args.work, env, rerun_command(args, j.table)) for j in jobs]
    write_summary(args.summary, args.out, smoke=args.smoke, records=records)
    failed = [f"{r['table']}/{r['name']}" for r in records if r.get("rc") != 0]
    print(f"reproduce: {len(records) - len(failed)} of {len(records)} tables made in "
          f"{time.perf_counter() - t0:.0f} s; load average now {os.getloadavg()[0]:.1f}; summary {args.summary}"
          + (f"; failed or not run: {', '.join(failed)}" if failed else ""), flush=True)
    return 1 if failed else 0


if __name__ == "__main__":
    run_script(main)
