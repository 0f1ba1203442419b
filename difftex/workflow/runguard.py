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

import atexit
import errno
import fcntl
import json
import logging
import os
import signal
import socket
import sys
import time
from pathlib import Path

from difftex.errors import ERROR_PREFIX, one_line, os_error_message
from difftex.workflow.runlog import INTERRUPTED_LINE, INTERRUPTED_STATUS

LOCK_NAME = Path(".snakemake") / "difftex" / "run.lock"
SNAKEMAKE_LOCKS = Path(".snakemake") / "locks"
SNAKEMAKE_INCOMPLETE = Path(".snakemake") / "incomplete"
TEMP_GLOB = ".*.part*"  # difftex.scene.files.atomic_path's temporary files


def exit_on_interrupt() -> None:
    """For the rest of this process: a Ctrl-C (KeyboardInterrupt) that no handler caught ends it
    with the one interrupted line and status 130, not a traceback and death by SIGINT.

    Snakemake's scheduler catches Ctrl-C while jobs run (the onerror handler then says the
    same); before it runs (while the Snakefile is read or the job graph built) and while it
    stops, the KeyboardInterrupt reaches the top level. Python then prints a traceback and,
    after finalizing, kills itself with SIGINT, so no exit status can be set but by leaving
    at once: the hook flushes the streams and logs and calls ``os._exit``. Snakemake's ``finally``
    blocks (its locks) have run by then, and the kernel releases the run lock.
    """
    if getattr(sys.excepthook, "difftex_interrupt", False):  # a Snakefile read twice in a process
        return
    previous = sys.excepthook

    def hook(exc_type, exc, tb):
        if not issubclass(exc_type, KeyboardInterrupt):
            return previous(exc_type, exc, tb)
        try:
            print(INTERRUPTED_LINE, file=sys.stderr, flush=True)
            sys.stdout.flush()
            logging.shutdown()
        finally:
            os._exit(INTERRUPTED_STATUS)

    hook.difftex_interrupt = True  # type: ignore[attr-defined]
    sys.excepthook = hook


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
    """Snakemake keeps its locks as files (the default backend), which this module can clear."""
    backend = getattr(getattr(workflow, "workflow_settings", None), "persistence_backend", None)
    return backend is None or getattr(backend, "name", str(backend)).lower() == "file"


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
        self.started = time.time()
        # set by the Snakefile's onsuccess/onerror handlers; a real run that ends without either
        # stopped on an error of Snakemake itself (e.g. its metadata on a full disk)
        self.finished = False
        self.interrupted = False  # Ctrl-C (SIGINT) seen
        self.snakemake_error = _LastError()

    def __call__(self, workflow) -> list:
        """Snakemake input-function hook: take the lock on the first call of a real run.
        Returns no inputs."""
        if not self.checked and is_real_run(workflow):
            self.checked = True
            self.acquire(clear_snakemake_locks=_file_backend(workflow))
            self.install_hooks()
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
            redo = remove_incomplete_outputs(self.workdir)
            if stale or redo:
                print(f"difftex: resuming after a run that did not end cleanly (killed or crashed): removed its "
                      f"locks and {redo} incomplete output(s), which are made again", file=sys.stderr, flush=True)
        check_writable(self.results)
        remove_temporary_files(self.results)

    def install_hooks(self) -> None:
        """For the rest of this Snakemake process: note Snakemake's last error and Ctrl-C, and
        report an abnormal end at exit."""
        logging.getLogger("snakemake.logging").addHandler(self.snakemake_error)
        atexit.register(self.at_exit)
        self._note_interrupts()

    def _note_interrupts(self) -> None:
        """Remember a Ctrl-C, then let Snakemake handle it as before (its scheduler turns the
        KeyboardInterrupt into a plain failure, which the failure report must not blame on a job).
        Once the run has ended (``finished``), ignore it: raised while Python joins the threads
        at exit, it would print an "Exception ignored" traceback after the summary."""
        previous = signal.getsignal(signal.SIGINT)
        if not callable(previous):
            return

        def handler(signum, frame):
            if self.finished:  # the run has ended and is printing its summary or exiting
                return None
            self.interrupted = True
            return previous(signum, frame)

        try:
            signal.signal(signal.SIGINT, handler)
        except ValueError:  # not the main thread: no note, the report is only less precise
            pass

    def at_exit(self) -> None:
        """When Snakemake stopped on its own error (no onsuccess/onerror), end the console with
        the jobs' error lines or Snakemake's message as one ``difftex: error:`` line."""
        if self.finished or self.snakemake_error.text is None:
            return
        from difftex.workflow.runlog import abnormal_end_report

        try:
            os.chdir(self.workdir)  # Snakemake has gone back to where it was started
        except OSError:
            pass
        lines = abnormal_end_report(self.results, self.started, self.snakemake_error.text, self.workdir)
        print("\n".join(lines), file=sys.stderr, flush=True)


class _LastError(logging.Handler):
    """Keeps the text of the last error Snakemake logged."""

    def __init__(self) -> None:
        super().__init__(logging.ERROR)
        self.text: str | None = None

    def emit(self, record: logging.LogRecord) -> None:
        try:
            self.text = record.getMessage()
        except Exception:  # noqa: BLE001 -- a log handler must never raise
            pass


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


def remove_incomplete_outputs(workdir: Path) -> int:
    """Delete the outputs Snakemake marked incomplete (jobs that were running when the run died)
    and their markers; only call this while holding the run lock. Returns how many outputs.

    ``--rerun-incomplete`` does this only for the jobs it sees when it first builds the job
    graph, and jobs that depend on a checkpoint (every per-polygon job) are added after that:
    a killed per-polygon job's first output then passes for done while its other outputs are
    missing. Deleting every marked output lets Snakemake see them missing and rerun the jobs.
    Marker names are Snakemake's file backend's: the output path, urlsafe base64, cut into
    '@'-prefixed folder names when longer than a file name may be.
    """
    from base64 import urlsafe_b64decode

    root = workdir / SNAKEMAKE_INCOMPLETE
    if not root.is_dir():
        return 0
    n = 0
    for marker in sorted(p for p in root.rglob("*") if p.is_file()):
        parts = marker.relative_to(root).parts
        try:
            key = urlsafe_b64decode("".join(p.lstrip("@") for p in parts).encode()).decode()
        except (ValueError, UnicodeDecodeError):
            continue  # not a marker (e.g. Snakemake's "migration_underway")
        out = Path(key) if Path(key).is_absolute() else workdir / key
        try:
            if out.is_file() or out.is_symlink():
                out.unlink()
                n += 1
            elif out.is_dir():
                import shutil

                shutil.rmtree(out)
                n += 1
            marker.unlink()
        except OSError as exc:
            stop(os_error_message(exc, out))
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
    """Delete difftex.scene.files's temporary files under ``folder`` (left by jobs killed mid-write).
    Returns how many."""
    n = 0
    if folder.is_dir():
        for f in folder.rglob(TEMP_GLOB):
            if f.is_file():
                f.unlink(missing_ok=True)
                n += 1
    return n
