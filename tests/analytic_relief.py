"""The analytic relief scene: the analytic wall (tests/analytic.py) with a recessed window and a
balcony that its proxy (the plane y = 0) lacks, photographed by pinhole cameras.

Every photo is ray cast here against the exact boxes (nearest hit of the wall plane with its two
openings, the recess's back pane and four reveals, the balcony's front and four sides) and
shaded with procedural textures, so the depths and what each photo sees follow from the
geometry, not from a run. The outward normal is -y: the recess lies at height -RECESS, the
balcony's front at +BALCONY.
"""

from __future__ import annotations

import numpy as np

from difftex.scene.camera import Photo

from analytic import WALL_H, WALL_W, make_input, make_photo  # noqa: F401  (make_input: the same wall's input)

RECESS = 0.3  # depth of the window's back pane behind the wall, metres
BALCONY = 0.4  # how far the balcony's front stands out
WINDOW = (0.6, 1.8, 1.0, 2.4)  # x0, x1, z0, z1 of the recess
BOX = (2.4, 3.6, 0.6, 1.6)  # x0, x1, z0, z1 of the balcony
SS = 2


def colour(x: np.ndarray, z: np.ndarray, surface: str) -> np.ndarray:
    """Procedural texture of each surface at (x, z): fine grain on the wall, mullions on the pane."""
    if surface == "wall":
        g = 0.5 + 0.15 * np.sin(37.0 * x + 3.0 * np.sin(23.0 * z)) * np.cos(29.0 * z)
        return np.stack([g, 0.9 * g, 0.7 * g], -1)
    if surface == "pane":  # glass with a cross of mullions and a frame
        mx = np.abs(x - (WINDOW[0] + WINDOW[1]) / 2) < 0.04
        mz = np.abs(z - (WINDOW[2] + WINDOW[3]) / 2) < 0.04
        edge = (np.minimum(x - WINDOW[0], WINDOW[1] - x) < 0.06) | (np.minimum(z - WINDOW[2], WINDOW[3] - z) < 0.06)
        bar = mx | mz | edge
        glass = 0.2 + 0.1 * np.sin(9.0 * x + 5.0 * z)
        return np.stack([np.where(bar, 0.95, glass), np.where(bar, 0.95, glass + 0.05), np.where(bar, 0.9, 0.5)], -1)
    if surface == "front":  # the balcony's parapet: vertical railing bars
        bar = (np.mod(x, 0.15) < 0.05).astype(float)
        return np.stack([0.3 + 0.5 * bar, 0.25 + 0.4 * bar, 0.2 + 0.2 * bar], -1)
    return np.broadcast_to(np.array([0.1, 0.1, 0.12]), (*x.shape, 3)).copy()  # reveals, sides


def _hit_rect(C, d, axis: int, value: float, ranges: dict[int, tuple[float, float]]):
    """Ray parameter s where C + s d meets the rectangle {X[axis] = value, X[a] in ranges[a]}; inf if not."""
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (value - C[axis]) / d[..., axis]
    X = C + s[..., None] * d
    ok = s > 1e-9
    for a, (lo, hi) in ranges.items():
        ok &= (X[..., a] >= lo) & (X[..., a] <= hi)
    return np.where(ok, s, np.inf)


def surfaces():
    """(name, axis, value, ranges, texture) of every face of the detailed wall."""
    wx0, wx1, wz0, wz1 = WINDOW
    bx0, bx1, bz0, bz1 = BOX
    d, b = RECESS, BALCONY
    return [
        ("pane", 1, d, {0: (wx0, wx1), 2: (wz0, wz1)}),
        ("reveal", 0, wx0, {1: (0, d), 2: (wz0, wz1)}),
        ("reveal", 0, wx1, {1: (0, d), 2: (wz0, wz1)}),
        ("reveal", 2, wz0, {0: (wx0, wx1), 1: (0, d)}),
        ("reveal", 2, wz1, {0: (wx0, wx1), 1: (0, d)}),
        ("front", 1, -b, {0: (bx0, bx1), 2: (bz0, bz1)}),
        ("side", 0, bx0, {1: (-b, 0), 2: (bz0, bz1)}),
        ("side", 0, bx1, {1: (-b, 0), 2: (bz0, bz1)}),
        ("side", 2, bz0, {0: (bx0, bx1), 1: (-b, 0)}),
        ("side", 2, bz1, {0: (bx0, bx1), 1: (-b, 0)}),
    ]


def render(photo: Photo, background=(0.9, 0.1, 0.9)) -> np.ndarray:
    """The detailed wall seen by ``photo`` (SS x SS supersampled, nearest hit)."""
    ys, xs = np.mgrid[0 : photo.height * SS, 0 : photo.width * SS].astype(np.float64)
    d = photo.unproject(np.stack([(xs + 0.5) / SS, (ys + 0.5) / SS], -1))
    C = photo.center
    s_wall = _hit_rect(C, d, 1, 0.0, {0: (0, WALL_W), 2: (0, WALL_H)})
    Xw = C + np.where(np.isfinite(s_wall), s_wall, 0)[..., None] * d
    x, z = Xw[..., 0], Xw[..., 2]
    in_window = (x > WINDOW[0]) & (x < WINDOW[1]) & (z > WINDOW[2]) & (z < WINDOW[3])
    s_wall = np.where(in_window, np.inf, s_wall)  # the opening
    cands = [("wall", s_wall)] + [(n, _hit_rect(C, d, a, v, r)) for n, a, v, r in surfaces()]
    S = np.stack([s for _, s in cands])
    k = S.argmin(0)
    best = S.min(0)
    img = np.empty((*best.shape, 3))
    img[:] = background
    X = C + np.where(np.isfinite(best), best, 0)[..., None] * d
    for i, (name, _) in enumerate(cands):
        sel = (k == i) & np.isfinite(best)
        img[sel] = colour(X[..., 0][sel], X[..., 2][sel], name)
    return img.reshape(photo.height, SS, photo.width, SS, 3).mean((1, 3)).astype(np.float32)


def truth(frame) -> tuple[np.ndarray, np.ndarray]:
    """The wall seen from the front at ``frame``'s texels: colours (H, W, 3) and heights (H, W)."""
    tx, ty = frame.centres()
    X = frame.texel_to_world(tx, ty)
    x, z = X[..., 0], X[..., 2]
    win = (x > WINDOW[0]) & (x < WINDOW[1]) & (z > WINDOW[2]) & (z < WINDOW[3])
    box = (x > BOX[0]) & (x < BOX[1]) & (z > BOX[2]) & (z < BOX[3])
    col = np.where(win[..., None], colour(x, z, "pane"), colour(x, z, "wall"))
    col = np.where(box[..., None], colour(x, z, "front"), col)
    h = np.where(win, -RECESS, np.where(box, BALCONY, 0.0))
    return col.astype(np.float32), h


def photos(n_yaw=(-35, -20, 0, 20, 35), pitches=(-15, 10, 30), size=(320, 240), f=300.0) -> list[Photo]:
    """Photos from the front half-space: yaws x pitches (degrees), 6 m from the wall's centre."""
    return [
        make_photo(f"p{i:02d}.png", yaw, dist=6.0, pitch_deg=p, f=f, size=size)
        for i, (yaw, p) in enumerate((y, p) for y in n_yaw for p in pitches)
    ]
