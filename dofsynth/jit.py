"""Compiled per-pixel passes (numba) for processes that render many samples.

A few passes of every sample are elementwise work that numpy spreads over several sweeps of
memory: the exact sRGB encode (dofsynth.color.linear_to_srgb8), the highlight boost and its
inverse (dofsynth.render.highlight) and a cutout's un-premultiplying
(dofsynth.compose.place_premultiplied). Each has a plain-Python kernel with its numba signature
beside its numpy reference; the kernels are compiled (or loaded from numba's cache) and used
*only once `enable()` has been called*, which dofsynth.generate.worker.setup_process does: a
generation worker, `generate --workers 1`, the benchmarks. That costs a process about 0.6 CPU s
once, at `enable()` (importing numba and loading the compiled code; after a checkout or an edit
of a kernel's module the first process compiles it, a few seconds, and caches it in
__pycache__ beside the module, or in numba's cache folder where that one is read-only), and
about 110 MiB of resident memory (72 MiB of it the LLVM library's pages, shared between
processes); a sample then costs 7-10 % less CPU time (docs/generate.md, "Speed and memory").
Other processes (`dofsynth render`, library callers, tests calling the renderer) keep the numpy
passes: their start-up stays light.

The kernels give the same bytes as the references: the same IEEE operations in the same order
(+, -, *, /, sqrt, compares and table look-ups; numba's default never fuses or reorders them),
checked on adversarial values in tests/test_jit.py. DOFSYNTH_JIT=0 keeps them off (as does a
missing numba, or one that fails to compile them: a warning says so and the numpy passes run);
DOFSYNTH_JIT=1 turns them on in every process.
"""
from __future__ import annotations

import importlib.util
import os
import sys

ENV = "DOFSYNTH_JIT"
_STATE = {"on": None}  # None: not decided (DOFSYNTH_JIT=1 turns on, else off until enable())
_KERNELS: list = []  # every Kernel made: `enable()` loads them all


def _setting() -> str:
    want = os.environ.get(ENV, "")
    if want not in ("", "0", "1"):
        raise ValueError(f"{ENV}={want!r}: want 0 (numpy passes) or 1 (compiled passes in every process)")
    return want


def enable() -> bool:
    """Use the compiled kernels in this process from now on (unless DOFSYNTH_JIT=0 or numba
    is missing); returns whether they are on. Results do not depend on it."""
    if _setting() == "0":
        _STATE["on"] = False
        return False
    if importlib.util.find_spec("numba") is None:
        _STATE["on"] = False
        return False
    _STATE["on"] = True
    try:
        for k in _KERNELS:  # loaded now, with the process's start-up, not on its first sample
            k.get()
    except Exception as exc:  # a numba that cannot build them here: the numpy passes, said once
        _STATE["on"] = False
        print(f"dofsynth: warning: compiled per-pixel passes unavailable ({type(exc).__name__}: {exc}); "
              f"using the numpy passes (the same bytes, slower)", file=sys.stderr, flush=True)
        return False
    return True


def disable() -> None:
    """Back to the numpy references in this process (tests compare the two)."""
    _STATE["on"] = False


def enabled() -> bool:
    """Whether the compiled kernels are on in this process."""
    if _STATE["on"] is None:
        return enable() if _setting() == "1" else False
    return bool(_STATE["on"])


class Kernel:
    """A plain-Python function of numpy arrays and scalars, compiled by numba for one
    `signature` (numba's type string; any array layout where it says `[:, :]`) when the
    kernels are on (cached on disk; IEEE semantics: no fast-math, division by zero gives inf
    or NaN as in numpy). `get()` is the compiled function, or None while the kernels are off."""

    def __init__(self, fn, signature: str):
        self.fn, self.signature, self._compiled = fn, signature, None
        _KERNELS.append(self)

    def get(self):
        if not enabled():
            return None
        if self._compiled is None:
            import numba

            self._compiled = numba.njit(self.signature, cache=True, nogil=True, error_model="numpy")(self.fn)
        return self._compiled
