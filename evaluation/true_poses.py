"""A synthetic scene with the poses its photos were rendered at: the bound of perfect registration.

    python evaluation/true_poses.py --scene data/synth/survey/gable --out evaluation/out/gable_true_poses

`difftex synth` renders every photo at its true pose and writes a pose with noise added
(`pose_noise_rot_deg`, `pose_noise_trans`), as a bundle adjustment would leave it; the true pose
of each photo is in synth.json (`views[].R_true`, `t_true`). This writes a scene folder whose
COLMAP model carries the true poses (images.txt and frames.txt rewritten, everything else
linked), so any command that takes a scene (variants.py, table1.py) measures what texturing would
reach with the photos registered exactly: the bound that alignment refinement works towards.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

LINKED = ("images", "ground_truth", "proxy.obj", "synth.json")
COPIED = ("cameras.txt", "points3D.txt", "rigs.txt")


def true_pose_fields(view: dict) -> list[str]:
    """QW QX QY QZ TX TY TZ of a view's true world-to-camera pose, as COLMAP writes them."""
    q = Rotation.from_matrix(np.asarray(view["R_true"], dtype=np.float64)).as_quat()  # x, y, z, w
    return [repr(float(v)) for v in (q[3], q[0], q[1], q[2], *view["t_true"])]


def rewrite_images(text: str, true: dict[str, list[str]]) -> tuple[str, dict[str, list[str]]]:
    """images.txt with each image's pose replaced; also image id -> its new pose fields."""
    lines, out, by_id, i = text.split("\n"), [], {}, 0
    while i < len(lines):
        line = lines[i]
        if line.startswith("#") or not line.strip():
            out.append(line)
            i += 1
            continue
        f = line.split()
        f[1:8] = true[f[9]]
        by_id[f[0]] = f[1:8]
        out += [" ".join(f), lines[i + 1] if i + 1 < len(lines) else ""]
        i += 2
    return "\n".join(out), by_id


def rewrite_frames(text: str, by_id: dict[str, list[str]]) -> str:
    """frames.txt (one camera per frame) with each frame's rig-from-world pose replaced."""
    out = []
    for line in text.splitlines():
        f = line.split(" ")
        if not line.startswith("#") and len(f) > 9:
            f[2:9] = by_id[f[-1]]  # the frame's data id is its image's
        out.append(" ".join(f))
    return "\n".join(out) + "\n"


def write_true_pose_scene(scene: Path, out: Path) -> int:
    """Write ``out``; returns the number of photos whose pose was replaced."""
    meta = json.loads((scene / "synth.json").read_text())
    true = {v["name"]: true_pose_fields(v) for v in meta["views"] if "R_true" in v}
    if not true:
        raise ValueError(f"{scene / 'synth.json'}: no true poses (views[].R_true); not a difftex synth scene")
    sparse = scene / "sparse" / "0"
    tmp = out.with_name(out.name + ".tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    (tmp / "sparse" / "0").mkdir(parents=True)
    for name in LINKED:
        os.symlink((scene / name).resolve(), tmp / name)
    for name in COPIED:
        if (sparse / name).exists():
            shutil.copy(sparse / name, tmp / "sparse" / "0" / name)
    images, by_id = rewrite_images((sparse / "images.txt").read_text(), true)
    (tmp / "sparse" / "0" / "images.txt").write_text(images)
    if (sparse / "frames.txt").exists():
        (tmp / "sparse" / "0" / "frames.txt").write_text(rewrite_frames((sparse / "frames.txt").read_text(), by_id))
    shutil.rmtree(out, ignore_errors=True)
    tmp.rename(out)
    return len(by_id)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", required=True, type=Path)
    ap.add_argument("--out", required=True, type=Path)
    a = ap.parse_args(argv)
    for need in (a.scene / "synth.json", a.scene / "sparse" / "0" / "images.txt"):
        if not need.exists():
            print(f"true_poses: {need}: missing (a difftex synth scene with a text COLMAP model is needed)")
            return 2
    try:
        n = write_true_pose_scene(a.scene, a.out)
    except (ValueError, KeyError) as e:
        print(f"true_poses: {e}")
        return 2
    print(f"true_poses: {a.out} ({n} photos at their true poses)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
