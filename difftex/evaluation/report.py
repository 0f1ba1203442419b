"""Static HTML report of one results folder (and a side-by-side page over several).

One page that a person reads without the docs: what was textured and what not (and why), the
model rendered beside a photo, the metrics, per polygon its maps with a named colour legend, the
texel size and what set it, the optimizer's loss curves and per-level diagnostics, and the photo
filter's decisions. Plain HTML with relative links to the PNGs the stages wrote, plus the loss
curves written here as SVG (difftex.evaluation.losscurve); no scripts, no network, so it opens
from disk.

Every file is optional and read defensively: a missing file drops its section, a missing key
shows "n/a" (the optimizer's stats.json gains diagnostics over time).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from difftex.evaluation.html import CSS, _esc, _fig, _html, _num, _read, _table
from difftex.evaluation.losscurve import LOSS_COLOURS, loss_curve
from difftex.layout import COVERAGE, MODEL_NAME, REPORT, SOURCE_NPZ, SOURCE_PNG, SUMMARY, TEXTURE, Results
from difftex.scene.files import write_text

BOUND = {  # difftex.geometry.density.TexelSize.bound: what set a polygon's texel size
    "photos": "photos",
    "max_long_side": "cap max_long_side",
    "memory": "cap max_mb",
    "min_long_side": "floor min_long_side",
    "density": "fixed density",
    "long_side": "fixed long_side",
}
# per-level keys the diagnostics table shows in its own columns, or not at all
_LEVEL_SHOWN = {
    "level",
    "shape",
    "long_side",
    "candidates",
    "iterations",
    "cap",
    "converged",
    "final",
    "loss",
    "weight_change",
    "eliminated_pixels",
    "dropped_photos",
    "active_slots_mean",
    "time_s",
    "v_tilde",
}


def _share(x: float) -> str:
    return "&lt;1%" if 0 < x < 0.005 else f"{100 * x:.0f}%"


def _legend(colours: dict, tdir: Path) -> str:
    """Colour swatch, photo name and share of the polygon's seen texels, for its source map."""
    shares = {}
    npz = tdir / SOURCE_NPZ
    if npz.is_file():
        try:
            with np.load(npz, allow_pickle=False) as d:
                names, dom = [str(x) for x in d["photos"]], d["dominant"]
            counts = np.bincount(dom[dom >= 0].ravel().astype(np.int64), minlength=len(names))
            shares = {n: c / max(counts.sum(), 1) for n, c in zip(names, counts)}
        except (OSError, KeyError, ValueError):
            shares = {}
    items = [
        f"<span class=sw style='background:{_esc(c)}'></span>{_esc(n)}"
        + (f" <span class=small>{_share(shares[n])}</span>" if n in shares else "")
        for n, c in colours.items()
    ]
    return f"<p class='small legend'>Source map: {' '.join(items)}</p>" if items else ""


def _level_table(stats: dict) -> str:
    """The optimizer's per-level diagnostics, one column per level (coarse to fine): the known
    quantities first, then any further number the optimizer logs per level, by its key."""
    levels = [lv for lv in stats.get("levels") or [] if isinstance(lv, dict)]
    if not levels:
        return ""

    def last(v):
        return (
            v[-1]
            if isinstance(v, list) and v and not isinstance(v[-1], (list, dict))
            else (None if isinstance(v, list) else v)
        )

    def size(lv):
        shape = lv.get("shape")
        return f"{shape[1]}x{shape[0]}" if isinstance(shape, list) and len(shape) == 2 else None

    rows = [
        ("map (texels)", size),
        ("candidate photos", lambda lv: lv.get("candidates")),
        ("iterations / cap", lambda lv: f"{lv['iterations']} / {lv.get('cap', 'n/a')}" if "iterations" in lv else None),
        ("converged", lambda lv: lv.get("converged")),
    ]
    rows += [(f"final loss: {k}", lambda lv, k=k: (lv.get("final") or {}).get(k)) for k, _ in LOSS_COLOURS]
    rows += [
        ("weight change (last check)", lambda lv: last(lv.get("weight_change"))),
        ("eliminated pixels", lambda lv: lv.get("eliminated_pixels")),
        ("active slots per texel", lambda lv: lv.get("active_slots_mean")),
        ("photos dropped", lambda lv: lv.get("dropped_photos")),
        ("time (s)", lambda lv: lv.get("time_s")),
    ]
    extra = sorted(
        {
            k
            for lv in levels
            for k, v in lv.items()
            if k not in _LEVEL_SHOWN
            and (
                isinstance(v, (int, float, str, bool))
                or (isinstance(v, list) and v and isinstance(v[-1], (int, float)))
            )
        }
    )
    rows += [(k, lambda lv, k=k: last(lv.get(k))) for k in extra]
    return "<p class=small>Optimizer diagnostics per level (coarse to fine):</p>" + _table(
        ["level"] + [str(i) for i in range(len(levels))], [[name] + [get(lv) for lv in levels] for name, get in rows]
    )


def _polygon_rows(pids, vis, model, reports, stats, metrics) -> tuple[list[str], list[list]]:
    """The polygons table: photos, coverage, map and texel size (and what set it), optimization, metrics."""
    maps = {r.get("polygon_id"): r for r in (metrics.get("maps") or {}).get("polygons", []) if isinstance(r, dict)}
    persp = (metrics.get("perspective") or {}).get("polygons") or {}
    mrows = {r.get("id"): r for r in model.get("polygons", []) if isinstance(r, dict)}
    head = [
        "polygon",
        "photos",
        "coverage",
        "map (texels)",
        "texel size (scene units)",
        "set by",
        "photos' texel size",
        "iterations",
        "photos dropped",
        "time (s)",
        "notes",
    ]
    with_maps, with_q = bool(maps), bool(persp)
    if with_maps:
        head += ["Error 90%", "Error 95%", "SSIM", "LPIPS"]
    if with_q:
        head += ["Q_front", "Q_vc"]
    rows = []
    for pid in pids:
        v, st, rep, m = vis.get(pid, {}), stats.get(pid, {}), reports.get(pid, {}), mrows.get(pid, {})
        size = f"{v['width']}x{v['height']}" if "width" in v and "height" in v else None
        its = [lv.get("iterations") for lv in st.get("levels") or [] if isinstance(lv, dict)]
        notes = []
        why = m.get("untextured_reason") or v.get("untextured_reason")
        if why:
            notes.append(f"<span class=warn>untextured: {_esc(why)}</span>")
        if v.get("textured_from_oblique"):
            ang = v.get("oblique_angles") or {}
            lo, hi = (f"{min(ang.values()):.0f}", f"{max(ang.values()):.0f}") if ang else ("", "")
            notes.append(
                "oblique photos only" + (f" ({lo} deg)" if lo == hi and ang else f" ({lo}-{hi} deg)" if ang else "")
            )
        if v.get("textured_from_glimpses"):
            notes.append("from glimpses (under filter.min_pixels)")
        for name, r in (v.get("rescued") or {}).items():
            n = r.get("texels")
            notes.append(
                f"{_esc(name)} kept for the {n} texel{'' if n == 1 else 's'} only it sees ({_esc(r.get('why'))})"
            )
        t = rep.get("time_s") if rep.get("time_s") is not None else st.get("time_stage_s", st.get("time_total_s"))
        cov = rep.get("coverage", v.get("coverage"))
        row = [
            pid,
            len(v.get("photos", [])) if v else None,
            cov,
            size,
            v.get("texel_size"),
            _html(_esc(BOUND.get(v.get("texel_size_bound"), v.get("texel_size_bound") or "n/a"))),
            v.get("photo_texel_size"),
            "+".join(str(i) for i in its) if its else None,
            len(st.get("dropped") or []) if st else None,
            t,
            _html("<br>".join(notes)),
        ]
        if with_maps:
            mp = maps.get(pid, {})
            row += [mp.get("error90"), mp.get("error95"), mp.get("ssim"), mp.get("lpips")]
        if with_q:
            row += [(persp.get(pid) or {}).get("q_front"), (persp.get(pid) or {}).get("q_vc")]
        rows.append(row)
    return head, rows


def _metrics_section(metrics: dict) -> list[str]:
    if not metrics:
        return [
            "<h2>Metrics</h2><p class=small>No evaluation in this results folder (run.evaluate: false, or the "
            "evaluate job has not run).</p>"
        ]
    parts = ["<h2>Metrics</h2>"]
    if "maps" in metrics:
        o = (metrics["maps"] or {}).get("overall") or {}
        parts.append(
            "<h3>Against the ground-truth maps (synthetic scene)</h3>"
            + _table(
                ["texels", "Error 90%", "Error 95%", "SSIM", "LPIPS", "PSNR (dB)"],
                [[o.get("texels"), o.get("error90"), o.get("error95"), o.get("ssim"), o.get("lpips"), o.get("psnr")]],
                ".4f",
            )
            + "<p class=small>Error: RGB distance per texel in [0, sqrt 3]; LPIPS: "
            f"{_esc(o.get('lpips_variant', 'n/a'))}.</p>"
        )
    views = metrics.get("views") or {}
    if views:
        o = views.get("overall") or {}
        rows = [
            [r.get("photo"), r.get("compared_pixels"), r.get("ssim"), r.get("lpips"), r.get("psnr"), r.get("skipped")]
            for r in views.get("views", [])
            if isinstance(r, dict)
        ]
        rows.append(
            [
                _html("<b>all (pixel-weighted)</b>"),
                sum(r[1] or 0 for r in rows),
                o.get("ssim"),
                o.get("lpips"),
                o.get("psnr"),
                None,
            ]
        )
        held = views.get("held_out")
        what = f"held-out photos ({_esc(', '.join(held))})" if held else "the scene's ground-truth views"
        parts.append(
            f"<h3>Rendered into {what}</h3>"
            + _table(["view", "compared pixels", "SSIM", "LPIPS", "PSNR (dB)", "skipped"], rows, ".4f")
            + f"<p class=small>The textured proxy rendered into each camera and compared with the photo on the "
            f"proxy's pixels; LPIPS: {_esc(o.get('lpips_variant', 'n/a'))}.</p>"
        )
    if "perspective" in metrics:
        p = metrics["perspective"] or {}
        parts.append(
            f"<p>Perspective quality (texel-weighted over polygons): Q_front {_num(p.get('q_front'), '.4f')}, "
            f"Q_vc {_num(p.get('q_vc'), '.4f')} (1 = every texel from a head-on, consistent view).</p>"
        )
    return parts


def _photos_section(photos: dict, vis: dict) -> list[str]:
    """The photo filter's table: per photo kept or dropped and why, polygons seen and used for
    (``vis``: the visibility rows, which add the photos taken back for texels only they see)."""
    recs = [r for r in photos.get("photos") or [] if isinstance(r, dict)]
    if not recs:
        return []
    used: dict[str, list[str]] = {}
    for pid, d in (photos.get("polygons") or {}).items():
        for n in (d or {}).get("kept", []):
            used.setdefault(n, []).append(pid)
    for pid, row in vis.items():
        for n in row.get("rescued") or {}:
            used.setdefault(n, []).append(f"{pid} (only the texels no other photo sees)")
    cfg = photos.get("config") or {}
    rows = []
    for r in recs:
        seen = ", ".join(f"{k} {v.get('angle_deg', 0):.0f}&deg;" for k, v in (r.get("polygons") or {}).items())
        rows.append(
            [
                r.get("name"),
                r.get("kept"),
                _html(_esc(r.get("reason") or "")),
                r.get("sharpness_rel"),
                _html(seen),
                _html(_esc(", ".join(used.get(r.get("name"), []))) or "-"),
            ]
        )
    return [
        "<h2>Photo filter</h2>",
        f"<p class=small>Photos are dropped when they see no polygon or are blurry (sharpness below "
        f"{_num(cfg.get('blur_ratio'))} x the median); per polygon, views beyond {_num(cfg.get('max_angle_deg'))}&deg; "
        "are left out unless they are its only photos (or the only ones of some of its texels).</p>",
        _table(
            ["photo", "kept", "reason", "sharpness (x median)", "polygons seen (viewing angle)", "used for"],
            rows,
            ".2f",
        ),
    ]


def write_report(results: str | Path, out: str | Path | None = None, scene: str | Path | None = None) -> Path:
    """R/report/index.html (or ``out``) for results folder R; returns its path."""
    results = Path(results)
    res = Results(results)
    out = Path(out) if out is not None else res.report_html
    base = out.parent
    base.mkdir(parents=True, exist_ok=True)
    tdir = res.textures_dir
    from difftex.evaluation.evaluate import (
        visibility_dir,  # R/visibility, or the shared one an evaluation's method folder names
    )

    vis_rows = [r for r in _read(visibility_dir(results) / SUMMARY).get("polygons", []) if isinstance(r, dict)]
    vis = {str(r.get("id")): r for r in vis_rows}
    model = _read(res.model_summary)
    photos = _read(res.photos_json)
    metrics = _read(res.metrics)
    textured = sorted(p.name for p in tdir.iterdir() if (p / TEXTURE).is_file()) if tdir.is_dir() else []
    pids = list(vis) + [p for p in textured if p not in vis]
    reports = {pid: _read(res.polygon_textures(pid) / REPORT) for pid in pids}
    stats = {pid: _read(res.stats(pid)) for pid in pids}
    methods = sorted({r.get("method") for r in reports.values() if r.get("method")})
    parts = [
        f"<!doctype html><html><head><meta charset='utf-8'><title>difftex report: {_esc(results.name)}</title>"
        f"<style>{CSS}</style></head><body><h1>difftex report: {_esc(results.name)}</h1>",
        f"<p>Results folder <code>{_esc(results)}</code>; method <b>{_esc(', '.join(methods) or 'n/a')}</b>; "
        f"<b>{len(textured)} of {len(pids)}</b> polygons textured.</p>",
    ]
    # --- what is not textured, and what only poorly
    untextured = model.get("untextured_reasons") or {
        pid: r.get("untextured_reason") or "no photo sees it" for pid, r in vis.items() if pid not in textured
    }
    if untextured:
        parts.append(
            "<h2>Untextured polygons (grey in the model)</h2><ul>"
            + "".join(f"<li><b>{_esc(p)}</b>: {_esc(w)}</li>" for p, w in untextured.items())
            + "</ul>"
        )
    oblique = {pid: r.get("oblique_angles") or {} for pid, r in vis.items() if r.get("textured_from_oblique")}
    if oblique:
        parts.append(
            "<p class=warn>Textured from oblique photos only (every photo sees them beyond filter.max_angle_deg; "
            "expect stretched detail): "
            + ", ".join(
                f"<b>{_esc(p)}</b>" + (f" ({min(a.values()):.0f}&deg;)" if a else "") for p, a in oblique.items()
            )
            + "</p>"
        )
    # --- the model
    view = model.get("view_check") or {}
    mv = res.model_dir / str(view.get("image") or f"{MODEL_NAME}_view.png")
    if mv.is_file():
        parts.append(
            "<h2>Model</h2>"
            + _fig(
                mv,
                base,
                f"left: photo {view.get('photo', '')}; right: the textured model "
                f"rendered from its camera (mean colour difference {_num(view.get('mean_abs_diff'))})",
                "wide",
            )
        )
    parts += _metrics_section(metrics)
    # --- polygons
    if pids:
        head, rows = _polygon_rows(pids, vis, model, reports, stats, metrics)
        parts.append(
            "<h2>Polygons</h2>"
            + _table(head, rows)
            + "<p class=small>Texel size: the side of a texel on the building, in the scene's units (those of "
            "the COLMAP model). Set by: <i>photos</i>, the detail the photos resolve there (photos' texel size, "
            "their ground sampling distance) divided by texture.density_scale; or a cap or floor of the "
            "texture section (max_long_side, max_mb of memory, min_long_side), or a fixed density or "
            "long_side. Iterations: per level, coarse to fine.</p>"
        )
    scene = Path(scene) if scene else (Path(metrics["scene"]) if metrics.get("scene") else None)
    for pid in [p for p in pids if p in textured]:
        pdir = res.polygon_textures(pid)
        figs = [
            _fig(pdir / TEXTURE, base, "texture", "map"),
            _fig(pdir / SOURCE_PNG, base, "texel source map: dominant photo per texel (grey: filled)", "map"),
            _fig(pdir / COVERAGE, base, "coverage (white: seen by a photo, grey: filled)", "map"),
            _fig(res.error_map(pid), base, "error x3 against the ground truth", "map"),
        ]
        if scene is not None:
            figs.append(_fig(scene / "ground_truth" / "maps" / f"{pid}.png", base, "ground truth", "map"))
        st = stats.get(pid) or {}
        curve = loss_curve(st, base / f"loss_{pid}.svg", f"{pid}: loss per iteration") if st else None
        v = vis.get(pid, {})
        n_cand = len(v.get("photos", []))
        facts = [
            f"{n_cand} candidate photo{'' if n_cand == 1 else 's'}" if v else "",
            "oblique photos only: " + ", ".join(f"{n} {a:.0f} deg" for n, a in (v.get("oblique_angles") or {}).items())
            if v.get("textured_from_oblique")
            else "",
            f"{len(st.get('used_photos') or [])} used" if st.get("used_photos") is not None else "",
            "dropped: "
            + ", ".join(
                f"{d.get('photo')} (level {d.get('level')}, iteration {d.get('iteration')})"
                for d in st.get("dropped") or []
                if isinstance(d, dict)
            )
            if st.get("dropped")
            else "",
            f"converged: {'/'.join(_num(lv.get('converged')) for lv in st.get('levels') or [] if isinstance(lv, dict))}"
            if st.get("levels")
            else "",
            f"device {st['device']}" if st.get("device") else "",
        ]
        parts.append(
            f"<h3 id='{_esc(pid)}'>{_esc(pid)}</h3>{''.join(f for f in figs if f)}"
            + _legend(reports.get(pid, {}).get("source_colours") or {}, pdir)
            + (f"<p class=small>{_esc('; '.join(f for f in facts if f))}</p>" if any(facts) else "")
            + "<div class=row>"
            + (
                _fig(curve, base, "loss terms per iteration (log scale); dashed lines: next level", "wide")
                if curve
                else ""
            )
            + f"<div>{_level_table(st)}</div></div>"
        )
    parts += _photos_section(photos, vis)
    # --- held-out views
    if res.views_dir.is_dir():
        parts.append("<h2>Held-out views (render | photo | error x3)</h2>")
        for r in (metrics.get("views") or {}).get("views", []):
            photo = str(r.get("photo"))
            parts.append(
                f"<div><b>{_esc(r.get('photo'))}</b> SSIM {_num(r.get('ssim'), '.4f')} LPIPS "
                f"{_num(r.get('lpips'), '.4f')} PSNR {_num(r.get('psnr'), '.2f')}<br>"
                + _fig(res.view(photo, "render"), base, "render")
                + _fig(res.view(photo, "photo"), base, "photo")
                + _fig(res.view(photo, "error"), base, "error")
                + "</div>"
            )
    # --- timings of the workflow, when it ran
    bench = stage_benchmarks(results)
    if bench:
        parts.append(
            "<h2>Workflow time per stage (Snakemake benchmarks)</h2>"
            + _table(
                ["stage", "jobs", "wall s (sum)", "max RSS (MB)"],
                [[r, d["jobs"], d["seconds"], d["max_rss_mb"]] for r, d in bench.items()],
                ".1f",
            )
        )
    parts.append("</body></html>")
    write_text(out, "\n".join(parts))
    return out


def stage_benchmarks(results: Path) -> dict[str, dict]:
    """{rule: {"jobs": n, "seconds": sum of wall seconds, "max_s": the longest job's, "cpu_s": sum of
    Snakemake's cpu_time, "max_rss_mb": max}} from Snakemake's benchmark files R/benchmarks/<rule>/*.tsv.

    cpu_time is sampled from the job's processes and misses most of a long texture job's CPU
    (15 of 41 s per job on archive at `balanced`): a lower bound, not summed into any report."""
    out: dict[str, dict] = {}
    root = Results(results).benchmarks_dir
    if not root.is_dir():
        return out
    for tsv in sorted(root.rglob("*.tsv")):
        rule = tsv.relative_to(root).parts[0]
        lines = tsv.read_text().splitlines()
        if len(lines) < 2:
            continue
        head, row = lines[0].split("\t"), lines[1].split("\t")
        rec = dict(zip(head, row))
        d = out.setdefault(rule, {"jobs": 0, "seconds": 0.0, "max_s": 0.0, "cpu_s": 0.0, "max_rss_mb": 0.0})
        d["jobs"] += 1
        try:
            d["seconds"] += float(rec.get("s", 0))
            d["max_s"] = max(d["max_s"], float(rec.get("s", 0)))
            cpu, rss = rec.get("cpu_time", "NA"), rec.get("max_rss", "NA")
            if cpu not in ("NA", "-", ""):
                d["cpu_s"] += float(cpu)
            if rss not in ("NA", "-", ""):
                d["max_rss_mb"] = max(d["max_rss_mb"], float(rss))
        except ValueError:
            pass
    return out
