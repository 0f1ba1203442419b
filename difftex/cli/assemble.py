"""difftex assemble: per-polygon textures -> atlas pages, OBJ + MTL + PNG and GLB (and with
``assemble.tileset`` or --tileset, a 3D Tiles 1.1 tileset in <out-dir>/tileset/)."""

from __future__ import annotations

NAME = "assemble"
HELP = "pack per-polygon textures into atlas pages and write the textured model (OBJ, GLB)"


def add_arguments(parser) -> None:
    from difftex.layout import MODEL_NAME

    parser.add_argument("--scene", required=True, help="scene folder (its proxy model is written unchanged)")
    parser.add_argument("--textures", required=True, help="folder with <polygon id>/texture.png")
    parser.add_argument(
        "--visibility",
        help="folder with <polygon id>.npz (UV frames) and summary.json (default: visibility/ beside --textures)",
    )
    parser.add_argument("--config", help="YAML config; section 'assemble' is read")
    parser.add_argument(
        "--out-dir", required=True, help="output folder (model.obj/.mtl, atlas PNGs, model.glb, summary.json)"
    )
    parser.add_argument("--name", default=MODEL_NAME, help=f"base name of the output files (default: {MODEL_NAME})")
    parser.add_argument(
        "--tileset",
        action="store_true",
        help="also write <out-dir>/tileset/ (3D Tiles 1.1), as assemble.tileset: true does",
    )


def _read_frame_and_mask(path):
    """Only the UV frame and texel mask of a visibility file (the per-photo masks are not needed)."""
    import json

    import numpy as np

    from difftex.errors import DifftexError
    from difftex.geometry.frames import UVFrame

    try:
        with np.load(path, allow_pickle=False) as d:
            frame = UVFrame.from_dict(json.loads(str(d["frame"])))
            H, W = (int(x) for x in d["shape"])
            mask = np.unpackbits(d["texel_mask"], count=H * W).astype(bool).reshape(H, W)
    except (OSError, KeyError, ValueError) as exc:
        raise DifftexError(f"{path}: not a difftex visibility file ({exc})") from None
    return frame, mask


def _view_check(scene_dir, proxy, info, glb, out_png) -> dict | None:
    """Render the reloaded GLB from the photo that sees most polygons; write the render beside
    the photo (left: photo, right: model) and their mean colour difference where the model is."""
    from collections import Counter

    import numpy as np

    from difftex.export.check import render_view
    from difftex.geometry.frames import sample_photo
    from difftex.scene.camera import load_photos
    from difftex.scene.files import read_image, write_image
    from difftex.scene.loading import find_sparse

    counts = Counter(name for row in info.values() for name in row.get("photos", []))
    if not counts:
        return None
    name = counts.most_common(1)[0][0]
    photos = {p.name: p for p in load_photos(find_sparse(scene_dir), scene_dir / "images", check_images=False)}
    if name not in photos:
        return None
    photo = photos[name]
    render, covered, pix = render_view(glb, proxy, photo)
    shot = sample_photo(read_image(scene_dir / "images" / name), pix)
    write_image(out_png, np.concatenate([shot, np.where(covered[..., None], render, 0.0)], axis=1))
    diff = float(np.abs(render - shot)[covered].mean()) if covered.any() else None
    return {
        "photo": name,
        "image": out_png.name,
        "covered_share": round(float(covered.mean()), 4),
        "mean_abs_diff": None if diff is None else round(diff, 4),
    }


def polygon_notes(summary: dict, info: dict) -> None:
    """Say in the model summary where each polygon's photos came from, and why the untextured
    ones have none (from the visibility summary's rows, ``info``: id -> row)."""
    summary["untextured_reasons"] = {}
    summary["textured_from_oblique"] = {}
    for row in summary["polygons"]:
        meta = info.get(row["id"], {})
        if not row["textured"]:
            why = meta.get("untextured_reason") or (
                "no visibility record (not in the visibility summary)" if not meta else "no texture was written for it"
            )
            row["untextured_reason"] = summary["untextured_reasons"][row["id"]] = why
            continue
        if meta.get("textured_from_oblique"):
            row["oblique_angles"] = summary["textured_from_oblique"][row["id"]] = meta.get("oblique_angles", {})
        if meta.get("textured_from_glimpses"):
            row["textured_from_glimpses"] = True
        if meta.get("rescued"):
            row["rescued"] = meta["rescued"]


def _scene_up(scene_dir):
    """The photos' up (what the texturing takes as up), or None when the scene has no photos."""
    from difftex.scene.camera import load_photos, scene_up
    from difftex.scene.loading import find_sparse

    photos = load_photos(find_sparse(scene_dir), scene_dir / "images", check_images=False)
    return scene_up(photos) if photos else None


def _semantics(summary: dict, proxy) -> None:
    """Name each polygon's CityJSON semantic type and building in the model summary (when it has them)."""
    by_id = {p.id: p for p in proxy.polygons}
    for row in summary["polygons"]:
        poly = by_id[row["id"]]
        if poly.semantic:
            row["semantic"], row["building"] = poly.semantic, poly.building


def run(args) -> int:
    import time
    from pathlib import Path

    import numpy as np
    from rich.console import Console
    from rich.progress import track

    from difftex.compose.outputs import OutputConfig
    from difftex.config import section
    from difftex.errors import DifftexError
    from difftex.export.assemble import AssembleConfig, PolygonTexture, assemble
    from difftex.layout import NORMAL, SUMMARY, TEXTURE, TILESET_DIR, Results, visibility_file
    from difftex.scene.files import read_image, read_json, write_json
    from difftex.scene.loading import find_proxy
    from difftex.scene.proxy import load_proxy

    t0 = time.time()
    console = Console(stderr=True)
    cfg = section(args.config, "assemble", AssembleConfig)
    out_cfg = section(args.config, "output", OutputConfig)
    scene = Path(args.scene)
    if not scene.is_dir():
        raise DifftexError(f"{scene}: scene folder not found")
    textures = Path(args.textures)
    # the layout of a results folder: R/textures beside R/visibility
    vis_dir = Path(args.visibility) if args.visibility else Results(textures.parent).visibility_dir
    proxy = load_proxy(find_proxy(scene))

    info = {}
    vsum = vis_dir / SUMMARY
    if vsum.is_file():
        for p in read_json(vsum).get("polygons", []):
            info[str(p["id"])] = p
    unknown = sorted(set(info) - set(proxy.ids))
    if unknown:
        raise DifftexError(f"{vsum}: polygon id(s) {', '.join(unknown[:5])} are not in {proxy.path} (stale results?)")

    items = []
    for poly in track(proxy.polygons, description="loading textures", console=console, transient=True):
        meta = info.get(poly.id, {})
        coverage = float(meta.get("coverage", 0.0))
        n_photos = len(meta.get("photos", []))
        npz = visibility_file(vis_dir, poly.id)
        frame = mask = tex = None
        if npz.is_file():
            frame, mask = _read_frame_and_mask(npz)
        png = textures / poly.id / TEXTURE
        if frame is not None and png.is_file() and coverage > 0:
            tex = read_image(png)
            if tex.shape[:2] != mask.shape:
                # a texture at another resolution than the visibility level: resample the mask
                iy = (np.arange(tex.shape[0]) + 0.5) * mask.shape[0] / tex.shape[0]
                ix = (np.arange(tex.shape[1]) + 0.5) * mask.shape[1] / tex.shape[1]
                mask = mask[np.minimum(iy.astype(int), mask.shape[0] - 1)][
                    :, np.minimum(ix.astype(int), mask.shape[1] - 1)
                ]
        normal_png = textures / poly.id / NORMAL
        items.append(
            PolygonTexture(
                polygon=poly,
                frame=frame,
                texture=tex,
                mask=mask if tex is not None else None,
                coverage=coverage if tex is not None else 0.0,
                photos=n_photos,
                normal=read_image(normal_png) if tex is not None and normal_png.is_file() else None,
            )
        )

    out_dir = Path(args.out_dir)
    with console.status(f"packing {len(items)} textures and writing the model"):
        summary = assemble(items, out_dir, cfg, name=args.name, bits=out_cfg.bits)
    polygon_notes(summary, info)
    _semantics(summary, proxy)
    if cfg.tileset or args.tileset:
        from difftex import __version__
        from difftex.export.tiles import write_tileset

        with console.status("writing the 3D Tiles tileset"):
            up = _scene_up(scene) if cfg.tileset_georef is None else None
            tiles = write_tileset(items, out_dir / TILESET_DIR, cfg, generator=f"difftex {__version__}", up=up)
        summary["tileset"] = {**tiles, "file": f"{TILESET_DIR}/{tiles['file']}"}
    if cfg.glb and cfg.verify:
        with console.status("rendering a view of the model"):
            summary["view_check"] = _view_check(
                scene, proxy, info, out_dir / summary["glb"], out_dir / f"{args.name}_view.png"
            )
    summary = {
        "scene": scene.resolve().name,
        "scene_path": str(scene.resolve()),
        **summary,
        "seconds": round(time.time() - t0, 2),
    }
    write_json(out_dir / SUMMARY, summary)

    n_tex = sum(1 for p in summary["polygons"] if p["textured"])
    console.print(f"{n_tex}/{len(items)} polygons textured, {len(summary['atlas_pages'])} atlas page(s)")
    for pid, angles in summary["textured_from_oblique"].items():
        console.print(
            f"textured from oblique photos only: {pid} ({', '.join(f'{n} {a:.0f} deg' for n, a in angles.items())})"
        )
    for pid, why in summary["untextured_reasons"].items():
        console.print(f"untextured (grey): {pid}: {why}")
    if "tileset" in summary:
        ts = summary["tileset"]
        console.print(
            f"3D Tiles: {out_dir / ts['file']} ({len(ts['tiles'])} tile(s), "
            + ("georeferenced" if ts["georeferenced"] else "local frame" + (", up = +z" if ts["levelled"] else ""))
            + ")"
        )
    chk = summary.get("check")
    if chk:
        ok = not chk["missing_polygons"] and chk["max_area_rel_error"] < 1e-4
        console.print(
            f"GLB check: {chk['glb_polygons']} polygons reloaded, max colour difference {chk['max_color_error']:.4f}"
            + ("" if ok else f", MISSING {chk['missing_polygons']} / area error {chk['max_area_rel_error']:.2g}")
        )
        if not ok:
            raise DifftexError(f"{out_dir / summary['glb']}: reloaded model does not match the proxy")
    print(out_dir / summary.get("glb", summary["obj"]))
    return 0
