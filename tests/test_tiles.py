"""3D Tiles 1.1 output (difftex.export.tiles): one GLB tile per building with its own atlas, the
tiles' content back in the scene frame after the runtime's y-up -> z-up turn, bounding boxes
around it, the geo-reference, `difftex assemble --tileset` on a CityJSON scene, and the reference
validators (CesiumGS 3d-tiles-validator, Khronos glTF validator) where they are installed."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from difftex.cli import main
from difftex.errors import DifftexError
from difftex.export.assemble import AssembleConfig
from difftex.export.check import sample_atlas
from difftex.export.tiles import (
    WGS84_A,
    WGS84_F,
    building_groups,
    enu_to_ecef,
    level_rotation,
    root_transform,
    write_tileset,
)
from difftex.geometry.frames import texel_mask, uv_frame
from difftex.scene.files import read_json, write_image, write_json, write_npz
from difftex.scene.proxy import load_proxy

from tests.scenes import make_scene
from tests.test_assemble import UP, _items, _scene
from tests.test_cityjson import city, house, write_city

REPO = Path(__file__).resolve().parents[1]
# glTF content -> 3D Tiles frame, what a runtime applies to every tile's glTF (3D Tiles 1.1)
Y_UP_TO_Z_UP = np.array([[1.0, 0, 0, 0], [0, 0, -1, 0], [0, 1, 0, 0], [0, 0, 0, 1]])


def _tile_meshes(path: Path) -> dict:
    """{node name: (vertices in the tileset frame, trimesh geometry)} of a tile GLB."""
    import trimesh

    scene = trimesh.load(path, file_type="glb", force="scene")
    out = {}
    for node in scene.graph.nodes_geometry:
        matrix, gname = scene.graph[node]
        geom = scene.geometry[gname]
        v = np.column_stack([geom.vertices, np.ones(len(geom.vertices))]) @ (Y_UP_TO_Z_UP @ matrix).T
        out[node] = (v[:, :3], geom)
    return out


def _in_box(points: np.ndarray, box: list[float], tol=1e-6) -> bool:
    c, axes = np.asarray(box[:3]), np.asarray(box[3:]).reshape(3, 3)
    local = (points - c) @ axes.T / (axes * axes).sum(1)  # axis-aligned boxes: exact
    return bool((np.abs(local) <= 1 + tol).all())


def test_tiles_hold_each_building_in_the_scene_frame_with_its_colours(tmp_path):
    items, colours = _items(np.random.default_rng(0), constant=True)
    cfg = AssembleConfig(padding=2, max_page_size=64)
    summary = write_tileset(items, tmp_path, cfg, generator="difftex test")
    ts = read_json(tmp_path / "tileset.json")
    assert ts["asset"] == {"version": "1.1", "generator": "difftex test"}
    root = ts["root"]
    assert "transform" not in root and not summary["georeferenced"] and not summary["levelled"]
    assert ts["geometricError"] >= root["geometricError"] > 0 and root["refine"] == "ADD"
    # the roof touches the front wall along its top edge; the two other walls stand apart
    assert [sorted(t["polygons"]) for t in summary["tiles"]] == [["front", "roof"], ["lshape"], ["holed"]]
    assert len(root["children"]) == 3
    polys = {p.id: p for p in _scene()}
    seen = []
    for child, row in zip(root["children"], summary["tiles"]):
        assert child["geometricError"] == 0 and child["content"]["uri"] == row["file"]
        assert _in_box(np.concatenate([polys[p].outer for p in row["polygons"]]), root["boundingVolume"]["box"])
        meshes = _tile_meshes(tmp_path / row["file"])
        assert sorted(meshes) == sorted(row["polygons"])
        for pid, (verts, geom) in meshes.items():
            seen.append(pid)
            assert _in_box(verts, child["boundingVolume"]["box"]), pid
            # back in the scene frame: the vertices lie on the polygon's plane and cover its area
            assert np.abs((verts - polys[pid].outer[0]) @ polys[pid].normal).max() < 1e-5, pid
            area = 0.5 * np.linalg.norm(
                np.cross(*(verts[geom.faces[:, 1:]] - verts[geom.faces[:, :1]]).transpose(1, 0, 2)), axis=1
            )
            assert area.sum() == pytest.approx(polys[pid].area, rel=1e-5), pid
            page = np.asarray(geom.visual.material.baseColorTexture.convert("RGB"), np.float32) / 255
            assert max(page.shape[:2]) <= 64  # assemble.max_page_size holds per tile
            got = sample_atlas(page, geom.visual.uv[geom.faces].mean(axis=1))
            want = colours.get(pid, np.array(cfg.untextured_color))
            assert np.abs(got - want).max() < 1.5 / 255, pid
    assert sorted(seen) == sorted(polys)


def test_rewrite_removes_tiles_no_longer_listed(tmp_path):
    items, _ = _items(np.random.default_rng(0), constant=True)
    write_tileset(items, tmp_path, AssembleConfig(padding=2))
    assert len(list((tmp_path / "tiles").glob("*.glb"))) == 3
    write_tileset(items[:1], tmp_path, AssembleConfig(padding=2))
    assert [p.name for p in (tmp_path / "tiles").glob("*.glb")] == ["building000.glb"]
    assert not list(tmp_path.rglob(".*"))  # no temporary files or page folders left


def test_cityjson_buildings_are_the_tiles(tmp_path):
    doc = city({"NL.house/1": house(lods=False), "house2": house(offset=(30.0, 0, 0), base=14, lods=False)})
    proxy = load_proxy(write_city(tmp_path / "p.city.json", doc))
    groups = building_groups(proxy.polygons)
    assert list(groups) == ["NL.house_1", "house2"] and [len(v) for v in groups.values()] == [6, 6]
    # the same polygons without CityJSON buildings: the two connected components
    from difftex.scene.proxy import Polygon

    plain = [Polygon(p.id, p.outer, p.holes) for p in proxy.polygons]
    assert list(building_groups(plain).values()) == list(groups.values())


def test_enu_frame_on_the_ellipsoid():
    m = enu_to_ecef(0.0, 0.0, 0.0)
    assert np.allclose(m[:3, 3], [WGS84_A, 0, 0]) and np.allclose(m[:3, :3], [[0, 0, 1], [1, 0, 0], [0, 1, 0]])
    pole = enu_to_ecef(0.0, 90.0, 10.0)
    assert np.allclose(pole[:3, 3], [0, 0, WGS84_A * (1 - WGS84_F) + 10.0], atol=1e-6)
    m = enu_to_ecef(13.4, 52.5, 34.0)  # Berlin
    assert np.allclose(m[:3, :3].T @ m[:3, :3], np.eye(3)) and np.linalg.det(m[:3, :3]) == pytest.approx(1.0)
    p = m[:3, 3]
    assert np.degrees(np.arctan2(p[1], p[0])) == pytest.approx(13.4)
    # the up axis is the ellipsoid's normal at the point: it is the gradient of x^2/a^2 + ... there
    b = WGS84_A * (1 - WGS84_F)
    grad = p / np.array([WGS84_A**2, WGS84_A**2, b**2])
    assert np.allclose(m[:3, 2], grad / np.linalg.norm(grad), atol=1e-9)
    t = root_transform({"lon": 13.4, "lat": 52.5, "height": 34.0})
    assert np.allclose(np.reshape(t, (4, 4)).T, m)  # column-major
    ecef = np.eye(4)
    ecef[:3, 3] = [1e6, 2e6, 3e6]
    assert root_transform({"ecef": ecef.T.reshape(-1).tolist()}) == ecef.T.reshape(-1).tolist()
    assert root_transform(None) is None


@pytest.mark.parametrize(
    "georef, needle",
    [
        ({"lon": 0.0}, "give lon, lat"),
        ({"lon": 0.0, "lat": 91.0}, "lat must be a number in [-90, 90]"),
        ({"lon": "x", "lat": 0.0}, "lon must be a number"),
        ({"ecef": [1, 2, 3]}, "ecef must be 16 numbers"),
        ({"ecef": [0.0] * 16}, "invertible"),
        ([1, 2], "must be null"),
    ],
)
def test_bad_georef_is_one_line(georef, needle):
    with pytest.raises(DifftexError) as exc:
        root_transform(georef)
    assert str(exc.value).startswith("assemble.tileset_georef: ") and needle in str(exc.value)


def _textured_city_scene(root: Path) -> tuple[Path, Path, dict[str, np.ndarray]]:
    """A scene folder whose proxy is two CityJSON houses, and beside it the visibility and
    texture files that `difftex assemble` reads (a constant colour per polygon, returned), without
    the optimizer."""
    scene = make_scene(root / "scene")
    (scene / "proxy.obj").unlink()
    doc = city({"house1": house(lods=False), "house2": house(offset=(16.0, 0, 0), base=14, lods=False)})
    write_city(scene / "proxy.city.json", doc)
    R = root / "results"
    rows = []
    rng = np.random.default_rng(1)
    colours: dict[str, np.ndarray] = {}
    for poly in load_proxy(scene / "proxy.city.json").polygons:
        frame = uv_frame(poly, UP, long_side=32)
        mask = texel_mask(poly, frame)
        write_npz(
            R / "visibility" / f"{poly.id}.npz",
            frame=np.array(json.dumps(frame.to_dict())),
            texel_mask=np.packbits(mask.ravel()),
            shape=np.array(frame.shape),
        )
        colour = np.round(rng.uniform(0.15, 0.95, 3) * 255) / 255  # exact in 8 bits
        write_image(R / "textures" / poly.id / "texture.png", np.broadcast_to(colour, (*frame.shape, 3)))
        colours[poly.id] = colour
        rows.append({"id": poly.id, "coverage": 1.0, "photos": []})
    write_json(R / "visibility" / "summary.json", {"polygons": rows})
    return scene, R, colours


def _assemble(scene: Path, R: Path, assemble_cfg: dict, *extra: str) -> dict:
    cfg = R / "config.yaml"
    cfg.write_text(json.dumps({"assemble": {"padding": 2, **assemble_cfg}}))
    argv = ["assemble", "--scene", str(scene), "--textures", str(R / "textures"), "--config", str(cfg)]
    assert main([*argv, "--out-dir", str(R / "model"), *extra]) == 0
    return read_json(R / "model" / "summary.json")


def test_assemble_writes_a_georeferenced_tileset_of_a_cityjson_scene(tmp_path):
    scene, R, _ = _textured_city_scene(tmp_path)
    summary = _assemble(scene, R, {"tileset": True, "tileset_georef": {"lon": 7.1, "lat": 50.7, "height": 60.0}})
    assert summary["tileset"]["file"] == "tileset/tileset.json" and summary["tileset"]["georeferenced"]
    assert [t["name"] for t in summary["tileset"]["tiles"]] == ["house1", "house2"]
    rows = {r["id"]: r for r in summary["polygons"]}
    assert (
        rows["house2_RoofSurface_1"]["semantic"] == "RoofSurface"
        and rows["house2_RoofSurface_1"]["building"] == "house2"
    )
    ts = read_json(R / "model" / "tileset" / "tileset.json")
    assert np.allclose(np.reshape(ts["root"]["transform"], (4, 4)).T, enu_to_ecef(7.1, 50.7, 60.0))
    assert ts["root"]["children"][0]["extras"]["semantics"]["house1_WallSurface_0"] == "WallSurface"
    # the same without the config key, by the command's flag: the local frame, levelled (the
    # cameras of make_scene are about upright in a z-up frame, so the turn is small)
    from difftex.scene.camera import load_photos, scene_up

    summary = _assemble(scene, R, {}, "--tileset")
    assert not summary["tileset"]["georeferenced"] and summary["tileset"]["levelled"]
    transform = np.reshape(read_json(R / "model/tileset/tileset.json")["root"]["transform"], (4, 4)).T
    up = scene_up(load_photos(scene / "sparse" / "0", scene / "images", check_images=False))
    assert np.allclose(transform, level_rotation(up)) and np.allclose(transform, np.eye(4), atol=0.05)


@pytest.mark.parametrize("up", [(0, 0, 1), (0, 0, -1), (0.2, -0.9, 0.1), (1, 0, 0)])
def test_level_rotation_turns_up_to_z(up):
    m = level_rotation(np.asarray(up, float))
    u = np.asarray(up, float) / np.linalg.norm(up)
    assert np.allclose(m[:3, :3] @ u, [0, 0, 1]) and np.allclose(m[:3, :3].T @ m[:3, :3], np.eye(3))
    assert np.linalg.det(m[:3, :3]) == pytest.approx(1.0) and np.allclose(m[3], [0, 0, 0, 1])


# ---------------------------------------------------------------------------------------------
# Reference validators (installed by .ci/run into .cache/npm when npm is there)


def _npm_bin(name: str) -> list[str] | None:
    local = REPO / ".cache" / "npm" / "node_modules" / ".bin" / name
    if local.is_file():
        return [str(local)]
    found = shutil.which(name)
    return [found] if found else None


def test_3d_tiles_validator_finds_no_error(tmp_path):
    """CesiumGS's reference validator on the tileset of a tiny scene (it also runs the Khronos
    glTF validator on every tile)."""
    exe = _npm_bin("3d-tiles-validator")
    if exe is None or shutil.which("node") is None:
        pytest.skip(
            "3d-tiles-validator is not installed (.ci/run installs it into .cache/npm: "
            "npm install --prefix .cache/npm 3d-tiles-validator)"
        )
    scene, R, _ = _textured_city_scene(tmp_path)
    _assemble(scene, R, {"tileset": True, "tileset_georef": {"lon": 7.1, "lat": 50.7, "height": 60.0}})
    report = tmp_path / "report.json"
    tileset = R / "model" / "tileset" / "tileset.json"
    p = subprocess.run(
        [*exe, "--tilesetFile", str(tileset), "--reportFile", str(report)],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert report.is_file(), p.stdout + p.stderr
    rep = json.loads(report.read_text())
    assert rep["numErrors"] == 0, json.dumps(rep["issues"], indent=1)[:4000]
    assert rep["numWarnings"] == 0, json.dumps(rep["issues"], indent=1)[:4000]


GLTF_VALIDATE = """
const fs = require("fs");
const validator = require(process.argv[1]);
(async () => {
  const out = {};
  for (const f of process.argv.slice(2)) {
    const r = await validator.validateBytes(new Uint8Array(fs.readFileSync(f)));
    out[f] = {errors: r.issues.numErrors, warnings: r.issues.numWarnings,
              messages: r.issues.messages.filter((m) => m.severity <= 1).slice(0, 5)};
  }
  console.log(JSON.stringify(out));
})();
"""


def test_gltf_validator_finds_no_error_in_the_tiles(tmp_path):
    """The Khronos glTF validator (npm gltf-validator) on every tile, as 3d-tiles-validator runs it."""
    module = REPO / ".cache" / "npm" / "node_modules" / "gltf-validator"
    if not module.is_dir() or shutil.which("node") is None:
        pytest.skip(
            "gltf-validator is not installed (.ci/run installs it: npm install --prefix .cache/npm gltf-validator)"
        )
    items, _ = _items(np.random.default_rng(0), constant=True)
    summary = write_tileset(items, tmp_path, AssembleConfig(padding=2))
    files = [str(tmp_path / t["file"]) for t in summary["tiles"]]
    p = subprocess.run(
        ["node", "-e", GLTF_VALIDATE, str(module), *files],
        capture_output=True,
        text=True,
        timeout=120,
        env=dict(os.environ),
    )
    assert p.returncode == 0, p.stderr
    result = json.loads(p.stdout)
    for f, r in result.items():
        assert r["errors"] == 0 and r["warnings"] == 0, (f, r)


# ---------------------------------------------------------------------------------------------
# CesiumJS in headless Chromium (npm cesium in .cache/npm, Debian's chromium)

CESIUM = REPO / ".cache" / "npm" / "node_modules" / "cesium" / "Build" / "Cesium"
CHROMIUM = Path("/usr/bin/chromium")
# The page loads the tileset with unlit shading (the texture colours reach the screen unchanged),
# looks at it from the south-south-west and above, and posts the canvas back once every tile is in.
CESIUM_PAGE = """<!doctype html><html><head><meta charset="utf-8"><script src="cesium/Cesium.js"></script>
<link href="cesium/Widgets/widgets.css" rel="stylesheet">
<style>html,body{margin:0;background:#000} #c{width:800px;height:600px}</style></head>
<body><div id="c"></div><script>
const post = (kind, body) => fetch("/" + kind, {method: "POST", body: body});
window.onerror = (m) => post("log", "error: " + m);
(async () => {
  try {
    const viewer = new Cesium.Viewer("c", {baseLayer: false, baseLayerPicker: false, geocoder: false,
      timeline: false, animation: false, homeButton: false, sceneModePicker: false, infoBox: false,
      navigationHelpButton: false, selectionIndicator: false, fullscreenButton: false, skyBox: false,
      skyAtmosphere: false, terrainProvider: new Cesium.EllipsoidTerrainProvider(),
      contextOptions: {webgl: {preserveDrawingBuffer: true}}});
    viewer.scene.globe.show = false;
    viewer.scene.backgroundColor = Cesium.Color.BLACK;
    const tileset = await Cesium.Cesium3DTileset.fromUrl("tileset/tileset.json",
      {customShader: new Cesium.CustomShader({lightingModel: Cesium.LightingModel.UNLIT})});
    viewer.scene.primitives.add(tileset);
    await viewer.zoomTo(tileset, new Cesium.HeadingPitchRange(0.3, -0.4, 0));
    tileset.allTilesLoaded.addEventListener(async () => {
      for (let i = 0; i < 10; i++) { viewer.render(); await new Promise((r) => setTimeout(r, 100)); }
      post("shot", viewer.canvas.toDataURL("image/png"));
    });
  } catch (e) { post("log", "error: " + e + " " + (e.stack || "")); }
})();
</script></body></html>
"""


def _cesium_screenshot(site: Path, timeout: float = 150.0) -> tuple[np.ndarray | None, list[str]]:
    """Serve ``site`` on a loopback port, open its index.html in headless Chromium (software
    WebGL) and return the canvas the page posts back (float RGB), with the page's log lines."""
    import base64
    import http.server
    import io
    import threading

    from PIL import Image

    shot: list[bytes] = []
    logs: list[str] = []
    done = threading.Event()

    class Handler(http.server.SimpleHTTPRequestHandler):
        def __init__(self, *a, **k):
            super().__init__(*a, directory=str(site), **k)

        def log_message(self, *a):
            pass

        def do_POST(self):
            body = self.rfile.read(int(self.headers["Content-Length"])).decode()
            if self.path == "/shot":
                shot.append(base64.b64decode(body.split(",", 1)[1]))
            else:
                logs.append(body)
            self.send_response(204)
            self.end_headers()
            if shot or body.startswith("error"):
                done.set()

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    flags = ["--headless", "--no-sandbox", "--use-angle=swiftshader", "--enable-unsafe-swiftshader"]
    browser = subprocess.Popen(
        [str(CHROMIUM), *flags, "--remote-debugging-port=0", f"--user-data-dir={site / 'profile'}",
         f"http://127.0.0.1:{server.server_address[1]}/index.html"],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )  # fmt: skip
    try:
        done.wait(timeout)
    finally:
        browser.terminate()
        browser.wait(30)
        server.shutdown()
    if not shot:
        return None, logs
    return np.asarray(Image.open(io.BytesIO(shot[0])).convert("RGB"), np.float32) / 255, logs


@pytest.mark.skipif(
    not (CHROMIUM.is_file() and CESIUM.is_dir()),
    reason="needs Debian's chromium and npm cesium in .cache/npm (.ci/run installs both when root)",
)
def test_cesium_draws_the_tileset_upright_with_its_textures(tmp_path):
    """CesiumJS, the reference 3D Tiles runtime, draws the georeferenced tileset of two houses:
    the polygons' texture colours reach the screen, each house's roof above its front wall (the
    y-up/z-up turn is right: a wrong one lays the houses on their side), the window a hole."""
    scene, R, colours = _textured_city_scene(tmp_path)
    _assemble(scene, R, {"tileset": True, "tileset_georef": {"lon": 7.1, "lat": 50.7, "height": 60.0}})
    site = tmp_path / "site"
    site.mkdir()
    (site / "index.html").write_text(CESIUM_PAGE)
    (site / "cesium").symlink_to(CESIUM)
    (site / "tileset").symlink_to(R / "model" / "tileset")
    img, logs = _cesium_screenshot(site)
    assert img is not None, f"no screenshot; page said: {logs}"
    write_image(tmp_path / "cesium.png", img)  # for a person to look at
    assert img.shape == (600, 800, 3)

    def where(pid: str, tol: float = 6 / 255) -> np.ndarray:
        return np.argwhere(np.abs(img - colours[pid]).max(-1) <= tol)

    for building in ("house1", "house2"):
        wall, roof = where(f"{building}_WallSurface_0"), where(f"{building}_RoofSurface_0")
        assert len(wall) > 500 and len(roof) > 500, (building, len(wall), len(roof))
        assert roof[:, 0].mean() < wall[:, 0].mean()  # rows grow downwards: the roof is above
        # the window: a hole of background inside the front wall's outline on screen
        (r0, c0), (r1, c1) = wall.min(0), wall.max(0)
        inner = img[r0 + (r1 - r0) // 3 : r1 - (r1 - r0) // 5, c0 + (c1 - c0) // 3 : c1 - (c1 - c0) // 3]
        assert (inner.max(-1) < 0.05).sum() > 50, building
