"""difftex synth: generate a synthetic building scene with ground truth (Mitsuba 3 renders)."""

from __future__ import annotations

NAME = "synth"
HELP = "Generate synthetic buildings with ground-truth texture maps (the paper's virtual data set)."


def _pair(text: str) -> tuple[float, float]:
    import argparse

    try:
        parts = [float(x) for x in text.split(",")]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected ROT_DEG[,TRANS_M], got '{text}'") from None
    if len(parts) not in (1, 2) or min(parts) < 0:
        raise argparse.ArgumentTypeError(f"expected ROT_DEG[,TRANS_M] >= 0, got '{text}'")
    return parts[0], (parts[1] if len(parts) == 2 else 0.0)


def add_arguments(p) -> None:
    import argparse

    from difftex.synth.presets import DISTRICTS, PRESETS

    p.add_argument("--preset", default="tiny", choices=sorted([*PRESETS, *DISTRICTS]),
                   help="scene size and content (default: tiny); city, city-block: districts for scale tests")
    p.add_argument("--district", type=int, metavar="N",
                   help="a district of N buildings for scale tests (docs/synth.md, Districts); --views per building")
    p.add_argument("--out", help="output folder (default: data/synth/<preset>)")
    p.add_argument("--seed", type=int, default=0, help="random seed; same seed, same scene (default 0)")
    p.add_argument("--building", action="append", help="only this building of the preset (repeatable)")
    p.add_argument("--views", type=int, help="training photos per building")
    p.add_argument("--held-out", type=int, dest="held_out_views", help="held-out ground-truth views per building")
    p.add_argument("--width", type=int, help="photo width in pixels")
    p.add_argument("--height", type=int, help="photo height in pixels")
    p.add_argument("--spp", type=int, help="samples per pixel of the photos")
    p.add_argument("--gt-spp", type=int, help="samples per texel of the ground-truth maps")
    p.add_argument("--heldout-spp", type=int, help="samples per pixel of the held-out views (0: --gt-spp)")
    p.add_argument("--sampler", choices=["independent", "stratified", "multijitter", "orthogonal", "ldsampler"],
                   help="Mitsuba sampler of every render (survey: ldsampler)")
    p.add_argument("--gt-long-side", type=int, help="longest side of a ground-truth map in texels")
    p.add_argument("--pose-noise", type=_pair, metavar="ROT_DEG[,TRANS_M]",
                   help="std of the error added to the written poses (rendering uses the true pose)")
    p.add_argument("--exposure-range", type=float, help="max |log2 gain| of a photo, in stops")
    p.add_argument("--white-balance", type=float, help="std of the per-channel log gain of a photo")
    p.add_argument("--image-noise", type=float, help="legacy additive Gaussian noise std, linear units (with --iso 0)")
    p.add_argument("--iso", type=float, help="camera model: sensor ISO, Poisson-Gaussian noise (0: off)")
    p.add_argument("--lens-blur", type=float, help="camera model: Gaussian lens blur sigma in pixels")
    p.add_argument("--jpeg-quality", type=int, help="camera model: write JPEG photos at this quality (0: PNG)")
    p.add_argument("--occluders", action=argparse.BooleanOptionalAction, default=None,
                   help="trees, poles and cars in front of the facades")
    p.add_argument("--relief-depth", type=float, help="window recess / cornice depth in metres (0: flat facades)")
    p.add_argument("--distortion", type=float, help="SIMPLE_RADIAL k of the photos (0: PINHOLE)")
    p.add_argument("--sun", action=argparse.BooleanOptionalAction, default=None, help="directional sun besides the sky")
    p.add_argument("--variant", choices=["auto", "llvm_ad_rgb", "scalar_rgb"], help="Mitsuba variant (default auto)")
    p.add_argument("--no-previews", action="store_true", help="skip the contact sheet / overlay / map pictures")
    p.add_argument("--dense", action="store_true",
                   help="also write each scene's COLMAP-like dense reconstruction into <scene>/dense/ (as synth-dense)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def overrides_from_args(args) -> dict:
    keys = ["views", "held_out_views", "width", "height", "spp", "gt_spp", "heldout_spp", "sampler", "gt_long_side",
            "exposure_range", "white_balance", "image_noise", "iso", "lens_blur", "jpeg_quality", "occluders",
            "relief_depth", "distortion", "sun", "variant"]
    out = {k: getattr(args, k) for k in keys if getattr(args, k, None) is not None}
    if args.pose_noise is not None:
        out["pose_noise_rot_deg"], out["pose_noise_trans"] = args.pose_noise
    if args.no_previews:
        out["previews"] = False
    return out


def run(args) -> int:
    import time
    from pathlib import Path

    from difftex.errors import DifftexError
    from difftex.synth import generate
    from difftex.synth.presets import DISTRICTS

    if args.district is not None or args.preset in DISTRICTS:
        if args.dense:
            raise DifftexError("--dense is for building presets; a district has no detailed model to reconstruct")
        return _run_district(args)
    out = Path(args.out) if args.out else Path("data") / "synth" / args.preset
    ov = overrides_from_args(args)
    for k in ("views", "width", "height", "spp", "gt_spp", "gt_long_side"):
        if k in ov and ov[k] < 1:
            raise DifftexError(f"--{k.replace('_', '-')} must be >= 1, got {ov[k]}")
    t0 = time.perf_counter()
    generate(args.preset, out, seed=args.seed, progress=not args.quiet, buildings=args.building, **ov)
    print(f"synth: wrote {out} in {time.perf_counter() - t0:.1f} s")
    if args.dense:
        from difftex.cli.synth_dense import write_scene_dense

        for scene in scene_dirs(args.preset, out, args.building):
            write_scene_dense(scene, progress=not args.quiet)
    return 0


def scene_dirs(preset: str, out, buildings: list[str] | None) -> list:
    """The scene folders ``generate`` wrote: ``out`` for a one-building preset, else ``out/<name>``
    per building asked for (all by default)."""
    from difftex.synth.presets import get_preset

    specs = get_preset(preset).buildings
    if len(specs) == 1:
        return [out]
    return [out / name for name in (buildings or [b.name for b in specs])]


def _run_district(args) -> int:
    """``--district N`` or a district preset: only --out, --seed, --views, --width, --height apply."""
    import time
    from pathlib import Path

    from difftex.errors import DifftexError
    from difftex.synth.district import DistrictConfig, generate_district
    from difftex.synth.presets import DISTRICTS

    preset = args.preset if args.preset in DISTRICTS else "city-block"
    kw = dict(DISTRICTS[preset])
    if args.district is not None:
        kw["buildings"] = args.district
    kw.update({k: getattr(args, k) for k in ("views", "width", "height") if getattr(args, k, None) is not None})
    name = preset if args.district is None else f"district{args.district}"
    out = Path(args.out) if args.out else Path("data") / "synth" / name
    t0 = time.perf_counter()
    m = generate_district(out, DistrictConfig(**kw), seed=args.seed, progress=not args.quiet)
    if m["unseen_polygons"]:
        raise DifftexError(f"{out}: {len(m['unseen_polygons'])} polygon(s) seen by no photo (raise --views)")
    print(f"synth: wrote {out} ({m['polygons']} polygons, {m['photos']} photos) in {time.perf_counter() - t0:.1f} s")
    return 0
