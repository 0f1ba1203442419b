"""Mitsuba 3 rendering of the detailed model: photos, ortho ground-truth maps, position AOVs.

The truth must not come from difftex's own mapping code, so every image here is ray traced by
Mitsuba from the detailed geometry; only the camera conventions are converted (and checked by
tests/test_synth.py against the written COLMAP cameras).
"""

from __future__ import annotations

import functools
import subprocess
import sys

import numpy as np

from difftex.errors import DifftexError
from difftex.synth.detail import DetailedModel
from difftex.synth.presets import SAMPLERS

_PROBE = (
    "import mitsuba as mi; mi.set_variant('{v}'); "
    "s = mi.load_dict({{'type': 'scene', 'integrator': {{'type': 'path'}}, 'e': {{'type': 'constant'}}, 'r': "
    "{{'type': 'sphere'}}, "
    "'sensor': {{'type': 'perspective', 'to_world': mi.ScalarTransform4f().translate([0, 0, -4]), "
    "'film': {{'type': 'hdrfilm', 'width': 8, 'height': 8}}}}}}); mi.render(s, spp=4)"
)


@functools.cache
def choose_variant(requested: str = "auto") -> str:
    """llvm_ad_rgb when it works here, else scalar_rgb.

    A mismatched libLLVM aborts the process inside the JIT (no Python exception), so the probe
    runs in a subprocess.
    """
    try:
        import mitsuba  # noqa: F401
    except ImportError as exc:
        raise DifftexError(f"mitsuba is not installed ({exc}); pip install mitsuba") from None
    cands = ["llvm_ad_rgb", "scalar_rgb"] if requested == "auto" else [requested]
    for v in cands:
        if v == "scalar_rgb":
            return v
        r = subprocess.run([sys.executable, "-c", _PROBE.format(v=v)], capture_output=True, timeout=300)
        if r.returncode == 0:
            return v
    if requested != "auto":
        raise DifftexError(f"mitsuba variant '{requested}' does not run here (for llvm: apt-get install libllvm19)")
    return "scalar_rgb"


def _mi(variant: str):
    import mitsuba as mi

    if mi.variant() != variant:
        mi.set_variant(variant)
    return mi


def _mesh(mi, part):
    m = mi.Mesh(part.name, len(part.vertices), len(part.faces), has_vertex_texcoords=part.uv is not None)
    p = mi.traverse(m)
    p["vertex_positions"] = part.vertices.astype(np.float32).ravel()
    p["faces"] = part.faces.astype(np.uint32).ravel()
    if part.uv is not None:
        p["vertex_texcoords"] = part.uv.astype(np.float32).ravel()
    p.update()
    if part.bitmap is not None:
        refl = {
            "type": "bitmap",
            "bitmap": mi.Bitmap(part.bitmap),
            "raw": True,
            "filter_type": "bilinear",
            "wrap_mode": "clamp",
        }
    else:
        refl = {"type": "rgb", "value": list(part.color)}
    m.set_bsdf(mi.load_dict({"type": "twosided", "b": {"type": "diffuse", "reflectance": refl}}))
    return m


def build_scene(
    variant: str,
    model: DetailedModel,
    ground: np.ndarray,
    ground_size: float,
    lighting: dict,
    occluders: bool,
    integrator: dict | None = None,
):
    """A Mitsuba scene of the detailed model (+ occluders), ground plane, sky and sun."""
    mi = _mi(variant)
    T = mi.ScalarTransform4f
    d: dict = {"type": "scene", "integrator": integrator or {"type": "path", "max_depth": lighting["max_depth"]}}
    d["sky"] = {"type": "constant", "radiance": {"type": "rgb", "value": lighting["sky"]}}
    if max(lighting.get("sun_irradiance", [0.0])) > 0:
        d["sun"] = {
            "type": "directional",
            "direction": list(-np.asarray(lighting["sun_dir"])),
            "irradiance": {"type": "rgb", "value": lighting["sun_irradiance"]},
        }
    for i, part in enumerate(model.parts):
        d[f"part{i:03d}"] = _mesh(mi, part)
    d["ground"] = {
        "type": "rectangle",
        "to_world": T().scale([ground_size / 2, ground_size / 2, 1.0]),
        "bsdf": {
            "type": "diffuse",
            "reflectance": {
                "type": "bitmap",
                "bitmap": mi.Bitmap(ground),
                "raw": True,
                "to_uv": T().scale([ground_size / 6, ground_size / 6, 1]),
            },
        },
    }
    if occluders:
        for i, prim in enumerate(model.occluders):
            s = {"type": prim.kind}
            for k, v in prim.params.items():
                s[k] = T(v) if k == "to_world" else v
            s["bsdf"] = {
                "type": "twosided",
                "b": {"type": "diffuse", "reflectance": {"type": "rgb", "value": list(prim.color)}},
            }
            d[f"occ{i:03d}"] = s
    return mi.load_dict(d)


def perspective_sensor(variant: str, R: np.ndarray, t: np.ndarray, f: float, width: int, height: int, spp: int,
                       sampler: str = "independent"):
    """Mitsuba camera for a COLMAP pose: Mitsuba's camera x is left and y up, COLMAP's right and down."""
    mi = _mi(variant)
    C = -R.T @ t
    M = np.eye(4)
    M[:3, 0], M[:3, 1], M[:3, 2], M[:3, 3] = -R[0], -R[1], R[2], C
    fov = float(np.degrees(2 * np.arctan(width / 2 / f)))
    return mi.load_dict(
        {
            "type": "perspective",
            "fov": fov,
            "fov_axis": "x",
            "to_world": mi.ScalarTransform4f(M.tolist()),
            "near_clip": 0.05,
            "far_clip": 1e5,
            "film": {
                "type": "hdrfilm",
                "width": int(width),
                "height": int(height),
                "rfilter": {"type": "box"},
                "pixel_format": "rgb",
            },
            "sampler": sampler_dict(variant, sampler, spp),
        }
    )


def ortho_sensor(variant: str, frame, standoff: float, spp: int, sampler: str = "independent"):
    """Orthographic camera whose film is exactly a UV frame's texel grid.

    Measured Mitsuba convention: film column c sees camera-local x = 1 - 2(c+.5)/W and row r
    local y = (1 - 2(r+.5)/H) * H/W. Mapping local x to -W s/2 e_u and local y to -W s/2 e_v
    puts texel (tx, ty) at O + s tx e_u + s ty e_v (docs/conventions.md, step 6).
    """
    mi = _mi(variant)
    s, W, H = frame.texel_size, frame.width, frame.height
    centre = frame.origin + s * (W / 2) * frame.e_u + s * (H / 2) * frame.e_v
    M = np.eye(4)
    M[:3, 0] = -(s * W / 2) * frame.e_u
    M[:3, 1] = -(s * W / 2) * frame.e_v
    M[:3, 2] = -frame.normal
    M[:3, 3] = centre + standoff * frame.normal
    return mi.load_dict(
        {
            "type": "orthographic",
            "to_world": mi.ScalarTransform4f(M.tolist()),
            "near_clip": 1e-3,
            "far_clip": 1e5,
            "film": {"type": "hdrfilm", "width": int(W), "height": int(H), "rfilter": {"type": "box"}},
            "sampler": sampler_dict(variant, sampler, spp),
        }
    )


def effective_spp(sampler: str, spp: int) -> int:
    """The sample count Mitsuba 3.9 actually takes for ``sampler`` asked for ``spp`` samples.

    Stratified samplers need a square (``ldsampler``: a power of 4, ``orthogonal``: a prime
    squared) and silently round up; asking for the rounded count keeps the manifest truthful
    and Mitsuba quiet. Mirrors ``Sampler::sample_count()`` (checked in tests/test_synth.py).

    Args:
        sampler: a Mitsuba sampler plugin name (``SAMPLERS``).
        spp: samples per pixel asked for, >= 1.

    Returns:
        The count, >= ``spp``.
    """
    if sampler not in SAMPLERS:
        raise DifftexError(f"unknown Mitsuba sampler '{sampler}' (known: {', '.join(SAMPLERS)})")
    if spp < 1:
        raise DifftexError(f"samples per pixel must be >= 1, got {spp}")
    if sampler == "ldsampler":
        return 4 ** max(1, int(np.ceil(np.log(spp) / np.log(4) - 1e-9)))  # square and a power of two
    if sampler == "stratified":
        return int(np.ceil(np.sqrt(spp))) ** 2
    if sampler == "multijitter":
        # A grid of round(sqrt n) columns and ceil(n / columns) rows.
        cols = max(1, int(np.sqrt(spp)))
        return cols * int(np.ceil(spp / cols))
    if sampler == "orthogonal":
        r = max(2, int(np.ceil(np.sqrt(spp))))
        while any(r % d == 0 for d in range(2, int(np.sqrt(r)) + 1)):
            r += 1
        return r * r
    return int(spp)


def sampler_dict(variant: str, sampler: str, spp: int) -> dict:
    """Mitsuba sampler description with a sample count it takes as is (see ``effective_spp``)."""
    return {"type": sampler, "sample_count": effective_spp(sampler, spp)}


def render(variant: str, scene, sensor, spp: int, seed: int) -> np.ndarray:
    """Render ``sensor``'s film; ``spp`` is rounded up as the sensor's sampler wants it."""
    mi = _mi(variant)
    spp = int(sensor.sampler().sample_count())
    img = np.array(mi.render(scene, sensor=sensor, spp=spp, seed=int(seed)), dtype=np.float32)
    return img[..., :3] if img.shape[-1] >= 3 else img


def ray_hit_distance(variant: str, scene, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Distance to the first hit along each ray (inf for a miss)."""
    mi = _mi(variant)
    dirs = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    if variant.startswith("scalar"):
        out = np.full(len(origins), np.inf)
        for i, (o, d) in enumerate(zip(origins, dirs)):
            si = scene.ray_intersect(mi.Ray3f(mi.Point3f(*o), mi.Vector3f(*d)))
            if si.is_valid():
                out[i] = float(si.t)
        return out
    ray = mi.Ray3f(
        mi.Point3f(*[origins[:, k].astype(np.float32) for k in range(3)]),
        mi.Vector3f(*[dirs[:, k].astype(np.float32) for k in range(3)]),
    )
    si = scene.ray_intersect(ray)
    t = np.array(si.t, dtype=np.float64)
    t[~np.array(si.is_valid())] = np.inf
    return t


def to_srgb(linear: np.ndarray) -> np.ndarray:
    x = np.clip(linear, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055).astype(np.float32)
