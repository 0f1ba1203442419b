"""The report's loss curves (difftex.evaluation.losscurve): SVG that parses, on a log scale,
with gaps where a term is not positive, at the extremes of range and length."""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET

import pytest

from difftex.evaluation.losscurve import linear_step, log_ticks, loss_curve, loss_svg

NS = "{http://www.w3.org/2000/svg}"


def parse(svg: str):
    root = ET.fromstring(svg)
    lines = {}
    for pl in root.iter(f"{NS}polyline"):
        pts = [tuple(map(float, p.split(","))) for p in pl.get("points").split()]
        lines.setdefault(pl.get("stroke"), []).append(pts)
    return root, lines


def test_log_ticks_and_linear_steps():
    assert log_ticks(0.003, 20.0) == [0.01, 0.1, 1.0, 10.0]
    assert log_ticks(0.15, 0.9) == [0.2, 0.5]  # less than a decade: 2 and 5 times
    assert log_ticks(0.31, 0.32) == [0.31]  # nothing inside: the lower end
    with pytest.raises(ValueError):
        log_ticks(0.0, 1.0)
    assert linear_step(7) == 1 and linear_step(40) == 5 and linear_step(370) == 50 and linear_step(10_000) == 1000


def test_curve_is_monotone_on_a_log_axis_with_levels_and_legend():
    levels = [
        {"shape": [16, 32], "loss": {"total": [10.0, 1.0, 0.1], "render": [1.0, 1.0, 1.0], "para": [0.0] * 3}},
        {"shape": [64, 128], "loss": {"total": [0.01, 0.001], "render": [1.0, 1.0]}},
    ]
    root, lines = parse(loss_svg(levels, "wall00: loss"))
    total = lines["#000000"][0]
    assert len(total) == 5
    ys = [y for _, y in total]
    assert all(a < b for a, b in zip(ys, ys[1:]))  # falling loss: rising y (SVG y points down)
    # equal ratios are equal steps: a log scale
    steps = [b - a for a, b in zip(ys, ys[1:])]
    assert max(steps) - min(steps) < 0.2
    assert "#2ca02c" not in lines  # para is zero throughout: left out, and not in the legend
    text = " ".join(t.text or "" for t in root.iter(f"{NS}text"))
    assert "level 1 128x64" in text and "wall00: loss" in text and "para" not in text
    assert sum(1 for ln in root.iter(f"{NS}line") if ln.get("stroke-dasharray")) == 1  # one level boundary


def test_non_positive_and_non_finite_values_are_gaps():
    levels = [{"loss": {"total": [1.0, 0.5, 0.0, float("nan"), 0.2, 0.1, -1.0, 0.05]}}]
    _, lines = parse(loss_svg(levels))
    runs = lines["#000000"]
    assert [len(set(run)) for run in runs] == [2, 2, 1]  # a lone value is a dot (a zero-length line)
    for run in lines["#000000"]:
        assert all(math.isfinite(v) for p in run for v in p)


@pytest.mark.parametrize(
    "values",
    [[0.5], [0.3, 0.3, 0.3], [1e-30, 1e30], [1e-12] * 4],
    ids=["one-iteration", "flat", "60-decades", "tiny-flat"],
)
def test_extremes_give_finite_points_inside_the_axes(values):
    root, lines = parse(loss_svg([{"loss": {"total": values}}]))
    W, H = float(root.get("width")), float(root.get("height"))
    pts = [p for run in lines["#000000"] for p in run]
    assert pts and all(0 <= x <= W and 0 <= y <= H and math.isfinite(x) and math.isfinite(y) for x, y in pts)


def test_no_loss_writes_nothing(tmp_path):
    assert loss_svg([{"loss": {"total": [0.0, 0.0]}}]) is None
    assert loss_curve({"levels": [{"iterations": 3}]}, tmp_path / "c.svg") is None
    assert not (tmp_path / "c.svg").exists()
    assert loss_curve({"levels": [{"loss": {"total": [2.0, 1.0]}}]}, tmp_path / "c.svg") == tmp_path / "c.svg"
    ET.parse(tmp_path / "c.svg")
