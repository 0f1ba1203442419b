"""How far `difftex synth --preset tiny` output moves between machines, measured on one machine.

Mitsuba's LLVM variant compiles its kernels for the CPU it runs on: the vector width (16 lanes
with AVX-512, 8 with AVX2) and instruction selection differ between machines, and the
`auto` variant falls back to `scalar_rgb` where LLVM does not run. This script generates the
tiny scene under such conditions, each in its own process, and compares the photos and
ground-truth maps with a reference generated under default conditions:

  repeat    the same conditions again (the same-machine promise: identical bytes)
  threads1  one Dr.Jit thread instead of all cores
  avx2      LLVM kernels for an AVX2 CPU, 8 lanes (what a machine without AVX-512 runs)
  scalar    the scalar_rgb variant (a machine where LLVM does not run)

    python scripts/synth_determinism.py --out /tmp/det            # about 3 min on 2 cores

It prints a markdown table: per condition, the share of differing 8-bit values and their largest
and mean absolute difference, over photos and over ground-truth maps.
"""

from __future__ import annotations

import argparse
import ctypes
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

CONDITIONS = ("reference", "repeat", "threads1", "avx2", "scalar")


def _llvm_target(cpu: str, features: str, width: int) -> None:
    """Dr.Jit's jit_llvm_set_target (C API, not bound in Python): compile for another CPU."""
    import drjit

    lib = ctypes.CDLL(str(Path(drjit.__file__).parent / "libdrjit-core.so"))
    fn = lib["_Z19jit_llvm_set_targetPKcS0_j"]  # jit_llvm_set_target(const char*, const char*, uint32_t)
    fn.argtypes = [ctypes.c_char_p, ctypes.c_char_p, ctypes.c_uint32]
    fn(cpu.encode(), features.encode(), width)


def generate_one(condition: str, out: Path) -> None:
    """Generate the tiny scene into ``out`` under ``condition`` (in this process)."""
    import drjit as dr
    import mitsuba as mi

    from difftex.synth import generate

    variant = "scalar_rgb" if condition == "scalar" else "llvm_ad_rgb"
    mi.set_variant(variant)
    if condition == "threads1":
        dr.set_thread_count(1)
    if condition == "avx2":
        _llvm_target("haswell", "+avx,+avx2,+fma,+f16c,+sse4.2,+popcnt,+bmi,+bmi2,+lzcnt,+movbe", 8)
    generate("tiny", out, progress=False, variant=variant, previews=False)


def _pngs(root: Path) -> dict[str, np.ndarray]:
    from PIL import Image

    files = sorted((root / "images").glob("*.png")) + sorted((root / "ground_truth" / "maps").glob("*.png"))
    return {str(f.relative_to(root)): np.asarray(Image.open(f).convert("RGB"), np.int16) for f in files}


def compare(ref: Path, other: Path) -> dict:
    a, b = _pngs(ref), _pngs(other)
    out = {}
    for group, prefix in (("photos", "images/"), ("maps", "ground_truth/")):
        keys = [k for k in a if k.startswith(prefix)]
        d = np.concatenate([np.abs(a[k] - b[k]).ravel() for k in keys])
        out[group] = {
            "files": len(keys),
            "identical_files": sum(bool(np.array_equal(a[k], b[k])) for k in keys),
            "differing_values": float((d > 0).mean()),
            "max_abs": int(d.max()),
            "mean_abs": float(d.mean()),
        }
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, required=True, help="work folder (one scene per condition)")
    ap.add_argument("--one", choices=CONDITIONS, help=argparse.SUPPRESS)  # internal: one condition
    args = ap.parse_args()
    if args.one:
        generate_one(args.one, args.out / args.one)
        return 0
    env = dict(os.environ, DRJIT_CACHE_DIR=str(args.out / "drjit-cache"))  # no kernel reuse across targets
    for cond in CONDITIONS:
        if not (args.out / cond / "synth.json").is_file():
            subprocess.run([sys.executable, __file__, "--out", str(args.out), "--one", cond], check=True, env=env)
    rows = {cond: compare(args.out / "reference", args.out / cond) for cond in CONDITIONS[1:]}
    (args.out / "determinism.json").write_text(json.dumps(rows, indent=2))
    print(
        "| condition | photos identical | differing 8-bit values | max / mean abs diff | maps identical | differing "
        "values | max / mean abs diff |"
    )
    print("|---|---|---|---|---|---|---|")
    for cond, r in rows.items():
        p, m = r["photos"], r["maps"]
        print(
            f"| {cond} | {p['identical_files']}/{p['files']} | {100 * p['differing_values']:.2f} % | "
            f"{p['max_abs']} / {p['mean_abs']:.3f} | {m['identical_files']}/{m['files']} | "
            f"{100 * m['differing_values']:.2f} % | {m['max_abs']} / {m['mean_abs']:.3f} |"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
