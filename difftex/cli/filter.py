"""difftex filter: photo filtering stage."""

from __future__ import annotations

NAME = "filter"
HELP = "Drop photos that see no polygon, blurry photos, and per polygon extremely inclined views."


def add_arguments(p) -> None:
    p.add_argument("--scene", required=True, help="scene folder (images/, sparse/0/, proxy.obj)")
    p.add_argument("--config", help="YAML config; section 'filter' is read")
    p.add_argument("--out", required=True, help="output JSON table (a CSV is written beside it)")
    p.add_argument("--quiet", action="store_true")


def run(args) -> int:
    from pathlib import Path

    from difftex.config import FilterConfig, section
    from difftex.geometry.photo_filter import filter_photos, write_table
    from difftex.scene.loading import load_scene

    cfg = section(args.config, "filter", FilterConfig)
    scene = load_scene(args.scene)
    result = filter_photos(scene.proxy, scene.photos, cfg, progress=not args.quiet)
    out = Path(args.out)
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
