"""Facade layouts (windows, balconies, signs, cornices) and their painted albedo bitmaps.

Everything is drawn with numpy from the seed: no image is downloaded. A face's bitmap covers
the bounding box of its 2D polygon (u along, v up for walls); row 0 is the top (largest v).
The layout is shared by the painter and by the relief builder, so a recessed window's opening
in the geometry is exactly where its frame is painted.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from math import ceil

import numpy as np
from scipy import ndimage

from difftex.synth.buildings import Face


@dataclass
class Layout:
    windows: list[tuple[float, float, float, float]] = field(default_factory=list)  # u0, v0, u1, v1
    shopfronts: list[tuple[float, float, float, float]] = field(default_factory=list)
    doors: list[tuple[float, float, float, float]] = field(default_factory=list)
    signs: list[tuple[float, float, float, float]] = field(default_factory=list)
    balconies: list[tuple[float, float, float]] = field(default_factory=list)  # u0, u1, v (slab top)
    cornice: bool = False
    courses: list[float] = field(default_factory=list)  # heights of string courses
    style: dict = field(default_factory=dict)

    def openings(self) -> list[tuple[float, float, float, float]]:
        """Rectangles recessed into the wall."""
        return self.windows + self.shopfronts + self.doors


@dataclass
class Bitmap:
    """A face's albedo: pixels (H, W, 3) linear float32 and the 2D rectangle they cover."""

    pixels: np.ndarray
    u0: float
    v1: float  # top edge (v of row 0)
    size_u: float
    size_v: float

    def uv(self, p2d: np.ndarray) -> np.ndarray:
        """Mitsuba texture coordinates of 2D face points (measured: Mitsuba's v=0 is bitmap row 0)."""
        return np.stack([(p2d[:, 0] - self.u0) / self.size_u, (self.v1 - p2d[:, 1]) / self.size_v], axis=1)


PALETTE = {
    "brick": [(0.36, 0.12, 0.07), (0.45, 0.2, 0.12), (0.3, 0.16, 0.1), (0.5, 0.32, 0.2)],
    "plaster": [(0.7, 0.62, 0.48), (0.62, 0.64, 0.6), (0.72, 0.55, 0.42), (0.55, 0.6, 0.66), (0.75, 0.72, 0.62)],
    "panel": [(0.42, 0.44, 0.46), (0.58, 0.56, 0.5), (0.25, 0.3, 0.34), (0.6, 0.52, 0.4)],
    "stone": [(0.55, 0.5, 0.42), (0.48, 0.47, 0.45), (0.62, 0.58, 0.5)],
    "frame": [(0.8, 0.8, 0.78), (0.08, 0.08, 0.09), (0.25, 0.14, 0.07), (0.35, 0.38, 0.4)],
    "sign": [(0.6, 0.05, 0.04), (0.04, 0.12, 0.45), (0.05, 0.3, 0.1), (0.8, 0.6, 0.05), (0.05, 0.05, 0.05)],
}


def _pick(rng, key):
    c = np.asarray(PALETTE[key][rng.integers(len(PALETTE[key]))], np.float32)
    return np.clip(c * rng.uniform(0.9, 1.1, 3), 0.02, 0.9).astype(np.float32)


def make_layout(face: Face, character: str, rng: np.random.Generator, relief: float, balconies: bool) -> Layout:
    """Windows on a floor grid, a shop floor with signs for shops, balconies for dwellings."""
    lay = Layout()
    L, He = face.length, face.eave
    base = rng.choice(["brick", "plaster", "panel", "stone"], p=[0.35, 0.3, 0.2, 0.15])
    lay.style = {
        "base": str(base),
        "base_color": _pick(rng, str(base)).tolist(),
        "frame_color": _pick(rng, "frame").tolist(),
        "trim_color": np.clip(_pick(rng, "stone") * 1.1, 0, 0.9).tolist(),
        "sign_color": _pick(rng, "sign").tolist(),
        "mullions": bool(rng.random() < 0.7),
        "plinth": bool(rng.random() < 0.6),
    }
    if face.kind != "wall" or L < 2.0 or He < 2.5:
        return lay
    ground = {"shop": 4.5, "civic": 4.2, "office": 3.8, "residential": 3.0}.get(character, 3.5)
    floor_h = {"residential": 3.0, "office": 3.6, "civic": 4.0, "shop": 3.5}.get(character, 3.3)
    floor_h *= rng.uniform(0.95, 1.05)
    bay = rng.uniform(2.6, 3.6) if character != "civic" else rng.uniform(3.0, 4.2)
    nbay = max(1, int((L - 1.0) // bay))
    bay = (L - 1.0) / nbay
    margin = 0.5
    ww = min(bay * rng.uniform(0.45, 0.65), bay - 0.5)
    wh = min(floor_h * rng.uniform(0.42, 0.55), floor_h - 1.2)
    sill = rng.uniform(0.8, 1.0)
    shop = character == "shop" or (character == "office" and rng.random() < 0.4)
    cornice_h = 0.45 if relief > 0 else 0.0
    # floors above the ground floor
    levels = []
    z = ground
    while z + floor_h <= He - cornice_h - 0.2 + 1e-6:
        levels.append(z)
        z += floor_h
    for i in range(nbay):
        c = margin + (i + 0.5) * bay
        # ground floor
        if shop and He >= ground + 0.5:
            sw = bay * rng.uniform(0.75, 0.88)
            lay.shopfronts.append((c - sw / 2, 0.35, c + sw / 2, ground - 1.2))
        elif i == nbay // 2:
            lay.doors.append((c - 0.6, 0.0, c + 0.6, min(2.4, ground - 0.4)))
        elif He >= ground:
            lay.windows.append((c - ww / 2, sill, c + ww / 2, min(sill + wh, ground - 0.4)))
        for zl in levels:
            lay.windows.append((c - ww / 2, zl + sill, c + ww / 2, zl + sill + wh))
            if balconies and character == "residential" and relief > 0 and i % 2 == 0:
                lay.balconies.append((c - ww / 2 - 0.4, c + ww / 2 + 0.4, zl + 0.05))
    if shop and He >= ground + 0.5:
        for i in range(nbay):
            if rng.random() < 0.75:
                c = margin + (i + 0.5) * bay
                sw = bay * rng.uniform(0.6, 0.85)
                lay.signs.append((c - sw / 2, ground - 1.05, c + sw / 2, ground - 0.3))
    elif character == "civic" and rng.random() < 0.8 and He > ground + 1:
        sw = min(L * 0.6, 14.0)
        lay.signs.append((L / 2 - sw / 2, ground - 0.9, L / 2 + sw / 2, ground - 0.25))
    lay.cornice = relief > 0
    if levels and relief > 0:
        lay.courses.append(ground)
    return lay


# --- painting -------------------------------------------------------------------------------

def _smooth_noise(rng, shape, cell_px, amp):
    h, w = shape
    gh, gw = max(2, int(ceil(h / cell_px)) + 2), max(2, int(ceil(w / cell_px)) + 2)
    g = rng.standard_normal((gh, gw)).astype(np.float32)
    big = ndimage.zoom(g, (h / gh * 1.0001 + 1e-6, w / gw * 1.0001 + 1e-6), order=3)[:h, :w]
    if big.shape != (h, w):
        big = np.pad(big, ((0, h - big.shape[0]), (0, w - big.shape[1])), mode="edge")
    return 1.0 + amp * big


def _hash(a, b, seed):
    """Deterministic per-cell pseudo-random in [0, 1) (brick-by-brick colour jitter)."""
    x = (a.astype(np.int64) * 73856093) ^ (b.astype(np.int64) * 19349663) ^ (seed * 83492791)
    x = (x ^ (x >> 13)) * 1274126177
    return ((x ^ (x >> 16)) & 0xFFFF).astype(np.float32) / 65536.0


def _base(style, U, V, rng, color):
    seed = int(rng.integers(1 << 20))
    color = np.asarray(color, np.float32)
    if style == "brick":
        bh, bl, mortar = 0.075, 0.24, 0.012
        row = np.floor(V / bh)
        shift = (row % 2) * bl / 2
        col = np.floor((U + shift) / bl)
        fu, fv = (U + shift) / bl - col, V / bh - row
        j = _hash(row, col, seed)
        img = color * (0.78 + 0.44 * j)[..., None]
        is_m = (fv * bh < mortar) | (fu * bl < mortar)
        img[is_m] = np.float32([0.55, 0.53, 0.5])
        return img
    if style == "panel":
        pw, ph, seam = 1.2, 0.6, 0.015
        row, col = np.floor(V / ph), np.floor(U / pw)
        j = _hash(row, col, seed)
        img = color * (0.9 + 0.2 * j)[..., None]
        seamm = ((V / ph - row) * ph < seam) | ((U / pw - col) * pw < seam)
        img[seamm] *= 0.35
        # fine vertical ribbing: the high-frequency detail that blurs first
        img *= (0.93 + 0.07 * np.cos(2 * np.pi * U / 0.05))[..., None]
        return img
    if style == "stone":
        sh = 0.35
        row = np.floor(V / sh)
        sl = 0.5 + 0.4 * _hash(row, row * 0 + 7, seed)
        shift = _hash(row, row * 0 + 3, seed) * sl
        col = np.floor((U + shift) / sl)
        j = _hash(row, col, seed)
        img = color * (0.85 + 0.3 * j)[..., None]
        joint = ((V / sh - row) * sh < 0.01) | (((U + shift) / sl - col) * sl < 0.01)
        img[joint] *= 0.6
        return img
    img = np.broadcast_to(color, U.shape + (3,)).copy()
    return img


def _sub(img, U, V, rect, pad=0.0):
    """Views of the pixels around a rectangle: U varies along columns only and V along rows only
    (V decreasing), so the window is found by binary search instead of a whole-image mask."""
    u0, v0, u1, v1 = rect
    c0, c1 = np.searchsorted(U[0], [u0 - pad, u1 + pad])
    r0, r1 = np.searchsorted(-V[:, 0], [-(v1 + pad), -(v0 - pad)])
    return img[r0:r1, c0:c1], U[r0:r1, c0:c1], V[r0:r1, c0:c1]


def _fill(img, U, V, rect, color):
    u0, v0, u1, v1 = rect
    m = (U >= u0) & (U < u1) & (V >= v0) & (V < v1)
    img[m] = color
    return m


def _window(img, U, V, rect, frame_color, rng, mullions, shop=False):
    img, U, V = _sub(img, U, V, rect, 0.01)
    u0, v0, u1, v1 = rect
    fw = 0.07
    _fill(img, U, V, rect, frame_color)
    inner = (u0 + fw, v0 + fw, u1 - fw, v1 - fw)
    m = (U >= inner[0]) & (U < inner[2]) & (V >= inner[1]) & (V < inner[3])
    if not m.any():
        return
    t = (V[m] - inner[1]) / max(inner[3] - inner[1], 1e-6)
    s = (U[m] - inner[0]) / max(inner[2] - inner[0], 1e-6)
    glass = np.float32([0.06, 0.09, 0.12]) + np.float32([0.1, 0.12, 0.14]) * t[:, None]
    refl = np.exp(-(((s - t * 0.8 - rng.uniform(-0.2, 0.6)) / 0.12) ** 2))
    glass = glass + 0.12 * refl[:, None]
    if shop:  # goods behind the glass: coloured blobs
        k = _hash(np.floor(U[m] / 0.35), np.floor(V[m] / 0.5), int(rng.integers(1 << 20)))
        glass = glass * 0.6 + 0.3 * np.stack([k, (k * 7) % 1, (k * 13) % 1], 1) * (t < 0.45)[:, None]
    img[m] = glass
    if mullions:
        mu = 0.5 * (inner[0] + inner[2])
        mv = inner[3] - (inner[3] - inner[1]) / 3
        bar = m & ((np.abs(U - mu) < 0.03) | (np.abs(V - mv) < 0.03))
        img[bar] = frame_color


def _door(img, U, V, rect, rng):
    img, U, V = _sub(img, U, V, rect, 0.01)
    u0, v0, u1, v1 = rect
    wood = np.float32([0.25, 0.13, 0.06]) * rng.uniform(0.8, 1.2)
    _fill(img, U, V, rect, np.float32([0.1, 0.1, 0.1]))
    inner = (u0 + 0.08, v0, u1 - 0.08, v1 - 0.08)
    m = _fill(img, U, V, inner, wood)
    grain = 0.85 + 0.15 * np.sin(U[m] * 180 + np.sin(V[m] * 7) * 3)
    img[m] *= grain[:, None]
    mid = 0.5 * (inner[0] + inner[2])
    img[m & (np.abs(U - mid) < 0.015)] *= 0.3


# Segments of a text-like glyph in a unit cell (x right, y up): a 2x3 stroke grid plus diagonals.
_SEGS = np.array([
    [0, 1, 1, 1], [0, 0.5, 1, 0.5], [0, 0, 1, 0], [0, 0, 0, 0.5], [0, 0.5, 0, 1], [1, 0, 1, 0.5],
    [1, 0.5, 1, 1], [0.5, 0, 0.5, 1], [0, 0, 1, 1], [0, 1, 1, 0], [0, 1, 0.5, 0.5], [1, 1, 0.5, 0.5],
], np.float32)


def _sign(img, U, V, rect, bg, rng):
    img, U, V = _sub(img, U, V, rect, 0.01)
    u0, v0, u1, v1 = rect
    m = _fill(img, U, V, rect, np.asarray(bg, np.float32))
    if not m.any():
        return
    ink = np.float32([0.92, 0.9, 0.85]) if np.mean(bg) < 0.4 else np.float32([0.05, 0.05, 0.05])
    h = (v1 - v0) * 0.6
    gw = h * 0.55
    sw = h * 0.13
    n = max(1, int((u1 - u0 - h * 0.5) / (gw * 1.35)))
    start = u0 + 0.5 * (u1 - u0 - n * gw * 1.35 + gw * 0.35)
    ys, xs = np.nonzero(m)
    Us, Vs = U[ys, xs], V[ys, xs]
    for k in range(n):
        if rng.random() < 0.12:  # word gap
            continue
        segs = _SEGS[rng.choice(len(_SEGS), size=int(rng.integers(2, 5)), replace=False)]
        gx0, gy0 = start + k * gw * 1.35, v0 + (v1 - v0 - h) / 2
        sel = (Us > gx0 - sw) & (Us < gx0 + gw + sw)
        if not sel.any():
            continue
        px, py = (Us[sel] - gx0) / gw, (Vs[sel] - gy0) / h
        hit = np.zeros(px.shape, bool)
        for x0, y0, x1, y1 in segs:
            # distance to the segment, in metres (cell is anisotropic: scale back)
            ax, ay = (px - x0) * gw, (py - y0) * h
            bx, by = (x1 - x0) * gw, (y1 - y0) * h
            t = np.clip((ax * bx + ay * by) / max(bx * bx + by * by, 1e-9), 0, 1)
            hit |= (ax - t * bx) ** 2 + (ay - t * by) ** 2 < (sw / 2) ** 2
        idx = np.nonzero(sel)[0][hit]
        img[ys[idx], xs[idx]] = ink


def paint_face(face: Face, layout: Layout, rng: np.random.Generator, density: float, max_side: int) -> Bitmap:
    p2 = face.poly2d
    umin, vmin = p2.min(0)
    umax, vmax = p2.max(0)
    su, sv = umax - umin, vmax - vmin
    dens = min(density, max_side / max(su, sv))
    W, H = max(2, int(ceil(su * dens))), max(2, int(ceil(sv * dens)))
    size_u, size_v = W / dens, H / dens
    cu = umin + (np.arange(W, dtype=np.float32) + 0.5) / dens
    cv = vmax - (np.arange(H, dtype=np.float32) + 0.5) / dens
    U, V = np.meshgrid(cu, cv)
    st = layout.style
    if face.kind == "roof":
        img = _roof(face, U, V, rng)
    else:
        img = _base(st["base"], U, V, rng, st["base_color"])
        if st["plinth"]:  # fine checker band: high frequency at the bottom of the wall
            m = V < 0.6
            chk = ((np.floor(U / 0.1) + np.floor(V / 0.1)) % 2).astype(np.float32)
            img[m] = (np.asarray(st["trim_color"], np.float32) * (0.7 + 0.3 * chk[m, None]))
        for v in layout.courses:
            _fill(img, U, V, (umin - 1, v - 0.2, umax + 1, v + 0.05), np.asarray(st["trim_color"], np.float32))
        if layout.cornice:
            trim = np.asarray(st["trim_color"], np.float32)
            _fill(img, U, V, (umin - 1, face.eave - 0.45, umax + 1, face.eave + 1e-3), trim)
        frame = np.asarray(st["frame_color"], np.float32)
        for r in layout.windows:
            _window(img, U, V, r, frame, rng, st["mullions"])
            # dirt streak under the sill
            u0, v0, u1, v1 = r
            si, sU, sV = _sub(img, U, V, (u0, v0 - 1.2, u1, v0))
            m = (sU >= u0) & (sU < u1) & (sV < v0) & (sV > v0 - 1.2)
            si[m] *= (0.82 + 0.18 * np.clip((v0 - sV[m]) / 1.2, 0, 1))[:, None]
        for r in layout.shopfronts:
            _window(img, U, V, r, frame * 0.5, rng, True, shop=True)
        for r in layout.doors:
            _door(img, U, V, r, rng)
        for r in layout.signs:
            _sign(img, U, V, r, st["sign_color"], rng)
        img *= _smooth_noise(rng, img.shape[:2], max(8, int(2.0 * dens)), 0.06)[..., None]
    img *= rng.uniform(0.97, 1.03, 3).astype(np.float32)
    speck = 1.0 + 0.04 * rng.standard_normal(img.shape[:2]).astype(np.float32)
    img = np.clip(img * speck[..., None], 0.01, 0.95).astype(np.float32)
    return Bitmap(img, float(umin), float(vmax), float(size_u), float(size_v))


def _roof(face, U, V, rng):
    seed = int(rng.integers(1 << 20))
    if abs(face.normal[2]) < 0.95:  # sloped: tile rows
        th, tw = 0.3, 0.25
        row = np.floor(V / th)
        col = np.floor((U + (row % 2) * tw / 2) / tw)
        j = _hash(row, col, seed)
        base = np.float32([0.35, 0.12, 0.08]) if rng.random() < 0.6 else np.float32([0.18, 0.19, 0.21])
        fv = V / th - row
        img = base * (0.75 + 0.3 * j)[..., None] * (0.7 + 0.4 * fv)[..., None]
        return img
    base = np.float32([0.32, 0.31, 0.29]) * rng.uniform(0.8, 1.2)
    img = np.broadcast_to(base, U.shape + (3,)).copy()
    img *= _smooth_noise(rng, U.shape, 40, 0.1)[..., None]
    j = _hash(np.floor(U / 0.03), np.floor(V / 0.03), seed)  # gravel
    img *= (0.75 + 0.5 * j)[..., None]
    seam = ((U % 4.0) < 0.06) | ((V % 4.0) < 0.06)
    img[seam] *= 0.55
    return img


def ground_bitmap(rng: np.random.Generator, size_m: float, px: int = 1024) -> np.ndarray:
    """Asphalt with paving-stone sidewalk texture, tiled over the ground plane."""
    dens = px / size_m
    c = (np.arange(px, dtype=np.float32) + 0.5) / dens
    U, V = np.meshgrid(c, c)
    img = np.broadcast_to(np.float32([0.16, 0.16, 0.17]), U.shape + (3,)).copy()
    img *= _smooth_noise(rng, U.shape, 64, 0.15)[..., None]
    img *= (0.85 + 0.3 * _hash(np.floor(U / 0.05), np.floor(V / 0.05), 11))[..., None]
    return np.clip(img, 0.02, 0.9).astype(np.float32)
