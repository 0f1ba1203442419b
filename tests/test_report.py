"""Static HTML report: every picture it shows exists, nothing is fetched from the network."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from difftex.io import write_image, write_json
from difftex.report import comparison_page, markdown_table_html, write_report


def fake_results(root: Path, method="difftex") -> Path:
    rng = np.random.default_rng(0)
    for pid in ("wall00", "roof00"):
        d = root / "textures" / pid
        for f in ("texture.png", "source.png", "coverage.png"):
            write_image(d / f, rng.random((16, 24, 3)).astype(np.float32))
        write_json(d / "report.json", {"method": method, "coverage": 0.9, "filled_texels": 3, "time_s": 1.5,
                                       "source_colours": {"a.jpg": "#ff0000"}})
        write_image(root / "evaluation" / "error_maps" / f"{pid}.png", rng.random((16, 24)).astype(np.float32))
        loss = {k: list(np.linspace(1, 0.1, 30)) for k in ("total", "render", "ghost", "persp", "para")}
        write_json(root / "optimized" / pid / "stats.json", {"levels": [{"loss": loss}, {"loss": loss}], "time_total_s": 2.0})
    write_json(root / "evaluation" / "metrics.json", {
        "maps": {"overall": {"error90": 0.1, "error95": 0.2, "ssim": 0.8, "lpips": 0.3, "psnr": 25.0, "lpips_variant": "stlpips"},
                 "polygons": [{"polygon_id": "wall00", "error90": 0.1, "error95": 0.2, "ssim": 0.8, "lpips": 0.3}]},
        "perspective": {"q_front": 0.9, "q_vc": 0.8, "polygons": {"wall00": {"q_front": 0.9, "q_vc": 0.8}}}})
    return root


def local_links(html_text: str) -> list[str]:
    return re.findall(r'(?:src|href)="([^"]+)"', html_text) + re.findall(r"href='([^']+)'", html_text)


def test_report_links_resolve_and_loss_curves_are_drawn(tmp_path):
    r = fake_results(tmp_path / "R")
    out = write_report(r)
    text = out.read_text()
    assert "http://" not in text and "https://" not in text and "<script" not in text
    links = local_links(text)
    assert len(links) >= 2 * 4 + 2  # 3 maps + error map + loss curve per polygon
    for link in links:
        assert (out.parent / link).resolve().is_file(), link
    for pid in ("wall00", "roof00"):
        png = out.parent / f"loss_{pid}.png"
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "0.1000" in text and "Q_front 0.9000" in text


def test_comparison_page_and_markdown_tables(tmp_path):
    a = fake_results(tmp_path / "a", "average")
    b = fake_results(tmp_path / "b", "mrf")
    md = "# T\n\n- note\n\n| Method | SSIM |\n|---|---|\n| x | 0.5 |\n"
    h = markdown_table_html(md)
    assert "<th>Method</th>" in h and "<td>0.5</td>" in h and "---" not in h
    out = comparison_page(tmp_path / "index.html", "T", md, {"average": a, "mrf": b})
    text = out.read_text()
    for link in local_links(text):
        if link.endswith("index.html"):
            continue  # per-method reports are written separately
        assert (out.parent / link).resolve().is_file(), link
