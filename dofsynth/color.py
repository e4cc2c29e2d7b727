"""Colour transfer functions (the highlight boost is in dofsynth.render.highlight).

All images in files are sRGB-encoded; every blur and composite happens in linear light
(float32). Functions here are pure and vectorised over any array shape.

Fast paths (docs/rendering.md, "Colour conversions"): 8-bit sRGB decodes through a 256-entry
table (`srgb8_to_linear`), and linear light encodes straight to 8-bit sRGB through tables
indexed by the float's top 16 bits (`linear_to_srgb8`) that are *exact*: it returns the round-half-up quantisation of the
float64 sRGB formula for every float32 input, with no power function evaluated per pixel.
"""
from __future__ import annotations

from decimal import Decimal, localcontext

import numpy as np

from dofsynth.jit import Kernel


def srgb_decode_exact(v: float) -> float:
    """The linear value of sRGB level v in [0, 1], correctly rounded to float64."""
    if v <= 0.04045:
        with localcontext() as ctx:
            ctx.prec = 40
            return float(Decimal(v) / Decimal("12.92"))
    with localcontext() as ctx:
        ctx.prec = 40
        return float(((Decimal(v) + Decimal("0.055")) / Decimal("1.055")) ** Decimal("2.4"))


_CHUNK = 1 << 16  # values converted at a time: the temporaries stay in cache (8x faster at 2048 px)


def _blockwise(x: np.ndarray, convert) -> np.ndarray:
    """convert(v, o) over float32 x in blocks of _CHUNK values (o: the output block)."""
    x = np.asarray(x, dtype=np.float32)
    out = np.empty(x.shape, np.float32)
    flat_in, flat_out = x.reshape(-1), out.reshape(-1)
    for s in range(0, flat_in.size, _CHUNK):
        convert(flat_in[s : s + _CHUNK], flat_out[s : s + _CHUNK])
    return out


def _decode(v: np.ndarray, o: np.ndarray) -> None:
    np.add(v, np.float32(0.055), out=o)
    o /= np.float32(1.055)
    np.power(o, np.float32(2.4), out=o)
    low = v <= np.float32(0.04045)
    o[low] = v[low] / np.float32(12.92)


def _encode(v: np.ndarray, o: np.ndarray) -> None:
    v = np.clip(v, 0.0, 1.0)
    np.power(v, np.float32(1 / 2.4), out=o)
    o *= np.float32(1.055)
    o -= np.float32(0.055)
    low = v <= np.float32(0.0031308)
    o[low] = v[low] * np.float32(12.92)


def srgb_to_linear(x: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1 sRGB decoding of values in [0, 1] (float32 out)."""
    return _blockwise(x, _decode)


def linear_to_srgb(x: np.ndarray) -> np.ndarray:
    """sRGB encoding of linear values; input is clipped to [0, 1] first (float32 out)."""
    return _blockwise(x, _encode)


# ------------------------------------------------------------------------------ lookup tables
# 8-bit decode: the formula at k/255 in exact decimal arithmetic, rounded once to float32 (the
# same table on every machine: no platform power function involved).
SRGB8_TO_LINEAR = np.array([srgb_decode_exact(k / 255.0) for k in range(256)]).astype(np.float32)
SRGB8_TO_LINEAR.setflags(write=False)


def srgb8_to_linear(u8: np.ndarray) -> np.ndarray:
    """8-bit sRGB codes (uint8, any shape) -> linear light float32 through a 256-entry table."""
    u8 = np.asarray(u8)
    if u8.dtype != np.uint8:
        raise ValueError(f"srgb8_to_linear wants uint8 codes, got {u8.dtype}")
    return SRGB8_TO_LINEAR[u8]


def _encode_tables():
    """Thresholds and the table of `linear_to_srgb8`, indexed by the top 16 bits of a float32.

    Code k+1 starts at the linear value T_k where the sRGB value reaches (k + 0.5) / 255 (round
    half up). T_k (float64) is moved up to the nearest float32, so for a float32 x the test
    `x >= T32_k` is exactly `x >= T_k`. The float32 values sharing their top 16 bits (sign,
    exponent, 7 mantissa bits) form a bin no wider than 1/128 of its magnitude, which holds at
    most one threshold (their gaps are wider: 3.0e-4 at the linear toe, 0.9 % of x at 1;
    asserted): `base[i]` is the code of the bin's smallest value and `step[i]` the threshold
    inside it (NaN when there is none, which no comparison passes). Negative values and NaN
    have code 0, values from 1 code 255 (+inf shares its bin with NaNs: it is taken as 2).
    """
    t64 = np.array([srgb_decode_exact((k + 0.5) / 255.0) for k in range(255)])
    t32 = t64.astype(np.float32)
    t32 = np.where(t32.astype(np.float64) < t64, np.nextafter(t32, np.float32(2.0)), t32).astype(np.float32)
    top = np.arange(1 << 16, dtype=np.uint32)
    finite = top < 0x7F80  # non-negative and finite (0x7F80: +inf and NaN; from 0x8000: negative)
    first = (top[finite] << 16).view(np.float32)  # each bin's smallest and largest value
    last = ((top[finite] << 16) | 0xFFFF).view(np.float32)
    below = np.searchsorted(t32, first, side="right")  # thresholds <= its smallest value
    inside = np.searchsorted(t32, last, side="right") - below
    assert inside.max() <= 1
    base = np.zeros(1 << 16, np.uint8)
    base[: finite.sum()] = below
    step = np.full(1 << 16, np.nan, np.float32)
    one = np.flatnonzero(inside == 1)
    step[one] = t32[below[one]]
    return t32, base, step


SRGB8_THRESHOLDS, _BASE, _STEP = _encode_tables()


def _srgb8_kernel(x, base, step, out):
    """`linear_to_srgb8` of a 2-D float32 x into uint8 out, one value at a time: the same
    look-ups and compare (+inf takes the bin of 2; NaN and negatives find code 0)."""
    for r in range(x.shape[0]):
        for c in range(x.shape[1]):
            v = x[r, c]
            i = np.int64(0x4000) if v == np.inf else np.int64(np.float32(v).view(np.uint32) >> np.uint32(16))
            code = base[i]
            if v >= step[i]:
                code += np.uint8(1)
            out[r, c] = code


_SRGB8 = Kernel(_srgb8_kernel, "void(float32[:, :], uint8[::1], float32[::1], uint8[:, :])")  # (dofsynth.jit)


def linear_to_srgb8(x: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """Linear light (clipped to [0, 1]; NaN counts as 0) -> 8-bit sRGB codes (uint8).

    Exactly `floor(srgb(x) * 255 + 0.5)` with the float64 sRGB formula, for every float32 x
    (x is cast to float32 first): the code is the number of thresholds `SRGB8_THRESHOLDS` <= x,
    found with two look-ups in tables indexed by the top 16 bits of x and one compare. Monotone
    in x. Works in blocks of 64K values, so the temporaries stay small whatever the image size
    (with the compiled kernels on, dofsynth.jit: one pass, the same codes).
    `out` (uint8, x's shape) is filled if given.
    """
    x = np.asarray(x, dtype=np.float32)
    if out is None:
        out = np.empty(x.shape, np.uint8)
    flat_out = out.reshape(-1)
    if not np.shares_memory(flat_out, out):
        raise ValueError("linear_to_srgb8: out must be a contiguous uint8 array")
    compiled = _SRGB8.get()
    if compiled is not None and x.size and out.dtype == np.uint8:
        # one row when x is contiguous (or 1-D), else its last axis: a 2-D view is read where it lies
        rows = (1, -1) if x.ndim < 2 or x.flags.c_contiguous else (-1, x.shape[-1])
        compiled(x.reshape(rows), _BASE, _STEP, out.reshape(rows))
        return out
    flat_in = x.reshape(-1)  # a copy only for a non-contiguous x
    i = np.empty(min(_CHUNK, flat_in.size), np.intp)
    v = np.empty(i.size, np.float32)
    t = np.empty(i.size, np.float32)
    cmp = np.empty(i.size, bool)
    for a in range(0, flat_in.size, _CHUNK):
        b = min(a + _CHUNK, flat_in.size)
        n = b - a
        ii, vv, tt, cc = i[:n], v[:n], t[:n], cmp[:n]
        np.minimum(flat_in[a:b], np.float32(2.0), out=vv)  # +inf -> 2 (its bin holds NaNs); NaN stays
        np.right_shift(vv.view(np.uint32), 16, out=ii, casting="unsafe")
        o = flat_out[a:b]
        _BASE.take(ii, out=o, mode="wrap")  # (ii < 2**16 always: "wrap" only skips the bounds checks, 2x faster)
        _STEP.take(ii, out=tt, mode="wrap")
        np.greater_equal(vv, tt, out=cc)  # False against NaN: no threshold in the bin
        o += cc
    return out
