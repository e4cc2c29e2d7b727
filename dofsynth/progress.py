"""Progress and verbosity, one owner for every command.

`bar(total, desc, unit)` is a tqdm bar on a terminal; when stderr is redirected (a log file, a
batch job) it prints one plain line every `LINE_STEP` of the work instead, with the rate and
the time left, and no carriage-return frames. `-q/--quiet` (no bars, no summaries; errors
still print) and `-v/--verbose` (more detail) are the same on every command: the CLI sets
`VERBOSITY` once (`set_verbosity`), and code asks `quiet()` / `verbose()`.
"""
from __future__ import annotations

import os
import sys
import time

LINE_STEP = 0.1  # redirected output: a line each tenth of the work
VERBOSITY = 1     # 0 quiet, 1 normal, 2 verbose


def set_verbosity(quiet: bool = False, verbose: bool = False) -> None:
    global VERBOSITY
    VERBOSITY = 0 if quiet else 2 if verbose else 1


def quiet() -> bool:
    return VERBOSITY == 0


def verbose() -> bool:
    return VERBOSITY >= 2


def _duration(s: float) -> str:
    s = int(round(s))
    return f"{s // 3600}h{s % 3600 // 60:02d}m" if s >= 3600 else f"{s // 60}m{s % 60:02d}s" if s >= 60 else f"{s}s"


class LineProgress:
    """tqdm's update/close/set_postfix_str for redirected output: a line per LINE_STEP."""

    def __init__(self, total: int | None, desc: str, unit: str, initial: int = 0, file=None):
        self.total, self.desc, self.unit, self.n = total, desc, unit, initial
        self.file = file or sys.stderr
        self.t0, self.start, self.postfix = time.perf_counter(), initial, ""
        self.next_mark = LINE_STEP

    def set_postfix_str(self, text: str) -> None:
        self.postfix = text

    def update(self, n: int = 1) -> None:
        self.n += n
        if self.total and self.n / self.total + 1e-12 >= self.next_mark and self.n < self.total:
            self._line()
            while self.next_mark <= self.n / self.total:
                self.next_mark += LINE_STEP

    def _line(self) -> None:
        dt = time.perf_counter() - self.t0
        rate = (self.n - self.start) / dt if dt > 0 else 0.0
        parts = [f"{self.desc}: {self.n}/{self.total} {self.unit}s" if self.total else f"{self.desc}: {self.n} {self.unit}s"]
        if self.total:
            parts[0] += f" ({self.n / self.total:.0%})"
        parts.append(f"{rate:.3g} {self.unit}s/s")
        if self.total and rate > 0:
            parts.append(f"{_duration((self.total - self.n) / rate)} left")
        if self.postfix:
            parts.append(self.postfix)
        print(", ".join(parts), file=self.file, flush=True)

    def close(self) -> None:
        if self.n > self.start:
            self._line()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


class _Off:
    n = 0

    def update(self, n: int = 1) -> None: ...
    def set_postfix_str(self, text: str) -> None: ...
    def close(self) -> None: ...
    def __enter__(self): return self
    def __exit__(self, *exc): ...


def bar(total: int | None, desc: str, unit: str = "sample", *, initial: int = 0, enabled: bool = True,
        leave: bool = True):
    """A progress bar: tqdm on a terminal, lines when redirected, nothing when quiet or
    `enabled` is False."""
    if not enabled or quiet():
        return _Off()
    if not sys.stderr.isatty():
        return LineProgress(total, desc, unit, initial)
    from tqdm import tqdm

    try:  # a pseudo-terminal whose size was never set reports 0 x 0: tqdm would draw nothing
        sized = os.get_terminal_size(sys.stderr.fileno()).columns > 0
    except OSError:
        sized = False
    size = {} if sized else {"ncols": 80, "nrows": 24}
    return tqdm(total=total, initial=initial, desc=desc, unit=unit, dynamic_ncols=sized, smoothing=0.1,
                leave=leave, file=sys.stderr, **size)


def track(items, desc: str, unit: str = "sample", *, enabled: bool = True):
    """Iterate `items` (a sized collection) under a `bar`."""
    with bar(len(items), desc, unit, enabled=enabled) as b:
        for x in items:
            yield x
            b.update(1)


def say(*args, **kw) -> None:
    """print() of a summary line (what was written where): nothing when quiet."""
    if not quiet():
        print(*args, **kw)


def note(text: str) -> None:
    """A detail line (e.g. one per finished shard), on stderr, only with -v/--verbose; above a
    live terminal bar, not through it."""
    if not verbose():
        return
    if sys.stderr.isatty():
        from tqdm import tqdm

        tqdm.write(text, file=sys.stderr)
    else:
        print(text, file=sys.stderr, flush=True)
