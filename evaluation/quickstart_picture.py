"""The quick start's picture: one wall of the bundled example, as a photo shows it (an occluder in
front), as it is (the ground truth) and as difftex textures it.

    .venv/bin/snakemake --cores all                      # the bundled example, default settings
    .venv/bin/python evaluation/quickstart_picture.py    # then this, in the repository's root

reads data/synth/tiny (the scene) and results/tiny (difftex's run on it) and writes
docs/images/quickstart.png. The committed picture is of a run with the default settings, whose
texels match the photos' density (240x140 texels on the wall it shows, about 1 minute on 2
cores with the scene's generation); after ``--config preset=fast`` the texture has a quarter of
that density (60x35 texels), and the windows are blurred.

The wall and the photo are chosen, unless given (--polygon, --photo), as the pair where a wall
looks largest in a photo that sees all of it: in the bundled example a street-level photo
straight at a facade, with a tree and a lamp post in front of it. Every panel is shown at the
same height; the photo is a crop of the wall's bounding box (a small margin around it), the
texture is resampled into the ground truth's frame (as Table 1 scores it).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

REPO = Path(__file__).resolve().parents[1]
HEIGHT = 260  # pixels of each panel's image
LABEL_H = 26  # pixels of the label strip above each panel
GAP = 8  # pixels between panels
MARGIN = 0.06  # of the wall's projected size, around the photo's crop


def wall_in_photo(frame, photo) -> tuple[float, tuple[int, int, int, int]] | None:
    """(projected area in pixels, crop box x0, y0, x1, y1) of the frame's rectangle in the photo,
    or None when a corner lies behind the camera or outside the photo."""
    from difftex.geometry.frames import texel_to_pixel

    tx = np.array([0.0, frame.width, frame.width, 0.0])
    ty = np.array([0.0, 0.0, frame.height, frame.height])
    pix, depth = texel_to_pixel(frame, photo, tx, ty)
    if not (np.isfinite(pix).all() and (depth > 0).all()):
        return None
    x, y = pix[:, 0], pix[:, 1]
    if x.min() < 0 or y.min() < 0 or x.max() > photo.width or y.max() > photo.height:
        return None
    area = 0.5 * abs(float(np.dot(x, np.roll(y, 1)) - np.dot(y, np.roll(x, 1))))  # shoelace
    mx, my = MARGIN * (x.max() - x.min()), MARGIN * (y.max() - y.min())
    box = (max(0, int(x.min() - mx)), max(0, int(y.min() - my)),
           min(photo.width, int(np.ceil(x.max() + mx))), min(photo.height, int(np.ceil(y.max() + my))))
    return area, box


def choose(scene: Path, polygons: list[str], photos, polygon: str | None, photo: str | None):
    """(polygon id, photo, crop box): the given ones, or the wall that looks largest in a photo
    that sees all of it."""
    from difftex.errors import DifftexError
    from difftex.geometry.frames import UVFrame
    from difftex.scene.files import read_json

    if polygon is not None and polygon not in polygons:
        raise DifftexError(f"polygon {polygon!r} has no ground truth and texture (have: {', '.join(polygons)})")
    if photo is not None and photo not in {p.name for p in photos}:
        raise DifftexError(f"{scene}: no registered photo {photo!r}")
    best = None
    for pid in [polygon] if polygon else polygons:
        frame = UVFrame.from_dict(read_json(scene / "ground_truth" / "frames" / f"{pid}.json"))
        if polygon is None and abs(float(frame.normal[2])) > 0.5:
            continue  # a roof: no occluder stands in front of it
        for ph in photos:
            if photo is not None and ph.name != photo:
                continue
            seen = wall_in_photo(frame, ph)
            if seen is not None and (best is None or seen[0] > best[0]):
                best = (seen[0], pid, ph, seen[1])
    if best is None:
        raise DifftexError(f"{scene}: no photo sees all of {polygon or 'any wall'}"
                           f"{'' if photo is None else ' in ' + photo}")
    return best[1:]


def panel(img: np.ndarray, label: str, font):
    """``img`` scaled to HEIGHT pixels high (Lanczos), under its label."""
    from PIL import Image, ImageDraw

    tile = Image.fromarray((np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8))
    tile = tile.resize((max(1, round(tile.width * HEIGHT / tile.height)), HEIGHT), Image.LANCZOS)
    out = Image.new("RGB", (tile.width, HEIGHT + LABEL_H), "white")
    out.paste(tile, (0, LABEL_H))
    ImageDraw.Draw(out).text((2, 3), label, fill="black", font=font)
    return out


def make_picture(scene: str | Path = REPO / "data" / "synth" / "tiny", results: str | Path = REPO / "results" / "tiny",
                 polygon: str | None = None, photo: str | None = None):
    """The picture (a PIL image) and a one-line description of what it shows.

    Args:
        scene: a synthetic scene folder (its ground_truth/ and photos).
        results: difftex's results folder of a run on it.
        polygon, photo: the wall and the photo to show (default: :func:`choose`).
    """
    from PIL import Image, ImageFont

    from difftex.errors import DifftexError
    from difftex.evaluation.evaluate import load_textures, resample_texture
    from difftex.geometry.frames import UVFrame
    from difftex.scene.files import read_image, read_json
    from difftex.scene.loading import load_scene

    scene, results = Path(scene), Path(results)
    gt = scene / "ground_truth"
    if not (gt / "frames").is_dir():
        raise DifftexError(f"{scene}: no ground_truth/frames (a scene made by difftex synth is needed)")
    textures = load_textures(results)
    polygons = sorted(p for p in textures if (gt / "frames" / f"{p}.json").is_file())
    if not polygons:
        raise DifftexError(f"{results}: no texture of a polygon with ground truth in {scene}")
    photos = load_scene(scene).photos
    pid, ph, (x0, y0, x1, y1) = choose(scene, polygons, photos, polygon, photo)
    frame = UVFrame.from_dict(read_json(gt / "frames" / f"{pid}.json"))
    truth = read_image(gt / "maps" / f"{pid}.png")
    tex = textures[pid]
    ours = resample_texture(tex.texture, tex.frame, frame)
    crop = read_image(ph.image_path)[y0:y1, x0:x1]
    font = ImageFont.load_default(size=17)
    tw, th = tex.texture.shape[1], tex.texture.shape[0]
    panels = [panel(crop, f"a photo ({x1 - x0}x{y1 - y0} px)", font),
              panel(truth, "ground truth", font),
              panel(ours, f"difftex ({tw}x{th} texels)", font)]
    canvas = Image.new("RGB", (sum(p.width for p in panels) + GAP * (len(panels) - 1), panels[0].height), "white")
    x = 0
    for p in panels:
        canvas.paste(p, (x, 0))
        x += p.width + GAP
    what = (f"{pid} of {scene.name}: {ph.name} cropped to the wall ({x1 - x0}x{y1 - y0} px), the ground truth, "
            f"difftex's {tw}x{th}-texel texture from {results}")
    return canvas, what


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="data/synth/tiny", help="the synthetic scene (default: the bundled example)")
    ap.add_argument("--results", default="results/tiny", help="difftex's results folder of a run on it")
    ap.add_argument("--polygon", help="the wall to show (default: the one a photo shows largest)")
    ap.add_argument("--photo", help="the photo to crop, e.g. img_0015.png (default: the one showing the wall largest)")
    ap.add_argument("--out", default="docs/images/quickstart.png", help="PNG to write")
    args = ap.parse_args(argv)
    from PIL import Image

    img, what = make_picture(args.scene, args.results, args.polygon, args.photo)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(out.stem + ".tmp.png")
    # 256 colours, no dithering: a quarter of the bytes (150 KB, not 580), no visible loss here
    img.quantize(256, method=Image.Quantize.FASTOCTREE, dither=0).save(tmp, optimize=True)
    tmp.replace(out)
    print(f"quickstart_picture: {out} ({img.width}x{img.height}, {out.stat().st_size // 1024} KB): {what}")
    return 0


if __name__ == "__main__":
    from evaluation.common import run_script

    run_script(main)
