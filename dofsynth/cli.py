"""The `dofsynth` command line.

Every module in `dofsynth.commands` that defines `register(subparsers)` adds one subcommand;
`register` builds its parser and sets `func=run`, where `run(args) -> int` is the exit status.
"""
from __future__ import annotations

import argparse
import importlib
import pkgutil
import sys

from dofsynth import __version__
from dofsynth import commands


class UserError(Exception):
    """A problem with the user's input: printed as one clear line, exit status 2."""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="dofsynth",
        description=(
            "Synthetic shallow depth-of-field data, the DeepLens way: layered scenes of a "
            "background photo and two foreground cutouts, blurred per plane in linear light "
            "and composited back to front; plus the networks that learn from them."
        ),
        epilog="Run `dofsynth COMMAND --help` for the options of each command.",
    )
    parser.add_argument("--version", action="version", version=f"dofsynth {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for info in sorted(pkgutil.iter_modules(commands.__path__), key=lambda m: m.name):
        module = importlib.import_module(f"dofsynth.commands.{info.name}")
        if hasattr(module, "register"):
            module.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except (UserError, ValueError, FileNotFoundError) as exc:
        print(f"dofsynth {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"dofsynth {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    raise SystemExit(main())
