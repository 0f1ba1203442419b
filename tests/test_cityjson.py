"""CityJSON proxies (difftex.scene.cityjson through load_proxy): LOD choice, transform, holes,
semantic types kept, ground surfaces skipped, stable ids, and one clear line for bad input."""

from __future__ import annotations

import json
import logging

import numpy as np
import pytest

from difftex.cli import main
from difftex.errors import DifftexError
from difftex.scene.loading import find_proxy
from difftex.scene.proxy import load_proxy, triangulate

from tests.scenes import make_scene

SCALE, TRANSLATE = 0.001, [100.0, 200.0, 10.0]

# A 10 x 6 house, walls 3 high, a gable roof with its ridge along x at height 5, and a 2 x 1
# window hole in the front wall (y = 0). Vertices 0-3 ground, 4-7 eaves, 8-9 ridge, 10-13 window.
HOUSE = [
    [0, 0, 0], [10, 0, 0], [10, 6, 0], [0, 6, 0],
    [0, 0, 3], [10, 0, 3], [10, 6, 3], [0, 6, 3],
    [0, 3, 5], [10, 3, 5],
    [4, 0, 1], [6, 0, 1], [6, 0, 2], [4, 0, 2],
]  # fmt: skip
# the outer shell: outer rings counter-clockwise seen from outside, the window hole clockwise
SHELL = [
    [[0, 3, 2, 1]],  # ground
    [[0, 1, 5, 4], [10, 13, 12, 11]],  # front wall with the window
    [[1, 2, 6, 9, 5]],  # right gable wall
    [[2, 3, 7, 6]],  # back wall
    [[3, 0, 4, 8, 7]],  # left gable wall
    [[4, 5, 9, 8]],  # front roof
    [[6, 7, 8, 9]],  # back roof
]
SEMANTICS = {
    "surfaces": [{"type": "GroundSurface"}, {"type": "WallSurface"}, {"type": "RoofSurface"}],
    "values": [[0, 1, 1, 1, 1, 2, 2]],
}


def house(oid="house1", offset=(0.0, 0.0, 0.0), base=0, lods=True) -> tuple[dict, list]:
    """(CityObject, its vertices in metres) of the gable house, its indices starting at ``base``."""
    shell = [[[i + base for i in ring] for ring in surface] for surface in SHELL]
    geometry = [{"type": "Solid", "lod": "2.2", "boundaries": [shell], "semantics": SEMANTICS}]
    if lods:  # a coarser and a finer geometry: the 2.2 one must win
        box = [[[base + i for i in ring]] for ring in ([0, 3, 2, 1], [0, 1, 5, 4], [4, 5, 6, 7])]
        geometry = [
            {"type": "MultiSurface", "lod": "1.2", "boundaries": box},
            *geometry,
            {"type": "MultiSurface", "lod": "3", "boundaries": box},
        ]
    verts = (np.asarray(HOUSE, float) + offset).tolist()
    return {"type": "Building", "geometry": geometry}, verts


def city(objects: dict[str, tuple[dict, list]], version="2.0") -> dict:
    """A CityJSON document of objects {id: (object, vertices)}, vertices stored as integers."""
    verts = [v for _, vs in objects.values() for v in vs]
    ints = np.round((np.asarray(verts) - TRANSLATE) / SCALE).astype(int).tolist()
    return {
        "type": "CityJSON",
        "version": version,
        "transform": {"scale": [SCALE] * 3, "translate": TRANSLATE},
        "CityObjects": {oid: obj for oid, (obj, _) in objects.items()},
        "vertices": ints,
    }


def write_city(path, doc) -> str:
    path.write_text(json.dumps(doc))
    return str(path)


def translated(offset=(0.0, 0.0, 0.0)):
    return np.asarray(HOUSE, float) + offset


def test_house_polygons_semantics_holes_and_transform(tmp_path, caplog):
    path = write_city(tmp_path / "proxy.city.json", city({"house1": house(offset=TRANSLATE)}))
    with caplog.at_level(logging.WARNING):
        proxy = load_proxy(path)
    assert proxy.ids == [
        "house1_WallSurface_0",
        "house1_WallSurface_1",
        "house1_WallSurface_2",
        "house1_WallSurface_3",
        "house1_RoofSurface_0",
        "house1_RoofSurface_1",
    ]
    warned = [r.getMessage() for r in caplog.records if "GroundSurface" in r.getMessage()]
    assert len(warned) == 1 and "house1_GroundSurface_0" in warned[0] and "skipped" in warned[0]
    by = {p.id: p for p in proxy.polygons}
    assert {p.semantic for p in proxy.polygons} == {"WallSurface", "RoofSurface"}
    assert {p.building for p in proxy.polygons} == {"house1"}
    front = by["house1_WallSurface_0"]
    assert len(front.holes) == 1 and front.area == pytest.approx(30.0 - 2.0, rel=1e-9)
    assert np.allclose(front.outer[0], np.asarray(TRANSLATE))  # scale and translate applied
    assert np.allclose(front.normal, [0, -1, 0])
    assert by["house1_WallSurface_1"].area == pytest.approx(6 * 3 + 6 * 2 / 2)  # the gable
    assert by["house1_RoofSurface_0"].area == pytest.approx(10 * np.hypot(3, 2))
    centre = np.asarray(TRANSLATE) + [5, 3, 2]
    for p in proxy.polygons:  # every surface faces outwards
        assert (p.centroid - centre) @ p.normal > 0, p.id
    v, t = triangulate(front)  # the project's hole handling
    assert 0.5 * np.linalg.norm(np.cross(v[t[:, 1]] - v[t[:, 0]], v[t[:, 2]] - v[t[:, 0]]), axis=1).sum() == (
        pytest.approx(28.0)
    )
    assert load_proxy(path).ids == proxy.ids  # stable across reruns


def test_parts_belong_to_their_building_and_versions_and_hole_order(tmp_path):
    """A BuildingPart's polygons carry its parent's id; CityJSON 1.0 without a transform reads
    too; a hole given counter-clockwise is turned clockwise."""
    obj, verts = house(lods=False)
    # as in the 3D BAG: the building has an LOD0 footprint and an LOD1 block, its part the LOD2.2
    # solid; the part's surfaces are the proxy, the building's geometries would duplicate them
    block = [[[0, 1, 5, 4]]]
    building = {
        "type": "Building",
        "children": ["b-part"],
        "geometry": [
            {"type": "MultiSurface", "lod": "0", "boundaries": [[[0, 3, 2, 1]]]},
            {"type": "MultiSurface", "lod": "1.2", "boundaries": block},
        ],
    }
    doc = city({"b": (building, []), "b-part": (obj, verts)}, version="1.1")
    doc["CityObjects"]["b-part"] = {**obj, "type": "BuildingPart", "parents": ["b"]}
    proxy = load_proxy(write_city(tmp_path / "a.json", doc))
    assert {p.building for p in proxy.polygons} == {"b"} and len(proxy) == 6
    assert proxy.ids[0] == "b-part_WallSurface_0"
    # an LOD0 footprint alone is nothing to texture
    doc["CityObjects"] = {"b": building}
    doc["CityObjects"]["b"]["geometry"] = building["geometry"][:1]
    with pytest.raises(DifftexError, match="no building surface of LOD 1 to 2.2"):
        load_proxy(write_city(tmp_path / "c.json", doc))

    flipped = [list(r) for r in SHELL[1]]
    flipped[1] = flipped[1][::-1]
    geom = {"type": "MultiSurface", "lod": 2, "boundaries": [flipped]}
    old = {"type": "CityJSON", "version": "1.0", "CityObjects": {"w": {"type": "Building", "geometry": [geom]}}}
    old["vertices"] = HOUSE
    wall = load_proxy(write_city(tmp_path / "b.json", old)).polygons[0]
    assert wall.id == "w_Surface_0" and wall.semantic == "Surface"
    assert wall.area == pytest.approx(28.0) and (np.cross(*np.diff(wall.holes[0][:3], axis=0)) @ wall.normal) < 0


def test_scene_folder_finds_the_cityjson_proxy_and_inspect_reports_semantics(tmp_path, capsys):
    scene = make_scene(tmp_path / "scene")
    (scene / "proxy.obj").unlink()
    write_city(scene / "proxy.city.json", city({"house1": house(offset=(-5.0, 0.0, -1.0))}))
    assert find_proxy(scene).name == "proxy.city.json"
    assert main(["inspect", str(scene)]) == 0
    out = capsys.readouterr().out
    assert "6 polygons" in out and "house1_WallSurface_0" in out and "WallSurface" in out


def _bad(doc_or_text):
    def write(path):
        path.write_text(doc_or_text if isinstance(doc_or_text, str) else json.dumps(doc_or_text))

    return write


def _edited(edit):
    def write(path):
        doc = city({"h": house()})
        edit(doc)
        path.write_text(json.dumps(doc))

    return write


def _bend(doc):
    doc["vertices"][9][0] += 700  # the ridge's end out of the right gable's plane: 0.7 m


def _wrong_nesting(doc):
    doc["CityObjects"]["h"]["geometry"][1]["boundaries"] = SHELL  # a Solid without its shell level


@pytest.mark.parametrize(
    "write, needles",
    [
        (_bad("{ not json"), ["not valid JSON", "line 1"]),
        (_bad(b"\xff\xfe".decode("latin-1")), ["not valid JSON"]),
        (_bad({"type": "FeatureCollection", "features": []}), ["not a CityJSON file", "FeatureCollection"]),
        (_bad([1, 2]), ["not a CityJSON file"]),
        (_edited(lambda d: d.pop("vertices")), ["no \"vertices\""]),
        (_edited(lambda d: d.update(vertices=[[1, 2]])), ["\"vertices\" must be a list of [x, y, z]"]),
        (_edited(lambda d: d.update(transform={"scale": [1, 1]})), ["\"transform\""]),
        (_edited(lambda d: d.update(CityObjects={})), ["no \"CityObjects\""]),
        (_edited(lambda d: d["vertices"].pop()), ["CityObject 'h'", "refers to vertex 13", "13 vertices"]),
        (_edited(_bend), ["'h_WallSurface_1'", "not planar"]),
        (_edited(_wrong_nesting), ["CityObject 'h'", "not nested as a Solid"]),
        (
            _edited(lambda d: d["CityObjects"]["h"]["geometry"][1]["semantics"].update(values=[[0, 1]])),
            ["semantics.values", "do not match"],
        ),
        (
            _edited(lambda d: d["CityObjects"]["h"].update(geometry=[d["CityObjects"]["h"]["geometry"][2]])),
            ["no building surface of LOD 1 to 2.2"],
        ),
    ],
)
def test_bad_cityjson_is_one_line_naming_the_file(tmp_path, capsys, write, needles):
    path = tmp_path / "proxy.city.json"
    write(path)
    with pytest.raises(DifftexError) as exc:
        load_proxy(path)
    msg = str(exc.value)
    assert msg.startswith(str(path)) and "\n" not in msg, msg
    for n in needles:
        assert n in msg, (n, msg)
    # the same through a command: one error line (after any warnings), no traceback
    scene = make_scene(tmp_path / "scene")
    (scene / "proxy.obj").unlink()
    write(scene / "proxy.city.json")
    assert main(["inspect", str(scene)]) == 2
    err = capsys.readouterr().err.strip()
    errors = [line for line in err.splitlines() if line.startswith("difftex: error: ")]
    assert len(errors) == 1 and "proxy.city.json" in errors[0] and "Traceback" not in err, err
    assert all(line.startswith(("difftex: error: ", "difftex: warning: ")) for line in err.splitlines()), err
