"""difftex mrf: "Let There Be Color"-style baseline for one polygon (same outputs as difftex baseline)."""

from __future__ import annotations

NAME = "mrf"
HELP = "texture one polygon by MRF view selection over texel patches (graph cuts) with seam leveling"


def add_arguments(parser) -> None:
    from difftex.cli._polygon import add_common

    add_common(parser)
    parser.add_argument(
        "--out-dir",
        required=True,
        help="output folder for texture.png, source.png, source.npz, coverage.png, report.json",
    )
    parser.add_argument("--patch", type=int, help="patch side in texels (overrides mrf.patch)")
    parser.add_argument("--smoothness", type=float, help="Potts weight (overrides mrf.smoothness)")


def run(args) -> int:
    import dataclasses

    from difftex.cli._polygon import load
    from difftex.config import section
    from difftex.evaluation.mrf import MRFConfig, run_polygon

    cfg, compute, inp = load(args)
    # the photo sampling of difftex's own run (optimize.supersample): a comparison then
    # compares the selection, not the sampling
    mcfg = dataclasses.replace(section(args.config, "mrf", MRFConfig), supersample=cfg.supersample)
    if args.patch is not None:
        mcfg = dataclasses.replace(mcfg, patch=args.patch)
    if args.smoothness is not None:
        mcfg = dataclasses.replace(mcfg, smoothness=args.smoothness)
    rep = run_polygon(inp, args.out_dir, mcfg, compute.device)
    print(
        f"mrf {inp.polygon_id}: {rep['labels']} photos, {len(rep['photos_used'])} used, "
        f"coverage {rep['coverage']:.3f}, {rep['time_s']:.1f}s"
    )
    return 0
