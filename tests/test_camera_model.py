"""The synthetic photos' camera model and the noise estimator, on images with known noise."""

from __future__ import annotations

import numpy as np
import pytest

from difftex.errors import DifftexError
from difftex.synth import camera_model as cm
from difftex.synth.noise_level import box_downsample, immerkaer_sigma, noise_sigma


def _flat(value: float, h: int = 200, w: int = 240) -> np.ndarray:
    return np.full((h, w, 3), value, np.float32)


def test_sensor_noise_has_the_poisson_gaussian_std():
    """On a flat image the std is sqrt(x / Q + (r / Q)^2) with Q = full_well * 100 / ISO, the mean
    is unbiased, and four times the ISO doubles the noise (shot noise dominates)."""
    cam = cm.CameraModel(iso=400, full_well=20000, read_noise=3)
    assert cam.white_electrons == 5000
    x = _flat(0.2)
    y = cm.sensor_noise(x, cam.white_electrons, cam.read_noise, np.random.default_rng(0))
    want = float(cm.sensor_noise_std(0.2, cam.white_electrons, cam.read_noise))
    assert y.std() == pytest.approx(want, rel=0.02)
    assert y.mean() == pytest.approx(0.2, abs=3 * want / np.sqrt(y.size))
    y4 = cm.sensor_noise(x, cam.white_electrons / 4, cam.read_noise, np.random.default_rng(0))
    assert y4.std() / y.std() == pytest.approx(2.0, rel=0.03)
    # dark pixels: read noise is what is left
    dark = cm.sensor_noise(_flat(0.0), 5000.0, 30.0, np.random.default_rng(1))
    assert dark.mean() > 0 and dark.max() <= 1  # clipped at 0: a positive mean, as on a camera without bias


def test_camera_is_deterministic_from_its_generator():
    lin = np.random.default_rng(3).uniform(0.05, 0.6, (40, 50, 3)).astype(np.float32)
    cam = cm.CameraModel(iso=200, lens_blur=0.5, jpeg_quality=90)
    a, ja = cm.apply_camera(lin, cam, 1.1, (1.0, 0.98, 1.02), np.random.default_rng([5, 0, 1, 17]))
    b, jb = cm.apply_camera(lin, cam, 1.1, (1.0, 0.98, 1.02), np.random.default_rng([5, 0, 1, 17]))
    c, _ = cm.apply_camera(lin, cam, 1.1, (1.0, 0.98, 1.02), np.random.default_rng([5, 0, 2, 17]))
    assert ja == jb and np.array_equal(a, b) and not np.array_equal(a, c)
    assert ja[:2] == b"\xff\xd8"  # a JPEG file
    assert cam.suffix == ".jpg" and cm.CameraModel().suffix == ".png"


def test_legacy_noise_path_is_the_old_formula():
    """iso 0 with image_noise: exactly what the generator did before the camera model, so the tiny
    and paper presets keep their bytes."""
    lin = np.random.default_rng(3).uniform(0, 1, (20, 30, 3)).astype(np.float32)
    gain, wb = 1.3, (1.02, 0.97, 1.0)
    srgb, jpeg = cm.apply_camera(lin, cm.CameraModel(image_noise=0.004), gain, wb, np.random.default_rng([1, 2, 3, 17]))
    old = lin * gain * np.asarray(wb, np.float32)
    old = old + np.random.default_rng([1, 2, 3, 17]).normal(0, 0.004, old.shape).astype(np.float32)
    assert jpeg is None
    np.testing.assert_array_equal(srgb, cm.srgb_encode(old))


def test_lens_blur_keeps_the_mean_and_spreads_a_point():
    img = _flat(0.0, 31, 31)
    img[15, 15] = 1.0
    out = cm.lens_blur(img, 1.0)
    assert out.sum() == pytest.approx(img.sum(), rel=1e-5)
    assert out[15, 15, 0] == pytest.approx(1 / (2 * np.pi), rel=0.05)  # peak of a unit 2D Gaussian
    np.testing.assert_array_equal(cm.lens_blur(img, 0.0), img)


def test_jpeg_round_trip_is_close():
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:64, 0:80]
    codes = np.stack([xx * 3, yy * 3, (xx + yy) * 2], -1).clip(0, 255).astype(np.uint8)
    data, dec = cm.jpeg_encode(codes, 95)
    assert dec.shape == codes.shape and np.abs(dec.astype(int) - codes).mean() < 2
    noisy = (codes + rng.normal(0, 3, codes.shape)).clip(0, 255).astype(np.uint8)
    assert len(cm.jpeg_encode(noisy, 50)[0]) < len(cm.jpeg_encode(noisy, 95)[0])


@pytest.mark.parametrize(
    "call",
    [
        lambda: cm.CameraModel(iso=100, image_noise=0.01),
        lambda: cm.CameraModel(jpeg_quality=101),
        lambda: cm.CameraModel(full_well=0),
        lambda: cm.sensor_noise(np.zeros((4, 4)), 100.0, 1.0, np.random.default_rng()),
        lambda: cm.expose(_flat(0.1, 4, 4), -1.0, (1, 1, 1)),
        lambda: cm.lens_blur(_flat(0.1, 4, 4), -0.5),
        lambda: cm.jpeg_encode(np.zeros((4, 4, 3), np.float32), 90),
        lambda: noise_sigma(_flat(0.5, 2, 2)),
    ],
)
def test_bad_input_is_refused(call):
    with pytest.raises(DifftexError):
        call()


def test_noise_estimator_recovers_known_noise_beside_texture():
    """Gaussian noise of std 0.01 on a shaded ramp, half of it covered by brick-like texture: the
    flat-tile estimate is within 10 % of 0.01 and the texture alone reads as nearly 0; Immerkaer on
    the whole image is pulled up by the texture. Box-downsampling by 2 halves white noise."""
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:256, 0:384].astype(np.float32)
    base = 0.3 + 0.3 * xx / 384 + 0.1 * yy / 256
    bricks = 0.15 * (((yy // 8) % 2 == 0) ^ ((xx // 16) % 2 == 0)) + 0.05 * np.sin(1.3 * xx) * np.cos(0.9 * yy)
    base = np.where(xx < 192, base + bricks, base)
    img = (base[..., None] + rng.normal(0, 0.01, (256, 384, 3))).astype(np.float32)
    assert noise_sigma(img) == pytest.approx(0.01, rel=0.1)
    assert noise_sigma(np.repeat(base[..., None], 3, -1)) < 0.001  # the texture alone reads as (almost) no noise
    assert immerkaer_sigma(img) > noise_sigma(img)  # the whole image: texture leaks in
    assert noise_sigma(box_downsample(img, 2)) == pytest.approx(0.005, rel=0.15)


def test_effective_spp_is_mitsubas_sample_count():
    """The manifest's sample counts are what Mitsuba renders with (its samplers round up)."""
    mi = pytest.importorskip("mitsuba")
    from difftex.synth.render import _mi, choose_variant, effective_spp

    _mi(choose_variant("auto"))
    level = mi.log_level()
    mi.set_log_level(mi.LogLevel.Error)
    try:
        for sampler in ("independent", "stratified", "multijitter", "orthogonal", "ldsampler"):
            for n in (1, 3, 9, 16, 24, 50, 64, 100, 256, 300):
                got = mi.load_dict({"type": sampler, "sample_count": n}).sample_count()
                assert effective_spp(sampler, n) == got, (sampler, n)
    finally:
        mi.set_log_level(level)
