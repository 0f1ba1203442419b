"""difftex filter: photo filtering stage (whole scene, one chunk of photos, or the chunks' merge)."""

from __future__ import annotations

NAME = "filter"
HELP = "Drop photos that see no polygon, blurry photos, and per polygon extremely inclined views."
REUSE_FREED_MEMORY = True  # difftex.cli._memory: keep freed memory for reuse in this job


def add_arguments(p) -> None:
    p.add_argument("--scene", required=True, help="scene folder (images/, sparse/0/, proxy.obj)")
    p.add_argument("--config", help="YAML config; section 'filter' is read")
    p.add_argument("--out", required=True,
                   help="output JSON table (a CSV is written beside it); with --part, the chunk's records")
    p.add_argument("--part", help="PART/PARTS: measure only this chunk of the scene's photos (difftex.scene.partition)")
    p.add_argument("--parts", nargs="+", help="merge these chunks' records (from --part runs) into the table")
    p.add_argument("--quiet", action="store_true")


def chunk_photos(scene, part: str) -> list:
    """The scene's photos in chunk ``part`` (``PART/PARTS``) of its image files."""
    from difftex.scene.camera import check_photo_file, image_files
    from difftex.scene.loading import find_sparse
    from difftex.scene.partition import parse_part, photo_chunk

    j, n = parse_part(part)
    images = scene.root / "images"
    names = set(photo_chunk([p.relative_to(images).as_posix() for p in image_files(images)], j, n))
    photos = [ph for ph in scene.photos if ph.name in names]
    sparse = find_sparse(scene.root)
    for ph in photos:  # the scene was read without its files; this chunk's are checked here
        check_photo_file(ph, sparse)
    if j == 0:  # and the first chunk warns once of photos the model does not list, as a whole-scene read does
        from difftex.scene.camera import model_file, read_reconstruction, warn_unlisted

        warn_unlisted(images, read_reconstruction(sparse), model_file(sparse, "images"))
    return photos


def merged_records(scene, paths: list[str]) -> tuple[list, float]:
    """Every photo's record from the chunks' files, in the scene's photo order, and the chunks' seconds."""
    from difftex.errors import DifftexError
    from difftex.geometry.photo_filter import record_from_dict
    from difftex.scene.files import read_json

    by_name, seconds = {}, 0.0
    for path in paths:
        data = read_json(path)
        if not isinstance(data, dict) or "records" not in data:
            raise DifftexError(f"{path}: not a chunk of the difftex filter stage")
        seconds += float(data.get("seconds", 0.0))
        for d in data["records"]:
            try:
                by_name[d["name"]] = record_from_dict(d)
            except DifftexError as exc:
                raise DifftexError(f"{path}: {exc}") from None
    missing = [ph.name for ph in scene.photos if ph.name not in by_name]
    if missing:
        raise DifftexError(
            f"{paths[0]}: the filter's chunks measure no record of {len(missing)} photo(s) ({missing[0]}, ...): "
            "rerun the filter stage")
    return [by_name[ph.name] for ph in scene.photos], seconds


def run(args) -> int:
    import time
    from pathlib import Path

    from difftex.config import FilterConfig, section
    from difftex.geometry.photo_filter import decide_photos, filter_photos, photo_records, write_table
    from difftex.scene.files import write_json
    from difftex.scene.loading import load_scene

    t0 = time.perf_counter()
    cfg = section(args.config, "filter", FilterConfig)
    # a chunk or the merge reads the cameras only: each chunk checks its own photos' files
    scene = load_scene(args.scene, check_images=not (args.part or args.parts))
    out = Path(args.out)
    if args.part:
        photos = chunk_photos(scene, args.part)
        records = photo_records(scene.proxy, photos, cfg, progress=not args.quiet)
        secs = time.perf_counter() - t0
        write_json(out, {"part": args.part, "records": [r.__dict__ for r in records], "seconds": round(secs, 3)})
        print(f"{scene.name}: photos {args.part}: {len(photos)} of {len(scene.photos)} measured in {secs:.1f} s "
              f"-> {out}")
        return 0
    if args.parts:
        records, chunk_s = merged_records(scene, args.parts)
        result = decide_photos(scene.proxy, scene.photos, records, cfg)
        result["seconds"] = round(chunk_s + result["seconds"], 3)
    else:
        result = filter_photos(scene.proxy, scene.photos, cfg, progress=not args.quiet)
    write_table(result, out, out.with_suffix(".csv"))
    kept = sum(r["kept"] for r in result["photos"])
    print(
        f"{scene.name}: {len(scene.photos)} photos, {kept} kept; {len(scene.proxy)} polygons; {result['seconds']:.1f} s"
    )
    for pid, d in result["polygons"].items():
        note = (
            "; oblique photos only"
            if d.get("textured_from_oblique")
            else "; from glimpses"
            if d.get("textured_from_glimpses")
            else f"; untextured: {d['untextured_reason']}"
            if d.get("untextured_reason")
            else ""
        )
        print(f"  {pid}: {len(d['kept'])} photos kept, {len(d['dropped'])} dropped{note}")
    print(f"table: {out}")
    return 0
