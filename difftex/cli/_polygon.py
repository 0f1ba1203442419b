"""Shared loading for the per-polygon stage commands (texture, baseline, mrf)."""

from __future__ import annotations


def add_common(parser, config=True, many=False) -> None:
    parser.add_argument("--scene", required=True, help="scene folder (images/, sparse/0/, proxy)")
    parser.add_argument(
        "--visibility", required=True, nargs="+" if many else None,
        help="the polygons' visibility .npz files (difftex visibility), textured one after another" if many
        else "the polygon's visibility .npz (difftex visibility)",
    )
    if config:
        parser.add_argument(
            "--config", default=None, help="YAML config; its 'optimize:' and 'compute:' sections are read"
        )
    parser.add_argument(
        "--compute-config", default=None, help="YAML whose 'compute:' section is read instead of --config's"
    )
    parser.add_argument("--heights-dir", default=None,
                        help="the heights stage's folder: a polygon with a <polygon>.npz there is mapped through it")
    parser.add_argument("--threads", type=int, default=0, help="torch CPU threads (0: torch's default)")
    parser.add_argument("--device", default=None, choices=["auto", "cpu", "cuda"], help="overrides compute.device")
    parser.add_argument("--compile", default=None, choices=["auto", "on", "off"], help="overrides compute.compile")
    parser.add_argument("--compile-min-slots", type=int, default=None, help="overrides compute.compile_min_slots")


def add_job(parser, decode_cache: bool = False) -> None:
    """The options of a command that a workflow job runs on several polygons: ``--done`` (its
    job file) and, for a command that decodes photos, ``--decode-cache-mb``."""
    parser.add_argument("--done", help="after the last polygon, write this JSON listing them (the workflow's job file)")
    if decode_cache:
        parser.add_argument("--decode-cache-mb", type=float, default=512.0,
                            help="with several polygons, keep up to this many MB of decoded photos for the next ones")


def decoder(args, n_polygons: int):
    """``decode_photo``, or one DecodeCache that the command's polygons share (they usually see
    the same photos: each is decoded once, up to ``--decode-cache-mb``)."""
    from difftex.scene.files import DecodeCache, decode_photo

    return DecodeCache(args.decode_cache_mb) if n_polygons > 1 and args.decode_cache_mb > 0 else decode_photo


def load(args):
    """(OptimizeConfig, ComputeConfig, PolygonInput) for the command's scene, visibility file and config."""
    cfg, compute, inputs = load_many(args, [args.visibility])
    return cfg, compute, next(inputs)


def load_many(args, visibility: list[str], torch_threads: bool = True):
    """(OptimizeConfig, ComputeConfig, iterator of PolygonInput): the scene is read once, each
    polygon's visibility file when the iterator reaches it (so one polygon's inputs are held at a time).
    ``torch_threads``: set torch's threads from ``--threads`` (False: a command that imports no torch)."""
    import dataclasses

    from difftex.config import section
    from difftex.geometry.visibility import load_visibility
    from difftex.method.config import ComputeConfig, OptimizeConfig
    from difftex.sampling.crops import polygon_input_from_visibility
    from difftex.scene.loading import load_scene

    if torch_threads and args.threads and args.threads > 0:
        import torch

        torch.set_num_threads(args.threads)
    path = getattr(args, "config", None)
    cfg = section(path, "optimize", OptimizeConfig)
    compute = section(getattr(args, "compute_config", None) or path, "compute", ComputeConfig)
    over = {"device": args.device, "compile": args.compile, "compile_min_slots": args.compile_min_slots}
    compute = dataclasses.replace(compute, **{k: v for k, v in over.items() if v is not None})
    scene = load_scene(args.scene, check_images=False)
    photos = {p.name: p for p in scene.photos}
    inputs = (with_heights(polygon_input_from_visibility(load_visibility(v), photos, up=scene.up),
                           getattr(args, "heights_dir", None)) for v in visibility)
    return cfg, compute, inputs


def with_heights(inp, heights_dir):
    """``inp`` with the height field the heights stage wrote for it, where there is one."""
    from pathlib import Path

    if heights_dir is None or not (Path(heights_dir) / f"{inp.polygon_id}.npz").is_file():
        return inp
    from difftex.compose.heights import read_heights

    frame, heights, _ = read_heights(Path(heights_dir) / f"{inp.polygon_id}.npz", inp.polygon_id)
    inp.dense = (frame, heights)
    return inp
