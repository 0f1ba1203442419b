"""The reprojection peer: texrecon on the user's dense mesh, baked orthographically onto the proxy.

This is how production tools texture a simplified model (RealityCapture's texture reprojection,
Metashape's texture transfer): the photos texture the DENSE mesh, and that texture is then baked
onto the simplified one. Here:

1. **preparation** (:func:`prepare`): the scene's dense mesh (:func:`find_mesh`: a path, else the
   first of :data:`difftex.geometry.dense.MESH_NAMES` in ``<scene>/dense/``, else any OBJ / GLB /
   PLY mesh there) is read, checked to lie in the proxy's frame, cropped to the proxy's box grown
   by :data:`CROP_MARGIN` of its diagonal (the rest of a survey's ground cannot reach a facade's
   texels, but occluders near the building stay, for texrecon's visibility test) and decimated by
   quadric edge collapse to ``max_faces`` triangles (pymeshlab). The photos are those of the
   texrecon peer, exported the same way (:func:`difftex.evaluation.peers.run.export_photos`,
   :func:`difftex.evaluation.peers.texrecon.prepare`);
2. **program**: texrecon textures the dense mesh (:func:`difftex.evaluation.peers.texrecon.run`);
3. **bake** (:func:`collect`): every texel of each polygon's UV frame casts ``k x k`` rays from
   the plane point + H n along -n (n the outward normal; H = ``relief``, at most a fifth of the
   polygon's shorter side, as the dense relief of :class:`~difftex.geometry.heightfield.HeightFieldConfig`);
   the first hit within [-H, H] of the plane is sampled in texrecon's atlas at the hit's UV
   (bilinear). A ray that meets nothing within the slab, or a face texrecon left untextured (it
   drops the faces no photo sees), leaves its sub-texel uncovered; a texel is covered where any
   of its sub-texels is, as :func:`difftex.evaluation.peers.objimport.import_obj` counts it.

Rays are cast by Mitsuba's LLVM variant (:data:`difftex.geometry.raycast.MITSUBA_VARIANT`);
without it the same first hits come from rasterising the triangles orthographically in the frame
(:func:`_hits_raster`, numpy): all rays of a polygon are parallel, so a z-buffer along the normal
is exact. The tests compare the two.
"""

from __future__ import annotations

import shlex
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from difftex.errors import DifftexError
from difftex.evaluation.peers import texrecon
from difftex.geometry.dense import MESH_NAMES, MESH_SUFFIXES, DenseMesh, classify
from difftex.geometry.frames import UVFrame

CROP_MARGIN = 0.25  # the proxy's box grown by this share of its diagonal before decimation
RAY_CHUNK = 1 << 22  # rays per Mitsuba call (memory: about 100 bytes a ray)


# --------------------------------------------------------------------------------------------
# Availability: texrecon, and a dense mesh in the scene


def find_mesh(scene_dir: str | Path, path: str | Path | None = None) -> Path | None:
    """The dense mesh to texture: ``path`` (relative to the scene folder, or absolute) when given,
    else the first of MESH_NAMES in ``<scene>/dense/``, else its first OBJ / GLB / glTF / PLY mesh.

    Returns:
        The file, or None when ``<scene>/dense/`` holds no mesh (a point cloud is not one).
    """
    if path is not None:
        p = Path(path)
        return p if p.is_absolute() else Path(scene_dir) / p
    folder = Path(scene_dir) / "dense"
    if not folder.is_dir():
        return None
    named = [folder / n for n in MESH_NAMES]
    other = [f for s in MESH_SUFFIXES for f in sorted(folder.glob(f"*{s}")) if f not in named]
    for f in named + other:
        if f.is_file() and classify(f).kind == "mesh":
            return f
    return None


def mesh_unavailable(scene_dir: str | Path, path: str | Path | None = None) -> str:
    """Why the scene has no dense mesh for this peer ('' when it has one)."""
    f = find_mesh(scene_dir, path)
    if f is None:
        return (
            f"reprojection: {Path(scene_dir) / 'dense'} holds no dense mesh ({', '.join(MESH_NAMES)}, or an "
            "OBJ / GLB / PLY mesh); give one with --dense-mesh"
        )
    if not f.is_file():
        return f"reprojection: {f}: dense mesh not found"
    return ""


def unavailable_reason(scene_dir: str | Path | None = None, path: str | Path | None = None) -> str:
    """Why the peer cannot run ('' when it can): texrecon missing, or (given a scene) no dense mesh."""
    why = texrecon.unavailable_reason()
    if why or scene_dir is None:
        return why
    return mesh_unavailable(scene_dir, path)


def available() -> bool:
    return texrecon.available()


def check_available() -> None:
    texrecon.check_available()


def dense_mesh_path(scene_dir: str | Path, path: str | Path | None = None) -> Path:
    """The dense mesh of :func:`find_mesh`, or a DifftexError with :func:`mesh_unavailable`'s line."""
    why = mesh_unavailable(scene_dir, path)
    if why:
        raise DifftexError(why)
    return find_mesh(scene_dir, path).resolve()  # type: ignore[union-attr]


# --------------------------------------------------------------------------------------------
# Preparation: the dense mesh cropped and decimated


def crop(mesh: DenseMesh, lo: np.ndarray, hi: np.ndarray, margin: float = CROP_MARGIN) -> DenseMesh:
    """The faces with a corner inside the box (``lo``, ``hi``) grown by ``margin`` of its diagonal,
    unreferenced vertices dropped."""
    pad = margin * float(np.linalg.norm(hi - lo))
    inside = np.all((mesh.vertices >= lo - pad) & (mesh.vertices <= hi + pad), axis=1)
    faces = mesh.faces[inside[mesh.faces].any(1)]
    used, inv = np.unique(faces, return_inverse=True)
    return DenseMesh(mesh.vertices[used], inv.reshape(-1, 3).astype(np.int64))


def decimate(mesh: DenseMesh, max_faces: int) -> DenseMesh:
    """At most ``max_faces`` triangles by MeshLab's quadric edge collapse (planar regions kept
    planar, no flipped normals); the mesh itself when it is small enough."""
    if len(mesh.faces) <= max_faces:
        return mesh
    import pymeshlab

    centre = mesh.vertices.mean(0)  # MeshLab stores float32: UTM coordinates would lose centimetres
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=mesh.vertices - centre, face_matrix=mesh.faces.astype(np.int32)))
    ms.meshing_decimation_quadric_edge_collapse(targetfacenum=int(max_faces), preservenormal=True, planarquadric=True)
    ms.meshing_remove_unreferenced_vertices()
    m = ms.current_mesh()
    return DenseMesh(np.asarray(m.vertex_matrix(), np.float64) + centre, np.asarray(m.face_matrix(), np.int64))


def prepare(method: str, work: Path, cams: list, mesh, frames, cfg) -> dict:
    """texrecon's inputs with the dense mesh (``cfg.dense_mesh``) in place of the proxy's.

    Args:
        mesh: the proxy mesh (its box crops the dense one); cams: the exported pinhole cameras.
    Returns:
        texrecon's job plus the dense mesh's path and face counts (source, cropped, decimated).
    """
    from difftex.geometry.dense import check_frame, read_mesh

    if not cfg.dense_mesh:
        raise DifftexError("reprojection: no dense mesh given (run_peer finds the scene's)")
    src = Path(cfg.dense_mesh)
    dense = read_mesh(src)
    lo, hi = mesh.vertices.min(0), mesh.vertices.max(0)
    check_frame(dense.vertices, lo, hi, src)
    n_source = len(dense.faces)
    dense = crop(dense, lo, hi)
    n_cropped = len(dense.faces)
    if n_cropped == 0:
        raise DifftexError(f"{src}: no face of the dense mesh near the proxy")
    dense = decimate(dense, cfg.max_faces)
    job = texrecon.prepare("texrecon", work, cams, dense, frames, cfg)
    job.update(
        dense_mesh=str(src),
        mesh_ply=str(work / "mesh.ply"),
        faces_source=n_source,
        faces_cropped=n_cropped,
        max_faces=cfg.max_faces,
        supersample=cfg.oversample,
        relief=cfg.relief,
    )
    return job


run = texrecon.run  # the program is texrecon itself, timed the same way


# --------------------------------------------------------------------------------------------
# The textured dense mesh


@dataclass
class TexturedMesh:
    """The dense mesh as texrecon textured it.

    vertices (V, 3) float64 world; faces (F, 3) int64; uv (F, 3, 2) atlas coordinates of each
    corner (OBJ convention: v up); material (F,) atlas index, -1 for a face left untextured;
    atlases: premultiplied (H, W, 4) float32 images (r w, g w, b w, w).
    """

    vertices: np.ndarray
    faces: np.ndarray
    uv: np.ndarray
    material: np.ndarray
    atlases: list


def textured_mesh(obj: Path, vertices: np.ndarray, faces: np.ndarray) -> TexturedMesh:
    """texrecon's OBJ attached to the mesh it was given (``vertices``, ``faces``).

    texrecon writes every input vertex in order and only the faces it textured; a face keeps the
    UVs of the OBJ face on the same three vertices, the others are untextured. So rays still stop
    at faces no photo saw (they are surface) instead of passing through to what lies behind. An
    OBJ whose vertices are not the input's is used on its own (its textured faces only).
    """
    from difftex.evaluation.peers.objimport import read_atlas, read_obj, textured_triangles

    V, T, obj_faces, images = read_obj(obj)
    materials = sorted(images)
    atlases = []
    for m in materials:
        rgb, w = read_atlas(images[m], "uv")  # as the texrecon peer reads it
        atlases.append(np.concatenate([rgb * w[..., None], w[..., None]], -1))
    tv, tt, tm = textured_triangles(obj_faces, materials)
    # texrecon prints coordinates as float32: compare within their precision and a hair of the extent
    tol = 1e-4 * float(np.ptp(vertices)) + 1e-6 * float(np.abs(vertices).max())
    if len(V) != len(vertices) or not np.allclose(V, vertices, rtol=0.0, atol=tol):
        return TexturedMesh(V, tv, T[tt] if len(tv) else np.zeros((0, 3, 2)), tm, atlases)
    face_of = match_faces(faces, tv)
    ok = face_of >= 0
    uv = np.zeros((len(faces), 3, 2))
    material = np.full(len(faces), -1, np.int64)
    # the OBJ face may start at another corner: take its UVs in the input face's corner order
    for c in range(3):
        for j in range(3):
            same = ok & (faces[:, c] == tv[np.maximum(face_of, 0), j])
            uv[same, c] = T[tt[face_of[same], j]]
    material[ok] = tm[face_of[ok]]
    return TexturedMesh(np.asarray(vertices, np.float64), np.asarray(faces, np.int64), uv, material, atlases)


def match_faces(faces: np.ndarray, other: np.ndarray) -> np.ndarray:
    """(F,) index of the face of ``other`` (M, 3) on the same three vertices, -1 for none."""
    if len(other) == 0:
        return np.full(len(faces), -1, np.int64)
    keys = np.concatenate([np.sort(faces, 1), np.sort(other, 1)])
    _, inv = np.unique(keys, axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    lookup = np.full(inv.max() + 1, -1, np.int64)
    lookup[inv[len(faces) :]] = np.arange(len(other))
    return lookup[inv[: len(faces)]]


# --------------------------------------------------------------------------------------------
# First hits along the normal


class Caster:
    """A triangle mesh prepared for orthographic first-hit queries over UV frames.

    ``backend``: "mitsuba" (Mitsuba's LLVM variant), "numpy" (a z-buffer along the normal), or
    "auto" (Mitsuba when its LLVM variant loads).
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, backend: str = "auto"):
        from difftex.geometry.raycast import mitsuba_available

        if backend == "auto":
            backend = "mitsuba" if mitsuba_available() else "numpy"
        if backend not in ("mitsuba", "numpy"):
            raise ValueError(f"backend must be auto, mitsuba or numpy, got {backend!r}")
        self.backend = backend
        self.vertices, self.faces = np.asarray(vertices, np.float64), np.asarray(faces, np.int64)
        self.centre = self.vertices.mean(0) if len(self.vertices) else np.zeros(3)  # float32 frame origin
        self._scene: Any = self._mitsuba_scene() if backend == "mitsuba" and len(self.faces) else None

    def _mitsuba_scene(self):
        from difftex.geometry.raycast import mitsuba_scene

        return mitsuba_scene(self.vertices - self.centre, self.faces)

    def hits(self, frame: UVFrame, lo: float, hi: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The first surface along -n from height ``hi`` down to ``lo`` at every texel centre.

        Returns:
            (face (H, W) int64, -1 for none; barycentrics (H, W, 3) of the hit in the face's
            corners; height (H, W) float64 of the hit along the normal, NaN for none).
        """
        if not len(self.faces):
            return np.full(frame.shape, -1, np.int64), np.zeros((*frame.shape, 3)), np.full(frame.shape, np.nan)
        if self.backend == "mitsuba":
            return self._hits_mitsuba(frame, lo, hi)
        return _hits_raster(self.vertices, self.faces, frame, lo, hi)

    def _hits_mitsuba(self, frame: UVFrame, lo: float, hi: float):
        import mitsuba as mi

        tx, ty = frame.centres()
        o = (frame.texel_to_world(tx, ty) + hi * frame.normal - self.centre).reshape(-1, 3).astype(np.float32)
        d = (-np.asarray(frame.normal)).astype(np.float32)
        n = len(o)
        face, bary, t = np.full(n, -1, np.int64), np.zeros((n, 3)), np.full(n, np.inf)
        for a in range(0, n, RAY_CHUNK):
            oo = o[a : a + RAY_CHUNK]
            ray = mi.Ray3f(mi.Point3f(oo[:, 0], oo[:, 1], oo[:, 2]), mi.Vector3f(*d.tolist()))
            ray.maxt = float(hi - lo)  # type: ignore[assignment]  # drjit broadcasts it
            pi = self._scene.ray_intersect_preliminary(ray)
            tt = np.asarray(pi.t, np.float64)
            hit = np.isfinite(tt) & (tt <= hi - lo)
            uv = np.asarray(pi.prim_uv, np.float64).reshape(2, -1)  # weights of corners 1 and 2
            s = slice(a, a + len(oo))
            face[s] = np.where(hit, np.asarray(pi.prim_index, np.int64), -1)
            bary[s] = np.stack([1.0 - uv[0] - uv[1], uv[0], uv[1]], -1) * hit[:, None]
            t[s] = np.where(hit, tt, np.inf)
        h = np.where(face >= 0, hi - t, np.nan)
        return face.reshape(frame.shape), bary.reshape(*frame.shape, 3), h.reshape(frame.shape)


def _hits_raster(V: np.ndarray, F: np.ndarray, frame: UVFrame, lo: float, hi: float):
    """:meth:`Caster.hits` by rasterising the faces in the frame: every texel keeps the highest
    of the heights (along n) of the faces over it within [lo, hi]. An orthographic projection
    keeps barycentric coordinates, so the frame's are the hit's."""
    from difftex.evaluation.peers.objimport import raster_triangles

    corners = V[F]  # (F, 3, 3)
    hc = (corners - frame.origin) @ frame.normal  # (F, 3) corner heights
    tc = frame.world_to_texel(corners)  # (F, 3, 2)
    near = (hc.min(1) <= hi) & (hc.max(1) >= lo)
    near &= (tc[..., 0].max(1) >= 0) & (tc[..., 0].min(1) <= frame.width)
    near &= (tc[..., 1].max(1) >= 0) & (tc[..., 1].min(1) <= frame.height)
    sel = np.nonzero(near)[0]
    face = np.full(frame.shape, -1, np.int64)
    bary = np.zeros((*frame.shape, 3))
    height = np.full(frame.shape, np.nan)
    rr, cc, ti, lam = raster_triangles(frame.shape, tc[sel])
    h = np.einsum("nk,nk->n", lam, hc[sel[ti]])
    keep = (h >= lo) & (h <= hi)
    rr, cc, ti, lam, h = rr[keep], cc[keep], ti[keep], lam[keep], h[keep]
    pix = rr * frame.width + cc
    order = np.lexsort((sel[ti], -h, pix))  # per texel the highest first; on an edge, the lower face index
    first = order[np.r_[True, pix[order][1:] != pix[order][:-1]]] if len(order) else order
    face[rr[first], cc[first]] = sel[ti[first]]
    bary[rr[first], cc[first]] = lam[first]
    height[rr[first], cc[first]] = h[first]
    return face, bary, height


# --------------------------------------------------------------------------------------------
# The bake


def relief_bounds(frame: UVFrame, relief: float) -> tuple[float, float]:
    """[-H, H]: ``relief`` scene units, at most the dense relief's share of the polygon's shorter side."""
    from difftex.geometry.heightfield import HeightFieldConfig

    return HeightFieldConfig(range=(-relief, relief)).bounds(frame)


def bake_polygon(
    tm: TexturedMesh,
    caster: Caster,
    frame: UVFrame,
    mask: np.ndarray,
    k: int,
    relief: float,
    labels: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """One polygon's texture from the textured mesh, seen orthographically along its normal.

    Args:
        tm: the textured mesh; caster: its faces prepared for casting (the same faces).
        frame, mask: the polygon's UV frame and (H, W) texel mask.
        k: rays per texel along each axis (sub-texel centres, box-averaged).
        relief: H of :func:`relief_bounds`.
        labels: (F,) texrecon's view label per face (0 none, l: photo l - 1), or None.
    Returns:
        (texture (H, W, 3) float32, 0 where uncovered; covered (H, W) bool; the dominant photo
        index per texel (H, W), -1 where unknown, or None without labels).
    """
    lo, hi = relief_bounds(frame, relief)
    # in bands of rows: a full-density frame at k x k rays a texel holds tens of millions of rays
    rows = max(1, RAY_CHUNK // (k * k * frame.width))
    parts = [
        _bake_band(tm, caster, _band(frame, r, min(rows, frame.height - r)), k, lo, hi, labels)
        for r in range(0, frame.height, rows)
    ]
    tex = np.concatenate([p[0] for p in parts])
    cov_down = np.concatenate([p[1] for p in parts]) & mask
    src = np.where(cov_down, np.concatenate([p[2] for p in parts]), -1) if labels is not None else None
    return np.where(cov_down[..., None], tex, 0.0).astype(np.float32), cov_down, src


def _band(frame: UVFrame, row: int, rows: int) -> UVFrame:
    """Rows ``row`` .. ``row + rows`` of the frame as a frame of their own."""
    origin = frame.origin + row * frame.texel_size * frame.e_v
    return UVFrame(origin, frame.e_u, frame.e_v, frame.normal, frame.texel_size, frame.width, rows)


def _bake_band(
    tm: TexturedMesh, caster: Caster, frame: UVFrame, k: int, lo: float, hi: float, labels: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """:func:`bake_polygon` on one band of rows, without the mask: (texture, covered, sources or None)."""
    from difftex.evaluation.peers.objimport import box_down, fine_frame
    from difftex.geometry.frames import sample_photo

    face, bary, _ = caster.hits(fine_frame(frame, k), lo, hi)
    acc = np.zeros((*face.shape, 4), np.float32)
    mat = np.where(face >= 0, tm.material[np.maximum(face, 0)], -1)
    for m in np.unique(mat[mat >= 0]):
        j = mat == m
        uv = np.einsum("nk,nkd->nd", bary[j], tm.uv[face[j]])
        ih, iw = tm.atlases[m].shape[:2]
        acc[j] = sample_photo(tm.atlases[m], np.stack([uv[:, 0] * iw, (1 - uv[:, 1]) * ih], -1))
    w = acc[..., 3]
    cov = w >= 0.5  # as objimport.import_obj: covered where the atlas holds colour
    tex = np.where(cov[..., None], acc[..., :3] / np.maximum(w, 1e-6)[..., None], 0.0).astype(np.float32)
    tex, cov_down = box_down(tex, cov, k)
    src = block_mode(np.where(cov, labels[np.maximum(face, 0)] - 1, -1), k) if labels is not None else None
    return tex, cov_down, src


def block_mode(lab: np.ndarray, k: int) -> np.ndarray:
    """(H, W) the most frequent value >= 0 of every k x k block of ``lab`` (kH, kW), -1 where none."""
    H, W = lab.shape[0] // k, lab.shape[1] // k
    b = lab.reshape(H, k, W, k).transpose(0, 2, 1, 3).reshape(H, W, k * k)
    counts = np.stack([((b == b[..., i : i + 1]) & (b >= 0)).sum(-1) for i in range(k * k)], -1)
    best = np.take_along_axis(b, counts.argmax(-1)[..., None], -1)[..., 0]
    return np.where(counts.max(-1) > 0, best, -1)


def collect(job: dict, work: Path, frames, mesh) -> tuple[dict, dict | None, dict]:
    """(baked textures, per-polygon source photo maps or None, report extras) from texrecon's OBJ.

    ``mesh`` (the proxy's) is not used: the bake reads the dense mesh texrecon was given.
    """
    from difftex.geometry.dense import read_mesh

    obj = Path(job["prefix"] + ".obj")
    if not obj.is_file():
        raise DifftexError(f"{obj}: texrecon wrote no textured model")
    dense = read_mesh(Path(job["mesh_ply"]))
    tm = textured_mesh(obj, dense.vertices, dense.faces)
    labels = texrecon.read_labels(Path(job["prefix"] + "_labeling.vec"), len(tm.faces))
    caster = Caster(tm.vertices, tm.faces)
    imported: dict = {}
    sources: dict | None = {} if labels is not None else None
    for pid, fr in frames.frames.items():
        tex, cov, src = bake_polygon(tm, caster, fr, frames.masks[pid], job["supersample"], job["relief"], labels)
        imported[pid] = (tex, cov)
        if sources is not None:
            sources[pid] = src
    job["bake_backend"] = caster.backend
    job["textured_faces"] = int((tm.material >= 0).sum())
    return (
        imported,
        sources,
        {"source_map": "texrecon view selection on the dense mesh" if labels is not None else None},
    )


def describe(job: dict) -> dict:
    """What ran: texrecon's command and the dense mesh it textured (cropped, decimated), the bake."""
    from difftex.geometry.heightfield import HeightFieldConfig

    n, cropped, cap, k = job["faces"], job["faces_cropped"], job["max_faces"], job["supersample"]
    return {
        "program": "texrecon",
        "command": shlex.join(job["cmd"]),
        "dense_mesh": job["dense_mesh"],
        "dense_faces": {"source": job["faces_source"], "cropped": cropped, "to_texrecon": n},
        "decimation": f"quadric edge collapse {cropped} -> {n} faces (max_faces {cap})"
        if n < cropped
        else f"none ({n} faces <= max_faces {cap})",
        "crop": f"faces within the proxy's box grown by {CROP_MARGIN} of its diagonal",
        "bake": f"orthographic along each polygon's normal, {k}x{k} rays per texel from +H to -H, H = "
        f"min({job['relief']}, {HeightFieldConfig.max_share} x the polygon's shorter side); the first hit's atlas "
        "colour, bilinear",
        "bake_backend": job.get("bake_backend"),
        "textured_faces_in_obj": job.get("textured_faces"),
    }
