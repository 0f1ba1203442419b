"""mvs-texturing's ``texrecon`` as an extra baseline, run on the same scene and scored the same way.

``texrecon`` is a C++ program (Waechter et al. 2014); it is used only when an executable of that
name is on PATH (the evaluation commands skip it cleanly otherwise). The scene is exported in
its "scene folder" format (one ``.cam`` file per image: world-to-camera ``t``, ``R`` on the
first line, ``f d0 d1 paspect ppx ppy`` with ``f`` divided by the larger image side and the
principal point by width / height), the proxy as a triangulated PLY. Its textured OBJ is then
read back into difftex's per-polygon UV frames by :func:`import_obj`: every polygon texel is
located in the OBJ triangle lying on the polygon's plane that contains it, and the material's
image is sampled at the interpolated UV. ``import_obj`` works for any textured OBJ of the proxy
(difftex's own assembled model is used to test it).

Distortion: COLMAP's radial coefficients are not passed (texrecon expects undistorted images);
for the distorted real scene (lund-door, k = -0.03) this costs texrecon a little accuracy at
the image borders.
"""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import numpy as np

from difftex.errors import DifftexError


def available() -> bool:
    return shutil.which("texrecon") is not None


def cam_file_text(photo) -> str:
    K = photo.K()
    w, h = photo.width, photo.height
    f = K[0, 0] / max(w, h)
    t = " ".join(f"{x:.12g}" for x in photo.t)
    R = " ".join(f"{x:.12g}" for x in photo.R.reshape(-1))
    return f"{t} {R}\n{f:.12g} 0 0 {K[1, 1] / K[0, 0]:.12g} {K[0, 2] / w:.12g} {K[1, 2] / h:.12g}\n"


def export_scene(scene, out: Path) -> tuple[Path, Path]:
    """(scene folder, mesh.ply) for texrecon from a loaded difftex Scene."""
    import trimesh

    from difftex.assemble import triangulate
    from difftex.io import write_text

    sdir = out / "texrecon_scene"
    sdir.mkdir(parents=True, exist_ok=True)
    for ph in scene.photos:
        stem = Path(ph.name).stem
        link = sdir / (stem + Path(ph.name).suffix)
        if not link.exists():
            link.symlink_to(Path(ph.image_path).resolve())
        write_text(sdir / f"{stem}.cam", cam_file_text(ph))
    V, F = [], []
    for poly in scene.proxy.polygons:
        v, t = triangulate(poly)
        F.append(t + sum(len(x) for x in V))
        V.append(v)
    mesh = trimesh.Trimesh(np.concatenate(V), np.concatenate(F), process=False)
    ply = out / "proxy_mesh.ply"
    mesh.export(ply)
    return sdir, ply


def read_obj(path: Path) -> tuple[np.ndarray, np.ndarray, list[tuple[list[int], list[int], str]], dict[str, Path]]:
    """(positions, uvs, faces as (vertex ids, uv ids, material), material -> image) of an OBJ."""
    path = Path(path)
    V, T, faces, mtl_files = [], [], [], []
    mat = ""
    for ln in path.read_text().splitlines():
        p = ln.split()
        if not p:
            continue
        if p[0] == "v":
            V.append([float(x) for x in p[1:4]])
        elif p[0] == "vt":
            T.append([float(x) for x in p[1:3]])
        elif p[0] == "usemtl":
            mat = p[1]
        elif p[0] == "mtllib":
            mtl_files.append(path.parent / " ".join(p[1:]))
        elif p[0] == "f":
            vi, ti = [], []
            for c in p[1:]:
                s = c.split("/")
                vi.append(int(s[0]) - 1 if int(s[0]) > 0 else len(V) + int(s[0]))
                ti.append((int(s[1]) - 1 if int(s[1]) > 0 else len(T) + int(s[1])) if len(s) > 1 and s[1] else -1)
            faces.append((vi, ti, mat))
    images = {}
    for mf in mtl_files:
        cur = None
        for ln in mf.read_text().splitlines():
            p = ln.split()
            if p and p[0] == "newmtl":
                cur = p[1]
            elif p and p[0] == "map_Kd" and cur is not None:
                images[cur] = mf.parent / p[-1]
    return np.asarray(V, float).reshape(-1, 3), np.asarray(T, float).reshape(-1, 2), faces, images


def import_obj(obj: Path, frames: dict, masks: dict, plane_tol: float = 1e-3) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Per polygon id: (texture (H, W, 3) in its UV frame, covered (H, W) bool) from a textured OBJ."""
    from skimage.draw import polygon as fill

    from difftex.io import read_image
    from difftex.mapping import sample_photo

    V, T, faces, images = read_obj(obj)
    pix = {m: read_image(p) for m, p in images.items()}
    out = {}
    for pid, fr in frames.items():
        H, W = fr.shape
        tex = np.zeros((H, W, 3), np.float32)
        cov = np.zeros((H, W), bool)
        scale = max(fr.width, fr.height) * fr.texel_size
        for vi, ti, mat in faces:
            P = V[vi]
            if np.abs((P - fr.origin) @ fr.normal).max() > plane_tol * scale or mat not in pix or min(ti) < 0:
                continue
            uv = T[ti]
            for k in range(1, len(vi) - 1):  # fan triangulation of n-gons
                tri = [0, k, k + 1]
                t = fr.world_to_texel(P[tri])
                rr, cc = fill(t[:, 1] - 0.5, t[:, 0] - 0.5, shape=(H, W))
                if len(rr) == 0:
                    continue
                # barycentric coordinates of the texel centres in the triangle
                a, b, c = t
                M = np.array([[b[0] - a[0], c[0] - a[0]], [b[1] - a[1], c[1] - a[1]]])
                if abs(np.linalg.det(M)) < 1e-12:
                    continue
                q = np.stack([cc + 0.5 - a[0], rr + 0.5 - a[1]])
                l12 = np.linalg.solve(M, q)
                lam = np.stack([1 - l12[0] - l12[1], l12[0], l12[1]], -1)
                u = lam @ uv[tri]
                img = pix[mat]
                ih, iw = img.shape[:2]
                p_img = np.stack([u[:, 0] * iw, (1 - u[:, 1]) * ih], -1)
                tex[rr, cc] = sample_photo(img, p_img)
                cov[rr, cc] = True
        out[pid] = (tex, cov & masks[pid])
    return out


def run_scene(scene_dir: Path, out: Path, visibility_dir: Path, polygon_ids: list[str], timeout_s: int = 3600) -> dict:
    """Run texrecon on a scene and write difftex-style per-polygon outputs under ``out/textures``."""
    import time

    from difftex.scene import load_scene
    from difftex.outputs import write_texture_outputs
    from difftex.texture import finish_texture
    from difftex.visibility import load_visibility

    if not available():
        raise DifftexError("texrecon: no 'texrecon' executable on PATH (install mvs-texturing)")
    t0 = time.perf_counter()
    out = Path(out)
    if out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True)
    (out / "visibility.txt").write_text(str(Path(visibility_dir).resolve()))
    sc = load_scene(scene_dir)
    sdir, ply = export_scene(sc, out)
    prefix = out / "texrecon" / "model"
    prefix.parent.mkdir(parents=True)
    log = out / "texrecon.log"
    with open(log, "w") as fh:
        rc = subprocess.run(["texrecon", str(sdir), str(ply), str(prefix)], stdout=fh, stderr=subprocess.STDOUT,
                            timeout=timeout_s).returncode
    if rc != 0 or not prefix.with_suffix(".obj").is_file():
        raise DifftexError(f"texrecon failed (exit {rc}); see {log}")
    t_run = time.perf_counter() - t0
    vis = {pid: load_visibility(Path(visibility_dir) / f"{pid}.npz") for pid in polygon_ids}
    got = import_obj(prefix.with_suffix(".obj"), {p: v.frame for p, v in vis.items()}, {p: v.texel_mask for p, v in vis.items()})
    for pid, (tex, cov) in got.items():
        U, fill = finish_texture(tex, cov.astype(np.float32), vis[pid].texel_mask)
        write_texture_outputs(out / "textures" / pid, U, vis[pid].texel_mask, cov, np.full(cov.shape, -1), [],
                              {"polygon_id": pid, "method": "texrecon", **fill, "time_s": t_run / max(len(got), 1)})
    return {"texrecon_s": t_run, "total_s": time.perf_counter() - t0}
