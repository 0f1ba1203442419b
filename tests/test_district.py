"""The district generator for scale tests (difftex.synth.district, docs/synth.md *Districts*)."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pytest

from difftex.errors import DifftexError
from difftex.synth.district import DistrictConfig, flatten, generate_district, layout, raycast


def _digest(root: Path) -> dict[str, str]:
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file() and p.name != "synth_timing.json"}


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> tuple[Path, dict]:
    out = tmp_path_factory.mktemp("district") / "a"
    return out, generate_district(out, buildings=4, views=6, seed=3)


def test_same_seed_same_bytes(tiny, tmp_path):
    out, _ = tiny
    generate_district(tmp_path / "b", buildings=4, views=6, seed=3)
    a, b = _digest(out), _digest(tmp_path / "b")
    assert a == b and len(a) >= 24 + 6  # 24 photos, COLMAP files, proxy, manifest
    generate_district(tmp_path / "c", buildings=4, views=6, seed=4)
    assert _digest(tmp_path / "c")["proxy.obj"] != a["proxy.obj"]


def test_counts_and_coverage(tiny):
    out, m = tiny
    sizes = [len(b["polygons"]) for b in m["buildings"]]
    assert len(sizes) == 4 and all(6 <= n <= 12 for n in sizes)
    assert m["polygons"] == sum(sizes)
    assert m["photos"] == 24 and len(list((out / "images").glob("*.png"))) == 24
    # every polygon is seen by some photo (the generator's own ray casting)
    assert m["unseen_polygons"] == [] and min(c["photos"] for c in m["coverage"].values()) >= 1
    ids = [line.split()[1] for line in (out / "proxy.obj").read_text().splitlines() if line.startswith("g ")]
    assert ids == [fid for b in m["buildings"] for fid in b["polygons"]]


def test_loads_as_a_scene(tiny):
    from difftex.scene.loading import load_scene

    out, m = tiny
    sc = load_scene(out)
    assert len(sc.photos) == m["photos"] and len(sc.proxy) == m["polygons"]
    assert sc.photos[0].width == 160 and sc.photos[0].height == 120
    assert float(sc.up[2]) > 0.99


def test_raycast_agrees_with_projection(tiny):
    """A polygon's centroid, projected with the written camera, lands on a pixel of that polygon
    (when nothing stands in front of it)."""
    from difftex.scene.loading import load_scene

    out, _ = tiny
    sc = load_scene(out)
    faces = flatten(layout(DistrictConfig(buildings=4, views=6), 3), 3)
    checked = 0
    for ph in sc.photos[:8]:
        R, t = ph.R, ph.t
        f = float(ph.camera.params[0])
        ids, depth, _ = raycast(faces, R, t, f, ph.width, ph.height)
        for k, ring in enumerate(faces.outer):
            X = ring.mean(0)
            Xc = R @ X + t
            if Xc[2] <= 0.1:
                continue
            x, y = f * Xc[0] / Xc[2] + ph.width / 2, f * Xc[1] / Xc[2] + ph.height / 2
            if not (1 <= x < ph.width - 1 and 1 <= y < ph.height - 1):
                continue
            r, c = int(y), int(x)
            if abs(depth[r, c] - Xc[2]) < 0.01 * Xc[2]:
                assert ids[r, c] == k
                checked += 1
    assert checked >= 5


def test_bad_settings_are_refused(tmp_path):
    with pytest.raises(DifftexError, match="building"):
        DistrictConfig(buildings=0)
    with pytest.raises(DifftexError, match="unknown district setting"):
        generate_district(tmp_path, buildings=1, colour=2)
    assert np.isfinite(DistrictConfig().street)
