"""The reprojection peer: texrecon on the dense mesh, baked orthographically onto the proxy.

The bake is checked on an analytic textured mesh: a wall (the plane z = 0, facing +z) with a
recess, a box standing out of it, a face texrecon left untextured, a surface far above the
relief range (a tree's crown: not seen) and one far below (a miss). Its texture is known in
closed form, so every texel's colour is.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from difftex.evaluation.peers import reprojection as R
from difftex.evaluation.peers import texrecon
from difftex.geometry.dense import DenseMesh
from difftex.geometry.frames import UVFrame

# the frame: x in [0, 4] (columns), y in [2, 0] (rows, "down"), 0.1 units a texel; normal +z
FRAME = UVFrame(
    np.array([0.0, 2.0, 0.0]), np.array([1.0, 0, 0]), np.array([0, -1.0, 0]), np.array([0, 0, 1.0]), 0.1, 40, 20
)
GRAD = 0  # material 0: a gradient atlas, colour (u, v, 0.5) at atlas coordinates (u, v)
SOLID = 1  # material 1: solid blocks of 8 x 8 pixels
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # evaluation/peers.py, the tables' peer rows

BLOCKS = {
    "green": (0.1, 0.8, 0.1),
    "yellow": (0.9, 0.9, 0.1),
    "blue": (0.1, 0.2, 0.9),
    "magenta": (0.9, 0.1, 0.8),
    "cyan": (0.1, 0.9, 0.9),
}


def grad_uv(x, y):
    """The wall's atlas coordinates (inside the atlas by a margin: no border effects)."""
    return np.stack([0.05 + 0.9 * np.asarray(x) / 4, 0.05 + 0.9 * np.asarray(y) / 2], -1)


def atlases() -> list[np.ndarray]:
    r, c = np.mgrid[0:32, 0:64] + 0.5
    grad = np.stack([c / 64, 1 - r / 32, np.full_like(c, 0.5)], -1)
    solid = np.concatenate([np.broadcast_to(v, (8, 8, 3)) for v in BLOCKS.values()], 1)
    return [np.concatenate([a, np.ones((*a.shape[:2], 1))], -1).astype(np.float32) for a in (grad, solid)]


def rect(x0, x1, y0, y1, z):
    return [(x0, y0, z), (x1, y0, z), (x1, y1, z), (x0, y1, z)]


def side(p, q, z0, z1):
    """A vertical quad from (p, z0) to (q, z1) (the recess' and box's sides)."""
    return [(*p, z0), (*q, z0), (*q, z1), (*p, z1)]


def analytic_mesh() -> R.TexturedMesh:
    """The textured dense mesh of the module docstring (quads as two triangles each)."""
    quads = []  # (corners, material, colour block or None for the gradient)
    for r in [(0, 1, 0.5, 2), (2, 3.8, 0, 2), (1, 2, 0, 0.5), (1, 2, 1.5, 2)]:
        quads.append((rect(*r, 0.0), GRAD, None))
    quads.append((rect(0, 1, 0, 0.5, 0.0), -1, None))  # untextured
    quads.append((rect(1, 2, 0.5, 1.5, -0.3), SOLID, "green"))  # the recess' bottom
    for p, q in [((1, 0.5), (2, 0.5)), ((2, 0.5), (2, 1.5)), ((2, 1.5), (1, 1.5)), ((1, 1.5), (1, 0.5))]:
        quads.append((side(p, q, -0.3, 0.0), SOLID, "yellow"))
    quads.append((rect(2.5, 3.5, 0.5, 1.5, 0.25), SOLID, "blue"))  # the box's top
    for p, q in [((2.5, 0.5), (3.5, 0.5)), ((3.5, 1.5), (2.5, 1.5))]:
        quads.append((side(p, q, 0.0, 0.25), SOLID, "yellow"))
    quads.append((rect(0.2, 0.8, 1.0, 1.8, 2.0), SOLID, "magenta"))  # far above the wall
    quads.append((rect(3.8, 4.0, 0, 2, -2.0), SOLID, "cyan"))  # far behind it
    V, F, UV, M = [], [], [], []
    names = list(BLOCKS)
    for corners, mat, block in quads:
        n = len(V)
        V += corners
        c = np.asarray(corners)
        uv = (
            grad_uv(c[:, 0], c[:, 1])
            if block is None
            else np.broadcast_to([(8 * names.index(block) + 4) / 40, 0.5], (4, 2))
        )
        for tri in ((0, 1, 2), (0, 2, 3)):
            F.append([n + i for i in tri])
            UV.append(uv[list(tri)])
            M.append(mat)
    return R.TexturedMesh(np.asarray(V, float), np.asarray(F), np.asarray(UV), np.asarray(M), atlases())


def expected(relief_limited: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """(colour (H, W, 3), covered (H, W)) of every texel; ``relief_limited``: H = 0.2 (neither
    the box's top at 0.25 nor the recess' bottom at -0.3 within it)."""
    tx, ty = FRAME.centres()
    X = FRAME.texel_to_world(tx, ty)
    x, y = X[..., 0], X[..., 1]
    col = np.concatenate([grad_uv(x, y), np.full((*x.shape, 1), 0.5)], -1)
    cov = np.ones(x.shape, bool)
    recess = (x > 1) & (x < 2) & (y > 0.5) & (y < 1.5)
    box = (x > 2.5) & (x < 3.5) & (y > 0.5) & (y < 1.5)
    if relief_limited:
        cov &= ~recess
    else:
        col[recess] = BLOCKS["green"]
        col[box] = BLOCKS["blue"]
    cov &= ~((x < 1) & (y < 0.5)) & ~(x > 3.8)  # the untextured face; the miss
    return np.where(cov[..., None], col, 0.0), cov


@pytest.mark.parametrize("backend", ["mitsuba", "numpy"])
@pytest.mark.parametrize("relief", [1.0, 0.2])
def test_bake_gives_the_front_most_surface_along_the_normal(backend, relief):
    if backend == "mitsuba":
        from difftex.geometry.raycast import mitsuba_available

        if not mitsuba_available():
            pytest.skip("Mitsuba's LLVM variant does not load here")
    tm = analytic_mesh()
    # relief 1.0 is capped at a fifth of the 2-unit short side: H = 0.4
    assert R.relief_bounds(FRAME, relief) == pytest.approx((-min(relief, 0.4), min(relief, 0.4)))
    mask = np.ones(FRAME.shape, bool)
    mask[0, 0] = False
    tex, cov, src = R.bake_polygon(tm, R.Caster(tm.vertices, tm.faces, backend), FRAME, mask, 2, relief)
    want, want_cov = expected(relief_limited=relief < 0.25)
    want_cov &= mask
    np.testing.assert_array_equal(cov, want_cov)
    np.testing.assert_allclose(tex[cov], want[cov], atol=1e-4)
    assert (tex[~cov] == 0).all() and src is None


def test_the_two_backends_find_the_same_hits():
    from difftex.evaluation.peers.objimport import fine_frame
    from difftex.geometry.raycast import mitsuba_available

    if not mitsuba_available():
        pytest.skip("Mitsuba's LLVM variant does not load here")
    tm = analytic_mesh()
    ff = fine_frame(FRAME, 3)
    a = R.Caster(tm.vertices, tm.faces, "mitsuba").hits(ff, -0.4, 0.4)
    b = R.Caster(tm.vertices, tm.faces, "numpy").hits(ff, -0.4, 0.4)
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_allclose(a[1], b[1], atol=1e-5)
    np.testing.assert_allclose(a[2], b[2], atol=1e-5, equal_nan=True)
    assert np.nanmax(a[2]) == pytest.approx(0.25) and np.nanmin(a[2]) == pytest.approx(-0.3)


def test_source_map_is_the_label_of_the_faces_seen():
    tm = analytic_mesh()
    labels = np.where(tm.material == SOLID, 3, 2)  # texrecon's labels: view l is photo l - 1
    labels[tm.material < 0] = 0
    _, cov, src = R.bake_polygon(
        tm, R.Caster(tm.vertices, tm.faces, "numpy"), FRAME, np.ones(FRAME.shape, bool), 2, 1.0, labels
    )
    want, _ = expected()
    solid = np.isin(want, np.asarray(list(BLOCKS.values()))).all(-1)
    np.testing.assert_array_equal(src, np.where(cov, np.where(solid, 2, 1), -1))
    np.testing.assert_array_equal(R.block_mode(np.array([[0, 0, 5, -1], [1, -1, -1, -1]]), 2), [[0, 5]])


def test_texrecon_obj_is_attached_to_the_mesh_it_was_given(tmp_path):
    """Only the textured faces are in the OBJ, each may start at another corner; the others stay
    in the mesh, untextured."""
    from difftex.scene.files import write_image

    V = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [2, 0, 0]], float)
    F = np.array([[0, 1, 2], [0, 2, 3], [1, 4, 2]])
    write_image(tmp_path / "a.png", np.full((4, 4, 3), 0.5, np.float32))
    (tmp_path / "m.mtl").write_text("newmtl material0000\nmap_Kd a.png\n")
    lines = [
        "mtllib m.mtl",
        *(f"v {x} {y} {z}" for x, y, z in V),
        "vt 0.1 0.1",
        "vt 0.9 0.1",
        "vt 0.9 0.9",
        "usemtl material0000",
        "f 3/3 4/1 1/2",
    ]  # face 1 (0, 2, 3), starting at its corner 2
    (tmp_path / "m.obj").write_text("\n".join(lines) + "\n")
    tm = R.textured_mesh(tmp_path / "m.obj", V, F)
    np.testing.assert_array_equal(tm.material, [-1, 0, -1])
    np.testing.assert_allclose(tm.uv[1], [[0.9, 0.1], [0.9, 0.9], [0.1, 0.1]])
    assert len(tm.faces) == 3 and len(tm.atlases) == 1
    # an OBJ on other vertices is taken on its own
    other = R.textured_mesh(tmp_path / "m.obj", V + 5.0, F)
    assert len(other.faces) == 1 and other.material.tolist() == [0]


def grid(n: int, z: float = 0.0) -> DenseMesh:
    """A 4 x 2 plane at height z, n x n/2 quads."""
    m = n // 2
    xs, ys = np.meshgrid(np.linspace(0, 4, n + 1), np.linspace(0, 2, m + 1))
    V = np.stack([xs.ravel(), ys.ravel(), np.full(xs.size, z)], -1)
    i = (np.arange(m)[:, None] * (n + 1) + np.arange(n)[None]).ravel()
    F = np.concatenate([np.stack([i, i + 1, i + n + 2], -1), np.stack([i, i + n + 2, i + n + 1], -1)])
    return DenseMesh(V, F)


def test_crop_and_decimate():
    g = grid(100)
    far = grid(10, z=50.0)
    both = DenseMesh(np.concatenate([g.vertices, far.vertices]), np.concatenate([g.faces, far.faces + len(g.vertices)]))
    c = R.crop(both, np.array([0, 0, -0.1]), np.array([4, 2, 0.1]))
    assert len(c.faces) == len(g.faces) and np.abs(c.vertices[:, 2]).max() == 0
    d = R.decimate(c, 1000)
    assert 500 <= len(d.faces) <= 1000 and np.abs(d.vertices[:, 2]).max() < 1e-6
    assert R.decimate(c, 10**6) is c


def test_find_mesh_prefers_the_named_meshes(tmp_path):
    from difftex.geometry.meshing import write_ply

    assert R.find_mesh(tmp_path) is None
    dense = tmp_path / "dense"
    dense.mkdir()
    (dense / "fused.ply").write_bytes(
        b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\n"
        b"property float z\nend_header\n0 0 0\n"
    )
    assert R.find_mesh(tmp_path) is None  # a cloud is not a mesh
    write_ply(dense / "a_mesh.ply", grid(4))
    assert R.find_mesh(tmp_path) == dense / "a_mesh.ply"
    write_ply(dense / "meshed-poisson.ply", grid(4))
    assert R.find_mesh(tmp_path) == dense / "meshed-poisson.ply"
    assert R.find_mesh(tmp_path, "elsewhere.obj") == tmp_path / "elsewhere.obj"
    assert "not found" in R.mesh_unavailable(tmp_path, "elsewhere.obj")


def test_without_a_dense_mesh_the_peer_is_unavailable_with_one_line(tmp_path, monkeypatch, capsys):
    import evaluation.peers as P
    from difftex.cli import main

    from tests.scenes import make_scene

    fake = tmp_path / "texrecon"  # texrecon "installed": the dense mesh is what is missing
    fake.write_text("#!/bin/sh\nexit 0\n")
    fake.chmod(0o755)
    monkeypatch.setenv("DIFFTEX_TEXRECON", str(fake))
    scene = make_scene(tmp_path / "s")
    why = P.unavailable("reprojection", scene)
    assert why.startswith("reprojection: ") and "dense" in why and "meshed-poisson.ply" in why and "\n" not in why
    assert P.run_peer("reprojection", scene, tmp_path / "R", {})["missing"] == why
    assert main(["peer", "--method", "reprojection", "--scene", str(scene), "--out", str(tmp_path / "R")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "holds no dense mesh" in err[0]
    assert not (tmp_path / "R").exists()


@pytest.mark.slow
@pytest.mark.skipif(not texrecon.available(), reason=texrecon.unavailable_reason() or "texrecon unavailable")
def test_reprojection_end_to_end_matches_the_photos(tmp_path, monkeypatch):
    """texrecon on a dense mesh of the rendered wall (a fine grid of it, found in the scene's
    dense/ folder), baked onto the proxy: the photos' content where averaging puts it."""
    import json

    from difftex.geometry.meshing import write_ply

    import tests.test_peers as T

    made = T.rendered_scene

    def with_dense_mesh(root):
        made(root)
        g = grid(80)  # x in [0, 4], y in [0, 2] at z = 0 -> the wall x in [-2, 2], z in [0, 2] at y = 0
        V = np.stack([g.vertices[:, 0] - 2, np.zeros(len(g.vertices)), g.vertices[:, 1]], -1)
        (root / "dense").mkdir()
        write_ply(root / "dense" / "meshed-poisson.ply", DenseMesh(V, g.faces))
        return root

    monkeypatch.setattr(T, "rendered_scene", with_dense_mesh)
    T.check_texture(*T.run_and_compare(tmp_path, "reprojection"))
    rec = json.loads((tmp_path / "R" / "reprojection" / "peer.json").read_text())
    prog = rec["peer_program"]
    assert prog["dense_mesh"].endswith("dense/meshed-poisson.ply") and prog["dense_faces"]["to_texrecon"] == 80 * 40 * 2
    assert prog["decimation"].startswith("none") and rec["label"].startswith("reprojection")


def test_bands_of_rows_bake_the_same_as_one(monkeypatch):
    tm = analytic_mesh()
    caster = R.Caster(tm.vertices, tm.faces, "numpy")
    labels = np.arange(len(tm.faces)) // 2 + 1  # one label a quad: its diagonal is no tie to break
    whole = R.bake_polygon(tm, caster, FRAME, np.ones(FRAME.shape, bool), 2, 1.0, labels)
    monkeypatch.setattr(R, "RAY_CHUNK", 2 * 2 * FRAME.width * 3)  # bands of 3 rows (the last of 2)
    banded = R.bake_polygon(tm, caster, FRAME, np.ones(FRAME.shape, bool), 2, 1.0, labels)
    for a, b in zip(whole, banded):
        np.testing.assert_array_equal(a, b)
