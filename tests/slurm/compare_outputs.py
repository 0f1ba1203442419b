"""Compare two difftex result trees (a SLURM run and a local run of the same workflow).

    python tests/slurm/compare_outputs.py SLURM_DIR LOCAL_DIR [--tolerance 0.02]

Texture PNGs (under a `textures/` folder) must exist in both runs, have the same shapes, and
agree to within the tolerance (max abs difference of values in [0, 1]). Optimization is
deterministic on CPU, and both runs use the same thread counts. Other PNGs and every NPZ
found in both trees are compared too (same keys and shapes for NPZ; their max abs difference
is reported). Files that only one run wrote are listed but do not fail the comparison,
because report extras change with the workflow version. Exit status 1 on a mismatch.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from difftex.scene.files import read_image

SKIP = {".snakemake", "benchmarks", "logs"}


def files(root: Path, ext: str) -> set[Path]:
    return {p.relative_to(root) for p in root.rglob(f"*{ext}") if not SKIP & set(p.parts)}


def png_diff(a: Path, b: Path) -> float:
    x, y = read_image(a), read_image(b)
    if x.shape != y.shape:
        raise ValueError(f"shape {x.shape} != {y.shape}")
    return float(np.abs(x - y).max()) if x.size else 0.0


def npz_diff(a: Path, b: Path) -> float:
    worst = 0.0
    with np.load(a) as za, np.load(b) as zb:
        if sorted(za.files) != sorted(zb.files):
            raise ValueError(f"arrays {sorted(za.files)} != {sorted(zb.files)}")
        for k in za.files:
            x, y = za[k], zb[k]
            if x.shape != y.shape:
                raise ValueError(f"[{k}] shape {x.shape} != {y.shape}")
            if x.dtype.kind in "biuf" and x.size:
                worst = max(worst, float(np.abs(x.astype(np.float64) - y.astype(np.float64)).max()))
    return worst


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("slurm", type=Path)
    ap.add_argument("local", type=Path)
    ap.add_argument("--tolerance", type=float, default=0.02)
    ap.add_argument("--partial", action="store_true",
                    help="the runs stopped before the textures (a --target): compare what exists")
    args = ap.parse_args(argv)
    a, b = args.slurm, args.local
    problems: list[str] = []

    pa, pb = files(a, ".png"), files(b, ".png")
    tex_a = {p for p in pa if "textures" in p.parts}
    tex_b = {p for p in pb if "textures" in p.parts}
    if not tex_a and not args.partial:
        problems.append(f"no texture PNG under {a}")
    if tex_a != tex_b:
        problems.append(f"texture PNGs differ: only slurm {sorted(map(str, tex_a - tex_b))[:5]}, "
                        f"only local {sorted(map(str, tex_b - tex_a))[:5]}")
    only = sorted(map(str, (pa ^ pb) - (tex_a ^ tex_b)))
    if only:
        print(f"note: {len(only)} PNGs written by one run only (not compared): {only[:5]}")

    worst_tex, worst_tex_name, worst_other, worst_other_name = 0.0, "-", 0.0, "-"
    for rel in sorted(pa & pb):
        try:
            d = png_diff(a / rel, b / rel)
        except ValueError as exc:
            problems.append(f"{rel}: {exc}")
            continue
        if rel in tex_a and d >= worst_tex:
            worst_tex, worst_tex_name = d, str(rel)
        elif rel not in tex_a and d >= worst_other:
            worst_other, worst_other_name = d, str(rel)

    na, nb = files(a, ".npz"), files(b, ".npz")
    if args.partial and not (pa & pb) and not (na & nb):
        problems.append(f"nothing to compare under {a} and {b}")
    worst_npz, worst_npz_name = 0.0, "-"
    for rel in sorted(na & nb):
        try:
            d = npz_diff(a / rel, b / rel)
        except ValueError as exc:
            problems.append(f"{rel}: {exc}")
            continue
        if d >= worst_npz:
            worst_npz, worst_npz_name = d, str(rel)

    print(f"compared {len(tex_a & tex_b)} texture PNGs: max abs difference {worst_tex:.6f} ({worst_tex_name})")
    print(f"compared {len(pa & pb) - len(tex_a & tex_b)} other PNGs: max abs difference "
          f"{worst_other:.6f} ({worst_other_name})")
    print(f"compared {len(na & nb)} NPZ files: max abs difference {worst_npz:.6g} ({worst_npz_name})")
    if worst_tex > args.tolerance:
        problems.append(f"texture max abs difference {worst_tex:.6f} > tolerance {args.tolerance}")
    for p in problems:
        print(f"MISMATCH: {p}", file=sys.stderr)
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
