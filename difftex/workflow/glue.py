"""Helpers of the Snakemake workflow (Snakefile, workflow/rules/*.smk): config merging, per-stage
config files, scene inputs, resource estimates, the end-of-run summary and report.

Kept out of the Snakefile so that they can be tested and so that `snakemake --lint` sees
no functions mixed with rules.
"""

from __future__ import annotations

import copy
import json
from pathlib import Path
from typing import Any

from difftex.errors import DifftexError
from difftex.evaluation.report import stage_benchmarks
from difftex.layout import STATS, Results
from difftex.scene.camera import IMAGE_SUFFIXES, image_files  # noqa: F401 -- IMAGE_SUFFIXES: common.smk reads it here

# Sections each stage command reads (docs/stages.md). A stage's config file holds only these,
# so a change elsewhere leaves its file, and therefore its outputs, untouched.
STAGE_SECTIONS = {
    "filter": ("filter",),
    # the texel sizes' memory cap counts optimize.top_k slots per texel
    "visibility": ("texture", "visibility", "optimize.top_k"),
    # the initialization reads only what fixes the photos' crops (decode scale, supersampling, the
    # relief sweep's range, and whether the sweep runs on a polygon); the one-job texture stage and
    # the optimization read the whole section
    "initialize": ("optimize.exact_decode", "optimize.supersample", "optimize.relief", "optimize.relief_range",
                   "optimize.relief_min_cos", "optimize.relief_min_elevation"),
    # histogram matching (run.split): the transfers' own keys, the level they are estimated at, and
    # what the photos are mapped with there (the crops' keys and the relief they are mapped through);
    # a key ending in * stands for every key of the section that starts with what precedes it
    "histmatch": ("optimize.histogram_matching", "optimize.histmatch_*", "optimize.long_side_start",
                  "optimize.exact_decode", "optimize.supersample", "optimize.relief*"),
    "texture": ("optimize",),
    # the height fields from dense geometry (the GPU stereo keys are the dense_stereo rule's)
    "heights": ("dense.source", "dense.range", "dense.max_share", "dense.long_side", "dense.layers",
                "dense.smoothness"),
    # COLMAP PatchMatch stereo on a GPU (rule dense_stereo): its keys of the same section, the
    # switch dense.stereo left out (the rule runs only when it is on)
    "dense": ("dense.max_image_size", "dense.photos", "dense.num_*", "dense.window_*", "dense.geom_*",
              "dense.gpu_*"),
    # device and compilation: read by the texture jobs, but not an input of them (no result changes)
    "compute": ("compute",),
    "output": ("output",),
    "assemble": ("assemble", "output"),
    "evaluate": ("evaluate",),
}

SPARSE_FILES = ("cameras", "images", "points3D")
EXAMPLE_SCENE = "data/synth/tiny"


# ---------------------------------------------------------------------------------------------
# Configuration


def deep_merge(base: dict, over: dict) -> dict:
    """``over`` merged into a copy of ``base``; nested dicts merge, everything else replaces."""
    out = copy.deepcopy(dict(base))
    for k, v in (over or {}).items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = deep_merge(out[k], v)
        else:
            out[k] = copy.deepcopy(v)
    return out


def expand_dotted(d: dict) -> dict:
    """{"optimize.lr": 0.01} -> {"optimize": {"lr": 0.01}} (snakemake --config has no nesting)."""
    out: dict = {}
    for k, v in (d or {}).items():
        parts = str(k).split(".")
        cur = out
        for p in parts[:-1]:
            nxt = cur.get(p)
            if not isinstance(nxt, dict):
                nxt = cur[p] = {}
            cur = nxt
        leaf = parts[-1]
        if isinstance(v, dict) and isinstance(cur.get(leaf), dict):
            cur[leaf] = deep_merge(cur[leaf], expand_dotted(v))
        else:
            cur[leaf] = expand_dotted(v) if isinstance(v, dict) else v
    return out


def coerce_types(user: Any, default: Any) -> Any:
    """Snakemake's --config reads nested values as plain strings ('optimize={lr: 0.01}' gives
    lr = "0.01"); parse such a string as YAML wherever the default is not a string."""
    import yaml

    if isinstance(user, dict):
        d = default if isinstance(default, dict) else {}
        return {k: coerce_types(v, d.get(k)) for k, v in user.items()}
    if isinstance(user, list):
        d = default[0] if isinstance(default, list) and default else None
        return [coerce_types(v, d) for v in user]
    if isinstance(user, str) and not isinstance(default, str):
        try:
            return yaml.safe_load(user) if user.strip() else user
        except yaml.YAMLError:
            return user
    if isinstance(user, str) and default == "auto":
        # "auto" modes that also take a number (texture.density) or a boolean (run.evaluate); not
        # YAML's on/off booleans, which are modes of their own (compute.compile)
        if user.strip().lower() in ("true", "false"):
            return user.strip().lower() == "true"
        try:
            return float(user)
        except ValueError:
            return user
    return user


def _load_yaml(path: Path) -> dict:
    import yaml

    try:
        data = yaml.safe_load(path.read_text()) or {}
    except FileNotFoundError:
        raise DifftexError(f"{path}: file not found") from None
    except yaml.YAMLError as exc:
        raise DifftexError(f"{path}: not valid YAML ({str(exc).splitlines()[0]})") from None
    if not isinstance(data, dict):
        raise DifftexError(f"{path}: must be a mapping")
    return data


def resolve_config(repo: str | Path, user: dict | None) -> dict:
    """defaults (config/config.yaml) < preset (config/presets/<name>.yaml) < the user's values
    (--configfile files and --config keys, dotted keys expanded)."""
    repo = Path(repo)
    defaults = _load_yaml(repo / "config" / "config.yaml")
    user = coerce_types(expand_dotted(dict(user or {})), defaults)
    preset = user.get("preset", defaults.get("preset"))
    cfg = defaults
    if preset:
        path = repo / "config" / "presets" / f"{preset}.yaml"
        if not path.is_file():
            known = sorted(p.stem for p in (repo / "config" / "presets").glob("*.yaml"))
            raise DifftexError(f"unknown preset '{preset}' (known: {', '.join(known)})")
        cfg = deep_merge(cfg, _load_yaml(path))
    cfg = deep_merge(cfg, user)
    if cfg.get("scene") is None:
        cfg["scene"] = ""
    return cfg


def user_config(repo: str | Path, configfiles, cli_config) -> dict:
    """The user's layer: --configfile files, then --config values. The repo's own
    config/config.yaml given as --configfile is left out, or its values would override the preset."""
    default = (Path(repo) / "config" / "config.yaml").resolve()
    user: dict = {}
    for f in configfiles or ():
        if Path(f).resolve() != default:
            user = deep_merge(user, _load_yaml(Path(f)))
    return deep_merge(user, dict(cli_config or {}))


def validate(cfg: dict, schema_path: str | Path) -> None:
    """Schema check with a one-line message naming the key (the snakemake.utils.validate error
    prints the whole schema)."""
    import jsonschema
    import yaml

    schema = yaml.safe_load(Path(schema_path).read_text())
    validator = jsonschema.Draft202012Validator(schema)
    errors = sorted(validator.iter_errors(cfg), key=lambda e: list(e.absolute_path))
    if errors:
        e = errors[0]
        where = ".".join(str(p) for p in e.absolute_path) or "config"
        raise DifftexError(f"invalid configuration: {where}: {e.message}")


def stage_config_text(cfg: dict, stage: str) -> str:
    """The YAML text of a stage's config file: the sections and keys STAGE_SECTIONS gives it."""
    import yaml

    sections: dict = {}
    for s in STAGE_SECTIONS[stage]:
        if s.endswith("*"):  # the keys of a section with this prefix
            sec, prefix = s[:-1].split(".", 1)
            sections.setdefault(sec, {}).update({k: v for k, v in cfg[sec].items() if k.startswith(prefix)})
        elif "." in s:  # one key of a section
            sec, key = s.split(".", 1)
            sections.setdefault(sec, {})[key] = cfg[sec][key]
        else:
            sections[s] = cfg[s]
    header = f"# written by the difftex workflow: the '{stage}' stage's sections\n"
    return header + yaml.safe_dump(sections, sort_keys=True)


def stage_config_paths(results: str | Path, texts: dict[str, str]) -> dict[str, str]:
    """{stage: R/config/<stage>-<digest>.yaml}: each stage's config file, named by its content.

    The files are made by the workflow's ``stage_config`` rule, not when the Snakefile is read,
    so a dry run writes nothing. A changed section gives a new file name, hence a changed input
    of that stage's jobs and of nothing else: Snakemake reruns exactly what reads the section,
    and the file's content can never be stale (a rewritten file of the same name could be, in a
    results folder whose metadata Snakemake lost).
    """
    import hashlib

    res = Results(results)
    return {
        stage: str(res.stage_config(stage, hashlib.sha256(text.encode()).hexdigest()[:12]))
        for stage, text in texts.items()
    }


# ---------------------------------------------------------------------------------------------
# Scene


def scene_name(scene: str | Path) -> str:
    """The results folder's name: the scene folder's, with characters a shell would split on
    or expand (spaces, quotes, $...) replaced by '_', so that every path the rules pass to a
    command is one word. Letters of any script are kept."""
    import re

    name = Path(scene).resolve().name
    safe = re.sub(r"_+", "_", re.sub(r"[^\w.+@,=-]", "_", name)).strip("_")
    if not safe or safe.strip(".") == "":
        raise DifftexError(f"{scene}: cannot name the results folder after this scene path")
    return safe


def dense_source(scene: str | Path, source: str):
    """The scene's dense geometry for the heights rule (difftex.geometry.dense.find_source),
    or None; a bad path stops the workflow with one line."""
    from difftex.geometry.dense import find_source

    return find_source(scene, source) if Path(scene).is_dir() else None


def dense_inputs(source) -> list[str]:
    """The files the heights rule reads of a dense source: the file, or a workspace's depth maps
    and model (a changed one reruns the heights and what follows)."""
    if source is None:
        return []
    if source.path.is_file():
        return [str(source.path)]
    files = sorted((source.path / "stereo" / "depth_maps").glob("*.bin"))
    return [str(p) for p in files + sorted((source.path / "sparse").glob("*.*"))]


def scene_inputs(scene: str | Path) -> list[str]:
    """The files a scene's stages depend on: proxy, COLMAP model, photos. Adding a photo adds an
    input, and Snakemake reruns what depends on the photo set."""
    from difftex.scene.loading import PROXY_NAMES

    root = Path(scene)
    if not root.is_dir():
        raise DifftexError(f"{root}: scene folder not found (set scene=path/to/scene)")
    proxies = [root / n for n in PROXY_NAMES if (root / n).is_file()]
    if not proxies:
        raise DifftexError(f"{root}: no proxy model ({', '.join(PROXY_NAMES)})")
    sparse = root / "sparse" / "0"
    if not sparse.is_dir():
        sparse = root / "sparse"
    model = [sparse / f"{n}{ext}" for n in SPARSE_FILES for ext in (".bin", ".txt") if (sparse / f"{n}{ext}").is_file()]
    if not any(p.stem == "images" for p in model):
        raise DifftexError(f"{root}: no COLMAP model in sparse/0 (cameras/images .bin or .txt)")
    images = image_files(root / "images")
    if not images:
        raise DifftexError(f"{root / 'images'}: no photos")
    return [str(p) for p in [proxies[0], *model, *images]]


_POLYGONS_CACHE: dict[tuple[str, int], list[dict]] = {}


def polygons(summary: str | Path) -> list[dict]:
    """Polygon rows of R/visibility/summary.json (cached per file version: the workflow asks for
    them once per job and resource of every polygon)."""
    from difftex.scene.files import read_json

    path = Path(summary)
    key = (str(path.resolve()), path.stat().st_mtime_ns if path.exists() else -1)
    if key not in _POLYGONS_CACHE:
        data = read_json(path)
        try:
            _POLYGONS_CACHE[key] = list(data["polygons"])
        except (KeyError, TypeError):
            raise DifftexError(f"{summary}: not a visibility summary (no 'polygons')") from None
    return _POLYGONS_CACHE[key]


def textured_ids(summary: str | Path) -> list[str]:
    """Polygons worth optimizing: at least one candidate photo and some coverage."""
    return [str(p["id"]) for p in polygons(summary) if p.get("photos") and float(p.get("coverage", 0)) > 0]


_JOBS_CACHE: dict[tuple, dict[str, list[str]]] = {}


def texture_jobs(summary: str | Path, cfg: dict) -> dict[str, list[str]]:
    """The texture jobs of the polygons worth optimizing (``jobs.texture_jobs``), cached per
    summary version and config: the workflow asks once per job and input of every polygon."""
    from difftex.workflow.jobs import texture_jobs as plan

    path = Path(summary)
    key = (str(path.resolve()), path.stat().st_mtime_ns, json.dumps([cfg["optimize"], cfg["run"]], sort_keys=True))
    if key not in _JOBS_CACHE:
        ids = set(textured_ids(summary))
        _JOBS_CACHE[key] = plan([p for p in polygons(summary) if str(p["id"]) in ids], cfg)
    return _JOBS_CACHE[key]


def polygon_row(summary: str | Path, pid: str) -> dict:
    for p in polygons(summary):
        if str(p["id"]) == pid:
            return p
    raise DifftexError(f"{summary}: no polygon '{pid}'")


def photo_paths(scene: str | Path, row: dict) -> list[str]:
    return [str(Path(scene) / "images" / name) for name in row.get("photos", [])]


# ---------------------------------------------------------------------------------------------
# Summary and report


def run_summary(results: str | Path) -> dict:
    """Everything the end-of-run message and the report show."""
    from difftex.scene.files import read_json

    res = Results(results)
    model = res.model_dir
    summary = read_json(res.model_summary)
    out = {
        "results": str(res.root),
        "model": {
            **{k: str(model / summary[k]) for k in ("glb", "obj", "mtl") if k in summary},
            **({"tileset": str(model / summary["tileset"]["file"])} if "tileset" in summary else {}),
        },
        "atlas_pages": [str(model / p["file"]) for p in summary.get("atlas_pages", [])],
        "polygons": summary.get("polygons", []),
        "untextured": summary.get("untextured", []),
        # model summaries written before these notes have none: every untextured one then reads "no photo sees it"
        "untextured_reasons": summary.get("untextured_reasons", {}),
        "textured_from_oblique": summary.get("textured_from_oblique", {}),
        "check": summary.get("check"),
        "stages": stage_benchmarks(res.root),
        "texels": _texel_sizes(res),
        "devices": _devices(res),
        "mixed_resolution": _mixed_resolution(res),
        "blurry": _blurry_photos(res),
    }
    if res.metrics.is_file():
        out["evaluation"] = str(res.metrics)
    if res.report_html.is_file():
        out["html_report"] = str(res.report_html)
    return out


def _texel_sizes(res: Results) -> dict:
    """Per polygon id: its texel size (scene units) and what set it, from the visibility summary."""
    from difftex.scene.files import read_json

    path = res.visibility_summary
    if not path.is_file():
        return {}
    try:
        rows = read_json(path).get("polygons", [])
    except (DifftexError, AttributeError):
        return {}
    return {r["id"]: (r.get("texel_size"), r.get("texel_size_bound")) for r in rows if "id" in r}


def _blurry_photos(res: Results) -> dict:
    """The photos the filter dropped as blurry, least sharp first, from R/photos.json:
    {"blur_ratio": ..., "photos": {name: sharpness / median}}; {} when none or no table."""
    from difftex.scene.files import read_json

    path = res.photos_json
    if not path.is_file():
        return {}
    try:
        table = read_json(path)
        rows = [r for r in table["photos"] if not r["kept"] and str(r["reason"]).startswith("blurry")]
        ratio = table.get("config", {}).get("blur_ratio")
    except (DifftexError, AttributeError, KeyError, TypeError):
        return {}
    if not rows:
        return {}
    rows.sort(key=lambda r: r.get("sharpness_rel", 0.0))
    return {"blur_ratio": ratio, "photos": {r["name"]: r.get("sharpness_rel") for r in rows}}


def _devices(res: Results) -> dict[str, int]:
    """How many polygons each torch device textured (from the texture stage's stats)."""
    out: dict[str, int] = {}
    for st in sorted(res.optimized_dir.glob(f"*/{STATS}")):
        try:
            dev = json.loads(st.read_text()).get("device")
        except (OSError, ValueError):
            continue
        if dev:
            out[dev] = out.get(dev, 0) + 1
    return out


def _mixed_resolution(res: Results) -> dict[str, float]:
    """Polygons textured as mixed resolution and their spread (from the texture stage's stats)."""
    out: dict[str, float] = {}
    for st in sorted(res.optimized_dir.glob(f"*/{STATS}")):
        try:
            d = json.loads(st.read_text())
        except (OSError, ValueError):
            continue
        if d.get("mixed_resolution") and d.get("resolution_spread") is not None:
            out[str(d.get("polygon_id", st.parent.name))] = float(d["resolution_spread"])
    return out


def _polygon_state(p: dict) -> str:
    """One polygon's line of the summary: coverage and photos, and where they came from."""
    if not p.get("textured"):
        return "untextured (grey)"
    state = f"coverage {100 * p['coverage']:5.1f}%, {p['photos']:3d} photos"
    if p.get("oblique_angles"):
        state += f", oblique only ({min(p['oblique_angles'].values()):.0f} deg)"
    elif p.get("textured_from_glimpses"):
        state += ", from glimpses (under filter.min_pixels)"
    if p.get("rescued"):
        n = len(p["rescued"])
        state += f", {n} of them only for texels no other photo sees"
    return state


def format_summary(s: dict) -> str:
    """The end-of-run message: polygons, times, the GLB check, what is untextured and why, files."""
    polys = s["polygons"]
    n_tex = sum(1 for p in polys if p.get("textured"))
    lines = [f"difftex: {n_tex}/{len(polys)} polygons textured"]
    if polys:
        w = max(len(p["id"]) for p in polys)
        texels = s.get("texels") or {}
        for p in polys:
            size = "x".join(map(str, p["texture_size"])) if p.get("texture_size") else "-"
            ts, bound = texels.get(p["id"], (None, None))
            if ts and p.get("texture_size"):
                size += f" texels of {ts:.3g} units" + (f" (set by {bound})" if bound and bound != "photos" else "")
            mixed = (s.get("mixed_resolution") or {}).get(p["id"])
            note = f", mixed resolution (finest photo {mixed:.1f}x the median)" if mixed and p.get("textured") else ""
            lines.append(f"  {p['id']:<{w}}  {_polygon_state(p)}{note}  {size}")
    if s["stages"]:
        total = sum(d["seconds"] for d in s["stages"].values())
        parts = ", ".join(
            f"{r} {d['seconds']:.0f}s" + (f"/{d['jobs']}" if d["jobs"] > 1 else "") for r, d in s["stages"].items()
        )
        lines.append(f"time: {total:.0f} s of jobs ({parts})")
    if s.get("devices"):
        lines.append("device: " + ", ".join(f"{d} ({n} polygons)" for d, n in s["devices"].items()))
    chk = s.get("check")
    if chk:
        lines.append(
            f"GLB reloaded: {chk['glb_polygons']} polygons, max colour difference to the textures "
            f"{chk['max_color_error']:.3f}"
        )
    oblique = s.get("textured_from_oblique") or {}
    if oblique:
        lines.append(
            "textured from oblique photos only (every photo sees them beyond filter.max_angle_deg): "
            + ", ".join(f"{pid} ({min(a.values()):.0f} deg)" if a else pid for pid, a in oblique.items())
        )
    blurry = s.get("blurry") or {}
    if blurry.get("photos"):
        shown = [f"{n} ({r:.2g})" if isinstance(r, float) else n for n, r in blurry["photos"].items()]
        more = f", and {len(shown) - 10} more" if len(shown) > 10 else ""
        ratio = blurry.get("blur_ratio")
        lines.append(
            f"{len(shown)} photo{'s' if len(shown) > 1 else ''} dropped as blurry (sharpness below "
            f"filter.blur_ratio{f' = {ratio:g}' if isinstance(ratio, (int, float)) else ''} x the median; "
            f"photos.csv): {', '.join(shown[:10])}{more}"
        )
    if s["untextured"]:
        reasons = s.get("untextured_reasons") or {}
        lines.append("untextured (grey), no photo sees them:")
        lines += [f"  {pid}: {reasons.get(pid, 'no photo sees it')}" for pid in s["untextured"]]
    if s.get("evaluation"):
        lines.append(f"metrics: {s['evaluation']}")
    if s.get("html_report"):
        lines.append(f"report: {s['html_report']}")
    lines.append(f"atlas: {', '.join(s['atlas_pages'])}")
    for k, label in (("obj", "OBJ"), ("glb", "GLB"), ("tileset", "3D Tiles")):
        if k in s["model"]:
            lines.append(f"{label}: {s['model'][k]}")
    return "\n".join(lines)


def print_summary(results: str | Path) -> None:
    """The onsuccess message; silent when the model is not there (a partial target was run)."""
    path = Results(results).model_summary
    if not path.is_file():
        return
    try:
        print("\n" + format_summary(run_summary(results)))
    except (DifftexError, KeyError, TypeError, ValueError) as exc:
        print(f"difftex: cannot summarise {path}: {exc}")


def write_report(results: str | Path, out: str | Path) -> None:
    """R/report.md: the summary, per-stage times and (if any) the evaluation metrics."""
    from difftex.scene.files import read_json, write_text

    s = run_summary(results)
    md = [f"# difftex results: {Path(results).name}", "", "```", format_summary(s), "```", ""]
    if s["stages"]:
        md += ["## Stages", "", "| stage | jobs | wall s (sum) | max RSS MB |", "|---|---:|---:|---:|"]
        for r, d in s["stages"].items():
            md.append(f"| {r} | {d['jobs']} | {d['seconds']:.1f} | {d['max_rss_mb']:.0f} |")
        md.append("")
    if s.get("evaluation"):
        md += ["## Evaluation", "", "```json", json.dumps(read_json(s["evaluation"]), indent=2)[:20000], "```", ""]
    write_text(out, "\n".join(md))


def want_evaluation(cfg: dict) -> bool:
    """run.evaluate: true, false, or auto (when this difftex has the `evaluate` command)."""
    import importlib.util

    mode = cfg["run"]["evaluate"]
    if mode is False:
        return False
    has_cmd = importlib.util.find_spec("difftex.cli.evaluate") is not None
    if mode is True and not has_cmd:
        raise DifftexError("run.evaluate is true but this difftex has no 'evaluate' command")
    return has_cmd

