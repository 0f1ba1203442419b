"""The per-polygon output files: texture.png (8 or 16 bit), source.png (the texel source map),
source.npz (the dominant photo per texel, as numbers), coverage.png, report.json, and
composite.npz, the float texture that the texturing stage hands to them.

No torch here: the workflow's per-polygon ``finish`` rule runs this inside Snakemake itself.
"""

from __future__ import annotations

import colorsys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from difftex.layout import COVERAGE, HEIGHT, NORMAL, REPORT, SOURCE_NPZ, SOURCE_PNG, TEXTURE, TEXTURE_EXR

FILLED_GREY = 0.5  # source map: texels no photo sees, filled from their neighbours

# matplotlib's ``tab10`` (Tableau 10) as 8-bit values: importing matplotlib for these ten colours
# was half of a polygon's finish job (0.23 s); tests/test_report.py checks them against it.
TAB10 = tuple(
    (r / 255, g / 255, b / 255)
    for r, g, b in (
        (31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40), (148, 103, 189),
        (140, 86, 75), (227, 119, 194), (127, 127, 127), (188, 189, 34), (23, 190, 207),
    )
)


def palette(n: int) -> list[tuple[float, float, float]]:
    """``n`` distinguishable colours: matplotlib's qualitative ``tab10`` (Tableau 10) without its
    grey, which would read as a filled texel (FILLED_GREY); then rounds of the same nine hues,
    alternately lighter and darker, each round further from the base (half-way to white, 40 %
    darker, three quarters to white, ...), all distinct in 8 bits for the first 90 or so.

    Returns:
        n (r, g, b) tuples in [0, 1].
    """
    base = [c for c in TAB10 if not (c[0] == c[1] == c[2])]
    out = []
    for i in range(n):
        h, light, s = colorsys.rgb_to_hls(*base[i % len(base)])
        rnd = i // len(base)
        if rnd % 2:  # lighter: l -> 1 - (1 - l) / 2, / 4, ...
            light = 1 - (1 - light) * 0.5 ** ((rnd + 1) // 2)
        elif rnd:  # darker: l -> 0.6 l, 0.36 l, ...
            light = light * 0.6 ** (rnd // 2)
        out.append(tuple(float(v) for v in colorsys.hls_to_rgb(h, light, s)))
    return out


def source_colours(dominant: np.ndarray, names: list[str]) -> dict[str, tuple[float, float, float]]:
    """Colour of each photo that is the dominant one of some texel, in photo order.

    Only the photos the map shows get a colour, so a polygon's map uses the palette's most
    distinct colours first; the legend (report.json's ``source_colours``) names them. The same
    photo may therefore have another colour in another polygon's map.
    """
    present = [int(k) for k in np.unique(dominant[dominant >= 0])]
    if present and present[-1] >= len(names):
        raise ValueError(f"dominant photo index {present[-1]} but only {len(names)} photo names")
    return dict(zip((names[k] for k in present), palette(len(present))))


def source_map(dominant: np.ndarray, names: list[str], mask: np.ndarray, filled: np.ndarray | None = None,
               colours: dict[str, tuple] | None = None) -> np.ndarray:
    """The paper's texel source map: each texel coloured by its dominant photo (Fig. 5).

    Args:
        dominant: (H, W) photo index into ``names`` (-1: none).
        mask: (H, W) the polygon's texels; outside them the map is black.
        filled: (H, W) texels filled from their neighbours, shown grey (FILLED_GREY).
        colours: photo name -> colour (default: :func:`source_colours`).
    Returns:
        (H, W, 3) float32 image.
    """
    colours = source_colours(dominant, names) if colours is None else colours
    out = np.zeros((*dominant.shape, 3), np.float32)
    for n, name in enumerate(names):
        if name in colours:
            out[dominant == n] = colours[name]
    if filled is not None:
        out[filled] = FILLED_GREY
    out[~mask] = 0.0
    return out


def coverage_image(mask: np.ndarray, seen: np.ndarray) -> np.ndarray:
    """Grey image: 255 texel seen by a photo, 128 filled from neighbours, 0 outside the polygon."""
    img = np.zeros(mask.shape, np.float32)
    img[mask & ~seen] = 128 / 255
    img[mask & seen] = 1.0
    return img


def write_texture_outputs(
    out_dir: str | Path,
    U: np.ndarray,
    mask: np.ndarray,
    seen: np.ndarray,
    dominant: np.ndarray,
    names: list[str],
    report: dict,
    bits: int = 8,
    exr: bool = False,
) -> None:
    """texture.png, source.png, source.npz, coverage.png, report.json (and texture.exr), each
    written atomically.

    source.npz holds ``dominant`` (H, W) int16, the index into ``photos`` of each texel's
    dominant photo (-1: none), for tools that need the photo ids (``difftex evaluate``), not the
    colours of source.png.
    """
    from difftex.scene.files import write_image, write_json, write_npz

    out_dir = Path(out_dir)
    write_image(out_dir / TEXTURE, np.clip(U, 0, 1), bits=bits)
    if exr:
        write_image(out_dir / TEXTURE_EXR, U)
    colours = source_colours(dominant, names)
    write_image(out_dir / SOURCE_PNG, source_map(dominant, names, mask, mask & ~seen, colours))
    dom = np.where(mask & seen, dominant, -1)
    write_npz(out_dir / SOURCE_NPZ, dominant=dom.astype(np.int16), photos=np.array(names, dtype=str))
    write_image(out_dir / COVERAGE, coverage_image(mask, seen))
    report = dict(report)
    report["source_colours"] = {
        n: "#{:02x}{:02x}{:02x}".format(*(int(round(255 * v)) for v in c)) for n, c in colours.items()
    }
    write_json(out_dir / REPORT, report)


@dataclass(frozen=True)
class OutputConfig:
    """The ``output:`` section: formats of the texture files (not the textures themselves)."""

    bits: int = 8  # bit depth of texture.png and the atlas pages (8 or 16)
    exr: bool = False  # also texture.exr per polygon (half float)

    def __post_init__(self):
        if int(self.bits) not in (8, 16):
            raise ValueError(f"bits must be 8 or 16, got {self.bits}")


def normal_map(heights: np.ndarray, texel_size: float) -> np.ndarray:
    """The tangent-space normal map of a height field, as glTF's ``normalTexture`` reads it.

    Texel x runs along the frame's e_u (glTF's +X, "right"), texel y along e_v, which points
    down the image, so glTF's +Y ("up") is -e_v; +Z is the polygon's outward normal. With
    h(x, y) in scene units and central differences over texels of size s, the surface normal is
    (-dh/dx, +dh/dy, s) normalised (dh/dy is taken down the image, hence the sign).

    Args:
        heights: (H, W) heights along the normal, scene units.
        texel_size: scene units per texel, > 0.

    Returns:
        (H, W, 3) float32 in [0, 1]: (n + 1) / 2; (0.5, 0.5, 1) where the field is flat.
    """
    if heights.ndim != 2 or texel_size <= 0:
        raise ValueError(f"heights must be (H, W) and texel_size > 0, got {heights.shape} and {texel_size}")
    h = heights.astype(np.float64)
    gy, gx = np.gradient(h) if min(h.shape) > 1 else (np.zeros_like(h), np.zeros_like(h))
    n = np.stack([-gx, gy, np.full_like(h, float(texel_size))], -1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    return ((n + 1.0) / 2.0).astype(np.float32)


def finish_polygon(composite: str | Path, out_dir: str | Path, cfg: OutputConfig = OutputConfig()) -> dict:
    """texture.png (cfg.bits), source.png, source.npz, coverage.png, report.json (and texture.exr) of one
    polygon from its composite.npz, and with a relief its height field (height.exr, scene units
    along the normal) and normal map (normal.png, glTF tangent space); returns the report."""
    from difftex.scene.files import write_image

    U, mask, seen, dominant, names, report = read_composite(composite)
    write_texture_outputs(out_dir, U, mask, seen, dominant, names, report, bits=cfg.bits, exr=cfg.exr)
    relief = read_relief(composite)
    out_dir = Path(out_dir)
    if relief is None:
        for stale in (HEIGHT, NORMAL):  # of an earlier run with a relief
            (out_dir / stale).unlink(missing_ok=True)
        return report
    heights, texel_size = relief
    write_image(out_dir / HEIGHT, heights[..., None].astype(np.float32))
    write_image(out_dir / NORMAL, normal_map(heights, texel_size), bits=8)
    return report


def write_composite(
    path: str | Path,
    U: np.ndarray,
    mask: np.ndarray,
    seen: np.ndarray,
    dominant: np.ndarray,
    names: list[str],
    report: dict,
    relief: tuple[np.ndarray, float] | None = None,
) -> None:
    """A polygon's composed texture in float (half precision), before quantisation to a PNG.

    The texturing stage writes it; assembly turns it into the per-polygon PNGs and the atlas at
    the configured bit depth, so a change of output format does not redo the texturing.
    ``relief``: the polygon's height field (H, W) in scene units and the texel size, when the
    texturing mapped the photos through one.
    """
    import json

    from difftex.scene.files import write_npz

    extra = {}
    if relief is not None:
        extra = {"heights": np.asarray(relief[0], np.float32), "texel_size": np.array(float(relief[1]))}
    write_npz(
        path,
        texture=np.asarray(U, np.float16),
        mask=np.packbits(mask.ravel()),
        seen=np.packbits(seen.ravel()),
        shape=np.array(seen.shape),
        dominant=dominant.astype(np.int32),
        photos=np.array(names, dtype=str),
        report=np.array(json.dumps(report)),
        **extra,
    )


def read_relief(path: str | Path) -> tuple[np.ndarray, float] | None:
    """(heights (H, W) float32, texel size) of a composite written with a relief, else None (only
    those two members are read: the texture beside them can be hundreds of MB)."""
    from difftex.errors import DifftexError

    try:
        with np.load(path, allow_pickle=False) as d:
            if "heights" not in d.files:
                return None
            return d["heights"].astype(np.float32), float(d["texel_size"])
    except (OSError, ValueError, KeyError) as exc:
        raise DifftexError(f"{path}: unreadable npz ({exc})") from None


def read_composite(path: str | Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, list[str], dict]:
    """(U (H, W, 3) float32, texel mask, seen (H, W) bool, dominant (H, W), photo names, report) of write_composite."""
    import json

    from difftex.errors import DifftexError
    from difftex.scene.files import read_npz

    d = read_npz(path)
    try:
        H, W = (int(v) for v in d["shape"])
        seen = np.unpackbits(d["seen"], count=H * W).astype(bool).reshape(H, W)
        mask = np.unpackbits(d["mask"], count=H * W).astype(bool).reshape(H, W)
        return (
            d["texture"].astype(np.float32),
            mask,
            seen,
            d["dominant"].astype(np.int64),
            [str(x) for x in d["photos"]],
            json.loads(str(d["report"])),
        )
    except (KeyError, ValueError) as exc:
        raise DifftexError(f"{path}: not a difftex composite texture ({exc})") from None
