"""Ways to break a scene, for the failure tests: each takes a scene folder (a copy) and edits it."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np

TEMP_GLOB = ".*.part*"  # difftex.scene.files.atomic_path's temporary files


def copy_scene(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst)
    return dst


def data_lines(path: Path) -> list[tuple[int, list[str]]]:
    """(index, tokens) of the non-comment, non-empty lines of a COLMAP text file."""
    lines = path.read_text().splitlines()
    return [(i, ln.split()) for i, ln in enumerate(lines) if ln.strip() and not ln.startswith("#")]


def edit_tokens(path: Path, which: int, edit) -> None:
    """Apply ``edit(tokens) -> tokens`` to the ``which``-th data line of a COLMAP text file.
    In images.txt the data lines alternate image line / points line (points lines may be
    empty and are then not counted): use ``image_line`` for images."""
    lines = path.read_text().splitlines()
    i, tokens = data_lines(path)[which]
    lines[i] = " ".join(edit(list(tokens)))
    path.write_text("\n".join(lines) + "\n")


def image_lines(path: Path) -> list[int]:
    """Line indices of the image lines of images.txt (each followed by its points line)."""
    lines = path.read_text().splitlines()
    out, i = [], 0
    while i < len(lines):
        s = lines[i].strip()
        if s and not s.startswith("#"):
            out.append(i)
            i += 2
        else:
            i += 1
    return out


def edit_image(scene: Path, k: int, edit) -> None:
    """Apply ``edit(tokens) -> tokens`` to the k-th image line of sparse/0/images.txt."""
    path = scene / "sparse/0/images.txt"
    lines = path.read_text().splitlines()
    i = image_lines(path)[k]
    lines[i] = " ".join(edit(lines[i].split()))
    path.write_text("\n".join(lines) + "\n")


def append_image(scene: Path, tokens: list[str], points: str = "") -> None:
    path = scene / "sparse/0/images.txt"
    path.write_text(path.read_text().rstrip("\n") + "\n" + " ".join(tokens) + "\n" + points + "\n")


def first_image_tokens(scene: Path) -> list[str]:
    path = scene / "sparse/0/images.txt"
    return path.read_text().splitlines()[image_lines(path)[0]].split()


def set_camera(scene: Path, k: int, edit) -> None:
    edit_tokens(scene / "sparse/0/cameras.txt", k, edit)


def transform_proxy(scene: Path, fn) -> None:
    """Apply ``fn(vertices (N, 3)) -> (N, 3)`` to every 'v' line of proxy.obj."""
    path = scene / "proxy.obj"
    lines = path.read_text().splitlines()
    idx = [i for i, ln in enumerate(lines) if ln.startswith("v ")]
    V = np.array([[float(x) for x in lines[i].split()[1:4]] for i in idx])
    W = fn(V)
    for i, v in zip(idx, W):
        lines[i] = "v {:.12g} {:.12g} {:.12g}".format(*v)
    path.write_text("\n".join(lines) + "\n")


def scale_proxy(scene: Path, factor: float) -> None:
    transform_proxy(scene, lambda V: (V - V.mean(0)) * factor + V.mean(0))


def add_polygon(scene: Path, name: str, loop) -> None:
    """Append an n-gon group to proxy.obj."""
    path = scene / "proxy.obj"
    text = path.read_text().rstrip("\n")
    nv = sum(1 for ln in text.splitlines() if ln.startswith("v "))
    loop = np.asarray(loop, float)
    vs = "\n".join("v {:.12g} {:.12g} {:.12g}".format(*v) for v in loop)
    face = "f " + " ".join(str(nv + 1 + i) for i in range(len(loop)))
    path.write_text(f"{text}\n{vs}\ng {name}\n{face}\n")


def turn_camera_around(scene: Path, k: int) -> None:
    """Rotate the k-th image's camera by 180 degrees about its own y axis (same centre): it looks
    away from the building."""
    from scipy.spatial.transform import Rotation

    def edit(t):
        qw, qx, qy, qz = map(float, t[1:5])
        R = Rotation.from_quat([qx, qy, qz, qw]).as_matrix()
        D = np.diag([-1.0, 1.0, -1.0])
        x, y, z, w = Rotation.from_matrix(D @ R).as_quat()
        tv = D @ np.array(list(map(float, t[5:8])))
        return [t[0], *(f"{v:.17g}" for v in (w, x, y, z, *tv)), *t[8:]]

    edit_image(scene, k, edit)


def n_images(scene: Path) -> int:
    return len(image_lines(scene / "sparse/0/images.txt"))


def temp_files(folder: Path) -> list[Path]:
    """difftex's temporary files left under ``folder`` (there must be none)."""
    return sorted(Path(folder).rglob(TEMP_GLOB)) if Path(folder).exists() else []


def make_unwritable(folder: Path):
    """Make ``folder`` unwritable for this process; returns an undo function, or None when
    that is impossible here (root without the immutable attribute)."""
    import os
    import subprocess

    folder.mkdir(parents=True, exist_ok=True)
    if os.geteuid() != 0:
        folder.chmod(0o555)
        return lambda: folder.chmod(0o755)
    r = subprocess.run(["chattr", "+i", str(folder)], capture_output=True)
    if r.returncode != 0:
        return None
    return lambda: subprocess.run(["chattr", "-i", str(folder)], check=True)
