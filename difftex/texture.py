"""Final composition of a polygon's texture, hole filling, the texel source map, and the outputs.

The composition streams the candidate photos one at a time at the target resolution:
U(t) = sum_k w_k(t) I^_k(t) / sum_k w_k(t), with I^_k the photo mapped into texel space (through
its brightness transfer when histogram matching is on) and w_k any per-photo weight field: the
optimized weights, or a baseline's.
"""

from __future__ import annotations

import colorsys
import zlib
from pathlib import Path
from typing import Callable

import numpy as np
import torch
import torch.nn.functional as F

from difftex.optimize import MappedPhoto, PolygonInput, build_samplers, map_photo, pick_device


def compose_from_photos(inp: PolygonInput, weight_of: Callable[[int, MappedPhoto], torch.Tensor | None],
                        device="cpu", samplers=None) -> tuple[np.ndarray, np.ndarray]:
    """(U (H, W, 3), weight sum (H, W)) at the target frame; ``weight_of(n, mapped)`` gives photo n's (H, W) weights."""
    device = torch.device(device) if not isinstance(device, torch.device) else device
    samplers = samplers if samplers is not None else build_samplers(inp, device)
    H, W = inp.frame.shape
    acc = torch.zeros(3, H, W, device=device)
    wsum = torch.zeros(H, W, device=device)
    for n in sorted(samplers):
        mp = map_photo(inp, n, inp.frame, samplers[n], inp.texel_mask, device)
        if mp is None:
            continue
        w = weight_of(n, mp)
        if w is None:
            continue
        w = w.to(device) * mp.visible
        acc += mp.colour * w[None]
        wsum += w
    U = acc / wsum.clamp_min(1e-12)[None]
    U = torch.where(wsum[None] > 0, U, torch.zeros_like(U))
    return U.permute(1, 2, 0).cpu().numpy(), wsum.cpu().numpy()


def fill_holes(img: np.ndarray, known: np.ndarray, levels: int = 16) -> np.ndarray:
    """Fill unknown texels from their neighbours by push-pull (masked pyramid averaging).

    Smooth and fast at 2048^2; skimage's biharmonic inpainting would take minutes at that size
    and nearest-neighbour filling leaves streaks. Known texels are returned unchanged.
    """
    known = np.asarray(known, bool)
    if known.all() or not known.any():
        return img.copy()
    x = torch.from_numpy(np.ascontiguousarray(img, dtype=np.float32)).permute(2, 0, 1)[None]
    m = torch.from_numpy(known.astype(np.float32))[None, None]
    pyr = [(x * m, m)]
    for _ in range(levels):
        c, w = pyr[-1]
        if min(c.shape[-2:]) <= 1 or bool((w > 0).all()):
            break
        pyr.append((F.avg_pool2d(c, 2, ceil_mode=True), F.avg_pool2d(w, 2, ceil_mode=True)))
    c, w = pyr[-1]
    est = c / w.clamp_min(1e-8)
    if not bool((w > 0).all()):  # coarsest level still has gaps: use the global mean there
        mean = (c.sum((2, 3)) / w.sum((2, 3)).clamp_min(1e-8))[:, :, None, None]
        est = torch.where(w > 0, est, mean.expand_as(est))
    for c, w in reversed(pyr[:-1]):
        up = F.interpolate(est, size=c.shape[-2:], mode="bilinear", align_corners=False)
        own = c / w.clamp_min(1e-8)
        a = w.clamp(0, 1)
        est = a * own + (1 - a) * up
    out = est[0].permute(1, 2, 0).numpy()
    res = img.astype(np.float32).copy()
    res[~known] = out[~known]
    return res


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


def finish_texture(U: np.ndarray, weight_sum: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, dict]:
    """Fill the polygon's unseen texels (and the margin outside it, so bilinear lookups at its
    border never fetch black), and describe what was filled."""
    seen = (weight_sum > 0) & mask
    filled_in_polygon = mask & ~seen
    out = fill_holes(U, seen) if seen.any() else U.copy()
    info = {
        "texels": int(mask.sum()),
        "seen_texels": int(seen.sum()),
        "coverage": float(seen.sum() / max(mask.sum(), 1)),
        "filled_texels": int(filled_in_polygon.sum()),
        "fill": "push-pull from neighbouring seen texels" if filled_in_polygon.any() else None,
        "filled_outside_polygon": True,
    }
    return out, info


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


def dominant_from_slots(idx: np.ndarray, W: np.ndarray) -> np.ndarray:
    """Dominant photo per texel from a slot layout (-1 where no weight)."""
    j = W.argmax(0)
    d = np.take_along_axis(idx, j[None], 0)[0]
    return np.where(W.max(0) > 0, d, -1)


def compose_slots(inp: PolygonInput, idx: np.ndarray, W: np.ndarray, device="cpu") -> tuple[np.ndarray, np.ndarray]:
    """Texture from optimized slot weights (photo weights summed over the slots holding them)."""
    idx_t = torch.from_numpy(idx.astype(np.int64))
    W_t = torch.from_numpy(W.astype(np.float32))

    def weight_of(n, mp):
        return (W_t * (idx_t == n)).sum(0)

    return compose_from_photos(inp, weight_of, device=pick_device(device) if isinstance(device, str) else device)
