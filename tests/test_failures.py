"""Broken scenes and configurations, each built from the small synthetic scene and run through the
first stage that must notice (``difftex filter``, which loads and checks the whole scene):
one line ``difftex: error: <file>: <problem>`` naming the file, exit status 2, no traceback and
no output or temporary file left; or, where continuing is right, a ``difftex: warning:`` line,
printed once, and a complete output. docs/failures.md lists the same cases and behaviours.

The workflow-level cases (console of a Snakemake run, locks, kills, full disks) are in
test_failures_workflow.py.
"""

from __future__ import annotations

import errno
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from difftex.cli import main
from difftex.scene.files import read_image, read_json, write_image

from tests import breakage as B


def run(capsys, *argv) -> tuple[int, list[str]]:
    code = main([str(a) for a in argv])
    return code, capsys.readouterr().err.strip().splitlines()


def run_filter(capsys, scene: Path, out: Path, *extra) -> tuple[int, list[str]]:
    return run(capsys, "filter", "--scene", scene, "--out", out / "photos.json", "--quiet", *extra)


def assert_error(code, err, *needles):
    """Exit 2 and one error line, the last; lines before it may only be warnings (e.g. that the
    only polygon was skipped as degenerate, before 'no usable polygons')."""
    text = "\n".join(err)
    assert code == 2, text
    assert err and err[-1].startswith("difftex: error: "), text
    assert all(e.startswith("difftex: warning: ") for e in err[:-1]), text
    assert "Traceback" not in text
    for n in needles:
        assert n in err[-1], (n, err[-1])


def assert_warning(code, err, *needles):
    text = "\n".join(err)
    assert code == 0, text
    assert "Traceback" not in text and not any(e.startswith("difftex: error") for e in err), text
    hits = [e for e in err if e.startswith("difftex: warning: ") and all(n in e for n in needles)]
    assert len(hits) == 1, (needles, text)  # once, not once per use
    assert len(err) == len(set(err)), text


# ---------------------------------------------------------------------------------------------
# Cases: (id, how to break the scene, expected kind, words the line must hold)
# The words name the file (or a file inside the scene) and the problem.


def _cam(k, edit):
    return lambda s: B.set_camera(s, k, edit)


def _set(i, v):
    def edit(t):
        t[i] = v
        return t

    return edit


def _img(k, edit):
    return lambda s: B.edit_image(s, k, edit)


def _listed_twice(s):
    t = B.first_image_tokens(s)
    B.append_image(s, ["999", *t[1:]])


def _duplicate_image_id(s):
    t = B.first_image_tokens(s)
    B.append_image(s, [t[0], *t[1:9], "other.png"])


def _duplicate_camera(s):
    p = s / "sparse/0/cameras.txt"
    first = B.data_lines(p)[0][1]
    p.write_text(p.read_text() + " ".join(first) + "\n")


def _extra_photos(n):
    def brk(s):
        src = sorted((s / "images").glob("*.png"))[0]
        for i in range(n):
            shutil.copy(src, s / "images" / f"zz_extra_{i}.png")

    return brk


def _append_text(rel, text):
    return lambda s: (s / rel).write_text((s / rel).read_text() + text)


def _write_text(rel, text):
    return lambda s: (s / rel).write_text(text)


def _unlink(rel):
    return lambda s: (s / rel).unlink()


def _image_bytes(fn):
    def brk(s):
        p = sorted((s / "images").glob("*.png"))[3]
        p.write_bytes(fn(p.read_bytes()))

    return brk


def _wrong_size(s):
    write_image(sorted((s / "images").glob("*.png"))[2], np.zeros((50, 60, 3), np.float32))


def _proxy_text(text):
    return _write_text("proxy.obj", text)


def _to_binary(s):
    import pycolmap

    pycolmap.Reconstruction(str(s / "sparse/0")).write_binary(str(s / "sparse/0"))


def _binary_only(s):
    _to_binary(s)
    for f in (s / "sparse/0").glob("*.txt"):
        f.unlink()


def _binary_text_disagree(s):
    _to_binary(s)
    B.set_camera(s, 0, lambda t: [*t[:4], str(float(t[4]) * 1.05), *t[5:]])


def _frame_zero_quaternion(s):
    # COLMAP >= 3.12 layout: poses in frames.txt (rig_from_world), images.txt's are not read
    import pycolmap

    pycolmap.Reconstruction(str(s / "sparse/0")).write_text(str(s / "sparse/0"))
    B.edit_tokens(s / "sparse/0/frames.txt", 1, lambda t: [t[0], t[1], "0", "0", "0", "0", *t[6:]])


def _truncated_cameras_bin(s):
    _binary_only(s)
    p = s / "sparse/0/cameras.bin"
    p.write_bytes(p.read_bytes()[:30])


def _blur_all(s):
    from scipy.ndimage import gaussian_filter

    for p in (s / "images").glob("*.png"):
        write_image(p, gaussian_filter(read_image(p), sigma=(3, 3, 0)))


def _blur_one(s, k=3):
    from scipy.ndimage import gaussian_filter

    p = sorted((s / "images").glob("*.png"))[k]
    write_image(p, gaussian_filter(read_image(p), sigma=(3, 3, 0)))


def _turn_all(s):
    for k in range(B.n_images(s)):
        B.turn_camera_around(s, k)


def _inside_wall(s):
    # a wall inside the building, facing the front: every photo sees another polygon first
    B.add_polygon(s, "hidden", [[-3, 0, 1], [3, 0, 1], [3, 0, 5], [-3, 0, 5]])


def _sliver(s):
    # almost collinear (the third point is off the line by 3e-7): passes a zero-area test, not
    # the float32 one; unchecked it reached assembly and failed there after the whole run
    B.add_polygon(s, "sliver", [[0, -4.5, 0], [1, -4.5, 0.333333], [3, -4.5, 1]])


def _two_vertex_face(s):
    p = s / "proxy.obj"
    p.write_text(p.read_text() + "g stub\nf 1 2\n")


def _same_names(s):
    p = s / "proxy.obj"
    p.write_text(p.read_text().replace("g wall01", "g wall00"))


def _proxy_vertex(fn):
    def brk(s):
        p = s / "proxy.obj"
        lines = p.read_text().splitlines()
        i = next(k for k, ln in enumerate(lines) if ln.startswith("v "))
        lines[i] = fn(lines[i])
        p.write_text("\n".join(lines) + "\n")

    return brk


CASES = [
    # cameras.txt
    (
        "camera-unknown-model",
        _cam(0, _set(1, "FOO")),
        "error",
        ["cameras.txt:", "camera 1", "unknown camera model 'FOO'"],
    ),
    ("camera-nan-param", _cam(0, _set(4, "nan")), "error", ["cameras.txt:", "camera 1", "not finite"]),
    ("camera-inf-param", _cam(0, _set(6, "inf")), "error", ["cameras.txt:", "camera 1", "not finite"]),
    ("camera-focal-zero", _cam(0, _set(4, "0")), "error", ["cameras.txt:", "camera 1", "focal length 0"]),
    ("camera-focal-negative", _cam(0, _set(5, "-100")), "error", ["cameras.txt:", "camera 1", "focal length -100"]),
    ("camera-focal-implausible", _cam(0, _set(4, "1e7")), "error", ["cameras.txt:", "camera 1", "implausible"]),
    ("camera-few-params", _cam(0, lambda t: t[:-1]), "error", ["cameras.txt:", "camera 1", "takes 4 parameters"]),
    ("camera-text-param", _cam(0, _set(5, "abc")), "error", ["cameras.txt:", "camera 1", "not numbers"]),
    ("camera-zero-width", _cam(0, _set(2, "0")), "error", ["cameras.txt:", "camera 1", "not positive"]),
    ("camera-garbage-line", _append_text("sparse/0/cameras.txt", "garbage\n"), "error", ["cameras.txt:", "expected"]),
    ("camera-defined-twice", _duplicate_camera, "error", ["cameras.txt:", "camera 1 is defined twice"]),
    ("cameras-empty", _write_text("sparse/0/cameras.txt", "# nothing\n"), "error", ["cameras.txt", "no cameras"]),
    (
        "camera-huge-distortion",
        _cam(0, lambda t: [t[0], "SIMPLE_RADIAL", t[2], t[3], t[4], t[6], t[7], "50"]),
        "error",
        ["cameras.txt:", "camera 1", "distortion"],
    ),
    # images.txt
    ("image-nan-pose", _img(0, _set(5, "nan")), "error", ["images.txt:", "not finite"]),
    (
        "image-zero-quaternion",
        _img(1, lambda t: [t[0], "0", "0", "0", "0", *t[5:]]),
        "error",
        ["images.txt:", "quaternion is zero"],
    ),
    ("image-listed-twice", _listed_twice, "error", ["images.txt:", "listed twice", "image ids"]),
    ("image-id-twice", _duplicate_image_id, "error", ["images.txt:", "is used twice"]),
    ("image-unknown-camera", _img(0, _set(8, "7")), "error", ["images.txt:", "uses camera 7"]),
    ("image-text-pose", _img(2, _set(3, "x")), "error", ["images.txt:", "unreadable pose"]),
    ("image-short-line", _img(0, lambda t: t[:6]), "error", ["images.txt:", "expected"]),
    ("images-empty", _write_text("sparse/0/images.txt", "# nothing\n"), "error", ["images.txt", "no images"]),
    ("image-points-not-triples", lambda s: _set_points(s, "1.0 2.0"), "error", ["images.txt:", "triples"]),
    ("frame-zero-quaternion", _frame_zero_quaternion, "error", ["frames.txt", "quaternion is zero"]),
    ("points3d-garbage", _append_text("sparse/0/points3D.txt", "1 2 three\n"), "error", ["points3D.txt:"]),
    # photos
    ("photo-missing", lambda s: sorted((s / "images").glob("*.png"))[1].unlink(), "error", ["img_0001.png", "missing"]),
    ("photo-wrong-size", _wrong_size, "error", ["img_0002.png", "60x50", "camera"]),
    ("photo-corrupt-header", _image_bytes(lambda b: b"not a png at all"), "error", ["img_0003.png"]),
    ("photo-truncated", _image_bytes(lambda b: b[: len(b) // 2]), "error", ["img_0003.png"]),
    ("photo-empty-file", _image_bytes(lambda b: b""), "error", ["img_0003.png"]),
    (
        "photo-not-in-model",
        _extra_photos(1),
        "warning",
        ["images", "1 photo is not in the COLMAP model", "zz_extra_0.png"],
    ),
    ("photos-not-in-model", _extra_photos(3), "warning", ["images", "3 photos are not in the COLMAP model"]),
    # binary models
    ("binary-model", _binary_only, "ok", []),
    ("binary-and-text-agree", _to_binary, "warning", ["sparse/0", "both a binary and a text", "using the .bin"]),
    ("binary-and-text-disagree", _binary_text_disagree, "error", ["sparse/0", "disagree", "different cameras"]),
    ("cameras-bin-truncated", _truncated_cameras_bin, "error", ["cameras.bin", "truncated"]),
    # no model
    ("no-sparse-folder", lambda s: shutil.rmtree(s / "sparse"), "error", ["no COLMAP model"]),
    ("no-images-txt", _unlink("sparse/0/images.txt"), "error", ["sparse/0", "no COLMAP model"]),
    ("no-images-folder", lambda s: shutil.rmtree(s / "images"), "error", ["images", "not found"]),
    # proxy
    ("proxy-two-vertex-face", _two_vertex_face, "warning", ["proxy.obj:", "'stub'", "2 vertices"]),
    ("proxy-collinear-sliver", _sliver, "warning", ["proxy.obj", "'sliver'", "degenerate"]),
    ("proxy-same-names", _same_names, "warning", ["proxy.obj", "'wall00' -> wall00_1, wall00_2"]),
    ("proxy-not-planar", _proxy_vertex(lambda ln: "v -6 -3 0"), "error", ["proxy.obj", "'wall00'", "not planar"]),
    ("proxy-empty", _proxy_text("# nothing\n"), "error", ["proxy.obj", "no usable polygons"]),
    (
        "proxy-all-degenerate",
        _proxy_text("v 0 0 0\nv 1 0 0\nv 2 0 0\ng line\nf 1 2 3\n"),
        "error",
        ["proxy.obj", "no usable polygons"],
    ),
    ("proxy-bad-index", _append_text("proxy.obj", "g bad\nf 1 2 99\n"), "error", ["proxy.obj:", "vertex 99"]),
    ("proxy-malformed-vertex", _proxy_vertex(lambda ln: "v 1 two 3"), "error", ["proxy.obj:", "malformed OBJ line"]),
    ("proxy-nan-vertex", _proxy_vertex(lambda ln: "v nan 0 0"), "error", ["proxy.obj", "non-finite"]),
    ("proxy-missing", _unlink("proxy.obj"), "error", ["no proxy model"]),
    (
        "proxy-corrupt-ply",
        lambda s: ((s / "proxy.obj").unlink(), (s / "proxy.ply").write_bytes(b"ply\ngarbage")),
        "error",
        ["proxy.ply"],
    ),
    ("proxy-100x", lambda s: B.scale_proxy(s, 100), "error", ["proxy.obj", "does not fit the COLMAP model", "units"]),
    ("proxy-km-wide", lambda s: B.scale_proxy(s, 1000 / 18), "error", ["proxy.obj", "does not fit the COLMAP model"]),
    ("proxy-1mm", lambda s: B.scale_proxy(s, 0.001 / 18), "error", ["proxy.obj", "no usable polygons", "wrong units"]),
    (
        "proxy-elsewhere",
        lambda s: B.transform_proxy(s, lambda V: V + [500.0, 0, 0]),
        "error",
        ["proxy.obj", "does not fit"],
    ),
    ("proxy-10x-small", lambda s: B.scale_proxy(s, 0.1), "warning", ["proxy.obj", "far from the proxy"]),
    # what the photos see
    (
        "polygon-behind-everything",
        _inside_wall,
        "warning",
        ["proxy.obj", "no photo sees 1 of 7 polygons, untextured (grey): hidden (hidden behind other polygons in the"],
    ),
    (
        "camera-sees-nothing",
        lambda s: B.turn_camera_around(s, 4),
        "warning",
        ["images", "1 photo sees no proxy polygon"],
    ),
    ("every-photo-filtered-out", _turn_all, "error", ["images", "every photo was filtered out", "frame and units"]),
    ("all-photos-blurry", _blur_all, "ok", []),
    (
        "one-photo-blurry",
        _blur_one,
        "warning",
        ["images", "1 photo dropped as blurry (sharpness below filter.blur_ratio = 0.3 x the median): img_0003.png ("],
    ),
]


def _set_points(scene: Path, text: str) -> None:
    path = scene / "sparse/0/images.txt"
    lines = path.read_text().splitlines()
    i = B.image_lines(path)[0]
    lines[i + 1] = text
    path.write_text("\n".join(lines) + "\n")


@pytest.mark.parametrize("case, brk, kind, needles", CASES, ids=[c[0] for c in CASES])
def test_broken_scene(case, brk, kind, needles, small_synth_scene, tmp_path, capsys):
    scene = B.copy_scene(small_synth_scene, tmp_path / "scene")
    brk(scene)
    out = tmp_path / "out"
    code, err = run_filter(capsys, scene, out)
    if kind == "error":
        assert_error(code, err, *needles)
        assert not (out / "photos.json").exists() and not (out / "photos.csv").exists()
    else:
        if kind == "warning":
            assert_warning(code, err, *needles)
        else:
            assert code == 0 and not any(e.startswith("difftex: ") for e in err), err
        table = read_json(out / "photos.json")
        assert table["photos"] and table["polygons"]
    assert B.temp_files(tmp_path) == []


def test_cases_cover_every_kind():
    kinds = {c[2] for c in CASES}
    assert kinds == {"error", "warning", "ok"} and len(CASES) >= 55


# ---------------------------------------------------------------------------------------------
# What the warnings lead to


def test_unique_ids_reach_the_filter_table(small_synth_scene, tmp_path, capsys):
    scene = B.copy_scene(small_synth_scene, tmp_path / "scene")
    _same_names(scene)
    run_filter(capsys, scene, tmp_path)
    polys = read_json(tmp_path / "photos.json")["polygons"]
    assert {"wall00_1", "wall00_2"} <= set(polys) and "poly0001" not in polys
    # both walls are seen (the old fallback id made the second one 'seen by no photo')
    assert polys["wall00_1"]["kept"] and polys["wall00_2"]["kept"]


def test_all_blurry_photos_are_all_kept(small_synth_scene, tmp_path, capsys):
    """Sharpness is judged against the set's median, so a set blurred as a whole is kept whole
    (docs/failures.md): nothing to warn about, and nothing is lost."""
    scene = B.copy_scene(small_synth_scene, tmp_path / "scene")
    _blur_all(scene)
    assert run_filter(capsys, scene, tmp_path)[0] == 0
    photos = read_json(tmp_path / "photos.json")["photos"]
    assert len(photos) == B.n_images(scene) and sum(not p["kept"] and "blurry" in p["reason"] for p in photos) == 0


def test_the_blind_camera_is_dropped_with_its_reason(small_synth_scene, tmp_path, capsys):
    scene = B.copy_scene(small_synth_scene, tmp_path / "scene")
    B.turn_camera_around(scene, 4)
    run_filter(capsys, scene, tmp_path)
    rec = {r["name"]: r for r in read_json(tmp_path / "photos.json")["photos"]}
    assert rec["img_0004.png"]["kept"] is False and rec["img_0004.png"]["reason"] == "sees no proxy polygon"


def test_scene_path_with_spaces_and_accents(small_synth_scene, tmp_path, capsys):
    scene = B.copy_scene(small_synth_scene, tmp_path / "Kölner Dom (west)")
    code, err = run_filter(capsys, scene, tmp_path / "out dir")
    assert code == 0 and not err, err
    assert read_json(tmp_path / "out dir" / "photos.json")["photos"]


def test_every_polygon_beyond_the_angle_filter_keeps_its_oblique_photos(small_synth_scene, tmp_path, capsys):
    """The angle filter never takes a polygon's last photos: with every view beyond the limit,
    every polygon is textured from its oblique photos, and one warning names them."""
    cfg = tmp_path / "c.yaml"
    cfg.write_text("filter:\n  max_angle_deg: 0.01\n")
    code, err = run_filter(capsys, small_synth_scene, tmp_path / "out", "--config", cfg)
    assert_warning(code, err, "proxy.obj", "textured from oblique photos only", "filter.max_angle_deg = 0.01")
    polys = read_json(tmp_path / "out" / "photos.json")["polygons"]
    assert all(d["kept"] and d["textured_from_oblique"] for d in polys.values())


@pytest.mark.parametrize(
    "text, needles",
    [
        ("filter: {blur_ratio: abc}\n", ["blur_ratio"]),
        ("filter: [1, 2\n", ["c.yaml", "not valid YAML"]),
        ("filter:\n  blurr_ratio: 0.2\n", ["blurr_ratio", "unknown key"]),
    ],
    ids=["bad-value", "bad-yaml", "unknown-key"],
)
def test_bad_stage_config(text, needles, small_synth_scene, tmp_path, capsys):
    cfg = tmp_path / "c.yaml"
    cfg.write_text(text)
    code, err = run_filter(capsys, small_synth_scene, tmp_path / "out", "--config", cfg)
    assert_error(code, err, *needles)


def test_missing_scene_folder(tmp_path, capsys):
    assert_error(*run_filter(capsys, tmp_path / "nowhere", tmp_path), "nowhere", "scene folder not found")


# ---------------------------------------------------------------------------------------------
# Writing: read-only folders, full disks, modes


def test_read_only_output_folder(small_synth_scene, tmp_path, capsys):
    out = tmp_path / "ro"
    undo = B.make_unwritable(out)
    if undo is None:
        pytest.skip("cannot make a folder read-only here (root without chattr)")
    try:
        code, err = run_filter(capsys, small_synth_scene, out / "sub")
    finally:
        undo()
    assert_error(code, err, "sub", "not writable")
    assert not (out / "sub").exists()


def test_full_disk_during_a_write_leaves_nothing(tmp_path, monkeypatch):
    """A writer that fails with ENOSPC half-way: one line naming the final file, the temporary
    file removed, the previous version of the file untouched."""
    from difftex.errors import DifftexError
    from difftex.scene.files import atomic_path, write_json

    target = tmp_path / "r" / "stats.json"
    write_json(target, {"old": 1})
    with pytest.raises(DifftexError) as info:
        with atomic_path(target) as tmp:
            tmp.write_text('{"new": ')
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(tmp))
    msg = str(info.value)
    assert msg.startswith(str(target)) and "No space left on device" in msg and "\n" not in msg
    assert read_json(target) == {"old": 1}
    assert B.temp_files(tmp_path) == []


def test_cli_turns_os_errors_into_one_line(small_synth_scene, tmp_path, capsys, monkeypatch):
    """An OS error outside the atomic writers (here: reading a photo) is one line naming the file."""
    import difftex.geometry.photo_filter

    def fail(path, *a, **k):
        raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), str(path))

    monkeypatch.setattr(difftex.geometry.photo_filter, "decode_photo", fail)
    code, err = run_filter(capsys, small_synth_scene, tmp_path)
    assert_error(code, err, "img_0000.png", "Permission denied")


@pytest.mark.parametrize("umask, mode", [(0o022, 0o644), (0o002, 0o664), (0o077, 0o600)])
def test_outputs_follow_the_umask(tmp_path, umask, mode):
    from difftex.scene.files import write_image as wi
    from difftex.scene.files import write_json, write_npz

    old = os.umask(umask)
    try:
        write_json(tmp_path / "a.json", {})
        write_npz(tmp_path / "b.npz", x=np.zeros(2))
        wi(tmp_path / "c.png", np.zeros((2, 2, 3), np.float32))
    finally:
        os.umask(old)
    for f in ("a.json", "b.npz", "c.png"):
        assert (tmp_path / f).stat().st_mode & 0o777 == mode, f


def test_a_float_photo_with_nan_is_an_error_naming_it(tmp_path):
    """Only a float format can hold NaN (an 8-bit one is read without the check, which cost a
    quarter of a PNG's read time): the EXR with one NaN pixel is refused, naming the file; the
    same image as PNG reads back finite."""
    from difftex.errors import DifftexError

    img = np.full((8, 8, 3), 0.5, np.float32)
    write_image(tmp_path / "ok.png", img)
    assert np.isfinite(read_image(tmp_path / "ok.png")).all()
    img[3, 4, 1] = np.nan
    write_image(tmp_path / "bad.exr", img)
    with pytest.raises(DifftexError, match=r"bad\.exr: image holds NaN"):
        read_image(tmp_path / "bad.exr")


def test_every_photo_under_min_pixels_names_the_setting(small_synth_scene, tmp_path, capsys):
    """Photos that see the proxy, but no polygon of it with filter.min_pixels pixels: the error
    names the setting and the numbers, not the proxy's frame and units."""
    cfg = tmp_path / "c.yaml"
    cfg.write_text("filter:\n  min_pixels: 1000000\n")
    code, err = run_filter(capsys, small_synth_scene, tmp_path / "out", "--config", cfg)
    n = B.n_images(small_synth_scene)
    assert_error(
        code,
        err,
        "images: every photo was filtered out (sees no polygon with filter.min_pixels = 1000000 pixels: "
        f"{n} of {n}); nothing to texture. The photos see at most ",
        " pixels of a polygon at the filter's analysis size (filter.analysis_long_side = 640): "
        "set filter.min_pixels to ",
    )
    assert "frame and units" not in err[-1]
    most = int(err[-1].split("see at most ")[1].split()[0])
    assert 0 < most < 1000000 and err[-1].endswith(f"set filter.min_pixels to {most} or less.")
    # ... and that many pixels are enough
    cfg.write_text(f"filter:\n  min_pixels: {most}\n")
    code, err = run_filter(capsys, small_synth_scene, tmp_path / "out", "--config", cfg)
    assert code == 0 and not any(e.startswith("difftex: error") for e in err), err


def test_a_photo_under_min_pixels_is_named_with_the_setting(small_synth_scene, tmp_path, capsys):
    assert run_filter(capsys, small_synth_scene, tmp_path / "a")[0] == 0
    largest = {r["name"]: max(v["pixels"] for v in r["polygons"].values())
               for r in read_json(tmp_path / "a" / "photos.json")["photos"]}
    name, least = min(largest.items(), key=lambda kv: kv[1])
    assert sorted(largest.values())[1] > least  # one photo is below the threshold, the others above
    cfg = tmp_path / "c.yaml"
    cfg.write_text(f"filter:\n  min_pixels: {least + 1}\n")
    code, err = run_filter(capsys, small_synth_scene, tmp_path / "b", "--config", cfg)
    assert_warning(code, err, f"images: 1 photo sees no polygon with filter.min_pixels = {least + 1} pixels "
                   f"(at most {least}), dropped ({name})")
    rec = {r["name"]: r for r in read_json(tmp_path / "b" / "photos.json")["photos"]}
    assert rec[name]["kept"] is False and "filter.min_pixels" in rec[name]["reason"]


def test_a_blurry_photo_is_named_on_the_console_and_in_the_end_of_run_summary(small_synth_scene, tmp_path, capsys):
    """photos.csv is not the only place that says it: the filter's warning line (which the
    workflow prints again at the end of the run) and the summary after it."""
    from difftex.scene.files import write_json
    from difftex.workflow.glue import format_summary, run_summary

    scene = B.copy_scene(small_synth_scene, tmp_path / "scene")
    _blur_one(scene)
    R = tmp_path / "R"
    code, err = run_filter(capsys, scene, R)
    assert_warning(code, err, "1 photo dropped as blurry", "img_0003.png (0.")
    rec = {r["name"]: r for r in read_json(R / "photos.json")["photos"]}
    write_json(R / "model" / "summary.json", {"polygons": [], "untextured": []})
    lines = format_summary(run_summary(R)).splitlines()
    said = [ln for ln in lines if "blurry" in ln]
    assert said == [
        "1 photo dropped as blurry (sharpness below filter.blur_ratio = 0.3 x the median; photos.csv): "
        f"img_0003.png ({rec['img_0003.png']['sharpness_rel']:.2g})"
    ], lines


@pytest.mark.parametrize("how", ["file-size-limit", "full-disk"])
def test_an_image_write_that_stops_midway_leaves_the_previous_file(how, tmp_path):
    """model/model_view.png (or any PNG) whose write stops half-way: OpenImageIO's PNG writer
    still returns success and would leave a truncated file; write_image raises instead, naming
    the file, and the previous version stays. The writer is stopped by a file size limit
    (RLIMIT_FSIZE, any user) or by a full 64 kB tmpfs (root only)."""
    import resource
    import signal
    import subprocess

    from difftex.errors import DifftexError

    root = tmp_path / "disk"
    root.mkdir()
    mount = ["mount", "-t", "tmpfs", "-o", "size=64k", "tmpfs", str(root)]
    if how == "full-disk" and subprocess.run(mount, capture_output=True).returncode:
        pytest.skip("cannot mount a small tmpfs here (needs root)")
    rng = np.random.default_rng(0)
    target = root / "model" / "model_view.png"
    try:
        write_image(target, rng.random((8, 8, 3)))
        before = target.read_bytes()
        soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
        prev = signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write past the limit fails (EFBIG), no signal
        if how == "file-size-limit":
            resource.setrlimit(resource.RLIMIT_FSIZE, (20_000, hard))
        try:
            with pytest.raises(DifftexError) as info:
                write_image(target, rng.random((400, 600, 3)))  # about 700 kB of PNG: noise does not compress
        finally:
            resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
            signal.signal(signal.SIGXFSZ, prev)
        msg = str(info.value)
        assert "\n" not in msg
        if how == "full-disk":
            assert msg == f"{target}: No space left on device (free some space and run the same command again)"
        else:
            assert msg.startswith(f"{target}: cannot write image (Write error") and "could only write" in msg, msg
        assert target.read_bytes() == before
        assert B.temp_files(root) == []
    finally:
        if how == "full-disk":
            subprocess.run(["umount", str(root)], check=False)
