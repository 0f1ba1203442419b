"""evaluation/quickstart_picture.py: the README's picture (a photo of a wall with its occluder, the
ground truth, difftex's texture), on the reduced tiny scene with the ground truth standing in for
difftex's textures; bad input ends in one line."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from difftex.errors import DifftexError

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture
def ground_truth_as_textures(small_synth_scene, monkeypatch):
    """load_textures of any results folder: the scene's ground-truth maps in their own frames."""
    import difftex.evaluation.evaluate as ev
    from difftex.evaluation.results import PolygonTexture
    from difftex.geometry.frames import UVFrame
    from difftex.scene.files import read_image, read_json

    gt = small_synth_scene / "ground_truth"

    def textures(results):
        out = {}
        for f in sorted((gt / "frames").glob("*.json")):
            frame = UVFrame.from_dict(read_json(f))
            out[f.stem] = PolygonTexture(f.stem, read_image(gt / "maps" / f"{f.stem}.png"), frame,
                                         np.ones(frame.shape, bool), {}, Path(results))
        return out

    monkeypatch.setattr(ev, "load_textures", textures)
    return small_synth_scene


def test_the_picture_shows_a_wall_three_times(ground_truth_as_textures, tmp_path, capsys):
    from PIL import Image

    from evaluation import quickstart_picture as Q

    out = tmp_path / "docs" / "quickstart.png"
    assert Q.main(["--scene", str(ground_truth_as_textures), "--results", str(tmp_path), "--out", str(out)]) == 0
    line = capsys.readouterr().out
    assert line.startswith(f"quickstart_picture: {out} (") and line.count("\n") == 1
    assert "wall" in line and "cropped to the wall" in line  # a wall, never a roof
    img = Image.open(out)
    assert img.height == Q.HEIGHT + Q.LABEL_H and img.width > 2 * Q.GAP + Q.HEIGHT  # three panels in a row
    assert out.stat().st_size < 400_000 and not list(out.parent.glob("*.tmp.png"))


def test_the_chosen_wall_is_seen_whole(small_synth_scene):
    from difftex.geometry.frames import UVFrame
    from difftex.scene.files import read_json
    from difftex.scene.loading import load_scene
    from evaluation import quickstart_picture as Q

    scene = small_synth_scene
    photos = load_scene(scene).photos
    polygons = sorted(f.stem for f in (scene / "ground_truth" / "frames").glob("*.json"))
    pid, photo, (x0, y0, x1, y1) = Q.choose(scene, polygons, photos, None, None)
    assert 0 <= x0 < x1 <= photo.width and 0 <= y0 < y1 <= photo.height
    frame = UVFrame.from_dict(read_json(scene / "ground_truth" / "frames" / f"{pid}.json"))
    area = Q.wall_in_photo(frame, photo)[0]
    for other in polygons:  # no other wall is seen whole and larger in any photo
        f = UVFrame.from_dict(read_json(scene / "ground_truth" / "frames" / f"{other}.json"))
        if abs(f.normal[2]) <= 0.5:
            assert all((s := Q.wall_in_photo(f, p)) is None or s[0] <= area for p in photos)
    with pytest.raises(DifftexError, match="has no ground truth and texture"):
        Q.choose(scene, polygons, photos, "tower", None)
    with pytest.raises(DifftexError, match="no registered photo"):
        Q.choose(scene, polygons, photos, None, "nothing.png")


def test_bad_input_is_one_line(tmp_path):
    p = subprocess.run([sys.executable, "evaluation/quickstart_picture.py", "--scene", str(tmp_path),
                        "--out", str(tmp_path / "q.png")], cwd=REPO, capture_output=True, text=True)
    assert p.returncode != 0 and "Traceback" not in p.stderr
    assert p.stderr.strip() == f"quickstart_picture: {tmp_path}: no ground_truth/frames (a scene made by difftex " \
                               "synth is needed)"
    assert not (tmp_path / "q.png").exists()
