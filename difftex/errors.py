"""The one exception type users see, and the one-line form of every failure.

A failed command prints ``difftex: error: <file>: <problem>`` on one line and exits 2; a warning
is ``difftex: warning: <file>: <problem>``. The workflow's end-of-run handler looks for exactly
these prefixes in the job logs (difftex/workflow/runlog.py), so they are defined here once.
"""

from __future__ import annotations

import errno

ERROR_PREFIX = "difftex: error: "
WARNING_PREFIX = "difftex: warning: "


class DifftexError(Exception):
    """Bad input or a failed stage; the CLI prints ``difftex: error: <message>`` and exits 2."""


def one_line(text: str) -> str:
    """``text`` with every run of whitespace (newlines included) collapsed to one space."""
    return " ".join(str(text).split())


def os_error_message(exc: OSError, path: object = None) -> str:
    """'<file>: <problem>' for an operating-system error (disk full, permission denied...).

    Args:
        exc: the error; its ``filename`` names the file when the OS call had one.
        path: the file to name when ``exc`` does not (e.g. the final name of an atomic write).

    Returns:
        One line; disk-full and read-only errors get a hint on what to do.
    """
    where = path if path is not None else (exc.filename if exc.filename is not None else "")
    what = exc.strerror or type(exc).__name__
    hints = {
        errno.ENOSPC: "free some space and run the same command again",
        errno.EDQUOT: "free some space and run the same command again",
        errno.EACCES: "the folder is not writable for you",
        errno.EPERM: "the folder is not writable for you",
        errno.EROFS: "the folder is on a read-only file system",
    }
    hint = hints.get(exc.errno)
    msg = f"{what} ({hint})" if hint else what
    return one_line(f"{where}: {msg}" if where != "" else msg)
