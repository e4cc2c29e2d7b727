"""Ctrl-C and SIGTERM as exceptions, and the record that one came.

The command line (dofsynth.cli) turns both signals into `Interrupted` / `Terminated`, raised in
the main thread. Python can lose such an exception: C code that clears any error around a call
into Python (an attribute or dict lookup), a finalizer. So every stop signal is also noted here
(`note`), and long loops call `check()` at points where raising is safe (the generation pool
between messages): a stop that was lost on its way is raised there, within a second.
Standard library only: the earliest stages may import it.
"""
from __future__ import annotations

import signal


class Terminated(BaseException):
    """SIGTERM (what SLURM, systemd and Kubernetes send first), raised in the main thread so
    that a run stops as on Ctrl-C: the lock released, temp files removed, one line printed."""


class Interrupted(KeyboardInterrupt):
    """Ctrl-C as raised here. A subclass on purpose: CPython remembers a bare KeyboardInterrupt
    that escaped code it ran for an extension (an import's PyRun_*) and, at exit, kills itself
    with SIGINT, even when the interrupt was handled; it checks the exact type."""


_noted: list[int] = []  # stop signals received and not yet answered by a stopped run


def exception(signum: int) -> BaseException:
    return Interrupted() if signum == signal.SIGINT else Terminated()


def note(signum: int) -> None:
    """A stop signal came (called by the handler, before it raises)."""
    _noted.append(signum)


def answered() -> None:
    """The run has stopped (or starts afresh): nothing is pending any more."""
    _noted.clear()


def check() -> None:
    """Raise the stop of a signal that was noted but whose exception never arrived."""
    if _noted:
        raise exception(_noted[-1])
