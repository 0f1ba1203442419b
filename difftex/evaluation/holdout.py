"""Held-out photos for evaluation (paper Table 2): a copy of a scene whose COLMAP model lacks some
photos, which difftex.evaluation.evaluate later renders the textured proxy into."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np

from difftex.errors import DifftexError
from difftex.scene.camera import read_reconstruction
from difftex.scene.files import write_json, write_text
from difftex.scene.loading import find_proxy, find_sparse


def _pick_holdout(names: list[str], holdout) -> list[str]:
    """N evenly spread photo names (an int), or the given names (a list)."""
    if isinstance(holdout, int):
        if holdout == 0:
            return []
        if not 0 < holdout < len(names):
            raise DifftexError(f"holdout: need 0 < N < {len(names)} photos, got {holdout}")
        idx = np.linspace(0, len(names) - 1, holdout + 2)[1:-1].round().astype(int)
        return [names[i] for i in sorted(set(idx.tolist()))]
    missing = [n for n in holdout if n not in names]
    if missing:
        raise DifftexError(f"holdout: photo(s) not in the scene: {', '.join(missing[:3])}")
    return list(holdout)


def prepare_holdout(scene: str | Path, holdout, out: str | Path, keep: list[str] | None = None) -> dict:
    """A copy of ``scene`` whose COLMAP model lacks the held-out photos (and any not in ``keep``).

    Images and the proxy are symlinked; the text model is rewritten (held-out images removed,
    their observations dropped from the point tracks). ``holdout.json`` in the copy names the
    held-out photos and the original scene, which :func:`evaluate_results` renders into.
    """
    scene, out = Path(scene).resolve(), Path(out)
    sparse = find_sparse(scene)
    rec = read_reconstruction(sparse)
    names = sorted(im.name for im in rec.images.values())
    held = _pick_holdout(names, holdout)
    drop_names = set(held) | (set(names) - set(keep) if keep is not None else set())
    drop = {int(iid) for iid, im in rec.images.items() if im.name in drop_names}
    if out.exists():
        shutil.rmtree(out)
    (out / "images").mkdir(parents=True)
    (out / "sparse" / "0").mkdir(parents=True)
    tmp = out / "sparse" / "_txt"
    if (sparse / "images.txt").is_file():
        tmp = sparse
    else:
        tmp.mkdir()
        rec.write_text(str(tmp))
    for n in names:
        if n not in drop_names:
            dst = out / "images" / n
            dst.parent.mkdir(parents=True, exist_ok=True)
            dst.symlink_to((scene / "images" / n).resolve())
    prox = find_proxy(scene)
    (out / prox.name).symlink_to(prox)
    for extra in ("ground_truth", "synth.json"):  # synthetic scenes keep their ground truth
        if (scene / extra).exists():
            (out / extra).symlink_to((scene / extra).resolve())
    shutil.copyfile(tmp / "cameras.txt", out / "sparse" / "0" / "cameras.txt")
    # The text model is edited line by line, not through pycolmap (deregister the images, write the
    # model): a pycolmap round trip rewrites every pose and point at its own float precision, and
    # since pycolmap 4 an image belongs to a frame and a rig that would have to be cut too. Here the
    # kept images' poses and the points' coordinates are copied byte for byte, so the cut scene
    # holds exactly the model of the full one minus the held-out photos.
    lines = (tmp / "images.txt").read_text().splitlines()
    kept, i = [], 0
    while i < len(lines):
        ln = lines[i]
        if ln.startswith("#") or not ln.strip():
            kept.append(ln) if ln.startswith("#") else None
            i += 1
            continue
        pose, pts = ln, lines[i + 1] if i + 1 < len(lines) else ""
        i += 2
        if int(pose.split()[0]) in drop:
            continue
        kept += [pose, pts]
    write_text(out / "sparse" / "0" / "images.txt", "\n".join(kept) + "\n")
    p3 = []
    for ln in (tmp / "points3D.txt").read_text().splitlines():
        if ln.startswith("#") or not ln.strip():
            p3.append(ln)
            continue
        f = ln.split()
        track = [(f[k], f[k + 1]) for k in range(8, len(f) - 1, 2) if int(f[k]) not in drop]
        if len(track) < 2:
            continue
        p3.append(" ".join(f[:8] + [x for pair in track for x in pair]))
    write_text(out / "sparse" / "0" / "points3D.txt", "\n".join(p3) + "\n")
    if tmp.name == "_txt":
        shutil.rmtree(tmp)
    info = {"original_scene": str(scene), "held_out": held, "removed": sorted(drop_names),
            "kept": [n for n in names if n not in drop_names]}
    write_json(out / "holdout.json", info)
    return info
