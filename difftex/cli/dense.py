"""difftex dense: COLMAP PatchMatch stereo of a scene's photos on a GPU (a dense workspace with depth maps)."""

from __future__ import annotations

NAME = "dense"
HELP = ("Depth maps of the scene's photos by COLMAP's PatchMatch stereo on a GPU (needs pycolmap-cuda12; "
        "skipped with one line without CUDA), in a COLMAP dense workspace.")


def add_arguments(p) -> None:
    p.add_argument("--scene", required=True, help="scene folder (images/, sparse/0/)")
    p.add_argument("--out", required=True,
                   help="the dense workspace to make (images/, sparse/, stereo/depth_maps/, dense.json)")
    p.add_argument("--config", help="YAML config; the stereo keys of its 'dense' section are read")
    p.add_argument("--photos", help="with dense.photos: visible, the photos to match: the filter's R/photos.json "
                                    "(its kept photos) or a text file of names; default: every registered photo")
    p.add_argument("--done", help="a copy of the record dense.json, written last (the workspace holds it anyway)")


def stereo_config(path):
    """The ``dense`` section's stereo keys (difftex.scene.mvs.DenseStereoConfig); its switch
    ``stereo`` is the workflow's and its height-field keys are the heights stage's. Any other key
    is an error naming it."""
    import dataclasses

    from difftex.config import from_dict, read_config
    from difftex.scene.mvs import DenseStereoConfig

    data = dict(read_config(path).get("dense") or {}) if path else {}
    others = {"stereo"}
    try:
        from difftex.geometry.heightfield import HeightFieldConfig

        others |= {f.name for f in dataclasses.fields(HeightFieldConfig)}
    except ImportError:  # the heights stage is optional to this command
        others |= {"source", "range", "max_share", "long_side", "layers", "smoothness"}
    where = f"{path}: section 'dense'" if path else "dense"
    return from_dict(DenseStereoConfig, {k: v for k, v in data.items() if k not in others}, where=where)


def run(args) -> int:
    import logging
    from pathlib import Path

    from difftex.config import job_threads
    from difftex.scene import mvs
    from difftex.scene.files import write_json
    from difftex.scene.loading import find_sparse

    log = logging.getLogger("difftex.cli.dense")
    cfg = stereo_config(args.config)
    find_sparse(Path(args.scene))  # a wrong scene is an error with or without CUDA
    out = Path(args.out)
    if not mvs.cuda_available():
        # not an error: a workflow with dense.stereo on a CPU machine goes on without depth maps
        log.warning("dense: skipped, %s", mvs.SKIP_REASON)
        record = mvs.write_skipped(out)
    else:
        names = None
        if cfg.photos == "visible" and args.photos:
            names = mvs.read_photo_list(args.photos)
        record = mvs.run_dense_stereo(args.scene, out, names, cfg, threads=job_threads())
        rows = record["photos"]
        maps = [r for r in rows if r["kind"]]
        share = sorted(r["valid_share"] for r in maps)[len(maps) // 2]
        print(f"dense: {len(maps)} depth maps of {len(rows)} photos (median {100 * share:.0f} % of the pixels "
              f"with a depth) in {record['seconds']['total']:.1f}s -> {out}", flush=True)
    if args.done and Path(args.done).resolve() != (out / mvs.RECORD).resolve():
        write_json(args.done, record)
    return 0
