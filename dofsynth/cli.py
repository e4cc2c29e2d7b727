"""The `dofsynth` command line.

Every module in `dofsynth.commands` that defines `register(subparsers)` adds one subcommand;
`register` builds its parser and sets `func=run`, where `run(args) -> int` is the exit status.
"""
from __future__ import annotations

import argparse
import importlib
import pkgutil
import signal
import sys
import threading

from dofsynth import __version__
from dofsynth import commands, progress


class Terminated(BaseException):
    """SIGTERM (what SLURM, systemd and Kubernetes send first), raised in the main thread so
    that a run stops as on Ctrl-C: the lock released, temp files removed, one line printed."""


def _terminate(signum, frame):
    raise Terminated()


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
    _add_common(parser, top=True)
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for info in sorted(pkgutil.iter_modules(commands.__path__), key=lambda m: m.name):
        module = importlib.import_module(f"dofsynth.commands.{info.name}")
        if hasattr(module, "register"):
            module.register(sub)
    for p in _leaf_parsers(sub):
        _add_common(p)
    return parser


def _leaf_parsers(action) -> list[argparse.ArgumentParser]:
    """Every parser under a subparsers action that parses a command's own options."""
    out = []
    for p in dict.fromkeys(action.choices.values()):
        subs = [a for a in p._actions if isinstance(a, argparse._SubParsersAction)]
        out += _leaf_parsers(subs[0]) if subs else [p]
    return out


def _add_common(p: argparse.ArgumentParser, top: bool = False) -> None:
    """The options every command has, with one meaning everywhere (dofsynth.progress); they go
    before the command too (`dofsynth -q verify OUT`): a command's own copy does not reset
    what was given before it."""
    g = p.add_argument_group("output")
    loud = g.add_mutually_exclusive_group()
    unset = {} if top else {"default": argparse.SUPPRESS}
    loud.add_argument("-q", "--quiet", action="store_true", **unset,
                      help="no progress bars and no summaries (errors still print)")
    loud.add_argument("-v", "--verbose", action="store_true", **unset,
                      help="more detail, e.g. a line per finished shard")


# The optional dependencies some commands need, and the extra that installs them.
EXTRAS = {"torch": "train", "webdataset": "train", "tomli_w": "train", "ray": "ray"}


def _missing_extra(exc: ImportError) -> str | None:
    """One line naming the `pip install` that provides a missing optional module, else None."""
    top = (exc.name or "").split(".")[0]
    if top not in EXTRAS:
        return None
    return (f"this command needs {top}, which the base install leaves out: "
            f"pip install 'dofsynth[{EXTRAS[top]}]'")


def _os_error(exc: OSError) -> str:
    """An OSError in one line: what happened and to which file."""
    what = exc.strerror or str(exc)
    files = [f for f in (exc.filename, exc.filename2) if f]
    return f"{what}: {' -> '.join(map(str, files))}" if files else what


def main(argv: list[str] | None = None) -> int:
    """Run one command; every failure ends in one line on stderr and a non-zero status, by one
    rule for every command: 2 for bad input or usage (a bad value or file, a path that exists
    or cannot be written), 1 for a failure while working (a full disk, a dead worker, a check
    that found problems), 130 on Ctrl-C, 143 on SIGTERM. A command that can continue later
    says how (`resume_hint`)."""
    main_thread = threading.current_thread() is threading.main_thread()
    if main_thread:  # first: a signal while the parser imports the commands is handled too
        signal.signal(signal.SIGTERM, _terminate)
    name, again = "dofsynth", ""
    try:
        parser = build_parser()
        args = parser.parse_args(argv)
        if not getattr(args, "func", None):
            parser.print_help()
            return 2
        if args.quiet and args.verbose:
            raise ValueError("-q/--quiet and -v/--verbose: give one of them")
        progress.set_verbosity(args.quiet, args.verbose)
        hint = getattr(args, "resume_hint", None)
        again = f"; {line}" if hint and (line := hint(args)) else ""
        name = f"dofsynth {args.command}"
        return int(args.func(args) or 0)
    except (ValueError, FileNotFoundError) as exc:
        print(f"{name}: error: {exc}", file=sys.stderr)
        return 2
    except ImportError as exc:
        line = _missing_extra(exc)
        if line is None:
            raise
        print(f"{name}: error: {line}", file=sys.stderr)
        return 2
    except (FileExistsError, IsADirectoryError, NotADirectoryError, PermissionError) as exc:
        print(f"{name}: error: {_os_error(exc)}", file=sys.stderr)  # a path given that cannot be used: input
        return 2
    except OSError as exc:
        print(f"{name}: error: {_os_error(exc)}{again}", file=sys.stderr)
        return 1
    except RuntimeError as exc:
        print(f"{name}: error: {exc}{again}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"{name}: interrupted{again}", file=sys.stderr)
        return 130
    except Terminated:
        print(f"{name}: terminated (SIGTERM){again}", file=sys.stderr)
        return 143
    finally:
        if main_thread:
            signal.signal(signal.SIGTERM, signal.SIG_DFL)


if __name__ == "__main__":
    raise SystemExit(main())
