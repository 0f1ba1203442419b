"""Synthetic buildings with ground truth (the paper's virtual data set), rendered by Mitsuba 3.

``generate(preset, out_dir, seed, **overrides)`` writes, per building, a scene in the layout of
real scenes (images/, sparse/0/, proxy.obj) plus ground_truth/ (see docs/synth.md) and
preview pictures, and returns the folder it wrote.
"""

from __future__ import annotations

import time
from pathlib import Path

from difftex.synth.presets import PRESETS, BuildingSpec, SynthConfig, get_preset

__all__ = ["generate", "generate_scene", "PRESETS", "SynthConfig", "BuildingSpec", "get_preset"]


def generate(preset: str | SynthConfig, out_dir: str | Path, seed: int = 0, progress: bool = True,
             buildings: list[str] | None = None, **overrides) -> Path:
    """Generate a preset (or a config). One building: the scene is ``out_dir`` itself; several:
    one scene per building under ``out_dir/<name>``. ``buildings`` picks a subset by name.
    Returns ``out_dir``."""
    from difftex.errors import DifftexError
    from difftex.scene.files import write_json

    cfg = preset if isinstance(preset, SynthConfig) else get_preset(preset)
    cfg = cfg.replace(**overrides) if overrides else cfg
    specs = list(cfg.buildings)
    if buildings:
        known = {b.name: b for b in specs}
        missing = [b for b in buildings if b not in known]
        if missing:
            raise DifftexError(f"unknown building(s) {', '.join(missing)} (this preset has {', '.join(known)})")
        index = {b.name: i for i, b in enumerate(specs)}
        chosen = [(index[n], known[n]) for n in buildings]
    else:
        chosen = list(enumerate(specs))
    out_dir = Path(out_dir)
    single = len(specs) == 1
    summary = []
    for bi, spec in chosen:
        scene_dir = out_dir if single else out_dir / spec.name
        t0 = time.perf_counter()
        manifest = generate_scene(cfg, spec, scene_dir, seed=seed, building_index=bi, progress=progress,
                                  preset_name=preset if isinstance(preset, str) else "custom")
        summary.append({"building": spec.name, "dir": str(scene_dir), "seconds": time.perf_counter() - t0,
                        "timing": manifest["timing"]})
    if not single:
        write_json(out_dir / "synth_summary.json", {"preset": preset if isinstance(preset, str) else "custom",
                                                    "seed": seed, "scenes": summary})
    return out_dir


def generate_scene(cfg: SynthConfig, spec: BuildingSpec, scene_dir: str | Path, seed: int = 0,
                   building_index: int = 0, progress: bool = True, preset_name: str = "custom") -> dict:
    """One building's scene; returns its manifest (also written as ``synth.json``)."""
    from difftex.synth.pipeline import run_scene

    return run_scene(cfg, spec, Path(scene_dir), seed, building_index, progress, preset_name)
