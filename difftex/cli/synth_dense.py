"""difftex synth-dense: a COLMAP-like dense reconstruction (fused.ply, meshed-poisson.ply) of a
synthetic scene, written into its dense/ folder without rendering anything again."""

from __future__ import annotations

NAME = "synth-dense"
HELP = ("Write a COLMAP-like dense reconstruction (dense/fused.ply, dense/meshed-poisson.ply) of a "
        "`difftex synth` scene, from its model (no rendering).")


def add_arguments(p) -> None:
    p.add_argument("--scene", required=True, help="a `difftex synth` building scene (the folder holding synth.json)")
    p.add_argument("--noise", type=float, default=0.015,
                   help="std of the points' depth error along the viewing ray, scene units (default 0.015)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")


def run(args) -> int:
    from difftex.errors import DifftexError

    if not args.noise >= 0:
        raise DifftexError(f"--noise must be >= 0, got {args.noise}")
    write_scene_dense(args.scene, args.noise, progress=not args.quiet)
    return 0


def write_scene_dense(scene, noise: float = 0.015, progress: bool = True) -> dict:
    """Write ``<scene>/dense/`` and print one summary line (also used by ``difftex synth --dense``).

    Args:
        scene: a `difftex synth` building scene folder.
        noise: std of the depth error, scene units.
        progress: show a progress bar on stderr.

    Returns:
        The summary written to ``dense/dense.json``.
    """
    from pathlib import Path

    from rich.console import Console
    from rich.progress import MofNCompleteColumn, Progress

    from difftex.synth.dense import DenseSettings, read_manifest, write_dense

    scene = Path(scene)
    read_manifest(scene)  # a folder that is not a synth scene fails here, before the bar is drawn
    bar = Progress(*Progress.get_default_columns(), MofNCompleteColumn(), console=Console(stderr=True),
                   disable=not progress)
    task = bar.add_task(f"dense {scene.name}", total=None)
    with bar:
        summary = write_dense(scene, DenseSettings(noise=noise),
                              progress=lambda done, total: bar.update(task, completed=done, total=total))
    print(f"synth-dense: wrote {scene / 'dense'} ({summary['points']:,} points, {summary['mesh']['faces']:,} faces) "
          f"in {summary['seconds']['total']:.1f} s")
    return summary
