"""The highlight boost: near-white pixels turned into brighter-than-white light before blurring,
and its exact inverse after it.

A photo clips its highlights, so a blurred lamp or sun glint comes out dim and grey. `boost`
multiplies every channel of a linear pixel by the same factor

    B(x) = x * g(m),    m = max(R, G, B),
    g(m) = 1 + gain * w(s),    s = clip((m - T) / (1 - T), 0, 1),    w(s) = s ** power,

where T is the linear value of the sRGB level `threshold`: pixels darker than it are
unchanged and a white one becomes `1 + gain` times brighter, so a small highlight, spread by
the blur, still saturates into a visible disc of the aperture's shape. w is the piecewise-linear
interpolant of s ** power on KNOTS segments (knots in exact decimal arithmetic), so every
per-pixel operation is +, -, *, / or sqrt: correctly rounded, the same bytes on every CPU.

`unboost` is the exact inverse, applied to the blurred composite: m * g(m) is strictly
increasing, so from y = B(x) the original max m is the root of m * g(m) = max(y) (a quadratic
on each segment, solved in closed form) and x = y * m / max(y). Because a sample's targets
are `unboost(render(boost(planes)))` and its all-in-focus image `unboost(composite(boost(
planes)))`, a target equals the all-in-focus image wherever nothing reaching a pixel is
blurred, highlights included, and a pixel's hue (the ratios of its channels) is what it was.
"""
from __future__ import annotations

from decimal import Decimal, localcontext
from functools import lru_cache
from typing import NamedTuple

import numpy as np

from dofsynth.color import srgb_decode_exact
from dofsynth.jit import Kernel

KNOTS = 256
_ROWS = 128  # rows per block: small temporaries at any size


def _decimal_pow(base: float, exponent: float) -> float:
    """base ** exponent, rounded once from 40-digit decimal arithmetic (platform independent)."""
    if base == 0.0:
        return 0.0
    with localcontext() as ctx:
        ctx.prec = 40
        return float(Decimal(base) ** Decimal(exponent))


class _Tables(NamedTuple):
    """The boost's tables for one (threshold, gain, power), all float64 but `start_knot`."""

    t: float                # T, the linear value of the threshold
    width: float            # the knots' spacing in m
    m: np.ndarray           # per knot k: m_k,
    g: np.ndarray           # g_k,
    dg: np.ndarray          # per segment: g_k+1 - g_k,
    h: np.ndarray           # per knot: h_k = m_k * g_k
    scale: float            # `_segment`'s index of h: bins per unit of h - T,
    start_knot: np.ndarray  # and the knot at each bin's start
    a4: np.ndarray          # per segment, `_root`'s quadratic h(m_k + width f) = h_k + b f + a f^2: 4a,
    b: np.ndarray           # b,
    b2: np.ndarray          # and b^2


@lru_cache(maxsize=64)
def _tables(threshold: float, gain: float, power: float) -> _Tables:
    """The `_Tables` of a boost, checked."""
    if not 0.0 <= threshold < 1.0:
        raise ValueError(f"highlight threshold must be in [0, 1), got {threshold}")
    if gain < 0 or power <= 0:
        raise ValueError(f"highlight gain must be >= 0 and power > 0, got {gain}, {power}")
    t = srgb_decode_exact(float(threshold))
    width = (1.0 - t) / KNOTS
    g = np.array([1.0 + gain * _decimal_pow(k / KNOTS, power) for k in range(KNOTS + 1)])
    m = t + width * np.arange(KNOTS + 1)
    m[-1] = 1.0
    h = m * g
    # bins narrower than the knots' smallest gap in h (>= width: h' = g + m g' >= 1), so each
    # holds at most one knot
    scale = _INDEX_BINS / (h[-1] - t)
    starts = t + np.arange(_INDEX_BINS + 1) / scale
    assert np.diff(h).min() > 1.0 / scale
    start_knot = np.clip(np.searchsorted(h, starts, side="right") - 1, 0, KNOTS - 1)
    dg = np.diff(g)
    a, b = width * dg, m[:-1] * dg + width * g[:-1]
    return _Tables(t, width, m, g, dg, h, scale, start_knot, 4.0 * a, b, b * b)


_INDEX_BINS = 1 << 14


def _segment(y: np.ndarray, tables: _Tables) -> np.ndarray:
    """The segment k of h holding each y in (T, h_KNOTS): searchsorted(h, y, "right") - 1, found
    from the knot at the start of y's bin, moved by at most one knot each way (bins hold one
    knot at most; the second test covers the bin index's rounding). Neither move leaves
    [0, KNOTS - 1]: h_0 = T < y and y < h_KNOTS."""
    h = tables.h
    b = ((y - tables.t) * tables.scale).astype(np.intp)  # >= 0: y > T
    k = tables.start_knot[np.minimum(b, _INDEX_BINS, out=b)]
    k -= y < h[k]
    k += y >= h[k + 1]
    return k


def _channel_max(chans) -> np.ndarray:
    """The elementwise max of a sequence of same-shape channels (a new array), by np.maximum
    pairwise (numpy's reduce over a short axis is slow); NaN propagates."""
    if len(chans) == 1:
        return np.array(chans[0], copy=True)
    m = np.maximum(chans[0], chans[1])
    for c in chans[2:]:
        np.maximum(m, c, out=m)
    return m


def _factor(m: np.ndarray, tables: _Tables) -> np.ndarray:
    """g(m) (float64) for linear maxima above T: g_k + (g_k+1 - g_k) (s - k), s = (m - T) /
    (1 - T) * KNOTS clipped to [0, KNOTS], k = min(floor(s), KNOTS - 1)."""
    t, g, dg = tables.t, tables.g, tables.dg
    s = m - t
    s /= 1.0 - t
    np.clip(s, 0.0, 1.0, out=s)
    s *= KNOTS
    k = np.minimum(np.floor(s), KNOTS - 1)
    s -= k
    k = k.astype(np.intp)
    s *= dg[k]
    s += g[k]
    return s


def _root(mb: np.ndarray, tables: _Tables) -> np.ndarray:
    """m with m * g(m) = mb, for boosted maxima mb above T (float64): on segment k, with
    h(m_k + width f) = h_k + b f + a f^2 and r = mb - h_k, f = 2 r / (b + sqrt(b^2 + 4 a r))
    (the root without cancellation). Below T mb is unchanged; beyond white g is 1 + gain."""
    t, width, m, h = tables.t, tables.width, tables.m, tables.h
    inside = (mb > t) & (mb < h[-1])
    every = bool(inside.all())  # the usual case: no masks
    y = mb if every else mb[inside]
    k = _segment(y, tables)
    r = y - h[k]
    np.maximum(r, 0.0, out=r)
    den = tables.a4[k]
    den *= r
    den += tables.b2[k]
    np.sqrt(den, out=den)
    den += tables.b[k]
    f = 2.0 * r
    f /= den
    np.minimum(f, 1.0, out=f)
    f *= width
    f += m[k]
    if every:
        return f
    out = np.where(mb <= t, mb, mb / tables.g[-1])
    out[inside] = f
    return out


def _lines(block: np.ndarray, flat: np.ndarray):
    """Each channel of `block` (..., C) as a 1-D view over its memory, and where the values
    at C-order positions `flat` of block[..., c] lie in it. A block of whole rows is its
    channel flattened; a box inside wider rows (the frame of a canvas) the run from its first
    to its last value, rows `pitch` values apart (positions row * pitch + column); other
    layouts, index tuples."""
    chans = [block[..., c] for c in range(block.shape[-1])]
    try:
        return [c.reshape(-1, copy=False) for c in chans], flat
    except ValueError:
        pass
    c0 = chans[0]
    step, row = c0.strides[-1], c0.strides[0] if c0.ndim == 2 else 0
    if c0.ndim == 2 and step > 0 and row > 0 and row % step == 0 and row // step >= c0.shape[1]:
        pitch, w = row // step, c0.shape[1]
        n = (c0.shape[0] - 1) * pitch + w
        lines = [np.lib.stride_tricks.as_strided(c, shape=(n,), strides=(step,)) for c in chans]
        rows, cols = np.divmod(flat, w)
        rows *= pitch
        rows += cols
        return lines, rows
    return chans, np.unravel_index(flat, c0.shape)


def _boost_kernel(c0, c1, c2, lo, invert, t, width, scale, bins, knots, m, g, dg, h, start_knot, a4, b, b2):
    """`_apply` over three (rows, W) channel views in place, pixel by pixel (compiled:
    dofsynth.jit): the same float32 test against lo, the same float64 factor (`_factor`) or
    root (`_root`, `_segment`) in the same order of operations, each product rounded once."""
    one_t = 1.0 - t
    h_end, g_end = h[h.size - 1], g[g.size - 1]
    for r in range(c0.shape[0]):
        for col in range(c0.shape[1]):
            x0, x1, x2 = c0[r, col], c1[r, col], c2[r, col]
            if not (x0 > lo or x1 > lo or x2 > lo) or x0 != x0 or x1 != x1 or x2 != x2:
                continue  # no value above lo, or a NaN: untouched
            mv = np.float64(max(x0, x1, x2))
            if not invert:
                s = (mv - t) / one_t
                s = min(max(s, 0.0), 1.0) * knots
                kf = min(np.floor(s), knots - 1)
                k = np.int64(kf)
                s = (s - kf) * dg[k] + g[k]
            elif t < mv < h_end:
                k = start_knot[min(np.int64((mv - t) * scale), bins)]
                if mv < h[k]:
                    k -= 1
                if mv >= h[k + 1]:
                    k += 1
                rr = mv - h[k]
                if rr < 0.0:
                    rr = 0.0
                f = 2.0 * rr / (np.sqrt(a4[k] * rr + b2[k]) + b[k])
                if f > 1.0:
                    f = 1.0
                s = (f * width + m[k]) / mv
            else:
                s = (mv if mv <= t else mv / g_end) / mv
            c0[r, col] = np.float32(np.float64(x0) * s)
            c1[r, col] = np.float32(np.float64(x1) * s)
            c2[r, col] = np.float32(np.float64(x2) * s)


_BOOST = Kernel(_boost_kernel, "void(float32[:, :], float32[:, :], float32[:, :], float32, boolean, float64, float64, "
                               "float64, int64, float64, float64[::1], float64[::1], float64[::1], float64[::1], "
                               "intp[::1], float64[::1], float64[::1], float64[::1])")  # (dofsynth.jit)


def _compiled_apply(work: np.ndarray, tables: _Tables, lo: float, invert: bool) -> bool:
    """`_apply`'s passes over `work` (..., 3) in place by the compiled kernel, when the kernels
    are on and work is float32 with at most 3 axes; False (nothing done) otherwise."""
    kernel = _BOOST.get()
    if kernel is None or work.shape[-1] != 3 or work.ndim > 3 or work.dtype != np.float32:
        return False
    w3 = work.reshape(1, 1, 3) if work.ndim == 1 else (work[None] if work.ndim == 2 else work)  # views
    tb = tables
    kernel(w3[..., 0], w3[..., 1], w3[..., 2], np.float32(lo), invert, tb.t, tb.width, tb.scale, _INDEX_BINS,
           float(KNOTS), tb.m, tb.g, tb.dg, tb.h, tb.start_knot, tb.a4, tb.b, tb.b2)
    return True


def _apply(x, threshold, gain, power, out, axis, invert: bool):
    tables = _tables(float(threshold), float(gain), float(power))
    x = np.asarray(x, dtype=np.float32)
    if out is None:
        out = x.copy()
    elif out is not x:
        out[...] = x
    work = np.moveaxis(out, axis, -1)  # (..., C), a view
    lo = tables.t * (1.0 - 1e-6)  # (compared in float32 with the values)
    if _compiled_apply(work, tables, lo, invert):
        return out
    lead = work.reshape(-1, work.shape[-1]) if work.ndim < 2 else None
    blocks = [lead] if lead is not None else [work[r:r + _ROWS] for r in range(0, work.shape[0], _ROWS)]
    interleaved = work.strides[-1] == work.itemsize and work.shape[-1] > 1
    for block in blocks:
        if interleaved:  # the few pixels with a value above lo, found in one contiguous pass
            flat = np.flatnonzero(block > lo)
            if not flat.size:
                continue
            flat //= block.shape[-1]
            flat = flat[np.concatenate(([True], flat[1:] != flat[:-1]))]  # each pixel once, in order
            chans, idx = _lines(block, flat)
            vals = [chan[idx] for chan in chans]
            mx = _channel_max(vals)
            hit = mx > lo  # (False where a NaN makes the max NaN, as below)
            if not hit.all():
                flat, mx, vals = flat[hit], mx[hit], [v[hit] for v in vals]
                chans, idx = _lines(block, flat)
        else:  # planar: contiguous channel planes, their max in two passes
            mx = _channel_max(np.moveaxis(block, -1, 0))
            flat = np.flatnonzero(mx > lo)
            if not flat.size:
                continue
            mx = mx.reshape(-1)[flat]
            chans, idx = _lines(block, flat)
            vals = [chan[idx] for chan in chans]
        mv = mx.astype(np.float64)
        scale = (_root(mv, tables) / mv) if invert else _factor(mv, tables)
        for chan, v in zip(chans, vals):  # a channel at a time: 1-D gathers, not 3-value rows
            chan[idx] = np.multiply(v, scale, out=v, casting="unsafe")  # float64 product, rounded once
    return out


def boost(x: np.ndarray, threshold: float = 0.9, gain: float = 4.0, power: float = 2.0, *,
          out: np.ndarray | None = None, axis: int = -1) -> np.ndarray:
    """B(x) of linear light (float32, channels along `axis`); `out=x` works in place, also on
    a view. Only pixels whose max exceeds T are touched."""
    return _apply(x, threshold, gain, power, out, axis, invert=False)


def unboost(y: np.ndarray, threshold: float = 0.9, gain: float = 4.0, power: float = 2.0, *,
            out: np.ndarray | None = None, axis: int = -1) -> np.ndarray:
    """B^-1(y): the exact inverse of `boost` with the same parameters (float32 rounding aside)."""
    return _apply(y, threshold, gain, power, out, axis, invert=True)
