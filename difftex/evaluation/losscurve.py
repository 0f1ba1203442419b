"""The optimizer's loss curves as SVG line charts, for the HTML report.

Written out rather than drawn with matplotlib: the report is the last job of every run, and
matplotlib's import and six tight-layout PNGs were 1.5 of its 2 seconds on a six-polygon building
(the workflow's critical path). A log-scale line chart with a legend is a few SVG elements; the
browser draws it sharp at any zoom, and the file is text.
"""

from __future__ import annotations

import math
from html import escape as _esc
from pathlib import Path

# matplotlib's colours for the terms (k, C0, C3, C4, C1, C2), so the curves look as they did;
# "sparsity" is the paper's L1 term (weights: normalised), drawn only where it is on
LOSS_COLOURS = (
    ("total", "#000000"),
    ("render", "#1f77b4"),
    ("ghost", "#d62728"),
    ("sparsity", "#9467bd"),
    ("persp", "#ff7f0e"),
    ("para", "#2ca02c"),
)
SIZE = (900, 420)  # px: axes and legend readable at 100 %
MARGIN = (80, 110, 34, 52)  # left, right (legend), top (title), bottom (axis label)


def log_ticks(lo: float, hi: float) -> list[float]:
    """Tick values for a log axis over [lo, hi] (0 < lo <= hi): the decades, and 2 and 5 times
    them where fewer than three decades fall inside.

    Returns:
        increasing tick values inside [lo, hi] (at least one: lo when nothing else falls inside).
    """
    if not (0 < lo <= hi) or not math.isfinite(hi):
        raise ValueError(f"need 0 < lo <= hi, got {lo}, {hi}")
    first, last = math.floor(math.log10(lo)), math.ceil(math.log10(hi))
    decades = [10.0**e for e in range(first, last + 1)]
    inside = [t for t in decades if lo <= t <= hi]
    if len(inside) < 3:
        inside = sorted(t * m for t in decades for m in (1, 2, 5) if lo <= t * m <= hi)
    return inside or [lo]


def linear_step(n: int, most: int = 10) -> int:
    """A 1-2-5 step between integer ticks so that at most ``most`` ticks cover 1..n."""
    step = 1
    while n / step > most:
        for m in (2, 5, 10):
            if n / (step * m) <= most or m == 10:
                step *= m
                break
    return step


def _tick_label(v: float) -> str:
    return f"{v:g}" if 1e-3 <= v < 1e4 else f"{v:.0e}".replace("e-0", "e-").replace("e+0", "e")


def loss_svg(levels: list[dict], title: str = "") -> str | None:
    """The SVG text of the loss terms per iteration, levels one after another, on a log scale.

    Args:
        levels: stats.json's per-level dicts; each may hold ``loss`` ({term: [value per
            iteration]}) and ``shape`` ([h, w]).
        title: drawn above the chart.

    Returns:
        The SVG document, or None when no level has a total loss. A term that is zero or absent
        throughout (switched off) is left out; its non-positive values are gaps in its line.
    """
    series = []
    for key, colour in LOSS_COLOURS:
        ys = [float(y) for lv in levels for y in ((lv.get("loss") or {}).get(key) or [])]
        if any(y > 0 and math.isfinite(y) for y in ys):
            series.append((key, colour, ys))
    if not series or not any((lv.get("loss") or {}).get("total") for lv in levels):
        return None
    positive = [y for _, _, ys in series for y in ys if y > 0 and math.isfinite(y)]
    lo, hi = min(positive), max(positive)
    if hi <= lo * 1.0001:  # a flat curve: a decade around it
        lo, hi = lo / math.sqrt(10), hi * math.sqrt(10)
    n = max(len(ys) for _, _, ys in series)
    W, H = SIZE
    left, right, top, bottom = MARGIN
    x0, x1, y0, y1 = left, W - right, top, H - bottom
    llo, lhi = math.log10(lo), math.log10(hi)
    pad = 0.04 * (lhi - llo)  # the extremes off the frame, below the level labels
    llo, lhi = llo - pad, lhi + 2 * pad

    def px(i: float) -> float:  # iteration (1-based) -> x
        return x0 + (x1 - x0) * ((i - 1) / max(n - 1, 1))

    def py(v: float) -> float:
        return y1 - (y1 - y0) * (math.log10(v) - llo) / (lhi - llo)

    out = [
        f'<svg xmlns="http://www.w3.org/2000/svg" width="{W}" height="{H}" viewBox="0 0 {W} {H}" '
        'font-family="DejaVu Sans, Arial, sans-serif">',
        f'<rect width="{W}" height="{H}" fill="#ffffff"/>',
    ]
    for t in log_ticks(lo, hi):
        y = py(t)
        out.append(f'<line x1="{x0}" y1="{y:.1f}" x2="{x1}" y2="{y:.1f}" stroke="#dddddd"/>')
        out.append(f'<text x="{x0 - 6}" y="{y + 4:.1f}" font-size="12" text-anchor="end">{_tick_label(t)}</text>')
    step = linear_step(n)
    for i in range(step, n + 1, step):
        x = px(i)
        out.append(f'<line x1="{x:.1f}" y1="{y1}" x2="{x:.1f}" y2="{y1 + 5}" stroke="#000000"/>')
        out.append(f'<text x="{x:.1f}" y="{y1 + 19}" font-size="12" text-anchor="middle">{i}</text>')
    start = 0
    for k, lv in enumerate(levels):
        count = len((lv.get("loss") or {}).get("total") or [])
        shape = lv.get("shape")
        x = px(start + 1) if n > 1 else x0
        if k:
            xs = px(start + 0.5)
            out.append(
                f'<line x1="{xs:.1f}" y1="{y0}" x2="{xs:.1f}" y2="{y1}" stroke="#888888" stroke-dasharray="5,4"/>'
            )
        label = f"level {k}" + (f" {shape[1]}x{shape[0]}" if isinstance(shape, list) and len(shape) == 2 else "")
        out.append(f'<text x="{x + 3:.1f}" y="{y0 + 14}" font-size="11" fill="#555555">{_esc(label)}</text>')
        start += count
    for _key, colour, ys in series:
        runs, cur = [], []
        for i, y in enumerate(ys, 1):
            if y > 0 and math.isfinite(y):
                cur.append(f"{px(i):.1f},{py(y):.1f}")
            elif cur:
                runs.append(cur)
                cur = []
        runs += [cur] if cur else []
        for r in runs:
            pts = " ".join(r) if len(r) > 1 else f"{r[0]} {r[0]}"
            out.append(
                f'<polyline points="{pts}" fill="none" stroke="{colour}" stroke-width="1.6" '
                f'stroke-linejoin="round" stroke-linecap="round"/>'
            )
    out.append(f'<rect x="{x0}" y="{y0}" width="{x1 - x0}" height="{y1 - y0}" fill="none" stroke="#000000"/>')
    for j, (key, colour, _) in enumerate(series):
        y = y0 + 10 + 22 * j
        out.append(f'<line x1="{x1 + 12}" y1="{y}" x2="{x1 + 36}" y2="{y}" stroke="{colour}" stroke-width="2"/>')
        out.append(f'<text x="{x1 + 42}" y="{y + 4}" font-size="13">{_esc(key)}</text>')
    out.append(
        f'<text x="{(x0 + x1) / 2:.0f}" y="{H - 12}" font-size="13" text-anchor="middle">'
        "iteration (all levels, coarse to fine)</text>"
    )
    out.append(
        f'<text x="18" y="{(y0 + y1) / 2:.0f}" font-size="13" text-anchor="middle" '
        f'transform="rotate(-90 18 {(y0 + y1) / 2:.0f})">loss</text>'
    )
    if title:
        out.append(f'<text x="{(x0 + x1) / 2:.0f}" y="22" font-size="13" text-anchor="middle">{_esc(title)}</text>')
    out.append("</svg>")
    return "\n".join(out) + "\n"


def loss_curve(stats: dict, out: Path, title: str = "") -> Path | None:
    """Write the loss curve of a polygon's stats.json to ``out`` (an .svg file), atomically.

    Returns:
        ``out``, or None when the stats hold no loss (nothing is written).
    """
    from difftex.scene.files import write_text

    levels = [lv for lv in stats.get("levels") or [] if isinstance(lv, dict)]
    svg = loss_svg(levels, title)
    if svg is None:
        return None
    write_text(out, svg)
    return out
