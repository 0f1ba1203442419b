"""The per-polygon stages as separate jobs (run.split): initialize -> histmatch -> optimize ->
compose.

Checked: the files they hand on round-trip; a photo is decoded once per polygon (in the
initialization; the histogram matching and the optimization decode none); the split workflow
writes the same textures as the one-job ``texture`` stage; a change of an optimization key reruns
the optimization and what follows but not the histogram matching or the initialization, a change
of a histogram-matching key reruns the histogram matching and what follows, a change of what
fixes the crops reruns the initialization; a deleted file of a polygon is made again.
"""

from __future__ import annotations

import glob
import json
from pathlib import Path

import numpy as np
import pytest
from test_workflow import job_counts, snakemake

from difftex.compose.stage_files import (
    Brightness,
    OptimizedPolygon,
    compose_polygon,
    read_histmatch,
    read_init,
    read_optimized,
    write_composed,
    write_histmatch,
    write_init,
    write_optimized,
)
from difftex.errors import DifftexError
from difftex.geometry.frames import UVFrame
from difftex.layout import Results
from difftex.sampling.photos import PhotoCrop
from difftex.workflow import jobs


def test_split_auto_splits_for_a_gpu_or_a_cluster_only():
    assert jobs.split_stages("auto", 0, local=True) is False
    assert jobs.split_stages("auto", 1, local=True) is True
    assert jobs.split_stages("auto", 0, local=False) is True
    assert jobs.split_stages(True, 0, local=True) is True
    assert jobs.split_stages(False, 2, local=False) is False


def test_a_cluster_run_is_known_from_its_command_line():
    profile = Path(__file__).resolve().parents[1] / "workflow" / "profiles" / "slurm"
    assert jobs.cli_executor(["--executor", "slurm", "--jobs", "2"]) == "slurm"
    assert jobs.cli_executor(["--profile", str(profile), "--config", "scene=x"]) == "slurm"
    assert jobs.cli_executor(["--cores", "2"]) is None
    assert jobs.cli_executor(["-n", "--executor", "dryrun"]) is None
    assert jobs.cli_executor(["-q", "tests/", "--no-such-flag"]) is None  # not snakemake's: local


def test_crops_file_round_trips_and_refuses_another_polygons(tmp_path):
    rng = np.random.default_rng(0)
    crops = {
        0: PhotoCrop(rng.integers(0, 255, (5, 7, 3), dtype=np.uint8), 8, 16, 3),
        2: PhotoCrop(rng.integers(0, 65535, (1, 1, 3), dtype=np.uint16), 0, 0, 0),
    }
    path = tmp_path / "crops.npz"
    write_init(path, "wall", ["a.jpg", "b.jpg", "c.jpg"], crops, {"photo_reads": 2, "time_read_photos_s": 0.5})
    back, stats = read_init(path, "wall", ["a.jpg", "b.jpg", "c.jpg"])
    assert stats == {"photo_reads": 2, "time_read_photos_s": 0.5}
    assert set(back) == {0, 2}
    for n, c in crops.items():
        assert back[n].pixels.dtype == c.pixels.dtype and np.array_equal(back[n].pixels, c.pixels)
        assert (back[n].x0, back[n].y0, back[n].base) == (c.x0, c.y0, c.base)
    with pytest.raises(DifftexError, match="rerun the initialization"):
        read_init(path, "roof", ["a.jpg", "b.jpg", "c.jpg"])
    with pytest.raises(DifftexError, match="rerun the initialization"):
        read_init(path, "wall", ["a.jpg", "c.jpg"])
    path.write_bytes(b"not a zip")
    with pytest.raises(DifftexError, match="crops.npz"):
        read_init(path, "wall", ["a.jpg"])


@pytest.mark.parametrize("matched, relief", [(True, True), (True, False), (False, False)])
def test_histmatch_file_round_trips_and_refuses_another_polygons(tmp_path, matched, relief):
    from difftex.sampling.colour import identity_transfer
    from difftex.sampling.relief import Relief

    rng = np.random.default_rng(2)
    frame = UVFrame(origin=np.array([0.1, 0.2, 0.3]), e_u=np.array([1.0, 0, 0]), e_v=np.array([0, -1.0, 0]),
                    normal=np.array([0, 0, 1.0]), texel_size=0.1 / 3, width=5, height=4)
    transfers = [identity_transfer() * 0.9, None, rng.random((3, 2, identity_transfer().shape[-1])).astype(np.float32)]
    b = Brightness(
        transfers if matched else None, "b.jpg" if matched else None,
        Relief(frame, rng.random((4, 5)).astype(np.float32), rng.random((3, 4, 5)) > 0.5) if relief else None,
        {"photos": ["a.jpg"], "range": [np.float32(-0.5), 0.5], "time_s": 1.5} if relief else None, 0.25,
    )
    path = tmp_path / "transfers.npz"
    write_histmatch(path, "wall", ["a.jpg", "b.jpg", "c.jpg"], b)
    back = read_histmatch(path, "wall", ["a.jpg", "b.jpg", "c.jpg"])
    assert back.reference == b.reference and back.time_s == 0.25 and back.mapped is None
    if matched:  # the same bits (the optimization's colours go through them)
        assert back.transfers is not None and back.transfers[1] is None
        for t, u in zip(transfers, back.transfers):
            assert (t is None) == (u is None) and (t is None or (u.dtype == t.dtype and np.array_equal(t, u)))
    else:
        assert back.transfers is None
    if relief:
        assert back.relief is not None and b.relief is not None
        assert back.relief.frame.to_dict() == frame.to_dict()
        assert np.array_equal(back.relief.heights, b.relief.heights)
        assert np.array_equal(back.relief.hidden, b.relief.hidden)
        assert back.relief_stats == {"photos": ["a.jpg"], "range": [-0.5, 0.5], "time_s": 1.5}
    else:
        assert back.relief is None and back.relief_stats is None
    with pytest.raises(DifftexError, match="rerun the histogram matching"):
        read_histmatch(path, "roof", ["a.jpg", "b.jpg", "c.jpg"])
    path.write_bytes(b"not a zip")
    with pytest.raises(DifftexError, match="transfers.npz"):
        read_histmatch(path, "wall", ["a.jpg"])


def _optimized(rng, heights: bool) -> OptimizedPolygon:
    H, W, K = 6, 9, 2
    mask = np.ones((H, W), bool)
    mask[0, 0] = False
    wsum = rng.random((H, W)).astype(np.float32)
    wsum[2:4, 3:6] = 0  # unseen texels to fill
    return OptimizedPolygon(
        polygon_id="wall",
        names=["a.jpg", "b.jpg"],
        mask=mask,
        frame=UVFrame(origin=np.zeros(3), e_u=np.array([1.0, 0, 0]), e_v=np.array([0, -1.0, 0]),
                      normal=np.array([0, 0, 1.0]), texel_size=0.1, width=W, height=H),
        U=rng.random((H, W, 3)).astype(np.float32) * (wsum > 0)[..., None],
        weight_sum=wsum,
        dominant=rng.integers(-1, 2, (H, W)),
        stats={"levels": [{"long_side": 9, "time_s": 0.1}], "photo_reads": 2},
        histmatch=True,
        heights=rng.random((H, W)).astype(np.float32) if heights else None,
        idx=rng.integers(0, 2, (K, H, W)),
        W=rng.random((K, H, W)).astype(np.float32),
        transfers=None,
    )


@pytest.mark.parametrize("heights", [False, True])
def test_optimized_files_round_trip_to_the_same_composite(tmp_path, heights):
    opt = _optimized(np.random.default_rng(1), heights)
    write_optimized(tmp_path, opt)
    back = read_optimized(tmp_path)
    for key in ("U", "weight_sum", "dominant", "mask"):
        assert np.array_equal(getattr(back, key), getattr(opt, key)), key
    assert back.names == opt.names and back.stats == opt.stats and back.histmatch
    assert back.frame.to_dict() == opt.frame.to_dict()
    assert (back.heights is None) == (not heights)
    write_composed(tmp_path / "a.npz", opt)
    write_composed(tmp_path / "b.npz", back)
    a, b = np.load(tmp_path / "a.npz"), np.load(tmp_path / "b.npz")
    assert a.files == b.files and all(np.array_equal(a[k], b[k]) for k in a.files)
    U, seen, report = compose_polygon(back)
    assert report["filled_texels"] == 6 and not seen[2:4, 3:6].any() and np.isfinite(U).all()


# ---------------------------------------------------------------------------------------------
# The workflow on the tiny synthetic scene

SMALL = (
    "preset=fast",
    "texture={long_side: 128}",
    "optimize={long_side_start: 64, max_iters_per_level: [15, 8]}",
)


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    from difftex.synth import generate

    scene = tmp_path_factory.mktemp("synth") / "tiny"
    generate("tiny", scene, progress=False)
    out = {"scene": scene}
    for split in ("true", "false"):
        work = tmp_path_factory.mktemp(f"split_{split}")
        args = ("--cores", "2", "--config", f"scene={scene}", *SMALL, f"run={{evaluate: false, split: {split}}}")
        r = snakemake(work, *args)
        assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
        out[split] = (work / "results" / "tiny", args, work)
    return out


def _without_times(report: dict) -> dict:
    if isinstance(report, dict):
        return {k: _without_times(v) for k, v in report.items() if not k.startswith("time_")}
    if isinstance(report, list):
        return [_without_times(v) for v in report]
    return report


@pytest.mark.slow
def test_split_stages_write_the_one_jobs_textures(runs):
    R_split, R_one = runs["true"][0], runs["false"][0]
    composites = sorted(R_one.glob("optimized/*/composite.npz"))
    assert composites and len(composites) == len(list(R_split.glob("optimized/*/composite.npz")))
    for path in composites:
        a, b = np.load(path), np.load(R_split / path.relative_to(R_one))
        assert a.files == b.files
        for k in a.files:
            if k == "report":  # equal but for the stages' timings
                assert _without_times(json.loads(str(a[k]))) == _without_times(json.loads(str(b[k])))
            else:
                assert np.array_equal(a[k], b[k]), (path, k)
        pid = path.parent.name
        assert Results(R_one).texture(pid).read_bytes() == Results(R_split).texture(pid).read_bytes()
    # the split run's stages each left their jobs and logs; the one-job run has no crops
    assert glob.glob(str(Results(R_split).crops("*"))) and not Results(R_one).init_dir.exists()
    for stage in ("initialize", "histmatch", "optimize", "compose"):
        assert glob.glob(str(Results(R_split).log(stage, "*"))), stage
    assert glob.glob(str(Results(R_split).transfers("*"))) and not Results(R_one).histmatch_dir.exists()


@pytest.mark.slow
def test_an_optimization_change_reruns_optimize_not_initialize(runs):
    R, args, work = runs["true"]
    n_jobs = len(glob.glob(str(Results(R).job_file("initialize", "*"))))
    assert n_jobs >= 1
    rules = snakemake(work, "--list-rules", *args[2:]).stdout.split()
    assert {"filter", "visibility", "initialize", "histmatch", "optimize", "compose", "finish", "assemble",
            "evaluate"} <= set(rules)
    counts = job_counts(snakemake(work, "-n", *args, "optimize={lr: 0.01}").stdout)
    assert counts.get("optimize") == counts.get("compose") == counts.get("finish") == n_jobs, counts
    assert not {"initialize", "histmatch", "texture", "visibility"} & set(counts), counts
    # ... while what fixes the photos' crops reruns the initialization too
    counts = job_counts(snakemake(work, "-n", *args, "optimize={supersample: 1}").stdout)
    assert counts.get("initialize") == counts.get("optimize") == n_jobs, counts
    # and nothing is left to do
    again = snakemake(work, "-n", *args)
    assert "Nothing to be done" in again.stdout, again.stdout[-2000:]


# the rules of the split stages and what follows them; the scene stages before them
SPLIT_AFTER_HISTMATCH = ("histmatch", "optimize", "compose", "finish", "assemble")
SCENE_STAGES = ("filter_part", "filter", "visibility_tile", "visibility", "initialize")


@pytest.mark.slow
@pytest.mark.parametrize("change", ["{histmatch_model: quantile}", "{histmatch_reference: best}",
                                    "{histogram_matching: false}"])
def test_a_histogram_matching_change_reruns_histmatch_and_what_follows_only(runs, change):
    R, args, work = runs["true"]
    n_jobs = len(glob.glob(str(Results(R).job_file("histmatch", "*"))))
    assert n_jobs >= 1
    small = args[:-2] + (args[-2][:-1] + ", " + change[1:], args[-1])  # the test's optimize section plus the change
    dry = snakemake(work, "-n", *small)
    counts = job_counts(dry.stdout)
    assert all(counts.get(rule) == n_jobs for rule in SPLIT_AFTER_HISTMATCH[:-1]), (counts, dry.stdout[-2000:])
    assert counts.get("assemble") == 1, counts
    assert not set(SCENE_STAGES) & set(counts), counts


@pytest.mark.slow
def test_a_photo_is_decoded_once_per_polygon_and_the_optimization_decodes_none(runs, monkeypatch, tmp_path):
    import difftex.sampling.photos as photos_mod
    import difftex.scene.files as files_mod
    from difftex.compose.stage_files import initialize_polygon
    from difftex.compose.texturing import match_brightness, optimize_photos, texture_polygon
    from difftex.config import section
    from difftex.geometry.visibility import load_visibility
    from difftex.method.config import ComputeConfig, OptimizeConfig
    from difftex.sampling.photos import PhotoSet, polygon_input_from_visibility
    from difftex.scene.loading import load_scene

    R = runs["true"][0]
    cfg = section(str(sorted((R / "config").glob("texture-*.yaml"))[0]), "optimize", OptimizeConfig)
    scene = load_scene(runs["scene"], check_images=False)
    photos = {p.name: p for p in scene.photos}
    vis = sorted((R / "visibility").glob("*.npz"), key=lambda p: -p.stat().st_size)[0]
    inp = polygon_input_from_visibility(load_visibility(vis), photos)
    calls: list[str] = []

    def counting(path, *a, **kw):
        calls.append(str(path))
        return files_mod.decode_photo(path, *a, **kw)

    crops, stats = initialize_polygon(inp, cfg, counting)
    assert len(crops) >= 2 and len(calls) == len(crops) == stats["photo_reads"]
    assert len(set(calls)) == len(calls)  # each photo once

    def refuse(*a, **kw):
        raise AssertionError("the optimization decoded a photo")

    reference = texture_polygon(inp, cfg, ComputeConfig(device="cpu"))
    monkeypatch.setattr(files_mod, "decode_photo", refuse)
    monkeypatch.setattr(photos_mod, "decode_photo", refuse)
    ps = PhotoSet.from_crops(inp, crops, "cpu", cfg.supersample)
    opt = optimize_photos(ps, cfg, ComputeConfig(device="cpu"), read_stats=stats)
    assert opt.stats["photo_reads"] == len(crops)
    assert np.array_equal(compose_polygon(opt)[0], reference.texture)
    assert np.array_equal(opt.W, reference.W) and np.array_equal(opt.idx, reference.idx)
    # split as the workflow splits it: the transfers in their own stage, handed on in their file
    names = [p.name for p in inp.photos]
    write_histmatch(tmp_path / "transfers.npz", inp.polygon_id, names,
                    match_brightness(PhotoSet.from_crops(inp, crops, "cpu", cfg.supersample), cfg))
    brightness = read_histmatch(tmp_path / "transfers.npz", inp.polygon_id, names)
    split = optimize_photos(PhotoSet.from_crops(inp, crops, "cpu", cfg.supersample), cfg, ComputeConfig(device="cpu"),
                            read_stats=stats, brightness=brightness)
    assert np.array_equal(compose_polygon(split)[0], reference.texture) and np.array_equal(split.W, reference.W)
    # the file written by the workflow's initialize holds the same crops
    on_disk, _ = read_init(Results(R).crops(inp.polygon_id), inp.polygon_id, [p.name for p in inp.photos])
    assert set(on_disk) == set(crops) and all(np.array_equal(on_disk[n].pixels, crops[n].pixels) for n in crops)



@pytest.mark.slow
def test_the_initialize_command_imports_no_torch(runs, tmp_path):
    import subprocess
    import sys

    R = runs["true"][0]
    vis = sorted((R / "visibility").glob("*.npz"))[0]
    config = sorted((R / "config").glob("initialize-*.yaml"))[0]
    code = (
        "import sys\n"
        "from difftex.cli import main\n"
        f"rc = main(['initialize', '--threads', '1', '--scene', {str(runs['scene'])!r}, '--visibility', {str(vis)!r}, "
        f"'--out', {str(tmp_path / 'crops.npz')!r}, '--config', {str(config)!r}])\n"
        "assert rc == 0\n"
        "assert 'torch' not in sys.modules, 'torch imported'\n"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert r.returncode == 0, r.stdout + r.stderr
    crops, stats = read_init(tmp_path / "crops.npz", vis.stem, [str(x) for x in np.load(vis)["photos"]])
    assert crops and stats["photo_reads"] == len(crops)


@pytest.mark.slow
def test_a_deleted_file_of_a_split_stage_is_made_again(runs):
    # last in this module: it deletes and remakes files of the split run (the same bytes)
    R, args, work = runs["true"]
    res = Results(R)
    pid = sorted(p.parent.name for p in res.histmatch_dir.glob("*/transfers.npz"))[0]
    texture, transfers = res.texture(pid).read_bytes(), np.load(res.transfers(pid))["transfers"]
    res.transfers(pid).unlink()
    res.texture(pid).unlink()
    r = snakemake(work, *args)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    counts = job_counts(r.stdout + r.stderr)
    assert counts.get("histmatch") == counts.get("optimize") == 1 and "initialize" not in counts, counts
    assert np.array_equal(np.load(res.transfers(pid))["transfers"], transfers)
    assert res.texture(pid).read_bytes() == texture
    assert "Nothing to be done" in snakemake(work, "-n", *args).stdout
