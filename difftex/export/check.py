"""Checks of an exported model: the GLB reloaded and its colours sampled through its own UVs
(``verify_glb``), and the GLB rendered from a photo's camera (``render_view``, for the overlay).

Layer: export (difftex.export.assemble calls verify_glb after writing the model, so this module
takes its difftex.export.assemble.PolygonTexture items without importing that module).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np


def sample_atlas(page: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear samples of an atlas page at OBJ-convention UVs (v up)."""
    from difftex.geometry.frames import sample_photo

    h, w = page.shape[:2]
    pix = np.stack([uv[:, 0] * w, (1.0 - uv[:, 1]) * h], axis=1)
    return sample_photo(page, pix)


def verify_glb(path: Path, items: list, samples_per_polygon: int = 64, seed: int = 0) -> dict:
    """Reload the GLB with trimesh and check that it holds every polygon, covers its area, and
    shows the polygon's texture: colours sampled through the reloaded UVs at random points of
    each triangle are compared with the polygon's own texture at the same world points."""
    import trimesh

    from difftex.geometry.frames import sample_photo

    rng = np.random.default_rng(seed)
    scene = trimesh.load(path, file_type="glb", force="scene")
    missing, area_err, errs, worst = [], 0.0, [], ("", 0.0)
    page_cache: dict[int, np.ndarray] = {}
    for it in items:
        pid = it.polygon.id
        geom = scene.geometry.get(pid)
        if geom is None:
            missing.append(pid)
            continue
        area_err = max(area_err, abs(float(geom.area) - it.polygon.area) / max(it.polygon.area, 1e-12))
        if not it.textured:
            continue
        uvs = np.asarray(geom.visual.uv, np.float64)
        img = geom.visual.material.baseColorTexture
        key = id(img)
        if key not in page_cache:
            page_cache[key] = np.asarray(img.convert("RGB"), np.float32) / 255.0
        page = page_cache[key]
        # random barycentric points, area-weighted triangle choice
        tri = rng.choice(len(geom.faces), size=samples_per_polygon, p=geom.area_faces / geom.area_faces.sum())
        r = rng.random((samples_per_polygon, 2))
        r[r.sum(1) > 1] = 1 - r[r.sum(1) > 1]
        bary = np.column_stack([1 - r.sum(1), r])
        f = geom.faces[tri]
        X = np.einsum("ij,ijk->ik", bary, geom.vertices[f])
        uv = np.einsum("ij,ijk->ik", bary, uvs[f])
        got = sample_atlas(page, uv)
        t = it.frame.world_to_texel(X) * (it.texture.shape[1] / it.frame.width)
        want = sample_photo(it.texture, t)
        if it.mask is not None:
            from scipy.ndimage import binary_erosion

            # Bilinear taps at the polygon's edge reach outside texels, which the atlas has
            # dilated and the source texture has not: compare where all four taps are inside.
            inner_mask = binary_erosion(it.mask, structure=np.ones((3, 3), bool), border_value=0)
            ix = np.clip(np.floor(t[:, 0]).astype(int), 0, it.mask.shape[1] - 1)
            iy = np.clip(np.floor(t[:, 1]).astype(int), 0, it.mask.shape[0] - 1)
            inner = inner_mask[iy, ix]
            got, want = got[inner], want[inner]
        if len(got):
            # 8-bit PNG quantisation is 1/255; bilinear sampling of both adds nothing on top
            e = float(np.abs(got - want).max())
            errs.append(e)
            if e > worst[1]:
                worst = (pid, e)
    return {
        "glb_polygons": len(scene.geometry),
        "missing_polygons": missing,
        "max_area_rel_error": area_err,
        "max_color_error": max(errs) if errs else 0.0,
        "worst_polygon": worst[0],
    }


def render_view(glb: str | Path, proxy, photo, long_side: int = 512) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Render the reloaded GLB as photo ``photo`` sees it: the project's ray caster finds the
    nearest proxy polygon per pixel, the polygon's reloaded UVs (an affine function on its plane,
    fitted to its reloaded vertices) give the atlas position, the atlas is sampled bilinearly.

    Returns (render (h, w, 3), covered (h, w) bool, pixel centres (h, w, 2)) at a stride that
    makes the long side about ``long_side``.

    Not shared with ``difftex.evaluation.views.render_proxy`` on purpose: this one checks the
    written file, so it reads everything from the reloaded GLB (its UVs, its 8-bit atlas pages with
    their dilated borders, the grey patch of untextured polygons, which it counts as covered);
    render_proxy scores a results folder's own per-polygon textures (any method's: baselines and
    peers write no GLB), through their UV frames with the photo's camera model, and must tell
    textured pixels from untextured ones and report the polygon under each pixel. Both use the
    same ray caster (``id_buffer``) and the same bilinear sampler (``sample_photo``).
    """
    import trimesh

    from difftex.geometry.visibility import id_buffer

    stride = max(1, math.ceil(max(photo.width, photo.height) / long_side))
    ids, dist = id_buffer(proxy, photo, stride=stride)
    # the same pixel centres as id_buffer's
    ys = np.minimum(np.arange(0, photo.height, stride) + (0.5 * stride if stride > 1 else 0.5), photo.height - 0.5)
    xs = np.minimum(np.arange(0, photo.width, stride) + (0.5 * stride if stride > 1 else 0.5), photo.width - 0.5)
    pix = np.stack(np.meshgrid(xs, ys), axis=-1)
    scene = trimesh.load(glb, file_type="glb", force="scene")
    out = np.zeros((*ids.shape, 3), np.float32)
    covered = np.zeros(ids.shape, bool)
    pages: dict[int, np.ndarray] = {}
    for j, poly in enumerate(proxy.polygons):
        sel = ids == j
        geom = scene.geometry.get(poly.id)
        if not sel.any() or geom is None:
            continue
        rays = photo.unproject(pix[sel])
        X = photo.center + dist[sel][:, None].astype(np.float64) * rays
        A = np.column_stack([geom.vertices, np.ones(len(geom.vertices))])
        M = np.linalg.lstsq(A, np.asarray(geom.visual.uv, np.float64), rcond=None)[0]
        uv = np.column_stack([X, np.ones(len(X))]) @ M
        img = geom.visual.material.baseColorTexture
        if id(img) not in pages:
            pages[id(img)] = np.asarray(img.convert("RGB"), np.float32) / 255.0
        out[sel] = sample_atlas(pages[id(img)], uv)
        covered |= sel
    return out, covered, pix


