"""Camera projection, proxy loading, the UV frame and the texel <-> pixel mapping."""

from __future__ import annotations

import numpy as np
import pycolmap
import pytest

from difftex.geometry.frames import map_texels, pixel_to_texel, texel_mask, texel_to_pixel, uv_frame
from difftex.scene.camera import Photo
from difftex.scene.proxy import Polygon, load_proxy

from tests.scenes import look_at, wall, write_obj

CAMERA_MODELS = [
    ("PINHOLE", [500.0, 510.0, 320.0, 240.0]),
    ("SIMPLE_RADIAL", [500.0, 320.0, 240.0, -0.08]),
    ("RADIAL", [500.0, 320.0, 240.0, -0.08, 0.01]),
    ("OPENCV", [500.0, 505.0, 320.0, 240.0, -0.1, 0.02, 0.001, -0.001]),
    ("FULL_OPENCV", [500.0, 505.0, 320.0, 240.0, -0.1, 0.02, 0.001, -0.001, 0.001, 0.0, 0.0, 0.0]),
    ("OPENCV_FISHEYE", [400.0, 400.0, 320.0, 240.0, 0.02, 0.01, 0.0, 0.0]),
]


def make_photo(model: str, params, center=(0.5, -5.0, 1.2), target=(0.0, 0.0, 1.0)) -> Photo:
    cam = pycolmap.Camera(model=model, width=640, height=480, params=params)
    R, t = look_at(center, target)
    return Photo("p.png", None, cam, R, t, 640, 480, model)


@pytest.mark.parametrize("model,params", CAMERA_MODELS)
def test_texel_pixel_round_trip_below_a_hundredth_of_a_pixel(model, params):
    photo = make_photo(model, params)
    frame = uv_frame(Polygon("w", wall(-2, 2, 0, 2.5)), up=np.array([0, 0, 1.0]), long_side=512)
    tx, ty = frame.centres()
    pix, depth = texel_to_pixel(frame, photo, tx, ty)
    ok = photo.in_image(pix, margin=1) & (depth > 0)
    assert ok.mean() > 0.3  # the wall fills a good part of the view
    back = pixel_to_texel(frame, photo, pix[ok])
    pix2, _ = texel_to_pixel(frame, photo, back[:, 0], back[:, 1])
    err_px = np.linalg.norm(pix2 - pix[ok], axis=-1)
    assert err_px.max() < 0.01
    # and the texel round trip itself is tiny relative to a texel
    assert np.abs(back - np.stack([tx[ok], ty[ok]], -1)).max() < 0.01


def test_distortion_is_honoured_not_ignored():
    straight = make_photo("PINHOLE", [500.0, 500.0, 320.0, 240.0])
    bent = make_photo("SIMPLE_RADIAL", [500.0, 320.0, 240.0, -0.1])
    frame = uv_frame(Polygon("w", wall(-2, 2, 0, 2.5)), up=np.array([0, 0, 1.0]), long_side=64)
    tx, ty = frame.centres()
    p1, _ = texel_to_pixel(frame, straight, tx, ty)
    p2, _ = texel_to_pixel(frame, bent, tx, ty)
    far = np.linalg.norm(p1 - [320, 240], axis=-1) > 200
    assert np.nanmax(np.linalg.norm(p1 - p2, axis=-1)[far]) > 5.0


def test_projection_matches_pycolmap_for_all_models():
    X = np.array([[0.3, 0.2, 1.0], [-1.0, 0.0, 0.5], [1.5, 0.0, 2.0]])
    for model, params in CAMERA_MODELS:
        photo = make_photo(model, params)
        pix, depth = photo.project(X)
        ref = photo.camera.img_from_cam(photo.to_camera(X))
        np.testing.assert_allclose(pix, ref, atol=1e-9)
        assert (depth > 0).all()


def test_points_behind_camera_get_nan_pixels():
    photo = make_photo("PINHOLE", [500.0, 500.0, 320.0, 240.0])
    pix, depth = photo.project(np.array([[0.5, -10.0, 1.2]]))  # behind the camera at y=-5
    assert depth[0] < 0 and np.isnan(pix).all()


def test_uv_frame_is_a_right_handed_view_of_the_outside():
    poly = Polygon("w", wall(-2, 2, 0, 3))
    f = uv_frame(poly, up=np.array([0, 0, 1.0]), long_side=300)
    np.testing.assert_allclose(np.cross(f.e_u, f.e_v), -f.normal, atol=1e-12)
    np.testing.assert_allclose(f.normal, [0, -1, 0], atol=1e-12)
    np.testing.assert_allclose(f.e_v, [0, 0, -1], atol=1e-12)  # rows go down the facade
    np.testing.assert_allclose(f.e_u, [1, 0, 0], atol=1e-12)  # columns go left to right seen from outside
    assert (f.width, f.height) == (300, 225)
    np.testing.assert_allclose(f.texel_to_world(0.0, 0.0), [-2, 0, 3], atol=1e-12)  # top-left corner
    # every vertex lies inside the texel rectangle
    t = f.world_to_texel(poly.outer)
    assert (t >= -1e-9).all() and (t[:, 0] <= f.width + 1e-9).all() and (t[:, 1] <= f.height + 1e-9).all()


def test_uv_frame_uses_minimum_area_rectangle_for_rotated_polygons():
    # a square rotated by 30 degrees in its plane: the rectangle must follow its edges
    a = np.radians(30)
    sq = np.array([[np.cos(a + k * np.pi / 2), 0.0, np.sin(a + k * np.pi / 2)] for k in range(4)])[::-1] * 2
    poly = Polygon("r", sq)
    f = uv_frame(poly, up=np.array([0, 0, 1.0]), long_side=100)
    m = texel_mask(poly, f)
    assert m.mean() > 0.97
    side = np.linalg.norm(sq[1] - sq[0])
    assert abs(f.width * f.texel_size - side) < f.texel_size


def test_texel_mask_area_matches_polygon_area_and_holes():
    outer = wall(0, 4, 0, 4)
    hole = wall(1, 2, 1, 2)[::-1]
    poly = Polygon("h", outer, (hole,))
    f = uv_frame(poly, up=np.array([0, 0, 1.0]), long_side=400)
    m = texel_mask(poly, f)
    assert abs(m.sum() * f.texel_size**2 - poly.area) / poly.area < 0.01
    centre_of_hole = f.world_to_texel(np.array([1.5, 0, 1.5])).astype(int)
    assert not m[centre_of_hole[1], centre_of_hole[0]]


@pytest.mark.parametrize("scale", [1e-3, 1.0, 1e4])
def test_tiny_and_huge_polygons_have_finite_frames_and_masks(scale):
    poly = Polygon("s", wall(0, 2, 0, 1) * scale)
    f = uv_frame(poly, up=np.array([0, 0, 1.0]), long_side=256)
    m = texel_mask(poly, f)
    assert np.isfinite(f.A).all() and f.width == 256 and f.height == 128
    assert m.mean() > 0.98
    photo = make_photo(
        "PINHOLE",
        [500.0, 500.0, 320.0, 240.0],
        center=np.array([1.0, -3.0, 0.5]) * scale,
        target=np.array([1.0, 0, 0.5]) * scale,
    )
    mp = map_texels(f, photo)
    assert np.isfinite(mp.pix[mp.valid]).all() and mp.valid.mean() > 0.5


def test_grazing_and_back_views_are_not_valid():
    poly = Polygon("w", wall(-2, 2, 0, 2))
    f = uv_frame(poly, up=np.array([0, 0, 1.0]), long_side=64)
    behind = make_photo("PINHOLE", [500.0, 500.0, 320.0, 240.0], center=(0, 5, 1), target=(0, 0, 1))
    assert not map_texels(f, behind).valid.any()
    grazing = make_photo("PINHOLE", [500.0, 500.0, 320.0, 240.0], center=(6, -1e-4, 1), target=(0, 0, 1))
    m = map_texels(f, grazing)
    assert np.isfinite(m.cos_angle).all() and (m.cos_angle[m.valid] < 0.01).all()


def test_triangulated_box_groups_into_six_polygons(tmp_path):
    import trimesh

    box = trimesh.creation.box(extents=(4.0, 3.0, 2.0))
    for ext in ("ply", "obj", "glb", "off"):
        path = tmp_path / f"box.{ext}"
        if ext == "obj":
            write_obj(path, {f"t{i}": box.vertices[f] for i, f in enumerate(box.faces)})
            # one group per triangle would keep them apart: put all triangles in one group
            text = path.read_text().replace("\ng t", "\n# t")
            path.write_text(text)
        else:
            box.export(path)
        proxy = load_proxy(path)
        assert len(proxy) == 6, ext
        areas = sorted(round(p.area, 6) for p in proxy.polygons)
        assert areas == [6.0, 6.0, 8.0, 8.0, 12.0, 12.0]
        for p in proxy.polygons:
            assert len(p.outer) == 4  # diagonals of the triangulation are gone
            assert p.normal @ (p.centroid - box.centroid) > 0  # outward


def test_ngon_faces_are_kept_and_ids_are_stable(tmp_path):
    path = tmp_path / "p.obj"
    write_obj(path, {"facade": wall(0, 4, 0, 3), "facade 2": wall(4, 6, 0, 3), "x": wall(6, 7, 0, 3)})
    a, b = load_proxy(path), load_proxy(path)
    assert a.ids == b.ids == ["facade", "facade_2", "x"]
    # names equal once made safe: deterministic suffixes in file order (a warning lists them)
    write_obj(path, {"dup": wall(0, 4, 0, 3), "dup ": wall(4, 6, 0, 3)})
    assert load_proxy(path).ids == ["dup_1", "dup_2"]


@pytest.mark.parametrize(
    "model,params", [("PINHOLE", (500.0, 520.0, 61.0, 39.5)), ("SIMPLE_PINHOLE", (480.0, 64.0, 40.0))]
)
@pytest.mark.parametrize("stride", [1, 3])
def test_pinhole_camera_rays_match_colmap_unprojection(model, params, stride):
    from difftex.geometry.raycast import _camera_rays

    w, h = 128, 80
    d = _camera_rays(model, w, h, params, stride)
    ys = np.minimum(np.arange(0, h, stride) + 0.5 * stride, h - 0.5)
    xs = np.minimum(np.arange(0, w, stride) + 0.5 * stride, w - 0.5)
    gx, gy = np.meshgrid(xs, ys)
    cam = pycolmap.Camera(model=model, width=w, height=h, params=list(params))
    xy = np.asarray(cam.cam_from_img(np.stack([gx, gy], -1).reshape(-1, 2)))
    ref = np.concatenate([xy, np.ones((len(xy), 1))], 1)
    ref /= np.linalg.norm(ref, axis=1, keepdims=True)
    assert d.shape == (len(ys), len(xs), 3) and d.dtype == np.float32
    assert np.abs(d.reshape(-1, 3) - ref).max() < 1e-6
