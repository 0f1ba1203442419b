"""The per-polygon output files: texture.png (8 or 16 bit), source.png, coverage.png,
report.json, and composite.npz, the float texture that the texturing stage hands to them.

No torch here: the workflow's per-polygon ``finish`` rule runs this inside Snakemake itself.
"""

from __future__ import annotations

import colorsys
import zlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np


def photo_colour(name: str) -> tuple[float, float, float]:
    """A stable, distinct-looking colour per photo name (same photo, same colour in every map)."""
    h = zlib.crc32(name.encode()) / 2**32
    s = 0.55 + 0.45 * ((zlib.crc32(name.encode()[::-1]) % 1000) / 1000)
    return colorsys.hsv_to_rgb(h, s, 0.95)


def source_map(dominant: np.ndarray, names: list[str], mask: np.ndarray, filled: np.ndarray | None = None) -> np.ndarray:
    """The paper's texel source map: each texel coloured by its dominant photo (Fig. 5).

    ``dominant`` (H, W) is a photo index (-1: none). Outside the polygon black; filled holes grey.
    """
    out = np.zeros((*dominant.shape, 3), np.float32)
    for n, name in enumerate(names):
        out[dominant == n] = photo_colour(name)
    if filled is not None:
        out[filled] = 0.5
    out[~mask] = 0.0
    return out


def coverage_image(mask: np.ndarray, seen: np.ndarray) -> np.ndarray:
    """Grey image: 255 texel seen by a photo, 128 filled from neighbours, 0 outside the polygon."""
    img = np.zeros(mask.shape, np.float32)
    img[mask & ~seen] = 128 / 255
    img[mask & seen] = 1.0
    return img


def write_texture_outputs(out_dir: str | Path, U: np.ndarray, mask: np.ndarray, seen: np.ndarray,
                          dominant: np.ndarray, names: list[str], report: dict, bits: int = 8, exr: bool = False) -> None:
    """texture.png, source.png, coverage.png, report.json (and texture.exr), each written atomically."""
    from difftex.io import write_image, write_json

    out_dir = Path(out_dir)
    write_image(out_dir / "texture.png", np.clip(U, 0, 1), bits=bits)
    if exr:
        write_image(out_dir / "texture.exr", U)
    write_image(out_dir / "source.png", source_map(dominant, names, mask, mask & ~seen))
    write_image(out_dir / "coverage.png", coverage_image(mask, seen))
    report = dict(report)
    report["source_colours"] = {n: "#%02x%02x%02x" % tuple(int(round(255 * c)) for c in photo_colour(n)) for n in names}
    write_json(out_dir / "report.json", report)


@dataclass(frozen=True)
class OutputConfig:
    """The ``output:`` section: formats of the texture files (not the textures themselves)."""

    bits: int = 8  # bit depth of texture.png and the atlas pages (8 or 16)
    exr: bool = False  # also texture.exr per polygon (half float)

    def __post_init__(self):
        if int(self.bits) not in (8, 16):
            raise ValueError(f"bits must be 8 or 16, got {self.bits}")


def finish_polygon(composite: str | Path, out_dir: str | Path, cfg: OutputConfig = OutputConfig()) -> dict:
    """texture.png (cfg.bits), source.png, coverage.png, report.json (and texture.exr) of one
    polygon from its composite.npz; returns the report."""
    U, mask, seen, dominant, names, report = read_composite(composite)
    write_texture_outputs(out_dir, U, mask, seen, dominant, names, report, bits=cfg.bits, exr=cfg.exr)
    return report


def write_composite(path: str | Path, U: np.ndarray, mask: np.ndarray, seen: np.ndarray, dominant: np.ndarray,
                    names: list[str], report: dict) -> None:
    """A polygon's composed texture in float (half precision), before quantisation to a PNG.

    The texturing stage writes it; assembly turns it into the per-polygon PNGs and the atlas at
    the configured bit depth, so a change of output format does not redo the texturing.
    """
    import json

    from difftex.io import write_npz

    write_npz(path, texture=np.asarray(U, np.float16), mask=np.packbits(mask.ravel()), seen=np.packbits(seen.ravel()),
              shape=np.array(seen.shape),
              dominant=dominant.astype(np.int32), photos=np.array(names, dtype=str), report=np.array(json.dumps(report)))


def read_composite(path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, list[str], dict]:
    """(U (H, W, 3) float32, texel mask, seen (H, W) bool, dominant (H, W), photo names, report) of write_composite."""
    import json

    from difftex.errors import DifftexError
    from difftex.io import read_npz

    d = read_npz(path)
    try:
        H, W = (int(v) for v in d["shape"])
        seen = np.unpackbits(d["seen"], count=H * W).astype(bool).reshape(H, W)
        mask = np.unpackbits(d["mask"], count=H * W).astype(bool).reshape(H, W)
        return (d["texture"].astype(np.float32), mask, seen, d["dominant"].astype(np.int64), [str(x) for x in d["photos"]],
                json.loads(str(d["report"])))
    except (KeyError, ValueError) as exc:
        raise DifftexError(f"{path}: not a difftex composite texture ({exc})") from None


