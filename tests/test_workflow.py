"""The Snakemake workflow: configuration handling, lint, the rule graph, and one end-to-end run on
the tiny synthetic scene (outputs exist, load, cover the proxy; a rerun has nothing to do; an
optimization-only change reruns only optimization and what follows)."""

from __future__ import annotations

import glob
import importlib.util
import math
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from difftex.errors import DifftexError
from difftex.layout import Results
from difftex.workflow import glue as wf
from difftex.workflow import jobs

REPO = Path(__file__).resolve().parents[1]
SNAKEFILE = REPO / "Snakefile"
LUND = Path(os.environ.get("DIFFTEX_SHARED", REPO.parent / "shared")) / "data" / "lund-door"
BIN = Path(sys.executable).parent


def snakemake(workdir: Path, *args: str, timeout: int = 1800) -> subprocess.CompletedProcess:
    env = dict(os.environ, PATH=f"{BIN}{os.pathsep}{os.environ.get('PATH', '')}")
    return subprocess.run(
        [str(BIN / "snakemake"), "-s", str(SNAKEFILE), "--directory", str(workdir), *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        env=env,
    )


def job_counts(out: str) -> dict[str, int]:
    """{rule: count} from the 'Job stats' table of a (dry) run."""
    m = re.search(r"Job stats:\n.*?\n-+\s+-+\n(.*?)\ntotal", out, re.S)
    if not m:
        return {}
    return {line.split()[0]: int(line.split()[1]) for line in m.group(1).splitlines() if line.strip()}


# ---------------------------------------------------------------------------------------------
# Configuration


def test_presets_and_user_values_merge_in_order():
    cfg = wf.resolve_config(REPO, {"preset": "fast", "optimize": {"lr": "0.01"}})
    wf.validate(cfg, REPO / "workflow/schemas/config.schema.yaml")
    assert cfg["texture"]["density_scale"] == 0.25 and cfg["texture"]["density"] == "auto"  # from the preset
    assert cfg["optimize"]["lr"] == 0.01  # the user's string coerced to the default's type
    assert cfg["optimize"]["alpha"] == 1.0  # untouched default
    # a user value beats the preset: a long side given by the user sets the size, not auto
    cfg = wf.resolve_config(REPO, {"preset": "fast", "texture": {"long_side": "64"}})
    assert cfg["texture"]["long_side"] == 64
    from difftex.config import TextureConfig

    assert TextureConfig(**cfg["texture"]).mode == "long_side"
    cfg = wf.resolve_config(REPO, {"preset": "fast", "texture": {"density": "12.5", "long_side": 64}})
    assert TextureConfig(**cfg["texture"]).mode == "density" and cfg["texture"]["density"] == 12.5
    # the paper preset renders into the photos
    assert wf.resolve_config(REPO, {"preset": "paper"})["optimize"]["loss_mode"] == "render"


def test_every_preset_file_is_a_choice_the_schema_accepts():
    """A preset file the schema does not list is refused before the run starts, and a listed
    preset without its file fails at the merge: the two lists are the same."""
    schema = yaml.safe_load((REPO / "workflow/schemas/config.schema.yaml").read_text())
    listed = set(schema["properties"]["preset"]["enum"]) - {None}
    files = {p.stem for p in (REPO / "config" / "presets").glob("*.yaml")}
    assert listed == files and {"fast", "balanced", "paper"} <= files
    for name in sorted(files):
        wf.validate(wf.resolve_config(REPO, {"preset": name}), REPO / "workflow/schemas/config.schema.yaml")


def test_the_default_config_file_given_again_does_not_override_the_preset(tmp_path):
    mine = tmp_path / "mine.yaml"
    mine.write_text("optimize:\n  lr: 0.02\n")
    user = wf.user_config(REPO, [REPO / "config" / "config.yaml", mine], {"preset": "fast"})
    cfg = wf.resolve_config(REPO, user)
    assert cfg["texture"]["density_scale"] == 0.25 and cfg["optimize"]["lr"] == 0.02


@pytest.mark.parametrize(
    "user, message",
    [
        ({"optimize": {"lrr": 1}}, "lrr"),
        ({"optimize": {"loss_mode": "pixel"}}, "optimize.loss_mode"),
        ({"texture": {"long_side": 0}}, "texture.long_side"),
        ({"optimize": {"mixed_spread": 0.5}}, "optimize.mixed_spread"),  # 0 or >= 1, refused before any job
        ({"sceen": "x"}, "sceen"),
    ],
)
def test_bad_config_is_a_one_line_error(user, message):
    with pytest.raises(DifftexError, match=message):
        wf.validate(wf.resolve_config(REPO, user), REPO / "workflow/schemas/config.schema.yaml")
    with pytest.raises(DifftexError, match="unknown preset"):
        wf.resolve_config(REPO, {"preset": "fastest"})


def test_stage_files_hold_only_their_sections_and_are_named_by_their_content(tmp_path):
    cfg = wf.resolve_config(REPO, {})
    texts = {s: wf.stage_config_text(cfg, s) for s in wf.STAGE_SECTIONS}
    assert "lr:" in texts["texture"] and "lr:" not in texts["filter"]
    assert "device:" in texts["compute"] and "device:" not in texts["texture"]
    paths = wf.stage_config_paths(tmp_path, texts)
    assert not any(Path(p).exists() for p in paths.values())  # made by a rule, not when read
    cfg2 = wf.deep_merge(cfg, {"optimize": {"lr": 0.02}})
    paths2 = wf.stage_config_paths(tmp_path, {s: wf.stage_config_text(cfg2, s) for s in wf.STAGE_SECTIONS})
    # only the texture stage's file changes name, so only what reads it reruns
    assert {s for s in paths if paths[s] != paths2[s]} == {"texture"}
    # the stage_config rule's command (from the rule file), through the shell Snakemake uses
    rule = (REPO / "workflow/rules/scene.smk").read_text().split("rule stage_config:")[1].split("rule ")[0]
    command = rule.split("shell:")[1].strip().strip('"')
    text = wf.stage_config_text(cfg2, "texture") + "note: 'it''s' $HOME `x` \\n\n"
    out, log = Path(paths2["texture"]), tmp_path / "stage.log"
    out.parent.mkdir(parents=True, exist_ok=True)
    filled = command.replace("{params.text:q}", shlex.quote(text)).replace("{output:q}", shlex.quote(str(out)))
    subprocess.run(["bash", "-euo", "pipefail", "-c", filled.replace("{log:q}", shlex.quote(str(log)))], check=True)
    assert out.read_text() == text and not out.with_name(out.name + ".tmp").exists()


def test_memory_estimate_grows_with_texels_and_photos():
    run = wf.resolve_config(REPO, {})["run"]
    small = jobs.polygon_mem_mb(".", {"width": 256, "height": 256, "photos": ["a"]}, run)
    big = jobs.polygon_mem_mb(".", {"width": 2048, "height": 2048, "photos": ["a"] * 8}, run)
    assert run["base_mem_mb"] < small < big
    # slots are capped at top_k: 40 candidates cost 8 slots per texel plus their (cropped) photos
    row = {"width": 2048, "height": 2048, "photos": ["a"] * 40}
    capped, uncapped = jobs.polygon_mem_mb(".", row, run, top_k=8), jobs.polygon_mem_mb(".", row, run)
    slot_mb = 2048 * 2048 * float(run["bytes_per_texel_photo"]) / 2**20
    assert abs((uncapped - capped) - 32 * slot_mb) < 2


# ---------------------------------------------------------------------------------------------
# Rule graph (no stage runs)


def test_lint_is_clean(tmp_path):
    if not LUND.is_dir():
        pytest.skip(f"{LUND} missing")
    r = snakemake(tmp_path, "--lint", "--config", f"scene={LUND}")
    assert r.returncode == 0, r.stdout + r.stderr


def test_dry_run_plans_every_stage_and_a_wrong_key_stops_it(tmp_path):
    if not LUND.is_dir():
        pytest.skip(f"{LUND} missing")
    r = snakemake(tmp_path, "-n", "--config", f"scene={LUND}", "preset=fast")
    assert r.returncode == 0, r.stderr
    counts = job_counts(r.stdout)
    assert {"filter", "visibility", "assemble", "report", "html_report", "all"} <= set(counts)
    assert not (tmp_path / "results").exists()  # a dry run writes nothing
    bad = snakemake(tmp_path, "-n", "--config", f"scene={LUND}", "optimize={lrr: 1}")
    assert bad.returncode != 0 and "lrr" in bad.stdout + bad.stderr
    missing = snakemake(tmp_path, "-n", "--config", f"scene={tmp_path / 'nowhere'}")
    assert missing.returncode != 0 and "scene folder not found" in missing.stdout + missing.stderr


# ---------------------------------------------------------------------------------------------
# End to end on the tiny synthetic scene

STAGES = ("filter", "visibility", "texture", "assemble", "evaluate")


@pytest.fixture(scope="session")
def tiny_scene(tmp_path_factory):
    missing = [s for s in STAGES if importlib.util.find_spec(f"difftex.cli.{s}") is None]
    if missing:
        pytest.skip(f"difftex has no {', '.join(missing)} command yet")
    from difftex.synth import generate

    out = tmp_path_factory.mktemp("synth") / "tiny"
    generate("tiny", out, progress=False)
    return out


@pytest.mark.slow
def test_workflow_end_to_end(tiny_scene, tmp_path):
    import numpy as np
    import trimesh

    from difftex.scene.files import read_json
    from difftex.scene.proxy import load_proxy

    work = tmp_path / "work"
    # smaller than the fast preset: the test checks the plumbing, not the texture quality
    small = (
        "texture={long_side: 128}",
        "optimize={long_side_start: 64, max_iters_per_level: [15, 8]}",
        "evaluate={lpips: none, render_long_side: 256}",
    )
    args = ("--cores", "2", "--config", f"scene={tiny_scene}", "preset=fast", *small)
    r = snakemake(work, *args)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    R = Results(work / "results" / "tiny")
    glb, obj = R.model_file(".glb"), R.model_file(".obj")
    assert glb.is_file() and obj.is_file()
    assert str(glb.relative_to(work)) in r.stdout + r.stderr  # the end-of-run summary names the GLB
    # ... the device that textured the polygons and each polygon's texel size in scene units
    assert "device: cpu (" in r.stdout + r.stderr
    assert re.search(r"\d+x\d+ texels of [0-9.e-]+ units", r.stdout + r.stderr)

    proxy = load_proxy(tiny_scene / "proxy.obj")
    scene = trimesh.load(glb, force="scene")
    assert set(scene.geometry) == set(proxy.ids)
    for p in proxy.polygons:
        assert scene.geometry[p.id].area == pytest.approx(p.area, rel=1e-5)
    mesh = trimesh.load(obj, force="mesh")
    assert mesh.area == pytest.approx(sum(p.area for p in proxy.polygons), rel=1e-5)

    summary = read_json(R.model_summary)
    vis = {p["id"]: p for p in read_json(R.visibility_summary)["polygons"]}
    for row in summary["polygons"]:
        seen = vis[row["id"]]["coverage"] > 0 and vis[row["id"]]["photos"]
        assert row["textured"] == bool(seen), row
    assert summary["textured_area_share"] > 0.5
    assert summary["check"]["max_color_error"] < 0.02
    metrics = read_json(R.metrics)
    assert metrics["textured_polygons"] == len(proxy.ids) and "maps" in metrics
    # the rendered view of the reloaded GLB looks like the photo
    assert summary["view_check"]["mean_abs_diff"] < 0.25
    texture = np.asarray(scene.geometry[summary["polygons"][0]["id"]].visual.material.baseColorTexture)
    assert texture.std() > 0.01  # not a blank atlas
    # the HTML report shows the scene's view metrics (not n/a) and every polygon's maps
    page = R.report_html.read_text()
    assert f"{metrics['views']['overall']['ssim']:.4f}" in page
    assert all(f"<h3 id='{pid}'>" in page for pid in proxy.ids)

    # a second run has nothing to do
    again = snakemake(work, "-n", *args)
    assert again.returncode == 0 and "Nothing to be done" in again.stdout, again.stdout[-2000:]

    # an optimization-only change reruns texturing and what follows, not filter/visibility
    n_tex = len([p for p in summary["polygons"] if p["textured"]])
    # the tiny scene's polygons are small: they share texture jobs, each polygon's files apart
    n_jobs = len(glob.glob(str(R.job_file("texture", "*"))))
    assert 1 <= n_jobs < n_tex
    assert sum(R.composite(p["id"]).is_file() for p in summary["polygons"]) == n_tex
    changed = snakemake(work, "-n", *args, "optimize={lr: 0.01}")
    counts = job_counts(changed.stdout)
    assert counts.get("texture", 0) == n_jobs
    assert "filter" not in counts and "visibility" not in counts
    # device or compilation: only their file is rewritten, no texturing (same result to float tolerance)
    same = snakemake(work, "-n", *args, "compute={device: cpu, compile: 'off'}")
    assert same.returncode == 0, same.stdout[-2000:]
    assert set(job_counts(same.stdout)) <= {"compute_config", "all"}, same.stdout[-2000:]
    # an output-format change rewrites the files, no texturing
    counts = job_counts(snakemake(work, "-n", *args, "output={bits: 16}").stdout)
    assert counts.get("finish", 0) == n_jobs and "texture" not in counts  # one per texture job
    # ... and an assembly-only change only assembly
    counts = job_counts(snakemake(work, "-n", *args, "assemble={padding: 2}").stdout)
    # evaluation reads the textures, not the model; the reports read the model summary (the HTML
    # report: the untextured polygons' reasons and the model view); stage_config writes the new assemble file
    assert set(counts) == {"stage_config", "assemble", "report", "html_report", "all"}


def test_config_yaml_mirrors_the_stage_dataclasses():
    """config/config.yaml lists every key of each stage's config dataclass with its default, so
    the workflow's defaults are the method's and a new parameter is not forgotten."""
    import dataclasses

    import yaml

    from difftex.compose.outputs import OutputConfig
    from difftex.config import FilterConfig, TextureConfig, VisibilityConfig
    from difftex.evaluation.evaluate import EvaluateConfig
    from difftex.export.assemble import AssembleConfig
    from difftex.method.config import ComputeConfig, OptimizeConfig

    classes = {
        "texture": TextureConfig,
        "filter": FilterConfig,
        "visibility": VisibilityConfig,
        "optimize": OptimizeConfig,
        "compute": ComputeConfig,
        "output": OutputConfig,
        "assemble": AssembleConfig,
        "evaluate": EvaluateConfig,
    }
    cfg = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    for name, cls in classes.items():
        defaults = dataclasses.asdict(cls())
        assert set(cfg[name]) == set(defaults), name
        for key, value in defaults.items():
            mine = cfg[name][key]
            if isinstance(value, tuple):
                value, mine = list(value), list(mine)
            assert mine == value, f"{name}.{key}: config.yaml {mine!r} != {cls.__name__} {value!r}"


def test_version_names_torch_and_the_device():
    r = subprocess.run([sys.executable, "-m", "difftex", "--version"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    lines = r.stdout.splitlines()
    import torch

    assert lines[0].startswith("difftex ") and lines[1] == f"torch {torch.__version__}"
    assert lines[2].startswith("device: cuda" if torch.cuda.is_available() else "device: cpu")


def test_pack_jobs_auto_is_a_local_runs_cores_and_fixed_on_a_cluster():
    """`auto` packs small polygons into as many jobs as a local run has cores; on a cluster the
    main process and each job's own Snakemake see other core counts, so both use the fallback
    (a job's polygons must not depend on the process that asks); a number is kept."""
    assert jobs.pack_jobs("auto", local=True, cores=2) == 2
    assert jobs.pack_jobs("auto", local=True, cores=64) == 64
    assert jobs.pack_jobs("auto", local=False, cores=2) == jobs.PACK_JOBS_FALLBACK
    assert jobs.pack_jobs("auto", local=True, cores=None) == jobs.PACK_JOBS_FALLBACK
    assert jobs.pack_jobs(3, local=True, cores=16) == 3
    same = [{"id": f"w{i}", "width": 200, "height": 200, "photos": ["a"] * 4} for i in range(40)]
    for n in (1, 2, 5):
        cfg = wf.resolve_config(REPO, {"preset": "fast", "run": {"pack_jobs": n}})
        assert len(jobs.texture_jobs(same, cfg)) == n


def test_a_polygons_estimated_seconds_count_its_photos_as_well_as_its_iterations():
    """polygon_seconds = optimization (texel x slot x iteration caps) + mapping (texels x
    candidates) + set-up: at `fast` the mapping dominates, so of two polygons with the same
    texels and slots the one with 60 candidates takes longer than the one with 8; with the
    paper's iteration caps the optimization counts for more."""
    fast = wf.resolve_config(REPO, {"preset": "fast"})
    few = {"id": "a", "width": 600, "height": 250, "photos": ["p"] * 8}
    many = dict(few, photos=["p"] * 60)
    assert jobs.polygon_work(few, fast) == jobs.polygon_work(many, fast)  # top_k slots either way
    assert jobs.polygon_seconds(many, fast) > 3 * jobs.polygon_seconds(few, fast)
    run = fast["run"]
    mapping = 600 * 250 * 60 / run["texel_photos_per_second"]
    optim = 60 * jobs.polygon_work(many, fast) / run["texels_per_minute"]
    assert jobs.polygon_seconds(many, fast) == pytest.approx(optim + mapping + run["polygon_setup_s"])
    assert mapping > optim
    longer = wf.resolve_config(REPO, {"preset": "fast", "optimize": {"max_iters_per_level": [300, 150, 80, 40]}})

    def share(cfg):  # the optimization's share of the estimate
        return 60 * jobs.polygon_work(many, cfg) / cfg["run"]["texels_per_minute"] / jobs.polygon_seconds(many, cfg)

    assert share(longer) > share(fast)


def test_small_polygons_share_texture_jobs_and_large_ones_keep_their_own():
    cfg = wf.resolve_config(REPO, {"preset": "fast"})
    rows = [{"id": "facade", "width": 1024, "height": 600, "photos": ["a"] * 8}]
    rows += [{"id": f"jamb{i}", "width": 80 + i, "height": 300, "photos": ["a"] * 5} for i in range(30)]
    pack = float(cfg["run"]["pack_seconds"])
    n_jobs = jobs.pack_jobs(cfg["run"]["pack_jobs"], local=False, cores=None)
    work = {r["id"]: jobs.polygon_seconds(r, cfg) for r in rows}
    total = sum(work.values())
    limit = min(pack, max(work["facade"], total / n_jobs))  # no shared job larger than the facade's
    assert all(work[r["id"]] < limit for r in rows[1:])  # the jambs are below it
    assert sum(work[r["id"]] for r in rows[1:]) > limit  # ... and need more than one job
    plan = jobs.texture_jobs(rows, cfg)
    members = [pid for pids in plan.values() for pid in pids]
    assert sorted(members) == sorted(r["id"] for r in rows)  # every polygon once
    assert plan["facade"] == ["facade"]  # named by its polygon, alone
    groups = [pids for name, pids in plan.items() if name != "facade"]
    assert len(groups) < len(rows) - 1 and all(name.startswith("group-") for name in plan if name != "facade")
    largest_small = max(work[r["id"]] for r in rows[1:])
    assert all(sum(work[p] for p in g) <= limit + largest_small for g in groups)  # balanced, near the limit
    # many equal small polygons, none large: they share about pack_jobs jobs (not one)
    same = [{"id": f"w{i}", "width": 200, "height": 200, "photos": ["a"] * 4} for i in range(40)]
    assert len(jobs.texture_jobs(same, cfg)) == n_jobs
    # a small scene's polygons are not all in one job, however little work they hold
    few = [{"id": f"s{i}", "width": 60 + i, "height": 50, "photos": ["a"] * 3} for i in range(6)]
    assert 1 < len(jobs.texture_jobs(few, cfg)) <= n_jobs
    assert jobs.texture_jobs(rows, cfg) == plan  # stable
    # another membership is another job name; pack_seconds 0 is a job per polygon
    assert set(jobs.texture_jobs(rows[:-1], cfg)) != set(plan)
    alone = jobs.texture_jobs(rows, wf.deep_merge(cfg, {"run": {"pack_seconds": 0}}))
    assert alone == {r["id"]: [r["id"]] for r in rows}
    # a shared job asks for its largest polygon's memory plus the decoded photos it keeps
    big = max(jobs.polygon_mem_mb(".", r, cfg["run"], cfg["optimize"]["top_k"]) for r in rows[1:])
    assert big < jobs.job_mem_mb(".", rows[1:], cfg) <= big + cfg["run"]["decode_cache_mb"] + 1
    assert jobs.runtime_min(rows, cfg) >= jobs.runtime_min(rows[:1], cfg) >= 10
    # the render loss's jobs get the time of its slower iterations (a cluster's time limit)
    render = wf.deep_merge(cfg, {"optimize": {"loss_mode": "render"}})
    assert jobs.polygon_work(rows[0], render) == jobs.RENDER_LOSS_COST * jobs.polygon_work(rows[0], cfg)
    paper = wf.resolve_config(REPO, {"preset": "paper"})
    wall = [{"id": "wall", "width": 4096, "height": 3000, "photos": ["a"] * 8}]
    texel = wf.deep_merge(paper, {"optimize": {"loss_mode": "texel"}})
    assert jobs.runtime_min(wall, paper) > jobs.runtime_min(wall, texel) > 10
    # polygons with no work at all still get a job (a shared one)
    empty = [{"id": f"e{i}", "width": 0, "height": 0, "photos": ["a"]} for i in range(3)]
    assert sorted(p for m in jobs.texture_jobs(empty + rows[:1], cfg).values() for p in m) == sorted(
        ["e0", "e1", "e2", "facade"]
    )
    # the scheduler starts the longest jobs first: priority = estimated seconds
    by_id = {r["id"]: r for r in rows}
    prio = {name: jobs.priority([by_id[p] for p in pids], cfg) for name, pids in plan.items()}
    est = {name: sum(work[p] for p in pids) for name, pids in plan.items()}
    assert max(prio, key=prio.get) == max(est, key=est.get)
    assert all(abs(prio[n] - est[n]) <= 1 for n in plan)


def test_a_shared_jobs_decode_cache_is_counted_at_the_photos_stored_bit_depth(tmp_path):
    import numpy as np

    from difftex.scene.files import write_image

    cfg = wf.resolve_config(REPO, {"run": {"decode_cache_mb": 100000}})
    (tmp_path / "images").mkdir()
    img = np.random.default_rng(0).random((300, 400, 3))
    write_image(tmp_path / "images" / "p8.png", img, bits=8)
    write_image(tmp_path / "images" / "p16.png", img, bits=16)
    for name, per_value in (("p8.png", 1), ("p16.png", 2)):
        rows = [{"id": f"s{i}", "width": 50, "height": 40, "photos": [name] + [f"{name}.{i}.{j}" for j in range(9)]}
                for i in range(2)]
        alone = max(jobs.polygon_mem_mb(tmp_path, r, cfg["run"], cfg["optimize"]["top_k"]) for r in rows)
        # 19 distinct photos of the first one's size, kept as stored: RGB at 1 or 2 bytes a value
        cache = 19 * 400 * 300 * 3 * per_value / 2**20
        assert jobs.job_mem_mb(tmp_path, rows, cfg) == math.ceil(alone + cache)
    # the cache never asks for more than its budget
    small = wf.deep_merge(cfg, {"run": {"decode_cache_mb": 1}})
    assert jobs.job_mem_mb(tmp_path, rows, small) <= alone + 1


def test_polygons_that_share_photos_share_a_job_when_it_fits():
    """A roof goes into the job of the wall whose photos see it (the job decodes them once), not
    into the least-loaded job, as long as that job stays within the limit plus the decodes saved;
    a polygon that shares few photos does not tip a job over the limit."""
    cfg = wf.resolve_config(REPO, {"preset": "fast", "run": {"pack_jobs": 2}})
    a = [f"a{i}.png" for i in range(60)]
    b = [f"b{i}.png" for i in range(60)]
    rows = [
        {"id": "wallA", "width": 640, "height": 240, "photos": a},
        {"id": "wallB", "width": 620, "height": 230, "photos": b},  # slightly less work: least loaded
        {"id": "roofA", "width": 240, "height": 90, "photos": a[:35] + ["c.png"]},
        {"id": "roofB", "width": 230, "height": 90, "photos": b[:30] + ["d.png"]},
    ]
    plan = sorted(sorted(m) for m in jobs.texture_jobs(rows, cfg).values())
    assert plan == [["roofA", "wallA"], ["roofB", "wallB"]]
    # without the shared photos, the least-loaded rule pairs the roofs the other way round for the first
    blind = [dict(r, photos=[f"{r['id']}-{i}" for i in range(len(r["photos"]))]) for r in rows]
    assert sorted(sorted(m) for m in jobs.texture_jobs(blind, cfg).values()) != plan
    # no allowance: only the limit decides again
    none = wf.deep_merge(cfg, {"run": {"photo_decode_s": 0}})
    work = {r["id"]: jobs.polygon_seconds(r, cfg) for r in rows}
    for members in jobs.texture_jobs(rows, none).values():
        assert sum(work[p] for p in members) <= sum(work.values()) / 2 + max(work.values())
