"""Dense geometry as an input (difftex.geometry.dense, the heights stage): each reader on a small
file, the bad-input lines, and the workflow with a scene's dense/ folder end to end."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from difftex.errors import DifftexError
from difftex.geometry.dense import (
    back_project,
    check_frame,
    classify,
    find_source,
    read_cloud,
    read_depth_maps,
    read_mesh,
)

COLMAP_VERTEX = ("x", "y", "z", "nx", "ny", "nz")


def write_colmap_ply(path: Path, xyz: np.ndarray) -> None:
    """A cloud in COLMAP's fused.ply layout: binary little endian x y z nx ny nz (float) red green blue (uchar)."""
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {len(xyz)}"]
    header += [f"property float {n}" for n in COLMAP_VERTEX] + [f"property uchar {c}" for c in ("red", "green", "blue")]
    header.append("end_header")
    fields = [*((n, "<f4") for n in COLMAP_VERTEX), *((c, "u1") for c in ("red", "green", "blue"))]
    rec = np.zeros(len(xyz), dtype=fields)
    rec["x"], rec["y"], rec["z"] = xyz.T
    rec["nz"] = 1.0
    rec["red"] = 200
    path.write_bytes(("\n".join(header) + "\n").encode() + rec.tobytes())


def test_colmap_fused_cloud_reads_and_classifies(tmp_path):
    xyz = np.random.default_rng(0).uniform(-1, 1, (500, 3))
    write_colmap_ply(tmp_path / "fused.ply", xyz)
    assert classify(tmp_path / "fused.ply").kind == "cloud"
    assert read_cloud(tmp_path / "fused.ply") == pytest.approx(xyz, abs=1e-6)
    found = find_source(tmp_path.parent / tmp_path.name, "auto") if (tmp_path / "dense").is_dir() else None
    assert found is None  # auto looks in <scene>/dense/ only
    (tmp_path / "dense").mkdir()
    shutil.move(tmp_path / "fused.ply", tmp_path / "dense" / "fused.ply")
    src = find_source(tmp_path, "auto")
    assert src.kind == "cloud" and src.path.name == "fused.ply"
    assert find_source(tmp_path, "none") is None
    assert find_source(tmp_path, "dense/fused.ply") == src


def test_ascii_cloud_and_meshes_in_ply_obj_glb(tmp_path):
    import trimesh

    box = trimesh.creation.box(extents=[1, 2, 3])
    box.export(tmp_path / "scene_dense_mesh.ply")
    box.export(tmp_path / "m.obj")
    box.export(tmp_path / "m.glb")
    for name in ("scene_dense_mesh.ply", "m.obj", "m.glb"):
        assert classify(tmp_path / name).kind == "mesh"
        mesh = read_mesh(tmp_path / name)
        assert len(mesh.faces) == 12 and np.ptp(mesh.vertices, axis=0) == pytest.approx([1, 2, 3])
    pts = trimesh.PointCloud(np.arange(30, dtype=float).reshape(10, 3))
    pts.export(tmp_path / "scene_dense.ply", encoding="ascii")
    assert classify(tmp_path / "scene_dense.ply").kind == "cloud"
    assert read_cloud(tmp_path / "scene_dense.ply") == pytest.approx(np.arange(30).reshape(10, 3))
    # a folder: the cloud before the mesh (the photos' own evidence, not a surface fitted to it)
    assert find_source(tmp_path, str(tmp_path)).kind == "cloud"


def test_colmap_depth_maps_back_project_to_the_surface(tmp_path, small_synth_scene):
    """A workspace with one depth map of a plane z = 0 seen from a camera: the points lie on it."""
    import pycolmap

    from difftex.scene.loading import load_scene

    ws = tmp_path / "ws"
    rec = pycolmap.Reconstruction(str(small_synth_scene / "sparse" / "0"))
    (ws / "sparse").mkdir(parents=True)
    rec.write_binary(str(ws / "sparse"))
    photo = load_scene(small_synth_scene, check_images=False).photos[0]
    h, w = photo.height // 2, photo.width // 2  # PatchMatch's max_image_size: a smaller map
    ys, xs = np.mgrid[0:h, 0:w]
    rays = photo.unproject(np.stack([(xs + 0.5) * 2, (ys + 0.5) * 2], -1))
    C = photo.center
    s = -C[2] / rays[..., 2]  # the ground plane z = 0
    X = C + s[..., None] * rays
    depth = (X @ photo.R.T + photo.t)[..., 2].astype(np.float32)
    depth[s <= 0] = 0
    (ws / "stereo" / "depth_maps").mkdir(parents=True)
    dm = pycolmap.DepthMap.from_array(depth, 0.0, float(depth.max()))
    dm.write(str(ws / "stereo" / "depth_maps" / f"{photo.name}.geometric.bin"))
    assert classify(ws).kind == "depth"
    pts = read_depth_maps(ws, stride=1)
    assert len(pts) == int((depth > 0).sum())
    assert np.abs(pts[:, 2]).max() < 1e-3 * np.abs(C).max()


def test_back_projection_inverts_projection():
    K = np.array([[100.0, 0, 40], [0, 100, 30], [0, 0, 1]])
    R, t = np.eye(3), np.array([0.0, 0, 5])
    depth = np.full((60, 80), 5.0)
    pts = back_project(depth, K, (80, 60), R, t)
    assert pts[:, 2] == pytest.approx(0.0) and len(pts) == 4800
    assert pts[:, 0].min() == pytest.approx((0.5 - 40) / 100 * 5)


def test_bad_inputs_are_one_line(tmp_path):
    (tmp_path / "fused.ply").write_text("not a ply\n")
    with pytest.raises(DifftexError, match="fused.ply: not a PLY file"):
        classify(tmp_path / "fused.ply")
    (tmp_path / "cut.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 9\n")
    with pytest.raises(DifftexError, match="cut.ply: PLY header without end_header"):
        read_cloud(tmp_path / "cut.ply")
    (tmp_path / "x.las").write_text("")
    with pytest.raises(DifftexError, match="x.las: not dense geometry"):
        classify(tmp_path / "x.las")
    with pytest.raises(DifftexError, match="nowhere.ply: dense geometry not found"):
        find_source(tmp_path, "nowhere.ply")
    far = np.random.default_rng(0).uniform(0, 1, (1000, 3)) + [500000.0, 6000000.0, 0]
    message = r"far.ply: not in the proxy's frame: the median distance .* is 6\.0\d*e\+06 .* spans 1\.7"
    with pytest.raises(DifftexError, match=message):
        check_frame(far, np.zeros(3), np.ones(3), Path("far.ply"))
    check_frame(far - [500000.0, 6000000.0, 0], np.zeros(3), np.ones(3), Path("near.ply"))


def _snakemake(work: Path, *args: str) -> subprocess.CompletedProcess:
    import os

    bin_dir = Path(sys.executable).parent
    env = dict(os.environ, PATH=f"{bin_dir}{os.pathsep}{os.environ.get('PATH', '')}")
    return subprocess.run([str(bin_dir / "snakemake"), "-s", str(Path(__file__).parents[1] / "Snakefile"),
                           "--directory", str(work), *args], capture_output=True, text=True, env=env, timeout=1800)


def _proxy_cloud(scene: Path, rng, depth: float = 0.0) -> np.ndarray:
    """Points on the proxy's polygons, 1 cm noise along their normals; a patch of each wall
    ``depth`` behind it (a recess)."""
    from difftex.scene.proxy import load_proxy

    pts = []
    for p in load_proxy(scene / "proxy.obj").polygons:
        o, b1, b2 = p.plane_basis()
        uv = p.to_plane(p.outer)
        (u0, v0), (u1, v1) = uv.min(0), uv.max(0)
        u, v = rng.uniform(u0, u1, 4000), rng.uniform(v0, v1, 4000)
        h = rng.normal(0, 0.01, 4000)
        if abs(p.normal[2]) < 0.5:  # a wall: its middle recessed
            mid = (np.abs(u - (u0 + u1) / 2) < 0.2 * (u1 - u0)) & (np.abs(v - (v0 + v1) / 2) < 0.2 * (v1 - v0))
            h = h - depth * mid
        pts.append(o + u[:, None] * b1 + v[:, None] * b2 + h[:, None] * p.normal)
    return np.concatenate(pts)


@pytest.mark.slow
def test_workflow_with_a_dense_cloud(small_synth_scene, tmp_path):
    """The scene's dense/fused.ply is found, a heights job per tile writes each polygon's field,
    the texturing maps through it (stats say so); a corrupt cloud stops the run with one line."""
    from difftex.compose.heights import read_heights
    from difftex.layout import Results
    from difftex.scene.files import read_json

    scene = tmp_path / "scene"
    shutil.copytree(small_synth_scene, scene)
    (scene / "dense").mkdir()
    write_colmap_ply(scene / "dense" / "fused.ply", _proxy_cloud(scene, np.random.default_rng(0), depth=0.3))
    work = tmp_path / "work"
    args = ("--cores", "2", "--config", f"scene={scene}", "preset=fast", "texture={long_side: 64}",
            "optimize={long_side_start: 32, max_iters_per_level: [10, 5]}", "evaluate={lpips: none}")
    r = _snakemake(work, *args)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    R = Results(work / "results" / "scene")
    walls = [p["id"] for p in read_json(R.visibility_summary)["polygons"] if p["id"].startswith("wall") and p["photos"]]
    assert walls
    for pid in walls:
        frame, heights, stats = read_heights(R.heights_dir / f"{pid}.npz", pid)
        assert stats["evidence_share"] > 0.5
        assert (heights < -0.2).mean() > 0.05  # the recess
        relief = read_json(R.stats(pid))["relief"]
        assert relief["source"] == "dense" and relief["relief_share"] > 0.05
    assert "Nothing to be done" in _snakemake(work, "-n", *args).stdout

    (scene / "dense" / "fused.ply").write_text("garbage\n")
    bad = _snakemake(work, *args)
    assert bad.returncode != 0
    out = bad.stdout + bad.stderr
    assert "fused.ply: not a PLY file" in out and "Traceback" not in out


def test_heights_command_warns_for_a_polygon_without_points_and_skips_a_skipped_stage(small_synth_scene, tmp_path):
    """`difftex heights` on the visibility summary: a polygon with no point near it keeps its
    plane with one warning line naming the file and the polygon; a GPU stage that was skipped
    (no CUDA) leaves every polygon its plane."""
    from difftex.compose.heights import read_heights
    from difftex.scene.files import read_json
    from difftex.scene.proxy import load_proxy

    scene = tmp_path / "scene"
    shutil.copytree(small_synth_scene, scene)
    cloud = _proxy_cloud(scene, np.random.default_rng(1), depth=0.3)
    wall = next(p for p in load_proxy(scene / "proxy.obj").polygons if abs(p.normal[2]) < 0.5)
    near = np.abs((cloud - wall.outer[0]) @ wall.normal) < 0.5  # only that wall's plane keeps its points
    (scene / "dense").mkdir()
    write_colmap_ply(scene / "dense" / "fused.ply", cloud[near])
    run = lambda *a: subprocess.run([sys.executable, "-m", "difftex", *map(str, a)], capture_output=True, text=True)  # noqa: E731
    assert run("filter", "--quiet", "--scene", scene, "--out", tmp_path / "photos.json").returncode == 0
    assert run("visibility", "--quiet", "--scene", scene, "--photos", tmp_path / "photos.json",
               "--out-dir", tmp_path / "vis").returncode == 0
    out = tmp_path / "heights"
    r = run("heights", "--scene", scene, "--rows", tmp_path / "vis" / "summary.json", "--visibility-dir",
            tmp_path / "vis", "--out-dir", out, "--done", out / "done.json")
    assert r.returncode == 0, r.stderr
    done = read_json(out / "done.json")
    assert done["kind"] == "cloud" and len(done["polygons"]) == len(list((tmp_path / "vis").glob("*.npz")))
    warned = [line for line in r.stderr.splitlines() if "no dense geometry near polygon" in line]
    assert warned and all(line.startswith("difftex: warning: ") and "fused.ply" in line for line in warned)
    assert f"'{wall.id}'" not in r.stderr
    _, h, st = read_heights(out / f"{wall.id}.npz", wall.id)
    assert st["evidence_share"] > 0.1 and (h < -0.2).any()  # 4000 points over up to 512 x 512 texels

    skipped = tmp_path / "stereo"
    skipped.mkdir()
    (skipped / "dense.json").write_text('{"status": "skipped"}')
    r = run("heights", "--scene", scene, "--rows", tmp_path / "vis" / "summary.json", "--visibility-dir",
            tmp_path / "vis", "--source", skipped, "--out-dir", tmp_path / "h2", "--done", tmp_path / "h2.json")
    assert r.returncode == 0 and "the dense stage was skipped" in r.stdout
    assert read_json(tmp_path / "h2.json")["polygons"] == []
