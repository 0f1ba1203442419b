"""HTML building blocks of the reports (style, escaping, figures, tables, markdown tables) and the
side-by-side comparison page over several results folders (evaluation/table1.py, table2.py).

Plain HTML with relative links, no scripts, no network: every page opens from disk.
"""

from __future__ import annotations

import html
import os
from pathlib import Path

from difftex.layout import SOURCE_PNG, TEXTURE, Results
from difftex.scene.files import read_json, write_text

CSS = """body{font-family:sans-serif;font-size:15px;margin:1.5em;max-width:1500px;color:#222}
h2{border-bottom:2px solid #ccc;margin-top:1.6em}h3{margin:1.2em 0 .3em}
table{border-collapse:collapse;margin:.5em 0}
td,th{border:1px solid #bbb;padding:3px 7px;text-align:right;vertical-align:top}
th{background:#eee}td:first-child,th:first-child{text-align:left}td.l{text-align:left}
img{image-rendering:pixelated;max-width:420px;max-height:360px;border:1px solid #ccc;margin:2px}
img.map{max-width:none;max-height:none}img.wide{image-rendering:auto;max-width:100%;max-height:none}
figure{display:inline-block;margin:4px 10px 4px 0;vertical-align:top}
figcaption{font-size:85%;text-align:center;max-width:420px}
.small{font-size:88%;color:#444}.warn{color:#a40}
.sw{display:inline-block;width:1.1em;height:1.1em;border:1px solid #555;
vertical-align:middle;margin:0 .3em 0 .8em}.legend{line-height:1.9}
.row{display:flex;gap:1.2em;align-items:flex-start;flex-wrap:wrap}"""


def _esc(x) -> str:
    return html.escape(str(x))


def _rel(target: Path, start: Path) -> str:
    return html.escape(os.path.relpath(target, start).replace(os.sep, "/"))


MAP_BOX = (420, 360)  # maps are shown scaled to fit this box (width, height), small ones enlarged


def _fig(path: Path, base: Path, caption: str, cls: str = "") -> str:
    """A linked picture with its caption; a texel map ("map") is scaled to fit MAP_BOX, so that a
    64-texel map is as readable as a 2048-texel one."""
    if not path.is_file():
        return ""
    size = ""
    if cls == "map":
        from difftex.scene.files import image_size

        try:
            w, h = image_size(path)
            k = min(MAP_BOX[0] / w, MAP_BOX[1] / h)
            size = f' width="{max(1, round(w * k))}" height="{max(1, round(h * k))}"'
        except Exception:  # noqa: BLE001 -- an unreadable picture is shown as the browser can
            size = ""
    c = f' class="{cls}"' if cls else ""
    return (
        f'<figure><a href="{_rel(path, base)}"><img{c}{size} src="{_rel(path, base)}" alt="{_esc(caption)}"></a>'
        f"<figcaption>{_esc(caption)}</figcaption></figure>"
    )


def _num(v, fmt: str = ".4g") -> str:
    if v is None:
        return "n/a"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, float):
        return format(v, fmt)
    if isinstance(v, (list, tuple)):
        return _esc(", ".join(str(x) for x in v)) if v else "-"
    return _esc(v)


def _table(header: list[str], rows: list[list], fmt: str = ".4g") -> str:
    h = "".join(f"<th>{_esc(x)}</th>" for x in header)
    body = "".join(
        "<tr>"
        + "".join(c[1] if isinstance(c, tuple) and c[0] == "html" else f"<td>{_num(c, fmt)}</td>" for c in r)
        + "</tr>"
        for r in rows
    )
    return f"<table><tr>{h}</tr>{body}</table>"


def _html(text: str, cls: str = "l") -> tuple:
    """A table cell holding ready-made HTML (``_table`` escapes everything else)."""
    return ("html", f"<td class={cls}>{text}</td>")


def _read(path: Path) -> dict:
    """A JSON file as a dict, {} when it is missing or not a dict."""
    try:
        data = read_json(path) if path.is_file() else {}
    except Exception:  # noqa: BLE001 -- a report shows what it can; a broken file is reported as absent
        return {}
    return data if isinstance(data, dict) else {}


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


def comparison_page(
    out: str | Path, title: str, table_md: str, runs: dict[str, str | Path], scene: str | Path | None = None
) -> Path:
    """One page: the table, links to each method's report, and every polygon's textures side by side."""
    out = Path(out)
    base = out.parent
    parts = [
        "<!doctype html><html><head><meta "
        f"charset='utf-8'><title>{html.escape(title)}</title><style>{CSS}</style></head><body>",
        markdown_table_html(table_md),
        "<h2>Reports per method</h2><ul>",
    ]
    res = {m: Results(r) for m, r in runs.items()}
    for m, rs in res.items():
        parts.append(f"<li><a href='{_rel(rs.report_html, base)}'>{html.escape(m)}</a></li>")
    parts.append("</ul><h2>Textures side by side</h2>")
    pids = sorted({p.name for rs in res.values() for p in rs.textures_dir.glob("*") if (p / TEXTURE).is_file()})
    for pid in pids:
        figs = []
        if scene is not None:
            figs.append(_fig(Path(scene) / "ground_truth" / "maps" / f"{pid}.png", base, "ground truth"))
        for m, rs in res.items():
            figs.append(_fig(rs.texture(pid), base, m))
            figs.append(_fig(rs.polygon_textures(pid) / SOURCE_PNG, base, f"{m} sources"))
        parts.append(f"<h3>{html.escape(pid)}</h3>" + "".join(f for f in figs if f))
    parts.append("</body></html>")
    write_text(out, "\n".join(parts))
    return out
