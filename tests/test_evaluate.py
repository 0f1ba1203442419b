"""Evaluation: resampling into ground-truth frames, map metrics, held-out renders, scene copies."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from difftex.errors import DifftexError
from difftex.evaluation.evaluate import (
    EvaluateConfig,
    PolygonTexture,
    check_same_plane,
    evaluate_maps,
    resample_texture,
    view_weights,
)
from difftex.evaluation.holdout import prepare_holdout
from difftex.evaluation.views import render_proxy
from difftex.geometry.frames import UVFrame, texel_mask, uv_frame
from difftex.scene.files import write_image, write_json
from difftex.scene.proxy import Polygon

from tests import piq_weights as W
from tests.scenes import make_scene, wall

UP = np.array([0.0, 0.0, 1.0])
SHARED = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"


def linear_texture(frame: UVFrame) -> np.ndarray:
    """Colour = affine function of the world point (bilinear interpolation reproduces it exactly)."""
    tx, ty = frame.centres()
    X = frame.texel_to_world(tx, ty)
    return np.stack([0.1 + 0.2 * (X[..., 0] + 2), 0.1 + 0.3 * X[..., 2], np.full(X.shape[:2], 0.5)], -1).astype(
        np.float32
    )


def poly() -> Polygon:
    return Polygon("front", wall(-2, 2, 0, 2))


def test_resample_same_frame_is_identity():
    f = uv_frame(poly(), UP, long_side=64)
    rng = np.random.default_rng(0)
    tex = rng.random((*f.shape, 3)).astype(np.float32)
    np.testing.assert_allclose(resample_texture(tex, f, f), tex, atol=1e-6)


def test_resample_finer_texture_to_coarse_frame_keeps_affine_colours():
    fine = uv_frame(poly(), UP, long_side=128)
    coarse = uv_frame(poly(), UP, long_side=32)
    out = resample_texture(linear_texture(fine), fine, coarse)
    ref = linear_texture(coarse)
    inner = np.zeros(coarse.shape, bool)
    inner[2:-2, 2:-2] = True  # edge texels clamp
    np.testing.assert_allclose(out[inner], ref[inner], atol=2e-3)


def test_resample_into_a_mirrored_frame():
    f = uv_frame(poly(), UP, long_side=64)
    # same rectangle, e_u reversed (and the normal kept: e_v reversed too, a 180 degree turn)
    g = UVFrame(
        origin=f.origin + f.e_u * f.width * f.texel_size + f.e_v * f.height * f.texel_size,
        e_u=-f.e_u,
        e_v=-f.e_v,
        normal=f.normal,
        texel_size=f.texel_size,
        width=f.width,
        height=f.height,
    )
    rng = np.random.default_rng(1)
    tex = rng.random((*f.shape, 3)).astype(np.float32)
    np.testing.assert_allclose(resample_texture(tex, f, g), tex[::-1, ::-1], atol=1e-5)


def test_check_same_plane_rejects_other_planes():
    f = uv_frame(poly(), UP, long_side=64)
    check_same_plane(f, f, "x")
    moved = UVFrame(f.origin + 0.5 * f.normal, f.e_u, f.e_v, f.normal, f.texel_size, f.width, f.height)
    with pytest.raises(DifftexError, match="off difftex's plane"):
        check_same_plane(f, moved, "x")
    flipped = UVFrame(f.origin, -f.e_u, f.e_v, -f.normal, f.texel_size, f.width, f.height)
    with pytest.raises(DifftexError, match="normal"):
        check_same_plane(f, flipped, "x")


def test_dominant_photos_come_back_from_source_npz_not_from_colours(tmp_path):
    """The evaluation reads each texel's dominant photo from source.npz (numbers), whatever
    colours source.png uses; texels no photo saw, or outside the polygon, have none."""
    from difftex.compose.outputs import write_texture_outputs

    names = ["a.jpg", "b.jpg", "c.jpg"]
    frame = uv_frame(poly(), UP, long_side=30)
    dom = np.random.default_rng(2).integers(-1, 3, frame.shape)
    mask = texel_mask(poly(), frame)
    seen = mask & (dom >= 0)
    write_texture_outputs(
        tmp_path / "t", np.zeros((*frame.shape, 3), np.float32), mask, seen, dom, names, {"method": "frontal"}
    )
    pt = PolygonTexture("front", np.zeros((*frame.shape, 3)), frame, mask, {"method": "frontal"}, tmp_path / "t")
    got_names, w, how = view_weights(pt, tmp_path)
    assert got_names == names and how == "dominant photo (source.npz)"
    np.testing.assert_array_equal(w.argmax(0)[seen], dom[seen])
    assert (w.sum(0)[~seen] == 0).all() and (w.sum(0)[seen] == 1).all()


def gt_folder(root: Path, frame: UVFrame, gt: np.ndarray, mask: np.ndarray) -> Path:
    write_image(root / "ground_truth" / "maps" / "front.png", gt)
    write_image(root / "ground_truth" / "masks" / "front.png", mask.astype(np.float32))
    write_json(root / "ground_truth" / "frames" / "front.json", frame.to_dict())
    return root


@pytest.mark.parametrize("offset", [0.0, 0.1])
def test_map_metrics_known_answers(tmp_path, offset):
    frame = uv_frame(poly(), UP, long_side=64)
    mask = texel_mask(poly(), frame)
    gt = np.round(linear_texture(frame) * 255) / 255  # exactly representable in the 8-bit PNG
    gt_folder(tmp_path, frame, gt, mask)
    tex = PolygonTexture("front", np.clip(gt + offset, 0, 1), frame, mask, {"coverage": 1.0}, tmp_path)
    res = evaluate_maps(tmp_path, {"front": tex}, EvaluateConfig(lpips="none"))
    o = res["overall"]
    # a constant offset d in every channel is a per-texel error of d sqrt(3), at every percentile
    assert o["error90"] == pytest.approx(offset * math.sqrt(3), abs=1e-5)
    assert o["error95"] == pytest.approx(offset * math.sqrt(3), abs=1e-5)
    if offset == 0:
        assert o["ssim"] == pytest.approx(1.0, abs=1e-9) and o["psnr"] > 100  # float32 round trip only
    else:
        assert o["psnr"] == pytest.approx(20.0, abs=1e-3)  # MSE 0.01


def test_map_metrics_lpips_column_says_what_made_it(tmp_path, monkeypatch, caplog):
    from difftex.evaluation import metrics

    frame = uv_frame(poly(), UP, long_side=64)
    mask = texel_mask(poly(), frame)
    gt = np.round(linear_texture(frame) * 255) / 255
    gt_folder(tmp_path, frame, gt, mask)
    for kind in ("maps", "masks"):  # a second polygon with the same ground truth
        (tmp_path / "ground_truth" / kind / "back.png").write_bytes(
            (tmp_path / "ground_truth" / kind / "front.png").read_bytes()
        )
    write_json(tmp_path / "ground_truth" / "frames" / "back.json", frame.to_dict())
    tex = PolygonTexture(
        "front", np.clip(gt + 0.05 * np.sin(np.arange(gt.shape[1]))[None, :, None], 0, 1), frame, mask, {}, tmp_path
    )
    textures = {"front": tex, "back": tex}
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "torch"))  # no classic LPIPS weights here
    o = evaluate_maps(tmp_path, textures, EvaluateConfig(lpips="lpips"))["overall"]
    assert o["lpips"] is None and o["lpips_variant"].startswith(
        "unavailable: classic LPIPS (piq) needs lpips_weights.pt and vgg16-397923af.pth in "
    )
    assert caplog.text.count("unavailable") == 1  # once per evaluation, not per polygon
    o = evaluate_maps(tmp_path, textures, EvaluateConfig(lpips="none"))["overall"]
    assert (o["lpips"], o["lpips_variant"]) == (None, "none")
    if metrics.lpips_source("stlpips")[0] is not None:  # auto falls back to ST-LPIPS and says so, in one line
        caplog.clear()
        o = evaluate_maps(tmp_path, textures, EvaluateConfig(lpips="auto"))["overall"]
        assert o["lpips"] > 0 and o["lpips_variant"].startswith("ST-LPIPS (stlpips-pytorch")
        notes = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
        assert len(notes) == 1 and notes[0].startswith("LPIPS (auto): classic LPIPS (piq) needs"), notes
        assert "reporting ST-LPIPS instead" in notes[0] and "\n" not in notes[0]
    # with the two weight files in a configured folder: classic LPIPS through piq, no note
    folder = W.write_piq_weights(tmp_path / "weights")
    caplog.clear()
    for variant in ("auto", "lpips"):
        res = evaluate_maps(tmp_path, textures, EvaluateConfig(lpips=variant, lpips_weights=str(folder)))
        o = res["overall"]
        assert o["lpips_variant"].startswith("LPIPS (piq 0.8.0, VGG16: torchvision ImageNet weights")
        assert math.isfinite(o["lpips"]) and o["lpips"] > 0
        assert all(math.isfinite(r["lpips"]) for r in res["polygons"])
    assert not [r for r in caplog.records if r.levelname == "WARNING"]
    assert not (tmp_path / "torch").exists()  # nothing was downloaded


def test_evaluate_command_passes_the_lpips_weights_folder(tmp_path, monkeypatch, capsys):
    import difftex.evaluation.evaluate as ev
    from difftex.cli import main

    seen = {}

    def fake_evaluate(scene, results, cfg, out_dir=None, progress=True):
        seen["cfg"] = cfg
        return {"time_s": 0.0}

    monkeypatch.setattr(ev, "evaluate_results", fake_evaluate)
    monkeypatch.setattr(ev, "summary_line", lambda res: "")
    monkeypatch.setattr(ev, "to_json", lambda res: res)
    cfg = tmp_path / "c.yaml"
    cfg.write_text("evaluate: {lpips: lpips, lpips_weights: /from/config}\n")
    argv = ["evaluate", "--scene", str(tmp_path), "--results", str(tmp_path), "--out", str(tmp_path / "m.json")]
    assert main([*argv, "--config", str(cfg)]) == 0
    assert (seen["cfg"].lpips, seen["cfg"].lpips_weights) == ("lpips", "/from/config")
    assert main([*argv, "--config", str(cfg), "--lpips-weights", str(tmp_path / "w")]) == 0
    assert seen["cfg"].lpips_weights == str(tmp_path / "w")


def test_map_metrics_at_another_resolution_resample_first(tmp_path):
    gframe = uv_frame(poly(), UP, long_side=32)
    mask = texel_mask(poly(), gframe)
    gt_folder(tmp_path, gframe, linear_texture(gframe), mask)
    fine = uv_frame(poly(), UP, long_side=128)
    tex = PolygonTexture("front", linear_texture(fine), fine, texel_mask(poly(), fine), {}, tmp_path)
    o = evaluate_maps(tmp_path, {"front": tex}, EvaluateConfig(lpips="none"))["overall"]
    assert o["error90"] < 0.01  # only 8-bit rounding of the ground truth and clamped edge texels


def test_render_proxy_reproduces_the_texture_at_each_pixel(tmp_path):
    from difftex.scene.loading import load_scene

    root = make_scene(tmp_path / "s", size=(96, 72))
    sc = load_scene(root)
    pol = sc.proxy.polygons[0]
    frame = uv_frame(pol, sc.up, long_side=256)
    tex = PolygonTexture(pol.id, linear_texture(frame), frame, texel_mask(pol, frame), {}, tmp_path)
    ph = sc.photos[1]
    img, ids, textured = render_proxy(ph, sc.proxy, {pol.id: tex})
    assert textured.sum() > 500 and (textured == (ids == 0)).all()
    # independent answer: the pixel ray meets the wall plane y = 0 at X; colour is affine in X
    ys, xs = np.nonzero(textured)
    d = ph.unproject(np.stack([xs + 0.5, ys + 0.5], -1))
    C = ph.center
    X = C + (-C[1] / d[:, 1])[:, None] * d
    want = np.stack([0.1 + 0.2 * (X[:, 0] + 2), 0.1 + 0.3 * X[:, 2], np.full(len(X), 0.5)], -1)
    inner = (X[:, 0] > -1.98) & (X[:, 0] < 1.98) & (X[:, 2] > 0.02) & (X[:, 2] < 1.98)
    np.testing.assert_allclose(img[ys, xs][inner], want[inner], atol=1e-3)


def test_prepare_holdout_removes_the_photos_from_the_model(tmp_path):
    from difftex.scene.loading import load_scene

    root = make_scene(tmp_path / "s", centers=((0, -6, 1), (2, -6, 1.5), (-2, -5, 0.5), (1, -7, 1)))
    info = prepare_holdout(root, 1, tmp_path / "copy")
    assert len(info["held_out"]) == 1 and info["held_out"][0] not in info["kept"]
    sc = load_scene(tmp_path / "copy")
    assert sorted(p.name for p in sc.photos) == info["kept"] and len(sc.photos) == 3
    orig = {p.name: p for p in load_scene(root).photos}
    for p in sc.photos:  # poses survive the copy
        np.testing.assert_allclose(p.R, orig[p.name].R, atol=1e-12)
    info2 = prepare_holdout(root, ["img00.png", "img03.png"], tmp_path / "copy2")
    assert info2["kept"] == ["img01.png", "img02.png"]
    with pytest.raises(DifftexError, match="not in the scene"):
        prepare_holdout(root, ["nope.png"], tmp_path / "copy3")
    with pytest.raises(DifftexError):
        prepare_holdout(root, 4, tmp_path / "copy4")


@pytest.mark.skipif(not (SHARED / "lund-door").is_dir(), reason="shared real scenes not present")
def test_prepare_holdout_on_a_real_scene_keeps_tracks_consistent(tmp_path):
    from difftex.scene.camera import read_reconstruction

    info = prepare_holdout(SHARED / "lund-door", 2, tmp_path / "copy")
    rec = read_reconstruction(tmp_path / "copy" / "sparse" / "0")
    names = {im.name for im in rec.images.values()}
    assert names == set(info["kept"]) and len(names) == 10
    assert rec.num_points3D() > 1000


def test_textured_obj_reads_back_into_the_uv_frames(tmp_path):
    """texrecon's output is read back with import_obj; difftex's own assembled OBJ is a known answer."""
    from difftex.evaluation.peers.texrecon import import_obj
    from difftex.export.assemble import AssembleConfig, assemble
    from difftex.export.assemble import PolygonTexture as AT

    p = poly()
    frame = uv_frame(p, UP, long_side=64)
    mask = texel_mask(p, frame)
    tex = linear_texture(frame)
    assemble([AT(p, frame, tex, mask, 1.0, 1)], tmp_path / "m", AssembleConfig(glb=False, verify=False, padding=2))
    got, cov = import_obj(tmp_path / "m" / "model.obj", {p.id: frame}, {p.id: mask})[p.id]
    assert cov[mask].all()
    np.testing.assert_allclose(got[mask], tex[mask], atol=2.5 / 255)  # 8-bit atlas


def test_texrecon_cam_file_encodes_the_camera(tmp_path):
    from difftex.evaluation.peers.texrecon import cam_file_text
    from difftex.scene.loading import load_scene

    ph = load_scene(make_scene(tmp_path / "s", size=(96, 72))).photos[0]
    l1, l2 = [list(map(float, ln.split())) for ln in cam_file_text(ph).splitlines()]
    np.testing.assert_allclose(l1[:3], ph.t, atol=1e-9)
    np.testing.assert_allclose(np.reshape(l1[3:], (3, 3)), ph.R, atol=1e-9)
    K = ph.K()
    assert (
        l2[0] * 96 == pytest.approx(K[0, 0])
        and l2[4] * 96 == pytest.approx(K[0, 2])
        and l2[5] * 72 == pytest.approx(K[1, 2])
    )


@pytest.mark.slow
def test_evaluate_command_on_a_held_out_scene_copy(tmp_path):
    """Scene copy without one photo -> visibility -> a baseline -> difftex evaluate (views + Q metrics)."""
    import json

    from difftex.cli import main

    root = make_scene(tmp_path / "s", centers=((0, -6, 1), (2, -6, 1.5), (-2, -5, 0.5), (1, -7, 1)))
    prepare_holdout(root, ["img01.png"], tmp_path / "copy")
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text(
        "texture: {long_side: 32}\nvisibility: {min_texels: 4}\ncompute: {device: cpu}\nevaluate: {lpips: none, "
        "render_long_side: 96}\n"
    )
    R = tmp_path / "R"
    assert (
        main(
            [
                "visibility",
                "--quiet",
                "--scene",
                str(tmp_path / "copy"),
                "--config",
                str(cfg),
                "--out-dir",
                str(R / "visibility"),
            ]
        )
        == 0
    )
    assert (
        main(
            [
                "baseline",
                "--scene",
                str(tmp_path / "copy"),
                "--visibility",
                str(R / "visibility" / "front.npz"),
                "--config",
                str(cfg),
                "--method",
                "frontal",
                "--out-dir",
                str(R / "textures" / "front"),
            ]
        )
        == 0
    )
    out = R / "evaluation" / "metrics.json"
    assert (
        main(
            [
                "evaluate",
                "--quiet",
                "--scene",
                str(tmp_path / "copy"),
                "--results",
                str(R),
                "--config",
                str(cfg),
                "--out",
                str(out),
            ]
        )
        == 0
    )
    m = json.loads(out.read_text())
    assert m["views"]["held_out"] == ["img01.png"] and m["views"]["overall"]["views"] == 1
    assert m["views"]["views"][0]["compared_pixels"] > 100
    # the photos are noise and the texture comes from other noise photos: no structure in common
    assert -0.2 < m["views"]["overall"]["ssim"] < 0.3
    assert 0 < m["perspective"]["q_front"] <= 1 and m["perspective"]["polygons"]["front"]["q_source"].startswith(
        "dominant"
    )
    assert (R / "evaluation" / "views" / "img01_render.png").is_file()
    # a bad scene is one line naming it
    assert main(["evaluate", "--scene", str(tmp_path / "nope"), "--results", str(R), "--out", str(out)]) == 2


def test_side_by_side_takes_pngs_in_the_ground_truth_frame(tmp_path):
    """evaluation/side_by_side.py: a PNG run (variants.py --textures) is cropped as it is, beside the
    truth; a PNG of another size is one clear line, not a traceback."""
    from difftex.scene.files import read_image
    from evaluation.side_by_side import main as side_by_side

    frame = UVFrame(np.zeros(3), np.array([1.0, 0, 0]), np.array([0, 0, -1.0]), np.array([0, -1.0, 0]), 0.1, 40, 20)
    gt = tmp_path / "scene" / "ground_truth"
    write_json(gt / "frames" / "wall.json", frame.to_dict())
    truth = np.zeros((20, 40, 3), np.float32)
    truth[:, 20:] = 1.0
    write_image(gt / "maps" / "wall.png", truth)
    variant = np.full((20, 40, 3), 0.5, np.float32)
    write_image(tmp_path / "v.png", variant)
    out = tmp_path / "sbs.png"
    assert side_by_side(["--scene", str(tmp_path / "scene"), "--run", f"variant={tmp_path / 'v.png'}",
                         "--polygon", "wall", "--crop", "0.25,0,1,1", "--max-width", "200", "--out", str(out)]) == 0
    img = read_image(out)
    assert img.shape[1] <= 200 and img.shape[0] > 22  # two crops of 30x20 texels under their labels
    tile = img[22:, : (img.shape[1] - 6) // 2]
    assert np.allclose(tile, 0.5, atol=0.01)  # the variant as it is, no resampling
    right = img[22:, img.shape[1] - (img.shape[1] - 6) // 2 :]
    assert right[:, -1].min() > 0.99  # the truth's white half, cropped the same way
    write_image(tmp_path / "small.png", variant[:10])
    with pytest.raises(SystemExit, match="not the ground-truth frame's 40x20"):
        side_by_side(["--scene", str(tmp_path / "scene"), "--run", f"small={tmp_path / 'small.png'}",
                      "--polygon", "wall", "--out", str(tmp_path / "x.png")])


def test_evaluation_script_names_bad_input_in_one_line(tmp_path):
    """An evaluation script run as a command: a --run folder without textures (DifftexError deep in
    difftex) ends in one line that names the script and the folder, exit status 1, no traceback."""
    import subprocess
    import sys

    root = Path(__file__).resolve().parents[1]
    p = subprocess.run(
        [sys.executable, str(root / "evaluation" / "side_by_side.py"), "--scene", str(tmp_path), "--run",
         f"a={tmp_path / 'empty'}", "--polygon", "wall", "--out", str(tmp_path / "x.png")],
        capture_output=True, text=True,
    )
    assert p.returncode == 1 and "Traceback" not in p.stderr, p.stderr
    lines = p.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("side_by_side: ") and "no textures/ folder" in lines[0]
    assert not (tmp_path / "x.png").exists()


def test_side_by_side_of_a_held_out_view_crops_each_rendering_beside_the_photo(tmp_path):
    """evaluation/side_by_side.py --view: every run's rendering into the held-out camera, cropped
    the same way, then the held-out photo; a run without that rendering is one clear line."""
    from difftex.scene.files import read_image
    from evaluation.side_by_side import main as side_by_side

    runs = []
    for name, value in (("a", 0.2), ("b", 0.8)):
        views = tmp_path / name / "evaluation" / "views"
        write_image(views / "IMG_1_render.png", np.full((30, 40, 3), value, np.float32))
        write_image(views / "IMG_1_photo.png", np.ones((30, 40, 3), np.float32))
        runs += ["--run", f"{name}={tmp_path / name}"]
    out = tmp_path / "views.png"
    assert side_by_side(["--scene", str(tmp_path), "--view", "IMG_1", *runs, "--crop", "0,0,0.5,1",
                         "--max-width", "200", "--out", str(out)]) == 0
    img = read_image(out)
    w = (img.shape[1] - 2 * 6) // 3  # three crops of 20x30 pixels: a, b, the photo
    assert img.shape[1] <= 200 and np.allclose(img[22:, :w], 0.2, atol=0.01)
    assert np.allclose(img[22:, w + 6 : 2 * w + 6], 0.8, atol=0.01) and img[22:, -w:].min() > 0.99
    with pytest.raises(SystemExit, match="no rendering of view 'IMG_2'"):
        side_by_side(["--scene", str(tmp_path), "--view", "IMG_2", *runs, "--out", str(out)])
    assert side_by_side(["--scene", str(tmp_path), "--view", "IMG_1.JPG", *runs, "--out", str(out)]) == 0
    with pytest.raises(SystemExit, match="--polygon .* or --view"):
        side_by_side(["--scene", str(tmp_path), *runs, "--out", str(out)])
