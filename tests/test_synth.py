"""The synthetic-scene generator checked against itself, independently of the optimiser.

Two small scenes are generated once per session: the ``tiny`` preset through the CLI (occluders,
exposure variation, pinhole cameras) and a "clean" one (no occluders, reference exposure,
radial distortion) for comparing photos with the ground-truth maps.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("mitsuba")

from difftex.errors import DifftexError  # noqa: E402
from difftex.scene.files import read_image  # noqa: E402
from difftex.synth import generate, get_preset  # noqa: E402

CLEAN = dict(views=6, held_out_views=1, width=240, height=180, gt_long_side=384, points3d=40, occluders=False,
             exposure_range=0.0, white_balance=0.0, image_noise=0.0, distortion=-0.08, street_fraction=0.5,
             spp=64, gt_spp=64, previews=False)


@pytest.fixture(scope="session")
def tiny_scene(tmp_path_factory) -> Path:
    """The README/CI example, made exactly as a user makes it: ``difftex synth --preset tiny``."""
    from difftex.cli import main

    out = tmp_path_factory.mktemp("synth") / "tiny"
    assert main(["synth", "--preset", "tiny", "--out", str(out), "--seed", "3", "--quiet"]) == 0
    return out


@pytest.fixture(scope="session")
def clean_scene(tmp_path_factory) -> Path:
    return generate("tiny", tmp_path_factory.mktemp("synth") / "clean", seed=5, progress=False, **CLEAN)


def _manifest(root: Path) -> dict:
    return json.loads((root / "synth.json").read_text())


def _cfg(man: dict):
    from difftex.synth.presets import BuildingSpec, SynthConfig

    c = dict(man["config"])
    c["buildings"] = tuple(BuildingSpec(**b) for b in c["buildings"])
    return SynthConfig(**c)


def _written_cameras(root: Path) -> dict:
    """name -> (pycolmap camera, R, t) straight from the written COLMAP text model."""
    import pycolmap

    rec = pycolmap.Reconstruction(str(root / "sparse" / "0"))
    out = {}
    for im in rec.images.values():
        m = im.cam_from_world().matrix()
        out[im.name] = (rec.cameras[im.camera_id], m[:, :3], m[:, 3])
    return out


def _intrinsics(man: dict, camera_id: int):
    from difftex.synth.cameras import Intrinsics

    c = next(c for c in man["cameras"] if c["camera_id"] == camera_id)
    return Intrinsics(camera_id, c["width"], c["height"], c["f"], c["k"])


def _smooth(pos: np.ndarray, rel: float = 0.25) -> np.ndarray:
    """Pixels whose position is a locally planar continuation of its neighbours (no edges, no sky)."""
    ok = np.zeros(pos.shape[:2], bool)
    c = pos[1:-1, 1:-1]
    d2x = pos[1:-1, 2:] + pos[1:-1, :-2] - 2 * c
    d2y = pos[2:, 1:-1] + pos[:-2, 1:-1] - 2 * c
    d1 = np.linalg.norm(pos[1:-1, 2:] - pos[1:-1, :-2], axis=-1) + 1e-9
    ok[1:-1, 1:-1] = (
        (np.linalg.norm(d2x, axis=-1) < rel * d1)
        & (np.linalg.norm(d2y, axis=-1) < rel * d1)
        & (np.linalg.norm(c, axis=-1) > 1e-3)
    )
    return ok


@pytest.mark.slow
@pytest.mark.parametrize("which", ["tiny_scene", "clean_scene"])
def test_detailed_points_project_onto_their_pixels(which, request):
    """Mitsuba's ray-traced surface point under each pixel, projected with the *written* COLMAP
    camera (pycolmap's own projection, distortion included), lands within 0.5 px of that pixel."""
    from difftex.synth.pipeline import position_image

    root = request.getfixturevalue(which)
    man = _manifest(root)
    cfg = _cfg(man)
    assert cfg.pose_noise_rot_deg == 0 and cfg.pose_noise_trans == 0
    cams = _written_cameras(root)
    spec = cfg.buildings[0]
    for v in man["views"][:: max(1, len(man["views"]) // 3)]:
        intr = _intrinsics(man, v["camera_id"])
        pos = position_image(cfg, spec, man["seed"], 0, np.array(v["R_true"]), np.array(v["t_true"]), intr)
        cam, R, t = cams[v["name"]]
        ok = _smooth(pos)
        assert ok.sum() > 0.2 * ok.size, f"{v['name']}: too few surface pixels"
        yy, xx = np.nonzero(ok)
        Xc = pos[yy, xx].astype(np.float64) @ R.T + t
        xy = np.asarray(cam.img_from_cam(Xc))
        err = np.linalg.norm(xy - np.stack([xx + 0.5, yy + 0.5], 1), axis=1)
        # Pixel-average positions carry ~0.07 px sampling noise at 16 spp; 0.5 px is the spec.
        assert np.percentile(err, 99) < 0.5, f"{v['name']}: 99th percentile {np.percentile(err, 99):.3f} px"
        assert np.median(err) < 0.15


def _bilinear(img: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    from scipy.ndimage import map_coordinates

    return np.stack([map_coordinates(img[..., c], [y - 0.5, x - 0.5], order=1, mode="nearest")
                     for c in range(img.shape[-1])], -1)


@pytest.mark.slow
def test_ground_truth_map_matches_frontal_photos(clean_scene):
    """Where a photo sees a wall within 35 degrees of frontal (no occluders in this scene), the photo
    and the ground-truth map at the same surface point agree.

    The surface point under a pixel comes from Mitsuba (position AOV); the map is box-blurred to the
    photo pixel's footprint (2-3 texels here). Measured on this configuration (seed 5, 64 spp):
    mean |difference| 0.018-0.021 in sRGB units (Monte Carlo noise of both renders), mean signed
    difference <= 0.005, and on textured texels (local std > 0.04) about 1/3 of the error of the map
    shifted by (4, 3) texels. Tolerances: mean < 0.03, |bias| < 0.01, textured < 0.6 x shifted.
    """
    from scipy import ndimage

    from difftex.geometry.frames import UVFrame
    from difftex.scene.proxy import load_proxy
    from difftex.synth.pipeline import position_image

    root = clean_scene
    man = _manifest(root)
    cfg = _cfg(man)
    polys = {p.id: p for p in load_proxy(root / "proxy.obj").polygons}
    errs, signed, tex_err, tex_shift = [], [], [], []
    for v in man["views"]:
        R, t = np.array(v["R_true"]), np.array(v["t_true"])
        C = -R.T @ t
        intr = _intrinsics(man, v["camera_id"])
        photo = read_image(root / "images" / v["name"])
        pos = None
        for pid, poly in polys.items():
            n = poly.normal
            if not pid.startswith("wall") or -R[2] @ n < np.cos(np.deg2rad(35)) or (C - poly.centroid) @ n <= 0:
                continue
            if pos is None:
                pos = position_image(cfg, cfg.buildings[0], man["seed"], 0, R, t, intr, spp=32)
                ok = _smooth(pos)
            frame = UVFrame.from_dict(json.loads((root / "ground_truth" / "frames" / f"{pid}.json").read_text()))
            gt = read_image(root / "ground_truth" / "maps" / f"{pid}.png")
            yy, xx = np.nonzero(ok & (np.abs(pos.astype(np.float64) @ n - poly.offset) < 0.01))
            tex = frame.world_to_texel(pos[yy, xx].astype(np.float64))
            keep = (tex[:, 0] > 5) & (tex[:, 1] > 5) & (tex[:, 0] < frame.width - 5) & (tex[:, 1] < frame.height - 5)
            yy, xx, tex = yy[keep], xx[keep], tex[keep]
            if len(yy) < 200:
                continue
            footprint = np.linalg.norm(pos[yy, xx] - C, axis=1).mean() / intr.f / frame.texel_size
            k = max(1, int(round(footprint)))
            gtb = ndimage.uniform_filter(gt, size=(k, k, 1))
            ph = photo[yy, xx]
            g = _bilinear(gtb, tex[:, 0], tex[:, 1])
            gs = _bilinear(gtb, tex[:, 0] + 4, tex[:, 1] + 3)
            local_std = ndimage.generic_filter(gt.mean(-1), np.std, size=5)
            textured = local_std[tex[:, 1].astype(int), tex[:, 0].astype(int)] > 0.04
            errs.append(np.abs(g - ph).mean(-1))
            signed.append(ph - g)
            tex_err.append(np.abs(g - ph).mean(-1)[textured])
            tex_shift.append(np.abs(gs - ph).mean(-1)[textured])
    assert errs, "no frontal view of a wall in the clean scene"
    e, b = np.concatenate(errs), np.concatenate(signed).mean(0)
    te, ts = np.concatenate(tex_err), np.concatenate(tex_shift)
    print(
        f"GT vs photo: {len(errs)} wall views, {len(e)} px, mean {e.mean():.4f}, bias {b.round(4)}, "
        f"textured {te.mean():.4f} vs shifted {ts.mean():.4f} ({len(te)} px)"
    )
    assert e.mean() < 0.03
    assert np.abs(b).max() < 0.01
    assert len(te) > 500 and te.mean() < 0.6 * ts.mean()


def test_frames_match_difftex_uv_frames(tiny_scene):
    """The written frames are the ones difftex computes from the scene (same up, same frame)."""
    from difftex.geometry.frames import UVFrame, uv_frame
    from difftex.scene.loading import load_scene

    scene = load_scene(tiny_scene)
    assert len(scene.photos) == get_preset("tiny").views and len(scene.proxy.polygons) >= 6
    assert scene.up[2] > 0.99
    for poly in scene.proxy.polygons:
        d = json.loads((tiny_scene / "ground_truth" / "frames" / f"{poly.id}.json").read_text())
        mine = UVFrame.from_dict(d)
        ref = uv_frame(poly, scene.up, long_side=max(mine.width, mine.height))
        for k in ("origin", "e_u", "e_v", "normal"):
            np.testing.assert_allclose(getattr(mine, k), getattr(ref, k), atol=1e-9, err_msg=f"{poly.id}.{k}")
        assert (mine.width, mine.height) == (ref.width, ref.height)
        gt = read_image(tiny_scene / "ground_truth" / "maps" / f"{poly.id}.png")
        assert gt.shape[:2] == (mine.height, mine.width)


def test_layout_and_pictures(tiny_scene):
    man = _manifest(tiny_scene)
    assert len(list((tiny_scene / "images").glob("*.png"))) == len(man["views"]) == get_preset("tiny").views
    assert man["config"]["occluders"] and man["building"]["occluder_primitives"] > 0
    gains = [v["gain"] for v in man["views"]]
    assert max(gains) / min(gains) > 1.1  # exposure varies between photos
    held = tiny_scene / "ground_truth" / "views"
    seen = set()
    for v in man["held_out_views"]:
        ids = read_image(held / "polygon_ids" / v["name"])[..., 0] * 65535
        labels = set(np.unique(np.round(ids).astype(int)).tolist())
        assert 0 in labels and len(labels) >= 2  # background and at least one polygon
        seen |= labels
        assert read_image(held / "images" / v["name"]).shape[:2] == ids.shape
    assert len(seen) >= 4  # together the held-out views cover several polygons
    for pic in ("contact_sheet.png", "proxy_overlay.png", "ground_truth_maps.png"):
        assert (tiny_scene / "preview" / pic).stat().st_size > 10_000


def test_polygon_ids_agree_with_rendered_geometry(tiny_scene):
    """The id image says which proxy polygon a held-out pixel sees; Mitsuba's surface point there
    (occluder-free) must lie on that polygon's plane, up to the relief depth."""
    from difftex.scene.proxy import load_proxy
    from difftex.synth.pipeline import position_image

    man = _manifest(tiny_scene)
    cfg = _cfg(man)
    polys = load_proxy(tiny_scene / "proxy.obj").polygons
    v = man["held_out_views"][0]
    intr = _intrinsics(man, v["camera_id"])
    pos = position_image(
        cfg, cfg.buildings[0], man["seed"], 0, np.array(v["R"]), np.array(v["t"]), intr, occluders=False
    )
    ids = np.round(read_image(tiny_scene / "ground_truth" / "views" / "polygon_ids" / v["name"])[..., 0] * 65535)
    ok = _smooth(pos) & (ids > 0)
    yy, xx = np.nonzero(ok)
    dist = np.array(
        [abs(polys[int(ids[y, x]) - 1].normal @ pos[y, x] - polys[int(ids[y, x]) - 1].offset) for y, x in zip(yy, xx)]
    )
    assert np.mean(dist < cfg.relief_depth * 1.5 + 0.05) > 0.97


def test_same_seed_same_scene(tmp_path):
    """Same seed: identical manifest and identical bytes for a photo; another seed differs."""
    kw = dict(
        views=2,
        held_out_views=1,
        width=64,
        height=48,
        gt_long_side=32,
        points3d=10,
        previews=False,
        spp=4,
        gt_spp=4,
        progress=False,
    )
    a = generate("tiny", tmp_path / "a", seed=11, **kw)
    b = generate("tiny", tmp_path / "b", seed=11, **kw)
    c = generate("tiny", tmp_path / "c", seed=12, **kw)
    assert (a / "synth.json").read_text() == (b / "synth.json").read_text()
    assert (a / "synth.json").read_text() != (c / "synth.json").read_text()
    name = _manifest(a)["views"][0]["name"]
    assert (a / "images" / name).read_bytes() == (b / "images" / name).read_bytes()
    assert (a / "proxy.obj").read_bytes() == (b / "proxy.obj").read_bytes()
    assert (a / "ground_truth" / "maps" / "wall00.png").read_bytes() == (
        b / "ground_truth" / "maps" / "wall00.png"
    ).read_bytes()


def test_building_styles_have_sane_proxies():
    """Every style gives 6-40 planar polygons whose outward normals point away from the building."""
    from difftex.synth.buildings import make_building
    from difftex.synth.presets import BuildingSpec

    for style in ("box", "gable", "lshape", "tower", "courtyard"):
        b = make_building(BuildingSpec(style, style, 30.0, 22.0, 12.0), np.random.default_rng(0))
        assert 6 <= len(b.faces) <= 40, style
        for f in b.faces:
            n = f.normal
            np.testing.assert_allclose(np.cross(f.a, f.b), n, atol=1e-9)
            # outward: a point just outside the face is not inside the footprint volume
            import shapely

            c = f.outer.mean(0) + 0.05 * n
            inside = b.footprint.contains(shapely.Point(c[:2])) and c[2] < f.outer[:, 2].max() - 1e-6 and c[2] > 0
            if f.kind == "wall":
                assert not inside or f.outer[:, 2].min() > 0, f"{style} {f.id} normal points inwards"
            else:
                assert n[2] > 0.3, f"{style} {f.id}"


def test_cli_rejects_bad_values(tmp_path, capsys):
    from difftex.cli import main

    assert main(["synth", "--out", str(tmp_path / "x"), "--views", "0", "--quiet"]) == 2
    assert "views" in capsys.readouterr().err
    with pytest.raises(DifftexError):
        get_preset("nope")


def _gt_map_twice(cfg, long_side: int = 64) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A ground-truth map (tiny preset's building, its first wall) rendered with two render seeds,
    as the generator renders it (``render_gt_map``); sRGB, and the texel mask."""
    from difftex.geometry.frames import texel_mask, uv_frame
    from difftex.scene.proxy import Polygon
    from difftex.synth import render as rd
    from difftex.synth.pipeline import build_model, render_gt_map

    spec = cfg.buildings[0]
    variant = rd.choose_variant(cfg.variant)
    building, _, _, model, ground, ground_size, lighting, _, _ = build_model(cfg, spec, 0, 0)
    scene = rd.build_scene(variant, model, ground, ground_size, lighting, occluders=False)
    face = building.walls[0]
    poly = Polygon(id=face.id, outer=face.outer.copy())
    frame = uv_frame(poly, up=np.array([0.0, 0.0, 1.0]), long_side=long_side)
    standoff = model.protrusion[poly.id] + 0.3
    a, b = (rd.to_srgb(render_gt_map(cfg, scene, variant, frame, standoff, seed=s)) for s in (1, 2))
    return a, b, texel_mask(poly, frame)


# A ground-truth map rendered twice with different Monte Carlo seeds differs, in sRGB units, by at
# most this RMS over the polygon's texels and this much at any texel (0.1 % of texels may exceed it:
# grazing relief edges). Measured (tiny preset, walls at 96 texels): ldsampler 256 spp 0.0047-0.0059 RMS,
# max 0.04-0.05; 1024 spp 0.0025-0.0031, max 0.02-0.03; the old independent 16 spp 0.054-0.067, max 0.3-0.37.
# This test's wall at 64 texels (coarser texels, more texture per texel): 0.0066 / 0.043 and 0.066 / 0.23.
GT_RMS_BOUND = 0.01
GT_P999_BOUND = 0.06


def _gt_spread(cfg) -> tuple[float, float]:
    a, b, mask = _gt_map_twice(cfg)
    d = np.abs(a - b)[mask]
    return float(np.sqrt(np.mean(d**2))), float(np.percentile(d, 99.9))


def test_ground_truth_is_converged_across_seeds():
    """With the survey settings (ldsampler, gt_spp 256 as in survey-tiny), two renders of a map
    agree within the bounds: the truth carries no noise a texture could not match."""
    cfg = get_preset("tiny").replace(sampler="ldsampler", gt_spp=get_preset("survey-tiny").gt_spp)
    rms, p999 = _gt_spread(cfg)
    print(f"ground truth, ldsampler {cfg.gt_spp} spp: RMS {rms:.4f}, 99.9 % {p999:.4f}")
    assert rms < GT_RMS_BOUND and p999 < GT_P999_BOUND


def test_old_ground_truth_setting_fails_the_bound():
    """The old setting (independent sampler, 16 spp) is far outside the bound: the test above can fail."""
    cfg = get_preset("tiny").replace(sampler="independent", gt_spp=16)
    rms, p999 = _gt_spread(cfg)
    print(f"ground truth, independent 16 spp: RMS {rms:.4f}, 99.9 % {p999:.4f}")
    assert rms > 3 * GT_RMS_BOUND and p999 > GT_P999_BOUND


@pytest.fixture(scope="session")
def survey_tiny(tmp_path_factory) -> Path:
    from difftex.cli import main

    out = tmp_path_factory.mktemp("synth") / "survey-tiny"
    assert main(["synth", "--preset", "survey-tiny", "--out", str(out), "--seed", "2", "--quiet"]) == 0
    return out


def test_survey_photos_are_camera_jpegs_that_load(survey_tiny):
    """survey-tiny writes JPEG photos named .jpg in the COLMAP model, loads as a scene, records the
    camera model and sampler, and keeps the truth lossless (PNG) and free of the camera's noise."""
    from difftex.scene.loading import load_scene
    from difftex.synth.noise_level import noise_sigma

    man = _manifest(survey_tiny)
    names = [v["name"] for v in man["views"]]
    assert names and all(n.endswith(".jpg") for n in names)
    assert sorted(p.name for p in (survey_tiny / "images").iterdir()) == sorted(names)
    assert (survey_tiny / "images" / names[0]).read_bytes()[:2] == b"\xff\xd8"
    txt = (survey_tiny / "sparse" / "0" / "images.txt").read_text()
    assert all(n in txt for n in names)
    scene = load_scene(survey_tiny)
    assert sorted(p.name for p in scene.photos) == sorted(names)
    r = man["renderer"]
    assert r["sampler"] == "ldsampler" and r["camera_model"]["iso"] > 0 and r["camera_model"]["jpeg_quality"] > 0
    assert r["spp"]["ground_truth_maps"] >= 256
    assert list((survey_tiny / "ground_truth" / "maps").glob("*.png"))
    held = next((survey_tiny / "ground_truth" / "views" / "images").iterdir())
    assert held.suffix == ".png"
    assert noise_sigma(read_image(survey_tiny / "images" / names[0]), tile=16) > 0


def test_survey_preset_lays_out_a_drone_survey():
    """200 photos per building, about 10 at street level, the rest drone orbits looking down; the
    written poses are off by about a pixel (true vs written projection of the building's corners)."""
    from difftex.synth import cameras as cams
    from difftex.synth.buildings import make_building
    from difftex.synth.pipeline import _rngs

    cfg = get_preset("survey")
    assert len(cfg.buildings) == 3 and {b.style for b in cfg.buildings} >= {"lshape", "courtyard"}
    assert (cfg.width, cfg.height, cfg.views) == (800, 600, 200) and cfg.sampler == "ldsampler"
    assert 0.25 <= cfg.relief_depth <= 0.3 and cfg.occluders and cfg.iso > 0 and cfg.jpeg_quality > 0
    spec = cfg.buildings[0]
    rng = _rngs(0, 0, 7)
    building = make_building(spec, rng[0])
    views = cams.make_views(building, cfg.views, cfg.street_fraction, rng[5], prefix="img_", suffix=".jpg",
                            rings=cfg.drone_rings)
    kinds = [v.kind for v in views]
    assert len(views) == 200 and kinds.count("street") == 10
    down = np.degrees(np.arcsin([-v.R[2][2] for v in views if v.kind == "drone"]))  # R[2]: the viewing direction
    assert down.min() > 15 and np.median(down) > 25, np.percentile(down, [0, 50])  # an oblique gimbal
    f = cfg.width / 2 / np.tan(np.deg2rad(65) / 2)
    corners = np.concatenate([face.outer for face in building.faces])
    shifts = []
    for v in views[:60]:
        Rw, tw = cams.perturb(v.R, v.t, cfg.pose_noise_rot_deg, cfg.pose_noise_trans, rng[5])
        a, b = corners @ v.R.T + v.t, corners @ Rw.T + tw
        shifts.append(np.linalg.norm(f * (a[:, :2] / a[:, 2:] - b[:, :2] / b[:, 2:]), axis=1).mean())
    assert 0.6 < np.median(shifts) < 1.6, np.median(shifts)


def test_true_pose_scene_carries_the_poses_the_photos_were_rendered_at(survey_tiny, tmp_path):
    """evaluation/true_poses.py: the scene loads with every photo at synth.json's R_true, t_true
    (the written model has them with pose noise added), and the rest of the scene unchanged."""
    from difftex.scene.loading import load_scene
    from evaluation.true_poses import main as true_poses

    out = tmp_path / "true"
    assert true_poses(["--scene", str(survey_tiny), "--out", str(out)]) == 0
    given, true = load_scene(survey_tiny), load_scene(out)
    views = {v["name"]: v for v in _manifest(survey_tiny)["views"]}
    assert sorted(p.name for p in true.photos) == sorted(views)
    moved = 0.0
    for g, t in zip(sorted(given.photos, key=lambda p: p.name), sorted(true.photos, key=lambda p: p.name)):
        v = views[t.name]
        assert np.allclose(t.R, v["R_true"], atol=1e-9) and np.allclose(t.t, v["t_true"], atol=1e-9)
        assert (g.width, g.height, g.image_path.name) == (t.width, t.height, t.image_path.name)
        moved = max(moved, float(np.abs(g.t - t.t).max()))
    assert moved > 1e-4  # the written poses are the noisy ones
    assert true_poses(["--scene", str(tmp_path / "nowhere"), "--out", str(tmp_path / "x")]) == 2


def test_relief_bound_rebuilds_the_true_height_field(survey_tiny, tmp_path):
    """evaluation/relief_bound.py: the scene's building rebuilt from synth.json gives each wall
    the relief its geometry has (the openings' panes at -relief_depth, what stands in front
    above 0, the plain wall at 0, roofs flat), and the bound runs through variants.py with the
    true field in place of the sweep; a folder without synth.json is one DifftexError."""
    import json

    import difftex.compose.texturing as texturing
    from difftex.errors import DifftexError
    from evaluation.relief_bound import main, synth_model, true_heights, true_relief

    faces, layouts, relief = synth_model(survey_tiny)
    assert relief == _manifest(survey_tiny)["config"]["relief_depth"] > 0
    walls = [f for f in faces.values() if f.kind == "wall"]
    opened = 0
    for face in walls:
        lay = layouts[face.id]
        for u0, v0, u1, v1 in lay.openings():
            centre = face.to3d(np.array([(u0 + u1) / 2, (max(v0, 0.02) + v1) / 2]))
            in_front = true_heights(face, lay, relief, centre[None])[0]
            assert in_front == -relief or in_front > 0  # a pane, or a balcony or course before it
            opened += in_front == -relief
        lo = face.to3d(np.array([-5.0, -5.0]))  # off the wall's rectangle: plane
        assert true_heights(face, lay, relief, lo[None])[0] == 0.0
    assert opened > 0
    roofs = [f for f in faces.values() if f.kind == "roof"]
    pts = np.stack([f.to3d(f.poly2d.mean(0)) for f in roofs])
    assert all(true_heights(f, layouts[f.id], relief, p[None])[0] == 0.0 for f, p in zip(roofs, pts))

    saved = texturing.estimate_relief
    with true_relief(survey_tiny):
        assert texturing.estimate_relief is not saved
    assert texturing.estimate_relief is saved  # restored
    wall = walls[0].id
    out = tmp_path / "bound"
    assert main(["--scene", str(survey_tiny), "--polygons", wall, "--max-long-side", "96",
                 "--density-scale", "3.0", "--out", str(out)]) == 0
    res = json.loads(out.with_suffix(".json").read_text())
    assert set(res["variants"]) == {"defaults", "true relief"}
    # the field changed the mapping (the sweep finds nothing on so few, so small photos)
    assert res["variants"]["true relief"]["ssim"] != res["variants"]["defaults"]["ssim"]
    acc = tmp_path / "acc"
    assert main(["--accuracy", "--scene", str(survey_tiny), "--polygons", wall, "--max-long-side", "96",
                 "--density-scale", "3.0", "--optimize", '{"relief_min_cos": 0.0}', "--out", str(acc)]) == 0
    rows = json.loads(acc.with_suffix(".json").read_text())["rows"]
    assert [r["polygon"] for r in rows] == [wall] and rows[0]["photos"] >= 1
    with pytest.raises(DifftexError, match="synth.json"):
        synth_model(tmp_path)


def test_field_accuracy_counts_found_recesses_and_false_relief():
    """relief_bound.field_accuracy at its extremes: the true field scores 1 / 1 / 0, a flat field
    finds no recess and no false relief, a field off by more than the tolerance is within nowhere."""
    from evaluation.relief_bound import field_accuracy

    true = np.zeros((4, 6), np.float32)
    true[1:3, 1:3] = -0.3
    mask = np.ones_like(true, bool)
    assert field_accuracy(true, true, mask, 0.3, 0.05) == {"within": 1.0, "recess_found": 1.0, "false_relief": 0.0}
    flat = field_accuracy(np.zeros_like(true), true, mask, 0.3, 0.05)
    assert flat == {"within": 20 / 24, "recess_found": 0.0, "false_relief": 0.0}
    off = field_accuracy(true + 0.1, true, mask, 0.3, 0.05)
    assert off["within"] == 0.0 and off["false_relief"] == 1.0 and off["recess_found"] == 1.0
    assert np.isnan(field_accuracy(true, true, np.zeros_like(mask), 0.3, 0.05)["within"])  # no texel: NaN
