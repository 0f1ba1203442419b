"""Atomic file output and checked image input.

Every output is written to a temporary file in the target folder and renamed into place, so an
interrupted run never leaves a half-written file that a rerun (or Snakemake) would take as done.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import tempfile
import zipfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from difftex.errors import DifftexError, os_error_message


def current_umask() -> int:
    """The process's file-creation mask, read without changing it.

    ``os.umask`` can only be read by setting it, which races with other threads creating files;
    Linux shows it in /proc/self/status, so the set-and-restore is only the fallback.
    """
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it onto ``path`` only if the block succeeds.

    The temporary name keeps ``path``'s extension (or ``suffix``) because writers such as
    OpenImageIO and numpy choose the format from it. ``tempfile.mkstemp`` creates the file with
    mode 0600 whatever the umask; the result gets the mode a plain ``open`` would give (0666
    minus the umask), so colleagues and web servers can read the outputs where the umask allows.
    An OS error (disk full, permission denied) becomes a one-line DifftexError naming ``path``,
    and the temporary file is removed: nothing half-written is left.
    """
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        ext = suffix if suffix is not None else "".join(path.suffixes[-1:])
        fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=f".part{ext}", dir=path.parent)
        os.close(fd)
    except OSError as exc:
        raise DifftexError(os_error_message(exc, path)) from None
    tmp_path = Path(tmp)
    try:
        try:
            yield tmp_path
            os.chmod(tmp_path, 0o666 & ~current_umask())
            os.replace(tmp_path, path)
        except OSError as exc:
            raise DifftexError(os_error_message(exc, path)) from None
    finally:
        if tmp_path.exists():
            tmp_path.unlink()


def write_text(path: str | os.PathLike, text: str) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def _json_default(obj: Any) -> Any:
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")


def write_json(path: str | os.PathLike, data: Any) -> None:
    write_text(path, json.dumps(data, indent=2, default=_json_default) + "\n")


def read_json(path: str | os.PathLike) -> Any:
    path = Path(path)
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise DifftexError(f"{path}: file not found") from None
    except json.JSONDecodeError as exc:
        raise DifftexError(f"{path}: not valid JSON ({exc.msg} at line {exc.lineno})") from None


def write_npz(path: str | os.PathLike, **arrays: np.ndarray) -> None:
    """Compressed npz (readable by np.load), written atomically.

    Deflate at level 1, not np.savez_compressed's zlib default (6), which numpy does not let one
    choose: on a polygon's weights (K x texels float16 + int16) level 1 took half the time for
    files 6 % larger.
    """
    _write_npz(path, True, arrays)


def write_npz_stored(path: str | os.PathLike, **arrays: np.ndarray) -> None:
    """Uncompressed npz, written atomically: for decoded photos, which deflate shrinks little at
    many times the time (docs/stage-split.md)."""
    _write_npz(path, False, arrays)


def _write_npz(path: str | os.PathLike, compress: bool, arrays: dict[str, np.ndarray]) -> None:
    method = zipfile.ZIP_DEFLATED if compress else zipfile.ZIP_STORED
    with atomic_path(path, suffix=".npz") as tmp:
        with zipfile.ZipFile(tmp, "w", method, compresslevel=1 if compress else None) as zf:
            for name, value in arrays.items():
                with zf.open(f"{name}.npy", "w", force_zip64=True) as fh:
                    np.lib.format.write_array(fh, np.asanyarray(value), allow_pickle=False)


def read_npz(path: str | os.PathLike) -> dict[str, np.ndarray]:
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as data:
            return {k: data[k] for k in data.files}
    except FileNotFoundError:
        raise DifftexError(f"{path}: file not found") from None
    except (OSError, ValueError) as exc:
        raise DifftexError(f"{path}: unreadable npz ({exc})") from None


def _first_line(text: str) -> str:
    lines = [ln.strip() for ln in (text or "").strip().splitlines() if ln.strip()]
    return lines[0] if lines else ""


def read_image(
    path: str | os.PathLike, expected_size: tuple[int, int] | None = None, as_stored: bool = False
) -> np.ndarray:
    """Read an image as float32 RGB in [0, 1] (H, W, 3) with OpenImageIO.

    8/16-bit integer formats are normalised to [0, 1]; float formats (EXR) are kept linear as
    stored. ``expected_size`` is (width, height): a mismatch is an error naming the file.
    ``as_stored``: an 8/16-bit image is returned as its uint8/uint16 RGB values
    (:func:`to_float` converts them), so that a caller that needs only a crop converts only that.
    """
    import OpenImageIO as oiio

    path = Path(path)
    if not path.is_file():
        raise DifftexError(f"{path}: image file not found")
    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise DifftexError(f"{path}: cannot open image ({_first_line(oiio.geterror()) or 'unknown format'})")
    try:
        spec = inp.spec()
        if expected_size is not None and (spec.width, spec.height) != tuple(expected_size):
            raise DifftexError(
                f"{path}: image is {spec.width}x{spec.height} but its camera says {expected_size[0]}x{expected_size[1]}"
            )
        # 8/16-bit images are read as stored and scaled here: OIIO's own conversion to float was
        # a third of a PNG photo's read (23 -> 16 ms at 1024 x 768), and multiplying by the
        # float32 reciprocal gives its values bit for bit (tests/test_sampling.py)
        native = {oiio.UINT8: (oiio.UINT8, 255), oiio.UINT16: (oiio.UINT16, 65535)}.get(spec.format.basetype)
        pixels = inp.read_image(0, 0, 0, spec.nchannels, native[0] if native else oiio.FLOAT)
        if pixels is None or not isinstance(pixels, np.ndarray):
            raise DifftexError(f"{path}: corrupt image ({_first_line(inp.geterror()) or 'read failed'})")
        err = inp.geterror()
        if err:
            raise DifftexError(f"{path}: corrupt image ({_first_line(err)})")
    finally:
        inp.close()
    pixels = pixels.reshape(spec.height, spec.width, spec.nchannels)
    if spec.nchannels == 1:
        pixels = np.repeat(pixels, 3, axis=2)
    elif spec.nchannels == 2:  # grey + alpha
        pixels = np.repeat(pixels[:, :, :1], 3, axis=2)
    else:
        pixels = pixels[:, :, :3]
    if native:  # to_float's conversion is a contiguous copy already
        return np.ascontiguousarray(pixels) if as_stored else to_float(pixels)
    # only a float format can store NaN or infinity; an 8/16-bit one decodes to finite values,
    # and the check was a quarter of a PNG photo's read time
    if spec.format.basetype in (oiio.FLOAT, oiio.HALF, oiio.DOUBLE) and not np.isfinite(pixels).all():
        raise DifftexError(f"{path}: image holds NaN or infinite values")
    return np.ascontiguousarray(pixels, dtype=np.float32)


def to_float(pixels: np.ndarray) -> np.ndarray:
    """float32 in [0, 1] of uint8 / uint16 values (read_image(..., as_stored=True)); float as it is.

    Multiplied by the float32 reciprocal of 255 or 65535, in place on the converted copy: OIIO's
    own conversion to float, bit for bit (tests/test_sampling.py), without a second full-size
    temporary.
    """
    top = {np.dtype(np.uint8): 255, np.dtype(np.uint16): 65535}.get(pixels.dtype)
    if top is None:
        return np.asarray(pixels, dtype=np.float32)
    out = pixels.astype(np.float32)
    out *= np.float32(1.0 / top)
    return out


def _header(path: str | os.PathLike):
    """The image's OpenImageIO ImageSpec, from its header alone."""
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(path))
    if inp is None:
        raise DifftexError(f"{path}: cannot open image ({_first_line(oiio.geterror()) or 'unknown format'})")
    spec = inp.spec()
    inp.close()
    return spec


def image_size(path: str | os.PathLike) -> tuple[int, int]:
    """(width, height) from the header alone."""
    spec = _header(path)
    return spec.width, spec.height


def image_stored_bytes(path: str | os.PathLike) -> int:
    """Bytes of the image decoded as ``read_image(..., as_stored=True)`` keeps it, from the header:
    RGB at 1 byte per value (8-bit), 2 (16-bit) or 4 (anything else, as float32)."""
    import OpenImageIO as oiio

    spec = _header(path)
    per_value = {oiio.UINT8: 1, oiio.UINT16: 2}.get(spec.format.basetype, 4)
    return spec.width * spec.height * 3 * per_value


def write_image(path: str | os.PathLike, pixels: np.ndarray, bits: int = 8) -> None:
    """Write float RGB(A) in [0, 1] as 8/16-bit PNG/JPEG/TIFF or float EXR, atomically."""
    import OpenImageIO as oiio

    path = Path(path)
    arr = np.asarray(pixels, dtype=np.float32)
    if arr.ndim == 2:
        arr = arr[:, :, None]
    h, w, c = arr.shape
    if path.suffix.lower() == ".exr":
        fmt = oiio.HALF
    else:
        fmt = {8: oiio.UINT8, 16: oiio.UINT16}[bits]
        arr = np.clip(arr, 0.0, 1.0)
    with atomic_path(path) as tmp:
        out = oiio.ImageOutput.create(str(tmp))
        if out is None:
            raise DifftexError(f"{path}: cannot write image ({oiio.geterror().strip()})")
        spec = oiio.ImageSpec(w, h, c, fmt)
        ok = out.open(str(tmp), spec) and out.write_image(np.ascontiguousarray(arr))
        # A failed write does not always fail the call: on a full disk OpenImageIO's PNG writer
        # returns True from write_image and close and only records "Write error at position ...,
        # could only write ... bytes". The truncated file must not be renamed into place.
        err = out.geterror() if not ok or out.has_error else ""
        if not out.close():
            err += "\n" + out.geterror()
            ok = False
        if not ok or err.strip():
            _image_write_failed(path, tmp, err)


def _image_write_failed(path: Path, tmp: Path, err: str) -> None:
    """Raise for an image write that stopped: the disk-full message when the disk is (nearly)
    full, else OpenImageIO's first error line. ``atomic_path`` then removes the temporary file."""
    import errno
    import shutil

    try:
        full = shutil.disk_usage(tmp.parent).free < (1 << 20)
    except OSError:
        full = False
    if full:
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(tmp))
    first = next((ln.strip() for ln in err.splitlines() if ln.strip()), "unknown error")
    raise DifftexError(f"{path}: cannot write image ({first})")


JPEG_SUFFIXES = {".jpg", ".jpeg"}


def decode_photo(
    path: str | os.PathLike, size: tuple[int, int], reduce: int = 1, as_stored: bool = False
) -> np.ndarray:
    """An image of ``size`` (width, height) as float32 RGB (h, w, 3) in [0, 1], at 1/``reduce`` of
    full size (a power of 2).

    A JPEG is decoded at the reduced size directly (libjpeg's DCT scaling through Pillow's
    ``draft``: 1/2, 1/4, 1/8), which OpenImageIO cannot do; other formats are read in full with
    OpenImageIO (difftex.scene.files.read_image) and box-averaged. Pixel (j, i) of the result covers
    full-resolution pixels [j r, (j + 1) r) x [i r, (i + 1) r), as in a box pyramid. The size
    is ceil(width / r) x ceil(height / r).

    ``as_stored``: where no box-averaging is left to do, an 8/16-bit image comes back as its
    integer values (:func:`to_float` converts them): a texture job converts only the polygon's
    crop of each photo, not the whole photo (the conversion of a kept full-size float copy,
    page faults included, cost about as much as decoding a PNG).
    """
    if reduce < 1 or reduce & (reduce - 1):
        raise ValueError(f"reduce must be a power of two, got {reduce}")
    path = Path(path)
    if reduce > 1 and path.suffix.lower() in JPEG_SUFFIXES:
        img, got = _decode_jpeg_scaled(path, size, reduce)
        return img if (as_stored and got == reduce) else box_reduce(to_float(img), reduce // got)
    img = read_image(path, expected_size=size, as_stored=as_stored and reduce == 1)
    return img if reduce == 1 else box_reduce(img, reduce)


def _decode_jpeg_scaled(path: Path, size: tuple[int, int], reduce: int) -> tuple[np.ndarray, int]:
    """(image as stored (uint8, or what read_image gives), achieved reduction) of a JPEG decoded with
    DCT scaling (at most 1/8)."""
    from PIL import Image

    try:
        with Image.open(path) as im:
            width, height = size
            if im.size != (width, height):
                raise DifftexError(f"{path}: image is {im.size[0]}x{im.size[1]} but its camera says {width}x{height}")
            r = min(reduce, 8)
            im.draft("RGB", (math.ceil(width / r), math.ceil(height / r)))
            got = max(1, round(width / im.size[0]))
            arr = np.asarray(im.convert("RGB"))  # uint8
    except DifftexError:
        raise
    except (OSError, ValueError, SyntaxError) as exc:
        raise DifftexError(
            f"{path}: corrupt image ({str(exc).splitlines()[0] if str(exc) else type(exc).__name__})"
        ) from None
    if arr.shape[:2] != (math.ceil(height / got), math.ceil(width / got)):
        # a decoder that did not honour the draft exactly: fall back to the general path
        return read_image(path, expected_size=size, as_stored=True), 1
    return arr, got


def box_reduce(img: np.ndarray, r: int) -> np.ndarray:
    """Average r x r blocks (the last partial row/column of blocks averages what it has)."""
    if r <= 1:
        return img
    import torch
    import torch.nn.functional as F

    t = torch.from_numpy(np.ascontiguousarray(img, dtype=np.float32)).permute(2, 0, 1)[None]
    return F.avg_pool2d(t, r, ceil_mode=True, count_include_pad=False)[0].permute(1, 2, 0).numpy()


class DecodeCache:
    """``decode_photo`` with the last decodes kept, up to ``budget_mb`` of pixels (as decoded: float32,
    or 8/16-bit with ``as_stored``).

    A texture job of several polygons of one facade decodes the same photos for each of them
    (0.1 s for a 6-Mpixel JPEG at 1/2, about half of a small polygon's time). functools.lru_cache
    bounds entries, not bytes; photos differ 64x in size between decode scales.
    Callable like ``decode_photo``; ``decodes`` and ``hits`` count what it did.
    """

    def __init__(self, budget_mb: float = 512.0):
        from collections import OrderedDict

        self.budget = int(budget_mb * 2**20)
        self.entries: OrderedDict[tuple[str, tuple[int, int], int, bool], np.ndarray] = OrderedDict()
        self.decodes = 0
        self.hits = 0

    def nbytes(self) -> int:
        return int(sum(a.nbytes for a in self.entries.values()))

    def __call__(
        self, path: str | os.PathLike, size: tuple[int, int], reduce: int = 1, as_stored: bool = False
    ) -> np.ndarray:
        key = (str(path), (int(size[0]), int(size[1])), int(reduce), bool(as_stored))
        if key in self.entries:
            self.entries.move_to_end(key)
            self.hits += 1
            return self.entries[key]
        img = decode_photo(path, size, reduce, as_stored)
        self.decodes += 1
        if img.nbytes <= self.budget:
            self.entries[key] = img
            while self.nbytes() > self.budget:
                self.entries.popitem(last=False)
        return img
