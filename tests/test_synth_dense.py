"""The synthetic scenes' COLMAP-like dense reconstruction (difftex/synth/dense.py, `difftex synth-dense`).

The tiny preset's building is rebuilt without rendering and seen by three 160x120 photos: two
overlapping ones of the front wall (wall00, facing -y, with shop fronts) and one alone of the
back wall (wall01): the back wall is seen once, so it must not be reconstructed. Truth is
checked with numpy (point-triangle distances, pycolmap projection), not with the Mitsuba code
under test.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from difftex.synth import dense as D

SIGMA = 0.015
HEADER = (b"ply\nformat binary_little_endian 1.0\nelement vertex {n}\nproperty float x\nproperty float y\n"
          b"property float z\nproperty float nx\nproperty float ny\nproperty float nz\nproperty uchar red\n"
          b"property uchar green\nproperty uchar blue\nend_header\n")
W, H, F = 160, 120, 100.0
# name, centre, target: a1 and a2 overlap on the front wall, b alone sees the back wall
CAMERAS = [("a1", (-4, -14, 3), (-1, -4, 2.5)), ("a2", (4, -14, 3), (1, -4, 2.5)), ("b", (0, 14, 3), (0, 4, 2.5))]


def _poses():
    from difftex.geometry.frames import look_at

    out = []
    for name, C, T in CAMERAS:
        R = look_at(np.array(C, float), np.array(T, float))
        out.append((name, R, -R @ np.array(C, float)))
    return out


def _views():
    from difftex.synth.cameras import Intrinsics

    cam = Intrinsics(1, W, H, F, 0.0).pycolmap()
    return [D.View(name, R, t, cam) for name, R, t in _poses()]


@pytest.fixture(scope="module")
def src():
    from difftex.synth.presets import get_preset

    cfg = get_preset("tiny").replace(occluders=False)  # the truth below is the model's triangles and the ground
    return D.source_from_model(cfg, cfg.buildings[0], 0, 0, _views())


@pytest.fixture(scope="module")
def cloud(src):
    return D.fuse(src, D.DenseSettings(noise=SIGMA))


def _point_triangle_distance(P: np.ndarray, T: np.ndarray) -> np.ndarray:
    """Distance (N,) of points P (N, 3) to the nearest of triangles T (M, 3, 3) (Ericson's regions)."""
    best = np.full(len(P), np.inf)
    for a, b, c in T:
        ab, ac, ap = b - a, c - a, P - a
        n = np.cross(ab, ac)
        nn = n @ n
        if nn < 1e-18:
            continue
        # barycentrics of the projection; inside: distance to the plane
        v = (np.cross(ap, ac) @ n) / nn
        w = (np.cross(ab, ap) @ n) / nn
        inside = (v >= 0) & (w >= 0) & (v + w <= 1)
        d = np.where(inside, np.abs(ap @ n) / np.sqrt(nn), np.inf)
        for p0, p1 in ((a, b), (b, c), (c, a)):  # else the nearest edge
            e = p1 - p0
            s = np.clip(((P - p0) @ e) / (e @ e), 0, 1)
            d = np.minimum(d, np.linalg.norm(P - (p0 + s[:, None] * e), axis=1))
        best = np.minimum(best, d)
    return best


def _true_distance(src, X: np.ndarray) -> np.ndarray:
    tris = np.concatenate([p.vertices[p.faces] for p in src.model.parts])
    return np.minimum(_point_triangle_distance(X, tris), np.abs(X[:, 2]))  # the ground is z = 0


def test_points_lie_within_noise_of_the_true_surfaces(src, cloud):
    assert len(cloud.xyz) > 3000
    X = cloud.xyz[np.random.default_rng(0).choice(len(cloud.xyz), 1500, replace=False)]
    d = _true_distance(src, X)
    # |N(0, s)| has median 0.67 s; along an oblique ray the distance to the surface is less
    assert 0.2 * SIGMA < np.median(d) < 0.8 * SIGMA
    assert np.quantile(d, 0.99) < 4 * SIGMA
    np.testing.assert_allclose(np.linalg.norm(cloud.normals, axis=1), 1.0, atol=1e-4)


def test_density_is_about_the_photos_footprint(cloud):
    from scipy.spatial import cKDTree

    gap = cKDTree(cloud.xyz).query(cloud.xyz, k=2)[0][:, 1]
    # photos at 10-14 m with f = 100 px: about 0.1 m a pixel; the voxel grid keeps one point in each
    assert 0.07 < cloud.stats["voxel"] < 0.15
    assert 0.3 * cloud.stats["voxel"] < np.median(gap) < 1.5 * cloud.stats["voxel"]


def _glass_points(src, X: np.ndarray) -> int:
    """Points on a shop front's pane (the opening's back at -relief, less its frame), with room for the noise."""
    relief, n = 0.4, 0
    for face in src.building.walls:
        lay = src.layouts[face.id]
        uv, off = face.to2d(X), (X - face.origin) @ face.normal
        pane = np.abs(off + relief) < 4 * SIGMA
        for u0, v0, u1, v1 in lay.shopfronts + lay.windows:
            m = 0.07 + 0.06  # the frame, and the noise's sideways part along oblique rays
            inner = (uv[:, 0] > u0 + m) & (uv[:, 0] < u1 - m) & (uv[:, 1] > v0 + m) & (uv[:, 1] < v1 - m)
            n += int((pane & inner).sum())
    return n


def test_no_point_on_glass(src, cloud, monkeypatch):
    assert _glass_points(src, cloud.xyz) == 0
    # the photos do see the panes: without the glass test they are reconstructed
    monkeypatch.setattr(D, "_glass", lambda src, face_index, X: np.zeros(len(X), bool))
    assert _glass_points(src, D.fuse(src, D.DenseSettings(noise=SIGMA)).xyz) > 200


def test_points_seen_by_one_photo_are_absent(src, cloud):
    X = cloud.xyz
    back = (np.abs(X[:, 1] - 4.0) < 0.5) & (X[:, 2] > 0.3) & (np.abs(X[:, 0]) < 5.5)
    assert back.sum() == 0  # wall01 and its shop fronts: only photo b sees them
    assert cloud.stats["single_view"] > 1000
    # every point lies inside at least two photos (a 2 px margin for the noise)
    inside = np.zeros(len(X), int)
    for v in _views():
        Xc = X @ v.R.T + v.t
        xy = np.asarray(v.camera.img_from_cam(Xc))
        inside += ((Xc[:, 2] > 0) & (xy[:, 0] > -2) & (xy[:, 0] < W + 2) & (xy[:, 1] > -2) & (xy[:, 1] < H + 2))
    assert inside.min() >= 2


def test_same_seed_same_cloud(src, cloud):
    again = D.fuse(src, D.DenseSettings(noise=SIGMA))
    assert again.xyz.tobytes() == cloud.xyz.tobytes() and again.rgb.tobytes() == cloud.rgb.tobytes()


def test_fused_ply_is_colmaps_layout_and_round_trips(cloud, tmp_path):
    import trimesh

    from difftex.geometry.dense import read_cloud

    path = tmp_path / "fused.ply"
    D.write_fused_ply(path, cloud)
    data = path.read_bytes()
    header = HEADER.replace(b"{n}", str(len(cloud.xyz)).encode())
    assert data.startswith(header) and len(data) == len(header) + 27 * len(cloud.xyz)
    rec = np.frombuffer(data, "<f4,<f4,<f4,<f4,<f4,<f4,u1,u1,u1", offset=len(header))
    np.testing.assert_array_equal(np.stack([rec[f"f{k}"] for k in range(3)], 1), cloud.xyz.astype(np.float32))
    np.testing.assert_array_equal(np.stack([rec[f"f{k}"] for k in range(3, 6)], 1), cloud.normals)
    np.testing.assert_array_equal(np.stack([rec[f"f{k}"] for k in range(6, 9)], 1), cloud.rgb)
    pc = trimesh.load(str(path), file_type="ply", process=False)
    np.testing.assert_allclose(pc.vertices, cloud.xyz, atol=1e-5)
    np.testing.assert_array_equal(np.asarray(pc.colors)[:, :3], cloud.rgb)
    np.testing.assert_allclose(read_cloud(path), cloud.xyz, atol=1e-5)  # difftex's dense reader takes it


def _fake_scene(root):
    """A `difftex synth` scene folder holding only synth.json (the tiny preset, occluders on, the three cameras)."""
    from difftex.synth.presets import get_preset

    cfg = get_preset("tiny")
    meta = {"generator": "difftex synth", "preset": "tiny", "seed": 0, "building_index": 0,
            "building": {"name": "tiny"}, "config": cfg.to_dict(),
            "cameras": [{"camera_id": 1, "model": "PINHOLE", "width": W, "height": H, "f": F, "k": 0.0}],
            "views": [{"name": n, "camera_id": 1, "R_true": R.tolist(), "t_true": t.tolist()} for n, R, t in _poses()]}
    root.mkdir()
    (root / "synth.json").write_text(json.dumps(meta))
    return root


def test_write_dense_scene_cloud_mesh_summary(tmp_path):
    import trimesh
    from scipy.spatial import cKDTree

    scene = _fake_scene(tmp_path / "tiny")
    summary = D.write_dense(scene, D.DenseSettings(noise=SIGMA, mesh_detail=0.15))
    out = scene / "dense"
    assert sorted(p.name for p in out.iterdir()) == ["dense.json", "fused.ply", "meshed-poisson.ply"]  # no temp file
    assert json.loads((out / "dense.json").read_text())["points"] == summary["points"] > 3000
    X = np.asarray(trimesh.load(str(out / "fused.ply"), file_type="ply", process=False).vertices)
    assert (X[:, 2] > 2.0).sum() and summary["seconds"]["total"] > 0
    mesh = trimesh.load(str(out / "meshed-poisson.ply"), process=False)
    assert len(mesh.faces) == summary["mesh"]["faces"] > 1000
    assert mesh.visual.vertex_colors.shape[0] == len(mesh.vertices)
    # the mesh is near the points and covers them
    assert cKDTree(X).query(mesh.vertices)[0].max() <= summary["mesh"]["trim_distance"] + 1e-6
    assert np.median(cKDTree(mesh.vertices).query(X)[0]) < 0.1
    assert summary["mesh"]["trimmed_faces"] > 0  # the closed Poisson surface's bubble below the ground went


def test_cli_not_a_synth_scene_is_one_line(tmp_path, capsys):
    from difftex.cli import main

    assert main(["synth-dense", "--scene", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("difftex: error: ") and "synth.json" in err[0]
    (tmp_path / "synth.json").write_text('{"generator": "difftex synth"}')
    assert main(["synth-dense", "--scene", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "not the manifest" in err[0] and not (tmp_path / "dense").exists()


def test_synth_dense_flag_scene_folders_and_districts(tmp_path, capsys):
    from difftex.cli import main
    from difftex.cli.synth import scene_dirs

    assert scene_dirs("tiny", tmp_path, None) == [tmp_path]
    assert scene_dirs("survey", tmp_path, None) == [tmp_path / n for n in ("lblock", "gable", "courtyard")]
    assert scene_dirs("survey", tmp_path, ["gable"]) == [tmp_path / "gable"]
    assert main(["synth", "--preset", "city-block", "--dense", "--out", str(tmp_path / "d"), "--quiet"]) == 2
    assert "--dense is for building presets" in capsys.readouterr().err and not (tmp_path / "d").exists()
