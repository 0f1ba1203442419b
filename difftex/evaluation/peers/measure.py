"""A peer program run as a measured child process: its wall time, and the CPU time and peak memory of
its process tree (``run_measured``); the same figures for a phase run in this process (``measure_self``).

Shared by the peer driver (difftex.evaluation.peers.run) and the peers it runs (texrecon, MeshLab).
"""

from __future__ import annotations

import json
import os
import resource
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

from difftex.errors import DifftexError


@dataclass
class Phase:
    """Wall and CPU seconds and peak resident memory of one phase."""

    wall_s: float = 0.0
    cpu_s: float = 0.0
    peak_rss_mib: float = 0.0
    notes: dict = field(default_factory=dict)


class measure_self:
    """Context manager: a Phase for work done in this process.

    CPU is this process's user + system time; the peak is the process's resident high-water
    mark at the end of the phase (Linux cannot reset it, so it includes earlier phases).
    """

    def __enter__(self) -> Phase:
        self.phase = Phase()
        self._t = time.perf_counter()
        self._c = _self_cpu()
        return self.phase

    def __exit__(self, *exc) -> None:
        self.phase.wall_s = time.perf_counter() - self._t
        self.phase.cpu_s = _self_cpu() - self._c
        self.phase.peak_rss_mib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _self_cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


# The peer is started by a small launcher process (a bare interpreter, about 10 MB) that waits for
# it and reports getrusage(RUSAGE_CHILDREN): CPU of the peer and every descendant it waited for,
# and the peak RSS of the largest. Starting the peer from difftex directly would not do: Linux
# records the parent's memory high-water mark in the child's peak when it execs (difftex with
# torch loaded is ~1 GB), so every peer would seem to need at least that.
_LAUNCHER = """
import json, os, resource, sys
pid = os.posix_spawnp(sys.argv[2], sys.argv[2:], os.environ)
_, status = os.waitpid(pid, 0)
ru = resource.getrusage(resource.RUSAGE_CHILDREN)
with open(sys.argv[1], "w") as fh:
    json.dump({"cpu_s": ru.ru_utime + ru.ru_stime, "peak_rss_kib": ru.ru_maxrss}, fh)
code = os.waitstatus_to_exitcode(status)
sys.exit(128 - code if code < 0 else code)
"""


def run_measured(cmd: list[str], log: Path, timeout_s: float, env: dict | None = None, cwd: Path | None = None,
                 what: str = "peer") -> Phase:
    """Run ``cmd`` with stdout and stderr to ``log``; the Phase of its whole process tree.

    Args:
        cmd: the program and its arguments.
        log: file that receives the program's output.
        timeout_s: the program's process group is killed after this many seconds.
        what: the program's name for the error message.
    Returns:
        wall seconds, CPU seconds (user + system of the program and its waited-for descendants)
        and the peak resident memory of the largest of them (MiB).
    Raises:
        DifftexError: one line naming the program, the exit status or the time-out, and the log.
    """
    exe = cmd[0] if os.sep in cmd[0] else shutil.which(cmd[0], path=(env or os.environ).get("PATH"))
    if exe is None:
        raise DifftexError(f"{cmd[0]}: {what} program not found on PATH")
    usage = log.absolute().with_name(log.name + ".rusage.json")
    t0 = time.perf_counter()
    with open(log, "wb") as fh:
        # A new session: on a time-out the whole group (launcher, xvfb-run, Xvfb, MeshLab) is killed.
        p = subprocess.Popen([sys.executable, "-I", "-S", "-c", _LAUNCHER, str(usage), exe, *cmd[1:]], stdout=fh,
                             stderr=subprocess.STDOUT, env=env, cwd=cwd, start_new_session=True)
        try:
            rc = p.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait()
            raise DifftexError(f"{what} timed out after {timeout_s:.0f} s (log: {log})") from None
    wall = time.perf_counter() - t0
    if rc != 0 or not usage.is_file():
        raise DifftexError(f"{what} failed with exit status {rc}: {_last_line(log)} (log: {log})")
    ru = json.loads(usage.read_text())
    usage.unlink()
    return Phase(wall_s=wall, cpu_s=float(ru["cpu_s"]), peak_rss_mib=ru["peak_rss_kib"] / 1024.0)


def _last_line(log: Path) -> str:
    lines = [ln.strip() for ln in log.read_text(errors="replace").splitlines() if ln.strip()]
    return lines[-1][:200] if lines else "no output"
