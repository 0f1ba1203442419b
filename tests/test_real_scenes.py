"""The shared real scenes load, and their proxies sit on the buildings the photos show."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from difftex.geometry.frames import uv_frame
from difftex.geometry.visibility import id_buffer, prepare
from difftex.scene.loading import load_scene

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
SCENES = sorted(p.name for p in DATA.iterdir()) if DATA.is_dir() else []


@pytest.mark.skipif(not SCENES, reason="../shared/data not present")
@pytest.mark.parametrize("name", SCENES)
def test_real_scene_loads_and_proxy_agrees_with_the_sfm_points(name):
    import pycolmap

    sc = load_scene(DATA / name)
    assert len(sc.photos) >= 2 and len(sc.proxy) >= 1
    for poly in sc.proxy.polygons:
        f = uv_frame(poly, sc.up, long_side=256)
        assert np.isfinite(f.A).all()
    pp = prepare(sc.proxy)
    rec = pycolmap.Reconstruction(str(DATA / name / "sparse" / "0"))
    pts = np.array([p.xyz for p in rec.points3D.values()])
    diam = max(p.diameter for p in sc.proxy.polygons)
    for ph in sc.photos[:: max(1, len(sc.photos) // 3)]:
        ids, dist = id_buffer(pp, ph, stride=8)
        assert (ids >= 0).mean() > 0.15, ph.name  # the proxy covers a good part of every photo
        # SfM points seen through a proxy pixel lie near the proxy surface there: compare the
        # ray distance to the proxy with the distance to the point, in this photo.
        pix, depth = ph.project(pts)
        ok = ph.in_image(pix) & (depth > 0)
        px = (pix[ok] / 8).astype(int)
        px[:, 0] = np.minimum(px[:, 0], ids.shape[1] - 1)
        px[:, 1] = np.minimum(px[:, 1], ids.shape[0] - 1)
        hit = ids[px[:, 1], px[:, 0]] >= 0
        d_point = np.linalg.norm(pts[ok][hit] - ph.center, axis=1)
        d_proxy = dist[px[hit, 1], px[hit, 0]]
        assert hit.sum() > 100
        # most points are within a few percent of the proxy's size from its surface (relief,
        # statues, columns are not modelled, so some are not)
        assert np.median(np.abs(d_point - d_proxy)) < 0.05 * diam, ph.name
