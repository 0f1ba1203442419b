"""The whole-scene stages in bounded jobs (issue #32): photo chunks for the filter, spatial tiles of
polygons for visibility, and their merges, which must give exactly what one job over the whole
scene gives; the workflow plans as many jobs as the run.* sizes ask for, and on the 100-polygon
block its merged outputs equal the single-job run's."""

from __future__ import annotations

import glob
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from difftex.cli import main as cli_main
from difftex.errors import DifftexError
from difftex.layout import Results
from difftex.scene.camera import image_files
from difftex.scene.partition import (
    chunk_bounds,
    parse_part,
    part_name,
    part_spec,
    parts_for,
    photo_chunk,
    polygon_tiles,
)
from difftex.synth.district import generate_district
from difftex.workflow import jobs

REPO = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent


# ---------------------------------------------------------------------------------------------
# The splits


@pytest.mark.parametrize("count,parts", [(0, 1), (1, 1), (7, 3), (10, 10), (1000, 7), (3, 5)])
def test_chunks_cover_every_item_once_in_order_and_balanced(count, parts):
    bounds = [chunk_bounds(count, j, parts) for j in range(parts)]
    assert bounds[0][0] == 0 and bounds[-1][1] == count
    assert all(a[1] == b[0] for a, b in zip(bounds, bounds[1:]))  # contiguous, no gap or overlap
    sizes = [b - a for a, b in bounds]
    assert max(sizes) - min(sizes) <= 1
    names = [f"p{i:04d}.jpg" for i in range(count)]
    assert sum((photo_chunk(names, j, parts) for j in range(parts)), []) == names


def test_part_counts_names_and_specs():
    assert parts_for(0, 5) == 1 and parts_for(5, 5) == 1 and parts_for(6, 5) == 2 and parts_for(10_000, 1000) == 10
    with pytest.raises(DifftexError):
        parts_for(3, 0)
    assert part_name(2, 12) == "003-of-012" and part_spec("003-of-012") == "3/12" and parse_part("3/12") == (2, 12)
    assert part_spec(part_name(9999, 10000)) == "10000/10000"
    # names sort in part order, so the merge's inputs are in order whatever the count
    assert sorted(part_name(j, 1500) for j in range(1500)) == [part_name(j, 1500) for j in range(1500)]
    for bad in ("0/3", "4/3", "3", "a/b", "-1/2"):
        with pytest.raises(DifftexError):
            parse_part(bad)
    with pytest.raises(DifftexError):
        part_spec("3-12")
    with pytest.raises(DifftexError):
        chunk_bounds(10, 3, 3)


def test_tiles_are_spatial_disjoint_complete_and_balanced():
    rng = np.random.default_rng(0)
    # four well separated blocks of 25 polygons: four tiles are the four blocks
    centres = np.array([[0, 0, 0], [1000, 0, 0], [0, 1000, 0], [1000, 1000, 0]], float)
    pts = np.concatenate([c + rng.uniform(-10, 10, (25, 3)) for c in centres])
    order = rng.permutation(len(pts))  # the proxy's order is not spatial
    pts = pts[order]
    tiles = polygon_tiles(pts, 4)
    assert sorted(np.concatenate(tiles).tolist()) == list(range(100))
    blocks = [{int(np.argmin(np.linalg.norm(centres - pts[i], axis=1))) for i in t} for t in tiles]
    assert all(len(b) == 1 for b in blocks) and len({b.pop() for b in blocks}) == 4
    for n in (1, 3, 7, 33, 100):
        tiles = polygon_tiles(pts, n)
        sizes = [len(t) for t in tiles]
        assert len(tiles) == n and sum(sizes) == 100 and max(sizes) - min(sizes) <= 1
        assert all((np.diff(t) > 0).all() for t in tiles)  # each sorted, no repeats
        assert [t.tolist() for t in tiles] == [t.tolist() for t in polygon_tiles(pts, n)]  # deterministic


def test_tiles_at_extremes():
    assert [t.tolist() for t in polygon_tiles(np.zeros((0, 3)), 4)] == [[]]
    assert [t.tolist() for t in polygon_tiles(np.ones((1, 3)), 4)] == [[0]]
    same = polygon_tiles(np.zeros((9, 3)), 3)  # every centroid equal: split by index
    assert [t.tolist() for t in same] == [[0, 1, 2], [3, 4, 5], [6, 7, 8]]
    assert len(polygon_tiles(np.random.default_rng(1).normal(size=(5, 3)), 50)) == 5
    far = np.array([[0, 0, 0], [1e12, 0, 0], [1e-12, 0, 0], [2e12, 1, 0]])
    assert sorted(np.concatenate(polygon_tiles(far, 2)).tolist()) == [0, 1, 2, 3]
    with pytest.raises(DifftexError):
        polygon_tiles(np.array([[0, 0, np.nan], [1, 1, 1]]), 2)


# ---------------------------------------------------------------------------------------------
# The stages in parts equal the stages in one job


@pytest.fixture(scope="module")
def district(tmp_path_factory):
    out = tmp_path_factory.mktemp("district")
    generate_district(out, buildings=4, views=6, seed=5)
    return out


def _cli(*args: str) -> int:
    return cli_main(list(args))


def _table(path: Path) -> dict:
    data = json.loads(path.read_text())
    data.pop("seconds")
    return data


def test_filter_chunks_merge_to_the_single_job_table(district, tmp_path):
    assert _cli("filter", "--quiet", "--scene", str(district), "--out", str(tmp_path / "one.json")) == 0
    parts = [str(tmp_path / f"part{j}.json") for j in range(1, 4)]
    for j, path in enumerate(parts, 1):
        assert _cli("filter", "--quiet", "--scene", str(district), "--part", f"{j}/3", "--out", path) == 0
    # each chunk measured only its own photos, a third of them
    names = [json.loads(Path(p).read_text())["records"] for p in parts]
    counts = [len(n) for n in names]
    assert sum(counts) == len(image_files(district / "images")) and max(counts) - min(counts) <= 1
    # merged in any order of the files
    merged = str(tmp_path / "m.json")
    assert _cli("filter", "--quiet", "--scene", str(district), "--parts", *parts[::-1], "--out", merged) == 0
    assert _table(tmp_path / "m.json") == _table(tmp_path / "one.json")
    assert (tmp_path / "m.csv").read_text() == (tmp_path / "one.csv").read_text()


def test_a_missing_or_foreign_chunk_is_one_line(district, tmp_path, capsys):
    part = tmp_path / "p1.json"
    assert _cli("filter", "--quiet", "--scene", str(district), "--part", "1/2", "--out", str(part)) == 0
    capsys.readouterr()
    merged = str(tmp_path / "m.json")
    assert _cli("filter", "--quiet", "--scene", str(district), "--parts", str(part), "--out", merged) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "rerun the filter stage" in err[0] and str(part) in err[0]
    assert not (tmp_path / "m.json").exists()
    other = tmp_path / "other.json"
    other.write_text(json.dumps({"polygons": {}}))
    assert _cli("filter", "--quiet", "--scene", str(district), "--parts", str(other), "--out", merged) != 0
    assert "not a chunk of the difftex filter stage" in capsys.readouterr().err
    assert _cli("filter", "--quiet", "--scene", str(district), "--part", "3/2", "--out", str(part)) != 0
    assert "PART must be between 1 and PARTS" in capsys.readouterr().err


def _npz_equal(a: Path, b: Path) -> bool:
    with np.load(a) as x, np.load(b) as y:
        return sorted(x.files) == sorted(y.files) and all(np.array_equal(x[k], y[k]) for k in x.files)


def test_visibility_tiles_merge_to_the_single_job_result(district, tmp_path):
    table = tmp_path / "photos.json"
    assert _cli("filter", "--quiet", "--scene", str(district), "--out", str(table)) == 0
    one, tiled = tmp_path / "one", tmp_path / "tiled"
    assert _cli("visibility", "--quiet", "--scene", str(district), "--photos", str(table), "--out-dir", str(one)) == 0
    rows = [str(tiled / "tiles" / f"{j}.json") for j in range(1, 4)]
    for j, path in enumerate(rows, 1):
        assert _cli("visibility", "--quiet", "--scene", str(district), "--photos", str(table), "--out-dir", str(tiled),
                    "--tile", f"{j}/3", "--rows", path) == 0
    assert _cli("visibility", "--out-dir", str(tiled), "--merge", *rows) == 0
    assert _table(tiled / "summary.json") == _table(one / "summary.json")
    npz = sorted(p.name for p in one.glob("*.npz"))
    assert npz and npz == sorted(p.name for p in tiled.glob("*.npz"))
    assert all(_npz_equal(one / n, tiled / n) for n in npz)
    # a tile missing from the merge is one line, and no summary is written
    (tiled / "summary.json").unlink()
    with pytest.raises(DifftexError, match="do not hold every polygon once"):
        from difftex.cli.visibility import merge_tiles

        merge_tiles(rows[:2], tiled)
    assert not (tiled / "summary.json").exists()


# ---------------------------------------------------------------------------------------------
# The workflow's plan, and the 100-polygon block in the workflow


def test_the_workflow_plans_jobs_from_the_run_sizes(district):
    inputs = [str(district / "proxy.obj"), *(str(p) for p in image_files(district / "images"))]
    photos = len(inputs) - 1
    parts = jobs.filter_parts(inputs, district, 5)
    assert len(parts) == -(-photos // 5) and sum(len(v) for v in parts.values()) == photos
    assert sum(parts.values(), []) == inputs[1:]
    assert list(jobs.filter_parts(inputs, district, 10_000)) == ["001-of-001"]
    assert jobs.filter_parts([], REPO / "no-such-scene", 5) == {"001-of-001": []}  # the example, not yet made
    polygons = sum(1 for line in (district / "proxy.obj").read_text().splitlines() if line.startswith("f "))
    assert len(jobs.visibility_tiles(district, 7)) == -(-polygons // 7)
    assert jobs.visibility_tiles(REPO / "no-such-scene", 7) == ["001-of-001"]


def _snakemake(workdir: Path, *args: str) -> subprocess.CompletedProcess:
    env = dict(os.environ, PATH=f"{BIN}{os.pathsep}{os.environ.get('PATH', '')}")
    return subprocess.run([str(BIN / "snakemake"), "-s", str(REPO / "Snakefile"), "--directory", str(workdir), *args],
                          capture_output=True, text=True, timeout=1800, env=env)


def test_block_scene_stages_in_parts_equal_one_job(tmp_path):
    """The 100-polygon block (``difftex synth --preset city-block``): filter in 4 chunks and
    visibility in 4 tiles give the same photos.json, summary.json and masks as one job each."""
    scene = tmp_path / "block"
    assert _cli("synth", "--preset", "city-block", "--out", str(scene)) == 0
    runs = {}
    for name, run in (("one", "{filter_photos_per_job: 100000, visibility_polygons_per_job: 100000}"),
                      ("parts", "{filter_photos_per_job: 30, visibility_polygons_per_job: 30}")):
        work = tmp_path / name
        work.mkdir()
        args = ["--cores", "2", "--config", f"scene={scene}", "preset=fast", f"run={run}",
                "--", str(Results(f"results/{scene.name}").visibility_summary)]
        r = _snakemake(work, *args)
        assert r.returncode == 0, r.stderr[-3000:]
        runs[name] = Results(work / "results" / scene.name)
    one, parts = runs["one"], runs["parts"]
    assert len(glob.glob(str(parts.filter_part("*-of-004")))) == 4
    assert len(glob.glob(str(parts.visibility_tile("*-of-004")))) == 4
    assert len(glob.glob(str(one.visibility_tile("*")))) == 1
    assert _table(parts.photos_json) == _table(one.photos_json)
    assert _table(parts.visibility_summary) == _table(one.visibility_summary)
    npz = sorted(p.name for p in one.visibility_dir.glob("*.npz"))
    assert len(npz) >= 100 and npz == sorted(p.name for p in parts.visibility_dir.glob("*.npz"))
    assert all(_npz_equal(one.visibility_dir / n, parts.visibility_dir / n) for n in npz)


def test_a_chunk_checks_its_own_photo_files_only(district, tmp_path, capsys):
    import shutil

    from difftex.scene.files import read_image, write_image

    scene = tmp_path / "scene"
    shutil.copytree(district, scene)
    names = [p.relative_to(scene / "images").as_posix() for p in image_files(scene / "images")]
    bad = scene / "images" / names[-1]  # in the last chunk
    write_image(bad, read_image(bad)[:-8])  # 8 rows short of its camera's size
    assert _cli("filter", "--quiet", "--scene", str(scene), "--part", "1/2", "--out", str(tmp_path / "p1.json")) == 0
    capsys.readouterr()
    assert _cli("filter", "--quiet", "--scene", str(scene), "--part", "2/2", "--out", str(tmp_path / "p2.json")) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(bad) in err[0] and "but camera" in err[0], err
    assert not (tmp_path / "p2.json").exists()


def test_finish_pairs_composites_with_folders(tmp_path, capsys):
    out = tmp_path / "done.json"
    assert _cli("finish", "--composite", "a.npz", "b.npz", "--out-dir", str(tmp_path / "a"), "--done", str(out)) != 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "2 --composite files but 1 --out-dir folders" in err[0]
    assert not out.exists()
