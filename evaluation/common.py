"""Shared runner of the evaluation commands: one scene, several methods, the same inputs.

For a scene and a stage config, the photo filter and the visibility masks run once
(``OUT/common``); every method then textures every polygon from the same visibility files into
its own results folder ``OUT/<method>/textures/<pid>/`` and is scored by
``difftex evaluate`` into ``OUT/<method>/evaluation/metrics.json``. The stages are the
``difftex`` sub-commands, called in-process (no interpreter start-up per polygon), so the times
are those of the commands themselves. Method times are the sum over polygons of their per-polygon
stages; filter + visibility are shared and reported separately.
"""

from __future__ import annotations

import copy
import datetime as _dt
import json
import os
import platform
import shutil
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

METHODS = ("difftex", "average", "frontal", "mrf", "texrecon", "meshlab-face", "meshlab-blend")
LABELS = {"difftex": "DiffTex (ours)", "difftex-paper": "DiffTex as published (preset `paper`, same texel sizes)",
          "average": "Averaging (view blending)", "frontal": "Most frontal photo",
          "mrf": "MRF view selection + leveling (LTBC-style)", "texrecon": "texrecon (mvs-texturing)",
          "meshlab-face": "MeshLab per-face raster parameterization", "meshlab-blend": "MeshLab per-texel raster blend",
          "reprojection": "reprojection (texrecon on the dense mesh, baked)",
          "difftex-dense": "DiffTex with the scene's dense cloud (dense/)",
          "difftex-true-relief": "DiffTex through the true relief (the bound; synthetic scenes)"}


def run_script(main) -> None:
    """Exit with ``main()``'s status. Bad input that difftex names (a folder without textures, an
    unreadable file: DifftexError) ends in one line that names the script, not a traceback."""
    from difftex.errors import DifftexError

    try:
        sys.exit(main())
    except DifftexError as e:
        sys.exit(f"{Path(sys.argv[0]).stem}: {e}")


def machine() -> dict:
    import torch

    cpu = platform.processor() or ""
    try:
        for ln in Path("/proc/cpuinfo").read_text().splitlines():
            if ln.startswith("model name"):
                cpu = ln.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    ram = None
    try:
        for ln in Path("/proc/meminfo").read_text().splitlines():
            if ln.startswith("MemTotal"):
                ram = round(int(ln.split()[1]) / 1024**2, 1)
    except OSError:
        pass
    try:
        commit = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True
        ).stdout.strip()
        # code that differs from the commit made the figures: say so (results and docs do not count)
        changed = subprocess.run(
            ["git", "diff", "--quiet", "HEAD", "--", "difftex", "evaluation/*.py", "workflow", "config"],
            cwd=ROOT, capture_output=True,
        ).returncode
        if commit and changed == 1:
            commit += " + uncommitted code"
    except OSError:
        commit = ""
    return {
        "cpu": cpu,
        "cores": os.cpu_count(),
        "ram_gib": ram,
        "torch": torch.__version__,
        "torch_threads": torch.get_num_threads(),
        "cuda": torch.cuda.is_available(),
        "load_avg": os.getloadavg(),
        "platform": platform.platform(),
        "python": platform.python_version(),
        "git_commit": commit,
        "date_utc": _dt.datetime.now(_dt.UTC).strftime("%Y-%m-%d %H:%M UTC"),
    }


def base_config(long_side: int | None, preset: str | None = "fast", overrides: dict | None = None) -> dict:
    """The stage sections from config/config.yaml, a preset over them, then ``overrides`` (nested).

    ``long_side``: every polygon's map gets this long side (``texture.density: null``); None keeps
    the preset's density (``auto``: from the photos' ground sampling distance). ``preset`` None,
    "" or "default": config.yaml alone, what the workflow runs without a preset.
    """
    import yaml

    cfg = yaml.safe_load((ROOT / "config" / "config.yaml").read_text())
    if preset and preset != "default":
        cfg = _merge(cfg, yaml.safe_load((ROOT / "config" / "presets" / f"{preset}.yaml").read_text()) or {})
    cfg = {k: v for k, v in cfg.items() if isinstance(v, dict) and k not in ("run",)}
    if long_side is not None:
        cfg["texture"]["density"] = None
        cfg["texture"]["long_side"] = long_side
    cfg["compute"]["device"] = "cpu"
    return _merge(cfg, overrides or {})


def size_note(long_side: int | None, cfg: dict) -> str:
    """The tables' line on texel sizes: a fixed long side, or the preset's density."""
    t = cfg["texture"]
    if long_side:
        return f"**Reduced sizes**: texture long side {long_side} for every method (paper: 2048); "
    return (
        f"Texel size: `density: {t['density']}` at density_scale {t.get('density_scale')} (max long side "
        f"{t.get('max_long_side')}), per polygon from its photos, the same frames for every method; "
    )


def _merge(a: dict, b: dict) -> dict:
    out = copy.deepcopy(a)
    for k, v in b.items():
        out[k] = _merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else copy.deepcopy(v)
    return out


def difftex(*argv: str) -> float:
    """Run a difftex sub-command in-process; returns its wall time; raises on failure."""
    from difftex.cli import main

    t0 = time.perf_counter()
    rc = main([str(a) for a in argv])
    if rc != 0:
        raise RuntimeError(f"difftex {' '.join(map(str, argv))} failed with exit code {rc}")
    return time.perf_counter() - t0


def run_common(scene: Path, out: Path, cfg: dict, only: list[str] | None = None) -> dict:
    """Filter and visibility once per scene and config (``only``: texture just these polygons)."""
    from difftex.scene.files import read_json

    c = out / "common"
    c.mkdir(parents=True, exist_ok=True)
    cfg_path = c / "config.yaml"
    _write_yaml(cfg_path, cfg)
    t_f = difftex("filter", "--quiet", "--scene", scene, "--config", cfg_path, "--out", c / "photos.json")
    t_v = difftex(
        "visibility",
        "--quiet",
        "--scene",
        scene,
        "--photos",
        c / "photos.json",
        "--config",
        cfg_path,
        "--out-dir",
        c / "visibility",
    )
    summary = read_json(c / "visibility" / "summary.json")
    return {
        "config": cfg_path,
        "visibility": c / "visibility",
        "filter_s": t_f,
        "visibility_s": t_v,
        "polygons": [r for r in summary["polygons"] if r["photos"] and (not only or r["id"] in only)],
    }


def _write_yaml(path: Path, data: dict) -> None:
    import yaml

    from difftex.scene.files import write_text

    write_text(path, yaml.safe_dump(data, sort_keys=False))


def run_heights(scene: Path, r: Path, common: dict, source: str = "auto") -> tuple[Path | None, float]:
    """The heights stage on every polygon from the scene's dense geometry (``source``: as
    ``dense.source``): (its folder, or None when the scene has none; seconds)."""
    from difftex.geometry.dense import find_source

    if find_source(scene, source) is None:
        return None, 0.0
    out = Path(r) / "heights"
    t = difftex("heights", "--scene", scene, "--rows", Path(common["visibility"]) / "summary.json",
                "--visibility-dir", common["visibility"], "--config", common["config"], "--source",
                source, "--out-dir", out, "--done", out / "done.json")
    return out, t


def run_method(method: str, scene: Path, r: Path, common: dict, cfg: dict | None = None,
               heights: Path | None = None) -> dict:
    """Texture every seen polygon with ``method`` into results folder ``r``; returns timings.

    ``cfg``: a stage config for this run only (ablations); default: the common one. ``heights``:
    difftex maps the photos through these height fields (difftex heights).
    """
    r = Path(r)
    if r.exists():
        shutil.rmtree(r)
    r.mkdir(parents=True)
    cfg_path = common["config"]
    if cfg is not None:
        cfg_path = r / "config.yaml"
        _write_yaml(cfg_path, cfg)
    (r / "visibility.txt").write_text(str(Path(common["visibility"]).resolve()))
    times = {}
    t0 = time.perf_counter()
    for row in common["polygons"]:
        pid = row["id"]
        vis = Path(common["visibility"]) / f"{pid}.npz"
        tex = r / "textures" / pid
        ts = time.perf_counter()
        if method == "difftex":
            difftex(
                "texture",
                "--scene",
                scene,
                "--visibility",
                vis,
                "--config",
                cfg_path,
                "--out-dir",
                r / "optimized" / pid,
                "--png-dir",
                tex,
                "--no-progress",
                *(("--heights-dir", heights) if heights is not None else ()),
            )
        elif method in ("average", "frontal"):
            difftex(
                "baseline",
                "--scene",
                scene,
                "--visibility",
                vis,
                "--config",
                cfg_path,
                "--method",
                method,
                "--out-dir",
                tex,
            )
        elif method == "mrf":
            difftex("mrf", "--scene", scene, "--visibility", vis, "--config", cfg_path, "--out-dir", tex)
        else:
            raise ValueError(method)
        times[pid] = time.perf_counter() - ts
    total = time.perf_counter() - t0
    return {"method": method, "results": str(r), "polygon_s": times, "total_s": total}


def evaluate(scene: Path, results: Path, lpips: str = "auto", config: Path | None = None) -> dict:
    from difftex.scene.files import read_json

    out = Path(results) / "evaluation" / "metrics.json"
    extra = ["--config", config] if config else []
    t = difftex("evaluate", "--quiet", "--scene", scene, "--results", results, "--out", out, "--lpips", lpips, *extra)
    m = read_json(out)
    m["eval_s"] = t
    return m


def add_table_args(ap, name: str) -> None:
    """The options every table command shares: LPIPS variant, work folder, output stem, threads."""
    ap.add_argument("--lpips", default="auto")
    ap.add_argument("--work", default=f"evaluation/out/{name}", help="work folder (results per method)")
    ap.add_argument("--out", default=f"evaluation/results/{name}", help="output stem (.md, .json)")
    ap.add_argument("--threads", type=int, default=2)


def scene_polygons(
    scene: Path, polygons: list[str] | None, density_scale: float, max_long_side: int,
    texel_candidates: int | None = None, long_side: int | None = None,
):
    """A scene's polygons at `density: auto` x ``density_scale`` (at most ``max_long_side``), or
    every map ``long_side`` texels long when it is given (Table 1's ``--long-side``): (the loaded
    scene, the visibility of each of ``polygons`` (None: all) that a photo sees), as the variant
    and bound scripts texture them.
    """
    from difftex.config import TextureConfig
    from difftex.geometry.visibility import scene_visibility
    from difftex.scene.loading import load_scene

    sc = load_scene(scene, check_images=False)
    cands = {p.id: [ph.name for ph in sc.photos] for p in sc.proxy.polygons if polygons is None or p.id in polygons}
    tex = (TextureConfig(density=None, long_side=long_side) if long_side else
           TextureConfig(density="auto", density_scale=density_scale, max_long_side=max_long_side))
    vis = scene_visibility(sc.proxy, sc.photos, sc.up, cands, tex, progress=False, texel_candidates=texel_candidates)
    return sc, [v for v in vis if v.photos]


def polygon_ids(text: str) -> list[str] | None:
    """--polygons value: comma-separated ids, or 'all' (None: every polygon)."""
    return None if text == "all" else text.split(",")


def fmt(v, nd=4) -> str:
    if v is None:
        return "n/a"
    if isinstance(v, float):
        return f"{v:.{nd}f}"
    return str(v)


def write_outputs(stem: Path, md: str, data: dict) -> None:
    from difftex.scene.files import write_json, write_text

    write_text(stem.with_suffix(".md"), md)
    write_json(stem.with_suffix(".json"), json.loads(json.dumps(data, default=str)))


def finish_table(stem: Path, lines: list[str], t_all: float, mach: dict, args, rows: list) -> str:
    """Close a table with the whole command's time, write <stem>.md/.json, print and return the markdown."""
    total = time.perf_counter() - t_all
    md = "\n".join(lines + ["", f"Whole command: {total:.0f} s."]) + "\n"
    write_outputs(Path(stem), md, {"machine": mach, "args": vars(args), "rows": rows, "total_s": total})
    print(md)
    return md


def header(title: str, command: str, m: dict, notes: list[str]) -> str:
    lines = [
        f"# {title}",
        "",
        f"Command: `{command}`  ",
        f"Date: {m['date_utc']}  ",
        f"Machine: {m['cpu']}, {m['cores']} cores, {m['ram_gib']} GiB RAM, torch {m['torch']} "
        f"({m['torch_threads']} threads), CUDA {'yes' if m['cuda'] else 'no'}; git {m['git_commit']}",
        "",
    ]
    lines += [f"- {n}" for n in notes]
    return "\n".join(lines) + "\n\n"
