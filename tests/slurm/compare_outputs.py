"""Compare two difftex result trees (a SLURM run and a local run of the same workflow).

    python tests/slurm/compare_outputs.py SLURM_DIR LOCAL_DIR [--tolerance 0.02]
    python tests/slurm/compare_outputs.py SLURM_DIR LOCAL_DIR --tolerance 0   # byte-identical

Texture PNGs (under a `textures/` folder) must exist in both runs, have the same shapes, and
agree to within the tolerance (max abs difference of values in [0, 1]). Optimization is
deterministic on CPU, and both runs use the same thread counts and the same texture-job
packing (`run.pack_jobs`), so they can also be required to be identical:

--tolerance 0 (or --exact) compares every texture PNG file's BYTES (`cmp`, not the decoded
values: same pixels, bit depth, channels and encoding), and every NPZ found in both trees must
hold exactly equal numeric arrays (their zip members carry write times, so NPZ files are
compared by their decoded arrays, not their bytes; text arrays, such as a composite's JSON
report with its timings, are not compared). Other PNGs (model views, atlas) are compared by bytes
too and reported, but only textures fail the check.

Other PNGs and every NPZ found in both trees are compared in either mode (same keys and shapes
for NPZ; their max abs difference is reported). Files that only one run wrote are listed but do
not fail the comparison, because report extras change with the workflow version. Exit status 1
on a mismatch.
"""

from __future__ import annotations

import argparse
import filecmp
import sys
from pathlib import Path

import numpy as np

from difftex.scene.files import read_image

SKIP = {".snakemake", "benchmarks", "logs"}


def files(root: Path, ext: str) -> set[Path]:
    return {p.relative_to(root) for p in root.rglob(f"*{ext}") if not SKIP & set(p.parts)}


def same_bytes(a: Path, b: Path) -> bool:
    return filecmp.cmp(a, b, shallow=False)


def png_diff(a: Path, b: Path) -> float:
    x, y = read_image(a), read_image(b)
    if x.shape != y.shape:
        raise ValueError(f"shape {x.shape} != {y.shape}")
    return float(np.abs(x - y).max()) if x.size else 0.0


def npz_diff(a: Path, b: Path) -> float:
    """Max abs difference over the numeric arrays (NaN in the same places is equal)."""
    worst = 0.0
    with np.load(a) as za, np.load(b) as zb:
        if sorted(za.files) != sorted(zb.files):
            raise ValueError(f"arrays {sorted(za.files)} != {sorted(zb.files)}")
        for k in za.files:
            x, y = za[k], zb[k]
            if x.shape != y.shape:
                raise ValueError(f"[{k}] shape {x.shape} != {y.shape}")
            if x.dtype.kind not in "biuf":
                continue  # text (a composite's JSON report holds timings): not compared
            if x.dtype != y.dtype:
                raise ValueError(f"[{k}] dtype {x.dtype} != {y.dtype}")
            if x.size:
                xf, yf = x.astype(np.float64), y.astype(np.float64)
                # NaN in the same places counts as equal
                nan = np.isnan(xf) & np.isnan(yf)
                d = np.abs(np.where(nan, 0.0, xf) - np.where(nan, 0.0, yf))
                worst = max(worst, float(np.nan_to_num(d, nan=np.inf).max()))
    return worst


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("slurm", type=Path)
    ap.add_argument("local", type=Path)
    ap.add_argument("--tolerance", type=float, default=0.02,
                    help="max abs difference of texture values in [0, 1]; 0: the texture PNG files "
                         "must be byte-identical and the NPZ arrays exactly equal")
    ap.add_argument("--exact", action="store_true", help="the same as --tolerance 0")
    ap.add_argument("--partial", action="store_true",
                    help="the runs stopped before the textures (a --target): compare what exists")
    args = ap.parse_args(argv)
    if args.tolerance < 0:
        ap.error("--tolerance must be >= 0")
    exact = args.exact or args.tolerance == 0
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
    tex_bytes_same, other_bytes_same, tex_bytes_differ = 0, 0, []
    for rel in sorted(pa & pb):
        is_tex = rel in tex_a
        if same_bytes(a / rel, b / rel):
            if is_tex:
                tex_bytes_same += 1
            else:
                other_bytes_same += 1
            continue  # identical files: difference 0
        if is_tex:
            tex_bytes_differ.append(str(rel))
        try:
            d = png_diff(a / rel, b / rel)
        except ValueError as exc:
            problems.append(f"{rel}: {exc}")
            continue
        if is_tex and d >= worst_tex:
            worst_tex, worst_tex_name = d, str(rel)
        elif not is_tex and d >= worst_other:
            worst_other, worst_other_name = d, str(rel)

    na, nb = files(a, ".npz"), files(b, ".npz")
    if args.partial and not (pa & pb) and not (na & nb):
        problems.append(f"nothing to compare under {a} and {b}")
    worst_npz, worst_npz_name, npz_equal = 0.0, "-", 0
    for rel in sorted(na & nb):
        try:
            d = npz_diff(a / rel, b / rel)
        except ValueError as exc:
            problems.append(f"{rel}: {exc}")
            continue
        npz_equal += d == 0
        if d >= worst_npz:
            worst_npz, worst_npz_name = d, str(rel)

    n_tex = len(tex_a & tex_b)
    n_main = sum(1 for p in tex_a & tex_b if p.name == "texture.png")
    print(f"compared {n_tex} texture PNGs ({n_main} texture.png): {tex_bytes_same} byte-identical, "
          f"max abs difference {worst_tex:.6f} ({worst_tex_name})")
    print(f"compared {len(pa & pb) - n_tex} other PNGs: {other_bytes_same} byte-identical, "
          f"max abs difference {worst_other:.6f} ({worst_other_name})")
    print(f"compared {len(na & nb)} NPZ files: {npz_equal} with exactly equal arrays, "
          f"max abs difference {worst_npz:.6g} ({worst_npz_name})")
    if exact:
        if tex_bytes_differ:
            problems.append(f"{len(tex_bytes_differ)} texture PNGs are not byte-identical "
                            f"(max abs difference {worst_tex:.6f}): {tex_bytes_differ[:5]}")
        if worst_npz > 0:
            problems.append(f"{len(na & nb) - npz_equal} NPZ files hold different arrays "
                            f"(max abs difference {worst_npz:.6g}, {worst_npz_name})")
        if not problems:
            print(f"EXACT: {tex_bytes_same} texture PNGs byte-identical ({n_main} texture.png), "
                  f"{npz_equal} NPZ files with equal arrays")
    elif worst_tex > args.tolerance:
        problems.append(f"texture max abs difference {worst_tex:.6f} > tolerance {args.tolerance}")
    for p in problems:
        print(f"MISMATCH: {p}", file=sys.stderr)
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
