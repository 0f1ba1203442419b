"""difftex heights: each polygon's relief height field from the scene's dense geometry."""

from __future__ import annotations

NAME = "heights"
HELP = ("Measure each polygon's relief (recesses, balconies) from a dense cloud, mesh or COLMAP depth maps of "
        "the same photos; the texturing stages map the photos through it.")


def add_arguments(p) -> None:
    p.add_argument("--scene", required=True, help="scene folder (its proxy; its dense/ folder with --source auto)")
    p.add_argument("--rows", required=True,
                   help="a visibility tile's rows (R/visibility/tiles/<tile>.json), or the visibility summary.json")
    p.add_argument("--visibility-dir", required=True, help="the visibility stage's folder (the polygons' frames)")
    p.add_argument("--config", help="YAML config; its 'dense' section is read")
    p.add_argument("--source", help="dense geometry: a file or folder (overrides dense.source)")
    p.add_argument("--out-dir", required=True, help="one <polygon>.npz per polygon here")
    p.add_argument("--done", required=True, help="the tile's list of its polygons (JSON), written last")


def run(args) -> int:
    import time
    from dataclasses import replace
    from pathlib import Path

    from difftex.compose.heights import tile_heights
    from difftex.errors import DifftexError
    from difftex.geometry.dense import find_source
    from difftex.layout import visibility_file
    from difftex.scene.files import read_json, write_json

    t0 = time.perf_counter()
    cfg = dense_config(args.config)
    if args.source:
        cfg = replace(cfg, source=args.source)
    rows = read_json(args.rows)
    key = next((k for k in ("rows", "polygons") if isinstance(rows, dict) and k in rows), None)
    if key is None:
        raise DifftexError(f"{args.rows}: neither a tile nor the summary of the difftex visibility stage")
    pids = [r["id"] for r in rows[key] if r.get("photos")]
    from difftex.scene.mvs import workspace_status

    skipped = workspace_status(Path(cfg.source)) == "skipped"  # the GPU stage found no CUDA
    source = None if skipped else find_source(args.scene, cfg.source)
    done: list[dict] = []
    if source is None:
        why = "the dense stage was skipped" if skipped else f"none in {cfg.source}"
        print(f"heights: no dense geometry ({why}): every polygon keeps its plane", flush=True)
    else:
        out = Path(args.out_dir)
        done = tile_heights(Path(args.scene), source, [visibility_file(args.visibility_dir, p) for p in pids], cfg,
                            [out / f"{p}.npz" for p in pids])
        for d in done:
            layers = ", ".join(f"{h} ({100 * s:.0f} %)" for h, s in (d["layers"] or {}).items())
            print(f"heights {d['polygon']}: layers {layers or 'none'}; evidence on {100 * d['evidence_share']:.0f} % "
                  f"of the texels, {d['seconds']:.1f}s", flush=True)
    write_json(args.done, {"source": str(source.path) if source else None,
                           "kind": source.kind if source else None, "polygons": done,
                           "seconds": round(time.perf_counter() - t0, 3)})
    return 0


def dense_config(path):
    """The ``dense`` section's height-field keys (HeightFieldConfig); its stereo keys belong to
    the GPU stage (difftex.scene.mvs.DenseStereoConfig) and are left to it."""
    import dataclasses

    from difftex.config import from_dict, read_config
    from difftex.geometry.heightfield import HeightFieldConfig
    from difftex.scene.mvs import DenseStereoConfig

    data = dict(read_config(path).get("dense") or {}) if path else {}
    stereo = {f.name for f in dataclasses.fields(DenseStereoConfig)} | {"stereo"}
    return from_dict(HeightFieldConfig, {k: v for k, v in data.items() if k not in stereo},
                     where=f"{path}: section 'dense'")
