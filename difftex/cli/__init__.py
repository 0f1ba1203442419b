"""The ``difftex`` command: one sub-command per module in this package.

Each module ``difftex/cli/<name>.py`` defines ``NAME``, ``HELP``, ``add_arguments(parser)`` and
``run(args) -> int``; they are discovered here so that stages can be added without touching this
file. Modules import their heavy dependencies inside ``run`` to keep ``difftex --help`` fast.

Every failure ends in one line on stderr, ``difftex: error: <file>: <problem>`` (exit 2), and
every warning is one line ``difftex: warning: ...``, printed once per process: the workflow
shows these lines on the console (docs/failures.md).
"""

from __future__ import annotations

import argparse
import importlib
import logging
import pkgutil
import sys
import traceback

from difftex import __version__
from difftex.errors import ERROR_PREFIX, WARNING_PREFIX, DifftexError, one_line, os_error_message


def _commands(only: str | None = None) -> list:
    """The command modules; ``only``: just that command's, when it has one (the workflow runs
    ``difftex finish`` once per texture job: importing every
    command's arguments, some of which import numpy and matplotlib, was most of their start-up)."""
    names = [info.name for info in pkgutil.iter_modules(__path__) if not info.name.startswith("_")]
    if only is not None and only.replace("-", "_") in names:
        names = [only.replace("-", "_")]
    mods = []
    for name in names:
        mod = importlib.import_module(f"{__name__}.{name}")
        if hasattr(mod, "NAME") and hasattr(mod, "run"):
            mods.append(mod)
    return sorted(mods, key=lambda m: m.NAME)


def build_parser(argv: list[str] | None = None) -> argparse.ArgumentParser:
    """The parser; with ``argv``, only the named command's sub-parser (all of them for --help)."""
    parser = argparse.ArgumentParser(prog="difftex", description=__doc__.splitlines()[0])
    parser.add_argument(
        "--version", action=_Version, nargs=0, help="print the versions, the torch build and its device"
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    first = next((a for a in argv if not a.startswith("-")), None) if argv else None
    for mod in _commands(first):
        p = sub.add_parser(mod.NAME, help=mod.HELP, description=mod.HELP)
        mod.add_arguments(p)
        p.set_defaults(_run=mod.run)
    return parser


class _Version(argparse.Action):
    """``difftex --version``: difftex, torch and the device the texture stage would use.

    A user on a GPU node checks here that the install found CUDA (torch is imported only here,
    not for ``--help``).
    """

    def __call__(self, parser, namespace, values, option_string=None):
        import torch

        cuda = torch.version.cuda
        if torch.cuda.is_available():
            device = f"cuda ({torch.cuda.get_device_name(0)})"
        else:
            device = "cpu" + (
                " (this torch has CUDA " + cuda + " but sees no GPU)" if cuda else " (CPU-only torch build)"
            )
        print(f"difftex {__version__}\ntorch {torch.__version__}\ndevice: {device}")
        parser.exit()


class _Once(logging.Filter):
    """Pass each distinct message once: several stages of one process may load the same scene,
    and a warning about it is worth one line."""

    def __init__(self) -> None:
        super().__init__()
        self.seen: set[str] = set()

    def filter(self, record: logging.LogRecord) -> bool:
        msg = record.getMessage()
        if msg in self.seen:
            return False
        self.seen.add(msg)
        return True


class _OneLine(logging.Formatter):
    def format(self, record: logging.LogRecord) -> str:
        prefix = ERROR_PREFIX if record.levelno >= logging.ERROR else WARNING_PREFIX
        return prefix + one_line(record.getMessage())


def _warnings_to_stderr() -> logging.Handler:
    """Route the package's log warnings to stderr as ``difftex: warning: ...`` lines."""
    handler = logging.StreamHandler(sys.stderr)
    handler.setLevel(logging.WARNING)
    handler.setFormatter(_OneLine())
    handler.addFilter(_Once())
    logging.getLogger("difftex").addHandler(handler)
    return handler


def main(argv: list[str] | None = None) -> int:
    own_process = argv is None  # the process is this command (not a test or a tool calling main)
    argv = sys.argv[1:] if argv is None else argv
    parser = build_parser(argv)
    args = parser.parse_args(argv)
    if not getattr(args, "_run", None):
        parser.print_help()
        return 1
    if own_process and getattr(sys.modules[args._run.__module__], "REUSE_FREED_MEMORY", False):
        from difftex.cli._memory import reuse_freed_memory

        reuse_freed_memory()
    handler = _warnings_to_stderr()
    try:
        return int(args._run(args) or 0)
    except DifftexError as exc:
        # One line, whatever a library put in the message.
        print(ERROR_PREFIX + one_line(str(exc)), file=sys.stderr)
        return 2
    except OSError as exc:
        # Disk full, permission denied, read-only folder: the OS names the file.
        print(ERROR_PREFIX + os_error_message(exc), file=sys.stderr)
        return 2
    except MemoryError:
        print(
            ERROR_PREFIX + f"{args.command}: out of memory (give the job more memory: run.base_mem_mb)", file=sys.stderr
        )
        return 2
    except KeyboardInterrupt:
        print("difftex: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:  # noqa: BLE001 -- a bug: keep its traceback, but end in the one line
        traceback.print_exc()
        print(
            ERROR_PREFIX + one_line(f"{args.command}: internal error {type(exc).__name__}: {exc} (traceback above)"),
            file=sys.stderr,
        )
        return 3
    finally:
        logging.getLogger("difftex").removeHandler(handler)


if __name__ == "__main__":
    sys.exit(main())
