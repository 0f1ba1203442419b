"""Stage parameters: one dataclass per stage, read from a section of a YAML/JSON config file.

The workflow's config/config.yaml holds every section (validated by workflow/schemas); each
stage command reads only its own sections, so a change to one stage's parameters reruns only
that stage and what follows.
"""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

from difftex.errors import DifftexError

T = TypeVar("T")


def from_dict(cls: type[T], data: dict[str, Any] | None, where: str = "") -> T:
    """Build a config dataclass, rejecting unknown keys with a message naming them."""
    data = dict(data or {})
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - names)
    if unknown:
        raise DifftexError(
            f"{where or cls.__name__}: unknown key(s) {', '.join(unknown)} (known: {', '.join(sorted(names))})"
        )
    for f in dataclasses.fields(cls):
        if f.name in data:
            problem = _type_problem(data[f.name], f.default)
            if problem:
                raise DifftexError(f"{where or cls.__name__}: {f.name}: {problem}")
    try:
        return cls(**data)
    except (TypeError, ValueError) as exc:
        raise DifftexError(f"{where or cls.__name__}: {exc}") from None


def _type_problem(value: Any, default: Any) -> str | None:
    """A value of the wrong kind for a scalar key (judged by its default), or None. A string
    where a number belongs would otherwise fail deep inside a stage with a Python error."""
    if value is None or default is None or default is dataclasses.MISSING:
        return None
    if isinstance(default, bool):
        return None if isinstance(value, bool) else f"must be true or false, got {value!r}"
    if isinstance(default, (int, float)):
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            return f"must be a number, got {value!r}"
    if isinstance(default, str) and not isinstance(value, str):
        return f"must be a string, got {value!r}"
    return None


def job_threads() -> int:
    """Threads a whole-scene job may use: OMP_NUM_THREADS, as the workflow sets it from the
    rule's ``threads``; without it, up to 4 of the machine's cores."""
    try:
        n = int(os.environ.get("OMP_NUM_THREADS", "0") or 0)
    except ValueError:
        n = 0
    return max(1, n or min(4, os.cpu_count() or 1))


def read_config(path: str | Path | None) -> dict[str, Any]:
    """The whole config file as a dict ({} when no file is given)."""
    if path is None:
        return {}
    import yaml

    path = Path(path)
    if not path.is_file():
        raise DifftexError(f"{path}: config file not found")
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as exc:
        raise DifftexError(f"{path}: not valid YAML ({str(exc).splitlines()[0]})") from None
    if not isinstance(data, dict):
        raise DifftexError(f"{path}: config must be a mapping of sections")
    return data


def section(path: str | Path | None, name: str, cls: type[T]) -> T:
    data = read_config(path).get(name) or {}
    return from_dict(cls, data, where=f"{path}: section '{name}'" if path else name)


@dataclass(frozen=True)
class TextureConfig:
    """Texture resolution, shared by visibility (texel masks) and texturing (the target level).

    What sets each polygon's texel size (``mode``): a numeric ``density`` (texels per scene
    unit); else ``long_side`` when it is given; else ``density: auto``, per polygon from its
    photos' ground sampling distance (difftex.geometry.density).
    """

    density: str | float | None = "auto"
    long_side: int | None = None  # texels on the longest side of every map (density None)
    density_scale: float = 1.0  # share of the photos' density that auto picks
    gsd_percentile: float = 25.0  # percentile over the polygon's texels of their finest frontal GSD
    max_long_side: int = 4096  # cap on a map's longer side (auto and numeric density)
    min_long_side: int = 16  # floor on a map's longer side (auto)
    max_mb: float = 2500.0  # cap on a polygon's optimization memory, MiB (auto and numeric density)

    def __post_init__(self):
        d = self.density
        if isinstance(d, str):
            if d != "auto":
                raise ValueError(f"density must be 'auto', a number of texels per scene unit or null, got {d!r}")
        elif d is not None:
            if isinstance(d, bool) or not float(d) > 0:
                raise ValueError(f"density must be > 0, got {d}")
        elif self.long_side is None:
            raise ValueError("set density (auto or texels per scene unit) or long_side")
        if self.long_side is not None and not 1 <= int(self.long_side) <= 16384:
            raise ValueError(f"long_side must be in 1..16384, got {self.long_side}")
        if not 0 < float(self.density_scale) <= 4:
            raise ValueError(f"density_scale must be in (0, 4], got {self.density_scale}")
        if not 0 <= float(self.gsd_percentile) <= 100:
            raise ValueError(f"gsd_percentile must be in [0, 100], got {self.gsd_percentile}")
        if not 1 <= int(self.min_long_side) <= int(self.max_long_side) <= 16384:
            raise ValueError("need 1 <= min_long_side <= max_long_side <= 16384")
        if not float(self.max_mb) > 0:
            raise ValueError(f"max_mb must be > 0, got {self.max_mb}")

    @property
    def mode(self) -> str:
        """ "density", "long_side" or "auto": what sets each polygon's texel size."""
        if self.density is not None and self.density != "auto":
            return "density"
        return "long_side" if self.long_side is not None else "auto"


@dataclass(frozen=True)
class FilterConfig:
    blur_ratio: float = 0.3  # drop a photo whose sharpness is below this share of the set's median
    max_angle_deg: float = 80.0  # per polygon, drop photos that see it more obliquely than this
    min_pixels: int = 16  # a photo "sees" a polygon with at least this many pixels at analysis size
    analysis_long_side: int = 640  # id buffers for filtering are computed at this photo size
    sharpness_long_side: int = 1024  # photos are downscaled to this before the Laplacian


@dataclass(frozen=True)
class VisibilityConfig:
    min_texels: int = 16  # a candidate photo must see at least this many texels of the polygon
    max_photos: int | None = None  # keep at most this many photos per polygon (best Q_a first)
    # a photo is a polygon's candidate only where it is among this many best (frontal x resolved)
    # of some texel, or alone sees some; None: every photo that sees the polygon
    texel_candidates: int | None = 24
