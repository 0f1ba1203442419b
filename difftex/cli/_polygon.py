"""Shared loading for the per-polygon optimizer stages (init, optimize, histmatch, baseline)."""

from __future__ import annotations

import json

import numpy as np

from difftex.errors import DifftexError


def add_common(parser, config=True) -> None:
    parser.add_argument("--scene", required=True, help="scene folder (images/, sparse/0/, proxy)")
    parser.add_argument("--visibility", required=True, help="the polygon's visibility .npz (difftex visibility)")
    if config:
        parser.add_argument("--config", default=None, help="YAML config; its 'optimize:' section is read")
    parser.add_argument("--threads", type=int, default=0, help="torch CPU threads (0: torch's default)")
    parser.add_argument("--device", default=None, choices=["auto", "cpu", "cuda"], help="overrides optimize.device")


def load(args):
    """(OptimizeConfig, PolygonInput) for the command's scene, visibility file and config."""
    import dataclasses

    import torch

    from difftex.config import section
    from difftex.optimize import OptimizeConfig, polygon_input_from_visibility
    from difftex.scene import load_scene
    from difftex.visibility import load_visibility

    if args.threads and args.threads > 0:
        torch.set_num_threads(args.threads)
    cfg = section(getattr(args, "config", None), "optimize", OptimizeConfig)
    if args.device:
        cfg = dataclasses.replace(cfg, device=args.device)
    scene = load_scene(args.scene, check_images=False)
    vis = load_visibility(args.visibility)
    inp = polygon_input_from_visibility(vis, {p.name: p for p in scene.photos})
    return cfg, inp


def transfers_by_name(path, data: dict, photos: list[str]) -> list | None:
    """Per-photo HSV transfers stored in an init/weights npz, reordered to ``photos``."""
    if "transfers" not in data:
        return None
    names = [str(x) for x in data["photos"]]
    pos = {n: i for i, n in enumerate(names)}
    missing = [n for n in photos if n not in pos]
    if missing:
        raise DifftexError(f"{path}: made for other photos (missing {', '.join(missing[:3])}); rerun 'difftex init'")
    has = data["has_transfer"]
    return [data["transfers"][pos[n]] if has[pos[n]] else None for n in photos]


def pack_transfers(transfers: list | None, n: int) -> dict:
    from difftex.histmatch import N_KNOTS, identity_transfer

    if transfers is None:
        return {}
    arr = np.stack([t if t is not None else identity_transfer() for t in transfers]) if n else np.zeros((0, 3, 2, N_KNOTS), np.float32)
    return {"transfers": arr.astype(np.float32), "has_transfer": np.array([t is not None for t in transfers], bool)}


def frame_json(frame) -> np.ndarray:
    return np.array(json.dumps(frame.to_dict()))
