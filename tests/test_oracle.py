"""The selection oracle of evaluation/bounds.py (difftex.evaluation.oracle)."""

import math

import pytest
import torch

from difftex.errors import DifftexError
from difftex.evaluation.oracle import blend_oracle, patch_oracle


def _scene(h=24, w=32, seed=0):
    g = torch.Generator().manual_seed(seed)
    ref = torch.rand(3, h, w, generator=g)
    return ref, g


def test_a_texel_takes_the_candidate_that_matches_the_truth_there():
    ref, g = _scene()
    good_left = ref.clone()
    good_left[:, :, 16:] = torch.rand(3, 24, 16, generator=g)  # wrong on the right half
    good_right = ref.clone()
    good_right[:, :, :16] = torch.rand(3, 24, 16, generator=g)
    cols = torch.stack([good_left, good_right])
    vis = torch.ones(2, 24, 32, dtype=torch.bool)
    for patch in (1, 5):
        tex, choice = patch_oracle(cols, vis, ref, patch)
        # away from the boundary between the halves, each side takes its exact candidate
        assert (choice[:, : 16 - patch // 2] == 0).all() and (choice[:, 16 + patch // 2 :] == 1).all()
        assert torch.allclose(tex[:, :, :14], ref[:, :, :14]) and torch.allclose(tex[:, :, 18:], ref[:, :, 18:])


def test_a_larger_patch_resists_a_lucky_noise_sample():
    ref, g = _scene()
    noisy = ref + 0.05 * torch.randn(3, 24, 32, generator=g)
    wrong = torch.rand(3, 24, 32, generator=g)
    wrong[:, 10, 10] = ref[:, 10, 10]  # one lucky texel in an otherwise wrong photo
    cols = torch.stack([noisy, wrong])
    vis = torch.ones(2, 24, 32, dtype=torch.bool)
    _, c1 = patch_oracle(cols, vis, ref, 1)
    _, c5 = patch_oracle(cols, vis, ref, 5)
    assert c1[10, 10] == 1 and c5[10, 10] == 0


def test_a_candidate_never_wins_where_it_does_not_see():
    ref, _ = _scene()
    exact = ref.clone()
    far = ref + 0.5
    cols = torch.stack([exact, far])
    vis = torch.ones(2, 24, 32, dtype=torch.bool)
    vis[0, :, 20:] = False  # the exact photo does not see the right part
    vis[:, 0, 0] = False  # nobody sees the corner
    tex, choice = patch_oracle(cols, vis, ref, 7)
    assert (choice[:, 20:][vis[1, :, 20:]] == 1).all()
    rows, cols_ = torch.arange(24)[:, None], torch.arange(32)
    assert bool(vis[choice.clamp_min(0), rows, cols_][choice >= 0].all())  # the chosen photo sees the texel
    assert choice[0, 0] == -1 and (tex[:, 0, 0] == 0).all()


def test_an_edge_texel_that_one_photo_barely_reaches_goes_to_the_photo_that_covers_it():
    ref, _ = _scene()
    edge = ref.clone()  # exact, but sees only column 0 (a sliver at its view's edge)
    cover = ref + 0.1  # slightly off, sees everything
    vis = torch.ones(2, 24, 32, dtype=torch.bool)
    vis[0, :, 1:] = False
    _, choice = patch_oracle(torch.stack([edge, cover]), vis, ref, 9)
    assert (choice[:, 0] == 1).all()


def test_bad_shapes_and_patch_sizes_are_refused():
    ref, _ = _scene()
    cols = ref[None].repeat(2, 1, 1, 1)
    vis = torch.ones(2, 24, 32, dtype=torch.bool)
    with pytest.raises(DifftexError, match="odd"):
        patch_oracle(cols, vis, ref, 4)
    with pytest.raises(DifftexError, match="do not match"):
        patch_oracle(cols, vis[:, :10], ref, 3)
    with pytest.raises(DifftexError, match=r"\(K, 3, H, W\)"):
        patch_oracle(cols[:, :2], vis, ref, 3)


def test_the_bounds_script_scores_every_row_of_every_polygon(small_synth_scene, tmp_path):
    import json

    from evaluation import bounds

    out = tmp_path / "bounds"
    assert bounds.main(["--scene", str(small_synth_scene), "--preset", "fast", "--patches", "1,3",
                        "--blend-tiles", "7", "--no-lpips", "--out", str(out)]) == 0
    res = json.loads(out.with_suffix(".json").read_text())
    names = ["ground truth at the texture's texel size", "average", "oracle, 1x1 patches", "oracle, 3x3 patches",
             "blend oracle, 7x7 tiles", "difftex (fast)"]
    assert list(res["rows"]) == names and res["polygons"]
    for n in names:
        assert [p["polygon_id"] for p in res["rows"][n]["polygons"]] == res["polygons"]
        assert 0 < res["rows"][n]["error95"] < math.sqrt(3) and -1 <= res["rows"][n]["ssim"] <= 1
    # the truth at about its own texel size is far closer to itself than any texture of the photos
    gt = res["rows"][names[0]]
    assert all(gt["ssim"] > res["rows"][n]["ssim"] and gt["error95"] < res["rows"][n]["error95"] for n in names[1:])
    assert "| oracle, 3x3 patches |" in out.with_suffix(".md").read_text()
    # the blend fitted to the truth is closer to it than the equal-weight blend it starts from
    assert res["rows"]["blend oracle, 7x7 tiles"]["error95"] < res["rows"]["average"]["error95"]
    for n in ("blend oracle, 7x7 tiles", "difftex (fast)", "average"):
        mo = res["rows"][n]["made_of"]
        assert 1.0 <= mo["photos_per_texel"] <= 20 and 0 < mo["cos"] <= 1 and mo["texel_px"] > 0  # 20 photos
    # the average weighs every photo equally: more photos per texel than the blends that choose
    assert res["rows"]["average"]["made_of"]["photos_per_texel"] > res["rows"]["difftex (fast)"]["made_of"][
        "photos_per_texel"]
    assert "made_of" not in res["rows"]["oracle, 3x3 patches"]
    assert [t["polygon_id"] for t in res["difftex_tail"]] == res["polygons"]
    for t in res["difftex_tail"]:
        assert t["tail_texels"] > 0 and all(0 <= t[k] <= 1 for k in ("median_photo_worse", "no_photo_right",
                                                                     "frontal_right"))


def test_the_bounds_script_at_table1s_long_side_scores_lpips_and_the_mrf_peer(small_synth_scene, tmp_path):
    import json

    from evaluation import bounds

    out = tmp_path / "bounds"
    assert bounds.main(["--scene", str(small_synth_scene), "--preset", "none", "--patches", "3", "--blend-tiles", "",
                        "--long-side", "64", "--mrf", "--out", str(out)]) == 0
    res = json.loads(out.with_suffix(".json").read_text())
    names = ["ground truth at the texture's texel size", "average", "oracle, 3x3 patches", bounds.MRF_ROW]
    assert list(res["rows"]) == names
    frames = [p["frame"] for p in res["rows"]["average"]["polygons"]]
    assert frames and all(max(f) == 64 for f in frames)  # every map 64 texels long, as Table 1's --long-side
    assert res["lpips_variant"] != "not computed"
    for n in names:
        assert 0 <= res["rows"][n]["lpips"] < 1
    # the truth at the texture's texel size is perceptually closer to itself than the average of the photos
    assert res["rows"][names[0]]["lpips"] < res["rows"]["average"]["lpips"]
    text = out.with_suffix(".md").read_text()
    assert "| LPIPS |" in text and "every map 64 texels long" in text and f"| {bounds.MRF_ROW} |" in text


def test_tail_causes_sorts_the_worst_texels_by_what_the_photos_hold():
    from difftex.evaluation.oracle import tail_causes

    h, w = 20, 40
    ref = torch.full((3, h, w), 0.5)
    right, wrong = ref.clone(), ref + 0.3
    frontal = wrong.clone()
    frontal[:, :, 10:20] = ref[:, :, 10:20]  # the frontal photo and one other are right in columns 10-19
    other = frontal.clone()
    cols = torch.stack([frontal, other, wrong, right])
    vis = torch.ones(4, h, w, dtype=torch.bool)
    vis[3, :, :30] = False  # the photo that is right everywhere sees only columns 30-39
    cos = torch.tensor([0.99, 0.6, 0.5, 0.4])[:, None, None].expand(4, h, w).contiguous()
    texture = ref.clone()
    texture[:, :, :20] += 0.2  # the texture is wrong in columns 0-19 (its tail), less than the wrong photos
    out = tail_causes(cols, vis, cos, ref, texture, torch.ones(h, w, dtype=torch.bool), patch=1, frontal=1)
    assert out["tail_texels"] == 20 * h
    assert out["median_photo_worse"] == pytest.approx(0.5)  # columns 0-9: every photo there is worse
    assert out["no_photo_right"] == pytest.approx(0.5)  # columns 0-9: no photo is right
    assert out["frontal_right"] == pytest.approx(0.5)  # columns 10-19
    with pytest.raises(DifftexError, match="do not match"):
        tail_causes(cols, vis, cos, ref[:, :10], texture, torch.ones(h, w, dtype=torch.bool))
    with pytest.raises(DifftexError, match="no texel"):
        tail_causes(cols, vis, cos, ref, texture, torch.zeros(h, w, dtype=torch.bool))


def _rms(a, b):
    return float(((a - b) ** 2).mean().sqrt())


def test_the_blend_oracle_averages_the_noise_of_the_right_photos_and_leaves_out_the_wrong_ones():
    ref, g = _scene()
    noisy = [ref + 0.1 * torch.randn(3, 24, 32, generator=g) for _ in range(4)]
    wrong = [torch.rand(3, 24, 32, generator=g) for _ in range(2)]
    cols = torch.stack(noisy + wrong)
    vis = torch.ones(6, 24, 32, dtype=torch.bool)
    blend, share = blend_oracle(cols, vis, ref, 8)
    photos = 1.0 / (share**2).sum(0)
    select, _ = patch_oracle(cols, vis, ref, 7)
    mean_right = torch.stack(noisy).mean(0)
    # four photos' noise averaged: about half a single photo's, as the mean of the right ones
    assert _rms(blend, ref) < 0.6 * _rms(select, ref)
    assert _rms(blend, ref) < 1.15 * _rms(mean_right, ref)
    assert _rms(blend, ref) < 0.5 * _rms(cols.mean(0), ref)  # the wrong photos are left out
    assert 2.5 < float(photos.min()) and float(photos.max()) < 4.5  # about the four right photos


def test_the_blend_oracle_renormalises_over_the_photos_that_see_a_texel():
    ref, g = _scene()
    exact = ref.clone()
    exact[:, :, 20:] = 5.0  # garbage where it does not see
    off = ref + 0.2
    vis = torch.ones(2, 24, 32, dtype=torch.bool)
    vis[0, :, 20:] = False
    vis[:, 0, 0] = False  # nobody sees the corner
    tex, share = blend_oracle(torch.stack([exact, off]), vis, ref, 12)
    photos = torch.where(share.sum(0) > 0, 1.0 / (share**2).sum(0).clamp_min(1e-12), 0.0)
    # where only the offset photo sees, it is the texture; the garbage never leaks in
    assert torch.allclose(tex[:, 1:, 24:], off[:, 1:, 24:], atol=1e-5)
    assert _rms(tex[:, 1:, :12], ref[:, 1:, :12]) < 0.02  # where both see, the exact photo wins
    assert (tex[:, 0, 0] == 0).all() and photos[0, 0] == 0
    assert float(photos[1:, :12].max()) < 1.1  # one photo where the exact one sees the whole block


def test_the_blend_oracle_handles_frames_that_are_not_a_multiple_of_the_tile_and_extreme_tiles():
    ref, g = _scene(h=7, w=11)
    cols = torch.stack([ref + 0.05 * torch.randn(3, 7, 11, generator=g) for _ in range(3)])
    vis = torch.ones(3, 7, 11, dtype=torch.bool)
    for tile in (1, 4, 64):
        tex, share = blend_oracle(cols, vis, ref, tile, chunk_values=50)  # several batches of blocks
        assert torch.allclose(share.sum(0), torch.ones(7, 11), atol=1e-5)  # shares of every seen texel
        photos = 1.0 / (share**2).sum(0)
        assert float(photos.min()) >= 1.0 - 1e-5 and float(photos.max()) <= 3.0 + 1e-5
        assert tex.shape == (3, 7, 11) and torch.isfinite(tex).all()
        assert _rms(tex, ref) <= _rms(cols.mean(0), ref) + 1e-4  # never worse than the average it starts from
    with pytest.raises(DifftexError, match="tile"):
        blend_oracle(cols, vis, ref, 0)
    with pytest.raises(DifftexError, match="do not match"):
        blend_oracle(cols, vis[:2], ref, 3)


def test_blend_summary_counts_photos_and_weighs_their_features():
    from difftex.evaluation.oracle import blend_summary

    w = torch.zeros(4, 2, 3)
    w[0, 0] = 1.0  # row 0: one photo
    w[:, 1] = 0.25  # row 1: four photos equally
    cos = torch.stack([torch.full((2, 3), c) for c in (1.0, 0.5, 0.5, 0.5)])
    mask = torch.ones(2, 3, dtype=torch.bool)
    s = blend_summary(w, mask, {"cos": cos})
    assert math.isclose(s["photos_per_texel"], 2.5, rel_tol=1e-6)  # (1 + 4) / 2
    assert math.isclose(s["cos"], (1.0 + 0.625) / 2, rel_tol=1e-6)
    # unnormalised weights are normalised per texel; texels without weight are left out
    w2 = w * 7.0
    w2[:, 0, 2] = 0.0
    assert math.isclose(blend_summary(w2, mask, {})["photos_per_texel"], (2 * 1 + 3 * 4) / 5, rel_tol=1e-6)
    with pytest.raises(DifftexError, match="no texel"):
        blend_summary(torch.zeros(4, 2, 3), mask, {})
    with pytest.raises(DifftexError, match="not shaped"):
        blend_summary(w, mask, {"cos": cos[:2]})
