"""The normalized level scatter of a plane whose disparity varies, for the layered renderer
(dofsynth.render.layered): `scatter_map` for a 2-D CoC map, `scatter_line` for a ramp (a map
that varies along one axis only), each summing K_k * (w_k P) over the CoC levels k
(dofsynth.render.levels) into its outputs and returning the sum of K_k * w_k, the normalizing
weight. Units: CoC radii in pixels; P premultiplied linear colour and alpha, float32. O is
the region written, E the region read: O grown by smax, the largest kernel's support radius.
"""
from __future__ import annotations

import cv2
import numpy as np
import scipy.fft as sfft

from dofsynth.optics.kernel import kernel, kernel_moments, support_radius
from dofsynth.render.fft import Convolver, copy_tile, is_small, trimmed
from dofsynth.render.levels import level_weight, level_weights

MAX_SLOPE = 0.5  # |grad c| (px per px) the Jacobian weight uses at most: it stays >= 1/2


def scatter_map(read, shape, c_e, smax, apertures, outs, level_step, level_ratio):
    """The level scatter of a 2-D CoC map c_e over E (`shape` (he, we)): for each aperture, the
    unnormalized sum over levels of K_k * (w_k src) over O added into its `outs` (C, oh, ow),
    src = read(channels, y0, y1, x0, x1) of E; returns the sums of K_k * w_k (the weights,
    (oh, ow)). Each level over the box of the pixels it weighs (per-row and per-column ranges),
    read when it is needed."""
    he, we = shape
    oh, ow = he - 2 * smax, we - 2 * smax
    C = outs[0].shape[0]
    levels, k0c, fc = level_weights(c_e, level_step, level_ratio)
    w_accs = [np.zeros((oh, ow), np.float32) for _ in apertures]
    in_rows, in_cols = _levels_along(k0c, levels.size)
    for k, ck in enumerate(levels):
        # the rows and columns holding a pixel of level k (k0 = k, or k0 = k - 1 with weight f)
        rows = np.flatnonzero(in_rows[:, k] | in_rows[:, max(k - 1, 0)])
        cols = np.flatnonzero(in_cols[:, k] | in_cols[:, max(k - 1, 0)])
        if rows.size == 0 or cols.size == 0:
            continue
        s = support_radius(ck)
        # only pixels within s of O reach it: E is O grown by smax >= s
        y0, y1 = max(int(rows[0]), smax - s), min(int(rows[-1]) + 1, smax + oh + s)
        x0, x1 = max(int(cols[0]), smax - s), min(int(cols[-1]) + 1, smax + ow + s)
        if y1 <= y0 or x1 <= x0:
            continue
        wk = level_weight(k0c[y0:y1, x0:x1], fc[y0:y1, x0:x1], k)
        if not wk.any():
            continue
        weighted = read(range(C), y0, y1, x0, x1)
        weighted *= wk
        ty0, tx0 = y0 - s - smax, x0 - s - smax  # where the strip's blur lands in O
        for aperture, out, w_acc in zip(apertures, outs, w_accs):
            cv = Convolver(float(ck), aperture, y1 - y0, x1 - x0)
            cv.add_into(copy_tile(wk), w_acc, ty0, tx0)
            cv.add_stack_into(weighted, out, ty0, tx0)
    return w_accs


def _levels_along(k0: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """(rows, n) and (cols, n) bool: whether each row and column of a lower-level index map k0
    (values in [0, n)) holds the index k; so a level's pixels lie in the box of its own rows and
    columns (a level of a receding ground is a band, however far the map's other levels reach)."""
    h, w = k0.shape
    rows, cols = np.zeros((h, n), bool), np.zeros(w * n, np.int64)
    col_base = np.arange(w, dtype=np.int64) * n
    step = max(1, (1 << 16) // max(w, 1))  # rows per block: small temporaries
    for r0 in range(0, h, step):
        block = k0[r0 : r0 + step] + col_base  # (rows, w): column c's level k at c * n + k
        cols += np.bincount(block.ravel(), minlength=w * n)
        block %= n
        block += (np.arange(r0, r0 + block.shape[0], dtype=np.int64) * n)[:, None]
        rows.reshape(-1)[block.ravel()] = True
    return rows, cols.reshape(w, n) > 0


LINE_GROUP_BYTES = 64 << 20  # `scatter_line` takes as many channels at once as fit in this (plane, spectra)


def scatter_line(read, shape, c_e, smax, apertures, outs, level_step, level_ratio):
    """`scatter_map` of a CoC map that varies along one axis only (c_e (he, 1) or (1, we): a
    ramp), with each pixel's disc weighted by the Jacobian of its parallax, 1 + p . grad(c); the
    weights are returned as a column or row.

    The kernels are shift-invariant along the other axis u, so E is transformed along u once
    (a real FFT of n_u >= E's length points: a kernel centred on 0 there wraps onto no output
    of O) and each level is convolved along its axis a in that domain: the strip of the level's
    pixels times its weight, an FFT of the strip plus the kernel's width, the product with the
    kernel's 2-D spectrum, the inverse. The levels' results add up in the u-spectrum and go back
    once. Small kernels (`fft.is_small`) are convolved directly instead, in space (so only the
    rows the FFT levels read go through the transform along u, and back). The weight's
    blur is a 1-D convolution with the kernel's projection on a. The work is laid out
    (C, a, u), u contiguous (the long transforms): E transposed for a horizontal ramp; channels
    go as many at a time as fit in LINE_GROUP_BYTES (E and two spectra each)."""
    a = 0 if c_e.shape[1] == 1 else 1  # the frame axis the CoC varies along
    u = 1 - a
    C = outs[0].shape[0]
    le_a, le_u = shape[a], shape[u]
    lo_a, lo_u = le_a - 2 * smax, le_u - 2 * smax  # O's size
    line = c_e[:, 0] if a == 0 else c_e[0]
    levels, k0, f = level_weights(line, level_step, level_ratio)
    # the slope of the CoC (px per px), for the Jacobian weight; None where it is 0
    g = np.clip(np.gradient(line.astype(np.float64)), -MAX_SLOPE, MAX_SLOPE).astype(np.float32) if line.size > 1 else None
    g = g if g is not None and np.any(g) else None
    plans = []  # per level: (radius, s, p0, p1, q0, q1, j0, small, passes per aperture)
    w_accs = [np.zeros(lo_a, np.float32) for _ in apertures]
    for k, ck in enumerate(levels):
        on = np.flatnonzero((k0 == k) | (k0 == k - 1))
        if on.size == 0:
            continue
        s = support_radius(ck)
        p0, p1 = max(int(on[0]), smax - s), min(int(on[-1]) + 1, smax + lo_a + s)  # pixels within s of O
        if p1 <= p0:
            continue
        wk = level_weight(k0[p0:p1], f[p0:p1], k)
        if not wk.any():
            continue
        gk = None if g is None else g[p0:p1]
        # per aperture, its passes (weight along a, kernel as (a, u)): K with the level's weight
        # and, where the slope varies, the first moment M with the weight times the slope; where
        # the slope is constant over the level's strip (a linear ramp, everywhere but where it
        # is clipped to [0, 1]), one pass, K + g M
        level_linear = gk is not None and _constant(gk)
        passes_of = []
        for aperture in apertures:
            kk = kernel(aperture, float(ck))
            passes = [(wk, kk)]
            if gk is not None:
                mk = kernel_moments(aperture, float(ck))[u]
                if float(np.abs(mk).max()) > 1e-6:  # (a disc's identity level has centroid 0: nothing)
                    passes = [(wk, kk + np.float32(gk.mean()) * mk)] if level_linear else [(wk, kk), (wk * gk, mk)]
            passes_of.append([(wv, kn if a == 0 else kn.T) for wv, kn in passes])
        # where the strip's blur lands in O along a (index j of its full convolution is E
        # position p0 - s + j)
        q0, q1 = max(p0 - s - smax, 0), min(p1 + s - smax, lo_a)
        j0 = q0 - (p0 - s - smax)
        for w_acc, passes in zip(w_accs, passes_of):
            for wv, kn in passes:
                w_acc[q0:q1] += np.convolve(wv, kn.sum(axis=1))[j0 : j0 + q1 - q0]
        small = is_small(*trimmed(passes_of[0][0][1]).shape)
        plans.append((float(ck), s, p0, p1, q0, q1, j0, small, passes_of))
    n_u = sfft.next_fast_len(le_u, real=True)
    nu2 = n_u // 2 + 1
    group = int(np.clip(LINE_GROUP_BYTES // (le_a * n_u * 4 + (le_a + lo_a) * nu2 * 8), 1, C))
    for c0 in range(0, C, group):
        chans = range(c0, min(c0 + group, C))
        # E as (G, a, u) in rows of n_u values, zero past le_u: the transform along u reads it
        # where it lies (scipy would copy it into a padded array)
        padded = np.empty((len(chans), le_a, n_u), np.float32)
        padded[:, :, le_u:] = 0.0
        x = padded[:, :, :le_u]
        if a == 0:
            read(chans, 0, shape[0], 0, shape[1], out=x)
        else:
            for ch, dst in zip(read(chans, 0, shape[0], 0, shape[1]), x):  # transposed into the stack
                res = cv2.transpose(ch, dst=dst)
                if res is not dst:
                    dst[...] = res
        # the group's sums in space, (G, lo_a, lo_u): the output itself for a vertical ramp
        res = [out[c0 : c0 + len(chans)] if a == 0 else np.zeros((len(chans), lo_a, lo_u), np.float32) for out in outs]
        for ck, s, p0, p1, q0, q1, j0, small, passes_of in plans:
            if not small:
                continue
            strips = {}  # per pass weight: the strip times it (the same for every aperture)
            for aperture, passes, r in zip(apertures, passes_of, res):
                for m, (wv, kn) in enumerate(passes):
                    if m not in strips:
                        strips[m] = x[:, p0:p1] * wv[:, None]
                    cv = Convolver(ck, aperture, p1 - p0, le_u, k=kn)
                    cv.add_stack_into(strips[m], r, p0 - smax - s, -smax - s)
        # the FFT levels' rows: E's they read (P0..P1) and O's they write (Q0..Q1), the only rows
        # transformed along u and back (each row on its own: the same values as the whole plane)
        big = [plan for plan in plans if not plan[7]]
        P0, P1 = (min(p[2] for p in big), max(p[3] for p in big)) if big else (0, 0)
        Q0, Q1 = (min(p[4] for p in big), max(p[5] for p in big)) if big else (0, 0)
        spec = None  # the group's spectrum along u, (G, P1 - P0, nu2), once a level needs it
        accs = [None] * len(apertures)  # per aperture: the FFT levels' sum in the u-spectrum, rows Q0..Q1
        for ck, s, p0, p1, q0, q1, j0, small, passes_of in big:
            if spec is None:
                spec = sfft.rfft(padded[:, P0:P1], axis=2)
            n_k = sfft.next_fast_len(p1 - p0 + 2 * s)
            fwd = {}  # per pass weight: the strip times it, transformed along a (n_k points)
            for i, passes in enumerate(passes_of):
                prod = None
                for m, (wv, kn) in enumerate(passes):
                    if m not in fwd:
                        buf = np.empty((len(chans), n_k, nu2), np.complex64)
                        # the real weight times both parts of each value (float32 views: the same
                        # products as a complex multiply by w + 0i, without its other terms)
                        np.multiply(spec[:, p0 - P0 : p1 - P0].view(np.float32), wv[:, None],
                                    out=buf[:, : p1 - p0].view(np.float32))
                        buf[:, p1 - p0 :] = 0.0
                        fwd[m] = sfft.fft(buf, axis=1, overwrite_x=True)
                    ks = line_spectrum(kn, s, n_u, n_k)
                    if prod is not None:
                        prod += fwd[m] * ks
                    elif i + 1 == len(passes_of):  # the last aperture: in place
                        prod = np.multiply(fwd[m], ks, out=fwd[m])
                    else:
                        prod = fwd[m] * ks
                back = sfft.ifft(prod, axis=1, overwrite_x=True)
                if accs[i] is None:
                    accs[i] = np.zeros((len(chans), Q1 - Q0, nu2), np.complex64)
                accs[i][:, q0 - Q0 : q1 - Q0] += back[:, j0 : j0 + q1 - q0]
        del x, padded, spec
        for i, (acc, r) in enumerate(zip(accs, res)):
            for j in range(len(chans) if acc is not None else 0):  # one channel at a time: memory
                r[j, Q0:Q1] += sfft.irfft(acc[j], n=n_u, axis=1)[:, smax : smax + lo_u]
            accs[i] = None
            if a == 1:
                for j, ch in enumerate(chans):
                    outs[i][ch] += cv2.transpose(r[j])
    return [w[:, None] if a == 0 else w[None, :] for w in w_accs]


SLOPE_TOLERANCE = 1e-5  # px per px: a slope varying less is taken as its mean (float32 CoC lines vary by ~1e-6)


def _constant(g: np.ndarray) -> bool:
    """Whether a slope profile is constant: within SLOPE_TOLERANCE, which changes the Jacobian
    weight 1 + p . g by at most 1e-5 (|p| <= 1), far below the level interpolation's error."""
    return float(g.max() - g.min()) <= SLOPE_TOLERANCE


def line_spectrum(k: np.ndarray, s: int, n_u: int, n_k: int) -> np.ndarray:
    """The 2-D DFT of kernel k ((2s+1)^2, axes (a, u)) that `scatter_line` multiplies by,
    (n_k, n_u // 2 + 1): an FFT of n_k points along a with the kernel starting at index 0, and
    a real FFT of n_u points along u with the kernel's centre at index 0 (its negative taps
    wrapped to the end)."""
    emb = np.zeros((2 * s + 1, n_u), np.float32)
    emb[:, : s + 1] = k[:, s:]
    emb[:, n_u - s :] = k[:, :s]
    return sfft.fft(sfft.rfft(emb, axis=1), n=n_k, axis=0)
