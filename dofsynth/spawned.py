"""The first code a spawned generation worker runs, before any heavy import.

A spawn child unpickles its Process object (the target and its arguments) before it runs
anything: if the target lived in a module that imports numpy, OpenCV and the renderer, a
parent killed during those seconds would leave the worker (and the multiprocessing resource
tracker it keeps open) running with parent 1. So the target is `main` here, in a top-level
module (a module of dofsynth.generate would import that package's heavy __init__ first) that
imports the standard library only, and the real work comes as one pickle (`payload`: a
function and its arguments) that is unpickled, with its imports, only after the worker is
bound to its parent: a parent-death signal (Linux; elsewhere a thread watching the parent's
pid), a shared flock on the run's workers lock, and SIGINT ignored (Ctrl-C is the parent's).
"""
from __future__ import annotations

import fcntl
import os
import pickle
import signal
import sys
import threading
import time

_PR_SET_PDEATHSIG = 1


def die_with(parent_pid: int) -> None:
    """End this process as soon as `parent_pid` is no longer its parent."""
    if sys.platform.startswith("linux"):
        import ctypes

        try:
            ctypes.CDLL("libc.so.6").prctl(_PR_SET_PDEATHSIG, signal.SIGKILL)
        except (OSError, AttributeError):
            pass
    if os.getppid() != parent_pid:  # the parent died before the signal was armed
        os._exit(1)

    def watch():
        while os.getppid() == parent_pid:
            time.sleep(0.5)
        os._exit(1)

    threading.Thread(target=watch, daemon=True, name="dofsynth-parent-watch").start()


def hold_shared(lock_path: str | None):
    """A shared flock on the run's workers lock, held until this process ends (its fd)."""
    if lock_path is None:
        return None
    fd = os.open(lock_path, os.O_RDWR | os.O_CREAT, 0o644)
    fcntl.flock(fd, fcntl.LOCK_SH)
    return fd


def main(conn, parent_pid: int, lock_path: str | None, payload: bytes) -> None:
    """Bind this worker to its parent, then run `fn(conn, *args)` of `payload`."""
    die_with(parent_pid)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # discards a Ctrl-C pending since the spawn
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
    lock_fd = hold_shared(lock_path)  # kept open (and so held) for the process's life
    fn, args = pickle.loads(payload)  # the heavy imports happen here
    fn(conn, *args)
    del lock_fd
