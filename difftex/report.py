"""Static HTML report of one results folder (and a side-by-side page over several).

Plain HTML with relative links to the PNGs the stages wrote (textures, texel source maps,
coverage, the evaluation's error maps and held-out renders) plus loss curves drawn here with
matplotlib (Agg, PNG); no scripts, no network, so it opens from disk in any browser.
"""

from __future__ import annotations

import html
import os
from pathlib import Path

from difftex.io import read_json, write_text

CSS = """body{font-family:sans-serif;margin:1.5em;max-width:1400px}table{border-collapse:collapse;margin:.5em 0}
td,th{border:1px solid #bbb;padding:3px 7px;text-align:right}th{background:#eee}td:first-child{text-align:left}
img{image-rendering:pixelated;max-width:256px;max-height:256px;border:1px solid #ccc;margin:2px}
figure{display:inline-block;margin:4px;vertical-align:top}figcaption{font-size:80%;text-align:center}
.small{font-size:85%;color:#444}"""


def _rel(target: Path, start: Path) -> str:
    return html.escape(os.path.relpath(target, start).replace(os.sep, "/"))


def _fig(path: Path, base: Path, caption: str) -> str:
    if not path.is_file():
        return ""
    return f'<figure><a href="{_rel(path, base)}"><img src="{_rel(path, base)}" alt="{html.escape(caption)}"></a><figcaption>{html.escape(caption)}</figcaption></figure>'


def _num(v, nd=4) -> str:
    if v is None:
        return "n/a"
    if isinstance(v, float):
        return f"{v:.{nd}f}"
    return html.escape(str(v))


def _table(header: list[str], rows: list[list]) -> str:
    h = "".join(f"<th>{html.escape(x)}</th>" for x in header)
    body = "".join("<tr>" + "".join(f"<td>{_num(c)}</td>" for c in r) + "</tr>" for r in rows)
    return f"<table><tr>{h}</tr>{body}</table>"


def loss_curve(stats: dict, out: Path) -> Path | None:
    """PNG of the optimizer's loss terms per iteration, levels one after another."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    levels = stats.get("levels") or []
    if not levels:
        return None
    fig, ax = plt.subplots(figsize=(5, 3), dpi=80)
    start = 0
    for key, colour in (("total", "k"), ("render", "C0"), ("persp", "C1"), ("para", "C2"), ("ghost", "C3")):
        xs, ys, start = [], [], 0
        for lv in levels:
            vals = (lv.get("loss") or {}).get(key) or []
            xs += list(range(start, start + len(vals)))
            ys += vals
            start += len(vals)
        if ys and any(y != 0 for y in ys):
            ax.plot(xs, ys, colour, lw=1, label=key)
    s = 0
    for lv in levels[:-1]:
        s += len((lv.get("loss") or {}).get("total") or [])
        ax.axvline(s, color="#999", lw=0.5, ls="--")
    ax.set_xlabel("iteration (levels separated by dashes)")
    ax.set_yscale("symlog", linthresh=1e-3)
    ax.set_ylim(bottom=0)  # losses are non-negative
    ax.legend(fontsize=7)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    from difftex.io import atomic_path

    with atomic_path(out) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
    return out


def write_report(results: str | Path, out: str | Path | None = None, scene: str | Path | None = None) -> Path:
    """R/report/index.html (or ``out``) for results folder R; returns its path."""
    results = Path(results)
    out = Path(out) if out is not None else results / "report" / "index.html"
    base = out.parent
    base.mkdir(parents=True, exist_ok=True)
    tdir = results / "textures"
    pids = sorted(p.name for p in tdir.iterdir() if (p / "texture.png").is_file()) if tdir.is_dir() else []
    metrics_path = results / "evaluation" / "metrics.json"
    metrics = read_json(metrics_path) if metrics_path.is_file() else {}
    parts = [f"<!doctype html><html><head><meta charset='utf-8'><title>difftex report: {html.escape(results.name)}</title>"
             f"<style>{CSS}</style></head><body><h1>difftex report: {html.escape(str(results))}</h1>"]
    methods = set()
    reports = {}
    for pid in pids:
        rp = tdir / pid / "report.json"
        reports[pid] = read_json(rp) if rp.is_file() else {}
        methods.add(reports[pid].get("method", "?"))
    parts.append(f"<p>Method: <b>{html.escape(', '.join(sorted(methods)) or 'n/a')}</b>; {len(pids)} textured polygons.</p>")
    # --- summary tables
    if metrics:
        rows = []
        if "maps" in metrics:
            o = metrics["maps"]["overall"]
            rows.append(["ground-truth maps", o.get("error90"), o.get("error95"), o.get("ssim"), o.get("lpips"), o.get("psnr")])
        if "views" in metrics:
            o = metrics["views"]["overall"]
            rows.append([f"held-out views ({o.get('views')})", None, None, o.get("ssim"), o.get("lpips"), o.get("psnr")])
        if rows:
            parts.append("<h2>Metrics</h2>" + _table(["against", "Error 90%", "Error 95%", "SSIM", "LPIPS", "PSNR"], rows))
            lv = (metrics.get("maps") or metrics.get("views") or {}).get("overall", {}).get("lpips_variant")
            parts.append(f"<p class=small>LPIPS variant: {html.escape(str(lv))}. Error: RGB distance in [0, sqrt 3].</p>")
        if "perspective" in metrics:
            p = metrics["perspective"]
            parts.append(f"<p>Q_front {_num(p['q_front'])}, Q_vc {_num(p['q_vc'])} (texel-weighted over polygons).</p>")
    # --- per polygon table
    prow = []
    mp = {r["polygon_id"]: r for r in (metrics.get("maps") or {}).get("polygons", [])}
    qp = (metrics.get("perspective") or {}).get("polygons", {})
    for pid in pids:
        rep = reports[pid]
        st = rep.get("optimize") or {}
        t = rep.get("time_s") if rep.get("time_s") is not None else st.get("time_total_s")
        m = mp.get(pid, {})
        prow.append([pid, rep.get("coverage"), rep.get("filled_texels"), t, m.get("error90"), m.get("error95"),
                     m.get("ssim"), m.get("lpips"), (qp.get(pid) or {}).get("q_front"), (qp.get(pid) or {}).get("q_vc")])
    if prow:
        parts.append("<h2>Polygons</h2>" + _table(["polygon", "coverage", "filled texels", "time (s)", "Error 90%", "Error 95%",
                                                   "SSIM", "LPIPS", "Q_front", "Q_vc"], prow))
    # --- pictures per polygon
    scene = Path(scene) if scene else (Path(metrics["scene"]) if metrics.get("scene") else None)
    for pid in pids:
        figs = [_fig(tdir / pid / "texture.png", base, "texture"), _fig(tdir / pid / "source.png", base, "texel source map"),
                _fig(tdir / pid / "coverage.png", base, "coverage (white seen, grey filled)"),
                _fig(results / "evaluation" / "error_maps" / f"{pid}.png", base, "error x3 vs ground truth")]
        if scene is not None:
            figs.append(_fig(scene / "ground_truth" / "maps" / f"{pid}.png", base, "ground truth"))
        stats_p = results / "optimized" / pid / "stats.json"
        if stats_p.is_file():
            png = loss_curve(read_json(stats_p), base / f"loss_{pid}.png")
            if png is not None:
                figs.append(_fig(png, base, "loss curves"))
        colours = reports[pid].get("source_colours") or {}
        legend = " ".join(f"<span style='background:{html.escape(c)}'>&nbsp;&nbsp;&nbsp;</span> {html.escape(n)}"
                          for n, c in colours.items())
        parts.append(f"<h3>{html.escape(pid)}</h3>{''.join(f for f in figs if f)}<p class=small>{legend}</p>")
    # --- held-out views
    vdir = results / "evaluation" / "views"
    if vdir.is_dir():
        parts.append("<h2>Held-out views (render | photo | error x3)</h2>")
        for r in (metrics.get("views") or {}).get("views", []):
            stem = Path(r["photo"]).stem
            parts.append(f"<div><b>{html.escape(r['photo'])}</b> SSIM {_num(r.get('ssim'))} LPIPS {_num(r.get('lpips'))}<br>"
                         + _fig(vdir / f"{stem}_render.png", base, "render") + _fig(vdir / f"{stem}_photo.png", base, "photo")
                         + _fig(vdir / f"{stem}_error.png", base, "error") + "</div>")
    # --- timings of the workflow, when it ran
    bench = results / "benchmarks"
    if bench.is_dir():
        rows = []
        for tsv in sorted(bench.rglob("*.tsv")):
            lines = tsv.read_text().splitlines()
            if len(lines) >= 2:
                rows.append([str(tsv.relative_to(bench)), float(lines[1].split("\t")[0])])
        if rows:
            parts.append("<h2>Workflow timings (Snakemake benchmarks)</h2>" + _table(["job", "seconds"], rows))
    parts.append("</body></html>")
    write_text(out, "\n".join(parts))
    return out


def markdown_table_html(md: str) -> str:
    """The markdown of an evaluation table as HTML (pipe tables and bullet lines only)."""
    out, in_table = [], False
    for ln in md.splitlines():
        if ln.startswith("|"):
            cells = [c.strip() for c in ln.strip().strip("|").split("|")]
            if all(set(c) <= set("-:") for c in cells):
                continue
            tag = "th" if not in_table else "td"
            if not in_table:
                out.append("<table>")
                in_table = True
            out.append("<tr>" + "".join(f"<{tag}>{html.escape(c).replace('**', '')}</{tag}>" for c in cells) + "</tr>")
            continue
        if in_table:
            out.append("</table>")
            in_table = False
        if ln.startswith("# "):
            out.append(f"<h1>{html.escape(ln[2:])}</h1>")
        elif ln.startswith("- "):
            out.append(f"<p class=small>{html.escape(ln[2:])}</p>")
        elif ln.strip():
            out.append(f"<p>{html.escape(ln)}</p>")
    if in_table:
        out.append("</table>")
    return "\n".join(out)


def comparison_page(out: str | Path, title: str, table_md: str, runs: dict[str, str | Path],
                    scene: str | Path | None = None) -> Path:
    """One page: the table, links to each method's report, and every polygon's textures side by side."""
    out = Path(out)
    base = out.parent
    parts = [f"<!doctype html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title><style>{CSS}</style></head><body>",
             markdown_table_html(table_md), "<h2>Reports per method</h2><ul>"]
    for m, r in runs.items():
        parts.append(f"<li><a href='{_rel(Path(r) / 'report' / 'index.html', base)}'>{html.escape(m)}</a></li>")
    parts.append("</ul><h2>Textures side by side</h2>")
    pids = sorted({p.name for r in runs.values() for p in (Path(r) / "textures").glob("*") if (p / "texture.png").is_file()})
    for pid in pids:
        figs = []
        if scene is not None:
            figs.append(_fig(Path(scene) / "ground_truth" / "maps" / f"{pid}.png", base, "ground truth"))
        for m, r in runs.items():
            figs.append(_fig(Path(r) / "textures" / pid / "texture.png", base, m))
            figs.append(_fig(Path(r) / "textures" / pid / "source.png", base, f"{m} sources"))
        parts.append(f"<h3>{html.escape(pid)}</h3>" + "".join(f for f in figs if f))
    parts.append("</body></html>")
    write_text(out, "\n".join(parts))
    return out
