"""The command keeps freed memory for its next allocations (difftex.cli.reuse_freed_memory):
a large block freed and allocated again is not faulted in afresh, unless the user set glibc's
malloc variables. Each case runs in its own process (the setting is process-wide)."""

from __future__ import annotations

import os
import platform
import subprocess
import sys

import pytest

pytestmark = pytest.mark.skipif(platform.libc_ver()[0] != "glibc", reason="glibc's mallopt only")

# Allocates and writes a 48 MiB block with the C library's malloc twice (numpy would ask the
# kernel for huge pages, torch does not); prints whether the setting was made and the minor page
# faults of the second round (the first grows the heap either way). 48 MiB is above the largest
# block glibc's default ever takes from its heap (32 MiB).
PROBE = """
import ctypes, resource, sys
from difftex.cli._memory import reuse_freed_memory
made = reuse_freed_memory() if sys.argv[1] == "on" else False
libc = ctypes.CDLL(None)
libc.prctl(41, 1, 0, 0, 0)  # PR_SET_THP_DISABLE: 4 KiB pages, where the kernel would give huge ones
libc.malloc.restype, libc.malloc.argtypes = ctypes.c_void_p, [ctypes.c_size_t]
libc.free.argtypes = [ctypes.c_void_p]
n = 48 << 20
def touch():
    p = libc.malloc(n)
    ctypes.memset(p, 1, n)
    libc.free(p)
touch()
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
touch()
print(made, resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""
PAGES = (48 << 20) // 4096  # pages of the block


def _probe(mode: str, **env: str) -> tuple[bool, int]:
    clean = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_") and k != "GLIBC_TUNABLES"}
    out = subprocess.run(
        [sys.executable, "-c", PROBE, mode], env={**clean, **env}, capture_output=True, text=True, check=True
    ).stdout.split()
    return out[0] == "True", int(out[1])


def test_a_freed_block_is_reused_without_new_page_faults():
    made, faults = _probe("on")
    assert made
    assert faults < PAGES // 20
    made, faults = _probe("off")  # glibc's default: the block is mapped afresh and faulted in
    assert not made
    assert faults > PAGES // 2


@pytest.mark.parametrize(
    "env", [{"MALLOC_MMAP_THRESHOLD_": "131072"}, {"GLIBC_TUNABLES": "glibc.malloc.trim_threshold=131072"}]
)
def test_the_users_malloc_variables_are_left_as_they_are(env):
    made, faults = _probe("on", **env)
    assert not made
    assert faults > PAGES // 2


def test_other_glibc_tunables_do_not_turn_the_setting_off():
    made, _ = _probe("on", GLIBC_TUNABLES="glibc.pthread.rseq=0")
    assert made


class _Command:
    """A stand-in command module whose run does nothing (``REUSE_FREED_MEMORY`` as given)."""

    def __init__(self, name: str, reuse: bool):
        self.NAME, self.HELP, self.__name__ = name, name, f"tests._command_{name}"
        if reuse:
            self.REUSE_FREED_MEMORY = True

        def run(args):
            return 0

        run.__module__ = self.__name__
        self.run = run

    def add_arguments(self, parser):
        pass


@pytest.mark.parametrize("reuse", [True, False])
def test_main_makes_the_setting_for_the_commands_that_ask_and_only_as_the_program(reuse, monkeypatch):
    import difftex.cli as cli
    import difftex.cli._memory as memory

    cmd = _Command("job", reuse)
    calls = []
    monkeypatch.setitem(sys.modules, cmd.__name__, cmd)
    monkeypatch.setattr(memory, "reuse_freed_memory", lambda: calls.append(1) or True)
    monkeypatch.setattr(cli, "_commands", lambda only=None: [cmd])
    monkeypatch.setattr(sys, "argv", ["difftex", "job"])
    assert cli.main() == 0  # as the program: its arguments from the command line
    assert calls == ([1] if reuse else [])
    assert cli.main(["job"]) == 0  # called by a tool or a test: never
    assert calls == ([1] if reuse else [])


def test_the_per_polygon_commands_and_the_filter_ask_for_the_setting():
    import importlib

    for name in ("texture", "optimize", "initialize", "filter"):
        assert importlib.import_module(f"difftex.cli.{name}").REUSE_FREED_MEMORY is True
    assert not hasattr(importlib.import_module("difftex.cli.assemble"), "REUSE_FREED_MEMORY")


def test_freed_pages_go_back_to_the_kernel_between_polygons():
    """malloc_trim after a polygon: the freed heap the setting keeps is returned, so resident
    memory falls back (the next polygon's peak does not sit on this one's free heap)."""
    probe = """
import ctypes, sys
from difftex.cli._memory import give_back_freed_memory, reuse_freed_memory
assert reuse_freed_memory()
libc = ctypes.CDLL(None)
libc.prctl(41, 1, 0, 0, 0)  # PR_SET_THP_DISABLE
libc.malloc.restype, libc.malloc.argtypes = ctypes.c_void_p, [ctypes.c_size_t]
libc.free.argtypes = [ctypes.c_void_p]
def rss_kb():
    return int(next(l for l in open("/proc/self/status") if l.startswith("VmRSS")).split()[1])
n = 256 << 20
p = libc.malloc(n); ctypes.memset(p, 1, n); libc.free(p)
kept = rss_kb()
print(give_back_freed_memory(), kept - rss_kb())
"""
    clean = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_") and k != "GLIBC_TUNABLES"}
    out = subprocess.run([sys.executable, "-c", probe], env=clean, capture_output=True, text=True, check=True)
    returned, freed_kb = out.stdout.split()
    assert returned == "True"
    assert int(freed_kb) > 200 << 10  # most of the 256 MiB block
