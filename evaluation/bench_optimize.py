"""Time and memory of the per-polygon optimizer at several texture sizes (and both loss modes).

    python evaluation/bench_optimize.py --scene ../shared/data/herzjesu-p8 --polygon facade \
        --sizes 512 1024 2048 --modes texel render --iters 10 --out evaluation/bench_optimize

Visibility is computed once at the largest size and resampled to the smaller ones. Each
(size, mode) runs in a fresh subprocess so that its peak resident memory (ru_maxrss) is its own.
With ``--iters N`` every level runs exactly N iterations (no convergence stop), so the per-level
iteration time is measured on equal terms; the time of a full run is then estimated as
setup + first iteration + (cap - 1) x the median later iteration, per level, for the default
caps (both are reported). The first iteration is separate because it carries torch.compile's
cost; ``--compile off auto`` compares eager with the default (compiled at large levels).

The bound: one iteration must at least read the level's data once (mapped colours, Q, the
perspective cost, the activation; render mode also its pixel sets) and read and write the
logits, their gradient and Adam's two moments: K x H x W x 57 bytes plus the pixel sets'. That
count divided by the memory bandwidth of one thread (a large tensor copy, measured in the same
run) is the time no implementation can beat on this machine; the table gives each level's
iteration time as a multiple of it.

``--python A B``: run every case under each interpreter (e.g. a venv with another torch build),
same machine, same run (the torch stack comparison of the issue on torch builds).
Writes <out>.json and <out>.md with the machine description.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shlex
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from evaluation import common as C  # noqa: E402


def machine() -> dict:
    """The shared machine description (evaluation/common.py) plus what this benchmark adds."""
    m = C.machine()
    import torch

    m["cuda"] = torch.cuda.get_device_name(0) if torch.cuda.is_available() else None
    return m


def visibility_file(scene: str, polygon: str, size: int, cache: Path) -> Path:
    from difftex.geometry.visibility import save_visibility, scene_visibility
    from difftex.scene.loading import load_scene

    path = cache / f"{Path(scene).name}_{polygon}_{size}.npz"
    if path.is_file():
        return path
    sc = load_scene(scene, check_images=False)
    names = [p.name for p in sc.photos]
    vis = scene_visibility(sc.proxy, sc.photos, sc.up, {polygon: names}, size, progress=False)
    (v,) = [v for v in vis if v.polygon_id == polygon]
    save_visibility(path, v)
    return path


# bytes one iteration must touch per slot: colours (3 x 4), Q (4), cost (4), active (1) read;
# logits (4) read, gradient (4) written and read, logits and Adam's moments (3 x 4) read and written
BYTES_PER_SLOT_ITER = 12 + 4 + 4 + 1 + 4 + 8 + 24


def copy_bandwidth(mib: int = 256, repeats: int = 5) -> float:
    """Bytes per second of a large float32 tensor copy (read + write) on the current threads."""
    import torch

    a = torch.rand(mib * 2**18)
    b = torch.empty_like(a)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        b.copy_(a)
        times.append(time.perf_counter() - t0)
    return 2 * a.numel() * 4 / sorted(times)[len(times) // 2]


def run_one(args) -> dict:
    import dataclasses

    import torch

    from difftex.geometry.visibility import load_visibility
    from difftex.method.config import ComputeConfig, OptimizeConfig
    from difftex.method.loop import optimize_polygon
    from difftex.sampling.photos import PhotoSet, polygon_input_from_visibility
    from difftex.sampling.texels import resample_nearest
    from difftex.scene.loading import load_scene

    torch.set_num_threads(args.threads)
    sc = load_scene(args.scene, check_images=False)
    vis = load_visibility(args.vis)
    inp = polygon_input_from_visibility(vis, {p.name: p for p in sc.photos}, up=sc.up)
    if max(inp.frame.shape) != args.one:
        frame = inp.frame.resized(args.one)
        inp = dataclasses.replace(inp, frame=frame, texel_visible=resample_nearest(inp.texel_visible, inp.frame, frame),
                                  texel_mask=resample_nearest(inp.texel_mask, inp.frame, frame))
    kw = dict(loss_mode=args.mode, histogram_matching=False)
    if args.iters:
        kw.update(max_iters_per_level=(args.iters,), min_iters_per_level=args.iters + 1, conv_window=args.iters)
    cfg = OptimizeConfig(**kw)
    compute = ComputeConfig(device=args.device, compile=args.compile_one)
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    t0 = time.perf_counter()
    photos = PhotoSet.load(inp, compute.device)
    t_read = time.perf_counter() - t0
    res = optimize_polygon(photos, cfg, compute)
    total = time.perf_counter() - t0
    peak_rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    bandwidth = copy_bandwidth(64)  # after the run: its buffers must not count in the peak RSS
    full_cfg = OptimizeConfig()
    levels = []
    est = t_read
    for i, lv in enumerate(res.stats["levels"]):
        per_it = lv["time_per_iter_s"]
        est += lv["time_setup_s"] + lv["time_first_iter_s"] + per_it * max(full_cfg.cap(i) - 1, 0)
        slots = lv["top_k"] * lv["shape"][0] * lv["shape"][1]
        need = slots * BYTES_PER_SLOT_ITER + lv.get("render_bytes", 0)
        levels.append({"long_side": lv["long_side"], "shape": lv["shape"], "candidates": lv["candidates"],
                       "top_k": lv["top_k"], "setup_s": round(lv["time_setup_s"], 3), "iter_s": round(per_it, 4),
                       "first_iter_s": round(lv["time_first_iter_s"], 3), "compiled": lv["compiled"],
                       "iterations": lv["iterations"], "tensor_mib": round(lv["tensor_bytes"] / 2**20, 1),
                       "render_pixels": lv.get("render_pixels"), "bytes_per_iter": need,
                       "bound_s": need / bandwidth, "x_bound": round(per_it / (need / bandwidth), 1)})
    out = {"size": args.one, "mode": args.mode, "compile": args.compile_one, "texels": res.stats["texels"],
           "photos": len(inp.photos), "torch": torch.__version__, "python": sys.executable,
           "bandwidth_gbs": round(bandwidth / 1e9, 2),
           "time_s": round(total, 2), "read_photos_s": round(t_read, 2),
           "est_full_run_s": round(est, 1), "peak_rss_mib": round(peak_rss / 1024, 1),
           "rss_before_mib": round(rss0 / 1024, 1), "levels": levels, "coverage": res.stats["coverage"]}
    if "cuda_peak_bytes" in res.stats:
        out["cuda_peak_mib"] = round(res.stats["cuda_peak_bytes"] / 2**20, 1)
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", required=True)
    ap.add_argument("--polygon", required=True)
    ap.add_argument("--sizes", type=int, nargs="+", default=[512, 1024, 2048])
    ap.add_argument("--modes", nargs="+", default=["texel", "render"], choices=["texel", "render"])
    ap.add_argument("--iters", type=int, default=10, help="iterations per level (0: the config's caps and convergence)")
    ap.add_argument("--device", default="auto")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--compile", nargs="+", default=["off", "auto"], choices=["off", "auto", "on"],
                    help="OptimizeConfig.compile settings to compare")
    ap.add_argument("--python", nargs="+", default=[sys.executable], help="interpreters to run every case under")
    ap.add_argument("--cache", default="/tmp/difftex_bench")
    ap.add_argument("--out", default="evaluation/bench_optimize")
    ap.add_argument("--one", type=int, help=argparse.SUPPRESS)
    ap.add_argument("--mode", default="texel", help=argparse.SUPPRESS)
    ap.add_argument("--vis", help=argparse.SUPPRESS)
    ap.add_argument("--compile-one", default="auto", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.one:
        print("RESULT " + json.dumps(run_one(args)))
        return 0
    cache = Path(args.cache)
    cache.mkdir(parents=True, exist_ok=True)
    vis = visibility_file(args.scene, args.polygon, max(args.sizes), cache)
    rows = []
    cases = [(py, size, m, c) for size in args.sizes for m in args.modes for c in args.compile for py in args.python]
    for py, size, mode, comp in cases:
        if True:
            cmd = [py, __file__, "--scene", args.scene, "--polygon", args.polygon, "--one", str(size),
                   "--mode", mode, "--vis", str(vis), "--iters", str(args.iters), "--device", args.device,
                   "--threads", str(args.threads), "--compile-one", comp]
            # a fresh inductor cache per run: the first iteration then carries a cold compile,
            # as in a cluster job on a new node, not kernels cached by an earlier run
            with tempfile.TemporaryDirectory(prefix="difftex_inductor_") as cache_dir:
                env = dict(os.environ, TORCHINDUCTOR_CACHE_DIR=cache_dir)
                p = subprocess.run(cmd, capture_output=True, text=True, env=env)
            line = [ln for ln in p.stdout.splitlines() if ln.startswith("RESULT ")]
            if p.returncode or not line:
                print(p.stderr[-2000:], file=sys.stderr)
                rows.append(
                    {
                        "size": size,
                        "mode": mode,
                        "compile": comp,
                        "python": py,
                        "error": p.stderr.strip().splitlines()[-1] if p.stderr.strip() else "failed",
                    }
                )
                continue
            r = json.loads(line[0][7:])
            rows.append(r)
            print(
                f"{r['torch']:14s} {size:5d} {mode:6s} {comp:4s} {r['time_s']:8.1f}s  x bound "
                f"{r['levels'][-1]['x_bound']:6.1f}  full~{r['est_full_run_s']:8.1f}s  "
                f"rss {r['peak_rss_mib']:8.1f} MiB",
                flush=True,
            )
    info = {
        "command": shlex.join(sys.argv),
        "scene": args.scene,
        "polygon": args.polygon,
        "iters_per_level": args.iters,
        "machine": machine(),
        "results": rows,
    }
    from difftex.scene.files import write_json, write_text

    write_json(args.out + ".json", info)
    m = info["machine"]
    from difftex.method.config import ComputeConfig, OptimizeConfig

    lines = [
        f"# Optimizer time and memory per polygon ({Path(args.scene).name} / {args.polygon})",
        "",
        f"Command: `{info['command']}`",
        "",
        f"Machine: {m['cpu']}, {m['cores']} cores, {m['ram_gib']} GiB RAM, torch {m['torch']}, "
        f"CUDA: {m['cuda'] or 'none'}, torch threads {args.threads}, load average at the end "
        f"{tuple(round(x, 1) for x in m['load_avg'])}.",
        "",
        f"Each level ran {args.iters} iterations (0 = config caps). 'full run' = read + setup + first iteration "
        "(which carries torch.compile's cost) + the rest of the default caps "
        f"({', '.join(str(c) for c in OptimizeConfig().max_iters_per_level)} iterations per level, the last repeating) "
        "x the median time of the later iterations. `compile`: OptimizeConfig.compile (auto compiles levels with "
        f"at least {ComputeConfig().compile_min_slots} K x H x W slot entries); 'compiled' lists the levels that were.",
        "",
        "Bound: the bytes one iteration must touch (K x H x W x "
        f"{BYTES_PER_SLOT_ITER} B, plus the render pixel sets) over the one-thread copy bandwidth measured in the "
        "same process; 'x bound' is the last level's iteration time in units of it.",
        "",
        "| torch | texels | mode | compile | photos | run (s) | est. full run (s) | peak RSS (MiB) | last level: "
        "s/iter | "
        "bytes/iter (MiB) | bound (s) | x bound | last level: first iter (s) | compiled levels | last level tensors "
        "(MiB) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        if "error" in r:
            lines.append(
                f"| {r.get('python', '')} | {r['size']} | {r['mode']} | {r.get('compile', '')} | | failed: "
                f"{r['error']} |" + " |" * 9
            )
            continue
        last = r["levels"][-1]
        comp_lv = ", ".join(str(lv["long_side"]) for lv in r["levels"] if lv.get("compiled")) or "none"
        lines.append(
            f"| {r['torch']} | {r['size']} ({r['texels']} in polygon) | {r['mode']} | {r['compile']} | {r['photos']} | "
            f"{r['time_s']} | {r['est_full_run_s']} | {r['peak_rss_mib']} | {last['iter_s']} | "
            f"{last['bytes_per_iter'] / 2**20:.0f} | {last['bound_s']:.4f} | {last['x_bound']} | "
            f"{last['first_iter_s']} | "
            f"{comp_lv} | {last['tensor_mib']} |"
        )
    write_text(args.out + ".md", "\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    C.run_script(main)
