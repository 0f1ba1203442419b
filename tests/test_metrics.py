"""Known-answer tests for difftex.evaluation.metrics, and its metrics against piq / scikit-image /
stlpips-pytorch on the same image pairs (classic LPIPS against piq.LPIPS, with stand-in weight files)."""

from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy import ndimage

from difftex.errors import DifftexError
from difftex.evaluation import metrics, perceptual

from tests import piq_weights as W


def texture(size=64, smooth=1.5, seed=0):
    """A smooth random RGB texture in [0, 1] (blurred noise, so 1-px shifts are small changes)."""
    rng = np.random.default_rng(seed)
    img = ndimage.gaussian_filter(rng.random((size, size, 3)), (smooth, smooth, 0))
    img = (img - img.min()) / (img.max() - img.min())
    return img.astype(np.float32)


def blur(img, sigma):
    return ndimage.gaussian_filter(img, (sigma, sigma, 0), mode="reflect").astype(np.float32)


def stlpips_available():
    return metrics.lpips_source("stlpips")[0] is not None


needs_stlpips = pytest.mark.skipif(not stlpips_available(), reason="stlpips-pytorch does not import here")


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
    expected = structural_similarity(
        img.astype(np.float64),
        ref.astype(np.float64),
        data_range=1.0,
        channel_axis=2,
        gaussian_weights=True,
        sigma=1.5,
        use_sample_covariance=False,
    )
    assert metrics.ssim(img, ref) == pytest.approx(expected, abs=1e-9)
    assert metrics.ssim(img, ref, np.ones(img.shape[:2], bool)) == pytest.approx(expected, abs=1e-9)


def test_ssim_mask_ignores_texels_outside():
    ref = texture()
    img = ref.copy()
    img[:, 32:] = np.random.default_rng(3).random((64, 32, 3))  # right half ruined
    mask = np.zeros((64, 64), bool)
    mask[:, : 32 - 5] = True  # 5 = half window: the SSIM windows there see only the intact half
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
    with pytest.raises(DifftexError, match=r"lie in \[0, 1\]"):
        metrics.ssim(img * 1.5 + 0.01, img)  # e.g. an HDR photo: data range 1 would be wrong
    with pytest.raises(DifftexError, match=r"lie in \[0, 1\]"):
        metrics.texel_error(img - 0.5, img)
    nan = img.copy()
    nan[3, 3, 1] = np.nan
    with pytest.raises(DifftexError, match="NaN"):
        metrics.psnr(nan, img)
    # float32 rounding just past 1 (resampled maps) is accepted and clipped, not an error.
    assert metrics.psnr(np.minimum(img + np.float32(1e-7), 1 + 1e-7), img) > 60


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


# --- agreement with piq and scikit-image on known pairs -------------------------------------------
#
# The evaluation's SSIM is scikit-image's map averaged over a mask (piq has no map output, see the
# metrics module docstring). These tests compute the same numbers through piq and skimage: in float64
# they differ by rounding only (abs 1e-12), because all three use the Gaussian 11x11 window with
# sigma 1.5, K1 = 0.01, K2 = 0.03, population covariances and only the windows that fit inside the
# image; the differences that remain are piq's float32 arithmetic (1e-5), piq's default
# downsampling, and piq's 1e-8 added to the MSE of PSNR, each tested below.


def as_batch(img):
    """(H, W, C) or (N, H, W, C) numpy -> (N, C, H, W) float64 tensor, as piq takes it."""
    t = torch.from_numpy(np.ascontiguousarray(img, np.float64))
    return (t[None] if t.dim() == 3 else t).permute(0, 3, 1, 2)


def piq_ssim(a, b, **kw):
    import piq

    return piq.ssim(as_batch(a), as_batch(b), data_range=1.0, **kw)


def skimage_ssim(a, b):
    from skimage.metrics import structural_similarity

    return structural_similarity(
        np.float64(a),
        np.float64(b),
        data_range=1.0,
        channel_axis=2,
        gaussian_weights=True,
        sigma=1.5,
        use_sample_covariance=False,
    )


def known_pairs():
    ref = texture(64, smooth=1.0, seed=5)
    noisy = np.clip(ref + np.random.default_rng(11).normal(0, 0.05, ref.shape), 0, 1).astype(np.float32)
    return {
        "identical": (ref, ref),
        "noise": (noisy, ref),
        "blur": (blur(ref, 1.0), ref),
        "shift": (np.roll(ref, 1, axis=1), ref),
        "black vs white": (np.zeros_like(ref), np.ones_like(ref)),
        "constant 0.2 vs 0.7": (np.full_like(ref, 0.2), np.full_like(ref, 0.7)),
    }


def triangle_mask(h, w):
    ys, xs = np.mgrid[:h, :w]
    return (ys > 6) & (xs > 4) & (xs * h < ys * w)  # a polygon's texels inside its bounding rectangle


@pytest.mark.parametrize("name", list(known_pairs()))
def test_ssim_equals_piq_and_skimage(name):
    a, b = known_pairs()[name]
    ours = metrics.ssim(a, b)
    assert ours == pytest.approx(skimage_ssim(a, b), abs=1e-12)
    assert ours == pytest.approx(float(piq_ssim(a, b, downsample=False)), abs=1e-12)
    # piq in the images' own float32: the variances are E[x^2] - E[x]^2, which cancels badly where
    # the image is flat (residues of ~1e-8 against C2 = 9e-4 move SSIM by ~1e-4 on a constant image);
    # the evaluation's SSIM is computed in float64 for that reason.
    import piq

    p32 = float(piq.ssim(as_batch(a).float(), as_batch(b).float(), data_range=1.0, downsample=False))
    assert ours == pytest.approx(p32, abs=1e-3 if name.startswith("constant") else 1e-5)


def test_ssim_of_constant_images_is_the_luminance_term():
    # Variances and covariance are 0, so SSIM = (2 a b + C1) / (a^2 + b^2 + C1), C1 = 0.01^2.
    for c1, c2 in ((0.2, 0.7), (0.0, 1.0), (1.0, 1.0), (0.0, 0.0)):
        a, b = np.full((16, 16, 3), c1), np.full((16, 16, 3), c2)
        expected = (2 * c1 * c2 + 1e-4) / (c1**2 + c2**2 + 1e-4)
        assert metrics.ssim(a, b) == pytest.approx(expected, abs=1e-9)
        assert float(piq_ssim(a, b, downsample=False)) == pytest.approx(expected, abs=1e-9)
    assert metrics.ssim(np.zeros((16, 16, 3)), np.ones((16, 16, 3))) < 1e-3  # black vs white: ~1e-4


def test_ssim_of_window_sized_images():
    a, b = texture(11, seed=1), texture(11, seed=2)  # exactly one window fits: the centre pixel's SSIM
    ours = metrics.ssim(a, b)
    assert ours == pytest.approx(skimage_ssim(a, b), abs=1e-12)
    assert ours == pytest.approx(float(piq_ssim(a, b, downsample=False)), abs=1e-12)
    assert -1 < ours < 0.9
    with pytest.raises(DifftexError, match="at least 11x11"):
        metrics.ssim(a[:10], b[:10])


def test_masked_ssim_equals_piq_per_window():
    # piq on the 11x11 crop around a pixel is the SSIM map at that pixel; the masked SSIM is the
    # mean of that map over the mask (minus the 5-texel border where no window fits).
    img, ref = known_pairs()["noise"]
    mask = triangle_mask(64, 64)
    ys, xs = np.nonzero(mask & np.pad(np.ones((54, 54), bool), 5))
    crops = lambda v: np.stack([v[y - 5 : y + 6, x - 5 : x + 6] for y, x in zip(ys, xs)])  # noqa: E731
    per_window = piq_ssim(crops(img), crops(ref), downsample=False, reduction="none").numpy()
    assert metrics.ssim(img, ref, mask) == pytest.approx(float(per_window.mean()), abs=1e-12)
    # The naive per-region call, piq on the mask's bounding rectangle, averages other windows.
    y0, y1, x0, x1 = ys.min() - 5, ys.max() + 6, xs.min() - 5, xs.max() + 6
    rect = float(piq_ssim(img[y0:y1, x0:x1], ref[y0:y1, x0:x1], downsample=False))
    assert abs(rect - metrics.ssim(img, ref, mask)) > 1e-3


def test_piq_default_downsampling_is_not_the_evaluation_ssim():
    ref = texture(512, smooth=1.0, seed=8)
    img = np.clip(ref + np.random.default_rng(3).normal(0, 0.05, ref.shape), 0, 1)
    ours = metrics.ssim(img, ref)
    default = float(piq_ssim(img, ref))  # downsample=True: 2x2 average pooling at 512 (f = round(512/256))
    pooled = lambda v: v.reshape(256, 2, 256, 2, 3).mean(axis=(1, 3))  # noqa: E731
    assert default == pytest.approx(metrics.ssim(pooled(img), pooled(ref)), abs=1e-9)
    assert default - ours > 0.05  # pooling averages the noise away
    print(f"512x512 noise pair: SSIM full resolution {ours:.4f}, piq default (2x2 pooled) {default:.4f}")  # for -s


def test_psnr_against_piq_and_skimage():
    import piq
    from skimage.metrics import peak_signal_noise_ratio

    img, ref = known_pairs()["noise"]
    mask = triangle_mask(64, 64)
    ours = metrics.psnr(img, ref, mask)
    x, y = (as_batch(v[mask][:, None, None, :]).permute(2, 1, 0, 3) for v in (img, ref))  # (1, 3, n, 1)
    assert ours == pytest.approx(
        peak_signal_noise_ratio(np.float64(ref[mask]), np.float64(img[mask]), data_range=1.0), abs=1e-9
    )
    # piq adds 1e-8 to the MSE, so it reads 10 log10(1 + 1e-8 / MSE) dB lower, and 80 dB for equal images.
    mse = 10 ** (-ours / 10)
    assert float(piq.psnr(x, y, data_range=1.0)) == pytest.approx(ours - 10 * math.log10(1 + 1e-8 / mse), abs=1e-9)
    assert float(piq.psnr(x, x, data_range=1.0)) == pytest.approx(80.0)
    assert metrics.psnr(img, img, mask) == math.inf
    assert metrics.psnr_from_mse(1e-2) == pytest.approx(20.0)
    with pytest.raises(DifftexError, match="mean squared error"):
        metrics.psnr_from_mse(float("nan"))


# --- LPIPS / ST-LPIPS through the reference packages ------------------------------------------------


def as_tensor(img):
    return torch.from_numpy(np.ascontiguousarray(img, np.float32)).permute(2, 0, 1)[None]


@needs_stlpips
def test_stlpips_equals_reference_package():
    from stlpips_pytorch import stlpips

    a, b = texture(48, seed=1)[:, :40], texture(48, seed=2)[:, :40]
    mask = triangle_mask(48, 40)
    with torch.no_grad():
        plain = float(
            stlpips.LPIPS(net="alex", variant="shift_tolerant", verbose=False)(
                as_tensor(a), as_tensor(b), normalize=True
            )
        )
        dmap = stlpips.LPIPS(net="alex", variant="shift_tolerant", spatial=True, verbose=False)(
            as_tensor(a), as_tensor(b), normalize=True
        )[0, 0].numpy()
    value, label = metrics.lpips(a, b, variant="stlpips")
    assert value == pytest.approx(plain, rel=1e-6)
    assert metrics.lpips(a, b, mask, variant="stlpips")[0] == pytest.approx(float(dmap[mask].mean()), rel=1e-6)
    assert label == "ST-LPIPS (stlpips-pytorch 0.0.2, alex shift-tolerant weights vST0.0)"


@pytest.fixture(scope="module")
def torch_home(tmp_path_factory):
    """A torch hub cache holding classic LPIPS's two weight files (random stand-ins, tests/piq_weights.py)."""
    home = tmp_path_factory.mktemp("torch_home")
    W.write_piq_weights(home / "hub" / "checkpoints")
    return home


@pytest.fixture
def hub_weights(torch_home, monkeypatch):
    monkeypatch.setenv("TORCH_HOME", str(torch_home))
    return torch_home / "hub" / "checkpoints"


def piq_lpips_from(folder):
    """``piq.LPIPS`` built by piq itself: it reads lpips_weights.pt from the hub cache (the file is
    there, so nothing is downloaded). Its VGG16 comes from the stand-in's ``features`` tensors:
    torchvision would load the real file strictly, classifier included (528 MB)."""
    import piq
    import piq.perceptual
    from torchvision.models import vgg16

    def vgg16_from_file(pretrained, progress):
        assert pretrained
        model = vgg16(weights=None)
        sd = torch.load(folder / W.VGG16_FILE, weights_only=True)
        model.features.load_state_dict({k.removeprefix("features."): v for k, v in sd.items()})
        return model

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(piq.perceptual, "vgg16", vgg16_from_file)
        return piq.LPIPS(reduction="none")


def test_weight_files_are_named_as_piq_and_torchvision_name_them(hub_weights):
    files = perceptual.lpips_weight_files()
    assert files == {"lpips": hub_weights / W.LPIPS_FILE, "vgg16": hub_weights / W.VGG16_FILE}
    assert perceptual.lpips_weight_files("/elsewhere") == {
        "lpips": Path("/elsewhere") / W.LPIPS_FILE,
        "vgg16": Path("/elsewhere") / W.VGG16_FILE,
    }


def test_classic_lpips_equals_piq(hub_weights):
    a, b = texture(64, seed=3), blur(texture(64, seed=3), 1.0)
    with torch.no_grad():
        expected = float(piq_lpips_from(hub_weights)(as_tensor(a), as_tensor(b)))
    assert expected > 0
    for variant in ("lpips", "auto"):  # auto prefers classic LPIPS when its weights are on disk
        value, label = metrics.lpips(a, b, variant=variant)
        assert value == pytest.approx(expected, rel=1e-6)
        assert label == (
            "LPIPS (piq 0.8.0, VGG16: torchvision ImageNet weights vgg16-397923af.pth + piq linear weights "
            "lpips_weights.pt)"
        )


def test_classic_lpips_from_a_configured_folder(hub_weights, tmp_path, monkeypatch):
    monkeypatch.setenv("TORCH_HOME", str(tmp_path / "empty"))  # nothing in the hub cache now
    a, b = texture(64, seed=3), blur(texture(64, seed=3), 1.0)
    value, label = metrics.lpips(a, b, variant="lpips", weights_dir=hub_weights)
    assert label.startswith("LPIPS (piq ") and math.isfinite(value) and value > 0
    assert metrics.lpips(a, b, variant="lpips")[0] is None
    assert not (tmp_path / "empty").exists()  # nothing was downloaded


def test_classic_lpips_mask(hub_weights):
    img = texture(64)
    other = img.copy()
    other[:, :32] = blur(img, 3.0)[:, :32]  # only the left half differs
    left = np.zeros((64, 64), bool)
    left[:, :32] = True
    full = metrics.lpips(other, img, variant="lpips")[0]
    d_left = metrics.lpips(other, img, left, variant="lpips")[0]
    d_right = metrics.lpips(other, img, ~left, variant="lpips")[0]
    assert d_right < full < d_left
    # the map averaged over every pixel is the plain distance (64 is a multiple of every layer's stride)
    net = perceptual.network("lpips", str(hub_weights), True, "cpu")
    with torch.no_grad():
        dmap = net(as_tensor(other), as_tensor(img))
    assert dmap.shape == (1, 1, 64, 64) and float(dmap.mean()) == pytest.approx(full, rel=1e-5)


def test_classic_lpips_unavailable_without_weights(tmp_path, monkeypatch, caplog):
    monkeypatch.setenv("TORCH_HOME", str(tmp_path))
    folder = tmp_path / "hub" / "checkpoints"
    value, label = metrics.lpips(texture(), texture(seed=1), variant="lpips")
    assert value is None
    assert label == (
        f"unavailable: classic LPIPS (piq) needs lpips_weights.pt and vgg16-397923af.pth in {folder} "
        "(missing: lpips_weights.pt, vgg16-397923af.pth; not downloaded: DIFFTEX_OFFLINE is set)"
    )
    assert label in caplog.text
    with pytest.raises(DifftexError, match="unavailable"):
        metrics.lpips(texture(), texture(), variant="lpips", required=True)
    if stlpips_available():  # auto falls back to ST-LPIPS, and says so in one line
        caplog.clear()
        value, label = metrics.lpips(texture(), texture(seed=1), variant="auto")
        assert value > 0 and label.startswith("ST-LPIPS")
        notes = [r.getMessage() for r in caplog.records]
        assert len(notes) == 1 and "\n" not in notes[0], notes
        assert notes[0].startswith("LPIPS (auto): classic LPIPS (piq) needs") and "reporting ST-LPIPS" in notes[0]
    assert not tmp_path.exists() or not list(tmp_path.rglob("*.p*"))  # nothing was downloaded


def test_classic_lpips_names_the_one_missing_file(hub_weights, tmp_path):
    (tmp_path / W.LPIPS_FILE).write_bytes((hub_weights / W.LPIPS_FILE).read_bytes())
    assert perceptual.classic_lpips_missing(tmp_path).endswith(
        "(missing: vgg16-397923af.pth; a configured folder is never downloaded into)"
    )
    assert perceptual.classic_lpips_missing(hub_weights) is None


def test_stlpips_unavailable_when_the_package_does_not_import(monkeypatch):
    monkeypatch.setitem(sys.modules, "stlpips_pytorch.stlpips", None)  # its import now fails
    value, label = metrics.lpips(texture(), texture(seed=1), variant="stlpips")
    assert value is None and label.startswith("unavailable: stlpips_pytorch.stlpips does not import")
    with pytest.raises(DifftexError, match="unknown"):
        metrics.lpips(texture(), texture(), variant="vgg")


def test_weights_that_do_not_fit_are_a_clear_error(hub_weights, tmp_path):
    for name in (W.LPIPS_FILE, W.VGG16_FILE):
        (tmp_path / name).write_bytes((hub_weights / name).read_bytes())
    a, b = texture(), texture(seed=1)
    sd = torch.load(tmp_path / W.VGG16_FILE, weights_only=True)
    sd.pop("features.10.bias")
    torch.save(sd, tmp_path / W.VGG16_FILE)
    with pytest.raises(DifftexError, match="vgg16-397923af.pth: not torchvision's VGG16 weights"):
        metrics.lpips(a, b, variant="lpips", weights_dir=tmp_path)
    (tmp_path / W.VGG16_FILE).write_bytes(b"not a checkpoint")
    with pytest.raises(DifftexError, match="vgg16-397923af.pth: unreadable torch weight file"):
        metrics.lpips(a, b, variant="lpips", weights_dir=tmp_path)
    (tmp_path / W.VGG16_FILE).write_bytes((hub_weights / W.VGG16_FILE).read_bytes())
    torch.save([torch.zeros(1, 64, 1, 1)] * 4, tmp_path / W.LPIPS_FILE)
    with pytest.raises(DifftexError, match="lpips_weights.pt: not piq's LPIPS weights"):
        metrics.lpips(a, b, variant="lpips", weights_dir=tmp_path)


def test_stlpips_needs_no_lpips_package(tmp_path):
    """The lpips package is not installed (pyproject.toml): ST-LPIPS runs with it unimportable."""
    import subprocess

    code = (
        "import sys; sys.modules['lpips'] = None\n"
        "import numpy as np\n"
        "from difftex.evaluation import metrics\n"
        "rng = np.random.default_rng(0); a = rng.random((40, 40, 3)); b = np.clip(a + 0.1, 0, 1)\n"
        "value, label = metrics.lpips(a, b, variant='stlpips', required=True)\n"
        "assert value > 0 and label.startswith('ST-LPIPS'), label\n"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path)
    assert r.returncode == 0, r.stderr[-2000:]


@needs_stlpips
def test_network_is_built_once_and_silently(capfd):
    perceptual.network.cache_clear()
    a, b = texture(seed=1), texture(seed=2)
    first = metrics.lpips(a, b, variant="stlpips")
    assert metrics.lpips(a, b, variant="stlpips") == first
    info = perceptual.network.cache_info()
    assert (info.misses, info.hits) == (1, 1)
    out = capfd.readouterr()
    assert out.out == "" and "Warning" not in out.err  # the packages print on construction unless told not to


@needs_stlpips
def test_stlpips_identical_blur_and_shift():
    img = texture(64)
    value, _ = metrics.lpips(img, img, variant="stlpips")
    assert value == 0.0
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


def test_lpips_small_image_is_an_error():
    with pytest.raises(DifftexError, match="at least 32x32"):
        metrics.lpips(texture(16), texture(16), variant="stlpips")


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


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_classic_lpips_cuda_matches_cpu(hub_weights):
    a, b = texture(64, seed=4), blur(texture(64, seed=4), 1.5)
    mask = np.zeros((64, 64), bool)
    mask[8:40, 16:60] = True
    for m in (None, mask):
        cpu = metrics.lpips(a, b, m, variant="lpips")[0]
        gpu = metrics.lpips(a, b, m, variant="lpips", device="cuda")[0]
        assert gpu == pytest.approx(cpu, rel=1e-4, abs=1e-6)


@needs_stlpips
def test_texture_metrics_keys():
    img = texture()
    out = metrics.texture_metrics(blur(img, 1.0), img, lpips_variant="stlpips")
    assert set(out) == {"error90", "error95", "ssim", "psnr", "lpips", "lpips_variant"}
    assert out["error90"] <= out["error95"] and 0 < out["ssim"] < 1 and out["lpips"] > 0
    assert out["lpips_variant"].startswith("ST-LPIPS")


def test_mean_gradient_orders_blur_sharp_and_noise():
    rng = np.random.default_rng(0)
    x = np.linspace(0, 8 * np.pi, 64)
    sharp = np.repeat(np.repeat((np.sin(x) > 0).astype(float)[None, :, None], 64, 0), 3, 2) * 0.8 + 0.1
    from scipy.ndimage import uniform_filter

    blurred = uniform_filter(sharp, size=(1, 5, 1), mode="nearest")
    noisy = np.clip(sharp + rng.normal(0, 0.1, sharp.shape), 0, 1)
    g = {k: metrics.mean_gradient(v) for k, v in (("blur", blurred), ("sharp", sharp), ("noise", noisy))}
    assert g["blur"] < g["sharp"] < g["noise"]
    # 8 edges of height 0.8 across 63 column pairs per row, none between rows; half the pairs are vertical
    assert g["sharp"] == pytest.approx(0.8 * 8 / 63 / 2, rel=0.15)
    one = np.zeros((64, 64), bool)
    one[5, 5] = True
    with pytest.raises(DifftexError, match="no pair"):
        metrics.mean_gradient(sharp, one)


def test_detail_gain_counts_the_references_edges_not_noise():
    """detail_gain is 1 for the reference itself, half for half its contrast, below 1 when blurred
    or displaced, and stays near 1 with noise added, which mean_gradient counts as sharpness."""
    from difftex.evaluation.metrics import detail_gain, mean_gradient

    rng = np.random.default_rng(0)
    x = np.arange(256)
    ref = np.repeat(np.repeat(((x // 8) % 2).astype(np.float32)[None, :, None], 128, 0), 3, 2) * 0.6 + 0.2
    assert detail_gain(ref, ref) == pytest.approx(1.0)
    assert detail_gain(0.5 + 0.5 * (ref - 0.5), ref) == pytest.approx(0.5)
    blurred = (ref + np.roll(ref, 1, 1) + np.roll(ref, -1, 1)) / 3
    assert 0.2 < detail_gain(blurred, ref) < 0.5
    assert detail_gain(np.roll(ref, 4, 1), ref) == pytest.approx(0.0, abs=1e-6)  # every edge displaced
    assert detail_gain(np.roll(ref, 8, 1), ref) == pytest.approx(-1.0)  # half a period: inverted
    noisy = np.clip(ref + rng.normal(0, 0.05, ref.shape), 0, 1).astype(np.float32)
    assert detail_gain(noisy, ref) == pytest.approx(1.0, abs=0.03)
    assert mean_gradient(noisy) > 1.5 * mean_gradient(ref)  # the plain gradient takes noise for detail
    # only pairs inside the mask count: a mask inside one stripe sees no edge of the reference
    mask = np.zeros(ref.shape[:2], bool)
    mask[:, 3:7] = True  # inside one stripe: the reference is flat there
    with pytest.raises(DifftexError):
        detail_gain(noisy, ref, mask)
