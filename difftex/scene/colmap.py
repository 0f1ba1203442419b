"""Reading a COLMAP model with checks that name the file, the line and the camera or image.

pycolmap reads both formats, but it accepts what difftex cannot use (a zero quaternion becomes
the identity, an image listed twice is loaded twice) and rejects the rest with its C++ check text
(``Check failed: camera.VerifyParams()``) that names neither the file nor the camera. So the text
files are checked line by line before pycolmap reads them, and the loaded model (either format)
is checked once more; a binary file that pycolmap cannot read is parsed here only to say where it
breaks. pycolmap stays the reader: its parsers follow COLMAP's format changes.

When a folder holds both a binary and a text model, COLMAP itself reads the binary one; so does
difftex, after checking that the two agree (a stale text export would otherwise go unnoticed).
"""

from __future__ import annotations

import logging
import math
import struct
from pathlib import Path

import numpy as np

from difftex.errors import DifftexError

log = logging.getLogger(__name__)

# COLMAP's own plausibility limits (Camera::HasBogusParams, as its mapper uses them), except the
# distortion bound, which is looser: strong fisheye models have legitimately large parameters.
MIN_FOCAL_RATIO, MAX_FOCAL_RATIO, MAX_EXTRA_PARAM = 0.1, 10.0, 10.0
# Agreement of a binary and a text model: the text format stores 17 significant digits.
AGREE_RTOL = 1e-6


def model_files(sparse_dir: Path) -> dict[str, dict[str, Path]]:
    """{"bin": {...}, "txt": {...}}: the complete models (cameras + images) in ``sparse_dir``,
    each as {"cameras": path, "images": path} plus "points3D", "frames" and "rigs" where present
    (COLMAP >= 3.12 keeps the poses in frames.*; older models in images.*)."""
    out = {}
    for ext in ("bin", "txt"):
        files = {n: sparse_dir / f"{n}.{ext}" for n in ("cameras", "images", "points3D", "frames", "rigs")}
        if files["cameras"].is_file() and files["images"].is_file():
            out[ext] = {n: p for n, p in files.items() if p.is_file()}
    return out


def _camera_template(model: str):
    """A pycolmap camera of ``model`` (for its parameter count and roles); None if unknown."""
    import pycolmap

    if model not in pycolmap.CameraModelId.__members__ or model == "INVALID":
        return None
    return pycolmap.Camera.create_from_model_name(0, model, 1.0, 1, 1)


def camera_problem(model: str, width: int, height: int, params: np.ndarray) -> str | None:
    """What is wrong with one camera, or None.

    Args:
        model: COLMAP model name (e.g. "PINHOLE").
        width, height: image size in pixels.
        params: the model's parameters in COLMAP's order.

    Returns:
        A short phrase ("focal length 0 (must be > 0)") or None when the camera is usable.
    """
    import pycolmap

    cam = _camera_template(model)
    if cam is None:
        known = [m for m in pycolmap.CameraModelId.__members__ if m != "INVALID"]
        return f"unknown camera model '{model}' (known: {', '.join(known)})"
    params = np.asarray(params, dtype=np.float64)
    if len(params) != len(cam.params):
        names = cam.params_info if hasattr(cam, "params_info") else ""
        return f"{model} takes {len(cam.params)} parameters{f' ({names})' if names else ''}, got {len(params)}"
    if width <= 0 or height <= 0:
        return f"image size {width}x{height} is not positive"
    if not np.isfinite(params).all():
        return f"parameters are not finite {params.tolist()}"
    side = max(width, height)
    for i in cam.focal_length_idxs():
        f = float(params[i])
        if f <= 0:
            return f"focal length {f:g} (must be > 0)"
        if not MIN_FOCAL_RATIO <= f / side <= MAX_FOCAL_RATIO:
            return (
                f"focal length {f:g} px is implausible for a {width}x{height} image "
                f"(focal / long side {f / side:.3g}, expected {MIN_FOCAL_RATIO:g} to {MAX_FOCAL_RATIO:g})"
            )
    for i in cam.extra_params_idxs():
        if abs(float(params[i])) > MAX_EXTRA_PARAM:
            return f"distortion parameter {i} = {float(params[i]):g} is implausible (|value| > {MAX_EXTRA_PARAM:g})"
    return None


# ---------------------------------------------------------------------------------------------
# Text files, line by line (before pycolmap reads them)


def _data_lines(path: Path):
    """(line number, stripped text) of the non-comment lines; blank lines are kept because
    images.txt gives every image a second (points) line, which may be empty."""
    try:
        text = path.read_text(errors="replace")
    except OSError as exc:
        raise DifftexError(f"{path}: cannot read ({exc.strerror})") from None
    for n, line in enumerate(text.splitlines(), 1):
        s = line.strip()
        if not s.startswith("#"):
            yield n, s


def check_cameras_text(path: Path) -> dict[int, str]:
    """Check cameras.txt; returns {camera id: model name}.

    Each line is ``CAMERA_ID MODEL WIDTH HEIGHT PARAMS...``.
    """
    cams: dict[int, str] = {}
    for n, s in _data_lines(path):
        if not s:
            continue
        parts = s.split()
        where = f"{path}:{n}"
        if len(parts) < 4:
            raise DifftexError(f"{where}: expected 'CAMERA_ID MODEL WIDTH HEIGHT PARAMS...', got '{s[:80]}'")
        try:
            cid = int(parts[0])
        except ValueError:
            raise DifftexError(f"{where}: camera id '{parts[0]}' is not an integer") from None
        try:
            w, h = int(parts[2]), int(parts[3])
        except ValueError:
            raise DifftexError(
                f"{where}: camera {cid}: width/height '{parts[2]} {parts[3]}' are not integers"
            ) from None
        try:
            params = np.array([float(x) for x in parts[4:]], dtype=np.float64)
        except ValueError:
            raise DifftexError(
                f"{where}: camera {cid}: parameters are not numbers ('{' '.join(parts[4:])[:80]}')"
            ) from None
        problem = camera_problem(parts[1], w, h, params)
        if problem:
            raise DifftexError(f"{where}: camera {cid} ({parts[1]}): {problem}")
        if cid in cams:
            raise DifftexError(f"{where}: camera {cid} is defined twice")
        cams[cid] = parts[1]
    if not cams:
        raise DifftexError(f"{path}: no cameras")
    return cams


def check_images_text(path: Path, cameras: dict[int, str]) -> None:
    """Check images.txt: every image's pose, camera and name, and its points line.

    COLMAP reads an image line (skipping blank and comment lines), then always one points line.
    """
    names: dict[str, int] = {}
    ids: set[int] = set()
    lines = iter(_data_lines(path))
    for n, s in lines:
        if not s:
            continue
        parts = s.split()
        where = f"{path}:{n}"
        if len(parts) < 10:
            raise DifftexError(f"{where}: expected 'IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME', got '{s[:80]}'")
        name = " ".join(parts[9:])
        try:
            iid, cid = int(parts[0]), int(parts[8])
        except ValueError:
            raise DifftexError(f"{where}: image '{name}': image or camera id is not an integer") from None
        try:
            pose = np.array([float(x) for x in parts[1:8]])
        except ValueError:
            raise DifftexError(f"{where}: image '{name}' has an unreadable pose ({' '.join(parts[1:8])})") from None
        problem = pose_problem(pose[:4], pose[4:])
        if problem:
            raise DifftexError(f"{where}: image '{name}': {problem}")
        if cid not in cameras:
            raise DifftexError(f"{where}: image '{name}' uses camera {cid}, which cameras.txt does not define")
        if name in names:
            raise DifftexError(f"{where}: image '{name}' is listed twice (image ids {names[name]} and {iid})")
        if iid in ids:
            raise DifftexError(f"{where}: image id {iid} is used twice")
        names[name] = iid
        ids.add(iid)
        pts = next(lines, (n + 1, ""))
        tokens = pts[1].split()
        if len(tokens) % 3:
            raise DifftexError(f"{path}:{pts[0]}: points of image '{name}' are not (X, Y, POINT3D_ID) triples")
    if not names:
        raise DifftexError(f"{path}: no images")


def pose_problem(qvec: np.ndarray, tvec: np.ndarray) -> str | None:
    """What is wrong with a cam_from_world pose (quaternion w, x, y, z; translation), or None."""
    if not (np.isfinite(qvec).all() and np.isfinite(tvec).all()):
        return "pose is not finite (NaN or inf)"
    if np.linalg.norm(qvec) < 1e-9:
        return "rotation quaternion is zero"
    return None


def check_points_text(path: Path) -> None:
    """Locate the first bad line of points3D.txt (``ID X Y Z R G B ERROR TRACK[]``)."""
    for n, s in _data_lines(path):
        if not s:
            continue
        parts = s.split()
        try:
            vals = [float(x) for x in parts]
        except ValueError:
            raise DifftexError(f"{path}:{n}: point line holds a value that is not a number") from None
        if len(vals) < 8 or (len(vals) - 8) % 2:
            raise DifftexError(f"{path}:{n}: expected 'ID X Y Z R G B ERROR (IMAGE_ID POINT2D_IDX)...'")
        if not all(math.isfinite(v) for v in vals[1:4]):
            raise DifftexError(f"{path}:{n}: point {parts[0]} has a non-finite position")


def check_cameras_binary(path: Path) -> None:
    """Locate the problem in a cameras.bin that pycolmap could not read.

    Layout (COLMAP): uint64 count, then per camera uint32 id, int32 model id, uint64 width,
    uint64 height, float64 params[count of the model].
    """
    import pycolmap

    data = path.read_bytes()
    by_id = {int(v): k for k, v in pycolmap.CameraModelId.__members__.items()}
    if len(data) < 8:
        raise DifftexError(f"{path}: truncated ({len(data)} bytes)")
    (count,) = struct.unpack_from("<Q", data, 0)
    pos = 8
    for k in range(count):
        if pos + 24 > len(data):
            raise DifftexError(f"{path}: truncated after {k} of {count} cameras")
        cid, mid, w, h = struct.unpack_from("<IiQQ", data, pos)
        pos += 24
        model = by_id.get(mid, f"model id {mid}")
        cam = _camera_template(model) if mid in by_id else None
        if cam is None:
            raise DifftexError(f"{path}: camera {cid}: unknown camera model ({model})")
        npar = len(cam.params)
        if pos + 8 * npar > len(data):
            raise DifftexError(f"{path}: truncated in camera {cid}")
        params = np.frombuffer(data, dtype="<f8", count=npar, offset=pos)
        pos += 8 * npar
        problem = camera_problem(model, int(w), int(h), params)
        if problem:
            raise DifftexError(f"{path}: camera {cid} ({model}): {problem}")
    if pos != len(data):
        raise DifftexError(f"{path}: {len(data) - pos} bytes after the last of its {count} cameras")


# ---------------------------------------------------------------------------------------------
# The loaded model


def _quat_t(image) -> tuple[np.ndarray, np.ndarray]:
    cfw = image.cam_from_world() if callable(image.cam_from_world) else image.cam_from_world
    q = np.asarray(cfw.rotation.quat, dtype=np.float64)  # pycolmap: x, y, z, w
    return np.array([q[3], q[0], q[1], q[2]]), np.asarray(cfw.translation, dtype=np.float64)


def check_reconstruction(rec, files: dict[str, Path]) -> None:
    """Checks on the loaded model that hold for both formats: usable cameras, finite non-zero
    poses, cameras that exist, and unique image names."""
    for cam in rec.cameras.values():
        problem = camera_problem(str(cam.model_name), int(cam.width), int(cam.height), np.asarray(cam.params))
        if problem:
            raise DifftexError(f"{files['cameras']}: camera {cam.camera_id} ({cam.model_name}): {problem}")
    seen: dict[str, int] = {}
    pose_file = files.get("frames", files["images"])
    for iid, image in rec.images.items():
        if hasattr(image, "has_pose") and not image.has_pose:
            continue
        if image.camera_id not in rec.cameras:
            raise DifftexError(
                f"{files['images']}: image '{image.name}' uses camera {image.camera_id}, which is not defined"
            )
        problem = pose_problem(*_quat_t(image))
        if problem:
            raise DifftexError(f"{pose_file}: image '{image.name}': {problem}")
        if image.name in seen:
            raise DifftexError(
                f"{files['images']}: image '{image.name}' is listed twice (image ids {seen[image.name]} and {iid})"
            )
        seen[image.name] = iid


def _close(a, b, scale: float = 1.0) -> bool:
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return a.shape == b.shape and bool(np.all(np.abs(a - b) <= AGREE_RTOL * np.maximum(scale, np.abs(b)) + 1e-12))


def model_difference(a, b) -> str | None:
    """The first difference between two loaded models (``a`` binary, ``b`` text), or None."""
    ia = {im.name: im for im in a.images.values()}
    ib = {im.name: im for im in b.images.values()}
    only_a, only_b = sorted(set(ia) - set(ib)), sorted(set(ib) - set(ia))
    if only_a or only_b:
        parts = []
        if only_a:
            parts.append(f"{len(only_a)} images only in the binary one (e.g. '{only_a[0]}')")
        if only_b:
            parts.append(f"{len(only_b)} only in the text one (e.g. '{only_b[0]}')")
        return f"the binary model has {len(ia)} images, the text one {len(ib)}: " + ", ".join(parts)
    centers = [(-(_rot(im).T @ _quat_t(im)[1])) for im in ia.values()]
    scale = float(np.ptp(np.asarray(centers), axis=0).max()) if len(centers) > 1 else 1.0
    for name in sorted(ia):
        qa, ta = _quat_t(ia[name])
        qb, tb = _quat_t(ib[name])
        qa, qb = qa / np.linalg.norm(qa), qb / np.linalg.norm(qb)
        if not (_close(qa, qb) or _close(qa, -qb)) or not _close(ta, tb, scale):
            return f"image '{name}' has different poses"
        ca, cb = a.cameras[ia[name].camera_id], b.cameras[ib[name].camera_id]
        if (ca.model_name, ca.width, ca.height) != (cb.model_name, cb.width, cb.height) or not _close(
            ca.params, cb.params
        ):
            return (
                f"image '{name}' has different cameras ({ca.model_name} {np.round(ca.params, 3).tolist()} vs "
                f"{cb.model_name} {np.round(cb.params, 3).tolist()})"
            )
    return None


def _rot(image) -> np.ndarray:
    cfw = image.cam_from_world() if callable(image.cam_from_world) else image.cam_from_world
    return np.asarray(cfw.rotation.matrix(), dtype=np.float64)


def _read(files: dict[str, Path], ext: str):
    """pycolmap's reader on one format, with the diagnosis of its failure."""
    import pycolmap

    if ext == "txt":
        cams = check_cameras_text(files["cameras"])
        check_images_text(files["images"], cams)
    rec = pycolmap.Reconstruction()
    try:
        (rec.read_text if ext == "txt" else rec.read_binary)(str(files["cameras"].parent))
    except Exception as exc:  # noqa: BLE001 -- pycolmap raises bare ValueError/IndexError with C++ context
        if ext == "txt" and "points3D" in files:
            check_points_text(files["points3D"])
        if ext == "bin":
            check_cameras_binary(files["cameras"])
        first = str(exc).strip().splitlines()[-1] if str(exc).strip() else type(exc).__name__
        raise DifftexError(
            f"{files['cameras'].parent}: unreadable COLMAP {'text' if ext == 'txt' else 'binary'} model ({first})"
        ) from None
    check_reconstruction(rec, files)
    return rec


def read_model(sparse_dir: str | Path):
    """The COLMAP model of a folder (pycolmap.Reconstruction), checked.

    Binary and text both present: both are read; they must agree (else an error saying which
    image differs), and the binary one is used, as COLMAP does, with a warning saying so.
    """
    sparse_dir = Path(sparse_dir)
    if not sparse_dir.is_dir():
        raise DifftexError(f"{sparse_dir}: COLMAP model folder not found")
    found = model_files(sparse_dir)
    if not found:
        raise DifftexError(f"{sparse_dir}: no COLMAP model (cameras/images .bin or .txt) in this folder")
    if len(found) == 1:
        ext, files = next(iter(found.items()))
        return _read(files, ext)
    rec_bin, rec_txt = _read(found["bin"], "bin"), _read(found["txt"], "txt")
    diff = model_difference(rec_bin, rec_txt)
    if diff:
        raise DifftexError(
            f"{sparse_dir}: holds a binary and a text COLMAP model that disagree ({diff}); "
            "remove the stale one (COLMAP itself would read the .bin files)"
        )
    log.warning("%s: holds both a binary and a text COLMAP model (they agree); using the .bin files", sparse_dir)
    return rec_bin
