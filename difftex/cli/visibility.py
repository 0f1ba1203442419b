"""difftex visibility: per-polygon texel and photo-space visibility masks."""

from __future__ import annotations

NAME = "visibility"
REUSE_FREED_MEMORY = True  # difftex.cli._memory: keep freed memory for reuse in this job
HELP = "Compute which texels of each polygon every kept photo sees (depth test against the whole proxy)."


def add_arguments(p) -> None:
    p.add_argument("--scene", help="scene folder (not with --merge)")
    p.add_argument("--photos", help="the filter stage's JSON table; without it every photo is a candidate")
    p.add_argument("--config", help="YAML config; sections 'texture' and 'visibility' are read")
    p.add_argument("--out-dir", required=True)
    p.add_argument("--tile", help="TILE/TILES: only this spatial tile of the polygons (difftex.scene.partition); "
                   "its rows go to --rows instead of summary.json")
    p.add_argument("--rows", help="with --tile: the tile's summary rows (JSON)")
    p.add_argument("--merge", nargs="+", help="write OUT_DIR/summary.json from these tiles' rows (no scene is read)")
    p.add_argument("--quiet", action="store_true")


def polygon_notes(filtered: dict, vis) -> dict:
    """The summary row's notes on where a polygon's photos came from, or why it has none.

    Args:
        filtered: the filter table's record of the polygon (may be empty).
        vis: its difftex.geometry.visibility.PolygonVisibility.
    """
    out: dict = {}
    for key in ("textured_from_oblique", "oblique_angles", "textured_from_glimpses", "glimpses"):
        if filtered.get(key):
            out[key] = filtered[key]
    if vis.rescued:
        out["rescued"] = vis.rescued
    if not vis.photos or vis.coverage == 0:
        out["untextured_reason"] = filtered.get("untextured_reason") or (
            f"none of its texels is visible in its {len(filtered.get('kept', []))} photo(s) "
            "(thinner than a texel, or hidden at full resolution)")
    return out


def merge_tiles(paths: list[str], out_dir) -> int:
    """summary.json from the tiles' rows, in the proxy's polygon order (as one job writes it)."""
    from pathlib import Path

    from difftex.errors import DifftexError
    from difftex.layout import SUMMARY
    from difftex.scene.files import read_json, write_json

    rows, seconds, scene = [], 0.0, None
    for path in paths:
        data = read_json(path)
        if not isinstance(data, dict) or "rows" not in data:
            raise DifftexError(f"{path}: not a tile of the difftex visibility stage")
        scene = scene or data.get("scene")
        seconds += float(data.get("seconds", 0.0))
        rows += data["rows"]
    if sorted(r["index"] for r in rows) != list(range(len(rows))):
        raise DifftexError(
            f"{paths[0]}: the visibility tiles do not hold every polygon once: rerun the visibility stage")
    rows = [{k: v for k, v in r.items() if k != "index"} for r in sorted(rows, key=lambda r: r["index"])]
    out = Path(out_dir)
    write_json(out / SUMMARY, {"scene": scene, "polygons": rows, "seconds": round(seconds, 2)})
    print(f"visibility of {len(rows)} polygons from {len(paths)} tile(s) -> {out / SUMMARY}")
    return 0


def run(args) -> int:
    if args.merge:
        return merge_tiles(args.merge, args.out_dir)
    import time
    from pathlib import Path

    from difftex.config import TextureConfig, VisibilityConfig, job_threads, read_config, section
    from difftex.errors import DifftexError
    from difftex.geometry.visibility import save_visibility, scene_visibility
    from difftex.layout import SUMMARY, visibility_file
    from difftex.scene.files import read_json, write_json
    from difftex.scene.loading import load_scene

    t0 = time.perf_counter()
    tex = section(args.config, "texture", TextureConfig)
    vcfg = section(args.config, "visibility", VisibilityConfig)
    if not args.scene:
        raise DifftexError("--scene is needed (except with --merge)")
    if bool(args.tile) != bool(args.rows):
        raise DifftexError("--tile and --rows go together")
    # a tile reads the cameras only: the filter stage's chunks checked every photo's file
    scene = load_scene(args.scene, check_images=not args.tile)
    only = None
    if args.tile:
        import numpy as np

        from difftex.scene.partition import parse_part, polygon_tiles

        j, n = parse_part(args.tile)
        tiles = polygon_tiles(np.array([p.centroid for p in scene.proxy.polygons]), n)
        only = tiles[j].tolist() if j < len(tiles) else []
    filtered: dict = {}  # the filter's record per polygon
    if args.photos:
        table = read_json(args.photos)
        try:
            filtered = dict(table["polygons"])
            cands = {pid: d["kept"] for pid, d in filtered.items()}
            # photos dropped as inclined: back only as the last source of some texels
            later = {
                pid: {n: d["dropped"].get(n, "inclined") for n in d.get("inclined", {})} for pid, d in filtered.items()
            }
        except (KeyError, AttributeError, TypeError):
            raise DifftexError(f"{args.photos}: not a difftex filter table") from None
    else:
        cands = {p.id: [ph.name for ph in scene.photos] for p in scene.proxy.polygons}
        later = {}
    top_k = int((read_config(args.config).get("optimize") or {}).get("top_k", 8))
    vis = scene_visibility(
        scene.proxy,
        scene.photos,
        scene.up,
        cands,
        tex,
        min_texels=vcfg.min_texels,
        max_photos=vcfg.max_photos,
        texel_candidates=vcfg.texel_candidates,
        progress=not args.quiet,
        top_k=top_k,
        fallback=later,
        threads=job_threads(),
        only=only,
    )
    out = Path(args.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    index = {p.id: i for i, p in enumerate(scene.proxy.polygons)}
    for v in vis:
        save_visibility(visibility_file(out, v.polygon_id), v)
        ts = v.texel_size or {}
        rows.append(
            {
                "id": v.polygon_id,
                "photos": v.photos,
                "coverage": round(v.coverage, 4),
                "width": v.frame.width,
                "height": v.frame.height,
                "texels": int(v.texel_mask.sum()),
                "texel_size": v.frame.texel_size,
                "photo_texel_size": ts.get("photo_texel_size"),
                "texel_size_bound": ts.get("bound"),
                **polygon_notes(filtered.get(v.polygon_id, {}), v),
            }
        )
        print(
            f"  {v.polygon_id}: {len(v.photos)} photos, coverage {100 * v.coverage:.1f}%, "
            f"{v.frame.width}x{v.frame.height} "
            f"texels of {v.frame.texel_size:.4g} units (set by {ts.get('bound')})"
            + (f"; {rows[-1]['untextured_reason']}" if "untextured_reason" in rows[-1] else "")
            + (f"; last source of some texels: {', '.join(v.rescued)}" if v.rescued else "")
        )
    secs = time.perf_counter() - t0
    if args.tile:
        rows = [{"index": index[r["id"]], **r} for r in rows]
        # the photos this tile decoded (its polygons' candidates): a photo seen by two tiles is read twice
        mine = {scene.proxy.polygons[i].id for i in only or []}
        read = set().union(*(set(cands.get(pid, ())) | set(later.get(pid, ())) for pid in mine)) if mine else set()
        write_json(args.rows, {"scene": str(scene.root), "tile": args.tile, "rows": rows, "seconds": round(secs, 2),
                               "photos_read": len(read & {ph.name for ph in scene.photos})})
        print(f"{scene.name}: visibility of tile {args.tile} ({len(vis)} polygons) in {secs:.1f} s -> {args.rows}")
        return 0
    write_json(out / SUMMARY, {"scene": str(scene.root), "polygons": rows, "seconds": round(secs, 2)})
    print(f"{scene.name}: visibility of {len(vis)} polygons in {secs:.1f} s -> {out}")
    return 0
