"""Visibility: id buffers, occlusion between proxy polygons, per-polygon masks on disk."""

from __future__ import annotations

import numpy as np
import pytest

from difftex.geometry.visibility import id_buffer, load_visibility, save_visibility, scene_visibility
from difftex.scene.loading import load_scene

from tests.scenes import make_scene, wall


@pytest.fixture
def occlusion_scene(tmp_path):
    # back wall at y=0; a smaller wall 1 m in front of it hides part of it from the camera at y=-6
    back = wall(-2, 2, 0, 2, y=0.0)
    front = wall(-0.5, 0.5, 0, 1, y=-1.0)
    root = make_scene(tmp_path / "occ", {"back": back, "front": front}, centers=[(0.0, -6.0, 1.0)], size=(320, 240))
    return load_scene(root)


def test_occluded_texels_are_the_projected_shadow_of_the_front_polygon(occlusion_scene):
    sc = occlusion_scene
    vis = scene_visibility(sc.proxy, sc.photos, sc.up, {"back": [sc.photos[0].name], "front": [sc.photos[0].name]}, 200)
    back = vis[0]
    assert back.polygon_id == "back" and back.photos == [sc.photos[0].name]
    f = back.frame
    tx, ty = f.centres()
    X = f.texel_to_world(tx, ty)
    # analytic shadow: scale the front wall from the camera centre onto the back plane (factor 6/5)
    in_shadow = (np.abs(X[..., 0]) < 0.6) & (X[..., 2] < 1.0)
    band = (np.abs(np.abs(X[..., 0]) - 0.6) < 0.05) | (np.abs(X[..., 2] - 1.0) < 0.05)
    seen = back.texel_visible[0]
    assert not seen[in_shadow & ~band].any()
    assert seen[~in_shadow & ~band & back.texel_mask].all()
    # the front polygon itself is fully visible
    assert vis[1].texel_visible[0][vis[1].texel_mask].mean() > 0.97
    # photo-space mask: the front polygon's pixels are not the back polygon's
    ph = sc.photos[0]
    a_back = back.a_mask_full(0, ph.width, ph.height)
    a_front = vis[1].a_mask_full(0, ph.width, ph.height)
    assert a_front.sum() > 500 and not (a_back & a_front).any()


def test_id_buffer_stride_agrees_with_full_resolution(occlusion_scene):
    sc = occlusion_scene
    full, _ = id_buffer(sc.proxy, sc.photos[0])
    coarse, _ = id_buffer(sc.proxy, sc.photos[0], stride=4)
    assert coarse.shape == (60, 80)
    sub = full[2::4, 2::4]
    assert (sub == coarse).mean() > 0.97


def test_photo_behind_the_wall_sees_nothing(tmp_path):
    root = make_scene(tmp_path / "s", centers=[(0.0, -6.0, 1.0), (0.0, 6.0, 1.0)])
    sc = load_scene(root)
    names = [p.name for p in sc.photos]
    vis = scene_visibility(sc.proxy, sc.photos, sc.up, {"front": names}, 64)[0]
    assert vis.photos == [names[0]]  # the photo from behind is not a candidate


def test_visibility_file_round_trip_and_levels(occlusion_scene, tmp_path):
    sc = occlusion_scene
    vis = scene_visibility(sc.proxy, sc.photos, sc.up, {"back": [sc.photos[0].name]}, 128)[0]
    save_visibility(tmp_path / "v.npz", vis)
    again = load_visibility(tmp_path / "v.npz")
    assert again.photos == vis.photos and again.frame.to_dict() == vis.frame.to_dict()
    assert (again.texel_visible == vis.texel_visible).all() and (again.texel_mask == vis.texel_mask).all()
    assert all((a == b).all() for a, b in zip(again.a_masks, vis.a_masks))
    assert again.texel_size == vis.texel_size and again.texel_size["bound"] == "long_side"


def test_polygon_without_photos_saves_and_loads(occlusion_scene, tmp_path):
    sc = occlusion_scene
    vis = scene_visibility(sc.proxy, sc.photos, sc.up, {"back": []}, 32)[0]
    assert vis.photos == [] and vis.coverage == 0.0
    save_visibility(tmp_path / "e.npz", vis)
    assert load_visibility(tmp_path / "e.npz").texel_visible.shape == (0, *vis.frame.shape)


def test_mitsuba_and_numpy_casting_agree(occlusion_scene, tmp_path):
    """The two ray-casting backends give the same id buffer (up to a few pixels grazing a polygon
    edge, where float32 and float64 round differently), on a pinhole and a distorted camera."""
    from difftex.geometry.raycast import ProxyCaster, id_buffer, mitsuba_available

    if not mitsuba_available():
        pytest.skip("Mitsuba's LLVM variant is not available (libLLVM)")
    scenes = [occlusion_scene, load_scene(make_scene(tmp_path / "d", model="SIMPLE_RADIAL"))]
    for sc in scenes:
        fast, exact = ProxyCaster.build(sc.proxy, "mitsuba"), ProxyCaster.build(sc.proxy, "numpy")
        for ph in sc.photos:
            a, da = id_buffer(fast, ph)
            b, db = id_buffer(exact, ph)
            assert (a >= 0).any()
            assert (a != b).mean() < 1e-3
            same = (a == b) & (a >= 0)
            assert np.allclose(da[same], db[same], rtol=1e-5)


def test_rays_outside_the_projected_proxy_are_not_cast(occlusion_scene):
    """A pinhole photo casts only the block of rays around the proxy's projected vertices; the
    id buffer is the one of every ray, at full resolution and on a stride grid."""
    import dataclasses

    from difftex.geometry.raycast import ProxyCaster, id_buffer, mitsuba_available, pixel_rays, proxy_window

    if not mitsuba_available():
        pytest.skip("Mitsuba's LLVM variant is not available (libLLVM)")
    sc = occlusion_scene
    caster = ProxyCaster.build(sc.proxy, "mitsuba")
    for ph in sc.photos:
        for stride in (1, 3):
            win = proxy_window(sc.proxy, ph, stride)
            assert win is not None
            ids, dist = id_buffer(caster, ph, stride)
            ref_ids, ref_dist = caster.cast(ph.center, pixel_rays(ph, stride))
            assert np.array_equal(ids, ref_ids) and np.array_equal(dist, ref_dist)
    # a proxy smaller in the frame: the window is a part of the grid
    ph = sc.photos[0]
    far = dataclasses.replace(ph, t=ph.t + np.array([0.0, 0.0, 20.0]))
    y0, y1, x0, x1 = proxy_window(sc.proxy, far, 1)
    assert 0 < (y1 - y0) * (x1 - x0) < 0.5 * far.width * far.height
    ids, _ = id_buffer(caster, far)
    assert (ids >= 0).any() and np.array_equal(ids, caster.cast(far.center, pixel_rays(far))[0])


def test_only_the_best_photos_of_some_texel_stay_candidates(tmp_path):
    """With texel_candidates = m, a photo stays only where it is among the m most frontal,
    resolved photos of some texel: with photos that all see the wall, the m most frontal stay;
    where the close frontal photos miss the wall's ends, the oblique photos that see them stay."""
    import math

    def scene(name, frontal_dist):
        centres = []
        for yaw, dist in [(0, frontal_dist), (4, frontal_dist), (-4, frontal_dist)] + [
            (a, 6) for a in (60, -60, 64, -64, 68, -68)
        ]:
            a = math.radians(yaw)
            centres.append((dist * math.sin(a), -dist * math.cos(a), 1.0))
        sc = load_scene(make_scene(tmp_path / name, {"w": wall(-2, 2, 0, 2)}, centers=centres, size=(320, 240)))
        names = [ph.name for ph in sc.photos]
        full = scene_visibility(sc.proxy, sc.photos, sc.up, {"w": names}, 64)[0]
        capped = scene_visibility(sc.proxy, sc.photos, sc.up, {"w": names}, 64, texel_candidates=3)[0]
        assert len(full.photos) == 9
        # every texel a photo saw is still seen
        assert np.array_equal(full.texel_visible.any(0), capped.texel_visible.any(0))
        return full, capped

    full, capped = scene("far", 6)  # every photo sees the whole wall: the three frontal ones stay
    assert capped.photos == ["img00.png", "img01.png", "img02.png"]
    full, capped = scene("near", 2.5)  # the frontal photos miss the ends: oblique ones texture them
    frontal = [full.photos.index(n) for n in ("img00.png", "img01.png", "img02.png")]
    assert not full.texel_visible[frontal].any(0)[full.texel_mask].all()
    assert {"img00.png", "img01.png", "img02.png"} < set(capped.photos)


@pytest.mark.parametrize("model", ["PINHOLE", "SIMPLE_RADIAL"])
def test_photos_and_polygons_cast_side_by_side_give_the_same_visibility(tmp_path, model):
    """threads > 1 reads polygons' texel visibility, and casts pinhole photos, in worker threads;
    the result (photos in order, masks, crops, texel sizes) is that of one thread. The last
    camera stands beside the back wall looking along it, so that the wall crosses its plane:
    even a pinhole photo is then ray-cast, under the caster's lock, from a worker thread;
    distorted photos are cast on one thread."""
    polys = {"back": wall(-2, 2, 0, 2, y=0.0), "front": wall(-0.5, 0.5, 0, 1, y=-1.0)}
    centers = [(0.0, -6.0, 1.0), (2.0, -6.0, 1.5), (-2.0, -5.0, 0.5), (1.0, -7.0, 0.8), (0.5, -0.6, 1.0)]
    targets = [(0.0, 0.0, 1.0)] * 4 + [(-2.0, 0.0, 1.0)]
    sc = load_scene(make_scene(tmp_path / "s", polys, centers=centers, target=targets, model=model))
    names = [p.name for p in sc.photos]
    cands = {"back": names, "front": names}
    one = scene_visibility(sc.proxy, sc.photos, sc.up, cands, 96, progress=False, threads=1)
    two = scene_visibility(sc.proxy, sc.photos, sc.up, cands, 96, progress=False, threads=3)
    assert [v.polygon_id for v in two] == ["back", "front"]
    for a, b in zip(one, two):
        assert a.photos == b.photos and len(a.photos) >= 3
        assert np.array_equal(a.texel_mask, b.texel_mask) and np.array_equal(a.texel_visible, b.texel_visible)
        assert np.array_equal(a.a_bbox, b.a_bbox)
        assert all(np.array_equal(x, y) for x, y in zip(a.a_masks, b.a_masks))
        assert a.texel_size == b.texel_size


def test_pinhole_crop_visibility_is_the_projected_one(occlusion_scene):
    """The pinhole fast path of crop_texel_visibility (the homography broadcast over the mask's
    rows and columns) marks the same texels as its general path, which projects each texel
    centre, with a partial crop box, a mask with holes, and a frame whose texels overhang the photo."""
    import difftex.geometry.visibility as V
    from difftex.geometry.frames import texel_mask, uv_frame

    sc = occlusion_scene
    ph = sc.photos[0]
    assert ph.is_pinhole
    ids, _ = id_buffer(V.ProxyCaster.build(sc.proxy), ph)
    for i, poly in enumerate(sc.proxy.polygons):
        frame = uv_frame(poly, sc.up, long_side=173)
        mask = texel_mask(poly, frame)
        mask[::7, ::5] = False  # holes
        a = ids == i
        rows, cols = np.flatnonzero(a.any(1)), np.flatnonzero(a.any(0))
        for box in [(int(cols[0]), int(rows[0]), int(cols[-1]) + 1, int(rows[-1]) + 1), (100, 60, 180, 140)]:
            crop = a[box[1] : box[3], box[0] : box[2]]
            fast = V.crop_texel_visibility(frame, ph, mask, box, crop)
            projected = V._crop_texel_visibility_projected(frame, ph, mask, box, crop)
            assert fast.any() and np.array_equal(fast, projected)


def test_crop_visibility_projects_only_the_texels_that_can_reach_the_crop(occlusion_scene):
    """A photo that sees part of a polygon (a pixel box) maps back to a texel span that holds every
    texel whose centre lands in the box, and is smaller than the frame; a box whose corner rays
    miss the plane (above the horizon of a plane seen edge-on) has an unbounded preimage: the
    whole frame."""
    import difftex.geometry.visibility as V
    from difftex.geometry.frames import texel_homography, texel_to_pixel, uv_frame

    sc = occlusion_scene
    ph, poly = sc.photos[0], sc.proxy.polygons[0]
    frame = uv_frame(poly, sc.up, long_side=400)
    H = texel_homography(frame, ph)
    full = (0, frame.shape[0]), (0, frame.shape[1])
    box = (100, 60, 180, 140)
    r0, r1, c0, c1 = V._texel_span_of_box(H, box, *full)
    assert 0 < (r1 - r0) * (c1 - c0) < 0.5 * frame.shape[0] * frame.shape[1]
    ty, tx = np.mgrid[0 : frame.shape[0], 0 : frame.shape[1]]
    pix, _ = texel_to_pixel(frame, ph, tx + 0.5, ty + 0.5)
    lands = (np.floor(pix[..., 0]) >= 100) & (np.floor(pix[..., 0]) < 180)
    lands &= (np.floor(pix[..., 1]) >= 60) & (np.floor(pix[..., 1]) < 140)
    assert lands.any() and not lands[:r0].any() and not lands[r1:].any()
    assert not lands[:, :c0].any() and not lands[:, c1:].any()
    # depth = ty - 50: rays through the photo's rows v < 1 meet the plane behind the camera
    behind = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 1.0, -50.0]])
    assert V._texel_span_of_box(behind, (0, 0, 320, 240), *full) == (*full[0], *full[1])
    assert V._texel_span_of_box(behind, (0, 2, 10, 4), *full)[0] > 0  # rows 2-4: in front, bounded
