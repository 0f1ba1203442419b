"""Static HTML report: every picture it shows exists, nothing is fetched from the network, it
says what is untextured and why, shows held-out metrics, texel sizes and per-level diagnostics,
reads partial results, and (with Chromium) renders as a page a person can read."""

from __future__ import annotations

import re
import shutil
import subprocess
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

from difftex.compose.outputs import FILLED_GREY, palette, source_map, write_texture_outputs
from difftex.evaluation.html import comparison_page, markdown_table_html
from difftex.evaluation.report import write_report
from difftex.scene.files import read_image, write_image, write_json

CHROMIUM = Path("/usr/bin/chromium")


def fake_results(root: Path, method="difftex", held_out=True, maps=False) -> Path:
    """A results folder as the workflow writes it: two textured polygons (one from oblique
    photos only, with a rescued photo), one untextured with its reason, filter table, model
    summary and view, metrics (held-out views, or ground-truth maps), optimizer stats."""
    rng = np.random.default_rng(0)
    names = [f"img{i}.jpg" for i in range(12)]
    for k, pid in enumerate(("wall00", "roof00")):
        d = root / "textures" / pid
        H, W = 48, 64
        dom = rng.integers(0, 12 if k == 0 else 2, (H, W))
        mask = np.ones((H, W), bool)
        seen = rng.random((H, W)) > 0.05
        write_texture_outputs(
            d,
            rng.random((H, W, 3)).astype(np.float32),
            mask,
            seen,
            dom,
            names,
            {"method": method, "coverage": 0.95, "filled_texels": 3, "time_s": 1.5},
        )
        loss = {
            key: list(np.linspace(1, 0.1, 30) * s)
            for key, s in (("total", 3), ("render", 1), ("ghost", 1), ("persp", 0.1), ("para", 0.0))
        }
        level = {
            "shape": [24, 32],
            "candidates": 12,
            "iterations": 30,
            "cap": 40,
            "converged": True,
            "loss": loss,
            "final": {"total": 0.3, "render": 0.1},
            "weight_change": [0.2, 0.05],
            "eliminated_pixels": 7,
            "dropped_photos": ["img3.jpg"],
            "time_s": 0.5,
            "effective_photos": 2.75,
        }  # a diagnostic added later
        write_json(
            root / "optimized" / pid / "stats.json",
            {
                "levels": [level, dict(level, shape=[48, 64])],
                "time_stage_s": 2.0,
                "device": "cpu",
                "dropped": [{"photo": "img3.jpg", "level": 0, "iteration": 12}],
                "used_photos": names[:11],
            },
        )
    polys = [
        {
            "id": "wall00",
            "photos": names,
            "coverage": 0.95,
            "width": 64,
            "height": 48,
            "texel_size": 0.0123,
            "photo_texel_size": 0.00307,
            "texel_size_bound": "photos",
            "rescued": {"img11.jpg": {"texels": 433, "why": "inclined (83.8 deg > 80.0)"}},
        },
        {
            "id": "roof00",
            "photos": names[:2],
            "coverage": 0.9,
            "width": 64,
            "height": 48,
            "texel_size": 0.0456,
            "photo_texel_size": 0.004,
            "texel_size_bound": "max_long_side",
            "textured_from_oblique": True,
            "oblique_angles": {"img0.jpg": 83.0, "img1.jpg": 88.8},
        },
        {
            "id": "inner",
            "photos": [],
            "coverage": 0.0,
            "width": 8,
            "height": 8,
            "texel_size": 0.5,
            "photo_texel_size": None,
            "texel_size_bound": "min_long_side",
            "untextured_reason": "hidden behind other polygons in the 4 photo(s) that have it in view",
        },
    ]
    write_json(root / "visibility" / "summary.json", {"polygons": polys})
    write_json(
        root / "photos.json",
        {
            "config": {"blur_ratio": 0.3, "max_angle_deg": 80.0},
            "photos": [
                {
                    "name": n,
                    "kept": n != "img5.jpg",
                    "reason": "blurry (sharpness 0.12 x median < 0.3)" if n == "img5.jpg" else "",
                    "sharpness_rel": 1.0,
                    "polygons": {"wall00": {"pixels": 900, "angle_deg": 12.5}},
                }
                for n in names
            ],
            "polygons": {"wall00": {"kept": names[:11]}, "roof00": {"kept": names[:2]}, "inner": {"kept": []}},
        },
    )
    write_image(root / "model" / "model_view.png", rng.random((40, 120, 3)).astype(np.float32))
    write_json(
        root / "model" / "summary.json",
        {
            "polygons": [],
            "untextured": ["inner"],
            "untextured_reasons": {"inner": polys[2]["untextured_reason"]},
            "view_check": {"photo": "img0.jpg", "image": "model_view.png", "mean_abs_diff": 0.0812},
        },
    )
    metrics = {"perspective": {"q_front": 0.9, "q_vc": 0.8, "polygons": {"wall00": {"q_front": 0.9, "q_vc": 0.8}}}}
    if held_out:
        metrics["views"] = {
            "overall": {"ssim": 0.6543, "lpips": 0.2345, "psnr": 21.5, "views": 1, "lpips_variant": "stlpips"},
            "views": [{"photo": "held.jpg", "compared_pixels": 5000, "ssim": 0.6543, "lpips": 0.2345, "psnr": 21.5}],
            "held_out": ["held.jpg"],
        }
        for kind in ("render", "photo", "error"):
            write_image(root / "evaluation" / "views" / f"held_{kind}.png", rng.random((30, 40, 3)).astype(np.float32))
    if maps:
        metrics["maps"] = {
            "overall": {
                "error90": 0.1,
                "error95": 0.2,
                "ssim": 0.8,
                "lpips": 0.3,
                "psnr": 25.0,
                "lpips_variant": "stlpips",
            },
            "polygons": [{"polygon_id": "wall00", "error90": 0.1111, "error95": 0.2, "ssim": 0.8, "lpips": 0.3}],
        }
        for pid in ("wall00", "roof00"):
            write_image(root / "evaluation" / "error_maps" / f"{pid}.png", rng.random((16, 24)).astype(np.float32))
    write_json(root / "evaluation" / "metrics.json", metrics)
    return root


def local_links(html_text: str) -> list[str]:
    return re.findall(r'(?:src|href)="([^"]+)"', html_text) + re.findall(r"href='([^']+)'", html_text)


def test_report_links_resolve_and_loss_curves_are_readable(tmp_path):
    r = fake_results(tmp_path / "R")
    out = write_report(r)
    text = out.read_text()
    assert "http://" not in text and "https://" not in text and "<script" not in text
    links = local_links(text)
    assert len(links) >= 2 * 4 + 1 + 3  # 3 maps + loss curve per polygon, model view, held-out view
    for link in links:
        assert (out.parent / link).resolve().is_file(), link
    for pid in ("wall00", "roof00"):
        svg = ET.parse(out.parent / f"loss_{pid}.svg").getroot()  # well-formed
        assert float(svg.get("width")) >= 800 and float(svg.get("height")) >= 400  # readable at 100 %
        lines = svg.findall("{http://www.w3.org/2000/svg}polyline")
        assert {ln.get("stroke") for ln in lines} >= {"#000000", "#1f77b4"}  # total and render drawn
        assert f'loss_{pid}.svg"' in text


def test_report_says_what_is_untextured_and_shows_held_out_metrics(tmp_path):
    text = write_report(fake_results(tmp_path / "R")).read_text()
    assert "<b>inner</b>: hidden behind other polygons in the 4 photo(s)" in text
    assert "oblique photos only (83-89 deg)" in text and "img11.jpg kept for the 433 texels only it sees" in text
    # held-out views: their metrics, not n/a, and no ground-truth columns full of n/a
    assert "0.6543" in text and "0.2345" in text and "21.5000" in text and "held.jpg" in text
    assert "Error 90%" not in text
    # texel size in scene units and what set it, map size, per-level diagnostics (known and new keys)
    assert "0.0123" in text and "cap max_long_side" in text and "64x48" in text
    assert "effective_photos" in text and "2.75" in text and "30 / 40" in text
    # the photo filter table
    assert "blurry (sharpness 0.12 x median &lt; 0.3)" in text and "wall00 12&deg;" in text
    assert "wall00 (only the texels no other photo sees)" in text  # img11.jpg, taken back by the visibility stage
    assert "Q_front 0.9000" in text


def test_report_with_ground_truth_maps_shows_their_columns(tmp_path):
    text = write_report(fake_results(tmp_path / "R", held_out=False, maps=True)).read_text()
    assert "Error 90%" in text and "0.1111" in text and "held-out" not in text


def test_report_of_partial_results_shows_na(tmp_path):
    """Only textures, no visibility summary, stats without the keys the report reads."""
    r = tmp_path / "R"
    d = r / "textures" / "wall00"
    write_image(d / "texture.png", np.full((8, 8, 3), 0.3, np.float32))
    write_json(r / "optimized" / "wall00" / "stats.json", {"levels": [{"iterations": 3}]})
    text = write_report(r).read_text()
    assert "1 of 1</b> polygons textured" in text and "n/a" in text
    assert "No evaluation" in text


@pytest.mark.skipif(
    not CHROMIUM.is_file(),
    reason="needs Debian's chromium at /usr/bin/chromium (apt-get install chromium; .ci/run installs it when root)",
)
def test_report_screenshot_in_headless_chromium(tmp_path):
    """The page as a browser draws it: the source maps, their legend swatches and the loss curves
    reach the screen (colours only those images and swatches carry appear in the screenshot)."""
    out = write_report(fake_results(tmp_path / "R"))
    shot = tmp_path / "shot.png"
    run = subprocess.run(
        [
            str(CHROMIUM),
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--hide-scrollbars",
            f"--screenshot={shot}",
            "--window-size=1400,2600",
            out.resolve().as_uri(),
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert shot.is_file(), run.stderr[-2000:]
    img = (read_image(shot)[..., :3] * 255).round().astype(int)
    assert img.shape[:2] == (2600, 1400)

    def pixels_near(rgb, tol=6):
        return int((np.abs(img - np.array(rgb) * 255).max(-1) <= tol).sum())

    pal = palette(12)
    assert pixels_near(pal[0]) > 500 and pixels_near(pal[1]) > 500  # source maps and swatches
    assert pixels_near((0.0, 0.0, 0.0), tol=20) > 2000  # text, and the loss curves' black total
    assert img.size // 3 - pixels_near((1.0, 1.0, 1.0)) > 100_000  # not a blank page
    shutil.copy(shot, out.parent / "screenshot.png")  # for a person to look at (tmp_path)


def test_palette_is_distinct_and_avoids_the_map_greys():
    cols = np.array(palette(60))
    assert len({tuple(np.round(c * 255).astype(int)) for c in cols}) == 60  # all distinct in 8 bits
    d = np.linalg.norm(cols[:9, None] - cols[None, :9], axis=-1)
    assert d[~np.eye(9, dtype=bool)].min() > 0.2  # the first nine: clearly different hues
    grey = np.abs(cols - cols.mean(1, keepdims=True)).max(1) < 0.05
    assert not (grey & (np.abs(cols.mean(1) - FILLED_GREY) < 0.1)).any()  # nothing reads as a filled texel
    assert (cols.max(1) > 0.1).all()  # nor as outside the polygon (black)


def test_source_map_colours_follow_the_photos_it_shows():
    names = ["a.jpg", "b.jpg", "c.jpg", "d.jpg"]
    dom = np.array([[3, 1], [-1, 3]])
    mask = np.array([[True, True], [True, False]])
    sm = source_map(dom, names, mask, filled=np.array([[False, False], [True, False]]))
    pal = palette(2)
    # only b and d appear: they get the palette's first two colours, in photo order
    assert np.allclose(sm[0, 1], pal[0]) and np.allclose(sm[0, 0], pal[1])
    assert np.allclose(sm[1, 0], FILLED_GREY) and np.allclose(sm[1, 1], 0)


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


def test_the_palette_starts_from_matplotlibs_tab10():
    from matplotlib import colormaps

    from difftex.compose.outputs import TAB10

    assert np.allclose(np.array(TAB10), np.array(colormaps["tab10"].colors), atol=1e-9)
