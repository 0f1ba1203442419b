"""Known-answer tests for difftex.metrics and the LPIPS networks in difftex.perceptual."""

from __future__ import annotations

import math
import sys
import types

import numpy as np
import pytest
import torch
from scipy import ndimage

from difftex import metrics, perceptual
from difftex.errors import DifftexError


def texture(size=64, smooth=1.5, seed=0):
    """A smooth random RGB texture in [0, 1] (blurred noise, so 1-px shifts are small changes)."""
    rng = np.random.default_rng(seed)
    img = ndimage.gaussian_filter(rng.random((size, size, 3)), (smooth, smooth, 0))
    img = (img - img.min()) / (img.max() - img.min())
    return img.astype(np.float32)


def blur(img, sigma):
    return ndimage.gaussian_filter(img, (sigma, sigma, 0), mode="reflect").astype(np.float32)


def stlpips_available():
    return perceptual.stlpips_weights_path() is not None


needs_stlpips = pytest.mark.skipif(not stlpips_available(), reason="stlpips-pytorch weights not installed")


# --- SSIM / PSNR / error percentiles -------------------------------------------------------------


def test_identical_images_are_perfect():
    img = texture()
    assert metrics.ssim(img, img) == pytest.approx(1.0, abs=1e-12)
    assert metrics.psnr(img, img) == math.inf
    assert metrics.error_percentiles(img, img) == {90.0: 0.0, 95.0: 0.0}


def test_ssim_decreases_with_blur():
    img = texture(smooth=0.7)
    values = [metrics.ssim(blur(img, s), img) for s in (0.5, 1.0, 2.0, 4.0)]
    assert values[0] < 1.0
    assert all(a > b for a, b in zip(values, values[1:])), values


def test_ssim_full_mask_equals_skimage_mean():
    from skimage.metrics import structural_similarity

    img, ref = blur(texture(), 1.0), texture()
    expected = structural_similarity(img.astype(np.float64), ref.astype(np.float64), data_range=1.0,
                                     channel_axis=2, gaussian_weights=True, sigma=1.5,
                                     use_sample_covariance=False)
    assert metrics.ssim(img, ref) == pytest.approx(expected, abs=1e-9)
    assert metrics.ssim(img, ref, np.ones(img.shape[:2], bool)) == pytest.approx(expected, abs=1e-9)


def test_ssim_mask_ignores_texels_outside():
    ref = texture()
    img = ref.copy()
    img[:, 32:] = np.random.default_rng(3).random((64, 32, 3))  # right half ruined
    mask = np.zeros((64, 64), bool)
    mask[:, :32 - 5] = True  # 5 = half window: the SSIM windows there see only the intact half
    assert metrics.ssim(img, ref, mask) == pytest.approx(1.0, abs=1e-9)
    assert metrics.ssim(img, ref) < 0.9


def test_psnr_known_offset_and_mask():
    ref = np.full((16, 16, 3), 0.5, np.float32)
    img = ref + np.float32(0.1)  # MSE 0.01 -> 20 dB
    assert metrics.psnr(img, ref) == pytest.approx(20.0, abs=1e-4)
    img[:8] = ref[:8]
    mask = np.zeros((16, 16), bool)
    mask[:8] = True
    assert metrics.psnr(img, ref, mask) == math.inf


def test_error_percentiles_known_distribution():
    # 100 texels whose red channel differs by 0.01, 0.02, ..., 1.00: distances k/100.
    ref = np.zeros((10, 10, 3), np.float32)
    img = ref.copy()
    img[..., 0] = (np.arange(1, 101).reshape(10, 10) / 100.0)[::-1]
    err = metrics.error_percentiles(img, ref)
    # Linear interpolation: the 90th percentile sits at rank 0.9 * 99 = 89.1 (0-based) of the
    # sorted distances -> 0.90 + 0.1 * (0.91 - 0.90) = 0.901; the 95th at 94.05 -> 0.9505.
    assert err[90.0] == pytest.approx(0.901, abs=1e-6)
    assert err[95.0] == pytest.approx(0.9505, abs=1e-6)


def test_error_is_euclidean_rgb_and_normalisation():
    ref = np.zeros((4, 4, 3), np.float32)
    img = np.full((4, 4, 3), 0.2, np.float32)  # distance 0.2 * sqrt(3)
    assert metrics.error_percentiles(img, ref)[95.0] == pytest.approx(0.2 * math.sqrt(3), abs=1e-6)
    assert metrics.error_percentiles(img, ref, normalized=True)[95.0] == pytest.approx(0.2, abs=1e-6)


def test_error_mask_excludes_texels():
    ref = np.zeros((8, 8, 3), np.float32)
    img = ref.copy()
    img[4:] = 1.0
    mask = np.zeros((8, 8), bool)
    mask[:4] = True
    assert metrics.error_percentiles(img, ref, mask) == {90.0: 0.0, 95.0: 0.0}
    assert metrics.error_percentiles(img, ref)[95.0] == pytest.approx(math.sqrt(3), abs=1e-6)


def test_bad_inputs_raise():
    img = texture(16)
    with pytest.raises(DifftexError, match="shapes differ"):
        metrics.psnr(img, img[:8])
    with pytest.raises(DifftexError, match="selects no texel"):
        metrics.psnr(img, img, np.zeros((16, 16), bool))
    with pytest.raises(DifftexError, match="mask shape"):
        metrics.ssim(img, img, np.ones((8, 8), bool))
    with pytest.raises(DifftexError, match="at least 11x11"):
        metrics.ssim(img[:8, :8], img[:8, :8])


# --- Q_front / Q_vc ------------------------------------------------------------------------------


def field(direction, shape=(8, 8)):
    return np.broadcast_to(np.asarray(direction, float), shape + (3,)).copy()


def test_q_front_frontal_and_inclined_fields():
    n = np.array([0.0, 0.0, 2.0])  # not unit: normalised inside
    assert metrics.q_front(field([0, 0, 1]), n) == pytest.approx(1.0)
    sixty = [math.sin(math.radians(60)), 0, math.cos(math.radians(60))]
    assert metrics.q_front(field(sixty), n) == pytest.approx(0.5)
    assert metrics.q_front(field([0, 0.3, -1]), n) == 0.0  # seen from behind
    with pytest.raises(DifftexError, match="normal"):
        metrics.q_front(field([0, 0, 1]), [0, 0, 0])


def test_q_vc_constant_and_symmetric_fields():
    assert metrics.q_vc(field([0.3, -0.2, 1.0])) == pytest.approx(1.0)
    a = math.radians(30)
    v = field([math.sin(a), 0, math.cos(a)])
    v[:, 4:] = [-math.sin(a), 0, math.cos(a)]
    # Mean direction is +z, every texel deviates 30 degrees: 1 - (pi/6)/(pi/2) = 2/3.
    assert metrics.q_vc(v) == pytest.approx(2.0 / 3.0)
    assert metrics.q_front(v, [0, 0, 1]) == pytest.approx(math.cos(a))
    # Opposite directions cancel: no consistency at all.
    v[:, 4:] = -v[:, :4]
    assert metrics.q_vc(v) == 0.0


def test_q_mask_and_weights():
    v = field([0, 0, 1])
    v[:, 4:] = [1, 0, 0]  # grazing half
    mask = np.zeros((8, 8), bool)
    mask[:, :4] = True
    assert metrics.q_front(v, [0, 0, 1], mask) == pytest.approx(1.0)
    assert metrics.q_vc(v, mask) == pytest.approx(1.0)
    assert metrics.q_front(v, [0, 0, 1]) == pytest.approx(0.5)
    w = np.where(mask, 3.0, 1.0)
    assert metrics.q_front(v, [0, 0, 1], weights=w) == pytest.approx(0.75)
    v[0, 0] = 0.0
    with pytest.raises(DifftexError, match="no view direction"):
        metrics.q_front(v, [0, 0, 1], mask)
    assert metrics.q_front(v, [0, 0, 1]) == pytest.approx(31 / 63)  # 31 frontal of 63 covered texels


def test_view_directions_blend_and_dominant():
    ys, xs = np.mgrid[-1:1:5j, -1:1:5j]
    pts = np.stack([xs, ys, np.zeros_like(xs)], axis=2)
    centres = np.array([[2.0, 0.0, 2.0], [-2.0, 0.0, 2.0]])
    w = np.ones((2, 5, 5))
    d = metrics.view_directions(pts, centres, w)
    np.testing.assert_allclose(np.linalg.norm(d, axis=2), 1.0)
    # Symmetric cameras: the blended direction at the centre texel is the normal.
    np.testing.assert_allclose(d[2, 2], [0, 0, 1], atol=1e-12)
    w[1] = 0.5
    dom = metrics.view_directions(pts, centres, w, mode="dominant")
    np.testing.assert_allclose(dom[2, 2], np.array([2, 0, 2]) / math.sqrt(8))
    single = metrics.view_directions(pts, centres[:1])
    np.testing.assert_allclose(single, dom)
    w[:, 0, 0] = 0
    assert not metrics.view_directions(pts, centres, w)[0, 0].any()


# --- LPIPS --------------------------------------------------------------------------------------


@needs_stlpips
def test_stlpips_weights_load_strictly():
    sd = torch.load(perceptual.stlpips_weights_path(), map_location="cpu", weights_only=True)
    net = perceptual.LPIPSNet(shift_tolerant=True)
    net.load_state_dict(sd, strict=True)  # every key of the file, and only those
    assert set(net.state_dict()) == set(sd)


@needs_stlpips
def test_mismatched_weights_are_a_clear_error(tmp_path):
    sd = torch.load(perceptual.stlpips_weights_path(), map_location="cpu", weights_only=True)
    sd.pop("lin4.model.1.weight")
    bad = tmp_path / "bad.pth"
    torch.save(sd, bad)
    with pytest.raises(DifftexError, match="do not fit"):
        perceptual.load_network(perceptual.WeightSource("stlpips", (bad,)))


@needs_stlpips
def test_stlpips_identical_blur_and_shift():
    img = texture(64)
    value, used = metrics.lpips(img, img, variant="stlpips")
    assert used == "stlpips" and value == 0.0
    values = [metrics.lpips(blur(img, s), img, variant="stlpips")[0] for s in (0.5, 1.0, 2.0, 3.0)]
    assert all(a < b for a, b in zip(values, values[1:])), values
    shifted = np.roll(img, 1, axis=1)
    mse = float(np.mean((shifted - img) ** 2))
    rng = np.random.default_rng(7)
    noisy = np.clip(img + rng.normal(0, math.sqrt(mse), img.shape), 0, 1).astype(np.float32)
    d_shift = metrics.lpips(shifted, img, variant="stlpips")[0]
    d_noise = metrics.lpips(noisy, img, variant="stlpips")[0]
    # Same pixel error, but a 1-px shift is perceptually (and for ST-LPIPS) much smaller.
    assert d_shift < 0.5 * d_noise, (d_shift, d_noise)


@needs_stlpips
def test_lpips_mask_selects_region():
    img = texture(64)
    other = img.copy()
    other[:, :32] = blur(img, 3.0)[:, :32]  # only the left half differs
    left = np.zeros((64, 64), bool)
    left[:, :32] = True
    full = metrics.lpips(other, img, variant="stlpips")[0]
    d_left = metrics.lpips(other, img, left, variant="stlpips")[0]
    d_right = metrics.lpips(other, img, ~left, variant="stlpips")[0]
    assert d_right < full < d_left


def test_lpips_unavailable(tmp_path, caplog):
    missing = tmp_path / "none.pth"
    value, used = metrics.lpips(texture(), texture(), variant="lpips", alexnet_path=missing)
    assert (value, used) == (None, "unavailable")
    assert "AlexNet weights not found" in caplog.text
    with pytest.raises(DifftexError, match="unavailable"):
        metrics.lpips(texture(), texture(), variant="stlpips", stlpips_path=missing, required=True)
    with pytest.raises(DifftexError, match="unknown"):
        metrics.lpips(texture(), texture(), variant="vgg")


@needs_stlpips
def test_auto_falls_back_to_stlpips(tmp_path):
    _, used = metrics.lpips(texture(), texture(seed=1), alexnet_path=tmp_path / "none.pth")
    assert used == "stlpips"


def test_lpips_small_image_is_an_error():
    if not stlpips_available():
        pytest.skip("stlpips-pytorch weights not installed")
    with pytest.raises(DifftexError, match="at least 32x32"):
        metrics.lpips(texture(16), texture(16), variant="stlpips")


# --- agreement with the reference packages (their torchvision-only imports stubbed) ---------------


def torchvision_alexnet_features():
    """torchvision.models.alexnet().features, layer for layer (seeded random weights)."""
    from torch import nn

    torch.manual_seed(0)
    return nn.Sequential(
        nn.Conv2d(3, 64, 11, stride=4, padding=2), nn.ReLU(inplace=True), nn.MaxPool2d(3, 2),
        nn.Conv2d(64, 192, 5, padding=2), nn.ReLU(inplace=True), nn.MaxPool2d(3, 2),
        nn.Conv2d(192, 384, 3, padding=1), nn.ReLU(inplace=True),
        nn.Conv2d(384, 256, 3, padding=1), nn.ReLU(inplace=True),
        nn.Conv2d(256, 256, 3, padding=1), nn.ReLU(inplace=True), nn.MaxPool2d(3, 2))


@pytest.fixture
def reference_packages(monkeypatch):
    """Import lpips / stlpips_pytorch with stub torchvision, IPython and torchsummary modules."""
    features = torchvision_alexnet_features()
    tv = types.ModuleType("torchvision")
    tv.models = types.SimpleNamespace(alexnet=lambda pretrained=True: types.SimpleNamespace(features=features))
    ipy = types.ModuleType("IPython")
    ipy.embed = lambda *a, **k: None
    ts = types.ModuleType("torchsummary")
    ts.summary = lambda *a, **k: None
    for name, mod in (("torchvision", tv), ("IPython", ipy), ("torchsummary", ts)):
        monkeypatch.setitem(sys.modules, name, mod)
    before = set(sys.modules)
    yield features
    for name in set(sys.modules) - before:
        if name.split(".")[0] in ("lpips", "stlpips_pytorch"):
            del sys.modules[name]


@needs_stlpips
def test_stlpips_matches_reference_package(reference_packages):
    from stlpips_pytorch import stlpips

    ref = stlpips.LPIPS(net="alex", variant="shift_tolerant", verbose=False)
    a, b = texture(48, seed=1)[:, :40], texture(48, seed=2)[:, :40]
    with torch.no_grad():
        expected = float(ref(perceptual._to_tensor(a, "cpu"), perceptual._to_tensor(b, "cpu"), normalize=True))
    assert metrics.lpips(a, b, variant="stlpips")[0] == pytest.approx(expected, rel=1e-5)


@pytest.mark.skipif(perceptual.lpips_linear_weights_path() is None, reason="lpips weights not installed")
def test_classic_lpips_matches_reference_package(reference_packages, tmp_path):
    import lpips as lpips_pkg

    features = reference_packages
    ckpt = {f"features.{k}": v for k, v in features.state_dict().items()}
    ckpt["classifier.1.weight"] = torch.zeros(4096, 9216)[:1]  # ignored, as in a real checkpoint
    path = tmp_path / perceptual.ALEXNET_CHECKPOINT
    torch.save(ckpt, path)
    ref = lpips_pkg.LPIPS(net="alex", verbose=False)
    a, b = texture(64, seed=3), blur(texture(64, seed=3), 1.0)
    with torch.no_grad():
        expected = float(ref(perceptual._to_tensor(a, "cpu"), perceptual._to_tensor(b, "cpu"), normalize=True))
    value, used = metrics.lpips(a, b, variant="auto", alexnet_path=path)
    assert used == "lpips"
    assert value == pytest.approx(expected, rel=1e-5)


@needs_stlpips
@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_stlpips_cuda_matches_cpu():
    a, b = texture(64, seed=4), blur(texture(64, seed=4), 1.5)
    mask = np.zeros((64, 64), bool)
    mask[8:40, 16:60] = True
    for m in (None, mask):
        cpu = metrics.lpips(a, b, m, variant="stlpips")[0]
        gpu = metrics.lpips(a, b, m, variant="stlpips", device="cuda")[0]
        assert gpu == pytest.approx(cpu, rel=1e-4, abs=1e-6)


@needs_stlpips
def test_texture_metrics_keys():
    img = texture()
    out = metrics.texture_metrics(blur(img, 1.0), img, lpips_variant="stlpips")
    assert set(out) == {"error90", "error95", "ssim", "psnr", "lpips", "lpips_variant"}
    assert out["error90"] <= out["error95"] and 0 < out["ssim"] < 1 and out["lpips"] > 0
