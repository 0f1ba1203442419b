"""Every per-polygon file of the results folder is part of the cache (difftex.workflow.products):
a finished job that lost one of its polygons' files (a deleted texture.png, composite.npz ...)
runs again, and the same command makes the file again, the same bytes.

The unit tests build a results folder by hand; the workflow test runs the small synthetic scene,
deletes files and runs the same command again.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from test_workflow import REPO, job_counts, snakemake

from difftex.layout import Results, polygon_products
from difftex.workflow import glue as wf
from difftex.workflow.products import (
    ONE_JOB_RULES,
    SPLIT_RULES,
    Rebuild,
    missing_products,
    missing_visibility,
    report_lines,
)


def _finish_jobs(res: Results, rules, jobs: dict[str, list[str]]) -> None:
    """Each job's list and its polygons' files, as a finished run leaves them."""
    for rule in rules:
        for job, pids in jobs.items():
            for f in [res.job_file(rule, job)] + [f for pid in pids for f in polygon_products(res, rule, pid)]:
                f.parent.mkdir(parents=True, exist_ok=True)
                f.write_text("x")


def test_finished_jobs_that_lost_a_polygons_file_are_found(tmp_path):
    res = Results(tmp_path)
    jobs = {"wall": ["wall"], "group-1": ["a", "b"]}
    _finish_jobs(res, ONE_JOB_RULES, jobs)
    assert missing_products(res, jobs, ONE_JOB_RULES) == {}
    res.texture("b").unlink()
    res.composite("wall").unlink()
    (res.polygon_textures("wall") / "report.json").unlink()
    assert missing_products(res, jobs, ONE_JOB_RULES) == {
        res.job_file("texture", "wall"): [res.composite("wall")],
        res.job_file("finish", "wall"): [res.polygon_textures("wall") / "report.json"],
        res.job_file("finish", "group-1"): [res.texture("b")],
    }
    # a job whose list is gone is not finished: Snakemake runs it anyway, nothing to add
    res.job_file("finish", "group-1").unlink()
    assert res.job_file("finish", "group-1") not in missing_products(res, jobs, ONE_JOB_RULES)
    # with output.exr, finish also leaves texture.exr
    exr = missing_products(res, {"wall": ["wall"]}, ("finish",), exr=True)
    assert res.polygon_textures("wall") / "texture.exr" in exr[res.job_file("finish", "wall")]


def test_the_split_stages_files_are_found_per_stage(tmp_path):
    res = Results(tmp_path)
    jobs = {"wall": ["wall"]}
    _finish_jobs(res, SPLIT_RULES, jobs)
    res.crops("wall").unlink()
    res.transfers("wall").unlink()
    res.optimized("wall").unlink()
    assert list(missing_products(res, jobs, SPLIT_RULES)) == [
        res.job_file("initialize", "wall"), res.job_file("histmatch", "wall"), res.job_file("optimize", "wall")]


def test_visibility_tiles_that_lost_a_polygons_file_are_found(tmp_path):
    res = Results(tmp_path)
    res.visibility_tile("1-of-2").parent.mkdir(parents=True)
    res.visibility_tile("1-of-2").write_text(json.dumps({"rows": [{"id": "wall"}, {"id": "roof"}]}))
    res.visibility_tile("2-of-2").write_text("not json")  # the merge reports it, not this
    res.visibility("wall").write_text("x")
    assert missing_visibility(res, ["1-of-2", "2-of-2", "3-of-3"]) == {
        res.visibility_tile("1-of-2"): [res.visibility("roof")]}
    res.visibility("roof").write_text("x")
    assert missing_visibility(res, ["1-of-2"]) == {}


def test_report_names_a_file_per_job_and_counts_the_rest(tmp_path):
    missing = {tmp_path / f"j{i}.json": [tmp_path / f"p{i}/texture.png", tmp_path / "x"] for i in range(7)}
    lines = report_lines(missing, real=True)
    assert len(lines) == 6 and all(line.startswith("difftex: ") for line in lines)
    assert "p0/texture.png and 1 more of its files missing" in lines[0] and "runs again" in lines[0]
    assert "2 more jobs" in lines[-1]
    assert "dry run" in report_lines(missing, real=False)[0]


def test_rebuild_deletes_the_lists_in_a_real_run_only(tmp_path, capsys):
    res = Results(tmp_path)
    rows = [{"id": pid, "photos": ["a.jpg"], "coverage": 1.0, "width": 8, "height": 8} for pid in ("wall", "roof")]
    res.visibility_summary.parent.mkdir(parents=True)
    res.visibility_summary.write_text(json.dumps({"polygons": rows}))
    cfg = wf.resolve_config(REPO, {"run": {"pack_seconds": 0}})  # a job per polygon
    jobs = wf.texture_jobs(res.visibility_summary, cfg)
    assert jobs == {"wall": ["wall"], "roof": ["roof"]}
    _finish_jobs(res, ONE_JOB_RULES, jobs)
    res.texture("roof").unlink()
    rebuild = Rebuild(tmp_path, cfg, split=False)
    assert list(rebuild.rebuild(real=False)) == [res.job_file("finish", "roof")]
    assert res.job_file("finish", "roof").is_file()  # a dry run changes nothing
    assert "would run again" in capsys.readouterr().err
    rebuild.rebuild(real=True)
    assert not res.job_file("finish", "roof").exists() and res.job_file("finish", "wall").is_file()
    assert "texture.png missing" in capsys.readouterr().err
    # before the visibility stage has run there is nothing to look at
    assert Rebuild(tmp_path / "none", cfg, split=True).rebuild(real=True) == {}


# ---------------------------------------------------------------------------------------------
# The workflow on the small synthetic scene

QUICK = (
    "preset=fast",
    "texture={long_side: 64}",
    "optimize={long_side_start: 32, max_iters_per_level: [5, 3]}",
    "run={evaluate: false, split: false}",
)


def _without_times(report):
    if isinstance(report, dict):
        return {k: _without_times(v) for k, v in report.items() if not k.startswith("time_")}
    if isinstance(report, list):
        return [_without_times(v) for v in report]
    return report


@pytest.fixture(scope="module")
def finished_run(small_synth_scene, tmp_path_factory):
    """The small scene textured once, and the command that did it (the tests below delete files
    and run it again, which leaves the run finished again)."""
    work = tmp_path_factory.mktemp("products") / "run"
    args = ("--cores", "2", "--config", f"scene={small_synth_scene}", *QUICK)
    r = snakemake(work, *args)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    return Results(work / "results" / "small"), work, args


def _textures(res: Results) -> dict[Path, bytes]:
    pids = sorted(f.parent.name for f in res.textures_dir.glob("*/texture.png"))
    return {f: f.read_bytes() for pid in pids for f in res.polygon_textures(pid).iterdir()}


def _same_textures(before: dict[Path, bytes]) -> None:
    """The same bytes, but the reports' timings of polygons whose texture job ran again."""
    for f, data in before.items():
        if f.name == "report.json":
            assert _without_times(json.loads(f.read_text())) == _without_times(json.loads(data)), f
        else:
            assert f.read_bytes() == data, f


@pytest.mark.slow
def test_a_deleted_texture_is_made_again_by_the_same_command(finished_run):
    res, work, args = finished_run
    before = _textures(res)
    pids = sorted({f.parent.name for f in before})
    gone, recomposed = pids[0], pids[-1]
    res.texture(gone).unlink()  # the case
    res.composite(recomposed).unlink()  # a file of the texture stage, and one of finish's with it
    (res.polygon_textures(recomposed) / "source.npz").unlink()

    dry = snakemake(work, "-n", *args)
    assert dry.returncode == 0 and "would run again" in dry.stderr, dry.stderr[-2000:]
    assert not res.texture(gone).exists()  # a dry run changes nothing

    again = snakemake(work, *args)
    assert again.returncode == 0, again.stdout[-3000:] + again.stderr[-3000:]
    counts = job_counts(again.stdout + again.stderr)
    # the texture job of the polygon that lost its composite.npz, the finish jobs of both, what
    # follows them, and nothing before them (their polygons' files are all there)
    assert counts.get("texture") == 1 and 1 <= counts.get("finish", 0) <= 2 and counts.get("assemble") == 1, counts
    assert not {"filter", "visibility", "visibility_tile", "initialize"} & set(counts), counts
    assert res.composite(recomposed).is_file()
    _same_textures(before)
    assert "Nothing to be done" in snakemake(work, "-n", *args).stdout


@pytest.mark.slow
def test_a_deleted_visibility_file_is_made_again(finished_run):
    import numpy as np

    res, work, args = finished_run
    before = _textures(res)
    pid = sorted(f.parent.name for f in res.textures_dir.glob("*/texture.png"))[0]
    arrays = dict(np.load(res.visibility(pid)))
    res.visibility(pid).unlink()
    again = snakemake(work, *args)
    assert again.returncode == 0, again.stdout[-3000:] + again.stderr[-3000:]
    assert "visibility_tile" in job_counts(again.stdout + again.stderr)
    back = np.load(res.visibility(pid))
    assert set(back.files) == set(arrays) and all(np.array_equal(back[k], arrays[k]) for k in arrays)
    _same_textures(before)
    assert "Nothing to be done" in snakemake(work, "-n", *args).stdout
