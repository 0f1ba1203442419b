"""difftex evaluate: Table 1/2 metrics of one results folder (difftex's or a baseline's)."""

from __future__ import annotations

NAME = "evaluate"
HELP = "score a textured proxy: ground-truth maps (synthetic), held-out views, Q_front / Q_vc"


def add_arguments(p) -> None:
    p.add_argument("--scene", required=True, help="scene folder (with ground_truth/ or holdout.json to score against)")
    p.add_argument("--results", required=True, help="results folder with textures/<pid>/ and visibility/")
    p.add_argument("--config", help="YAML config; section 'evaluate' is read")
    p.add_argument("--out", required=True, help="metrics JSON; error maps and renders go beside it")
    p.add_argument("--lpips", choices=["auto", "lpips", "stlpips", "none"], help="overrides evaluate.lpips")
    p.add_argument(
        "--lpips-weights",
        metavar="DIR",
        help="folder with classic LPIPS's lpips_weights.pt (piq) and vgg16-397923af.pth (torchvision); "
        "overrides evaluate.lpips_weights (default: the torch hub cache)",
    )
    p.add_argument("--quiet", action="store_true")


def run(args) -> int:
    import dataclasses
    from pathlib import Path

    from difftex.config import section
    from difftex.evaluation.evaluate import EvaluateConfig, evaluate_results, summary_line, to_json
    from difftex.scene.files import write_json

    cfg = section(args.config, "evaluate", EvaluateConfig)
    if args.lpips:
        cfg = dataclasses.replace(cfg, lpips=args.lpips)
    if args.lpips_weights:
        cfg = dataclasses.replace(cfg, lpips_weights=args.lpips_weights)
    out = Path(args.out)
    res = evaluate_results(args.scene, args.results, cfg, out_dir=out.parent, progress=not args.quiet)
    write_json(out, to_json(res))
    print(f"evaluate {Path(args.results).name}: {summary_line(res)} ({res['time_s']:.1f} s) -> {out}")
    return 0
