"""Noise of real photos next to synthetic ones, and render noise next to camera noise.

    python evaluation/photo_noise.py                       # real scenes + data/synth/survey
    python evaluation/photo_noise.py --render-noise        # + the render-vs-camera table (minutes)

Three tables go to evaluation/results/photo_noise.md (and .json), with the command and date:

1. Photo noise (``difftex.synth.noise_level.noise_sigma``: Immerkaer's estimator on the flattest
   unclipped 32x32 tiles), in 8-bit levels, of the shared real scenes' photos and of synthetic
   photos, at full resolution and box-downsampled 2x and 4x (towards the texel scale). Synthetic:
   the old setting (16 spp, independent sampler, additive noise 0.004, PNG), rendered here for a
   few photos of the survey's first building, and the rendered survey scenes.
2. (--render-noise) For one survey photo: the noise the camera's *sensor* adds (two sensor draws
   on one render) and the noise the *renderer* leaves (two render seeds, no sensor noise), per
   sampler and spp; both after exposure and lens blur, in sRGB floats before 8-bit quantisation and
   JPEG (which would floor both at the quantisation's own noise); exact differences, RMS and robust
   (1.4826 MAD) std.
"""

from __future__ import annotations

import argparse
import datetime
import json
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

REAL = ("herzjesu-p8", "lund-door", "sceaux-castle")
SCALES = (1, 2, 4)
OLD = dict(sampler="independent", spp=16, iso=0.0, image_noise=0.004, lens_blur=0.0, jpeg_quality=0)


def _levels(images, scales=SCALES) -> dict:
    """Median (and range) over images of the flat-tile noise, 8-bit levels, per downsampling."""
    from difftex.synth.noise_level import box_downsample, noise_sigma

    per = {k: [] for k in scales}
    for img in images:
        for k in scales:
            per[k].append(255 * noise_sigma(box_downsample(img, k)))
    return {k: (float(np.median(v)), float(np.min(v)), float(np.max(v)), len(v)) for k, v in per.items()}


def _read(paths):
    from difftex.scene.files import read_image

    for p in paths:
        yield read_image(p)[..., :3]


def _photos(folder: Path, every: int = 1) -> list[Path]:
    exts = {".jpg", ".jpeg", ".png"}
    return sorted(p for p in folder.iterdir() if p.suffix.lower() in exts)[::every]


def old_setting_photos(out: Path, views: int) -> list[Path]:
    """A few photos of the survey's first building with the old setting (rendered once, cached)."""
    from difftex.synth import generate, get_preset

    cfg = get_preset("survey")
    if not (out / "synth.json").is_file():
        generate(cfg, out, seed=0, progress=False, buildings=[cfg.buildings[0].name], views=views,
                 held_out_views=1, heldout_spp=4, gt_spp=4, gt_long_side=32, points3d=0, previews=False,
                 pose_noise_rot_deg=0.0, pose_noise_trans=0.0, **OLD)
    scene = out if (out / "images").is_dir() else out / cfg.buildings[0].name
    return _photos(scene / "images")


def render_noise_rows(samplers: list[tuple[str, int]], view_index: int = 1) -> list[dict]:
    """Camera noise and render noise in one survey photo (first building, one drone view)."""
    from difftex.synth import cameras as cams
    from difftex.synth import render as rd
    from difftex.synth.camera_model import expose, lens_blur, sensor_noise, srgb_encode
    from difftex.synth.noise_level import box_downsample
    from difftex.synth.pipeline import build_model
    from difftex.synth.presets import get_preset

    cfg = get_preset("survey")
    variant = rd.choose_variant(cfg.variant)
    building, _, _, model, ground, gsize, light, r_cam, _ = build_model(cfg, cfg.buildings[0], 0, 0)
    v = cams.make_views(building, 8, 0.0, r_cam, prefix="img_", rings=cfg.drone_rings)[view_index]
    scene = rd.build_scene(variant, model, ground, gsize, light, occluders=True)
    f = cfg.width / 2 / np.tan(np.deg2rad(65) / 2)
    camera = cfg.camera_model()

    def render(sampler, spp, seed):
        sensor = rd.perspective_sensor(variant, v.R, v.t, f, cfg.width, cfg.height, spp, sampler)
        return rd.render(variant, scene, sensor, spp, seed=seed)

    def optics(lin):
        return lens_blur(expose(lin, 1.0, (1.0, 1.0, 1.0)), camera.lens_blur)

    def sensor(lin, seed):
        return srgb_encode(sensor_noise(optics(lin), camera.white_electrons, camera.read_noise,
                                        np.random.default_rng(seed)))

    def stats(diff):
        out = {}
        for k in SCALES:
            d = box_downsample(diff, k) / np.sqrt(2)  # a difference of two draws has twice the variance
            out[k] = (255 * float(np.sqrt(np.mean(d**2))), 255 * 1.4826 * float(np.median(np.abs(d))))
        return out

    rows = []
    ref_s, ref_n = samplers[-1]
    ref = render(ref_s, ref_n, 1)
    rows.append({"what": f"camera sensor (ISO {camera.iso:g}, {camera.white_electrons:.0f} e- at white)",
                 "noise": stats(sensor(ref, 1) - sensor(ref, 2))})
    for s, n in samplers:
        a = ref if (s, n) == (ref_s, ref_n) else render(s, n, 1)
        b = render(s, n, 2)
        rows.append({"what": f"render, {s} {rd.effective_spp(s, n)} spp",
                     "noise": stats(srgb_encode(optics(a)) - srgb_encode(optics(b)))})
    return rows


def _fmt(stats: dict) -> str:
    return " | ".join(f"{m:.2f} ({lo:.2f}-{hi:.2f})" for m, lo, hi, _ in (stats[k] for k in SCALES))


def write_report(path: Path, argv: list[str], rows: list[tuple[str, str, dict]], rn: list[dict] | None) -> str:
    lines = [
        "# Photo noise: real photos, synthetic photos, render vs camera",
        "",
        f"Command: `python evaluation/photo_noise.py {' '.join(argv)}`, {datetime.date.today().isoformat()}.",
        "",
        "Flat-region noise std in 8-bit levels (`difftex.synth.noise_level.noise_sigma`: Immerkaer's "
        "estimator on the flattest 10 % of unclipped 32x32 tiles), median over the photos (min-max), at full "
        "resolution and box-downsampled 2x and 4x. Where texture survives the flat-tile selection (real photos "
        "downsampled, busy synthetic facades) the figure is an upper bound: white noise would halve per 2x.",
        "",
        "| photos | n | size | 1x | 2x | 4x |",
        "|---|---|---|---|---|---|",
    ]
    for name, size, st in rows:
        lines.append(f"| {name} | {st[1][3]} | {size} | " + _fmt(st).replace(" | ", " | ") + " |")
    if rn:
        lines += [
            "",
            "Render noise vs camera noise in one survey photo (building 1, a drone view, 800x600, after exposure "
            "and 0.5 px lens blur, sRGB before 8-bit quantisation and JPEG): the camera row is two sensor draws on "
            "one render, a render row two render seeds without sensor noise; 8-bit levels, RMS / robust std "
            "(1.4826 MAD), per downsampling.",
            "",
            "| noise of | 1x RMS / robust | 2x | 4x |",
            "|---|---|---|---|",
        ]
        for r in rn:
            lines.append(f"| {r['what']} | " + " | ".join(f"{r['noise'][k][0]:.2f} / {r['noise'][k][1]:.2f}"
                                                        for k in SCALES) + " |")
    text = "\n".join(lines) + "\n"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return text


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--shared", type=Path, default=REPO.parent / "shared" / "data", help="real scenes' folder")
    ap.add_argument("--survey", type=Path, default=REPO / "data" / "synth" / "survey", help="rendered survey")
    ap.add_argument("--every", type=int, default=20, help="measure every n-th survey photo (default 20)")
    ap.add_argument("--old-views", type=int, default=6, help="photos rendered with the old setting")
    ap.add_argument("--work", type=Path, default=REPO / "data" / "synth" / "photo_noise_old")
    ap.add_argument("--render-noise", action="store_true", help="also the render-vs-camera table (minutes)")
    ap.add_argument("--out", type=Path, default=REPO / "evaluation" / "results" / "photo_noise.md")
    args = ap.parse_args(argv)

    rows = []
    for name in REAL:
        paths = _photos(args.shared / name / "images")
        first = next(_read(paths[:1]))
        rows.append((f"real: {name}", f"{first.shape[1]}x{first.shape[0]}", _levels(_read(paths))))
        print(rows[-1][0], _fmt(rows[-1][2]), flush=True)
    old = old_setting_photos(args.work, args.old_views)
    rows.append(("synthetic, old setting (independent 16 spp, additive 0.004, PNG)", "800x600", _levels(_read(old))))
    print(rows[-1][0], _fmt(rows[-1][2]), flush=True)
    samplers = [("independent", 16), ("ldsampler", 16), ("ldsampler", 64), ("ldsampler", 256)]
    rn = render_noise_rows(samplers) if args.render_noise else None
    scenes = sorted(p for p in args.survey.iterdir() if (p / "synth.json").is_file()) if args.survey.is_dir() else []
    for scene in scenes:
        man = json.loads((scene / "synth.json").read_text())
        spp = man["renderer"].get("spp", {}).get("photos", man["config"]["spp"])
        label = f"synthetic survey: {scene.name} ({man['config']['sampler']} {spp} spp, ISO {man['config']['iso']:g})"
        rows.append((label, f"{man['config']['width']}x{man['config']['height']}",
                     _levels(_read(_photos(scene / "images", args.every)))))
        print(rows[-1][0], _fmt(rows[-1][2]), flush=True)
    text = write_report(args.out, argv, rows, rn)
    args.out.with_suffix(".json").write_text(json.dumps({"photos": [{"name": n, "size": s, "levels": st}
                                                                   for n, s, st in rows], "render_noise": rn},
                                                                 indent=1))
    print(text)
    return 0


if __name__ == "__main__":
    from evaluation.common import run_script

    run_script(main)
