"""Process-wide memory settings of the ``difftex`` command's jobs (glibc's malloc).

Not a command: ``main`` applies :func:`reuse_freed_memory` for the commands that ask for it,
and the per-polygon commands call :func:`give_back_freed_memory` between polygons.
"""

from __future__ import annotations

# glibc's mallopt parameters (malloc.h) and the environment variables that set them too
_M_TRIM_THRESHOLD, _M_MMAP_MAX = -1, -4
_MALLOC_ENV = ("MALLOC_TRIM_THRESHOLD_", "MALLOC_MMAP_MAX_", "MALLOC_MMAP_THRESHOLD_", "MALLOC_TOP_PAD_")


def _user_set_malloc() -> bool:
    """Whether the environment sets any of glibc's malloc parameters (then they are the user's)."""
    import os

    return any(k in os.environ for k in _MALLOC_ENV) or "glibc.malloc." in os.environ.get("GLIBC_TUNABLES", "")


def _libc(name: str, argtypes: list, restype):
    """The C library's function ``name`` with its ctypes signature, or None where it has none
    (not glibc: macOS, musl)."""
    import ctypes

    try:
        fn = getattr(ctypes.CDLL(None), name)
    except (OSError, AttributeError):
        return None
    fn.argtypes, fn.restype = argtypes, restype
    return fn


def reuse_freed_memory() -> bool:
    """Have glibc's malloc keep freed memory for the process's next allocations.

    By default glibc maps each block above a threshold (at most 32 MiB) afresh and unmaps it on
    free, and hands the heap's free top back to the kernel: every new texel-sized tensor, photo
    crop or decoded photo then faults in zeroed pages, much of a texture job's time as kernel
    time. With every block from the heap and no trimming, freed blocks are reused. The cost is a
    higher peak: freed blocks that fit no later request stay with the process until
    :func:`give_back_freed_memory` (docs/optimizer.md, "Time spent outside the arithmetic",
    has both figures). A process-wide
    setting: ``main`` makes it for the commands whose module sets ``REUSE_FREED_MEMORY`` (the
    per-polygon jobs and the filter, which allocate and free photo- and texel-sized arrays over
    and over), only when it runs as the program (not for a test or a tool that calls it), and
    not where the user set glibc's malloc variables or where the C library has no mallopt.

    Returns:
        Whether the setting was made.
    """
    import ctypes

    mallopt = None if _user_set_malloc() else _libc("mallopt", [ctypes.c_int, ctypes.c_int], ctypes.c_int)
    if mallopt is None:
        return False
    # the trim threshold is a C int: the largest, 2 GiB, is "never" for a job's free heap top
    return bool(mallopt(_M_MMAP_MAX, 0)) and bool(mallopt(_M_TRIM_THRESHOLD, 2**31 - 1))


def give_back_freed_memory() -> bool:
    """Return the free pages of every malloc arena to the kernel (glibc's ``malloc_trim(0)``).

    Called between the polygons of a texture job: within a polygon the freed blocks are reused
    (:func:`reuse_freed_memory`), and a job that textures many polygons one after the other does
    not carry one polygon's free, fragmented heap into the next one's peak.

    Returns:
        Whether pages were returned (False also where the C library has no malloc_trim).
    """
    import ctypes

    trim = _libc("malloc_trim", [ctypes.c_size_t], ctypes.c_int)
    return trim is not None and bool(trim(0))
