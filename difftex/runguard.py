"""One workflow run per working directory, and resuming by itself after a crash.

Snakemake locks a working directory with files under .snakemake/locks. A run killed by SIGKILL
or a power cut cannot delete them, and the next run then stops with ``LockException: Directory
cannot be locked`` until the user finds ``--unlock``. Lock files cannot tell a dead run from a
live one; an OS lock can: every real run holds ``fcntl.flock`` on .snakemake/difftex/run.lock,
which the kernel releases when the process ends, however it ends. So a run that gets the flock
knows that no other run of this workflow is alive, and Snakemake's lock files are stale: it
removes them (what ``--unlock`` does) and the temporary files of killed jobs. A run that
cannot get the flock stops with one line naming the run that holds it.

The check runs when Snakemake builds its job graph (an input function of the ``all`` and
``stage_config`` rules), because only then is it known whether this is a real run: a dry run,
``--summary`` or a cluster job (which parses the Snakefile again) takes and clears nothing.
Snakemake takes its own locks right after building the graph, so stale ones are gone by then.
"""

from __future__ import annotations

import errno
import fcntl
import json
import os
import socket
import sys
import time
from pathlib import Path

from difftex.errors import ERROR_PREFIX, one_line, os_error_message

LOCK_NAME = Path(".snakemake") / "difftex" / "run.lock"
SNAKEMAKE_LOCKS = Path(".snakemake") / "locks"
TEMP_GLOB = ".*.part*"  # difftex.io.atomic_path's temporary files


def stop(message: str, code: int = 1) -> None:
    """Print ``difftex: error: <message>`` on one line and end the process (no traceback).

    SystemExit passes through Snakemake's handlers, which catch Exception only; Snakemake still
    releases its own locks on the way out.
    """
    print(ERROR_PREFIX + one_line(message), file=sys.stderr, flush=True)
    raise SystemExit(code)


def is_real_run(workflow) -> bool:
    """True in the Snakemake process that will execute jobs: not a dry run, not --touch, not
    --summary/--dag (no executor), not a job process of a cluster executor."""
    try:
        from snakemake_interface_executor_plugins.settings import ExecMode
    except ImportError:  # pragma: no cover -- Snakemake >= 8 ships it
        return False
    if getattr(workflow, "executor_plugin", None) is None:
        return False
    if getattr(workflow, "dryrun", False) or getattr(workflow, "touch", False):
        return False
    return getattr(workflow, "exec_mode", None) == ExecMode.DEFAULT


def _file_backend(workflow) -> bool:
    backend = getattr(getattr(workflow, "workflow_settings", None), "persistence_backend", None)
    return backend is None or str(getattr(backend, "value", backend)).lower() == "file"


class RunGuard:
    """The working directory's run lock, held for the life of this Snakemake process.

    Args:
        results: the results folder of this scene (checked for writability, cleaned of
            temporary files of killed jobs).
        workdir: the working directory (Snakemake's, i.e. the current one by default).
    """

    def __init__(self, results: str | Path, workdir: str | Path | None = None) -> None:
        self.results = Path(results)
        self.workdir = Path(workdir) if workdir is not None else Path.cwd()
        self.fd: int | None = None
        self.checked = False

    def __call__(self, workflow) -> list:
        """Snakemake input-function hook: take the lock on the first call of a real run.
        Returns no inputs."""
        if not self.checked and is_real_run(workflow):
            self.checked = True
            self.acquire(clear_snakemake_locks=_file_backend(workflow))
        return []

    def acquire(self, clear_snakemake_locks: bool = True) -> None:
        """Take the lock or stop; then clean what a dead run left behind."""
        path = self.workdir / LOCK_NAME
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o666)
        except OSError as exc:
            stop(os_error_message(exc, self.workdir))
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as exc:
            os.close(fd)
            if exc.errno not in (errno.EWOULDBLOCK, errno.EAGAIN, errno.EACCES):
                stop(os_error_message(exc, path))
            stop(f"{self.workdir}: {describe_holder(path)} is using this folder; wait for it to end "
                 "(or stop it), then run the same command again")
        self.fd = fd
        os.ftruncate(fd, 0)
        os.write(fd, json.dumps(holder_info()).encode() + b"\n")
        if clear_snakemake_locks:
            stale = remove_stale_locks(self.workdir)
            if stale:
                print(f"difftex: resuming: removed {stale} stale lock file(s) of a run that did not end "
                      "cleanly (killed or crashed); incomplete outputs are redone", file=sys.stderr, flush=True)
        check_writable(self.results)
        remove_temporary_files(self.results)


def holder_info() -> dict:
    return {
        "pid": os.getpid(),
        "host": socket.gethostname(),
        "started": time.strftime("%Y-%m-%d %H:%M:%S"),
        "command": " ".join(sys.argv)[:300],
    }


def describe_holder(path: Path) -> str:
    """'another difftex run (pid 123 on host, started ...)' from the lock file's content."""
    try:
        info = json.loads(path.read_text().splitlines()[0])
        return f"another difftex run (pid {info['pid']} on {info['host']}, started {info['started']})"
    except (OSError, ValueError, KeyError, IndexError):
        return "another difftex run"


def remove_stale_locks(workdir: Path) -> int:
    """Delete Snakemake's lock files (only call this while holding the run lock). Returns how
    many there were."""
    lockdir = workdir / SNAKEMAKE_LOCKS
    if not lockdir.is_dir():
        return 0
    n = 0
    for f in lockdir.glob("*.lock"):
        try:
            f.unlink()
            n += 1
        except FileNotFoundError:
            pass
        except OSError as exc:
            stop(os_error_message(exc, f))
    return n


def check_writable(folder: Path) -> None:
    """Stop with one line when ``folder`` cannot be created or written (read-only results)."""
    try:
        folder.mkdir(parents=True, exist_ok=True)
        probe = folder / f".difftex-write-test.{os.getpid()}"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as exc:
        stop(os_error_message(exc, folder))


def remove_temporary_files(folder: Path) -> int:
    """Delete difftex.io's temporary files under ``folder`` (left by jobs killed mid-write).
    Returns how many."""
    n = 0
    if folder.is_dir():
        for f in folder.rglob(TEMP_GLOB):
            if f.is_file():
                f.unlink(missing_ok=True)
                n += 1
    return n
