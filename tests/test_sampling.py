"""Photo sampling on its own (difftex.sampling.photos): f_k^i, pyramids, one decode per photo, convergence.

Expectations come from the analytic wall (tests/analytic.py): a pinhole camera frontal to the
wall maps texels by a known scale, and a rendered photo mapped back gives the wall's pattern.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from difftex.geometry.frames import map_texels
from difftex.sampling.photos import PhotoSampler, PhotoSet
from difftex.sampling.texels import level_frame, resample_nearest, texel_map

from tests.analytic import (
    fast_cfg,
    gt_texture,
    make_input,
    make_photo,
    optimize,
    pattern,
    render,
)


def test_texel_map_of_a_frontal_camera_is_a_scaling():
    ph = make_photo("f", 0.0, dist=6.0, f=150.0)
    inp = make_input([ph], [render(ph)], long_side=64)
    tm = texel_map(inp.frame, ph)
    # a texel of s metres covers s * f / d pixels on each side: the footprint is that everywhere
    expected = inp.frame.texel_size * 150.0 / 6.0
    fp = tm.footprint[tm.valid]
    assert torch.allclose(fp, torch.full_like(fp, expected), rtol=1e-5)
    # cos is taken towards the camera centre: d / |C - X| at each texel
    tx, ty = inp.frame.centres()
    X = inp.frame.texel_to_world(tx, ty)
    cos = 6.0 / np.linalg.norm(X - ph.center, axis=-1)
    np.testing.assert_allclose(tm.cos.numpy()[tm.valid.numpy()], cos[tm.valid.numpy()], atol=1e-5)
    # same pixels as the reference (numpy) mapping
    ref = map_texels(inp.frame, ph)
    np.testing.assert_allclose(tm.pix.numpy()[ref.valid], ref.pix[ref.valid], atol=1e-3)
    assert (tm.valid.numpy() == ref.valid).all()


def test_texel_map_region_is_the_same_rectangle_of_the_full_map():
    ph = make_photo("o", 30.0, dist=6.0, pitch_deg=10.0)
    inp = make_input([ph], [render(ph)], long_side=64)
    full = texel_map(inp.frame, ph)
    part = texel_map(inp.frame, ph, region=(5, 20, 10, 40))
    torch.testing.assert_close(part.pix, full.pix[5:20, 10:40], equal_nan=True)
    torch.testing.assert_close(part.footprint, full.footprint[5:20, 10:40])


def test_pyramid_sampling_is_exact_at_pixel_centres_and_averages_at_coarse_footprints():
    rng = np.random.default_rng(0)
    img = rng.random((64, 96, 3)).astype(np.float32)
    s = PhotoSampler(img, (0, 0, 96, 64), torch.device("cpu"))
    ys, xs = np.mgrid[0:64, 0:96] + 0.5
    pix = torch.from_numpy(np.stack([xs, ys], -1).astype(np.float32))
    got = s.sample(pix, torch.ones(64, 96)).permute(1, 2, 0).numpy()
    np.testing.assert_allclose(got, img, atol=2e-3)  # float16 pyramid
    # footprint 2: level 1, the 2x2 box average, at the centres of 2x2 blocks
    ys2, xs2 = np.mgrid[0:32, 0:48] * 2.0 + 1.0
    pix2 = torch.from_numpy(np.stack([xs2, ys2], -1).astype(np.float32))
    got2 = s.sample(pix2, torch.full((32, 48), 2.0)).permute(1, 2, 0).numpy()
    box = img.reshape(32, 2, 48, 2, 3).mean((1, 3))
    np.testing.assert_allclose(got2, box, atol=2e-3)


def test_supersampling_integrates_the_texel_where_one_sample_blurs_two_texels_wide():
    """Texels of 4 x 4 pixels whose boxes straddle the level-2 pyramid blocks (shifted by 2 px):
    one trilinear sample falls between two level-2 pixels and averages 8 px across; 2 x 2
    sub-samples each hit a level-1 pixel of the box, so their mean is the texel's exact box
    average. On a linear ramp both are exact (the sub-samples are symmetric about the centre)."""
    rng = np.random.default_rng(1)
    img = rng.random((64, 96, 3)).astype(np.float32)
    s = PhotoSampler(img, (0, 0, 96, 64), torch.device("cpu"))
    ys, xs = np.mgrid[0:15, 0:23] * 4.0 + 4.0  # texel boxes [4i + 2, 4i + 6)
    pix = torch.from_numpy(np.stack([xs, ys], -1).astype(np.float32))
    fp = torch.full(pix.shape[:2], 4.0)
    exact = img[2:62, 2:94].reshape(15, 4, 23, 4, 3).mean((1, 3))
    one = s.sample(pix, fp).permute(1, 2, 0).numpy()
    four = s.sample(pix, fp, supersample=2).permute(1, 2, 0).numpy()
    np.testing.assert_allclose(four, exact, atol=2e-3)
    assert np.abs(one - exact).mean() > 10 * np.abs(four - exact).mean()
    # the single sample is the blurrier: its texels vary less about their mean
    assert one.std() < 0.8 * four.std()
    ramp = np.broadcast_to((0.002 * np.arange(96, dtype=np.float32))[None, :, None], (64, 96, 3)).copy()
    r = PhotoSampler(ramp, (0, 0, 96, 64), torch.device("cpu"))
    np.testing.assert_allclose(r.sample(pix, fp, 2).numpy(), r.sample(pix, fp).numpy(), atol=2e-3)


def test_texel_axes_are_the_steps_of_a_linear_map_up_to_its_edges():
    from difftex.sampling.photos import texel_axes

    A = torch.tensor([[3.0, 0.5], [-0.25, 2.0]])  # photo pixels per texel step (columns: x, y)
    ys, xs = torch.meshgrid(torch.arange(7.0), torch.arange(9.0), indexing="ij")
    pix = torch.stack([xs, ys], -1) @ A.T + torch.tensor([10.0, 20.0])
    ax, ay = texel_axes(pix)
    torch.testing.assert_close(ax, A[:, 0].expand(7, 9, 2))
    torch.testing.assert_close(ay, A[:, 1].expand(7, 9, 2))
    pix[3, 4] = float("nan")  # behind the camera: its neighbours' sub-samples fall on their centres
    ax, ay = texel_axes(pix)
    assert torch.isfinite(ax).all() and torch.isfinite(ay).all()
    assert (ax[3, 3] == 0).all() and (ay[2, 4] == 0).all()


def test_crop_box_must_align_with_the_decode_scale():
    with pytest.raises(ValueError):
        PhotoSampler(np.zeros((8, 8, 3), np.float32), (1, 0, 8, 8), torch.device("cpu"), base=1)


def test_mapped_photo_reproduces_the_wall():
    ph = make_photo("f", 0.0)
    inp = make_input([ph], [render(ph)], long_side=64)
    ps = PhotoSet.load(inp, "cpu")
    mp = ps.map(0, inp.frame, inp.texel_mask)
    got = mp.colour.permute(1, 2, 0).numpy()
    gt = gt_texture(inp)
    inner = mp.visible.numpy().copy()
    inner[:3], inner[-3:], inner[:, :3], inner[:, -3:] = False, False, False, False
    # checker edges blur by a texel; the median error away from them is small
    assert np.median(np.abs(got - gt)[inner]) < 0.02


def box_texture(inp, n: int = 8) -> np.ndarray:
    """The wall's pattern averaged over each texel's square (n x n points): what a texel holds."""
    tx, ty = inp.frame.centres()
    acc = np.zeros((*tx.shape, 3), np.float32)
    for j in range(n):
        for i in range(n):
            X = inp.frame.texel_to_world(tx + (i + 0.5) / n - 0.5, ty + (j + 0.5) / n - 0.5)
            acc += pattern(X[..., 0], X[..., 2])
    return acc / n**2


@pytest.mark.parametrize("yaw", [0.0, 35.0])
def test_the_texture_frame_is_supersampled_and_closer_to_the_wall(yaw):
    """PhotoSet.supersample: the polygon's own frame (the texture) is sampled 2 x 2 per texel
    and comes closer to what each texel of the wall holds (its pattern averaged over the
    texel) than one trilinear sample, which blurs over about two texels, frontal or oblique,
    at 3 photo pixels per texel (`fast`); a coarser level, which only steers the weights,
    takes one sample either way."""
    ph = make_photo("f", yaw)
    inp = make_input([ph], [render(ph)], long_side=32)
    ref = box_texture(inp)
    err, coarse = {}, {}
    frame = level_frame(inp.frame, 16)
    mask = resample_nearest(inp.texel_mask, inp.frame, frame)
    for s in (1, 2):
        ps = PhotoSet.load(inp, "cpu", supersample=s)
        mp = ps.map(0, inp.frame, inp.texel_mask)
        inner = mp.visible.numpy().copy()
        inner[:2], inner[-2:], inner[:, :2], inner[:, -2:] = False, False, False, False
        err[s] = float(np.abs(mp.colour.permute(1, 2, 0).numpy() - ref)[inner].mean())
        coarse[s] = ps.map(0, frame, mask).colour
    assert err[2] < 0.8 * err[1], err
    torch.testing.assert_close(coarse[1], coarse[2])


def test_resample_nearest_round_trip():
    ph = make_photo("f", 0.0)
    inp = make_input([ph], [render(ph)], long_side=64)
    coarse = level_frame(inp.frame, 16)
    m = resample_nearest(inp.texel_mask, inp.frame, coarse)
    assert m.shape == coarse.shape and m.all()


def test_each_photo_is_read_once_per_polygon():
    photos = [make_photo(f"p{i}", yaw) for i, yaw in enumerate((-30.0, 0.0, 25.0))]
    images = {ph.name: render(ph) for ph in photos}
    reads: dict[str, int] = {}

    def load(ph):
        reads[ph.name] = reads.get(ph.name, 0) + 1
        return images[ph.name]

    inp = make_input(photos, [images[p.name] for p in photos], long_side=64)
    inp = type(inp)(inp.polygon_id, inp.frame, inp.texel_mask, inp.photos, inp.texel_visible, load)
    res = optimize(inp, fast_cfg(histogram_matching=True, max_iters_per_level=(40, 30, 20), min_iters_per_level=10))
    # transfers, every level of the optimization and the final composition: one decode each
    assert reads == {p.name: 1 for p in photos}
    assert res.stats["photo_reads"] == 3


def test_a_level_stops_early_when_the_photos_agree():
    # three photos of the same wall, no occluder, no exposure difference: nothing to decide
    photos = [make_photo(f"p{i}", yaw) for i, yaw in enumerate((-20.0, 0.0, 20.0))]
    inp = make_input(photos, [render(ph, kind="flat") for ph in photos], long_side=64)
    res = optimize(inp, fast_cfg(max_iters_per_level=(300, 300, 300), min_iters_per_level=20))
    levels = res.stats["levels"]
    assert all(lv["converged"] for lv in levels)
    assert all(lv["iterations"] < lv["cap"] for lv in levels)


def test_decode_cache_returns_the_decode_and_keeps_within_its_budget(tmp_path):
    from PIL import Image

    from difftex.scene.files import DecodeCache, decode_photo

    rng = np.random.default_rng(0)
    paths = []
    for i in range(3):
        p = tmp_path / f"p{i}.jpg"
        Image.fromarray((rng.random((64, 96, 3)) * 255).astype(np.uint8)).save(p, quality=95)
        paths.append(p)
    cache = DecodeCache(budget_mb=1.0)
    first = cache(paths[0], (96, 64), 2)
    again = cache(paths[0], (96, 64), 2)
    assert again is first and (cache.decodes, cache.hits) == (1, 1)
    assert np.array_equal(first, decode_photo(paths[0], (96, 64), 2))
    # another scale is another decode
    assert cache(paths[0], (96, 64), 1).shape == (64, 96, 3) and cache.decodes == 2
    # a budget for one full-size photo: the least recently used goes
    one = 64 * 96 * 3 * 4 / 2**20
    small = DecodeCache(budget_mb=one * 1.5)
    for p in paths:
        small(p, (96, 64), 1)
    assert len(small.entries) == 1 and small.nbytes() <= small.budget
    small(paths[0], (96, 64), 1)
    assert small.decodes == 4  # evicted, decoded again
    # nothing kept at budget zero, the decode still returned
    assert DecodeCache(budget_mb=0)(paths[1], (96, 64), 1).shape == (64, 96, 3)


@pytest.mark.parametrize("consistency", [0.0, 1.0])
def test_a_level_is_the_same_whether_its_slots_are_written_at_the_end_or_per_photo(monkeypatch, consistency):
    """build_level writes the slots' data once the ranking is final when the mapped photos fit
    in MAP_CACHE_BYTES, and gathers them per photo otherwise: the same level either way."""
    import torch

    from difftex.method import levels as L
    from difftex.sampling.photos import PhotoSet
    from difftex.sampling.texels import level_frame

    photos = [make_photo(f"p{i}", yaw) for i, yaw in enumerate((-40.0, -20.0, 0.0, 20.0, 40.0))]
    inp = make_input(photos, [render(ph) for ph in photos], long_side=64)
    cfg = fast_cfg(top_k=2, consistency_sigma=consistency)
    frame = level_frame(inp.frame, 48)

    def level():
        ps = PhotoSet.load(inp, "cpu")
        coarse = L.build_level(ps, level_frame(inp.frame, 24), cfg)
        return L.build_level(ps, frame, cfg, prev=(coarse, torch.softmax(coarse.z0, 0) * coarse.visible))

    held = level()
    monkeypatch.setattr(L, "MAP_CACHE_BYTES", 0)
    streamed = level()
    assert streamed.maps == 2 * held.maps > 0  # the second mapped its photos twice
    assert not held.fixed_slots
    for name in ("idx", "visible", "colours", "sharp", "Q", "cost", "z0"):
        assert torch.equal(getattr(held, name), getattr(streamed, name)), name


@pytest.mark.parametrize(("fmt", "channels"), [("uint8", 3), ("uint8", 4), ("uint8", 1), ("uint16", 3), ("uint16", 2)])
def test_integer_images_read_as_oiio_converts_them_to_float(tmp_path, fmt, channels):
    """read_image reads 8/16-bit pixels as stored and scales them itself (faster): every value of
    the format equals OpenImageIO's own conversion to float, for RGB, RGBA, grey and grey + alpha."""
    import OpenImageIO as oiio

    from difftex.scene.files import read_image

    top = 255 if fmt == "uint8" else 65535
    values = np.arange(top + 1, dtype=np.uint8 if fmt == "uint8" else np.uint16)
    h, w = 64, (top + 1) // 64
    pixels = np.stack([np.roll(values, 17 * c).reshape(h, w) for c in range(channels)], axis=2)
    path = tmp_path / f"{fmt}_{channels}.png"
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), oiio.ImageSpec(w, h, channels, oiio.UINT8 if fmt == "uint8" else oiio.UINT16))
    assert out.write_image(pixels)
    out.close()
    inp = oiio.ImageInput.open(str(path))
    ref = inp.read_image(0, 0, 0, channels, oiio.FLOAT).reshape(h, w, channels)
    inp.close()
    ref = ref[:, :, :3] if channels >= 3 else np.repeat(ref[:, :, :1], 3, axis=2)
    got = read_image(path)
    assert got.dtype == np.float32 and got.shape == (h, w, 3) and got.flags.c_contiguous
    assert np.array_equal(got, ref)  # with alpha, OIIO's associated (premultiplied) colour in both
    if channels in (1, 3):
        assert got.min() == 0.0 and got.max() == 1.0


@pytest.mark.parametrize(("suffix", "reduce"), [(".png", 1), (".png", 2), (".jpg", 1), (".jpg", 2), (".jpg", 4)])
def test_decode_as_stored_converts_to_the_float_decode(tmp_path, suffix, reduce):
    """decode_photo(..., as_stored=True) returns the integer values where no box averaging is
    left (a PNG at full size, a JPEG at a DCT-scaled size), and to_float of it is the float decode."""
    from PIL import Image

    from difftex.scene.files import DecodeCache, decode_photo, to_float

    rng = np.random.default_rng(1)
    path = tmp_path / f"p{suffix}"
    Image.fromarray((rng.random((64, 96, 3)) * 255).astype(np.uint8)).save(path)
    ref = decode_photo(path, (96, 64), reduce)
    got = decode_photo(path, (96, 64), reduce, as_stored=True)
    assert ref.dtype == np.float32
    assert got.dtype == (np.float32 if (suffix == ".png" and reduce > 1) else np.uint8)
    assert np.array_equal(to_float(got), ref)
    cache = DecodeCache(budget_mb=10)
    assert np.array_equal(cache(path, (96, 64), reduce, as_stored=True), got)
    assert cache(path, (96, 64), reduce).dtype == np.float32 and cache.decodes == 2  # kept apart


def test_box_halve_equals_avg_pool2d_bit_for_bit():
    """The pyramid's 2x2 box average (written out) gives avg_pool2d's values exactly, odd sizes,
    the smallest maps and the ends of the range included."""
    import torch.nn.functional as F

    from difftex.sampling.photos import box_halve

    g = torch.Generator().manual_seed(3)
    for shape in [(3, 2, 2), (3, 3, 2), (1, 601, 799), (3, 64, 37)]:
        x = torch.rand(shape, generator=g)
        assert torch.equal(box_halve(x), F.avg_pool2d(x[None], 2)[0])
    ends = torch.tensor([[[0.0, 1.0], [1.0, 1.0]]])
    assert torch.equal(box_halve(ends), torch.tensor([[[0.75]]]))
    assert torch.equal(box_halve(torch.ones(2, 5, 5)), torch.ones(2, 2, 2))
