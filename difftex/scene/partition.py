"""How the whole-scene stages split a large scene into bounded jobs.

Photo filtering is per photo, so it splits into chunks of photos (contiguous runs of the scene's
image files in name order), merged by a gather that needs only their records. Visibility is per
polygon (each polygon's masks come from its own candidate photos, depth-tested against the whole
proxy), so it splits into spatial tiles of polygons: a tile's job decodes only the photos that see
its polygons, and nearby polygons share most of their photos, so few photos are read by more than
one tile. Both splits are pure functions of the scene's files, so the workflow (which plans the
jobs when it reads the Snakefile) and each job (which finds its share from its number) agree
without a plan file.
"""

from __future__ import annotations

import math

import numpy as np

from difftex.errors import DifftexError


def parts_for(count: int, per_job: int) -> int:
    """Number of jobs for ``count`` items at most ``per_job`` each (at least 1).

    Args:
        count: items (photos or polygons); 0 gives one job, which reports the empty scene itself.
        per_job: the configured bound, >= 1.
    """
    if per_job < 1:
        raise DifftexError(f"a whole-scene job must hold at least 1 item, not {per_job}")
    return max(1, math.ceil(count / per_job))


def part_name(part: int, parts: int) -> str:
    """A part's file-name stem, e.g. ``003-of-012``: the count is in the name, so another split
    (another ``run`` setting) makes other files instead of mixing with stale ones."""
    width = max(3, len(str(parts)))
    return f"{part + 1:0{width}d}-of-{parts:0{width}d}"


def parse_part(text: str) -> tuple[int, int]:
    """``"3/12"`` (1-based, as the job names count) -> (2, 12) (0-based part, parts)."""
    try:
        a, b = (int(x) for x in str(text).split("/"))
    except ValueError:
        raise DifftexError(f"--part {text}: expected PART/PARTS, e.g. 3/12") from None
    if not 1 <= a <= b:
        raise DifftexError(f"--part {text}: PART must be between 1 and PARTS")
    return a - 1, b


def chunk_bounds(count: int, part: int, parts: int) -> tuple[int, int]:
    """[start, stop) of chunk ``part`` when ``count`` items are cut into ``parts`` contiguous
    chunks whose sizes differ by at most one.

    Args:
        count: items, >= 0.
        part: 0-based chunk index, 0 <= part < parts.
        parts: number of chunks, >= 1.
    """
    if not 0 <= part < parts:
        raise DifftexError(f"part {part + 1} of {parts} does not exist")
    return count * part // parts, count * (part + 1) // parts


def photo_chunk(names: list[str], part: int, parts: int) -> list[str]:
    """The photo names of chunk ``part`` of ``parts`` (``names`` in the order of
    :func:`difftex.scene.camera.image_files`)."""
    a, b = chunk_bounds(len(names), part, parts)
    return names[a:b]


def polygon_tiles(centroids: np.ndarray, parts: int) -> list[np.ndarray]:
    """Split polygons into ``parts`` spatial tiles of near-equal size by recursive bisection.

    Each step cuts the polygons' centroids across their longest extent, at the rank that gives
    the two halves sizes in proportion to the tiles each will hold (a k-d split for any number of
    tiles, not only powers of two). Ties are broken by polygon index, so the split is a pure
    function of the proxy.

    Args:
        centroids: (P, 3) polygon centroids.
        parts: number of tiles wanted; more than P gives P tiles of one polygon.
    Returns:
        min(parts, P) arrays of polygon indices (each sorted), in a fixed order; together they
        hold every index once.
    Shape:
        centroids: (P, 3); each tile: (n_i,) with sum n_i = P.
    """
    c = np.asarray(centroids, dtype=np.float64).reshape(-1, 3)
    if len(c) == 0:
        return [np.zeros(0, np.int64)]
    if not np.isfinite(c).all():
        raise DifftexError("polygon centroids must be finite to tile the scene")

    def split(idx: np.ndarray, n: int) -> list[np.ndarray]:
        if n <= 1 or len(idx) <= 1:
            return [np.sort(idx)]
        pts = c[idx]
        axis = int(np.argmax(pts.max(0) - pts.min(0)))
        order = idx[np.lexsort((idx, pts[:, axis]))]
        left = n // 2
        cut = round(len(idx) * left / n)
        return split(order[:cut], left) + split(order[cut:], n - left)

    return split(np.arange(len(c)), min(int(parts), len(c)))


def part_spec(name: str) -> str:
    """A part's file-name stem (:func:`part_name`, ``003-of-012``) as the jobs' ``--part`` value (``3/12``)."""
    try:
        a, b = name.split("-of-")
        return f"{int(a)}/{int(b)}"
    except ValueError:
        raise DifftexError(f"{name}: not a part name (like 003-of-012)") from None
