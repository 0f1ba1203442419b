"""No grey polygon that a photo sees: the filter's angle and size tests, the visibility stage's
min_texels and the optimizer's photo drop never take the last photos of a polygon or texel, and
what stays untextured is named with the reason (paper, Sec. 3.4: improper photo removal causes
irreversible colour loss)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import torch

from difftex.config import FilterConfig
from difftex.geometry.photo_filter import filter_photos
from difftex.scene.files import read_image, read_json
from difftex.scene.loading import load_scene

from analytic import fast_cfg, gt_texture, make_input, make_photo, optimize, render, write_scene
from tests.scenes import make_scene, wall

torch.set_num_threads(1)

# ---------------------------------------------------------------------------------------------
# The filter


def test_polygon_seen_only_at_85_degrees_is_textured_not_grey(tmp_path):
    """The whole chain on the analytic wall photographed only from 84-86 degrees: the filter
    keeps the oblique photos, the texture follows the wall's pattern, and the model summary
    and the end-of-run message say it was textured from oblique photos."""
    from difftex.cli import main
    from difftex.workflow.glue import format_summary, run_summary

    photos = [
        make_photo("a.png", 85.0, dist=6.0),
        make_photo("b.png", -86.0, dist=6.0),
        make_photo("c.png", 84.0, dist=7.0, pitch_deg=5.0),
    ]
    scene = tmp_path / "scene"
    write_scene(scene, photos, [render(ph) for ph in photos])
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text(
        "texture:\n  density: null\n  long_side: 64\noptimize:\n  long_side_start: 32\n"
        "  max_iters_per_level: [40, 20]\ncompute:\n  device: cpu\n"
    )
    R = tmp_path / "R"
    assert (
        main(["filter", "--scene", str(scene), "--config", str(cfg), "--out", str(R / "photos.json"), "--quiet"]) == 0
    )
    poly = read_json(R / "photos.json")["polygons"]["wall"]
    assert poly["textured_from_oblique"] and sorted(poly["kept"]) == ["a.png", "b.png", "c.png"]
    angles = poly["oblique_angles"]
    assert all(80 < a < 88 for a in angles.values()) and list(angles.values()) == sorted(angles.values())
    assert (
        main(
            [
                "visibility",
                "--scene",
                str(scene),
                "--photos",
                str(R / "photos.json"),
                "--config",
                str(cfg),
                "--out-dir",
                str(R / "visibility"),
                "--quiet",
            ]
        )
        == 0
    )
    row = read_json(R / "visibility" / "summary.json")["polygons"][0]
    assert len(row["photos"]) == 3 and row["coverage"] > 0.9 and row["textured_from_oblique"]
    assert (
        main(
            [
                "texture",
                "--scene",
                str(scene),
                "--visibility",
                str(R / "visibility" / "wall.npz"),
                "--config",
                str(cfg),
                "--threads",
                "1",
                "--out-dir",
                str(R / "optimized" / "wall"),
                "--png-dir",
                str(R / "textures" / "wall"),
                "--no-progress",
            ]
        )
        == 0
    )
    tex = read_image(R / "textures" / "wall" / "texture.png")
    inp = make_input(photos, [render(ph) for ph in photos], long_side=64)
    gt = gt_texture(inp)
    # Seen edge-on, the wall is smeared along its width but sharp along its height: the row means
    # of the texture follow the pattern's (a flat grey texture has no such trend).
    rows_tex, rows_gt = tex[..., 2].mean(1), gt[..., 2].mean(1)
    assert np.corrcoef(rows_tex, rows_gt)[0, 1] > 0.9
    assert np.abs(tex - 0.5).max() > 0.2
    assert (
        main(
            [
                "assemble",
                "--scene",
                str(scene),
                "--textures",
                str(R / "textures"),
                "--config",
                str(cfg),
                "--out-dir",
                str(R / "model"),
            ]
        )
        == 0
    )
    summary = read_json(R / "model" / "summary.json")
    assert summary["untextured"] == [] and set(summary["textured_from_oblique"]["wall"]) == {"a.png", "b.png", "c.png"}
    text = format_summary(run_summary(R))
    assert "1/1 polygons textured" in text and "oblique" in text and "untextured" not in text


def _outside_in(loop: np.ndarray) -> np.ndarray:
    return loop[::-1].copy()  # reversed: the normal points the other way


def reason_scene(root):
    """A wall seen by three cameras, plus one polygon for every way of being unseen."""
    polygons = {
        "front": wall(-2, 2, 0, 2),
        "behind": wall(-1, 1, 0.5, 1.5, y=1.0),  # faces the cameras, but the front wall covers it
        "away": _outside_in(wall(5, 6, 0, 1, y=-1.0)),  # faces away from every camera
        "far": wall(60, 61, 0, 1),  # faces the cameras, outside their images
        "speck": wall(2.3, 2.34, 1.0, 1.04, y=-0.5),  # a few pixels: under min_pixels in every photo
    }
    return make_scene(root, polygons=polygons, centers=[(0.0, -6.0, 1.0), (1.0, -6.0, 1.2), (-1.0, -5.5, 0.8)])


def test_untextured_polygons_are_named_with_the_reason(tmp_path, caplog):
    sc = load_scene(reason_scene(tmp_path / "s"))
    table = filter_photos(sc.proxy, sc.photos, FilterConfig(), progress=False)
    polys = table["polygons"]
    assert polys["front"]["kept"] and not polys["front"]["textured_from_oblique"]
    assert "hidden behind other polygons" in polys["behind"]["untextured_reason"]
    assert "back-facing to every camera" in polys["away"]["untextured_reason"]
    assert "outside every photo" in polys["far"]["untextured_reason"]
    assert polys["behind"]["sight"]["hidden"] == 3 and polys["away"]["sight"]["back-facing"] == 3
    # seen, though in fewer pixels than min_pixels: kept from the photos that see some of it
    assert polys["speck"]["kept"] and polys["speck"]["textured_from_glimpses"]
    assert all(g["points"] > 0 for g in polys["speck"]["glimpses"].values())
    assert "untextured_reason" not in polys["speck"]
    warned = [r.getMessage() for r in caplog.records if "untextured (grey)" in r.getMessage()]
    assert len(warned) == 1 and "3 of 5 polygons" in warned[0] and "speck" not in warned[0]


def test_blurry_photos_are_the_reason_only_when_every_photo_of_it_is_blurry(tmp_path):
    from scipy.ndimage import gaussian_filter

    from difftex.scene.files import write_image

    # three cameras see the front wall, the fourth (to be blurred) only the side wall
    root = make_scene(
        tmp_path / "s",
        polygons={"front": wall(-2, 2, 0, 2), "side": wall(8, 9, 0, 2)},
        centers=[(-1.0, -6.0, 1.0), (-0.5, -6.0, 1.0), (0.0, -6.0, 1.0), (8.5, -6.0, 1.0)],
        target=[(0.0, 0.0, 1.0)] * 3 + [(8.5, 0.0, 1.0)],
    )
    sc = load_scene(root)
    seen_by = [
        ph.name
        for ph in sc.photos
        if "side" in filter_photos(sc.proxy, [ph], FilterConfig(), progress=False)["photos"][0]["polygons"]
    ]
    assert seen_by == ["img03.png"]
    img = read_image(root / "images" / "img03.png")
    write_image(root / "images" / "img03.png", gaussian_filter(img, (3, 3, 0)))
    table = filter_photos(sc.proxy, sc.photos, FilterConfig(), progress=False)
    assert table["polygons"]["side"]["kept"] == []
    assert "dropped as blurry (img03.png)" in table["polygons"]["side"]["untextured_reason"]


def test_angle_filter_keeps_the_frontal_photos_when_there_are_some(tmp_path):
    root = make_scene(tmp_path / "s", centers=[(0.0, -6.0, 1.0), (8.0, -0.6, 1.0)], target=(0.0, 0.0, 1.0))
    sc = load_scene(root)
    poly = filter_photos(sc.proxy, sc.photos, FilterConfig(max_angle_deg=70.0, min_pixels=4), progress=False)[
        "polygons"
    ]["front"]
    assert poly["kept"] == ["img00.png"] and not poly["textured_from_oblique"]
    assert list(poly["inclined"]) == ["img01.png"] and "inclined" in poly["dropped"]["img01.png"]
    # with every photo beyond the limit, all of them are kept, least oblique first in the record
    poly = filter_photos(sc.proxy, sc.photos, FilterConfig(max_angle_deg=1.0, min_pixels=4), progress=False)[
        "polygons"
    ]["front"]
    assert poly["textured_from_oblique"] and poly["kept"] == ["img00.png", "img01.png"] and poly["dropped"] == {}
    assert list(poly["oblique_angles"]) == ["img00.png", "img01.png"]


# ---------------------------------------------------------------------------------------------
# The visibility stage


def _sighting(name, cos):
    return SimpleNamespace(name=name, mean_cos=cos)


def test_last_sources_rescue_only_photos_that_add_texels():
    from difftex.geometry.visibility import last_sources

    mask = np.ones((4, 6), bool)
    left = np.zeros_like(mask)
    left[:, :3] = True
    right = ~left
    kept = [(_sighting("front", 0.9), None, left)]
    spare = [
        (_sighting("copy", 0.3), None, left.copy(), "inclined (83 deg > 80)"),  # adds nothing
        (_sighting("edge", 0.1), None, right, "inclined (85 deg > 80)"),
        (_sighting("side", 0.2), None, right, "inclined (84 deg > 80)"),
    ]  # less oblique: tried first
    out, rescued = last_sources(kept, spare, mask)
    assert [k[0].name for k in out] == ["front", "side"]
    assert rescued == {"side": {"texels": 12, "why": "inclined (84 deg > 80)"}}
    # nothing kept at all: the spare photos are the polygon's only sources
    out, rescued = last_sources([], spare, mask)
    assert [k[0].name for k in out] == ["copy", "side"] and rescued["copy"]["texels"] == 12
    # extremes: no spare photo, an empty polygon
    assert last_sources(kept, [], mask) == (kept, {})
    assert last_sources([], spare, np.zeros_like(mask)) == ([], {})


def test_inclined_photo_returns_for_the_texels_only_it_sees(tmp_path):
    """A frontal close-up sees the left part of the wall; an oblique photo sees all of it. The
    filter drops the oblique one (inclined), the visibility stage takes it back for the rest."""
    from difftex.config import TextureConfig
    from difftex.geometry.visibility import scene_visibility

    root = make_scene(tmp_path / "s", centers=[(-1.2, -1.5, 1.0), (8.0, -1.0, 1.0)], target=(-1.2, 0.0, 1.0))
    sc = load_scene(root)
    table = filter_photos(sc.proxy, sc.photos, FilterConfig(max_angle_deg=70.0, min_pixels=4), progress=False)
    d = table["polygons"]["front"]
    assert d["kept"] == ["img00.png"] and list(d["inclined"]) == ["img01.png"]
    tex = TextureConfig(density=None, long_side=64)
    cands = {"front": d["kept"]}
    alone = scene_visibility(sc.proxy, sc.photos, sc.up, cands, tex, progress=False)[0]
    both = scene_visibility(
        sc.proxy,
        sc.photos,
        sc.up,
        cands,
        tex,
        progress=False,
        fallback={"front": {"img01.png": d["dropped"]["img01.png"]}},
    )[0]
    assert alone.photos == ["img00.png"] and 0.2 < alone.coverage < 0.9
    assert both.photos == ["img00.png", "img01.png"] and both.coverage > alone.coverage + 0.1
    assert both.rescued["img01.png"]["why"].startswith("inclined")
    assert both.rescued["img01.png"]["texels"] == int(
        (both.texel_visible.any(0) & ~alone.texel_visible[0] & both.texel_mask).sum()
    )


def test_min_texels_does_not_take_a_polygons_only_photos(tmp_path):
    from difftex.config import TextureConfig
    from difftex.geometry.visibility import scene_visibility

    root = make_scene(tmp_path / "s")
    sc = load_scene(root)
    names = [p.name for p in sc.photos]
    tex = TextureConfig(density=None, long_side=4)  # 4 x 2 texels: every photo sees fewer than 16
    v = scene_visibility(sc.proxy, sc.photos, sc.up, {"front": names}, tex, min_texels=16, progress=False)[0]
    assert v.photos and v.coverage == 1.0
    assert all("min_texels" in r["why"] for r in v.rescued.values())


# ---------------------------------------------------------------------------------------------
# The optimizer's photo drop


def test_dropped_slot_mask_keeps_a_texels_last_source():
    from difftex.method.elimination import dropped_slot_mask

    # 2 slots over 1 x 3 texels: photo 0 sees texels 0-1, photo 1 texels 1-2
    idx = torch.tensor([[[0, 0, 1]], [[1, 1, -1]]])
    visible = torch.tensor([[[True, True, True]], [[True, True, False]]])
    lv = SimpleNamespace(idx=idx, visible=visible, z0=torch.zeros(2, 1, 3))
    none = torch.zeros_like(visible)
    m = dropped_slot_mask(lv, none, {1})
    assert m.tolist() == [[[False, False, False]], [[True, True, False]]]  # texel 2: photo 1 is its last source
    m = dropped_slot_mask(lv, none, {0, 1})  # both dropped: every texel keeps its best slot
    assert not (visible & ~m).sum(0).eq(0).any()
    eliminated = torch.tensor([[[True, False, False]], [[False, False, False]]])
    m = dropped_slot_mask(lv, eliminated, {1})  # texel 0's photo-0 pixel was eliminated: photo 1 stays there
    assert not m[1, 0, 0] and m[1, 0, 1]


def test_photo_drop_keeps_the_texels_only_the_dropped_photo_sees():
    """An aggressive tau_w drops the oblique photo, yet the texels only it sees keep their colour."""
    front = make_photo("front", 0.0, dist=2.5)  # sees the middle of the wall only
    side = make_photo("side", 60.0, dist=9.0)  # sees all of it
    photos = [front, side]
    inp = make_input(photos, [render(ph) for ph in photos], long_side=48)
    only_side = inp.texel_visible[1] & ~inp.texel_visible[0] & inp.texel_mask
    assert only_side.sum() > 100 and inp.texel_visible[0].sum() > 100
    # tau: weights under 0.2 count as zero, so the shared texels soon make "side" a photo to drop;
    # compared at full detail, where its blurred checker edges disagree with the frontal photo's
    # (low-passed they agree, every texel settles and nothing is dropped). With the relative Q_r
    # "side" (far fewer pixels per texel than "front") starts below tau in the blend, every
    # texel settles and no iteration runs to drop it: the earlier Q_r keeps the drop to test.
    cfg = fast_cfg(
        tau=0.2, tau_w=0.05, max_iters_per_level=(60, 30), consistency_sigma=0.0, resolution_reference="pixel"
    )
    res = optimize(inp, cfg)
    assert "side" in [d["photo"] for d in res.stats["dropped"]]
    assert res.seen[only_side].all()
    err = np.abs(res.U - gt_texture(inp)).mean(-1)
    assert err[only_side].mean() < 0.1


# ---------------------------------------------------------------------------------------------
# The summaries


def test_model_summary_and_end_message_name_the_untextured_with_their_reason():
    from difftex.cli.assemble import polygon_notes
    from difftex.workflow.glue import format_summary

    rows = [
        {"id": "front", "textured": True, "coverage": 1.0, "photos": 3, "texture_size": [64, 32]},
        {"id": "side", "textured": True, "coverage": 0.8, "photos": 1, "texture_size": [16, 32]},
        {"id": "inner", "textured": False, "coverage": 0.0, "photos": 0, "texture_size": None},
        {"id": "lost", "textured": False, "coverage": 0.0, "photos": 0, "texture_size": None},
    ]
    summary = {"polygons": rows, "untextured": ["inner", "lost"]}
    info = {
        "front": {"photos": ["a", "b", "c"]},
        "side": {"photos": ["a"], "textured_from_oblique": True, "oblique_angles": {"a": 84.6}},
        "inner": {
            "photos": [],
            "untextured_reason": "hidden behind other polygons in the 3 photo(s) that have it in view",
        },
    }
    info["front"]["rescued"] = {"c": {"texels": 40, "why": "inclined (84.0 deg > 80.0)"}}
    polygon_notes(summary, info)
    assert summary["textured_from_oblique"] == {"side": {"a": 84.6}}
    assert summary["untextured_reasons"]["inner"].startswith("hidden behind")
    assert "not in the visibility summary" in summary["untextured_reasons"]["lost"]
    text = format_summary({**summary, "results": "R", "model": {}, "atlas_pages": [], "stages": {}, "check": None})
    lines = text.splitlines()
    assert lines[0] == "difftex: 2/4 polygons textured"
    assert any(ln.startswith("  side") and "oblique only (85 deg)" in ln for ln in lines)
    assert any(ln.startswith("  front") and "1 of them only for texels no other photo sees" in ln for ln in lines)
    assert (
        "textured from oblique photos only (every photo sees them beyond filter.max_angle_deg): side (85 deg)" in lines
    )
    i = lines.index("untextured (grey), no photo sees them:")
    assert lines[i + 1] == "  inner: hidden behind other polygons in the 3 photo(s) that have it in view"
    assert lines[i + 2].startswith("  lost: no visibility record")
    assert "front" not in "\n".join(lines[i:])
    # a polygon textured as mixed resolution says so, with its spread
    text = format_summary({**summary, "results": "R", "model": {}, "atlas_pages": [], "stages": {}, "check": None,
                           "mixed_resolution": {"front": 4.65, "inner": 5.0}})
    lines = text.splitlines()
    assert any(ln.startswith("  front") and "mixed resolution (finest photo 4.7x the median)" in ln for ln in lines)
    assert not any(ln.startswith(("  side", "  inner")) and "mixed resolution" in ln for ln in lines)
