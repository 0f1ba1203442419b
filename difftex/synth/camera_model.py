"""The camera a training photo goes through: exposure, white balance, lens blur, sensor noise, JPEG.

A synthetic photo starts as Mitsuba's (converged) linear radiance at the reference exposure. A
real survey camera then scales it (exposure time x aperture x gain, per-channel white balance),
blurs it slightly (lens and anti-aliasing filter), turns light into electrons with Poisson shot
noise and adds the read-out's Gaussian noise, clips at the full well, encodes with the sRGB curve
and quantises to 8 bits, and usually compresses to JPEG. Each step is one function here; a
``CameraModel`` holds the parameters and ``apply_camera`` runs them in that order. Only the
training photos go through it: the ground-truth maps and held-out views stay the renderer's
reference-exposure radiance (docs/synth.md, *Camera model*).

Units: linear images are relative radiance, 1.0 = the sensor's white (full well at the set ISO);
sRGB images are floats in [0, 1]. Every random draw comes from the generator passed in, so a
photo is a function of the scene's seed.
"""

from __future__ import annotations

import io
from dataclasses import dataclass

import numpy as np

from difftex.errors import DifftexError

BASE_ISO = 100.0  # the ISO at which the full well maps to white


@dataclass(frozen=True)
class CameraModel:
    """Parameters of the photo pipeline (see docs/synth.md for the formulae).

    Attributes:
        iso: sensitivity; the electrons at white are ``full_well * BASE_ISO / iso``. 0 = no
            sensor noise (the legacy ``image_noise`` then applies, if set).
        full_well: electrons a pixel holds at base ISO (a 1-inch 20 MP drone sensor: ~20000).
        read_noise: std of the read-out noise, electrons.
        lens_blur: std of a Gaussian point spread, pixels; 0 = none.
        jpeg_quality: JPEG quality 1-100 (4:2:0 chroma subsampling); 0 = lossless 8-bit PNG.
        image_noise: legacy additive Gaussian std in linear units (old manifests); only with iso 0.
    """

    iso: float = 0.0
    full_well: float = 20000.0
    read_noise: float = 3.0
    lens_blur: float = 0.0
    jpeg_quality: int = 0
    image_noise: float = 0.0

    def __post_init__(self) -> None:
        if self.iso < 0 or self.full_well <= 0 or self.read_noise < 0 or self.lens_blur < 0 or self.image_noise < 0:
            raise DifftexError(f"camera model: iso, read_noise, lens_blur, image_noise must be >= 0 and "
                               f"full_well > 0, got {self}")
        if not (self.jpeg_quality == 0 or 1 <= self.jpeg_quality <= 100):
            raise DifftexError(f"camera model: jpeg_quality must be 0 (PNG) or 1-100, got {self.jpeg_quality}")
        if self.iso > 0 and self.image_noise > 0:
            raise DifftexError("camera model: set either iso (Poisson-Gaussian sensor) or the legacy image_noise "
                               "(additive Gaussian), not both")

    @property
    def suffix(self) -> str:
        """File suffix of the photos this camera writes."""
        return ".jpg" if self.jpeg_quality else ".png"

    @property
    def white_electrons(self) -> float:
        """Electrons at white (linear 1.0) at this ISO; inf without sensor noise."""
        return self.full_well * BASE_ISO / self.iso if self.iso > 0 else float("inf")


def _check_linear(image: np.ndarray, name: str) -> np.ndarray:
    img = np.asarray(image)
    if img.ndim != 3 or img.shape[-1] != 3:
        raise DifftexError(f"{name}: expected an (H, W, 3) image, got shape {img.shape}")
    if not np.issubdtype(img.dtype, np.floating):
        raise DifftexError(f"{name}: expected a float image, got {img.dtype}")
    return img


def expose(linear: np.ndarray, gain: float, white_balance: tuple[float, float, float]) -> np.ndarray:
    """Scale radiance by the photo's exposure and per-channel white-balance gains.

    Args:
        linear: relative radiance at the reference exposure.
        gain: exposure gain, > 0 (the generator draws ``2^U(-r, r)``).
        white_balance: per-channel gains, each > 0.

    Returns:
        The exposed linear image, float32.

    Shape:
        linear: (H, W, 3); returns (H, W, 3).
    """
    img = _check_linear(linear, "expose")
    wb = np.asarray(white_balance, np.float32)
    if gain <= 0 or wb.shape != (3,) or (wb <= 0).any():
        raise DifftexError(f"expose: gain and white balance must be > 0, got {gain}, {white_balance}")
    return (img * np.float32(gain) * wb).astype(np.float32)


def lens_blur(linear: np.ndarray, sigma_px: float) -> np.ndarray:
    """Blur by a Gaussian point spread function (lens and anti-aliasing filter).

    Applied to linear light, before the sensor: optics blur photons, not noise.

    Args:
        linear: linear image.
        sigma_px: std of the Gaussian in pixels, >= 0; 0 returns the input.

    Returns:
        The blurred image (edges: mirrored), float32.

    Shape:
        linear: (H, W, 3); returns (H, W, 3).
    """
    from scipy import ndimage

    img = _check_linear(linear, "lens_blur")
    if sigma_px < 0:
        raise DifftexError(f"lens_blur: sigma must be >= 0, got {sigma_px}")
    if sigma_px == 0:
        return img.astype(np.float32)
    return ndimage.gaussian_filter(img.astype(np.float32), sigma=(sigma_px, sigma_px, 0), mode="mirror")


def sensor_noise(linear: np.ndarray, white_electrons: float, read_noise: float,
                 rng: np.random.Generator) -> np.ndarray:
    """Poisson-Gaussian sensor: shot noise on the collected electrons plus read-out noise, clipped.

    ``e = Poisson(x * Q) + N(0, read_noise^2)``, returned as ``clip(e / Q, 0, 1)`` with ``Q`` the
    electrons at white. The noise std in linear units is ``sqrt(x / Q + (read_noise / Q)^2)``.

    Args:
        linear: exposed linear image; values above 1 saturate.
        white_electrons: electrons at white ``Q`` > 0 (``CameraModel.white_electrons``).
        read_noise: std of the read-out noise in electrons, >= 0.
        rng: the photo's random generator.

    Returns:
        The noisy linear image in [0, 1], float32.

    Shape:
        linear: (H, W, 3); returns (H, W, 3).
    """
    img = _check_linear(linear, "sensor_noise")
    if not white_electrons > 0 or read_noise < 0:
        raise DifftexError(f"sensor_noise: need white_electrons > 0 and read_noise >= 0, got {white_electrons}, "
                           f"{read_noise}")
    # Clip before counting: a saturated pixel holds a full well, no more.
    electrons = rng.poisson(np.clip(img, 0.0, 1.0).astype(np.float64) * white_electrons).astype(np.float64)
    electrons += rng.normal(0.0, read_noise, img.shape)
    return np.clip(electrons / white_electrons, 0.0, 1.0).astype(np.float32)


def sensor_noise_std(linear: np.ndarray | float, white_electrons: float, read_noise: float) -> np.ndarray:
    """Std of ``sensor_noise`` in linear units at signal ``linear`` (before clipping)."""
    x = np.clip(np.asarray(linear, np.float64), 0.0, 1.0)
    return np.sqrt(x / white_electrons + (read_noise / white_electrons) ** 2)


def additive_noise(linear: np.ndarray, sigma: float, rng: np.random.Generator) -> np.ndarray:
    """The legacy ``image_noise``: signal-independent Gaussian noise in linear units (no clipping).

    Kept so that scenes made before the camera model (presets ``tiny``, ``paper``) stay the same.

    Args:
        linear: linear image.
        sigma: std >= 0.
        rng: the photo's random generator.

    Returns:
        ``linear + N(0, sigma^2)``, float32.

    Shape:
        linear: (H, W, 3); returns (H, W, 3).
    """
    img = _check_linear(linear, "additive_noise")
    if sigma < 0:
        raise DifftexError(f"additive_noise: sigma must be >= 0, got {sigma}")
    return (img + rng.normal(0, sigma, img.shape).astype(np.float32)).astype(np.float32)


def srgb_encode(linear: np.ndarray) -> np.ndarray:
    """The sRGB transfer curve (IEC 61966-2-1) on values clipped to [0, 1].

    Args:
        linear: linear image.

    Returns:
        sRGB-encoded floats in [0, 1], float32, same shape.
    """
    x = np.clip(np.asarray(linear, np.float32), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055).astype(np.float32)


def quantize8(srgb: np.ndarray) -> np.ndarray:
    """Round sRGB floats in [0, 1] to 8-bit codes (uint8), as a camera's JPEG or PNG holds them."""
    return np.round(np.clip(np.asarray(srgb, np.float32), 0.0, 1.0) * 255.0).astype(np.uint8)


def jpeg_encode(codes: np.ndarray, quality: int) -> tuple[bytes, np.ndarray]:
    """Compress 8-bit RGB to JPEG (Pillow's libjpeg, 4:2:0 chroma as most cameras and drones write).

    Args:
        codes: 8-bit RGB image.
        quality: JPEG quality, 1-100.

    Returns:
        The JPEG file's bytes and the image they decode to (uint8), what a reader of the file sees.

    Shape:
        codes: (H, W, 3) uint8; the decoded image is (H, W, 3) uint8.
    """
    from PIL import Image

    arr = np.asarray(codes)
    if arr.dtype != np.uint8 or arr.ndim != 3 or arr.shape[-1] != 3:
        raise DifftexError(f"jpeg_encode: expected (H, W, 3) uint8, got {arr.shape} {arr.dtype}")
    if not 1 <= int(quality) <= 100:
        raise DifftexError(f"jpeg_encode: quality must be 1-100, got {quality}")
    buf = io.BytesIO()
    Image.fromarray(arr, "RGB").save(buf, format="JPEG", quality=int(quality), subsampling="4:2:0", optimize=False)
    data = buf.getvalue()
    decoded = np.asarray(Image.open(io.BytesIO(data)).convert("RGB"))
    return data, decoded


def apply_camera(linear: np.ndarray, camera: CameraModel, gain: float, white_balance: tuple[float, float, float],
                 rng: np.random.Generator) -> tuple[np.ndarray, bytes | None]:
    """Turn reference-exposure radiance into the photo a camera would store.

    Order: exposure and white balance, lens blur, sensor noise (or the legacy additive noise),
    sRGB curve, then 8-bit quantisation and JPEG when ``jpeg_quality`` is set.

    Args:
        linear: radiance at the reference exposure (1.0 = white at gain 1).
        camera: the pipeline's parameters.
        gain: the photo's exposure gain.
        white_balance: the photo's per-channel gains.
        rng: the photo's random generator (seeded from the scene seed and the photo index).

    Returns:
        The photo as sRGB floats in [0, 1] and the JPEG file's bytes. Without JPEG the bytes are
        None and the floats are what an 8-bit PNG writer quantises (as before the camera model,
        so older presets keep their bytes); with JPEG the floats are the decoded file / 255.

    Shape:
        linear: (H, W, 3); the photo is (H, W, 3).
    """
    x = expose(linear, gain, white_balance)
    x = lens_blur(x, camera.lens_blur)
    if camera.iso > 0:
        x = sensor_noise(x, camera.white_electrons, camera.read_noise, rng)
    elif camera.image_noise > 0:
        x = additive_noise(x, camera.image_noise, rng)
    srgb = srgb_encode(x)
    if not camera.jpeg_quality:
        return srgb, None
    data, decoded = jpeg_encode(quantize8(srgb), camera.jpeg_quality)
    return decoded.astype(np.float32) / 255.0, data
