"""Benchmark: time and peak memory of the photo-filtering and visibility stages on one scene.

    python evaluation/bench_visibility.py --scene ../shared/data/sceaux-castle --long-side 1024 2048

Each configuration runs in a fresh process so peak RSS is that stage's own. Writes
evaluation/results/bench_visibility.{json,md} with the machine it ran on.
"""

from __future__ import annotations

import argparse
import json
import shlex
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from evaluation import common as C  # noqa: E402

HERE = Path(__file__).resolve().parent

CHILD = r"""
import json, resource, sys, time
from difftex.cli import main
t = time.perf_counter()
code = main(sys.argv[1:])
print(json.dumps({"code": code, "seconds": time.perf_counter() - t,
                  "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}))
"""


def machine() -> dict:
    """The shared machine description (evaluation/common.py)."""
    return C.machine()


def run_stage(argv: list[str]) -> dict:
    out = subprocess.run([sys.executable, "-c", CHILD, *argv], capture_output=True, text=True)
    last = out.stdout.strip().splitlines()[-1] if out.stdout.strip() else "{}"
    res = json.loads(last)
    if res.get("code") != 0:
        raise SystemExit(f"stage failed: {' '.join(argv)}\n{out.stderr}")
    return res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", required=True)
    ap.add_argument("--long-side", type=int, nargs="+", default=[1024, 2048])
    ap.add_argument("--out", default=str(HERE / "results" / "bench_visibility"))
    args = ap.parse_args()
    from difftex.scene.loading import load_scene

    sc = load_scene(args.scene)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        photos = tmp / "photos.json"
        f = run_stage(["filter", "--scene", args.scene, "--out", str(photos), "--quiet"])
        rows.append({"stage": "filter", "long_side": None, **f})
        for ls in args.long_side:
            cfg = tmp / f"cfg{ls}.yaml"
            cfg.write_text(f"texture: {{long_side: {ls}}}\n")
            v = run_stage(["visibility", "--scene", args.scene, "--photos", str(photos), "--config", str(cfg),
                           "--out-dir", str(tmp / f"vis{ls}"), "--quiet"])
            size = sum(p.stat().st_size for p in (tmp / f"vis{ls}").glob("*.npz"))
            rows.append({"stage": "visibility", "long_side": ls, **v, "files_mib": size / 2**20})
    pixels = sum(p.width * p.height for p in sc.photos)
    result = {
        "command": "python evaluation/bench_visibility.py " + shlex.join(sys.argv[1:]),
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "machine": machine(),
        "scene": {
            "name": sc.name,
            "photos": len(sc.photos),
            "polygons": len(sc.proxy),
            "megapixels": round(pixels / 1e6, 1),
        },
        "runs": rows,
    }
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    from difftex.scene.files import write_json, write_text

    write_json(out.with_suffix(".json"), result)
    m = result["machine"]
    lines = [
        f"# Visibility benchmark: {sc.name}",
        "",
        f"`{result['command']}` on {result['date']}; {m['cpu']}, {m['cores']} cores, {m['ram_gib']} GiB, torch "
        f"{m['torch']}.",
        f"Scene: {len(sc.photos)} photos ({result['scene']['megapixels']} MP in all), {len(sc.proxy)} polygons.",
        "",
        "| stage | texture long side | time (s) | peak RSS (MiB) | mask files (MiB) |",
        "|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['stage']} | {r['long_side'] or '-'} | {r['seconds']:.1f} | {r['peak_rss_mib']:.0f} | "
            f"{r.get('files_mib', 0):.2f} |"
        )
    write_text(out.with_suffix(".md"), "\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    C.run_script(main)
