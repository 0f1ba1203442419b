"""Pictures for a person: a contact sheet of photos, the proxy drawn on one, the truth maps."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def _savefig(fig, path: Path) -> None:
    from difftex.scene.files import atomic_path

    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100)


def write_previews(scene_dir: Path, views, intr_by_id, polygons, max_photos: int = 16) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from difftex.scene.files import read_image

    out = scene_dir / "preview"
    step = max(1, len(views) // max_photos)
    picks = views[::step][:max_photos]
    cols = 4
    rows = int(np.ceil(len(picks) / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(cols * 3.2, rows * 2.6), squeeze=False)
    for ax in axes.ravel():
        ax.axis("off")
    for ax, v in zip(axes.ravel(), picks):
        ax.imshow(read_image(scene_dir / "images" / v.name))
        ax.set_title(f"{v.name} ({v.kind}, gain {v.gain:.2f})", fontsize=7)
    fig.tight_layout()
    _savefig(fig, out / "contact_sheet.png")
    plt.close(fig)

    # proxy overlay on the photo that sees most polygons, drawn with the *written* camera
    def n_seen(v):
        return sum(((p.outer @ v.R_written.T + v.t_written)[:, 2] > 0).all() for p in polygons)

    v = max(views, key=n_seen)
    c = intr_by_id[v.camera_id]
    cam = c.pycolmap()
    fig, ax = plt.subplots(figsize=(c.width / 100 * 2, c.height / 100 * 2))
    ax.imshow(read_image(scene_dir / "images" / v.name), extent=(0, c.width, c.height, 0))
    for p in polygons:
        loop = np.concatenate([p.outer, p.outer[:1]])
        dense = np.concatenate([np.linspace(loop[i], loop[i + 1], 20) for i in range(len(p.outer))])
        Xc = dense @ v.R_written.T + v.t_written
        if (Xc[:, 2] <= 0.1).any():
            continue
        xy = np.asarray(cam.img_from_cam(Xc))
        ax.plot(xy[:, 0], xy[:, 1], "-", color="yellow", lw=0.8)
        m = xy.mean(0)
        ax.text(m[0], m[1], p.id, color="yellow", fontsize=6, ha="center")
    ax.set_xlim(0, c.width)
    ax.set_ylim(c.height, 0)
    ax.axis("off")
    ax.set_title(f"proxy over {v.name} (written camera)", fontsize=8)
    fig.tight_layout()
    _savefig(fig, out / "proxy_overlay.png")
    plt.close(fig)

    n = len(polygons)
    cols = min(4, n)
    rows = int(np.ceil(n / cols))
    fig, axes = plt.subplots(rows, cols, figsize=(cols * 3.2, rows * 2.8), squeeze=False)
    for ax in axes.ravel():
        ax.axis("off")
    for ax, p in zip(axes.ravel(), polygons):
        img = read_image(scene_dir / "ground_truth" / "maps" / f"{p.id}.png")
        mask = read_image(scene_dir / "ground_truth" / "masks" / f"{p.id}.png")[..., 0] > 0.5
        img = img.copy()
        img[~mask] = img[~mask] * 0.35
        ax.imshow(img)
        ax.set_title(f"{p.id} {img.shape[1]}x{img.shape[0]}", fontsize=7)
    fig.tight_layout()
    _savefig(fig, out / "ground_truth_maps.png")
    plt.close(fig)
