"""The foreground colour of a photo + matte pair, where the matte is partly transparent.

A matting set's photo is the object composited over its original backdrop: wherever alpha is
between 0 and 1 (hair, fur, a net) the photo's colour holds backdrop too, which compositing
would carry into the new scene (a book title readable in a doll's hair). `estimate` solves for
the object's own colour F in I = alpha F + (1 - alpha) B with pymatting's multilevel
foreground estimation (Germer et al. 2020) over the matte's extent (the bounding box of
alpha > 0: the library always passes that crop, so the estimate of a pair has one definition),
and keeps the photo where alpha is 0 or 1. `space` says in which values that equation holds
for the set: "srgb", the photo's 8-bit codes (how matting sets are composited and annotated:
Composition-1k adds codes, and a matte drawn on a photo is fitted to its codes), or "linear"
light (mattes of linear renders). The result is quantised to 8-bit
sRGB codes (the precision of the photo) and cached on disk per pair (by both files' sha256:
the soft pixels' codes in a small .npy), so a large set pays for it once and every process,
cached or not, gets the same bytes. numba compiles pymatting for a generic x86-64 CPU
(NUMBA_CPU_NAME, unless set), so the estimate does not depend on the machine either.
"""
from __future__ import annotations

import functools
import io
import os
import sys
from pathlib import Path

import numpy as np

from dofsynth.color import linear_to_srgb8, srgb8_to_linear
from dofsynth.files import atomic_write_bytes

ESTIMATOR = "pymatting-ml"  # what sample records name; its version is part of the cache key
SPACES = ("srgb", "linear")
CACHE_ENV = "DOFSYNTH_CACHE"


def cache_dir() -> Path:
    """Where estimated foregrounds are kept: $DOFSYNTH_CACHE, else $XDG_CACHE_HOME/dofsynth,
    else ~/.cache/dofsynth."""
    if os.environ.get(CACHE_ENV):
        return Path(os.environ[CACHE_ENV])
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "dofsynth"


def estimator_id(space: str = "linear") -> str:
    """The estimator, its version and (unless linear) its space, as sample records name it
    (without importing it): "pymatting-ml-1.1.16" or "pymatting-ml-1.1.16-srgb"."""
    if space not in SPACES:
        raise ValueError(f"foreground estimation space must be one of {SPACES}, got {space!r}")
    return f"{ESTIMATOR}-{_installed_version()}" + ("" if space == "linear" else f"-{space}")


@functools.lru_cache(maxsize=1)
def _installed_version() -> str:
    """pymatting's installed version, read from its metadata once per process (each sample's
    record names it: reading the metadata files every time cost about 1 ms)."""
    from importlib.metadata import version

    return version("pymatting")


def _estimator():
    """pymatting's estimator, imported when first needed (1-7 s: numba compiles it)."""
    os.environ.setdefault("NUMBA_CPU_NAME", "generic")  # the same machine code (and bits) everywhere
    import pymatting

    return pymatting.estimate_foreground_ml


def estimate(rgb: np.ndarray, alpha: np.ndarray, photo_sha256: str, alpha_sha256: str,
             space: str = "linear") -> np.ndarray:
    """The object's linear colour (H, W, 3) float32 for a photo's linear colour and its matte in
    [0, 1]: estimated (in `space`) where 0 < alpha < 1, the photo's elsewhere (8-bit sRGB
    precision)."""
    soft = (alpha > 0) & (alpha < 1)
    n = int(np.count_nonzero(soft))
    if not n:
        return rgb
    # the cache holds the sRGB codes of the soft pixels only (raster order): a small .npy, read
    # without decoding an image
    path = cache_dir() / "foreground" / f"{estimator_id(space)}-{photo_sha256[:20]}-{alpha_sha256[:20]}-{n}.npy"
    codes = None
    if path.is_file():
        try:
            codes = np.load(io.BytesIO(path.read_bytes()), allow_pickle=False)
        except (OSError, ValueError, EOFError):
            codes = None  # a broken cache file is made again
        if codes is not None and (codes.shape != (n, 3) or codes.dtype != np.uint8):
            codes = None
    if codes is None:
        a = np.ascontiguousarray(alpha, dtype=np.float32)
        if space == "srgb":  # the photo's codes (exact: linear_to_srgb8 inverts the decode) as [0, 1]
            est = _estimator()(linear_to_srgb8(rgb).astype(np.float32) / np.float32(255.0), a)
            codes = np.floor(np.clip(np.asarray(est, np.float64)[soft], 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
        else:
            est = _estimator()(np.ascontiguousarray(rgb, dtype=np.float32), a)
            codes = linear_to_srgb8(np.asarray(est, np.float32)[soft])
        buf = io.BytesIO()
        np.save(buf, codes, allow_pickle=False)
        try:
            atomic_write_bytes(path, buf.getvalue())
        except OSError as exc:  # no cache: slower, the same bytes
            print(f"dofsynth: warning: cannot cache estimated foregrounds in {path.parent} ({exc.strerror or exc}); "
                  f"set {CACHE_ENV} to a writable folder", file=sys.stderr)
    out = np.array(rgb, dtype=np.float32, copy=True)
    out[soft] = srgb8_to_linear(codes)
    return out
