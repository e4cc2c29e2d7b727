"""Colour transfer functions and the highlight boost.

All images in files are sRGB-encoded; every blur and composite happens in linear light
(float32). Functions here are pure and vectorised over any array shape.

Fast paths (docs/rendering.md, "Colour conversions"): 8-bit sRGB decodes through a 256-entry
table (`srgb8_to_linear`), and linear light encodes straight to 8-bit sRGB through a two-level
table (`linear_to_srgb8`) that is *exact*: it returns the round-half-up quantisation of the
float64 sRGB formula for every float32 input, with no power function evaluated per pixel.
"""
from __future__ import annotations

import numpy as np


def _srgb_decode64(x: np.ndarray) -> np.ndarray:
    x = np.asarray(x, dtype=np.float64)
    return np.where(x <= 0.04045, x / 12.92, ((np.maximum(x, 0.04045) + 0.055) / 1.055) ** 2.4)


def srgb_to_linear(x: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1 sRGB decoding of values in [0, 1] (float32 out)."""
    x = np.asarray(x, dtype=np.float32)
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4).astype(np.float32)


def linear_to_srgb(x: np.ndarray) -> np.ndarray:
    """sRGB encoding of linear values; input is clipped to [0, 1] first (float32 out)."""
    x = np.clip(np.asarray(x, dtype=np.float32), 0.0, 1.0)
    return np.where(x <= 0.0031308, x * 12.92, 1.055 * x ** (1 / 2.4) - 0.055).astype(np.float32)


# ------------------------------------------------------------------------------ lookup tables
# 8-bit decode: the float64 formula at k/255, rounded once to float32 (exact to half an ulp).
SRGB8_TO_LINEAR = _srgb_decode64(np.arange(256) / 255.0).astype(np.float32)
SRGB8_TO_LINEAR.setflags(write=False)


def srgb8_to_linear(u8: np.ndarray) -> np.ndarray:
    """8-bit sRGB codes (uint8, any shape) -> linear light float32 through a 256-entry table."""
    u8 = np.asarray(u8)
    if u8.dtype != np.uint8:
        raise ValueError(f"srgb8_to_linear wants uint8 codes, got {u8.dtype}")
    return SRGB8_TO_LINEAR[u8]


def _encode_tables(bins: int):
    """Thresholds and the two-level table of `linear_to_srgb8`.

    Code k+1 starts at the linear value T_k where the sRGB value reaches (k + 0.5) / 255 (round
    half up). T_k (float64) is moved up to the nearest float32, so for a float32 x the test
    `x >= T32_k` is exactly `x >= T_k`. Bin i of width 1/bins holds at most one threshold (their
    smallest gap, at the linear toe, is 1 / (12.92 * 255) > 1 / bins): `base[i]` is the code at
    the bin's start and `step[i]` the threshold inside it times `bins` (exact: a power of two;
    +inf when there is none).
    """
    t64 = _srgb_decode64((np.arange(255) + 0.5) / 255.0)
    t32 = t64.astype(np.float32)
    t32 = np.where(t32.astype(np.float64) < t64, np.nextafter(t32, np.float32(2.0)), t32).astype(np.float32)
    assert np.min(np.diff(t64)) > 1.0 / bins
    starts = (np.arange(bins + 1) / bins).astype(np.float32)  # exact: bins is a power of two
    base = np.searchsorted(t32, starts, side="right").astype(np.uint8)  # thresholds <= start
    step = np.full(bins + 1, np.inf, np.float32)
    inside = np.searchsorted(t32, starts, side="right")  # first threshold > start
    ok = inside < 255
    nxt = np.where(ok, t32[np.minimum(inside, 254)], 2.0)
    ok &= nxt < starts + np.float32(1.0 / bins)
    step[ok] = nxt[ok] * np.float32(bins)
    return t32, base, step


ENCODE_BINS = 4096
SRGB8_THRESHOLDS, _BASE, _STEP = _encode_tables(ENCODE_BINS)


_CHUNK = 1 << 16  # elements per block: small temporaries, cache-resident tables


def linear_to_srgb8(x: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """Linear light (clipped to [0, 1]; NaN counts as 0) -> 8-bit sRGB codes (uint8).

    Exactly `floor(srgb(x) * 255 + 0.5)` with the float64 sRGB formula, for every float32 x
    (x is cast to float32 first): the code is the number of thresholds `SRGB8_THRESHOLDS` <= x,
    found with two table lookups. Monotone in x. Works in blocks of 64K values, so the
    temporaries stay small whatever the image size. `out` (uint8, x's shape) is filled if given.
    """
    x = np.asarray(x, dtype=np.float32)
    if out is None:
        out = np.empty(x.shape, np.uint8)
    flat_in = x.reshape(-1)  # a copy only for a non-contiguous x
    flat_out = out.reshape(-1)
    if not np.shares_memory(flat_out, out):
        raise ValueError("linear_to_srgb8: out must be a contiguous uint8 array")
    t = np.empty(min(_CHUNK, flat_in.size), np.float32)
    i = np.empty(t.size, np.intp)
    cmp = np.empty(t.size, bool)
    for a in range(0, flat_in.size, _CHUNK):
        b = min(a + _CHUNK, flat_in.size)
        n = b - a
        tt, ii, cc = t[:n], i[:n], cmp[:n]
        with np.errstate(over="ignore"):  # huge values become inf, then ENCODE_BINS
            np.multiply(flat_in[a:b], np.float32(ENCODE_BINS), out=tt)
        np.fmax(tt, np.float32(0.0), out=tt)  # fmax/fmin: NaN -> 0
        np.fmin(tt, np.float32(ENCODE_BINS), out=tt)
        ii[...] = tt  # truncation = floor for t >= 0
        o = flat_out[a:b]
        _BASE.take(ii, out=o)
        np.less_equal(_STEP.take(ii), tt, out=cc)  # t = clip(x) * bins exactly
        o += cc
    return out


# ------------------------------------------------------------------------------- highlights
def highlight_boost(
    linear: np.ndarray, threshold: float = 0.9, gain: float = 4.0, power: float = 2.0,
    *, out: np.ndarray | None = None,
) -> np.ndarray:
    """Turn near-white pixels into brighter-than-white light before blurring.

    With `m = max(R, G, B)` of the *sRGB-encoded* pixel and `t = threshold`, every channel of
    the linear pixel is multiplied by `1 + gain * s(m) ** power`, where
    `s(m) = clip((m - t) / (1 - t), 0, 1)`. Pixels darker than `t` are unchanged; a pure white
    pixel becomes `1 + gain` times brighter, so after blurring a small highlight still
    saturates and spreads into a visible bokeh disc. The boost is continuous in the pixel value.

    Only pixels whose linear max exceeds the linear value of `t` (less a margin) are touched,
    so the cost is a max over the channels plus work proportional to the bright pixels.
    `out=linear` boosts in place (float32 (..., C) input only); otherwise a new array.
    """
    if not 0.0 <= threshold < 1.0:
        raise ValueError(f"highlight threshold must be in [0, 1), got {threshold}")
    if gain < 0 or power <= 0:
        raise ValueError(f"highlight gain must be >= 0 and power > 0, got {gain}, {power}")
    linear = np.asarray(linear, dtype=np.float32)
    if out is None:
        out = linear.copy()
    elif out is not linear:
        out[...] = linear
    if out.ndim == 3 and out.shape[0] > _BOOST_ROWS:  # row blocks: small temporaries at any size
        for r in range(0, out.shape[0], _BOOST_ROWS):
            block = out[r:r + _BOOST_ROWS]
            _boost_block(block, threshold, gain, power)
        return out
    _boost_block(out if out.ndim > 1 else out[None], threshold, gain, power)  # one pixel: (1, C)
    return out


_BOOST_ROWS = 128


def _boost_block(work: np.ndarray, threshold: float, gain: float, power: float) -> None:
    """highlight_boost in place on a (..., C) float32 block (any strides)."""
    m = work[..., 0].copy()  # max over channels (numpy's reduce over a short last axis is slow)
    for c in range(1, work.shape[-1]):
        np.maximum(m, work[..., c], out=m)
    # s(m) > 0 needs srgb(m) > t, i.e. m > decode(t); the margin absorbs float32 rounding.
    lo = float(_srgb_decode64(threshold)) * (1.0 - 1e-3) - 1e-6
    idx = np.nonzero(m > lo)  # index tuples also write through a non-contiguous `out`
    if idx[0].size:
        ms = linear_to_srgb(m[idx])
        s = np.clip((ms - threshold) / (1.0 - threshold), 0.0, 1.0)
        work[idx] = (work[idx] * (1.0 + gain * s**power)[:, None]).astype(np.float32)
