"""Atlas packing, dilation, OBJ/GLB writing and their reload (difftex.export.assemble)."""

from __future__ import annotations

import numpy as np
import pytest

from difftex.errors import DifftexError
from difftex.export.assemble import AssembleConfig, PolygonTexture, assemble, dilate, pack, triangulate
from difftex.export.check import sample_atlas
from difftex.geometry.frames import texel_mask, uv_frame
from difftex.scene.proxy import Polygon

UP = np.array([0.0, 0.0, 1.0])


def _wall(pid, x0, x1, y, z1=3.0, holes=()):
    """A vertical wall in the plane y = const facing -y (counter-clockwise seen from -y)."""
    outer = np.array([[x0, y, 0.0], [x1, y, 0.0], [x1, y, z1], [x0, y, z1]])
    return Polygon(pid, outer, tuple(holes))


def _scene():
    square = _wall("front", 0.0, 4.0, 0.0)
    # L-shaped (non-convex) facade
    lshape = Polygon(
        "lshape",
        np.array([[5.0, 0, 0], [9.0, 0, 0], [9.0, 0, 1.5], [7.0, 0, 1.5], [7.0, 0, 3.0], [5.0, 0, 3.0]]),
    )
    # a wall with a window hole (hole clockwise seen from outside)
    hole = np.array([[11.0, 0, 1.0], [11.0, 0, 2.0], [12.0, 0, 2.0], [12.0, 0, 1.0]])
    holed = _wall("holed", 10.0, 13.0, 0.0, holes=(hole,))
    roof = Polygon("roof", np.array([[0.0, 0, 3], [4.0, 0, 3], [4.0, 2, 3], [0.0, 2, 3]]))
    return [square, lshape, holed, roof]


def _items(rng, long_side=40, constant=False, skip=("roof",)):
    items, colours = [], {}
    for p in _scene():
        frame = uv_frame(p, UP, long_side=long_side)
        if p.id in skip:
            items.append(PolygonTexture(p, frame))
            continue
        mask = texel_mask(p, frame)
        if constant:
            colours[p.id] = rng.uniform(0.1, 0.9, 3).astype(np.float32)
            tex = np.broadcast_to(colours[p.id], (*frame.shape, 3)).copy()
        else:
            # smooth random texture: bilinear sampling of it is well defined
            yy, xx = np.mgrid[0 : frame.height, 0 : frame.width] / long_side
            ph = rng.uniform(0, 6, 3)
            tex = (0.5 + 0.4 * np.sin(3 * xx[..., None] + 2 * yy[..., None] + ph)).astype(np.float32)
        tex[~mask] = 0.0  # what lies outside the polygon must not leak into the atlas
        items.append(PolygonTexture(p, frame, tex, mask, coverage=1.0, photos=2))
    return items, colours


def test_triangulate_keeps_area_orientation_and_holes():
    for p in _scene():
        v, t = triangulate(p)
        a, b, c = v[t[:, 0]], v[t[:, 1]], v[t[:, 2]]
        cr = np.cross(b - a, c - a)
        assert (cr @ p.normal > 0).all()
        assert 0.5 * np.linalg.norm(cr, axis=1).sum() == pytest.approx(p.area, rel=1e-9)


def test_dilate_fills_padding_with_nearest_valid_texel():
    tex = np.zeros((4, 5, 3), np.float32)
    tex[:, :2] = [1, 0, 0]
    tex[:, 2:] = [0, 0, 1]
    mask = np.ones((4, 5), bool)
    mask[:, 4] = False  # invalid column: must become blue (its nearest valid neighbour)
    tex[:, 4] = [0, 1, 0]
    out = dilate(tex, mask, 3)
    assert out.shape == (10, 11, 3)
    assert np.allclose(out[:, :3], [1, 0, 0])  # left padding copies the red edge
    assert np.allclose(out[:, -4:], [0, 0, 1])  # invalid column and right padding: blue
    assert not np.isclose(out, [0, 1, 0]).all(axis=-1).any()


def test_pack_no_overlap_and_pages_within_limit():
    rng = np.random.default_rng(1)
    sizes = {f"r{i}": (int(rng.integers(10, 90)), int(rng.integers(10, 90))) for i in range(40)}
    where, pages = pack(sizes, 128)
    assert len(pages) > 1 and all(w <= 128 and h <= 128 for w, h in pages)
    occ = [np.zeros((h, w), int) for w, h in pages]
    for rid, (b, x, y) in where.items():
        w, h = sizes[rid]
        occ[b][y : y + h, x : x + w] += 1
    assert max(o.max() for o in occ) == 1
    assert sum(o.sum() for o in occ) == sum(w * h for w, h in sizes.values())
    with pytest.raises(DifftexError):
        pack({"big": (200, 10)}, 128)


@pytest.mark.parametrize("max_page", [8192, 64])
def test_glb_and_obj_reload_with_each_polygon_showing_its_texture(tmp_path, max_page):
    import trimesh

    rng = np.random.default_rng(0)
    items, colours = _items(rng, constant=True)
    cfg = AssembleConfig(max_page_size=max_page, padding=4)
    summary = assemble(items, tmp_path, cfg)
    assert summary["untextured"] == ["roof"]
    if max_page == 64:
        assert len(summary["atlas_pages"]) > 1
    for page in summary["atlas_pages"]:
        assert page["width"] <= max_page and page["height"] <= max_page

    scene = trimesh.load(tmp_path / "model.glb", force="scene")
    assert set(scene.geometry) == {p.id for p in _scene()}
    for p in _scene():
        g = scene.geometry[p.id]
        assert g.area == pytest.approx(p.area, rel=1e-6)
        page = np.asarray(g.visual.material.baseColorTexture.convert("RGB"), np.float32) / 255
        uv = g.visual.uv[g.faces].mean(axis=1)  # triangle centroids
        got = sample_atlas(page, uv)
        want = colours.get(p.id, np.array(cfg.untextured_color))
        assert np.abs(got - want).max() < 1.5 / 255, p.id

    obj = trimesh.load(tmp_path / "model.obj", force="mesh")
    assert obj.area == pytest.approx(sum(p.area for p in _scene()), rel=1e-6)
    text = (tmp_path / "model.obj").read_text()
    for p in _scene():
        assert f"\ng {p.id}\n" in text
    assert "map_Kd model_atlas0.png" in (tmp_path / "model.mtl").read_text()


def test_texture_orientation_survives_the_round_trip(tmp_path):
    items, _ = _items(np.random.default_rng(3), long_side=64)
    summary = assemble(items, tmp_path, AssembleConfig(padding=2))
    chk = summary["check"]
    assert chk["missing_polygons"] == [] and chk["max_area_rel_error"] < 1e-6
    # 8-bit quantisation of both the atlas and nothing else
    assert chk["max_color_error"] < 2.0 / 255


def test_mirrored_texture_is_detected(tmp_path):
    """The check above can fail: a texture flipped left-right after packing is caught."""
    from difftex.export.check import verify_glb

    items, _ = _items(np.random.default_rng(3), long_side=64)
    assemble(items, tmp_path, AssembleConfig(padding=2))
    flipped = [
        PolygonTexture(it.polygon, it.frame, it.texture[:, ::-1].copy(), it.mask[:, ::-1].copy(), 1.0, 2)
        if it.textured
        else it
        for it in items
    ]
    assert verify_glb(tmp_path / "model.glb", flipped)["max_color_error"] > 0.1


def test_config_rejects_bad_values():
    from difftex.config import from_dict

    with pytest.raises(DifftexError):
        from_dict(AssembleConfig, {"max_page_size": 10})
    with pytest.raises(DifftexError):
        from_dict(AssembleConfig, {"page_size": 1024})
