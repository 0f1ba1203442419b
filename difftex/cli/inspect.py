"""difftex inspect: load a scene, check it, summarise it, and draw the proxy over photos."""

from __future__ import annotations

NAME = "inspect"
HELP = "Load a scene (photos, COLMAP model, proxy), report what it holds, write proxy overlays."


def add_arguments(p) -> None:
    p.add_argument("scene", help="scene folder (images/, sparse/0/, proxy.obj)")
    p.add_argument("--overlays", help="folder for proxy-over-photo images (PNG)")
    p.add_argument("--max-overlays", type=int, default=4, help="how many photos to draw (evenly spread)")
    p.add_argument("--long-side", type=int, default=256, help="texture long side used for the frame summary")


def run(args) -> int:
    import time
    from pathlib import Path

    import numpy as np

    from difftex.export.overlay import proxy_overlay
    from difftex.geometry.frames import uv_frame
    from difftex.scene.files import read_image, write_image
    from difftex.scene.loading import load_scene

    t0 = time.perf_counter()
    scene = load_scene(args.scene)
    models = sorted({p.model for p in scene.photos})
    print(
        f"{scene.name}: {len(scene.photos)} photos ({', '.join(models)}), {len(scene.proxy)} polygons, up "
        f"{np.round(scene.up, 3).tolist()}"
    )
    for poly in scene.proxy.polygons:
        f = uv_frame(poly, scene.up, long_side=args.long_side)
        print(
            f"  {poly.id:28s} area {poly.area:9.3f}  {len(poly.outer):3d} vertices  {f.width}x{f.height} texels at "
            f"long side {args.long_side}" + (f"  {poly.semantic}" if poly.semantic else "")
        )
    if args.overlays:
        out = Path(args.overlays)
        n = min(args.max_overlays, len(scene.photos))
        picks = np.unique(np.linspace(0, len(scene.photos) - 1, n).round().astype(int))
        for i in picks:
            ph = scene.photos[int(i)]
            img = read_image(ph.image_path, expected_size=(ph.width, ph.height))
            path = out / f"overlay_{Path(ph.name).stem}.png"
            write_image(path, proxy_overlay(scene.proxy, ph, img))
            print(f"  overlay: {path}")
    print(f"loaded and checked in {time.perf_counter() - t0:.1f} s")
    return 0
