"""Bad input gets one clear line naming the file and the problem, and no traceback."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from difftex.cli import main
from difftex.scene.files import write_image
from difftex.scene.proxy import load_proxy

from tests.scenes import make_scene, wall, write_obj


def run_cli(capsys, *argv) -> tuple[int, str]:
    code = main(list(argv))
    err = capsys.readouterr().err.strip()
    return code, err


def assert_one_line_error(code, err, *needles):
    assert code == 2, err
    assert len(err.splitlines()) == 1 and err.startswith("difftex: error: "), err
    assert "Traceback" not in err
    for n in needles:
        assert n in err, (n, err)


@pytest.fixture
def scene(tmp_path):
    return make_scene(tmp_path / "scene")


def test_good_scene_inspects(scene, capsys):
    code = main(["inspect", str(scene)])
    assert code == 0
    assert "3 photos" in capsys.readouterr().out


def test_missing_image(scene, capsys):
    (scene / "images" / "img01.png").unlink()
    assert_one_line_error(*run_cli(capsys, "inspect", str(scene)), "img01.png", "missing")


def test_corrupt_image_header(scene, capsys):
    (scene / "images" / "img01.png").write_bytes(b"this is not a png at all")
    assert_one_line_error(*run_cli(capsys, "inspect", str(scene)), "img01.png")


def test_truncated_image_fails_when_read(scene, capsys, tmp_path):
    p = scene / "images" / "img02.png"
    data = p.read_bytes()
    p.write_bytes(data[: len(data) // 2])
    code, err = run_cli(
        capsys, "filter", "--scene", str(scene), "--out", str(tmp_path / "out" / "photos.json"), "--quiet"
    )
    assert_one_line_error(code, err, "img02.png")
    assert not (tmp_path / "out" / "photos.json").exists()  # no half-written output


def test_wrong_image_size(scene, capsys):
    write_image(scene / "images" / "img00.png", np.zeros((50, 60, 3), np.float32))
    assert_one_line_error(*run_cli(capsys, "inspect", str(scene)), "img00.png", "60x50", "160x120")


def test_nan_pose(scene, capsys):
    lines = (scene / "sparse/0/images.txt").read_text().splitlines()
    parts = lines[0].split()
    parts[5] = "nan"  # the x of the translation
    lines[0] = " ".join(parts)
    (scene / "sparse/0/images.txt").write_text("\n".join(lines) + "\n")
    assert_one_line_error(*run_cli(capsys, "inspect", str(scene)), "img00.png", "not finite")


def test_missing_colmap_model(scene, capsys):
    for f in (scene / "sparse/0").iterdir():
        f.unlink()
    assert_one_line_error(*run_cli(capsys, "inspect", str(scene)), "sparse")


def test_garbled_colmap_model(scene, capsys):
    (scene / "sparse/0/cameras.txt").write_text("1 NOT_A_MODEL 10 10 1 2 3\n")
    assert_one_line_error(*run_cli(capsys, "inspect", str(scene)), "sparse")


def test_non_planar_polygon(scene, capsys):
    bent = wall(-2, 2, 0, 2)
    bent[2, 1] = 0.5  # lift one corner half a metre out of the plane
    write_obj(scene / "proxy.obj", {"bent": bent})
    assert_one_line_error(*run_cli(capsys, "inspect", str(scene)), "proxy.obj", "'bent'", "not planar", "deviation")


def test_empty_proxy(scene, capsys):
    (scene / "proxy.obj").write_text("# nothing here\n")
    assert_one_line_error(*run_cli(capsys, "inspect", str(scene)), "proxy.obj", "no usable polygons")


def test_degenerate_polygons_are_skipped_with_a_warning(tmp_path, caplog):
    path = tmp_path / "p.obj"
    line = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0.0]])  # collinear
    write_obj(path, {"good": wall(0, 1, 0, 1), "collinear": line, "point": np.zeros((4, 3))})
    with caplog.at_level(logging.WARNING):
        proxy = load_proxy(path)
    assert proxy.ids == ["good"]
    assert "collinear" in caplog.text and "degenerate" in caplog.text


def test_unsupported_proxy_format(scene, capsys):
    (scene / "proxy.obj").unlink()
    (scene / "proxy.obj.bak").write_text("")
    assert_one_line_error(*run_cli(capsys, "inspect", str(scene)), "no proxy model")


def test_camera_that_sees_nothing_is_dropped_with_its_reason(tmp_path, capsys):
    from difftex.scene.files import read_json

    root = make_scene(tmp_path / "s", centers=[(0.0, -6.0, 1.0), (0.5, -6.0, 1.0), (0.0, 6.0, 1.0)])
    out = tmp_path / "r" / "photos.json"
    assert main(["filter", "--scene", str(root), "--out", str(out), "--quiet"]) == 0
    table = read_json(out)
    rec = {r["name"]: r for r in table["photos"]}
    assert rec["img02.png"]["kept"] is False and "sees no proxy polygon" in rec["img02.png"]["reason"]
    assert rec["img00.png"]["kept"] is True
    assert (out.with_suffix(".csv")).read_text().count("\n") == 4


def test_bad_config_key(scene, capsys, tmp_path):
    cfg = tmp_path / "c.yaml"
    cfg.write_text("filter:\n  blurr_ratio: 0.2\n")
    code, err = run_cli(
        capsys, "filter", "--scene", str(scene), "--config", str(cfg), "--out", str(tmp_path / "x.json")
    )
    assert_one_line_error(code, err, "blurr_ratio", "unknown key")
