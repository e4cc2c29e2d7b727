"""Locks on a data set folder `OUT`, so two runs never write into it at once.

`OUT/.lock` (fcntl.flock): a whole run or a merge holds it exclusively (its pid inside); the
`--shards A:B` runs hold it shared, each plus `OUT/.lock.part-A-B` exclusively, and refuse a
live overlapping range. A lock file left by a killed run is not a lock (the kernel drops flock
locks with their process), so it never blocks a later run.

A run's worker processes hold `<its lock>.workers` shared while they live (dofsynth.generate.pool).
Taking an exclusive lock refuses while such a file is held: workers of a killed run that are
still alive would otherwise write into OUT beside the new run.
"""
from __future__ import annotations

import fcntl
import os
import re
from pathlib import Path

LOCK_NAME = ".lock"


class OutputInUseError(ValueError):
    """Another run holds the output folder's lock."""


class OutputLock:
    """`OUT/.lock` (or `OUT/<name>`): a non-blocking fcntl.flock, exclusive (a whole run or a
    merge; the holder's pid inside) or `shared` (the `--shards A:B` runs, which share OUT with
    each other but never with a whole run or a merge).

    An exclusive holder removes the file on release; a shared holder removes it only if it can
    then lock it exclusively (it was the last one). A lock file left by a killed run is not a
    lock (the kernel drops flock locks with their process), so it never blocks a later run.
    On a shared file system across machines this needs flock support there (NFSv4, Lustre
    mounted with `-o flock`, BeeGFS, GPFS); elsewhere it protects within one machine only.
    """

    def __init__(self, out: str | os.PathLike, name: str = LOCK_NAME, shared: bool = False):
        self.out = Path(out)
        self.path = self.out / name
        self.shared = shared
        self.fd: int | None = None

    def acquire(self) -> "OutputLock":
        self.out.mkdir(parents=True, exist_ok=True)
        mode = fcntl.LOCK_SH if self.shared else fcntl.LOCK_EX
        while True:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
            try:
                fcntl.flock(fd, mode | fcntl.LOCK_NB)
            except BlockingIOError:
                holder = os.read(fd, 64).decode(errors="replace").strip()
                os.close(fd)
                raise OutputInUseError(self._busy(holder)) from None
            if _same_file(self.path, fd):  # the holder we raced with may have unlinked it
                break
            os.close(fd)
        self.fd = fd
        if not self.shared:
            alive = [p.name for p in self._workers_locks() if _held_at_all(p)]
            if alive:
                self.release()
                raise OutputInUseError(f"{self.out}: worker processes of an earlier run are still alive and may write "
                                       f"into this folder ({', '.join(alive)} is held); wait a few seconds for them to "
                                       "end, or find and stop them (e.g. `fuser " + str(self.out / alive[0]) + "`)")
            os.ftruncate(fd, 0)
            os.write(fd, f"{os.getpid()}\n".encode())
            os.fsync(fd)
        return self

    @property
    def workers_path(self) -> Path:
        """The lock file the holder's worker processes hold shared while they live."""
        return self.path.with_name(self.path.name + ".workers")

    def _workers_locks(self) -> list[Path]:
        """The workers' lock files this lock must find free: its own; for the whole folder's
        lock, every run's (ranges included)."""
        if self.path.name == LOCK_NAME:
            return sorted(self.out.glob(f"{LOCK_NAME}*.workers"))
        return [self.workers_path]

    def _busy(self, holder: str) -> str:
        if holder:
            who = f"another dofsynth run (pid {holder})"
        else:
            ranges = sorted(p.name for p in self.out.glob(f"{LOCK_NAME}.part-*"))
            who = "dofsynth --shards runs" + (f" ({', '.join(ranges[:4])})" if ranges else "")
        return (f"{self.out}: {who} {'is' if holder else 'are'} writing into this folder (lock {self.path}); "
                "wait for it to finish or choose another --out")

    def release(self) -> None:
        if self.fd is None:
            return
        try:
            if self.shared:
                try:  # the last shared holder removes the file
                    fcntl.flock(self.fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                    if _same_file(self.path, self.fd):
                        self.path.unlink(missing_ok=True)
                except BlockingIOError:
                    pass
            else:
                self.path.unlink(missing_ok=True)
                if self.workers_path.exists() and not _held_at_all(self.workers_path):
                    self.workers_path.unlink(missing_ok=True)
            fcntl.flock(self.fd, fcntl.LOCK_UN)
        finally:
            os.close(self.fd)
            self.fd = None

    def __enter__(self) -> "OutputLock":
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()


def _same_file(path: Path, fd: int) -> bool:
    try:
        return os.stat(path).st_ino == os.fstat(fd).st_ino
    except FileNotFoundError:
        return False


def range_lock_name(first: int, stop: int) -> str:
    return f"{LOCK_NAME}.part-{first:06d}-{stop:06d}"


class RangeLock:
    """The locks of a `--shards A:B` run: `OUT/.lock` shared (no whole run or merge meanwhile)
    and `OUT/.lock.part-A-B` exclusive (not the same range twice); then any other live range
    lock that overlaps A:B is refused (two overlapping runs starting together both refuse)."""

    def __init__(self, out: str | os.PathLike, first: int, stop: int):
        self.out, self.first, self.stop = Path(out), first, stop
        self.locks: list[OutputLock] = []

    def acquire(self) -> "RangeLock":
        try:
            self.locks.append(OutputLock(self.out, shared=True).acquire())
            own = OutputLock(self.out, range_lock_name(self.first, self.stop))
            try:
                self.locks.append(own.acquire())
            except OutputInUseError as exc:
                raise OutputInUseError(f"{self.out}: shards {self.first}:{self.stop} are being made by another "
                                       f"run ({exc})") from None
            for p in sorted(self.out.glob(f"{LOCK_NAME}.part-*")):
                m = re.fullmatch(r"\.lock\.part-(\d+)-(\d+)", p.name)
                if not m or p == own.path:
                    continue
                a, b = int(m[1]), int(m[2])
                if a < self.stop and self.first < b and lock_state(p)[0] == "held":
                    raise OutputInUseError(f"{self.out}: --shards {self.first}:{self.stop} overlaps {a}:{b}, which "
                                           f"a running dofsynth run holds ({p.name}); the ranges of one data set "
                                           "must be disjoint")
        except BaseException:
            self.release()
            raise
        return self

    @property
    def workers_path(self) -> Path:
        """The lock file this range's worker processes hold shared while they live."""
        return OutputLock(self.out, range_lock_name(self.first, self.stop)).workers_path

    def release(self) -> None:
        while self.locks:
            self.locks.pop().release()

    def __enter__(self) -> "RangeLock":
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()


def lock_state(path: str | os.PathLike) -> tuple[str, str]:
    """The state of a lock file (`OUT/.lock`, a range lock), without taking it: ("absent", ""),
    ("stale", "") for a file left by a finished or killed run, or ("held", pid) while a run
    holds it exclusively (pid as written)."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except FileNotFoundError:
        return "absent", ""
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        fcntl.flock(fd, fcntl.LOCK_UN)
        return "stale", ""
    except BlockingIOError:
        return "held", os.read(fd, 64).decode(errors="replace").strip()
    finally:
        os.close(fd)


def _held_at_all(path: Path) -> bool:
    """Whether any process holds a flock (shared or exclusive) on `path`: probed with a
    non-blocking exclusive lock, released at once."""
    try:
        fd = os.open(path, os.O_RDONLY)
    except FileNotFoundError:
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        fcntl.flock(fd, fcntl.LOCK_UN)
        return False
    except BlockingIOError:
        return True
    finally:
        os.close(fd)
