"""One building's scene from start to finish: shell, facades, relief, cameras, renders, truth."""

from __future__ import annotations

import dataclasses
import functools
import platform
import time
from pathlib import Path

import numpy as np

from difftex.scene.planar import triangulate_rings
from difftex.synth.camera_model import apply_camera
from difftex.synth.presets import BuildingSpec, SynthConfig

EXPOSURE = 1.0  # linear scale of the reference exposure (ground truth); photos vary around it


def _rngs(seed: int, building_index: int, n: int):
    ss = np.random.SeedSequence([int(seed), int(building_index)])
    return [np.random.default_rng(s) for s in ss.spawn(n)]


def lighting_for(cfg: SynthConfig, rng: np.random.Generator) -> dict:
    az = rng.uniform(0, 2 * np.pi)
    el = np.deg2rad(rng.uniform(35, 60))
    sun_dir = np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])  # towards the sun
    return {
        "sky": [0.85, 0.93, 1.05],
        "sun_dir": sun_dir.tolist(),
        "sun_irradiance": [2.0, 1.9, 1.7] if cfg.sun else [0.0, 0.0, 0.0],
        "max_depth": int(cfg.max_depth),
    }


def build_model(cfg: SynthConfig, spec: BuildingSpec, seed: int, building_index: int):
    """Everything before rendering: shell, layouts, bitmaps, detail, lighting (deterministic)."""
    from difftex.synth.buildings import make_building
    from difftex.synth.detail import build_detail
    from difftex.synth.facades import ground_bitmap, make_layout, paint_face

    r_shell, r_layout, r_paint, r_detail, r_light, r_cam, r_photo = _rngs(seed, building_index, 7)
    building = make_building(spec, r_shell)
    layouts = {f.id: make_layout(f, spec.character, r_layout, cfg.relief_depth, cfg.balconies) for f in building.faces}
    trim = np.clip(np.array([0.62, 0.6, 0.55]) * r_layout.uniform(0.8, 1.15, 3), 0.05, 0.9).tolist()
    for lay in layouts.values():
        lay.style["trim_color"] = trim  # one trim colour per building: painted bands match the relief boxes
    bitmaps = {
        f.id: paint_face(f, layouts[f.id], r_paint, cfg.texture_density, cfg.texture_max_side) for f in building.faces
    }
    model = build_detail(building, layouts, bitmaps, cfg.relief_depth, r_detail, cfg.occluders, cfg.occluder_count)
    lo, hi = building.bounds()
    ground_size = float(max(300.0, 8 * np.linalg.norm(hi - lo)))
    ground = ground_bitmap(r_light, 6.0)
    lighting = lighting_for(cfg, r_light)
    return building, layouts, bitmaps, model, ground, ground_size, lighting, r_cam, r_photo


def run_scene(
    cfg: SynthConfig, spec: BuildingSpec, out: Path, seed: int, building_index: int, progress: bool, preset_name: str
) -> dict:
    import mitsuba
    from rich.console import Console
    from rich.progress import MofNCompleteColumn, Progress

    from difftex.scene.files import write_image, write_json
    from difftex.scene.proxy import Polygon, write_proxy_obj
    from difftex.synth import cameras as cams
    from difftex.synth import render as rd

    timing: dict[str, float] = {}
    t0 = time.perf_counter()
    variant = rd.choose_variant(cfg.variant)
    building, layouts, bitmaps, model, ground, ground_size, lighting, r_cam, r_photo = build_model(
        cfg, spec, seed, building_index
    )
    timing["model_s"] = time.perf_counter() - t0

    # --- cameras ------------------------------------------------------------------------------
    camera = cfg.camera_model()
    train = cams.make_views(building, cfg.views, cfg.street_fraction, r_cam, prefix="img_", suffix=camera.suffix,
                            rings=cfg.drone_rings)
    held = cams.make_views(
        building,
        cfg.held_out_views,
        0.5,
        r_cam,
        prefix="heldout_",
        kind_prefix="heldout",
        azimuth_offset=np.pi / max(cfg.views, 1) + 0.37,
        rings=cfg.drone_rings,
    )
    intr = [
        cams.Intrinsics(1, cfg.width, cfg.height, cfg.width / 2 / np.tan(np.deg2rad(65) / 2), cfg.distortion),
        cams.Intrinsics(2, cfg.width, cfg.height, cfg.width / 2 / np.tan(np.deg2rad(75) / 2), cfg.distortion),
    ]
    intr_by_id = {c.camera_id: c for c in intr}
    for v in train:
        v.R_written, v.t_written = cams.perturb(v.R, v.t, cfg.pose_noise_rot_deg, cfg.pose_noise_trans, r_cam)
        v.gain = float(2.0 ** r_photo.uniform(-cfg.exposure_range, cfg.exposure_range))
        v.wb = tuple(float(x) for x in np.exp(r_photo.normal(0, cfg.white_balance, 3)))

    n_gt = len(building.faces)
    total = len(train) + len(held) + n_gt
    # Not transient: the finished bar stays (as the tqdm bar did, which this replaces), on stderr.
    bar = Progress(*Progress.get_default_columns(), MofNCompleteColumn(), console=Console(stderr=True),
                   disable=not progress)
    advance = functools.partial(bar.advance, bar.add_task(f"synth {spec.name}", total=total))
    bar.start()
    try:

        # --- training photos (occluders in, per-photo exposure) -----------------------------------
        t1 = time.perf_counter()
        scene = rd.build_scene(variant, model, ground, ground_size, lighting, occluders=cfg.occluders)
        canv = {c.camera_id: cams.undistort_canvas(c) for c in intr}
        maps = {c.camera_id: cams.distortion_map(c, canv[c.camera_id]) for c in intr if c.k != 0}
        for i, v in enumerate(train):
            c = intr_by_id[v.camera_id]
            cw, ch = canv[c.camera_id]
            sensor = rd.perspective_sensor(variant, v.R, v.t, c.f, cw, ch, cfg.spp, cfg.sampler)
            lin = rd.render(variant, scene, sensor, cfg.spp, seed=1000 * building_index + i + 7919 * seed)
            if c.k != 0:
                lin = cams.warp(lin, maps[c.camera_id])
            # Only training photos go through the camera; the truth stays the renderer's radiance.
            srgb, jpeg = apply_camera(lin * EXPOSURE, camera, v.gain, v.wb,
                                      np.random.default_rng([seed, building_index, i, 17]))
            _write_photo(out / "images" / v.name, srgb, jpeg)
            advance(1)
        timing["photos_s"] = time.perf_counter() - t1
        timing["per_photo_s"] = timing["photos_s"] / max(len(train), 1)

        # --- sparse points on the detailed facades, seen (not occluded) from the true cameras ------
        t2 = time.perf_counter()
        points = _sample_points(cfg, building, layouts, bitmaps, train, intr_by_id, scene, variant, r_cam)
        cams.write_colmap(out / "sparse" / "0", intr, train, points)
        polygons = [Polygon(id=f.id, outer=f.outer.copy()) for f in building.faces]
        write_proxy_obj(
            out / "proxy.obj", polygons, header=f"difftex synth: building '{spec.name}' ({spec.style}), seed {seed}"
        )
        timing["colmap_s"] = time.perf_counter() - t2
        del scene

        # --- ground truth: occluder-free, reference exposure ---------------------------------------
        t3 = time.perf_counter()
        gt = out / "ground_truth"
        gscene = rd.build_scene(variant, model, ground, ground_size, lighting, occluders=False)
        # The frame must be the one difftex will compute: it takes 'up' from the written cameras (~+z;
        # the exact vector matters for flat roofs, whose e_v comes from up's tiny horizontal part).
        from difftex.scene.camera import load_photos, scene_up

        up = scene_up(load_photos(out / "sparse" / "0", out / "images", check_images=False))
        frames = _render_gt_maps(cfg, building, model, polygons, gscene, variant, gt, advance, up)
        timing["gt_maps_s"] = time.perf_counter() - t3
        t4 = time.perf_counter()
        for i, v in enumerate(held):
            c = intr_by_id[v.camera_id]
            cw, ch = canv[c.camera_id]
            sensor = rd.perspective_sensor(variant, v.R, v.t, c.f, cw, ch, cfg.held_out_spp, cfg.sampler)
            lin = rd.render(variant, gscene, sensor, cfg.held_out_spp, seed=500000 + 1000 * building_index + i)
            if c.k != 0:
                lin = cams.warp(lin, maps[c.camera_id])
            write_image(gt / "views" / "images" / v.name, rd.to_srgb(lin * EXPOSURE))
            ids = polygon_id_image(polygons, v.R, v.t, c)
            write_image(gt / "views" / "polygon_ids" / v.name, ids[..., None].astype(np.float32) / 65535.0, bits=16)
            advance(1)
        cams.write_colmap(gt / "views" / "sparse" / "0", intr, held, None, written=False)
        timing["held_out_s"] = time.perf_counter() - t4
    finally:
        bar.stop()
    del gscene

    write_json(
        gt / "polygons.json",
        {
            "ids": [p.id for p in polygons],
            "polygon_id_encoding": "ground_truth/views/polygon_ids/*.png: 16-bit, value = 1 + index into ids, 0 = no "
            "polygon",
            "frames": {p.id: frames[p.id] for p in polygons},
        },
    )
    timing["total_s"] = time.perf_counter() - t0
    manifest = {
        "generator": "difftex synth",
        "preset": preset_name,
        "seed": int(seed),
        "building_index": int(building_index),
        "building": {
            "name": spec.name,
            "style": spec.style,
            "width": spec.width,
            "depth": spec.depth,
            "height": spec.height,
            "character": spec.character,
            "top": building.top,
            "polygons": [
                {
                    "id": f.id,
                    "kind": f.kind,
                    "vertices": f.outer.round(6).tolist(),
                    "relief_protrusion": model.protrusion[f.id],
                }
                for f in building.faces
            ],
            "occluder_primitives": len(model.occluders),
        },
        "config": cfg.to_dict(),
        "renderer": {
            "mitsuba": mitsuba.__version__,
            "variant": variant,
            "exposure_reference": EXPOSURE,
            "sampler": cfg.sampler,
            "spp": {"photos": rd.effective_spp(cfg.sampler, cfg.spp),
                    "ground_truth_maps": rd.effective_spp(cfg.sampler, cfg.gt_spp),
                    "held_out_views": rd.effective_spp(cfg.sampler, cfg.held_out_spp)},
            "camera_model": dataclasses.asdict(camera),
            "tonemap": _tonemap_note(camera),
        },
        "lighting": lighting,
        "cameras": [
            {
                "camera_id": c.camera_id,
                "model": c.model,
                "width": c.width,
                "height": c.height,
                "f": c.f,
                "k": c.k,
                "render_canvas": list(canv[c.camera_id]),
            }
            for c in intr
        ],
        "views": [
            {
                "name": v.name,
                "kind": v.kind,
                "camera_id": v.camera_id,
                "gain": v.gain,
                "white_balance": list(v.wb),
                "R_true": v.R.tolist(),
                "t_true": v.t.tolist(),
            }
            for v in train
        ],
        "held_out_views": [
            {"name": v.name, "camera_id": v.camera_id, "R": v.R.tolist(), "t": v.t.tolist()} for v in held
        ],
        "points3D": int(len(points[0])) if points else 0,
        "timing": {k: round(float(x), 3) for k, x in timing.items()},
        "machine": {"python": platform.python_version(), "platform": platform.platform()},
    }
    # Timings and the machine differ between runs; keep them out of the deterministic manifest.
    det = {k: v for k, v in manifest.items() if k not in ("timing", "machine")}
    write_json(out / "synth.json", det)
    write_json(
        out / "synth_timing.json",
        {
            "timing": manifest["timing"],
            "machine": manifest["machine"],
            "views": len(train),
            "width": cfg.width,
            "height": cfg.height,
            "spp": cfg.spp,
            "sampler": cfg.sampler,
        },
    )
    if cfg.previews:
        from difftex.synth.preview import write_previews

        write_previews(out, train, intr_by_id, polygons)
    return manifest


def _write_photo(path: Path, srgb: np.ndarray, jpeg: bytes | None) -> None:
    """An 8-bit PNG of ``srgb``, or the camera's JPEG bytes as they are (re-encoding would add loss)."""
    from difftex.scene.files import atomic_path, write_image

    if jpeg is None:
        write_image(path, srgb)
        return
    with atomic_path(path) as tmp:
        tmp.write_bytes(jpeg)


def _tonemap_note(camera) -> str:
    if camera.iso > 0:
        noise = (f"Poisson-Gaussian sensor noise at ISO {camera.iso:g} ({camera.white_electrons:.0f} e- at white, "
                 f"read noise {camera.read_noise:g} e-)")
    else:
        noise = f"additive Gaussian noise {camera.image_noise:g}"
    blur = f", lens blur sigma {camera.lens_blur:g} px" if camera.lens_blur else ""
    store = f"8-bit JPEG quality {camera.jpeg_quality} (4:2:0)" if camera.jpeg_quality else "8-bit PNG"
    return f"photos: linear * gain * white balance{blur}, {noise}, sRGB OETF, {store}; truth: linear, sRGB, 8-bit PNG"


def _render_gt_maps(cfg, building, model, polygons, gscene, variant, gt: Path, advance, up) -> dict:
    from difftex.geometry.frames import texel_mask, uv_frame
    from difftex.scene.files import write_image, write_json
    from difftex.synth import render as rd

    frames = {}
    for k, poly in enumerate(polygons):
        frame = uv_frame(poly, up=up, long_side=cfg.gt_long_side)
        # The camera stands just in front of the relief, so nothing farther out (e.g. another wing
        # of the building) can come between it and the facade.
        standoff = model.protrusion[poly.id] + 0.3
        lin = render_gt_map(cfg, gscene, variant, frame, standoff, seed=900000 + k)
        write_image(gt / "maps" / f"{poly.id}.png", rd.to_srgb(lin))
        write_image(gt / "maps_linear" / f"{poly.id}.exr", lin)
        write_image(gt / "masks" / f"{poly.id}.png", texel_mask(poly, frame).astype(np.float32))
        fd = frame.to_dict()
        fd["standoff"] = standoff
        fd["up"] = np.asarray(up).tolist()
        write_json(gt / "frames" / f"{poly.id}.json", fd)
        frames[poly.id] = fd
        advance(1)
    return frames


def render_gt_map(cfg: SynthConfig, gscene, variant: str, frame, standoff: float, seed: int) -> np.ndarray:
    """One ground-truth map: linear radiance per texel of ``frame`` (reference exposure), seen by
    an orthographic camera ``standoff`` in front of the plane, ``cfg.gt_spp`` samples of
    ``cfg.sampler`` per texel. ``seed`` only changes the Monte Carlo draw (tests compare two)."""
    from difftex.synth import render as rd

    sensor = rd.ortho_sensor(variant, frame, standoff, cfg.gt_spp, cfg.sampler)
    return rd.render(variant, gscene, sensor, cfg.gt_spp, seed=seed) * EXPOSURE


def polygon_id_image(polygons, R, t, intr) -> np.ndarray:
    """Per pixel: 1 + index of the first proxy polygon its ray hits, 0 for none (numpy ray casting).

    Not ``difftex.geometry.raycast`` (Mitsuba) on purpose: this is ground truth, which must not
    come from the code it grades (docs/synth.md: the truth never comes from difftex's own mapping
    code), and float64 Moeller-Trumbore gives the same ids on every CPU, where Mitsuba's LLVM
    kernels change grazing-edge hits between AVX2 and AVX-512 machines (docs/synth.md,
    Determinism). One image per held-out view: speed does not matter here.
    """
    cam = intr.pycolmap()
    H, W = intr.height, intr.width
    yy, xx = np.mgrid[0:H, 0:W].astype(np.float64) + 0.5
    n = np.asarray(cam.cam_from_img(np.stack([xx.ravel(), yy.ravel()], 1)))
    d = np.column_stack([n, np.ones(len(n))]) @ R  # world directions (R^T d_cam)
    C = -R.T @ t
    best = np.full(len(d), np.inf)
    ids = np.zeros(len(d), np.uint16)
    for k, poly in enumerate(polygons):
        o, b1, b2 = poly.plane_basis()
        v2 = poly.to_plane(poly.outer).astype(np.float64)
        tris = triangulate_rings([v2])
        V = o + v2[:, :1] * b1 + v2[:, 1:2] * b2
        for tri in tris:
            p0, p1, p2 = V[tri]
            e1, e2 = p1 - p0, p2 - p0
            pv = np.cross(d, e2)
            det = pv @ e1
            ok = np.abs(det) > 1e-12
            inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
            tv = C - p0
            u = (pv @ tv) * inv
            qv = np.cross(tv, e1)
            v = (d @ qv) * inv
            tt = (qv @ e2) * inv
            hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (tt > 1e-6) & (tt < best)
            best[hit] = tt[hit]
            ids[hit] = k + 1
    return ids.reshape(H, W)


def _sample_points(cfg, building, layouts, bitmaps, views, intr_by_id, scene, variant, rng):
    """Points on plain wall surface (off openings and relief), with their true observations."""
    from difftex.synth import render as rd

    if cfg.points3d <= 0:
        return None
    walls = building.walls
    areas = np.array([w.length * w.eave for w in walls])
    pts, cols = [], []
    tries = 0
    while len(pts) < cfg.points3d and tries < 50 * cfg.points3d:
        tries += 1
        w = walls[rng.choice(len(walls), p=areas / areas.sum())]
        lay = layouts[w.id]
        u, v = rng.uniform(0.2, w.length - 0.2), rng.uniform(0.7, w.eave - 0.6)
        blocked = [(a - 0.05, b - 0.05, c + 0.05, e + 0.05) for a, b, c, e in lay.openings()]
        blocked += [(a - 0.1, vv - 0.3, c + 0.1, vv + 1.1) for a, c, vv in lay.balconies]
        blocked += [(-1, vv - 0.25, w.length + 1, vv + 0.1) for vv in lay.courses]
        if any(a <= u <= c and b <= v <= e for a, b, c, e in blocked):
            continue
        pts.append(w.to3d(np.array([[u, v]]))[0])
        bm = bitmaps[w.id]
        uv = bm.uv(np.array([[u, v]]))[0]
        H, W = bm.pixels.shape[:2]
        cols.append(bm.pixels[min(H - 1, int(uv[1] * H)), min(W - 1, int(uv[0] * W))])
    if not pts:
        return None
    X = np.array(pts)
    rgb = (np.clip(rd.to_srgb(np.array(cols)), 0, 1) * 255).round().astype(np.uint8)
    obs: dict[int, list] = {}
    for i, v in enumerate(views):
        c = intr_by_id[v.camera_id]
        Xc = X @ v.R.T + v.t
        front = Xc[:, 2] > 0.1
        if not front.any():
            continue
        cam = c.pycolmap()
        xy = np.full((len(X), 2), -1.0)
        xy[front] = np.asarray(cam.img_from_cam(Xc[front]))
        inside = front & (xy[:, 0] > 0) & (xy[:, 0] < c.width) & (xy[:, 1] > 0) & (xy[:, 1] < c.height)
        idx = np.nonzero(inside)[0]
        if len(idx) == 0:
            continue
        C = v.center
        dist = np.linalg.norm(X[idx] - C, axis=1)
        hit = rd.ray_hit_distance(variant, scene, np.repeat(C[None], len(idx), 0), X[idx] - C)
        vis = idx[hit > dist - 0.02]
        obs[i] = [(int(p), xy[p].tolist()) for p in vis]
    return X, rgb, obs


def position_image(
    cfg: SynthConfig,
    spec: BuildingSpec,
    seed: int,
    building_index: int,
    R,
    t,
    intr,
    occluders: bool | None = None,
    spp: int = 16,
) -> np.ndarray:
    """World position seen by each pixel of a photo taken with pose (R, t) and ``intr``, ray traced
    by Mitsuba through the same sensor (and distortion warp) as the photos. For tests."""
    from difftex.synth import cameras as cams
    from difftex.synth import render as rd

    variant = rd.choose_variant(cfg.variant)
    occ = cfg.occluders if occluders is None else occluders
    scene = _position_scene(cfg, spec, seed, building_index, occ, variant)
    cw, ch = cams.undistort_canvas(intr)
    sensor = rd.perspective_sensor(variant, R, t, intr.f, cw, ch, spp)
    pos = rd.render(variant, scene, sensor, spp, seed=1)
    if intr.k != 0:
        pos = cams.warp(pos, cams.distortion_map(intr, (cw, ch)))
    return pos


@functools.lru_cache(maxsize=2)
def _position_scene(cfg, spec, seed, building_index, occluders, variant):
    # Tests ask for several views of one scene; painting and loading it once saves seconds each.
    from difftex.synth import render as rd

    _, _, _, model, ground, ground_size, lighting, _, _ = build_model(cfg, spec, seed, building_index)
    return rd.build_scene(
        variant,
        model,
        ground,
        ground_size,
        lighting,
        occluders=occluders,
        integrator={"type": "aov", "aovs": "pp:position"},
    )
