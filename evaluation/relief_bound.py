"""The relief bound: relief-compensated mapping with a synthetic building's true height field.

    python evaluation/relief_bound.py --scene data/synth/survey/gable --polygons wall03 \
        --max-long-side 512 --density-scale 1.0 --out evaluation/results/relief_bound_survey_gable

`difftex synth` builds every building from its seed (difftex.synth.pipeline.build_model), and
the facade layouts that built its geometry give each wall's true relief along the outward
normal: the openings' back panes at -relief_depth, the cornice at +relief_depth, the string
courses at +relief_depth / 2, a balcony's slab and front rail at its depth (:func:`true_heights`,
the same boxes as difftex.synth.detail.build_detail). This runs evaluation/variants.py with the
sweep (``estimate_relief`` in difftex.compose.texturing) replaced by that field for as long as
the run lasts, so the mapping through the displaced surface, its self-occlusion and everything
after are the workflow's own: what `optimize.relief: true` would reach with a perfect sweep.
The variants default to the defaults against `relief: true`; ``--variants`` as in variants.py.

With ``--accuracy`` it scores the sweep itself instead: per wall, its field (the step limit
lifted, ``--optimize`` for the relief_* settings) against the true one (:func:`field_accuracy`):

    python evaluation/relief_bound.py --accuracy --scene data/synth/survey/gable \
        --optimize '{"relief_min_cos": 0.3}' --out evaluation/results/relief_sweep_survey_gable
"""

from __future__ import annotations

import argparse
import json
import shlex
import sys
from contextlib import contextmanager
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

DEFAULT_VARIANTS = '{"defaults": {}, "true relief": {"relief": true}}'


def synth_model(scene: Path):
    """(faces by id, layouts by id, relief depth) of the building a `difftex synth` scene shows."""
    from difftex.errors import DifftexError
    from difftex.synth.pipeline import build_model
    from difftex.synth.presets import get_preset

    path = scene / "synth.json"
    if not path.is_file():
        raise DifftexError(f"{path}: missing (the relief bound needs a `difftex synth` scene)")
    meta = json.loads(path.read_text())
    cfg = get_preset(meta["preset"])
    # the settings the layouts depend on, as the scene was made (a CLI flag may have changed them)
    cfg = cfg.replace(**{k: meta["config"][k] for k in ("relief_depth", "balconies") if k in meta.get("config", {})})
    name = meta["building"]["name"]
    specs = [b for b in cfg.buildings if b.name == name]
    if not specs:
        raise DifftexError(f"{path}: building '{name}' is not in synth preset '{meta['preset']}'")
    building, layouts, *_ = build_model(cfg, specs[0], meta["seed"], meta["building_index"])
    return {f.id: f for f in building.faces}, layouts, float(cfg.relief_depth)


def true_heights(face, layout, relief: float, X: np.ndarray) -> np.ndarray:
    """A wall's true height along its outward normal at world points ``X`` (..., 3): the
    front-most surface, as the orthographic ground truth sees it. Roofs: 0.

    Returns:
        (...) float32 scene units.
    """
    uv = face.to2d(X)
    u, v = uv[..., 0], uv[..., 1]
    h = np.zeros(u.shape, np.float32)
    if face.kind != "wall" or relief <= 0:
        return h
    for u0, v0, u1, v1 in layout.openings():  # build_detail lifts an opening's sill to 0.02
        h[(u >= u0) & (u <= u1) & (v >= max(v0, 0.02)) & (v <= v1)] = -relief
    # what stands in front of the wall, drawn last: it hides the openings behind it
    if layout.cornice:
        h[(v >= face.eave - 0.45) & (v <= face.eave)] = relief
    for c in layout.courses:
        h[(v >= c - 0.2) & (v <= c + 0.05)] = 0.5 * relief
    depth = float(np.clip(1.5 * relief, 0.0, 0.9))  # build_detail's balcony depth
    for u0, u1, vs in layout.balconies:  # the slab, then the front rail a metre high
        h[(u >= u0) & (u <= u1) & (v >= vs - 0.15) & (v <= vs + 1.0)] = depth
    return h


def true_field(face, layout, relief: float, frame, mask: np.ndarray) -> np.ndarray:
    """The true heights at ``frame``'s texel centres along the frame's normal, 0 outside ``mask``.

    Returns:
        (h, w) float32 scene units.
    """
    h = true_heights(face, layout, relief, frame.texel_to_world(*frame.centres()))
    if float(np.dot(face.normal, frame.normal)) < 0:  # the face's outward normal against the frame's
        h = -h
    return np.where(mask, h, 0.0).astype(np.float32)


def true_relief_estimator(faces: dict, layouts: dict, relief: float):
    """An ``estimate_relief`` that returns the true field at the sweep's frame, with the
    self-occlusion the workflow computes for a swept one."""
    from difftex.method.relief import occluding_relief
    from difftex.sampling.texels import level_frame, resample_nearest

    def estimate(photos, s):
        inp = photos.inp
        frame = level_frame(inp.frame, min(s.long_side, max(inp.frame.shape)))
        mask = resample_nearest(inp.texel_mask, inp.frame, frame)
        h = true_field(faces[inp.polygon_id], layouts[inp.polygon_id], relief, frame, mask)
        field = occluding_relief(photos, frame, h, mask)
        share = float((h[mask] != 0).mean()) if mask.any() else 0.0
        return field, {"photos": [], "long_side": max(frame.shape), "relief_share": share, "reason": "true field"}

    return estimate


@contextmanager
def true_relief(scene: Path):
    """For the block's duration, difftex.compose.texturing estimates relief as the truth."""
    import difftex.compose.texturing as texturing

    saved = texturing.estimate_relief
    texturing.estimate_relief = true_relief_estimator(*synth_model(scene))
    try:
        yield
    finally:
        texturing.estimate_relief = saved


def write_true_heights(scene: Path, visibility: Path, out: Path, long_side: int = 512) -> Path:
    """The true field of every wall with a visibility file in ``visibility``, as the heights
    stage's files in ``out`` (difftex.compose.heights): `difftex texture --heights-dir` maps
    through it exactly as through a measured one (evaluation/table1.py's bound row)."""
    from difftex.compose.heights import write_heights
    from difftex.geometry.visibility import load_visibility
    from difftex.sampling.texels import level_frame, resample_nearest

    faces, layouts, depth = synth_model(scene)
    for f in sorted(Path(visibility).glob("*.npz")):
        v = load_visibility(f)
        if v.polygon_id not in faces:
            continue
        fr = level_frame(v.frame, min(long_side, max(v.frame.shape)))
        mask = resample_nearest(v.texel_mask, v.frame, fr)
        h = true_field(faces[v.polygon_id], layouts[v.polygon_id], depth, fr, mask)
        write_heights(Path(out) / f"{v.polygon_id}.npz", v.polygon_id, fr, h, {"source": "true field"})
    return Path(out)


def dense_fields(scene: Path, source: str, vis: list, long_side: int = 512) -> dict:
    """{polygon: (frame, heights)} measured from the scene's dense geometry (difftex heights' own code)."""
    import dataclasses

    from difftex.compose.heights import polygon_box, polygon_field, read_geometry
    from difftex.geometry.dense import find_source
    from difftex.geometry.heightfield import HeightFieldConfig

    cfg = dataclasses.replace(HeightFieldConfig(), long_side=long_side)
    src = find_source(scene, source)
    if src is None:
        raise SystemExit(f"relief_bound: {scene}: no dense geometry ({source})")
    allv = np.concatenate([np.stack(polygon_box(v.frame, 0.0, 0.0)) for v in vis])
    geometry = read_geometry(src, (allv.min(0), allv.max(0)), 1.0)
    return {v.polygon_id: polygon_field(geometry, v.frame, v.texel_mask, cfg)[:2] for v in vis}


def field_accuracy(est: np.ndarray, true: np.ndarray, mask: np.ndarray, depth: float, tol: float) -> dict:
    """How a height field matches the true one over ``mask``.

    Returns:
        ``within``: share of the texels within ``tol``; ``recess_found``: share of the truly
        recessed texels (below -depth / 2) estimated below -depth / 2; ``false_relief``: share of
        the truly plane texels estimated off it by more than ``tol``.
    """
    e, t = est[mask], true[mask]
    rec, flat = t < -depth / 2, t == 0
    return {
        "within": float((np.abs(e - t) <= tol).mean()) if e.size else float("nan"),
        "recess_found": float((e[rec] < -depth / 2).mean()) if rec.any() else float("nan"),
        "false_relief": float((np.abs(e[flat]) > tol).mean()) if flat.any() else float("nan"),
    }


def sweep_accuracy(scene: Path, polygons: list[str] | None, density_scale: float, max_long_side: int,
                   overrides: dict, tol: float, dense: str | None = None) -> list[dict]:
    """Per polygon, the sweep's own field (its step limit lifted), or with ``dense`` the field
    measured from the scene's dense geometry (as ``dense.source``), against the true one."""
    import dataclasses

    import torch

    from difftex.method.config import OptimizeConfig
    from difftex.method.relief import estimate_relief
    from difftex.sampling.photos import PhotoSet, polygon_input_from_visibility
    from difftex.sampling.texels import resample_nearest
    from evaluation import common as C

    torch.set_num_threads(1)
    faces, layouts, depth = synth_model(scene)
    sc, vis = C.scene_polygons(scene, polygons, density_scale, max_long_side)
    by_name = {p.name: p for p in sc.photos}
    cfg = dataclasses.replace(OptimizeConfig(), relief=True, **overrides)
    vis = [v for v in vis if faces[v.polygon_id].kind == "wall"]
    measured = dense_fields(scene, dense, vis, cfg.relief_long_side) if dense else {}
    rows = []
    for v in vis:
        inp = polygon_input_from_visibility(v, by_name, up=sc.up)
        if dense:
            fr, heights = measured[v.polygon_id]
            st = {"photos": []}
        else:
            field, st = estimate_relief(PhotoSet.load(inp, "cpu"), cfg.relief_settings(), max_steps=10**9)
            fr, heights = field.frame, field.heights
        mask = resample_nearest(inp.texel_mask, inp.frame, fr)
        true = true_field(faces[v.polygon_id], layouts[v.polygon_id], depth, fr, mask)
        acc = field_accuracy(heights, true, mask, depth, tol) if st.get("reason") is None else {}
        rows.append({"polygon": v.polygon_id, "photos": len(st["photos"]), "steps": st.get("steps"),
                     "reason": st.get("reason"), **acc})
        print(f"relief_bound: {v.polygon_id}: {rows[-1]}", flush=True)
    return rows


def accuracy_main(args) -> int:
    from evaluation import common as C

    over = json.loads(args.optimize) if args.optimize else {}
    rows = sweep_accuracy(args.scene, C.polygon_ids(args.polygons) if args.polygons else None,
                          args.density_scale, args.max_long_side, over, args.tolerance, args.dense)
    cmd = "python evaluation/relief_bound.py " + shlex.join(args.argv)
    lines = [
        C.header(f"The relief {'from dense geometry' if args.dense else 'sweep'} against the true field: "
                 f"{args.scene.name}", cmd, C.machine(), [
            (f"the field measured from the scene's dense geometry (dense.source {args.dense})" if args.dense else
             f"optimize overrides {json.dumps(over)}; the sweep's own field with its step limit lifted")
            + ", at its frame; "
            f"within: share of texels within {args.tolerance} of the truth; recess found: share of the recessed "
            "texels (below -depth/2) estimated there; false relief: share of the plane's texels estimated off it."]),
        "| polygon | photos compared | steps | within | recess found | false relief | note |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        nums = [f"{r[k]:.3f}" if k in r else "-" for k in ("within", "recess_found", "false_relief")]
        lines.append(f"| {r['polygon']} | {r['photos']} | {r['steps'] if r['steps'] is not None else '-'} | "
                     f"{' | '.join(nums)} | {r['reason'] or ''} |")
    kept = {k: str(v) for k, v in vars(args).items() if k != "argv"}
    C.write_outputs(Path(args.out), "\n".join(lines) + "\n", {"args": kept, "rows": rows})
    return 0


def main(argv=None) -> int:
    from evaluation import variants

    args = list(sys.argv[1:] if argv is None else argv)
    if "--accuracy" in args:
        ap = argparse.ArgumentParser(description="the sweep's field against the true one")
        ap.add_argument("--accuracy", action="store_true")
        ap.add_argument("--scene", required=True, type=Path)
        ap.add_argument("--polygons")
        ap.add_argument("--density-scale", type=float, default=1.0)
        ap.add_argument("--max-long-side", type=int, default=512)
        ap.add_argument("--optimize", help="JSON optimize overrides (the relief_* settings)")
        ap.add_argument("--tolerance", type=float, default=0.05, help="scene units")
        ap.add_argument("--dense", help="score the field from the scene's dense geometry (a dense.source, e.g. auto)")
        ap.add_argument("--work", help="unused (evaluation/reproduce.py gives every script one)")
        ap.add_argument("--out", required=True)
        parsed = ap.parse_args(args)
        parsed.argv = args
        return accuracy_main(parsed)
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0], add_help=False)
    ap.add_argument("--scene", required=True, type=Path)
    known, _ = ap.parse_known_args(args)
    if "--variants" not in args:
        args += ["--variants", DEFAULT_VARIANTS]
    with true_relief(known.scene):
        return variants.main(args, command="python evaluation/relief_bound.py " + shlex.join(args))


if __name__ == "__main__":
    from evaluation.common import run_script

    run_script(main)
