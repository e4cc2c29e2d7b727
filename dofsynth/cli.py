"""The `dofsynth` command line.

Every module in `dofsynth.commands` that defines `register(subparsers)` adds one subcommand;
`register` builds its parser and sets `func=run`, where `run(args) -> int` is the exit status.
"""
from __future__ import annotations

import _thread
import argparse
import importlib
import pkgutil
import signal
import sys
import threading

from dofsynth import __version__
from dofsynth import commands, progress, stops


_pending: list[int] = []   # a stop signal kept back from where raising is unsafe (`_unsafe`)
_closing: list[bool] = []  # set while main ends: a signal then changes nothing


def _stop(signum, frame):
    """Ctrl-C and SIGTERM as exceptions in the main thread (Interrupted, Terminated), noted in
    dofsynth.stops first. One that lands where raising is unsafe (`_unsafe`: inside an import,
    a finalizer) is kept and raised by the next import statement outside any import
    (`_on_import`), once the command line is parsed, or when `_again` finds the main thread
    out of it (every 50 ms), whichever comes first."""
    if _closing:
        return
    stops.note(signum)
    if _unsafe(frame):
        _pending.append(signum)
        threading.Timer(0.05, _again, (signum,)).start()
        return
    _pending.clear()
    raise stops.exception(signum)


def _again(signum: int) -> None:
    """Deliver a kept stop signal to the main thread again, unless it was raised meanwhile."""
    if _pending and not _closing:
        _thread.interrupt_main(signum)


def _unsafe(frame) -> bool:
    """Whether an exception raised at `frame` could be lost or leave the import system broken:
    anywhere inside an import (the import machinery and the module bodies it runs: a library
    importing its parts may catch the error, or fail in its own way, e.g. a TypeError from a
    half-imported module), or in a finalizer (__del__), whose exceptions Python ignores."""
    while frame is not None:
        code = frame.f_code
        if code.co_name == "__del__" or code.co_filename.startswith("<frozen importlib"):
            return True
        frame = frame.f_back
    return False


def _on_import(event: str, args) -> None:
    """Audit hook: a kept stop signal is raised by the next import statement that is not
    itself inside an import (before that import starts)."""
    if _pending and event == "import" and not _unsafe(sys._getframe(1)):
        signum = _pending[-1]
        _pending.clear()
        raise stops.exception(signum)


_hooked: list[bool] = []


def _interrupted_by(exc: BaseException) -> BaseException | None:
    """The KeyboardInterrupt or Terminated behind an error (an extension module whose import a
    signal interrupted fails with ImportError("initialization failed"), a class body's
    __set_name__ with RuntimeError), or the stop itself; else None."""
    while exc is not None:
        if isinstance(exc, (KeyboardInterrupt, stops.Terminated)):
            return exc
        exc = exc.__cause__ or exc.__context__
    return None


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
    _closing.clear()
    stops.answered()
    if main_thread:  # first: a signal while the parser imports the commands is handled too
        if not _hooked:
            sys.addaudithook(_on_import)
            _hooked.append(True)
        old = {s: signal.signal(s, _stop) for s in (signal.SIGTERM, signal.SIGINT)
               if s == signal.SIGTERM or signal.getsignal(s) is signal.default_int_handler}
    name, again = "dofsynth", ""
    try:
        # the parser imports every command (numpy, OpenCV): Ctrl-C and SIGTERM wait until it is
        # built, then stop the run here, never inside the import machinery's callbacks
        # (the entry point, dofsynth.__main__, holds them from its first line already)
        held = {signal.SIGINT, signal.SIGTERM}
        if main_thread:
            signal.pthread_sigmask(signal.SIG_BLOCK, held)
        try:
            parser = build_parser()
        finally:
            if main_thread:  # a signal held since the entry's imports is raised here
                signal.pthread_sigmask(signal.SIG_UNBLOCK, held)
        args = parser.parse_args(argv)
        if not getattr(args, "func", None):
            parser.print_help()
            return 2
        if args.quiet and args.verbose:
            raise ValueError("-q/--quiet and -v/--verbose: give one of them")
        progress.set_verbosity(args.quiet, args.verbose)
        if _pending:  # a stop kept during the imports, none of which came after it
            _on_import("import", ())
        hint = getattr(args, "resume_hint", None)
        again = f"; {line}" if hint and (line := hint(args)) else ""
        name = f"dofsynth {args.command}"
        status = int(args.func(args) or 0)
        stops.check()  # a stop whose exception was lost on its way still ends the run as a stop
        return status
    except BaseException as exc:  # SystemExit (argparse, --help) goes on as it is
        if isinstance(exc, SystemExit):
            raise
        return _failed(name, again, exc)
    finally:
        _closing.append(True)
        _pending.clear()
        if main_thread:
            for s, handler in old.items():
                signal.signal(s, handler if s == signal.SIGINT else signal.SIG_DFL)


def _failed(name: str, again: str, exc: BaseException) -> int:
    """The one line and the status of a failed run (the rule of `main`); an error that a
    signal caused (Python wraps an exception raised inside an import, a __set_name__, ...)
    counts as that signal. Anything else unexpected goes on, with its traceback."""
    stop = _interrupted_by(exc)
    if stop is not None:
        return _stopped(name, again, stop)
    if isinstance(exc, (ValueError, FileNotFoundError)):
        print(f"{name}: error: {exc}", file=sys.stderr)
        return 2
    if isinstance(exc, ImportError):
        line = _missing_extra(exc)
        if line is None:
            raise exc
        print(f"{name}: error: {line}", file=sys.stderr)
        return 2
    if isinstance(exc, (FileExistsError, IsADirectoryError, NotADirectoryError, PermissionError)):
        print(f"{name}: error: {_os_error(exc)}", file=sys.stderr)  # a path given that cannot be used: input
        return 2
    if isinstance(exc, OSError):
        print(f"{name}: error: {_os_error(exc)}{again}", file=sys.stderr)
        return 1
    if isinstance(exc, RuntimeError):
        print(f"{name}: error: {exc}{again}", file=sys.stderr)
        return 1
    raise exc


def _stopped(name: str, again: str, stop: BaseException) -> int:
    """The one line and the status of a run stopped by Ctrl-C (130) or SIGTERM (143). A stop
    that interrupted a library's own clean-up (a `with` block's close) can leave an object
    whose finalizer then fails when it is collected, at exit: such "Exception ignored"
    tracebacks are consequences of the stop, so they are silenced for the rest of the run."""
    sys.unraisablehook = _after_stop
    stops.answered()
    if isinstance(stop, stops.Terminated):
        print(f"{name}: terminated (SIGTERM){again}", file=sys.stderr)
        return 143
    print(f"{name}: interrupted{again}", file=sys.stderr)
    return 130


def _after_stop(unraisable) -> None:
    """sys.unraisablehook once a run was stopped: finalizer errors are not reported."""


if __name__ == "__main__":
    raise SystemExit(main())
