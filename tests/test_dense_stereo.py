"""The dense stage (difftex.scene.mvs, ``difftex dense``, rule dense_stereo): its config keys, the
skip without CUDA (CLI and workflow), and the workspace on a real scene with the undistortion run
on the CPU and PatchMatch (CUDA only) replaced by a stand-in that writes depth maps."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from difftex.errors import DifftexError
from difftex.scene import mvs

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # evaluation/bench_dense_stereo.py
LUND = Path(os.environ.get("DIFFTEX_SHARED", REPO.parent / "shared")) / "data" / "lund-door"
BIN = Path(sys.executable).parent
SKIP_LINE = "difftex: warning: dense: skipped, pycolmap has no CUDA (install pycolmap-cuda12 on a GPU machine)"

needs_lund = pytest.mark.skipif(not LUND.is_dir(), reason=f"{LUND} missing")


def _registered(sparse: Path) -> list:
    import pycolmap

    rec = pycolmap.Reconstruction(str(sparse))
    return sorted((im for im in rec.images.values() if im.has_pose), key=lambda im: im.name), rec


class FakePatchMatch:
    """Stands in for pycolmap.patch_match_stereo: a constant geometric depth map per photo of the
    workspace's model, at its undistorted size; ``fail_after`` maps, then an interruption."""

    def __init__(self, depth: float = 5.0, fail_after: int | None = None):
        self.depth, self.fail_after, self.calls = depth, fail_after, []

    def __call__(self, workspace: Path, options) -> None:
        import pycolmap

        self.calls.append((Path(workspace), options))
        images, rec = _registered(Path(workspace) / "sparse")
        for i, im in enumerate(images):
            if self.fail_after is not None and i == self.fail_after:
                raise KeyboardInterrupt
            cam = rec.cameras[im.camera_id]
            depth = np.full((cam.height, cam.width), self.depth, np.float32)
            depth[: cam.height // 4] = 0  # a quarter without a depth
            path = Path(workspace) / mvs.DEPTH_DIR / f"{im.name}.geometric.bin"
            pycolmap.DepthMap.from_array(depth, 0.1, 100.0).write(str(path))


def _difftex(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "difftex", *args], capture_output=True, text=True, timeout=300)


def _snakemake(work: Path, *args: str) -> subprocess.CompletedProcess:
    env = dict(os.environ, PATH=f"{BIN}{os.pathsep}{os.environ.get('PATH', '')}")
    return subprocess.run([str(BIN / "snakemake"), "-s", str(REPO / "Snakefile"), "--directory", str(work), *args],
                          capture_output=True, text=True, timeout=900, env=env)


def _job_counts(out: str) -> dict[str, int]:
    import re

    m = re.search(r"Job stats:\n.*?\n-+\s+-+\n(.*?)\ntotal", out, re.S)
    return {ln.split()[0]: int(ln.split()[1]) for ln in m.group(1).splitlines() if ln.strip()} if m else {}


# ---------------------------------------------------------------------------------------------
# Configuration


def test_the_dense_section_gives_each_stage_its_keys(tmp_path):
    """The stereo keys of config.yaml's dense section make the default DenseStereoConfig; the
    heights stage reads the same section without tripping on them; a typo or a bad value is one
    line naming it; the workflow's stage file holds the stereo keys only."""
    from difftex.cli.dense import stereo_config
    from difftex.cli.heights import dense_config
    from difftex.workflow import glue as wf

    default = REPO / "config" / "config.yaml"
    assert stereo_config(default) == mvs.DenseStereoConfig()
    assert mvs.DenseStereoConfig().geom_consistency and mvs.DenseStereoConfig().photos == "visible"
    dense_config(default)  # the height-field keys' reader ignores the stereo keys
    for bad, word in (("photoss: all", "photoss"), ("max_image_size: 10", "max_image_size"),
                      ("photos: some", "photos"), ("window_radius: 40", "window_radius")):
        path = tmp_path / "c.yaml"
        path.write_text(f"dense:\n  {bad}\n")
        with pytest.raises(DifftexError, match=word) as err:
            stereo_config(path)
        assert "\n" not in str(err.value)
    cfg = wf.resolve_config(REPO, {"dense": {"stereo": True, "num_iterations": 3}})
    wf.validate(cfg, REPO / "workflow/schemas/config.schema.yaml")
    import yaml

    text = yaml.safe_load(wf.stage_config_text(cfg, "dense"))
    assert text == {"dense": {"max_image_size": 2000, "photos": "visible", "num_iterations": 3}}
    path = tmp_path / "stage.yaml"
    path.write_text(wf.stage_config_text(cfg, "dense"))
    assert stereo_config(path).num_iterations == 3


def test_photo_lists_and_their_checks(tmp_path):
    table = {"photos": [{"name": "a.jpg", "kept": True}, {"name": "b.jpg", "kept": False},
                        {"name": "c.jpg", "kept": True}]}
    (tmp_path / "photos.json").write_text(json.dumps(table))
    assert mvs.read_photo_list(tmp_path / "photos.json") == ["a.jpg", "c.jpg"]
    (tmp_path / "list.txt").write_text("# photos\na.jpg\n\nc.jpg\n")
    assert mvs.read_photo_list(tmp_path / "list.txt") == ["a.jpg", "c.jpg"]
    (tmp_path / "other.json").write_text("{}")
    with pytest.raises(DifftexError, match="not a table of the difftex filter stage"):
        mvs.read_photo_list(tmp_path / "other.json")
    with pytest.raises(DifftexError, match="photo list not found"):
        mvs.read_photo_list(tmp_path / "none.txt")


@needs_lund
def test_photos_must_be_registered_and_two_at_least():
    from difftex.scene.camera import read_reconstruction

    rec = read_reconstruction(LUND / "sparse" / "0")
    assert len(mvs.chosen_photos(rec, None, LUND)) == 12
    with pytest.raises(DifftexError, match=r"1 photo\(s\) to match are not registered in the model \(nope.jpg\)"):
        mvs.chosen_photos(rec, ["DSC_0001.JPG", "nope.jpg"], LUND)
    with pytest.raises(DifftexError, match="at least 2 photos"):
        mvs.chosen_photos(rec, ["DSC_0001.JPG"], LUND)


# ---------------------------------------------------------------------------------------------
# Without CUDA


@needs_lund
@pytest.mark.skipif(mvs.cuda_available(), reason="this pycolmap has CUDA: nothing is skipped")
def test_the_command_without_cuda_skips_in_one_line(tmp_path):
    """One warning line, status 0, no traceback; the workspace folder (an older one replaced)
    holds only the record saying why, and --done gets the same record."""
    out = tmp_path / "R" / "dense"
    (out / "stereo").mkdir(parents=True)
    (out / "stereo" / "old.bin").write_bytes(b"old")
    r = _difftex("dense", "--scene", str(LUND), "--out", str(out), "--config", str(REPO / "config" / "config.yaml"),
                 "--done", str(tmp_path / "done.json"))
    assert r.returncode == 0, r.stderr
    assert (r.stdout + r.stderr).strip().splitlines() == [SKIP_LINE]
    assert sorted(p.name for p in out.iterdir()) == ["dense.json"]
    record = json.loads((out / "dense.json").read_text())
    assert record["status"] == "skipped" and "pycolmap-cuda12" in record["reason"]
    assert json.loads((tmp_path / "done.json").read_text()) == record
    assert mvs.workspace_status(out) == "skipped"
    assert not mvs.partial_dir(out).exists() and not (out.parent / ".dense.old").exists()

    bad = _difftex("dense", "--scene", str(tmp_path / "nowhere"), "--out", str(out))
    assert bad.returncode == 2 and "Traceback" not in bad.stderr
    assert bad.stderr.strip().splitlines() == [f"difftex: error: {tmp_path / 'nowhere'}: no COLMAP model in sparse/0 "
                                               "(cameras.bin/.txt)"]


@pytest.mark.slow
@needs_lund
@pytest.mark.skipif(mvs.cuda_available(), reason="this pycolmap has CUDA: nothing is skipped")
def test_the_rule_without_cuda_is_skipped_cleanly(tmp_path):
    """dense.stereo on a CPU machine: the dense_stereo job succeeds with its one warning, shown
    again at the end of the run, and leaves the skipped record; nothing is left to do."""
    work = tmp_path / "work"
    args = ("--config", f"scene={LUND}", "dense={stereo: true, photos: all}")
    target = str(Path("results") / "lund-door" / "dense" / "dense.json")
    r = _snakemake(work, "--cores", "1", *args, "--", target)
    out = r.stdout + r.stderr
    assert r.returncode == 0, out[-3000:]
    assert "Traceback" not in out and out.count(SKIP_LINE) >= 1
    log = (work / "results" / "lund-door" / "logs" / "dense_stereo.log").read_text()
    assert log.strip().splitlines() == [SKIP_LINE]
    assert mvs.workspace_status(work / "results" / "lund-door" / "dense") == "skipped"
    assert "Nothing to be done" in _snakemake(work, "-n", *args, "--", target).stdout


# ---------------------------------------------------------------------------------------------
# The workflow


@needs_lund
def test_a_dry_run_shows_the_rule_only_with_dense_stereo(tmp_path):
    """With dense.stereo the rule is planned (after the filter, whose kept photos it matches) and
    lints clean; without it, or with dense.source: none, it is not."""
    base = ("-n", "--config", f"scene={LUND}", "preset=fast")
    on = _snakemake(tmp_path, *base, "dense={stereo: true}", "-p")
    assert on.returncode == 0, on.stderr[-2000:]
    counts = _job_counts(on.stdout)
    assert counts.get("dense_stereo") == 1 and counts.get("filter") == 1
    assert "results/lund-door/dense/dense.json" in on.stdout
    assert "--photos 'results/lund-door/photos.json'" in on.stdout
    lint = _snakemake(tmp_path, "--lint", "--config", f"scene={LUND}", "dense={stereo: true}")
    assert lint.returncode == 0 and "dense_stereo" not in lint.stdout + lint.stderr, lint.stdout
    for off in ((), ("dense={stereo: true, source: none}",)):
        r = _snakemake(tmp_path, *base, *off)
        assert r.returncode == 0 and "dense_stereo" not in _job_counts(r.stdout), r.stderr[-2000:]


# ---------------------------------------------------------------------------------------------
# The workspace, PatchMatch replaced


@needs_lund
def test_the_workspace_of_a_real_scene(tmp_path, monkeypatch):
    """Four photos of lund-door (SIMPLE_RADIAL, 1296 x 1936) undistorted on the CPU into a
    workspace of pinhole cameras at max_image_size: only those photos in images/, sparse/ and
    patch-match.cfg; PatchMatch runs in the partial folder with the config's options, and its
    depth maps land in out_dir/stereo/depth_maps/, with the record."""
    fake = FakePatchMatch()
    monkeypatch.setattr(mvs, "patch_match", fake)
    names = ["DSC_0001.JPG", "DSC_0002.JPG", "DSC_0003.JPG", "DSC_0004.JPG"]
    out = tmp_path / "dense"
    cfg = mvs.DenseStereoConfig(max_image_size=320, num_iterations=3)
    record = mvs.run_dense_stereo(LUND, out, names, cfg)

    (workspace, options), = fake.calls
    assert workspace == mvs.partial_dir(out) / "workspace"  # not out_dir: renamed there when complete
    assert (options.max_image_size, options.num_iterations, options.geom_consistency) == (320, 3, True)
    assert options.cache_size == mvs.CACHE_GB and options.gpu_index == "-1"
    assert not mvs.partial_dir(out).exists()
    assert sorted(p.name for p in (out / "images").iterdir()) == names
    images, rec = _registered(out / "sparse")
    assert [im.name for im in images] == names
    for im in images:
        cam = rec.cameras[im.camera_id]
        assert cam.model_name == "PINHOLE" and max(cam.width, cam.height) == 320
        from difftex.scene.files import image_size

        assert image_size(out / "images" / im.name) == (cam.width, cam.height)
        # the model's 2D points are the undistorted ones: its points reproject onto them
        pts = [(p2.xy, rec.points3D[p2.point3D_id].xyz) for p2 in im.points2D if p2.has_point3D()][:200]
        xy = np.array([cam.img_from_cam(im.cam_from_world() * X) for _, X in pts])
        assert np.median(np.linalg.norm(xy - np.array([p for p, _ in pts]), axis=1)) < 0.5
    cfg_lines = (out / "stereo" / "patch-match.cfg").read_text().split()
    assert [n for n in cfg_lines if n.endswith(".JPG")] == names
    maps = sorted(p.name for p in (out / mvs.DEPTH_DIR).iterdir())
    assert maps == [f"{n}.geometric.bin" for n in names]
    assert record == json.loads((out / "dense.json").read_text()) and mvs.workspace_status(out) == "done"
    assert [r["name"] for r in record["photos"]] == names
    for row in record["photos"]:
        assert row["kind"] == "geometric" and row["valid_share"] == pytest.approx(0.75, abs=0.01)
        assert row["median_depth"] == pytest.approx(5.0)
    assert record["config"]["max_image_size"] == 320 and set(record["seconds"]) == {"undistort", "patch_match", "total"}

    # what the heights stage reads of it (difftex.geometry.dense): points at depth 5 before each camera
    from difftex.geometry.dense import read_depth_maps

    pts = read_depth_maps(out, stride=8)
    assert len(pts) > 1000 and np.isfinite(pts).all()
    z = [pts @ im.cam_from_world().rotation.matrix()[2] + im.cam_from_world().translation[2] for im in images]
    assert np.abs(np.stack(z) - 5.0).min(axis=0).max() < 1e-3


@needs_lund
def test_an_interrupted_run_keeps_the_old_workspace_and_restarts(tmp_path, monkeypatch):
    """Killed during PatchMatch: out_dir is still the previous workspace, whole; the next run
    starts the partial folder again and replaces out_dir with the new one."""
    names = ["DSC_0005.JPG", "DSC_0006.JPG", "DSC_0007.JPG"]
    out = tmp_path / "dense"
    cfg = mvs.DenseStereoConfig(max_image_size=160)
    monkeypatch.setattr(mvs, "patch_match", FakePatchMatch(depth=5.0))
    first = mvs.run_dense_stereo(LUND, out, names, cfg)
    monkeypatch.setattr(mvs, "patch_match", FakePatchMatch(depth=7.0, fail_after=1))
    with pytest.raises(KeyboardInterrupt):
        mvs.run_dense_stereo(LUND, out, names[:2], cfg)
    assert json.loads((out / "dense.json").read_text()) == first
    assert len(list((out / mvs.DEPTH_DIR).iterdir())) == 3
    assert (mvs.partial_dir(out) / "workspace" / mvs.DEPTH_DIR / f"{names[0]}.geometric.bin").is_file()
    (mvs.partial_dir(out) / "stale.txt").write_text("left by the killed run")

    monkeypatch.setattr(mvs, "patch_match", FakePatchMatch(depth=7.0))
    again = mvs.run_dense_stereo(LUND, out, names[:2], cfg)
    assert [r["median_depth"] for r in again["photos"]] == [7.0, 7.0]
    assert sorted(p.name for p in (out / "images").iterdir()) == names[:2]
    assert not mvs.partial_dir(out).exists() and not (tmp_path / ".dense.old").exists()


@needs_lund
def test_no_depth_map_at_all_is_one_line(tmp_path, monkeypatch):
    monkeypatch.setattr(mvs, "patch_match", lambda workspace, options: None)
    with pytest.raises(DifftexError, match="PatchMatch wrote no depth map"):
        mvs.run_dense_stereo(LUND, tmp_path / "dense", ["DSC_0001.JPG", "DSC_0002.JPG"],
                             mvs.DenseStereoConfig(max_image_size=128))
    assert not (tmp_path / "dense").exists()


# ---------------------------------------------------------------------------------------------
# The GPU check's scoring (evaluation/bench_dense_stereo.py), on the CPU


@pytest.mark.slow
def test_the_bench_scores_depth_maps_against_the_synthetic_truth(tmp_path, monkeypatch):
    """On a small synthetic scene with radial distortion (its undistortion is not the identity):
    the true depth maps the bench makes agree with the scene's own 3D points where the workspace
    model sees them; scored against themselves they are complete and exact, and 3 % too deep
    they are off by 3 %."""
    pytest.importorskip("mitsuba")
    import pycolmap

    from difftex.synth import generate
    from evaluation import bench_dense_stereo as bench

    scene = generate("tiny", tmp_path / "scene", progress=False, views=5, held_out_views=1, width=160, height=120,
                     spp=4, gt_spp=4, gt_long_side=64, distortion=-0.08, occluders=False, previews=False)
    truth = bench.synth_truth(scene)
    views = {v["name"]: v for v in truth["manifest"]["views"]}
    orig = pycolmap.Reconstruction(str(scene / "sparse" / "0"))
    assert any(c.model_name == "SIMPLE_RADIAL" for c in orig.cameras.values())
    agree = []

    def true_maps(workspace: Path, options) -> None:
        rec = pycolmap.Reconstruction(str(workspace / "sparse"))
        for im in rec.images.values():
            cam, oim = rec.cameras[im.camera_id], orig.find_image_with_name(im.name)
            true, on = bench.true_depth_map(truth, views[im.name], im, cam, orig.cameras[oim.camera_id],
                                            (cam.height, cam.width))
            pycolmap.DepthMap.from_array(true.astype(np.float32), 0.1, 100.0).write(
                str(workspace / mvs.DEPTH_DIR / f"{im.name}.geometric.bin"))
            for p2 in im.points2D:  # the scene's points are on the true surface
                if p2.has_point3D():
                    x, y = np.floor(p2.xy).astype(int)
                    z = (im.cam_from_world() * rec.points3D[p2.point3D_id].xyz)[2]
                    if 0 <= x < cam.width and 0 <= y < cam.height and on[y, x]:
                        agree.append(abs(true[y, x] - z) / z)

    monkeypatch.setattr(mvs, "patch_match", true_maps)
    ws = tmp_path / "ws"
    mvs.run_dense_stereo(scene, ws, None, mvs.DenseStereoConfig(max_image_size=128))
    assert len(agree) > 50 and np.median(agree) < 0.01

    out = tmp_path / "bench"
    assert bench.main(["--scene", str(scene), "--workspace", str(ws), "--out", str(out), "--max-views", "3"]) == 0
    exact = json.loads(out.with_suffix(".json").read_text())["score"]["all"]
    assert exact["building_pixels"] > 1000 and exact["completeness"] == pytest.approx(1.0)
    assert exact["median_abs_err"] < 1e-4 and exact["within_1pct"] == pytest.approx(1.0)
    assert "| **all** |" in out.with_suffix(".md").read_text()

    for f in (ws / mvs.DEPTH_DIR).glob("*.geometric.bin"):
        dm = pycolmap.DepthMap()
        dm.read(str(f))
        pycolmap.DepthMap.from_array(dm.to_array() * 1.03, 0.1, 100.0).write(str(f))
    assert bench.main(["--scene", str(scene), "--workspace", str(ws), "--out", str(out), "--max-views", "3"]) == 0
    deep = json.loads(out.with_suffix(".json").read_text())["score"]["all"]
    assert deep["median_rel_err"] == pytest.approx(0.03, abs=1e-4) and deep["within_1pct"] == 0
    assert deep["completeness"] == pytest.approx(1.0)


def test_the_bench_without_cuda_is_one_line(tmp_path):
    if mvs.cuda_available():
        pytest.skip("this pycolmap has CUDA")
    (tmp_path / "images").mkdir()
    r = subprocess.run([sys.executable, str(REPO / "evaluation" / "bench_dense_stereo.py"), "--scene", str(tmp_path)],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0 and (r.stdout + r.stderr).strip().splitlines() == [
        "bench_dense_stereo: skipped, pycolmap has no CUDA (install pycolmap-cuda12 on a GPU machine)"]
