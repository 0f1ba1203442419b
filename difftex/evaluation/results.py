"""A results folder as the evaluation reads it, and the evaluation's config.

A results folder ``R`` holds ``R/textures/<pid>/texture.png`` (with ``source.npz`` and
``report.json``) per polygon and the polygons' frames in ``R/visibility/<pid>.npz`` (or the folder
``R/visibility.txt`` names). difftex.evaluation.evaluate scores it; difftex.evaluation.views
renders it into held-out cameras.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from difftex.errors import DifftexError
from difftex.geometry.frames import UVFrame
from difftex.layout import REPORT, TEXTURE, Results, visibility_file

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class EvaluateConfig:
    """The ``evaluate:`` config section."""

    lpips: str = "auto"  # auto | lpips | stlpips | none
    # folder holding classic LPIPS's weight files (piq's lpips_weights.pt, torchvision's
    # vgg16-397923af.pth); None: the torch hub cache (perceptual.lpips_weight_files)
    lpips_weights: str | None = None
    render_long_side: int = 768  # held-out views are rendered and compared at this long side
    error_maps: bool = True  # write per-polygon error maps (PNG) beside the metrics
    views: bool = True  # also score renders into held-out views (real: holdout.json; synthetic: ground_truth/views)
    device: str = "cpu"  # LPIPS device

    def __post_init__(self):
        if self.lpips not in ("auto", "lpips", "stlpips", "none"):
            raise ValueError(f"lpips must be auto, lpips, stlpips or none, got {self.lpips!r}")
        if not 32 <= int(self.render_long_side) <= 8192:
            raise ValueError(f"render_long_side must be in 32..8192, got {self.render_long_side}")


# --------------------------------------------------------------------------------------------
# Reading a results folder


@dataclass(eq=False)
class PolygonTexture:
    polygon_id: str
    texture: np.ndarray  # (H, W, 3)
    frame: UVFrame
    mask: np.ndarray  # (H, W) texel mask
    report: dict
    folder: Path


def visibility_dir(results: Path) -> Path:
    """R/visibility, or the folder named by R/visibility.txt (method folders share one)."""
    res = Results(results)
    if res.visibility_link.is_file():
        return Path(res.visibility_link.read_text().strip())
    return res.visibility_dir


def load_textures(results: str | Path) -> dict[str, PolygonTexture]:
    """Every polygon texture of a results folder with its UV frame (from the visibility file)."""
    from difftex.geometry.visibility import load_visibility
    from difftex.scene.files import read_image, read_json

    results = Path(results)
    tdir = Results(results).textures_dir
    if not tdir.is_dir():
        raise DifftexError(f"{results}: no textures/ folder (run the workflow or a baseline first)")
    vdir = visibility_dir(results)
    out = {}
    for sub in sorted(p for p in tdir.iterdir() if (p / TEXTURE).is_file()):
        vpath = visibility_file(vdir, sub.name)
        if not vpath.is_file():
            raise DifftexError(f"{vpath}: visibility file of textured polygon '{sub.name}' is missing")
        vis = load_visibility(vpath)
        tex = read_image(sub / TEXTURE)
        if tex.shape[:2] != vis.frame.shape:
            raise DifftexError(
                f"{sub / TEXTURE}: {tex.shape[1]}x{tex.shape[0]} texels, its frame says "
                f"{vis.frame.width}x{vis.frame.height}"
            )
        rep = read_json(sub / REPORT) if (sub / REPORT).is_file() else {}
        out[sub.name] = PolygonTexture(sub.name, tex, vis.frame, vis.texel_mask, rep, sub)
    if not out:
        raise DifftexError(f"{tdir}: no polygon textures ({TEXTURE}) in it")
    return out


def _lpips_plan(cfg: EvaluateConfig) -> tuple[str | None, str | None]:
    """(LPIPS network to compute, "lpips" or "stlpips", or None; label of the column when nothing
    is computed).

    Resolved once per evaluation, so that missing weights give one warning line, not one per
    polygon or view: "auto" without classic LPIPS's weight files says once that it reports ST-LPIPS.
    """
    from difftex.evaluation import perceptual

    if cfg.lpips == "none":
        return None, "none"
    kind, label = perceptual.lpips_source(cfg.lpips, cfg.lpips_weights)
    if kind is None:
        log.warning("LPIPS (%s) %s", cfg.lpips, label)
        return None, label
    if cfg.lpips == "auto" and kind == "stlpips":
        log.warning("%s", perceptual.lpips_fallback_note(cfg.lpips_weights))
    return kind, None
