"""The peers (texrecon, MeshLab): camera exports, proxy meshing, OBJ import, and end-to-end runs.

Camera exports are checked against difftex's own projection: a 3D point, projected the way each
program reads its file (Bundler's and MVE's documented formulas, re-implemented here), must land
on the pixel of the resampled photo that shows what difftex's projection of the point shows in the
original photo.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from difftex.errors import DifftexError
from difftex.geometry.frames import texel_mask, uv_frame
from difftex.scene.proxy import Polygon

from tests.scenes import look_at, make_scene, wall, write_colmap_text, write_obj

REPO = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("DIFFTEX_SHARED", REPO.parent / "shared")) / "data"
UP = np.array([0.0, 0.0, 1.0])


def load_photo(tmp_path, model="SIMPLE_RADIAL", params=None, size=(160, 120)):
    from difftex.scene.loading import load_scene

    return load_scene(make_scene(tmp_path / "s", size=size, model=model, params=params)).photos[0]


def points_in_view(photo, n=200, seed=0) -> np.ndarray:
    """World points whose projections spread over the photo (rays through random pixels)."""
    rng = np.random.default_rng(seed)
    pix = rng.uniform([0, 0], [photo.width, photo.height], size=(n, 2))
    return photo.center + photo.unproject(pix) * rng.uniform(2.0, 9.0, size=(n, 1))


# --------------------------------------------------------------------------------------------
# The ideal pinhole resampling


@pytest.mark.parametrize("model,params", [
    ("PINHOLE", [150.0, 160.0, 70.0, 65.0]),  # fx != fy, principal point off-centre
    ("SIMPLE_RADIAL", [150.0, 95.0, 50.0, -0.2]),  # strong barrel, principal point far off-centre
    ("SIMPLE_RADIAL", [150.0, 80.0, 60.0, 0.3]),  # strong pincushion: the rectangle must shrink
    ("OPENCV", [150.0, 148.0, 83.0, 57.0, -0.1, 0.02, 0.001, -0.002]),
])
def test_ideal_camera_sees_each_point_where_the_photo_does(tmp_path, model, params):
    from difftex.geometry.pinhole import ideal_camera, to_source_pixels

    ph = load_photo(tmp_path, model, params)
    cam = ideal_camera(ph)
    K = cam.K()
    assert K[0, 2] == cam.width / 2 and K[1, 2] == cam.height / 2 and K[0, 0] == K[1, 1]
    X = points_in_view(ph)
    p_ideal = cam.project(X)
    p_photo, _ = ph.project(X)
    inside = (p_ideal >= 0).all(1) & (p_ideal <= [cam.width, cam.height]).all(1)
    assert inside.sum() > 50
    np.testing.assert_allclose(to_source_pixels(ph, cam, p_ideal[inside]), p_photo[inside], atol=1e-6)
    # every output pixel sees the inside of the photo: no black padding for a peer to take as colour
    border = np.concatenate([np.stack([np.linspace(0, cam.width, 50), np.full(50, y)], 1) for y in (0, cam.height)]
                            + [np.stack([np.full(50, x), np.linspace(0, cam.height, 50)], 1) for x in (0, cam.width)])
    assert ph.in_image(to_source_pixels(ph, cam, border)).all()
    if params[-1] == 0.3:
        assert cam.width < 2 * min(params[1], 160 - params[1])  # shrunk to fit the pincushion


def test_resampled_photo_shows_the_photo_content_at_the_same_rays(tmp_path):
    from difftex.geometry.pinhole import ideal_camera, resample, to_source_pixels

    ph = load_photo(tmp_path, "SIMPLE_RADIAL", [150.0, 95.0, 50.0, -0.1])

    def pattern(p):  # smooth, so bilinear interpolation is nearly exact
        return np.stack([0.5 + 0.4 * np.sin(p[..., 0] / 9.0), 0.5 + 0.4 * np.cos(p[..., 1] / 7.0),
                         0.2 + 0.003 * p[..., 0]], -1)

    jj, ii = np.meshgrid(np.arange(ph.width) + 0.5, np.arange(ph.height) + 0.5)
    img = pattern(np.stack([jj, ii], -1)).astype(np.float32)
    cam = ideal_camera(ph)
    out = resample(ph, cam, img)
    assert out.shape == (cam.height, cam.width, 3)
    jj, ii = np.meshgrid(np.arange(cam.width) + 0.5, np.arange(cam.height) + 0.5)
    want = pattern(to_source_pixels(ph, cam, np.stack([jj, ii], -1)))
    np.testing.assert_allclose(out, want, atol=2e-3)
    # downscaled by 4: box-filtered first, so the mean colour is kept (no aliasing of the pattern)
    small = ideal_camera(ph, long_side=cam.width // 4)
    assert small.width == cam.width // 4 or small.width == cam.width // 4 - 1
    np.testing.assert_allclose(resample(ph, small, img).mean((0, 1)), out.mean((0, 1)), atol=0.02)


# --------------------------------------------------------------------------------------------
# The programs' camera files, read back with the programs' own formulas


def bundler_project(text: str, i: int, X: np.ndarray, width: int, height: int) -> np.ndarray:
    """Bundler (v0.3 doc): P = R X + t, p = -P / P_z, p' = f p (no distortion); origin at the image
    centre, y up. As pixels (x right, y down, pixel centres at +0.5): (w/2 + p'_x, h/2 - p'_y)."""
    lines = [ln for ln in text.splitlines() if not ln.startswith("#")]
    n = int(lines[0].split()[0])
    assert i < n
    block = lines[1 + 5 * i: 6 + 5 * i]
    f, k1, k2 = map(float, block[0].split())
    assert k1 == 0 and k2 == 0
    R = np.array([list(map(float, block[j].split())) for j in (1, 2, 3)])
    t = np.array(list(map(float, block[4].split())))
    P = X @ R.T + t
    p = -P[:, :2] / P[:, 2:3]
    return np.stack([width / 2 + f * p[:, 0], height / 2 - f * p[:, 1]], 1)


def mve_project(cam_text: str, X: np.ndarray, width: int, height: int) -> np.ndarray:
    """texrecon: MVE CameraInfo::fill_calibration (f times the larger side, paspect, ppoint times
    w / h) and TextureView::get_pixel_coords (K (R X + t), then -0.5 for array indices); returned
    +0.5, i.e. in COLMAP's pixel convention."""
    l1, l2 = [list(map(float, ln.split())) for ln in cam_text.splitlines()]
    t, R = np.array(l1[:3]), np.array(l1[3:]).reshape(3, 3)
    flen, d0, d1, paspect, ppx, ppy = l2
    assert d0 == 0 and d1 == 0
    if width / height * paspect < 1:
        ax, ay = flen * height / paspect, flen * height
    else:
        ax, ay = flen * width, flen * width * paspect
    K = np.array([[ax, 0, width * ppx], [0, ay, height * ppy], [0, 0, 1]])
    q = (X @ R.T + t) @ K.T
    index = q[:, :2] / q[:, 2:3] - 0.5  # get_pixel_coords: array index, pixel centres at integers
    return index + 0.5


@pytest.mark.parametrize("size,params", [((160, 120), [150.0, 95.0, 50.0, -0.1]),  # landscape
                                         ((90, 140), [120.0, 40.0, 80.0, 0.05])])  # portrait
def test_bundler_and_texrecon_cameras_project_like_difftex(tmp_path, size, params):
    from difftex.evaluation.peers.meshlab import bundler_text
    from difftex.evaluation.peers.texrecon import cam_file_text
    from difftex.geometry.pinhole import ideal_camera, to_source_pixels

    ph = load_photo(tmp_path, "SIMPLE_RADIAL", params, size=size)
    cam = ideal_camera(ph)
    X = points_in_view(ph)
    p_photo, _ = ph.project(X)
    for p in (
        bundler_project(bundler_text([cam, cam]), 1, X, cam.width, cam.height),
        mve_project(cam_file_text(cam), X, cam.width, cam.height),
    ):
        inside = (p >= 0).all(1) & (p <= [cam.width, cam.height]).all(1)
        assert inside.sum() > 50
        np.testing.assert_allclose(to_source_pixels(ph, cam, p[inside]), p_photo[inside], atol=1e-5)


@pytest.mark.skipif(not (SHARED / "herzjesu-p8").is_dir(), reason="shared real scenes not present")
def test_bundler_export_of_a_real_camera_with_off_centre_principal_point():
    """herzjesu-p8: fx != fy and the principal point 30 px off-centre, so the crop matters."""
    from difftex.evaluation.peers.meshlab import bundler_text
    from difftex.geometry.pinhole import ideal_camera, to_source_pixels
    from difftex.scene.loading import load_scene

    sc = load_scene(SHARED / "herzjesu-p8", check_images=False)
    ph = sc.photos[3]
    cam = ideal_camera(ph)
    assert cam.width < ph.width  # cropped around the principal point
    X = np.concatenate([p.outer for p in sc.proxy.polygons])
    p = bundler_project(bundler_text([cam]), 0, X, cam.width, cam.height)
    inside = (p >= 0).all(1) & (p <= [cam.width, cam.height]).all(1)
    assert inside.sum() > 20
    np.testing.assert_allclose(to_source_pixels(ph, cam, p[inside]), ph.project(X[inside])[0], atol=1e-4)


# --------------------------------------------------------------------------------------------
# Proxy mesh: ear clipping and subdivision


def u_with_hole() -> Polygon:
    """A U-shaped (non-convex) wall with a square window: a fan from any corner would cover the notch."""
    outer = np.array(
        [[0, 0, 0], [6, 0, 0], [6, 0, 4], [4, 0, 4], [4, 0, 1.5], [2, 0, 1.5], [2, 0, 4], [0, 0, 4]], float
    )
    outer = outer[::-1] if np.cross(outer[1] - outer[0], outer[2] - outer[0])[1] > 0 else outer
    hole = np.array([[4.5, 0, 0.5], [5.5, 0, 0.5], [5.5, 0, 1.0], [4.5, 0, 1.0]], float)
    p = Polygon("u", outer)
    hole = hole if np.dot(np.cross(hole[1] - hole[0], hole[2] - hole[0]), p.normal) < 0 else hole[::-1]
    return Polygon("u", outer, (hole,))


@pytest.mark.parametrize("max_edge", [100.0, 0.7, 0.2])
def test_proxy_mesh_covers_exactly_the_polygon_with_no_flipped_triangle(max_edge):
    import shapely

    from difftex.geometry.meshing import longest_edge, proxy_mesh
    from difftex.scene.proxy import Proxy

    poly = u_with_hole()
    mesh = proxy_mesh(Proxy([poly], Path("u.obj")), max_edge)
    c = mesh.corners
    cross = np.cross(c[:, 1] - c[:, 0], c[:, 2] - c[:, 0])
    assert (cross @ poly.normal > 0).all()  # no flipped (or degenerate) triangle
    assert 0.5 * np.linalg.norm(cross, axis=1).sum() == pytest.approx(poly.area, rel=1e-9)
    assert poly.area == pytest.approx(6 * 4 - 2 * 2.5 - 0.5, rel=1e-12)
    # no triangle lies in the notch or the window, so with the right total area they tile the polygon
    shape = shapely.Polygon(poly.to_plane(poly.outer), [poly.to_plane(poly.holes[0])])
    cen = poly.to_plane(c.mean(1))
    assert shapely.contains_xy(shape, cen[:, 0], cen[:, 1]).all()
    assert longest_edge(mesh.vertices, mesh.faces) <= min(max_edge, 100.0) or max_edge == 100.0
    if max_edge < 1:
        # conforming: every interior edge is shared by exactly two triangles
        e = np.sort(np.concatenate([mesh.faces[:, [0, 1]], mesh.faces[:, [1, 2]], mesh.faces[:, [2, 0]]]), 1)
        uniq, counts = np.unique(e, axis=0, return_counts=True)
        assert set(counts.tolist()) <= {1, 2}
        # ... and the edges used once are exactly the outline and the window
        b = uniq[counts == 1]
        perimeter = sum(np.linalg.norm(lp - np.roll(lp, 1, 0), axis=1).sum() for lp in (poly.outer, *poly.holes))
        assert np.linalg.norm(mesh.vertices[b[:, 0]] - mesh.vertices[b[:, 1]], axis=1).sum() == pytest.approx(perimeter)


def test_proxy_mesh_refuses_an_absurd_edge_length():
    from difftex.geometry.meshing import proxy_mesh
    from difftex.scene.proxy import Proxy

    with pytest.raises(DifftexError, match="edge length"):
        proxy_mesh(Proxy([u_with_hole()], Path("u.obj")), 1e-4)
    with pytest.raises(DifftexError):
        proxy_mesh(Proxy([u_with_hole()], Path("u.obj")), 0.0)


def test_rasterized_mesh_reaches_every_texel_of_the_polygon():
    from difftex.evaluation.peers.objimport import polygon_face_map
    from difftex.geometry.meshing import proxy_mesh
    from difftex.scene.proxy import Proxy

    poly = u_with_hole()
    mesh = proxy_mesh(Proxy([poly], Path("u.obj")), 0.3)
    frame = uv_frame(poly, UP, long_side=97)
    face = polygon_face_map(frame, mesh.corners)
    mask = texel_mask(poly, frame)
    assert (face[mask] >= 0).all()
    # a texel in the window or the notch is in no triangle (one texel of slack at the outline)
    from scipy.ndimage import binary_dilation

    assert (face[~binary_dilation(mask)] < 0).all()


# --------------------------------------------------------------------------------------------
# Reading textured OBJs back


def test_import_weights_the_atlas_by_its_coverage(tmp_path):
    """Half of the atlas is black (MeshLab's 'no photo'): those texels are uncovered, and the
    covered ones next to them keep their colour (no bleeding of black through bilinear lookups)."""
    from difftex.evaluation.peers.objimport import import_obj
    from difftex.scene.files import write_image

    p = Polygon("front", wall(-2, 2, 0, 2))
    frame = uv_frame(p, UP, long_side=64)
    mask = texel_mask(p, frame)
    atlas = np.zeros((64, 128, 3), np.float32)
    atlas[:, 64:] = [0.2, 0.6, 0.9]
    write_image(tmp_path / "a.png", atlas)
    (tmp_path / "m.mtl").write_text("newmtl m\nmap_Kd a.png\n")
    V = p.outer
    t = frame.world_to_texel(V) / [frame.width, frame.height]  # the atlas spans the frame exactly
    uv = np.stack([t[:, 0], 1 - t[:, 1]], 1)
    obj = [
        "mtllib m.mtl",
        *(f"v {x} {y} {z}" for x, y, z in V),
        *(f"vt {u} {v}" for u, v in uv),
        "usemtl m",
        "f 1/1 2/2 3/3",
        "f 1/1 3/3 4/4",
    ]
    (tmp_path / "m.obj").write_text("\n".join(obj) + "\n")
    tex, cov = import_obj(tmp_path / "m.obj", {"front": frame}, {"front": mask}, coverage="nonblack")["front"]
    assert not cov[:, : frame.width // 2 - 1].any() and cov[:, frame.width // 2 + 1 :].all()
    np.testing.assert_allclose(tex[cov], np.broadcast_to([0.2, 0.6, 0.9], tex[cov].shape), atol=1 / 255)
    tex_uv, cov_uv = import_obj(tmp_path / "m.obj", {"front": frame}, {"front": mask}, coverage="uv")["front"]
    assert cov_uv[mask].all() and tex_uv[:, 0].max() == 0.0  # 'uv' takes the atlas as it is


# --------------------------------------------------------------------------------------------
# End to end on a scene rendered in code


def pattern(x, z):
    """The wall's true colour at (x, z): large asymmetric gradients plus stripes of ~0.25 units."""
    return np.stack(
        [0.15 + 0.18 * (x + 2), 0.15 + 0.3 * z + 0.15 * np.sin(x * 25.0), 0.5 + 0.3 * np.sin(z * 19.0 + x * 3.0)], -1
    ).clip(0, 1)


def rendered_scene(root: Path) -> Path:
    """A 4 x 2 wall at y = 0 with :func:`pattern`, seen by four cameras, one distorted and off-centre."""
    from difftex.scene.camera import load_photos
    from difftex.scene.files import write_image

    centers = [(0.0, -6.0, 1.0), (2.0, -5.5, 1.5), (-2.0, -5.0, 0.5), (0.5, -4.5, 1.2)]
    images = []
    for i, c in enumerate(centers):
        R, t = look_at(c, (0.0, 0.0, 1.0))
        images.append((i + 1, f"img{i:02d}.png", 1 if i < 3 else 2, R, t))
    cams = [
        (1, "PINHOLE", 240, 180, [216.0, 216.0, 120.0, 90.0]),
        (2, "SIMPLE_RADIAL", 240, 180, [200.0, 131.0, 84.0, -0.08]),
    ]
    (root / "images").mkdir(parents=True)
    write_colmap_text(root / "sparse" / "0", cams, images)
    write_obj(root / "proxy.obj", {"front": wall(-2, 2, 0, 2)})
    for ph in load_photos(root / "sparse" / "0", root / "images", check_images=False):
        jj, ii = np.meshgrid(np.arange(ph.width) + 0.5, np.arange(ph.height) + 0.5)
        d = ph.unproject(np.stack([jj, ii], -1))
        s = -ph.center[1] / d[..., 1]
        X = ph.center + s[..., None] * d
        on = (s > 0) & (np.abs(X[..., 0]) <= 2) & (X[..., 2] >= 0) & (X[..., 2] <= 2)
        img = np.where(on[..., None], pattern(X[..., 0], X[..., 2]), 0.3)
        write_image(root / "images" / ph.name, img.astype(np.float32))
    return root


def corr(a: np.ndarray, b: np.ndarray, m: np.ndarray) -> float:
    return float(np.corrcoef(a[m].ravel(), b[m].ravel())[0, 1])


def run_and_compare(tmp_path, method):
    """Visibility, the averaging baseline and the peer on the rendered scene; (peer, average, truth, mask)."""
    import json

    from difftex.cli import main
    from difftex.geometry.visibility import load_visibility
    from difftex.scene.files import read_image

    scene = rendered_scene(tmp_path / "scene")
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text("texture: {long_side: 64}\nvisibility: {min_texels: 4}\ncompute: {device: cpu}\n")
    R = tmp_path / "R"
    assert (
        main(["visibility", "--quiet", "--scene", str(scene), "--config", str(cfg), "--out-dir", str(R / "vis")]) == 0
    )
    assert (
        main(
            [
                "baseline",
                "--scene",
                str(scene),
                "--visibility",
                str(R / "vis" / "front.npz"),
                "--config",
                str(cfg),
                "--method",
                "average",
                "--out-dir",
                str(R / "average" / "textures" / "front"),
            ]
        )
        == 0
    )
    assert (
        main(
            [
                "peer",
                "--method",
                method,
                "--scene",
                str(scene),
                "--visibility",
                str(R / "vis"),
                "--out",
                str(R / method),
                "--timeout",
                "300",
            ]
        )
        == 0
    )
    rec = json.loads((R / method / "peer.json").read_text())
    assert rec["peer"]["wall_s"] > 0 and rec["peer"]["cpu_s"] > 0 and rec["peer"]["peak_rss_mib"] > 1
    assert rec["polygons"]["front"] > 0.95
    vis = load_visibility(R / "vis" / "front.npz")
    tx, ty = vis.frame.centres()
    X = vis.frame.texel_to_world(tx, ty)
    truth = pattern(X[..., 0], X[..., 2])
    peer = read_image(R / method / "textures" / "front" / "texture.png")
    avg = read_image(R / "average" / "textures" / "front" / "texture.png")
    # the results folder is scored by difftex evaluate like any other
    assert (
        main(
            [
                "evaluate",
                "--quiet",
                "--scene",
                str(scene),
                "--results",
                str(R / method),
                "--lpips",
                "none",
                "--out",
                str(R / method / "evaluation" / "metrics.json"),
            ]
        )
        == 0
    )
    return peer, avg, truth, vis.texel_mask


def detail(img: np.ndarray) -> np.ndarray:
    """High-pass (image minus its Gaussian blur, sigma 3 texels): the stripes, not the gradients."""
    from scipy.ndimage import gaussian_filter

    return img - gaussian_filter(img, (3, 3, 0))


def check_texture(peer, avg, truth, mask):
    """The peer's map shows the photos' content where difftex's averaging does.

    Correlation of the maps' detail (:func:`detail`, on the mask shrunk by 4 texels so that the
    blur does not reach outside it), threshold 0.9: both sample the same four photos of an exactly
    planar, unoccluded wall and differ only by resampling and blend weights (measured 0.98-1.0,
    the average against the truth 0.998). A convention error (half a stripe off, i.e. a shift by
    2 texels, a mirrored or transposed map) gives at most 0.6, as the controls below show.
    """
    from scipy.ndimage import binary_erosion

    m = binary_erosion(mask, iterations=4)
    P, A, T = detail(peer), detail(avg), detail(truth)
    assert corr(A, T, m) > 0.97
    assert corr(P, A, m) > 0.9 and corr(P, T, m) > 0.9
    assert corr(peer, avg, mask) > 0.9  # and the colours at large
    assert corr(P[:, ::-1], A, m & m[:, ::-1]) < 0.7
    assert corr(P[:, 2:], A[:, :-2], m[:, 2:] & m[:, :-2]) < 0.7
    assert corr(P[2:], A[:-2], m[2:] & m[:-2]) < 0.7


@pytest.mark.slow
@pytest.mark.skipif(
    __import__("difftex.evaluation.peers.meshlab", fromlist=["x"]).unavailable_reason() != "",
    reason="MeshLab unavailable: "
    + __import__("difftex.evaluation.peers.meshlab", fromlist=["x"]).unavailable_reason(),
)
@pytest.mark.parametrize("method", ["meshlab-blend", "meshlab-face"])
def test_meshlab_end_to_end_matches_the_photos(tmp_path, method):
    check_texture(*run_and_compare(tmp_path, method))


@pytest.mark.slow
@pytest.mark.skipif(
    not __import__("difftex.evaluation.peers.texrecon", fromlist=["x"]).available(),
    reason=__import__("difftex.evaluation.peers.texrecon", fromlist=["x"]).unavailable_reason()
    or "texrecon unavailable",
)
def test_texrecon_end_to_end_matches_the_photos(tmp_path):
    check_texture(*run_and_compare(tmp_path, "texrecon"))


def test_failed_peer_leaves_no_results_folder_and_names_its_log(tmp_path, monkeypatch):
    """A peer that exits non-zero: one-line error naming the log; no (half-written) results folder."""
    from difftex.cli import main

    fake = tmp_path / "texrecon"
    fake.write_text("#!/bin/sh\necho 'Error: something broke' >&2\nexit 3\n")
    fake.chmod(0o755)
    monkeypatch.setenv("DIFFTEX_TEXRECON", str(fake))
    scene = make_scene(tmp_path / "s")
    assert (
        main(["peer", "--method", "texrecon", "--scene", str(scene), "--out", str(tmp_path / "R"), "--long-side", "32"])
        == 2
    )
    assert not (tmp_path / "R").exists()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".R.")]
    log = tmp_path / "R.log"
    assert "something broke" in log.read_text()


def test_missing_texrecon_is_one_clear_line(tmp_path, monkeypatch, capsys):
    from difftex.cli import main

    monkeypatch.setenv("DIFFTEX_TEXRECON", str(tmp_path / "nope"))
    assert (
        main(["peer", "--method", "texrecon", "--scene", str(make_scene(tmp_path / "s")), "--out", str(tmp_path / "R")])
        == 2
    )
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "DIFFTEX_TEXRECON" in err[0]
