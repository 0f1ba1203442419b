"""The analytic test scene: a textured wall photographed by pinhole cameras.

The photos are rendered here by ray casting onto the wall plane and evaluating a procedural
texture (2x2 supersampled), so every expectation follows from the geometry, not from a run.
Shared by the optimizer, histogram-matching and MRF tests.
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np

from difftex.compose.texturing import texture_polygon
from difftex.geometry.frames import look_at, map_texels, texel_mask, uv_frame
from difftex.method.config import ComputeConfig, OptimizeConfig
from difftex.sampling.photos import PolygonInput
from difftex.scene.camera import Photo
from difftex.scene.proxy import Polygon

WALL_W, WALL_H = 4.0, 3.0
UP = np.array([0.0, 0.0, 1.0])
CENTRE = np.array([WALL_W / 2, 0.0, WALL_H / 2])


def wall() -> Polygon:
    # plane y = 0, outward normal -y (towards the cameras at y < 0)
    return Polygon("wall", np.array([[0, 0, 0], [WALL_W, 0, 0], [WALL_W, 0, WALL_H], [0, 0, WALL_H]], float))


def pattern(x: np.ndarray, z: np.ndarray, kind: str = "checker") -> np.ndarray:
    """Ground-truth colour at wall point (x, z)."""
    if kind == "flat":
        return np.broadcast_to(np.array([0.4, 0.5, 0.6], np.float32), (*x.shape, 3)).copy()
    chk = ((np.floor(x / 0.25) + np.floor(z / 0.25)) % 2).astype(np.float32)
    r = 0.2 + 0.6 * chk
    g = 0.3 + 0.4 * (0.5 + 0.5 * np.sin(2.0 * x))
    b = 0.25 + 0.5 * chk * (z / WALL_H)
    return np.stack([r, g, b], -1).astype(np.float32)


def make_photo(
    name: str, yaw_deg: float, dist: float = 6.0, pitch_deg: float = 0.0, f: float = 150.0, size=(160, 120)
) -> Photo:
    import pycolmap

    a, p = math.radians(yaw_deg), math.radians(pitch_deg)
    C = CENTRE + dist * np.array([math.sin(a) * math.cos(p), -math.cos(a) * math.cos(p), math.sin(p)])
    R = look_at(C, CENTRE)
    w, h = size
    cam = pycolmap.Camera(model="PINHOLE", width=w, height=h, params=[f, f, w / 2, h / 2])
    return Photo(name=name, image_path=None, camera=cam, R=R, t=-R @ C, width=w, height=h, model="PINHOLE")


SS = 2  # supersampling of the rendered photos, per axis


def wall_points(photo: Photo) -> tuple[np.ndarray, np.ndarray]:
    """Where the rays of ``photo``'s SS x SS subpixels meet the wall's plane (y = 0): the points
    (H*SS, W*SS, 3) and whether they fall on the wall (H*SS, W*SS) bool."""
    ys, xs = np.mgrid[0 : photo.height * SS, 0 : photo.width * SS].astype(np.float64)
    d = photo.unproject(np.stack([(xs + 0.5) / SS, (ys + 0.5) / SS], -1))
    C = photo.center
    with np.errstate(divide="ignore", invalid="ignore"):
        s = -C[1] / d[..., 1]
    X = C + s[..., None] * d
    hit = (s > 0) & (X[..., 0] >= 0) & (X[..., 0] <= WALL_W) & (X[..., 2] >= 0) & (X[..., 2] <= WALL_H)
    return X, hit


def downsample(img: np.ndarray, photo: Photo) -> np.ndarray:
    """Subpixel colours (H*SS, W*SS, 3) averaged into the photo's pixels."""
    return img.reshape(photo.height, SS, photo.width, SS, 3).mean((1, 3))


def render(photo: Photo, kind: str = "checker", background=(0.9, 0.1, 0.9)) -> np.ndarray:
    """The wall seen by ``photo`` (2x2 supersampling); pixels missing the wall get ``background``."""
    X, hit = wall_points(photo)
    img = np.empty((*hit.shape, 3), np.float32)
    img[:] = background
    img[hit] = pattern(X[..., 0][hit], X[..., 2][hit], kind)
    return downsample(img, photo)


def make_input(photos, images, long_side=64) -> PolygonInput:
    poly = wall()
    frame = uv_frame(poly, UP, long_side=long_side)
    mask = texel_mask(poly, frame)
    vis = np.stack([map_texels(frame, ph).valid & mask for ph in photos])
    by_name = {ph.name: im for ph, im in zip(photos, images)}
    return PolygonInput("wall", frame, mask, list(photos), vis, lambda ph: by_name[ph.name])


def fast_cfg(**kw) -> OptimizeConfig:
    # the paper's doubling per level from 32 texels: the analytic scenes are 64-128 texels, where
    # the presets' x4 from 64 would leave a single level
    base = dict(
        long_side_start=32, level_step=2.0, max_iters_per_level=(300, 150, 80), min_iters_per_level=20,
        histogram_matching=False,
    )
    base.update(kw)
    return OptimizeConfig(**base)


def optimize(inp: PolygonInput, cfg: OptimizeConfig, device: str = "cpu", compile: str = "off") -> SimpleNamespace:
    """The texturing stage on ``inp``: U (the composed texture, holes filled), W, idx, stats."""
    tp = texture_polygon(inp, cfg, ComputeConfig(device=device, compile=compile))
    return SimpleNamespace(U=tp.texture, W=tp.W, idx=tp.idx, stats=tp.stats, seen=tp.seen)


def gt_texture(inp: PolygonInput) -> np.ndarray:
    tx, ty = inp.frame.centres()
    X = inp.frame.texel_to_world(tx, ty)
    return pattern(X[..., 0], X[..., 2])


def photo_masks(inp: PolygonInput):
    """a_k^i for the analytic wall: pixels whose ray hits the wall inside its outline."""
    from difftex.geometry.frames import pixel_to_texel

    boxes, crops = [], []
    for ph in inp.photos:
        ys, xs = np.mgrid[0 : ph.height, 0 : ph.width] + 0.5
        t = pixel_to_texel(inp.frame, ph, np.stack([xs, ys], -1))
        ok = np.isfinite(t).all(-1)
        ix = np.clip(np.floor(np.nan_to_num(t[..., 0])).astype(int), 0, inp.frame.width - 1)
        iy = np.clip(np.floor(np.nan_to_num(t[..., 1])).astype(int), 0, inp.frame.height - 1)
        inside = (
            ok & (t[..., 0] >= 0) & (t[..., 0] < inp.frame.width) & (t[..., 1] >= 0) & (t[..., 1] < inp.frame.height)
        )
        a = inside & inp.texel_mask[iy, ix]
        r, c = np.nonzero(a)
        x0, y0, x1, y1 = c.min(), r.min(), c.max() + 1, r.max() + 1
        boxes.append((x0, y0, x1, y1))
        crops.append(a[y0:y1, x0:x1])
    return np.array(boxes), crops


def occluded_region(inp: PolygonInput) -> np.ndarray:
    """Texels of the wall rectangle x in [1.5, 2.5], z in [1.0, 2.0]."""
    tx, ty = inp.frame.centres()
    X = inp.frame.texel_to_world(tx, ty)
    return (X[..., 0] > 1.5) & (X[..., 0] < 2.5) & (X[..., 2] > 1.0) & (X[..., 2] < 2.0)


def paint_occluder(
    ph: Photo, img: np.ndarray, colour=(0.05, 0.6, 0.05), grow=0.15, box=(1.5, 2.5, 1.0, 2.0)
) -> np.ndarray:
    """Paint the photo pixels of a wall rectangle (x0, x1, z0, z1), slightly enlarged, with a flat
    colour (default: the occluded region)."""
    x0, x1, z0, z1 = box
    img = img.copy()
    ys, xs = np.mgrid[0 : ph.height, 0 : ph.width] + 0.5
    d = ph.unproject(np.stack([xs, ys], -1))
    s = -ph.center[1] / d[..., 1]
    X = ph.center + s[..., None] * d
    occ = (X[..., 0] > x0 - grow) & (X[..., 0] < x1 + grow) & (X[..., 2] > z0 - grow) & (X[..., 2] < z1 + grow)
    img[occ] = colour
    return img


def write_scene(root, photos, images):
    """The analytic wall as a scene folder: COLMAP text model, PNG photos, proxy.obj."""
    from scipy.spatial.transform import Rotation

    from difftex.scene.files import write_image

    (root / "sparse" / "0").mkdir(parents=True)
    (root / "images").mkdir()
    cams, ims = [], []
    for i, (ph, img) in enumerate(zip(photos, images), 1):
        K = ph.K()
        cams.append(f"{i} PINHOLE {ph.width} {ph.height} {K[0, 0]} {K[1, 1]} {K[0, 2]} {K[1, 2]}")
        x, y, z, w = Rotation.from_matrix(ph.R).as_quat()
        ims.append(f"{i} {w} {x} {y} {z} {ph.t[0]} {ph.t[1]} {ph.t[2]} {i} {ph.name}\n\n")  # + empty POINTS2D line
        write_image(root / "images" / ph.name, img, bits=16)
    (root / "sparse" / "0" / "cameras.txt").write_text("\n".join(cams) + "\n")
    (root / "sparse" / "0" / "images.txt").write_text("".join(ims))
    (root / "sparse" / "0" / "points3D.txt").write_text("")
    v = wall().outer
    (root / "proxy.obj").write_text("".join(f"v {a} {b} {c}\n" for a, b, c in v) + "g wall\nf 1 2 3 4\n")
