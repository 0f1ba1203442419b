"""Side-by-side crops of the same polygon region from several methods and the ground truth.

    W=evaluation/out/table1_archive   # after: python evaluation/table1.py --scene data/synth/paper/archive ...
    python evaluation/side_by_side.py --scene data/synth/paper/archive --run difftex=$W/difftex \
        --run texrecon=$W/texrecon --run "MeshLab blend=$W/meshlab-blend" --run MRF=$W/mrf \
        --run average=$W/average --polygon wall00 --crop 0.08,0.3,0.25,0.7 --max-width 1500 \
        --out docs/images/table1_archive_wall00.png

For a person to look at, not a metric: every method's texture is resampled into the ground
truth's frame (the code Table 1 scores with, difftex.evaluation.evaluate.resample_texture), the
same crop (fractions x0,y0,x1,y1 of the ground-truth map) is cut from each and the crops are
written in one row, each under its label. Without ground truth (real scenes), the crops are cut
from the first run's frame and the others are resampled into it.

With ``--view NAME`` (Table 2's held-out photos) the crops are of each run's rendering of the
textured proxy into that held-out camera (``<run>/evaluation/views/NAME_render.png``, written by
``difftex evaluate``), beside the held-out photo itself:

    python evaluation/side_by_side.py --scene ../shared/data/lund-door --view DSC_0005 \
        --run difftex=evaluation/out/table2/lund-door/difftex --run MRF=evaluation/out/table2/lund-door/mrf \
        --crop 0.35,0.3,0.65,0.55 --out docs/images/table2_lund_door_tympanum.png
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

LABEL_H = 22  # pixels of the label strip above each crop
GAP = 6  # pixels between crops


def crop_box(shape: tuple[int, int], fractions: tuple[float, float, float, float]) -> tuple[int, int, int, int]:
    """(y0, y1, x0, x1) pixels of the fractional box (x0, y0, x1, y1) in an (H, W) image."""
    h, w = shape
    fx0, fy0, fx1, fy1 = fractions
    if not (0 <= fx0 < fx1 <= 1 and 0 <= fy0 < fy1 <= 1):
        raise SystemExit(f"side_by_side: --crop {fractions}: need 0 <= x0 < x1 <= 1 and 0 <= y0 < y1 <= 1")
    y0, x0 = round(fy0 * h), round(fx0 * w)
    return y0, max(round(fy1 * h), y0 + 1), x0, max(round(fx1 * w), x0 + 1)


def mosaic(crops: list[tuple[str, np.ndarray]], max_width: int):
    """One row of labelled crops, each scaled (nearest) to fit ``max_width`` in all."""
    from PIL import Image, ImageDraw

    h, w = crops[0][1].shape[:2]
    scale = max(1, (max_width - GAP * (len(crops) - 1)) // (w * len(crops)))
    cw, ch = w * scale, h * scale
    canvas = Image.new("RGB", (len(crops) * cw + GAP * (len(crops) - 1), ch + LABEL_H), "white")
    draw = ImageDraw.Draw(canvas)
    for i, (label, img) in enumerate(crops):
        tile = Image.fromarray((np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8)).resize((cw, ch), Image.NEAREST)
        x = i * (cw + GAP)
        canvas.paste(tile, (x, LABEL_H))
        draw.text((x + 3, 4), label, fill="black")
    return canvas


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", required=True, help="scene folder (its ground_truth/ is used when present)")
    ap.add_argument("--run", action="append", required=True,
                    help="LABEL=results folder, or LABEL=a PNG in the ground truth's frame (repeatable)")
    ap.add_argument("--polygon", help="the polygon whose textures to compare (not with --view)")
    ap.add_argument("--view", help="a held-out photo's name without extension: compare the runs' renderings into it")
    ap.add_argument("--crop", default="0,0,1,1", help="x0,y0,x1,y1 as fractions of the map")
    ap.add_argument("--max-width", type=int, default=1800, help="width of the written image, pixels")
    ap.add_argument("--out", required=True, help="PNG to write")
    args = ap.parse_args(argv)
    if (args.view is None) == (args.polygon is None):
        raise SystemExit("side_by_side: give one of --polygon (textures) or --view (held-out renderings)")
    if args.view is not None:
        return view_crops(args)

    from difftex.evaluation.evaluate import load_textures, resample_texture
    from difftex.geometry.frames import UVFrame
    from difftex.scene.files import read_image, read_json

    runs = []
    for spec in args.run:
        label, _, folder = spec.partition("=")
        if not folder:
            raise SystemExit(f"side_by_side: --run {spec!r}: expected LABEL=FOLDER")
        if folder.lower().endswith(".png"):  # a texture already in the ground truth's frame (variants.py --textures)
            runs.append((label, read_image(folder)))
            continue
        tex = load_textures(folder)
        if args.polygon not in tex:
            raise SystemExit(f"side_by_side: {folder}: no texture of polygon {args.polygon!r}")
        runs.append((label, tex[args.polygon]))
    gt = Path(args.scene) / "ground_truth"
    if (gt / "frames" / f"{args.polygon}.json").is_file():
        frame = UVFrame.from_dict(read_json(gt / "frames" / f"{args.polygon}.json"))
        ref = [("ground truth", read_image(gt / "maps" / f"{args.polygon}.png"))]
    elif all(isinstance(r, np.ndarray) for _, r in runs):
        raise SystemExit(f"side_by_side: {gt}: no ground-truth frame of {args.polygon!r} for the PNG textures")
    else:
        frame, ref = next(pt.frame for _, pt in runs if not isinstance(pt, np.ndarray)), []
    y0, y1, x0, x1 = crop_box(frame.shape, tuple(float(v) for v in args.crop.split(",")))
    for label, pt in runs:
        if isinstance(pt, np.ndarray) and pt.shape[:2] != frame.shape:
            raise SystemExit(f"side_by_side: {label}: a {pt.shape[1]}x{pt.shape[0]} PNG, not the ground-truth "
                             f"frame's {frame.shape[1]}x{frame.shape[0]}")
    crops = [
        (label, (pt if isinstance(pt, np.ndarray) else resample_texture(pt.texture, pt.frame, frame))[y0:y1, x0:x1])
        for label, pt in runs
    ]
    crops += [(label, img[y0:y1, x0:x1]) for label, img in ref]
    write_mosaic(crops, args.max_width, Path(args.out), "texels")
    return 0


def write_mosaic(crops: list[tuple[str, np.ndarray]], max_width: int, out: Path, unit: str) -> None:
    """:func:`mosaic` written to ``out`` through a temporary file (no half-written PNG), and said."""
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(out.stem + ".tmp.png")
    mosaic(crops, max_width).save(tmp)
    tmp.replace(out)
    h, w = crops[0][1].shape[:2]
    print(f"side_by_side: {out} ({len(crops)} crops of {w}x{h} {unit})")


def view_crops(args) -> int:
    """The same crop of every run's rendering into the held-out camera ``args.view``, then the photo.

    Args:
        args: the parsed command line (``view``: the photo's name, with or without its extension).

    Returns:
        0; a missing rendering or renderings of different sizes end the program with one line.
    """
    from difftex.scene.files import read_image

    args.view = Path(args.view).stem
    crops, photo = [], None
    for spec in args.run:
        label, _, folder = spec.partition("=")
        views = Path(folder) / "evaluation" / "views"
        render = views / f"{args.view}_render.png"
        if not render.is_file():
            raise SystemExit(f"side_by_side: {render}: no rendering of view {args.view!r} (run difftex evaluate)")
        crops.append((label, read_image(render)))
        if photo is None and (views / f"{args.view}_photo.png").is_file():
            photo = read_image(views / f"{args.view}_photo.png")
    if photo is not None:
        crops.append(("held-out photo", photo))
    if any(img.shape != crops[0][1].shape for _, img in crops):
        raise SystemExit(f"side_by_side: the renderings of {args.view!r} differ in size")
    y0, y1, x0, x1 = crop_box(crops[0][1].shape[:2], tuple(float(v) for v in args.crop.split(",")))
    write_mosaic([(label, img[y0:y1, x0:x1]) for label, img in crops], args.max_width, Path(args.out), "pixels")
    return 0


if __name__ == "__main__":
    from evaluation.common import run_script

    run_script(main)
