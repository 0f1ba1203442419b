"""The optimizer on the analytic wall (tests/analytic.py): occluders, pose errors, numerics,
compiled vs eager, the stage command, ablation switches."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch
from scipy.ndimage import binary_dilation, binary_erosion

from difftex.geometry.frames import level_sides, map_texels, sample_photo
from difftex.method.config import OptimizeConfig
from difftex.method.loop import photo_weight

from analytic import (
    UP,
    fast_cfg,
    gt_texture,
    make_input,
    make_photo,
    occluded_region,
    optimize,
    paint_occluder,
    photo_masks,
    render,
    wall,
    write_scene,
)

torch.set_num_threads(1)  # the CI machine has 2 shared cores; intra-op threads only contend

# ------------------------------------------------------------------------------------------


def test_level_sides():
    assert level_sides(2048, 256, True) == [256, 512, 1024, 2048]
    assert level_sides(600, 256, True) == [256, 600]  # 512 is within sqrt 2 of 600: left out
    assert level_sides(912, 64, True) == [64, 128, 256, 512, 912]
    assert level_sides(912, 64, True, step=4) == [64, 256, 912]
    assert level_sides(1100, 64, True, step=4) == [64, 256, 1100]  # 1024 is within 2x of 1100
    with pytest.raises(ValueError):
        level_sides(912, 64, True, step=1.0)
    assert level_sides(200, 256, True) == [200]
    assert level_sides(2048, 256, False) == [2048]


def test_config_rejects_unknown_and_bad_values():
    from difftex.errors import DifftexError

    with pytest.raises(DifftexError, match="unknown key"):
        OptimizeConfig.from_dict({"alpah": 1})
    with pytest.raises(DifftexError, match="loss_mode"):
        OptimizeConfig.from_dict({"loss_mode": "nvdiffrast"})
    with pytest.raises(DifftexError, match="resolution_reference"):
        OptimizeConfig.from_dict({"resolution_reference": "texel"})
    with pytest.raises(DifftexError, match="resolution_weight"):
        OptimizeConfig.from_dict({"resolution_weight": -1})
    cfg = OptimizeConfig.from_dict({"max_iters_per_level": [5, 3], "betas": [0.8, 0.9]})
    assert cfg.cap(0) == 5 and cfg.cap(7) == 3 and cfg.betas == (0.8, 0.9)


@pytest.mark.parametrize("mode", ["texel", "render"])
def test_single_frontal_photo_gives_the_rectified_photo(mode):
    ph = make_photo("a", 0.0)
    img = render(ph)
    # 128 texels over 4 m: a texel (3.1 cm) is smaller than a pixel (4 cm), so level 0 is sampled
    inp = make_input([ph], [img], long_side=128)
    if mode == "render":
        from difftex.geometry.visibility import id_buffer  # noqa: F401  (only the masks are needed)

        inp.a_bbox, inp.a_masks = photo_masks(inp)
    # one sample per texel (supersample 1): the rectified photo is the photo read at the texel
    # centres (test_sampling checks the 2 x 2 sub-samples against the wall itself)
    res = optimize(inp, fast_cfg(loss_mode=mode, supersample=1))
    m = map_texels(inp.frame, ph)
    rect = sample_photo(img, m.pix)
    ok = inp.texel_visible[0]
    assert res.stats["coverage"] == 1.0
    assert np.abs(res.U[ok] - rect[ok]).max() < 3e-3  # float16 photo storage
    assert np.allclose(photo_weight(res.idx, res.W, 0)[inp.texel_mask], 1.0)


def test_two_photos_occluded_pixels_are_not_used():
    # With two photos a disagreement is symmetric per texel; the prior (frontality, L_Persp)
    # decides, so the occluded photo here is the more oblique one. See the three-photo test
    # for occlusion found by colour consistency alone.
    clean, occl = make_photo("clean", -8.0), make_photo("occl", 30.0)
    imgs = [render(clean), paint_occluder(occl, render(occl))]
    inp = make_input([clean, occl], imgs, long_side=64)
    res = optimize(inp, fast_cfg())
    reg = occluded_region(inp) & inp.texel_visible.all(0)
    assert photo_weight(res.idx, res.W, 1)[reg].mean() < 0.1
    err = np.abs(res.U - gt_texture(inp)).mean(-1)[reg].mean()
    assert err < 0.05


def test_three_photos_occluder_in_the_most_frontal_photo_is_rejected():
    front, left, right = make_photo("front", 0.0), make_photo("left", -30.0), make_photo("right", 30.0)
    imgs = [paint_occluder(front, render(front)), render(left), render(right)]
    inp = make_input([front, left, right], imgs, long_side=64)
    res = optimize(inp, fast_cfg())
    vis = inp.texel_visible.all(0)
    reg = occluded_region(inp) & vis
    w_front = photo_weight(res.idx, res.W, 0)
    assert w_front[reg].mean() < 0.1  # not used where occluded
    outside = vis & ~occluded_region(inp)
    # but still the main source elsewhere (the most frontal; the photos agree there, so the
    # texels keep their Q blend: 1 : cos 30 : cos 30)
    shares = [photo_weight(res.idx, res.W, n)[outside].mean() for n in range(3)]
    assert shares[0] > 0.34 and shares[0] > max(shares[1:])
    err = np.abs(res.U - gt_texture(inp)).mean(-1)[reg].mean()
    assert err < 0.05


def test_settled_texels_keep_their_blend_and_run_no_iterations():
    # three photos that agree (flat wall, same exposure): nothing to decide but at the border,
    # where a texel's footprint reaches past the wall; the rest keeps its Q-proportional blend
    photos = [make_photo(f"p{i}", yaw) for i, yaw in enumerate((-20.0, 0.0, 20.0))]
    inp = make_input(photos, [render(ph, kind="flat") for ph in photos], long_side=64)
    res = optimize(inp, fast_cfg(settle_sigma=3.0, align=False))
    assert all(lv["settled_share"] > 0.95 for lv in res.stats["levels"])
    m = inp.texel_mask & inp.texel_visible.all(0)
    neff = 1.0 / (res.W**2).sum(0)[m]
    assert np.percentile(neff, 10) > 2.5  # a blend of the three (Q_a 0.94-1), not a selection
    plain = optimize(inp, fast_cfg(align=False, settle_sigma=0.0))  # the optimization alone narrows it down
    assert np.median(1.0 / (plain.W**2).sum(0)[m]) < np.median(neff)


def test_settling_leaves_the_occluder_to_the_optimization():
    front, left, right = make_photo("front", 0.0), make_photo("left", -30.0), make_photo("right", 30.0)
    imgs = [paint_occluder(front, render(front)), render(left), render(right)]
    inp = make_input([front, left, right], imgs, long_side=64)
    res = optimize(inp, fast_cfg(settle_sigma=3.0))
    last = res.stats["levels"][-1]
    assert 0.0 < last["settled_share"] < 1.0 and last["iterations"] > 0
    reg = occluded_region(inp) & inp.texel_visible.all(0)
    assert photo_weight(res.idx, res.W, 0)[reg].mean() < 0.1  # the occluded photo is not used there
    assert np.abs(res.U - gt_texture(inp)).mean(-1)[reg].mean() < 0.05


def test_occluders_in_every_texel_are_not_taken_for_noise():
    # five photos, each occluded over two fifths of the wall (photo i over fifths i and i+1,
    # cyclically): every texel has two occluded photos of five. The mean-based noise (RMS
    # distance to the mean) measured the occluders (sigma_c 0.29 and 0.28 against 0.02 without
    # them), so every texel settled and the occluders kept their Q share of the blend (0.16 on
    # average where occluded, mean error 0.114). The median-based sigma_c stays near the noise
    # (0.077 and 0.046): measured 0.075 occluded share, mean error 0.092.
    from analytic import WALL_H, WALL_W

    photos = [make_photo(f"p{i}", yaw) for i, yaw in enumerate((-24.0, -12.0, 0.0, 12.0, 24.0))]
    band = WALL_W / len(photos)

    def occlude(i, img):
        for b in (i, (i + 1) % len(photos)):
            img = paint_occluder(photos[i], img, box=(b * band, (b + 1) * band, -1.0, WALL_H + 1.0), grow=0.05)
        return img

    inp = make_input(photos, [occlude(i, render(ph)) for i, ph in enumerate(photos)], long_side=64)
    res = optimize(inp, fast_cfg(settle_sigma=3.0, align=False))
    assert all(lv["noise"] < 0.1 for lv in res.stats["levels"])
    tx, ty = inp.frame.centres()
    x = inp.frame.texel_to_world(tx, ty)[..., 0]
    vis = inp.texel_mask & inp.texel_visible.all(0)

    def inside(b):
        return (x > b * band + 0.1) & (x < (b + 1) * band - 0.1)

    shares = [
        photo_weight(res.idx, res.W, i)[vis & (inside(i) | inside((i + 1) % len(photos)))].mean()
        for i in range(len(photos))
    ]
    assert np.mean(shares) < 0.1  # a blend would give each its Q share, 0.2


def test_pose_error_photo_loses_weight_unless_aligned():
    names = ["a", "b", "c", "d"]
    yaws, pitches = [-12.0, 12.0, -4.0, 4.0], [6.0, 6.0, -6.0, -6.0]
    photos = [make_photo(n, y, pitch_deg=p) for n, y, p in zip(names, yaws, pitches)]
    imgs = [render(ph) for ph in photos]
    # photo "d" gets a 2 px pose error: a rotation of 2/f rad about its camera y axis
    bad = photos[3]
    ang = 2.0 / 150.0
    Ry = np.array([[math.cos(ang), 0, math.sin(ang)], [0, 1, 0], [-math.sin(ang), 0, math.cos(ang)]])
    R = Ry @ bad.R
    photos[3] = dataclasses.replace(bad, R=R, t=-R @ bad.center)
    inp = make_input(photos, imgs, long_side=64)
    res = optimize(inp, fast_cfg(align=False))
    m = inp.texel_mask & inp.texel_visible.all(0)
    share = np.array([photo_weight(res.idx, res.W, n)[m].mean() for n in range(4)])
    # reference: the same scene with accurate poses
    inp_ok = make_input([make_photo(n, y, pitch_deg=p) for n, y, p in zip(names, yaws, pitches)], imgs, long_side=64)
    res_ok = optimize(inp_ok, fast_cfg(align=False))
    share_ok = np.array([photo_weight(res_ok.idx, res_ok.W, n)[m].mean() for n in range(4)])
    assert share[3] < 0.5 * share_ok[3]
    assert share[3] < 0.5 * share[:3].mean()
    # aligned, the photo is corrected instead (by about its 2 px) and keeps its weight (four
    # photos: fewer than the defaults' align_min_photos, so with the fit's earlier settings)
    res = optimize(inp, fast_cfg(align=True, align_min_photos=0, align_gauge="median", align_robust=3.0,
                                 align_prior_px=2.0, align_model="translation"))
    shift = res.stats["corrections"]["d"]["params"][:2]
    assert 1.0 < abs(shift[0]) < 3.0
    share_al = np.array([photo_weight(res.idx, res.W, n)[m].mean() for n in range(4)])
    assert share_al[3] > 0.5 * share_ok[3]


@pytest.mark.parametrize("case", ["single", "flat", "grazing", "tau"])
def test_numerics_stay_finite(case):
    kind = "flat" if case == "flat" else "checker"
    if case == "single":
        photos = [make_photo("a", 20.0)]
    elif case == "grazing":
        photos = [make_photo("a", 87.0, dist=8.0), make_photo("b", -86.0, dist=8.0)]
    else:
        photos = [make_photo("a", -20.0), make_photo("b", 0.0), make_photo("c", 20.0)]
    imgs = [render(ph, kind) for ph in photos]
    inp = make_input(photos, imgs, long_side=48)
    caps = dict(max_iters_per_level=(30, 20, 10))  # finiteness only: few iterations suffice
    cfg = fast_cfg(tau=0.9, **caps) if case == "tau" else fast_cfg(**caps)
    for mode in ("texel", "render"):
        if mode == "render":
            inp.a_bbox, inp.a_masks = photo_masks(inp)
        res = optimize(inp, dataclasses.replace(cfg, loss_mode=mode))
        assert np.isfinite(res.U).all() and np.isfinite(res.W).all()
        for lvl in res.stats["levels"]:
            assert all(np.isfinite(v) for v in lvl["loss"]["total"])
        seen = inp.texel_mask & inp.texel_visible.any(0)
        # every texel some photo sees has a source, weights sum to one there
        assert np.allclose(res.W.sum(0)[seen], 1.0, atol=1e-4)
        if case == "flat":
            # border texels blend with the background through the pixel footprint; skip them
            from scipy.ndimage import binary_erosion

            inner = binary_erosion(seen, iterations=2)
            assert np.abs(res.U[inner] - np.array([0.4, 0.5, 0.6])).max() < 0.01


@pytest.mark.parametrize("mode", ["texel", "render"])
def test_compiled_objective_matches_eager(mode):
    """compile=on gives the eager weights up to float tolerance (or falls back to eager with
    a recorded reason where inductor cannot build, e.g. no C++ compiler). Four photos and
    top_k 3 exercise the per-texel slot matching of L_Para, not only the fixed layout."""
    photos = [make_photo("a", -20.0), make_photo("b", 5.0), make_photo("c", 25.0), make_photo("d", -3.0, pitch_deg=8.0)]
    imgs = [render(ph) for ph in photos]
    inp = make_input(photos, imgs, long_side=32)
    if mode == "render":
        inp.a_bbox, inp.a_masks = photo_masks(inp)
    cfg = fast_cfg(top_k=3, loss_mode=mode, max_iters_per_level=(25,), min_iters_per_level=25, coarse_to_fine=False)
    eager = optimize(inp, cfg, compile="off")
    comp = optimize(inp, cfg, compile="on")
    assert not eager.stats["levels"][0]["compiled"]
    # render: autograd through the compiled objective; texel: the written-out gradient compiled
    assert comp.stats["levels"][0]["compiled"] or "compile_failed" in comp.stats
    # Adam's steps on the logits (lr 0.1) carry float rounding further than on the weights
    assert np.abs(comp.W - eager.W).max() < 2e-3
    assert np.abs(comp.U - eager.U).max() < 1e-4


def test_auto_compile_only_large_cpu_levels():
    """compile=auto: eager below compile_min_slots and on CUDA (where compiling costs more than
    a level's iterations), compiled for a large CPU level; on and off are what they say."""
    from types import SimpleNamespace

    from difftex.method.config import ComputeConfig
    from difftex.method.objective import compiled_objective

    class Idx:
        def __init__(self, n, cuda):
            self.n, self.is_cuda = n, cuda

        def numel(self):
            return self.n

    cfg = OptimizeConfig()
    auto = ComputeConfig(compile="auto", compile_min_slots=1000)
    sizes = ((1000, False), (999, False), (10**9, True))
    big_cpu, small_cpu, big_cuda = (SimpleNamespace(idx=Idx(n, c)) for n, c in sizes)
    assert compiled_objective(big_cpu, cfg, auto) is not None
    assert compiled_objective(small_cpu, cfg, auto) is None
    assert compiled_objective(big_cuda, cfg, auto) is None
    assert compiled_objective(big_cuda, cfg, ComputeConfig(compile="on")) is not None
    assert compiled_objective(big_cpu, cfg, ComputeConfig(compile="off")) is None


@pytest.mark.gpu
def test_cuda_matches_cpu():
    if not torch.cuda.is_available():
        pytest.skip("no CUDA")
    photos = [make_photo("a", -20.0), make_photo("b", 5.0), make_photo("c", 25.0)]
    imgs = [render(ph) for ph in photos]
    inp = make_input(photos, imgs, long_side=64)
    a = optimize(inp, fast_cfg(), device="cpu")
    b = optimize(inp, fast_cfg(), device="cuda")
    assert np.abs(a.U - b.U).max() < 2e-3
    assert np.abs(a.W - b.W).mean() < 2e-3


# ------------------------------------------------------------------------------------------
# Texture utilities and the command chain


def test_fill_holes_fills_everything_and_keeps_known_texels():
    from difftex.compose.fill import fill_holes

    rng = np.random.default_rng(0)
    img = rng.random((40, 50, 3)).astype(np.float32)
    known = rng.random((40, 50)) > 0.7
    known[:, :20] = False  # a large hole
    out = fill_holes(img * known[..., None], known)
    assert np.array_equal(out[known], (img * known[..., None])[known])
    assert (out[~known] > 0).all() and np.isfinite(out).all()
    assert abs(out[~known].mean() - img[known].mean()) < 0.1  # filled from the neighbours' colours


@pytest.mark.slow
def test_command_chain_on_the_analytic_wall(tmp_path):
    import json

    from difftex.cli import main
    from difftex.scene.files import read_image

    photos = [make_photo("a.png", -15.0), make_photo("b.png", 5.0), make_photo("c.png", 25.0)]
    imgs = [render(ph) for ph in photos]
    imgs[2] = paint_occluder(photos[2], imgs[2])
    scene = tmp_path / "scene"
    write_scene(scene, photos, imgs)
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text(
        "texture:\n  long_side: 64\noptimize:\n  long_side_start: 32\n  max_iters_per_level: [100, 60]\n"
        "compute:\n  device: cpu\n"
    )
    R = tmp_path / "R"
    assert (
        main(["visibility", "--scene", str(scene), "--config", str(cfg), "--out-dir", str(R / "visibility"), "--quiet"])
        == 0
    )
    vis = str(R / "visibility" / "wall.npz")
    common = ["--scene", str(scene), "--visibility", vis, "--config", str(cfg), "--threads", "1"]
    assert main(["texture", *common, "--out-dir", str(R / "opt"), "--png-dir", str(R / "tex"), "--no-progress"]) == 0
    assert main(["baseline", *common, "--method", "average", "--out-dir", str(R / "avg")]) == 0
    stats = json.loads((R / "opt" / "stats.json").read_text())
    assert len(stats["levels"]) == 2 and set(stats["levels"][0]["loss"]) >= {
        "render",
        "ghost",
        "persp",
        "para",
        "total",
    }
    report = json.loads((R / "tex" / "report.json").read_text())
    assert report["coverage"] == 1.0 and report["histogram_matching"]
    tex = read_image(R / "tex" / "texture.png")
    avg = read_image(R / "avg" / "texture.png")
    from difftex.geometry.frames import uv_frame

    frame = uv_frame(wall(), UP, long_side=64)
    inp = make_input(photos, imgs, long_side=64)
    assert inp.frame.shape == frame.shape == tex.shape[:2]
    reg = occluded_region(inp) & inp.texel_visible.all(0)
    gt = gt_texture(inp)
    # the occluder (green) is averaged in by the baseline, not by the optimizer
    assert np.abs(tex - gt).mean(-1)[reg].mean() < 0.5 * np.abs(avg - gt).mean(-1)[reg].mean()
    # a stage given a missing visibility file fails with one line
    assert main(["texture", "--scene", str(scene), "--visibility", str(R / "nope.npz"), "--out-dir", str(R / "x")]) == 2

    # several polygons in one job (the workflow packs small ones): each gets its own files, the
    # photos are decoded once for the job, and the results are those of a job per polygon
    two = ["--scene", str(scene), "--visibility", vis, vis, "--config", str(cfg), "--threads", "1", "--no-progress"]
    done = R / "jobs" / "two.json"
    assert main(["texture", *two, "--out-dir", str(R / "a"), str(R / "b"), "--done", str(done)]) == 0
    assert [p["polygon"] for p in json.loads(done.read_text())["polygons"]] == ["wall", "wall"]
    one = np.load(R / "opt" / "composite.npz")
    for d in ("a", "b"):
        got = np.load(R / d / "composite.npz")
        assert set(got.files) == set(one.files)
        for k in set(one.files) - {"report"}:  # the report holds timings
            assert np.array_equal(got[k], one[k]), k
    assert main(["texture", *two, "--out-dir", str(R / "a")]) == 2  # one folder for two polygons


def test_ablation_switches():
    photos = [make_photo("a", -20.0), make_photo("b", 5.0), make_photo("c", 25.0)]
    imgs = [render(ph) for ph in photos]
    inp = make_input(photos, imgs, long_side=48)
    # no loss term: no iteration, the weights stay the initial Q (normalised)
    res = optimize(inp, fast_cfg(use_render=False, use_persp=False, use_para=False, data_elimination=False))
    assert all(lv["iterations"] == 0 for lv in res.stats["levels"])
    # single level without coarse-to-fine; terms switched off stay at zero in the curves
    res = optimize(inp, fast_cfg(coarse_to_fine=False, use_para=False, ghost=0.0, max_iters_per_level=(30,)))
    assert len(res.stats["levels"]) == 1 and res.stats["levels"][0]["shape"] == list(inp.frame.shape)
    lv = res.stats["levels"][0]
    assert max(lv["loss"]["para"]) == 0 and max(lv["loss"]["ghost"]) == 0 and max(lv["loss"]["persp"]) > 0
    # data elimination off: nothing eliminated or dropped even with an aggressive threshold
    res = optimize(inp, fast_cfg(data_elimination=False, sigma_k=0.1, tau_w=0.01))
    assert res.stats["dropped"] == [] and all(lv["eliminated_pixels"] == 0 for lv in res.stats["levels"])
    res = optimize(inp, fast_cfg(sigma_k=0.1, tau_w=0.01, settle_sigma=0.0))
    assert res.stats["dropped"] and sum(lv["eliminated_pixels"] for lv in res.stats["levels"]) > 0
    assert np.isfinite(res.U).all() and res.stats["coverage"] == 1.0


def test_selection_takes_one_photo_where_the_photos_disagree_and_keeps_the_blend_elsewhere():
    # in one rectangle every photo shows something else (as relief seen from three sides); where
    # the photos agree, the blend averages their noise
    photos = [make_photo("front", 0.0), make_photo("left", -30.0), make_photo("right", 30.0)]
    colours = [(0.7, 0.3, 0.2), (0.2, 0.4, 0.7), (0.3, 0.7, 0.3)]
    imgs = [paint_occluder(ph, render(ph), colour=c, grow=0.0) for ph, c in zip(photos, colours)]
    inp = make_input(photos, imgs, long_side=64)
    blend = optimize(inp, fast_cfg())
    sel = optimize(inp, fast_cfg(select=True, select_feather=0.0))
    reg = binary_erosion(occluded_region(inp), iterations=2) & inp.texel_visible.all(0)
    top = np.max([photo_weight(sel.idx, sel.W, n) for n in range(3)], axis=0)
    assert np.median(top[reg]) > 0.99  # one photo per texel there ...
    picked = np.argmax([photo_weight(sel.idx, sel.W, n)[reg].mean() for n in range(3)])
    assert np.abs(sel.U[reg] - colours[picked]).max() < 0.05  # ... whose colour is not mixed
    assert 0 < sel.stats["selection"]["selected_share"] < 0.5
    # away from the rectangle the photos agree (but for a few texels at the checker's edges):
    # the texture is the blend's
    far = inp.texel_visible.all(0) & ~binary_dilation(occluded_region(inp), iterations=6)
    assert (np.abs(sel.U - blend.U).max(-1)[far] > 1e-3).mean() < 0.02


def test_colour_change_ignores_weights_traded_between_agreeing_photos():
    """Weights moving between two slots of the same colour move no colour: the colour criterion
    (conv_colour) sees a converged texel where the weight criterion does not."""
    import torch

    from difftex.method.level_run import colour_change, weight_change

    K, h, w = 3, 4, 5
    colours = torch.zeros(K, 3, h, w)
    colours[0] = colours[1] = 0.5  # slots 0 and 1 agree
    colours[2] = 0.9
    W_old = torch.zeros(K, h, w)
    W_old[0] = 1.0
    W = torch.zeros(K, h, w)
    W[1] = 1.0  # every texel traded slot 0 for slot 1
    mask = torch.ones(h, w, dtype=torch.bool)
    assert weight_change(W, W_old, mask) == pytest.approx(1.0)
    assert colour_change(W, W_old, colours, mask) == pytest.approx(0.0)
    W2 = torch.zeros(K, h, w)
    W2[2] = 1.0  # to the disagreeing photo: the colour moves by |0.4| in each channel
    assert colour_change(W2, W_old, colours, mask) == pytest.approx(0.4 * 3**0.5, rel=1e-5)
    # settled texels outside the mask count as not moving
    assert colour_change(W2, W_old, colours, mask, q=0.5, fixed_share=0.6) == 0.0
    with pytest.raises(ValueError):
        OptimizeConfig(conv_colour=-1.0)
