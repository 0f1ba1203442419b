"""Any textured OBJ of the proxy read back into difftex's per-polygon UV frames.

This is how the peers (texrecon, MeshLab) are scored by the same code as difftex: their textured
mesh becomes one texture per polygon in the polygon's own frame (docs/conventions.md). A texel
centre is located in the OBJ triangle lying on the polygon's plane that contains it, and the
triangle's material image is sampled at the interpolated UV.

A peer's atlas is usually finer than the polygon's frame (texrecon's patches are at photo
resolution). Point-sampling it at the frame's texel centres would alias, while difftex and the
baselines average each texel's footprint in the photos; so each polygon is read at ``k`` times
the frame's resolution (``k`` from the atlas' texel density on that polygon, at most 8) and
box-averaged down to the frame.
"""

from __future__ import annotations

from math import ceil
from pathlib import Path

import numpy as np

from difftex.errors import DifftexError
from difftex.geometry.frames import UVFrame

MAX_SUPERSAMPLE = 8


def read_obj(
    path: str | Path,
) -> tuple[np.ndarray, np.ndarray, list[tuple[list[int], list[int], str]], dict[str, Path]]:
    """(positions (n, 3), uvs (m, 2), faces as (vertex ids, uv ids, material), material -> image path).

    Faces keep their OBJ corner lists (uv id -1 where the face has none).
    """
    path = Path(path)
    if not path.is_file():
        raise DifftexError(f"{path}: OBJ file not found")
    V, T, faces, mtl_files = [], [], [], []
    mat = ""
    for lineno, ln in enumerate(path.read_text(errors="replace").splitlines(), 1):
        p = ln.split()
        if not p:
            continue
        try:
            if p[0] == "v":
                V.append([float(x) for x in p[1:4]])
            elif p[0] == "vt":
                T.append([float(x) for x in p[1:3]])
            elif p[0] == "usemtl":
                mat = " ".join(p[1:])
            elif p[0] == "mtllib":
                mtl_files.append(path.parent / " ".join(p[1:]))
            elif p[0] == "f":
                vi, ti = [], []
                for c in p[1:]:
                    s = c.split("/")
                    vi.append(int(s[0]) - 1 if int(s[0]) > 0 else len(V) + int(s[0]))
                    ti.append((int(s[1]) - 1 if int(s[1]) > 0 else len(T) + int(s[1])) if len(s) > 1 and s[1] else -1)
                faces.append((vi, ti, mat))
        except (ValueError, IndexError):
            raise DifftexError(f"{path}:{lineno}: malformed OBJ line '{ln.strip()}'") from None
    images = {}
    for mf in mtl_files:
        if not mf.is_file():
            raise DifftexError(f"{mf}: material library named by {path} is missing")
        cur = None
        for ln in mf.read_text(errors="replace").splitlines():
            p = ln.split()
            if p and p[0] == "newmtl":
                cur = " ".join(p[1:])
            elif p and p[0] == "map_Kd" and cur is not None:
                images[cur] = mf.parent / p[-1]
    return np.asarray(V, float).reshape(-1, 3), np.asarray(T, float).reshape(-1, 2), faces, images


def textured_triangles(faces, materials: list[str]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(vertex ids (m, 3), uv ids (m, 3), material index (m,)) of the faces that have UVs and an image.

    n-gons are split as fans (peers write triangles; a fan is exact for the convex faces
    a mesh writer produces).
    """
    index = {m: i for i, m in enumerate(materials)}
    tv, tt, tm = [], [], []
    for vi, ti, mat in faces:
        if mat not in index or min(ti) < 0:
            continue
        for k in range(1, len(vi) - 1):
            tv.append((vi[0], vi[k], vi[k + 1]))
            tt.append((ti[0], ti[k], ti[k + 1]))
            tm.append(index[mat])
    return (np.asarray(tv, np.int64).reshape(-1, 3), np.asarray(tt, np.int64).reshape(-1, 3), np.asarray(tm, np.int64))


def raster_triangles(shape: tuple[int, int], P: np.ndarray, budget: int = 4_000_000) -> tuple[np.ndarray, ...]:
    """Texel centres inside triangles, vectorised over triangles of similar size.

    Args:
        shape: (H, W) of the texel grid.
        P: (m, 3, 2) triangle corners in continuous texel coordinates (texel centres at +0.5).
        budget: candidate texels tested per batch (memory bound).
    Returns:
        (rows, cols, triangle index, barycentric coordinates (n, 3)) for every (texel, triangle)
        pair with the texel centre inside or on the triangle. A texel on an edge shared by two
        triangles appears for both, so a conforming mesh leaves no texel out.
    """
    H, W = shape
    P = np.asarray(P, np.float64).reshape(-1, 3, 2)
    a = P[:, 0]
    M = np.stack([P[:, 1] - a, P[:, 2] - a], axis=-1)  # (m, 2, 2): columns b - a, c - a
    det = M[:, 0, 0] * M[:, 1, 1] - M[:, 0, 1] * M[:, 1, 0]
    scale = np.abs(M).reshape(len(P), -1).max(1) if len(P) else np.zeros(0)
    ok = np.abs(det) > 1e-12 * np.maximum(scale, 1e-30) ** 2
    lo = np.clip(np.floor(P.min(1) - 0.5).astype(np.int64), 0, [W - 1, H - 1])
    hi = np.clip(np.ceil(P.max(1) - 0.5).astype(np.int64), -1, [W - 1, H - 1])
    size = hi - lo + 1
    ok &= (size > 0).all(1) & (P.max(1) >= 0).all(1) & (P.min(1)[:, 0] <= W) & (P.min(1)[:, 1] <= H)
    idx = np.nonzero(ok)[0]
    idx = idx[np.argsort(size[idx].prod(1), kind="stable")]
    inv = np.zeros_like(M)
    inv[ok] = np.linalg.inv(M[ok])
    out_r, out_c, out_t, out_l = [], [], [], []
    start = 0
    while start < len(idx):
        # grow the batch while the padded candidate grid stays within the budget
        end = start + 1
        bw, bh = size[idx[start]]
        while end < len(idx):
            nw, nh = np.maximum([bw, bh], size[idx[end]])
            if (end + 1 - start) * nw * nh > budget:
                break
            bw, bh = nw, nh
            end += 1
        t = idx[start:end]
        oy, ox = np.mgrid[0:bh, 0:bw]
        cx = lo[t, 0][:, None] + ox.ravel()[None]  # (b, bw*bh)
        cy = lo[t, 1][:, None] + oy.ravel()[None]
        qx = cx + 0.5 - a[t, 0][:, None]
        qy = cy + 0.5 - a[t, 1][:, None]
        l1 = inv[t, 0, 0][:, None] * qx + inv[t, 0, 1][:, None] * qy
        l2 = inv[t, 1, 0][:, None] * qx + inv[t, 1, 1][:, None] * qy
        l0 = 1.0 - l1 - l2
        eps = 1e-9
        inside = (l0 >= -eps) & (l1 >= -eps) & (l2 >= -eps) & (cx <= hi[t, 0][:, None]) & (cy <= hi[t, 1][:, None])
        b, j = np.nonzero(inside)
        out_r.append(cy[b, j])
        out_c.append(cx[b, j])
        out_t.append(t[b])
        out_l.append(np.stack([l0[b, j], l1[b, j], l2[b, j]], -1))
        start = end
    if not out_r:
        z = np.zeros(0, np.int64)
        return z, z, z, np.zeros((0, 3))
    return np.concatenate(out_r), np.concatenate(out_c), np.concatenate(out_t), np.concatenate(out_l)


def on_plane(corners: np.ndarray, frame: UVFrame, tol: float = 1e-3) -> np.ndarray:
    """(m,) whether triangles (m, 3, 3) lie on the frame's plane, within ``tol`` of its diameter."""
    scale = max(frame.width, frame.height) * frame.texel_size
    return np.abs((corners - frame.origin) @ frame.normal).max(1) <= tol * scale


def supersample_factor(corners: np.ndarray, uv: np.ndarray, sizes: np.ndarray, frame: UVFrame) -> int:
    """Atlas pixels per frame texel (along one axis) on these triangles, rounded up, in 1..8.

    ``corners`` (m, 3, 3) world, ``uv`` (m, 3, 2) in [0, 1], ``sizes`` (m, 2) their images' (w, h).
    """
    if not len(corners):
        return 1
    e1, e2 = corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]
    world = 0.5 * np.linalg.norm(np.cross(e1, e2), axis=1).sum()
    px = uv * sizes[:, None, :]
    d1, d2 = px[:, 1] - px[:, 0], px[:, 2] - px[:, 0]
    atlas = 0.5 * np.abs(d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0]).sum()
    if not world > 0 or not atlas > 0:
        return 1
    r = np.sqrt(atlas / world) * frame.texel_size
    return int(np.clip(ceil(r - 0.25), 1, MAX_SUPERSAMPLE))


def fine_frame(frame: UVFrame, k: int) -> UVFrame:
    """The same rectangle with every texel split into k x k (exactly nested)."""
    return UVFrame(
        frame.origin, frame.e_u, frame.e_v, frame.normal, frame.texel_size / k, frame.width * k, frame.height * k
    )


def box_down(tex: np.ndarray, cov: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Mean of the covered sub-texels of every k x k block; covered where any sub-texel is."""
    if k == 1:
        return tex, cov
    H, W = cov.shape[0] // k, cov.shape[1] // k
    c = cov.reshape(H, k, W, k).astype(np.float32)
    s = (tex.reshape(H, k, W, k, 3) * c[..., None]).sum((1, 3))
    n = c.sum((1, 3))
    return (s / np.maximum(n, 1.0)[..., None]).astype(np.float32), n > 0


COVERAGE = ("uv", "alpha", "nonblack")


def read_atlas(path: Path, coverage: str = "uv") -> tuple[np.ndarray, np.ndarray]:
    """(RGB (H, W, 3), weight (H, W)) of an atlas image: where the writer says it put colour.

    ``coverage``: "uv" every pixel counts; "alpha" the alpha channel (1 where there is none);
    "nonblack" pixels that are not exactly black (MeshLab's per-face texture paints triangles
    that no photo sees (0, 0, 0) and has no alpha).
    """
    import OpenImageIO as oiio

    from difftex.scene.files import read_image

    if coverage not in COVERAGE:
        raise ValueError(f"coverage must be one of {COVERAGE}, got {coverage!r}")
    rgb = read_image(path)
    if coverage == "nonblack":
        return rgb, (rgb.max(-1) > 0.5 / 255).astype(np.float32)
    if coverage == "alpha":
        buf = oiio.ImageBuf(str(path))
        if buf.nchannels == 4:
            return rgb, np.asarray(buf.get_pixels(oiio.FLOAT), np.float32)[..., 3]
    return rgb, np.ones(rgb.shape[:2], np.float32)


def import_obj(
    obj: str | Path,
    frames: dict[str, UVFrame],
    masks: dict[str, np.ndarray],
    plane_tol: float = 1e-3,
    supersample: int | None = None,
    coverage: str = "uv",
) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Per polygon id: (texture (H, W, 3), covered (H, W) bool) in its UV frame, from a textured OBJ.

    Args:
        obj: the textured OBJ (with its MTL and images).
        frames, masks: every polygon's UV frame and texel mask, by id.
        plane_tol: a triangle belongs to a polygon's plane within this fraction of its diameter.
        supersample: sub-texels per texel along each axis; None picks it per polygon from the
            atlas' texel density (see the module docstring).
        coverage: which atlas pixels hold colour (:func:`read_atlas`); the atlas is sampled
            weighted by it (premultiplied), so uncovered pixels never bleed into covered texels.
    Returns:
        covered is False on texels no textured triangle reaches, where the atlas weight is below
        one half, and outside the mask; the texture is 0 there.
    """
    from difftex.geometry.frames import sample_photo

    V, T, faces, images = read_obj(obj)
    materials = sorted(images)
    atlases = [read_atlas(images[m], coverage) for m in materials]
    # premultiplied: (r w, g w, b w, w), so bilinear lookups average colour over covered pixels only
    pix = [np.concatenate([rgb * w[..., None], w[..., None]], -1) for rgb, w in atlases]
    del atlases
    sizes = np.array([[p.shape[1], p.shape[0]] for p in pix], np.float64).reshape(-1, 2)
    tv, tt, tm = textured_triangles(faces, materials)
    corners = V[tv] if len(tv) else np.zeros((0, 3, 3))
    out = {}
    for pid, fr in frames.items():
        sel = np.nonzero(on_plane(corners, fr, plane_tol))[0] if len(tv) else np.zeros(0, np.int64)
        k = supersample or supersample_factor(corners[sel], T[tt[sel]], sizes[tm[sel]], fr)
        ff = fine_frame(fr, k)
        acc = np.zeros((*ff.shape, 4), np.float32)
        if len(sel):
            rr, cc, ti, lam = raster_triangles(ff.shape, ff.world_to_texel(corners[sel]))
            tri = sel[ti]
            uv = np.einsum("nk,nkd->nd", lam, T[tt[tri]])
            for m in np.unique(tm[tri]):
                j = tm[tri] == m
                ih, iw = pix[m].shape[:2]
                acc[rr[j], cc[j]] = sample_photo(pix[m], np.stack([uv[j, 0] * iw, (1 - uv[j, 1]) * ih], -1))
        w = acc[..., 3]
        cov = w >= 0.5
        tex = np.where(cov[..., None], acc[..., :3] / np.maximum(w, 1e-6)[..., None], 0.0).astype(np.float32)
        tex, cov = box_down(tex, cov, k)
        out[pid] = (tex, cov & masks[pid])
    return out


def polygon_face_map(frame: UVFrame, corners: np.ndarray) -> np.ndarray:
    """(H, W) index of the triangle (of ``corners`` (m, 3, 3)) holding each texel centre, -1 for none."""
    face = np.full(frame.shape, -1, np.int64)
    if len(corners):
        rr, cc, ti, _ = raster_triangles(frame.shape, frame.world_to_texel(corners))
        face[rr, cc] = ti
    return face
