"""The per-polygon `texture` stage of a finished run, polygon by polygon, on a chosen device.

    python evaluation/bench_texture_stage.py --results results/herzjesu-p8 --scene ../shared/data/herzjesu-p8 \
        --device cuda --out evaluation/results/bench_texture_stage_gpu

Re-runs exactly the command the workflow's `texture` rule runs (`difftex texture`, same
visibility file and stage config, a fresh process per polygon, so torch's import and the scene's
loading are in the figures) into a scratch folder, with ``compute.device`` set to ``--device``.
For the GPU machine lent through the `device` tool (no Snakemake there): the upstream stages run
on any machine, their results travel with the scene, and this times the stage that holds the
method's cost. Writes <out>.json and <out>.md with the machine; per polygon: wall seconds of the
process, the method's own seconds (stats.json), iterations, texels, peak RSS and, on CUDA, peak
GPU memory. With ``--split``, the split run's three commands per polygon instead (`difftex
initialize`, `optimize`, `compose`; only `optimize` on the device), each timed.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def machine() -> dict:
    import torch

    info = {
        "cpu": platform.processor() or platform.machine(),
        "cores": os.cpu_count(),
        "torch": torch.__version__,
        "python": platform.python_version(),
    }
    if torch.cuda.is_available():
        info["gpu"] = torch.cuda.get_device_name(0)
    return info


def _difftex(args: list[str], threads: int) -> float:
    """Run one `difftex` command in a fresh process; its wall seconds."""
    cmd = [sys.executable, "-c", "import sys; from difftex.cli import main; sys.exit(main())", *args]
    path = str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")
    env = dict(os.environ, OMP_NUM_THREADS=str(threads), PYTHONPATH=path)
    t0 = time.perf_counter()
    p = subprocess.run(cmd, env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if p.returncode != 0:
        raise SystemExit(f"bench_texture_stage: difftex {args[0]} failed:\n{p.stdout[-2000:]}{p.stderr[-2000:]}")
    return wall


def run_polygon(
    results: Path, scene: Path, pid: str, config: Path, compute_yaml: Path, threads: int, scratch: Path,
    split: bool = False,
) -> dict:
    """Polygon ``pid`` through the workflow's commands: one `difftex texture` process, or with
    ``split`` the `initialize`, `optimize` and `compose` processes of a split run; wall times and stats."""
    out = scratch / pid
    vis = str(results / "visibility" / f"{pid}.npz")
    common = ["--threads", str(threads), "--scene", str(scene), "--visibility", vis, "--config", str(config)]
    walls = {}
    if split:
        crops = scratch / "init" / pid / "crops.npz"
        walls["initialize_s"] = _difftex(["initialize", *common, "--out", str(crops)], threads)
        walls["optimize_s"] = _difftex(
            ["optimize", "--no-progress", *common, "--init", str(crops), "--out-dir", str(out),
             "--compute-config", str(compute_yaml)], threads)
        walls["compose_s"] = _difftex(["compose", "--optimized", str(out)], threads)
        crops.unlink()
    else:
        walls["texture_s"] = _difftex(
            ["texture", "--no-progress", *common, "--compute-config", str(compute_yaml), "--out-dir", str(out)],
            threads)
    st = json.loads((out / "stats.json").read_text())
    return {
        "polygon": pid,
        "wall_s": round(sum(walls.values()), 2),
        **{k: round(v, 2) for k, v in walls.items()},
        "method_s": round(st["time_total_s"], 2),
        "device": st.get("device"),
        "texels": st["texels"],
        "long_side": max(st["levels"][-1]["shape"]),
        "iterations": sum(lv["iterations"] for lv in st["levels"]),
        "align_s": round(sum(a["time_s"] for a in st.get("alignment", [])), 2),
        "cuda_peak_mb": round(st["cuda_peak_bytes"] / 2**20) if "cuda_peak_bytes" in st else None,
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--results", required=True, type=Path, help="a run's results folder (visibility/, config/)")
    ap.add_argument("--scene", required=True, type=Path)
    ap.add_argument("--device", default="auto", choices=["auto", "cpu", "cuda"])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--polygons", help="comma-separated ids (default: every visibility file)")
    ap.add_argument("--split", action="store_true",
                    help="the split run's three commands per polygon (initialize, optimize, compose)")
    ap.add_argument("--out", required=True)
    a = ap.parse_args(argv)
    pids = a.polygons.split(",") if a.polygons else sorted(p.stem for p in (a.results / "visibility").glob("*.npz"))
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        compute = Path(tmp) / "compute.yaml"
        compute.write_text(f"compute:\n  device: {a.device}\n")
        config = sorted((a.results / "config").glob("texture-*.yaml"))[-1]
        t0 = time.perf_counter()
        for pid in pids:
            rows.append(run_polygon(a.results, a.scene, pid, config, compute, a.threads, Path(tmp), a.split))
            print(f"bench_texture_stage: {pid}: {rows[-1]}", flush=True)
        total = time.perf_counter() - t0
    rss = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
    res = {
        "command": "python evaluation/bench_texture_stage.py " + " ".join(argv if argv is not None else sys.argv[1:]),
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "machine": machine(),
        "device": a.device,
        "threads": a.threads,
        "split": a.split,
        "total_wall_s": round(total, 1),
        "peak_rss_mb": round(rss),
        "polygons": rows,
    }
    out = Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(res, indent=1))
    m = res["machine"]
    lines = [
        f"# The `texture` stage on {a.device}: {a.scene.name}",
        "",
        f"Command: `{res['command']}`  ",
        f"Date: {res['date']}  ",
        f"Machine: {m['cpu']}, {m['cores']} cores, {m.get('gpu', 'no GPU')}, torch {m['torch']}, {a.threads} threads",
        "",
        ("Per polygon, the split run's `difftex initialize`, `optimize` and `compose` processes"
         if a.split else "One `difftex texture` process per polygon")
        + f", one after another: {res['total_wall_s']} s in all, peak RSS {res['peak_rss_mb']} MB. "
        "Wall: the processes (import, scene, decode, method, outputs); method: stats.json's "
        "time_total_s; align: its alignment part.",
        "",
        "| polygon | device | texels | long side | iterations | wall (s) | "
        + ("initialize / optimize / compose (s) | " if a.split else "")
        + "method (s) | align (s) | GPU peak (MB) |",
        "|---|---|---|---|---|---|" + ("---|" if a.split else "") + "---|---|---|",
    ]
    for r in rows:
        gpu_mb = r["cuda_peak_mb"] if r["cuda_peak_mb"] is not None else ""
        parts = f"{r['initialize_s']} / {r['optimize_s']} / {r['compose_s']} | " if a.split else ""
        lines.append(
            f"| {r['polygon']} | {r['device']} | {r['texels']} | {r['long_side']} | {r['iterations']} | "
            f"{r['wall_s']} | {parts}{r['method_s']} | {r['align_s']} | {gpu_mb} |"
        )
    out.with_suffix(".md").write_text("\n".join(lines) + "\n")
    print(f"bench_texture_stage: {len(rows)} polygons in {total:.0f} s -> {out.with_suffix('.md')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
