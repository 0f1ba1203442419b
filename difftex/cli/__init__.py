"""The ``difftex`` command: one sub-command per module in this package.

Each module ``difftex/cli/<name>.py`` defines ``NAME``, ``HELP``, ``add_arguments(parser)`` and
``run(args) -> int``; they are discovered here so that stages can be added without touching this
file. Modules import their heavy dependencies inside ``run`` to keep ``difftex --help`` fast.
"""

from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys

from difftex import __version__
from difftex.errors import DifftexError


def _commands() -> list:
    mods = []
    for info in pkgutil.iter_modules(__path__):
        if info.name.startswith("_"):
            continue
        mod = importlib.import_module(f"{__name__}.{info.name}")
        if hasattr(mod, "NAME") and hasattr(mod, "run"):
            mods.append(mod)
    return sorted(mods, key=lambda m: m.NAME)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="difftex", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=f"difftex {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for mod in _commands():
        p = sub.add_parser(mod.NAME, help=mod.HELP, description=mod.HELP)
        mod.add_arguments(p)
        p.set_defaults(_run=mod.run)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "_run", None):
        parser.print_help()
        return 1
    try:
        return int(args._run(args) or 0)
    except DifftexError as exc:
        # One line, whatever a library put in the message.
        print("difftex: error: " + " ".join(str(exc).split()), file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("difftex: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
