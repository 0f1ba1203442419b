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
