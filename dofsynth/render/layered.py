"""The layered depth-of-field renderer: blur each plane on its own, composite back to front.

`render_layered(planes, focus, max_coc, aperture, options)` returns linear RGB (3, H, W)
float32. Each plane's premultiplied (colour * alpha, alpha) is blurred with the aperture kernel
of its signed CoC radius (dofsynth.optics.coc_radius) in pixels, then the blurred
planes are composited with "over". Every plane extends past the frame by edge replication: the
background, and a cutout where it reaches the frame's edge (an object cut by the frame goes on
beyond it, so its blurred edge does not fade there and show what lies behind).

Constant-disparity planes are convolved exactly (float32 FFT, overlap-save tiles for large
ones; cv2 for tiny kernels), cropped to the plane's alpha bounding box plus the kernel radius,
one channel at a time. Planes whose disparity varies use a normalized scatter: the signed CoC
is split into levels `c_k` of one grid fixed in CoC (shared by all planes and samples, so
their kernels are computed once per process), at most `max(level_step, level_ratio * |c_k|)`
pixels apart; each pixel is shared between its two
neighbouring levels with linear weights `w_k`, and `out = sum_k K_k * (w_k P) / sum_k K_k * w_k`
(the denominator is the same scatter applied to ones; a 1-D convolution when the map is a
broadcast row or column). A constant map is one level, i.e. the exact constant result. A ramp
(a broadcast row or column) is transformed once along the axis it is constant on and each level
convolved along the ramp in that spectrum (`_scatter_line`); each pixel's disc is also weighted by the Jacobian of its
parallax, 1 + p . grad(c) for the aperture point p it reaches (`kernel_moments`): what a thin lens
gathers from a slanted plane, which a plain scatter lacks. The approximations are the linear
interpolation of kernels between levels and the first-order Jacobian (docs/rendering.md).
No torch here: this module is on the data-generation path.
"""
from __future__ import annotations

import cv2
import numpy as np
import scipy.fft as sfft

from dofsynth.optics.coc import coc_radius
from dofsynth.optics.kernel import kernel, kernel_moments, support_radius
from dofsynth.render.fft import Convolver, copy_tile, is_small, trimmed
from dofsynth.render.frame import compact, grab, is_one
from dofsynth.render.planes import alpha_box

# Default relative level spacing of varying-disparity planes (RenderOptions.level_ratio).
LEVEL_RATIO = 1.0 / 32.0


def _composite_constant(acc, rgb, alpha, box, c, aperture, backmost, margin: int = 0) -> None:
    """Blur a constant-CoC plane over its alpha box and composite it "over" `acc` (3, H, W),
    one channel at a time: the blurred alpha first, then each premultiplied colour."""
    _, H, W = acc.shape
    s = support_radius(c)
    # the frame for the backmost plane (its box), else the alpha box; edge-replicated S px
    # beyond each frame edge it touches; its blur lands in O (`kept_regions` when the planes go
    # on past the part of the result that is kept)
    (gy0, gy1, gx0, gx1), (oy0, oy1, ox0, ox1) = kept_regions(box, s, H, W, margin)
    if oy1 <= oy0 or ox1 <= ox0:
        return
    h, w = gy1 - gy0, gx1 - gx0
    conv = Convolver(c, aperture, h, w)
    if backmost:  # acc is still black: add the blur straight into it, tile by tile
        one = is_one(alpha)
        for ch in range(3):
            def tile(y0, y1, x0, x1, out, ch=ch):
                grab(rgb[:, :, ch], gy0 + y0, gy0 + y1, gx0 + x0, gx0 + x1, True, out)
                if not one:
                    out *= grab(alpha, gy0 + y0, gy0 + y1, gx0 + x0, gx0 + x1, True)
            conv.add_into(tile, acc[ch, oy0:oy1, ox0:ox1], gy0 - s - oy0, gx0 - s - ox0)
        return
    # a cutout: acc *= 1 - blur(alpha), then acc += blur(colour * alpha), over O (the blurs
    # are added straight into acc, tile by tile)
    a_src = np.ascontiguousarray(grab(alpha, gy0, gy1, gx0, gx1, True), dtype=np.float32)
    keep = np.zeros((oy1 - oy0, ox1 - ox0), np.float32)
    conv.add_into(copy_tile(a_src), keep, gy0 - s - oy0, gx0 - s - ox0)
    np.subtract(np.float32(1.0), keep, out=keep)
    for ch in range(3):
        acc[ch, oy0:oy1, ox0:ox1] *= keep
        src = grab(rgb[:, :, ch], gy0, gy1, gx0, gx1, True)
        conv.add_into(lambda y0, y1, x0, x1, out: np.multiply(src[y0:y1, x0:x1], a_src[y0:y1, x0:x1], out=out),
                      acc[ch, oy0:oy1, ox0:ox1], gy0 - s - oy0, gx0 - s - ox0)


_GRIDS: dict[tuple[float, float], np.ndarray] = {}  # (level_step, level_ratio) -> its levels >= 0 so far


def _positive_levels(level_step: float, level_ratio: float, reach: float) -> np.ndarray:
    """The grid's levels >= 0 (px), from 0 to the first one >= reach: g_0 = 0 and
    g_{k+1} = g_k + max(level_step, level_ratio * g_k); computed once per spacing and extended
    as larger radii come (the same float values every time)."""
    key = (float(level_step), float(level_ratio))
    grid = _GRIDS.get(key)
    if grid is None or grid[-1] < reach:
        levels = [0.0] if grid is None else grid.tolist()
        while levels[-1] < reach:
            c = levels[-1]
            levels.append(c + max(level_step, level_ratio * c))
        grid = _GRIDS[key] = np.array(levels)
    return grid


def level_grid(cmin: float, cmax: float, level_step: float, level_ratio: float = 0.0) -> np.ndarray:
    """CoC levels (pixels) covering [c_min, c_max], taken from one grid that every plane of every
    sample shares (so each level's kernels are computed once per process and cached): 0 and
    +-g_k, g_{k+1} = g_k + max(level_step, level_ratio * g_k), from the last level <= c_min to
    the first >= c_max. With level_ratio 0 the step is fixed; above 0 it grows with the radius,
    where neighbouring kernels differ relatively less. A constant map (c_min = c_max) is the one
    level c_min itself."""
    if cmax <= cmin:
        return np.array([float(cmin)])
    pos = _positive_levels(level_step, level_ratio, max(abs(cmin), abs(cmax)))
    grid = np.concatenate([-pos[:0:-1], pos])
    lo = int(np.searchsorted(grid, cmin, side="right")) - 1  # the last level <= c_min
    hi = int(np.searchsorted(grid, cmax, side="left"))  # the first level >= c_max
    return grid[lo : hi + 1]


def level_weights(cmap: np.ndarray, level_step: float, level_ratio: float = 0.0):
    """CoC levels (pixels, `level_grid`) covering [c_min, c_max], and for each pixel its lower
    level index k0 and the weight f of level k0+1 (1 - f goes to level k0), linear in the
    pixel's CoC between the two levels.

    The levels lie on a grid fixed in CoC, so the result is continuous in focus, max_coc and
    the map (a level enters or leaves with weight 0) except where a map becomes constant: that
    is a single level, the constant-plane result, which a map varying by a hair differs from by
    the interpolation between its two grid levels (docs/rendering.md bounds it).
    """
    cmin, cmax = float(cmap.min()), float(cmap.max())
    levels = level_grid(cmin, cmax, level_step, level_ratio)
    if levels.size == 1:
        return levels, np.zeros(cmap.shape, np.int32), np.zeros(cmap.shape, np.float32)
    n = levels.size
    c = cmap.astype(np.float64)
    k0 = np.clip(np.searchsorted(levels, c, side="right") - 1, 0, n - 2).astype(np.int32)
    f = np.clip((c - levels[k0]) / (levels[k0 + 1] - levels[k0]), 0.0, 1.0).astype(np.float32)
    return levels, k0, f


MAX_SLOPE = 0.5  # |grad c| (px per px) the Jacobian weight uses at most: it stays >= 1/2


def _composite_varying(accs, rgb, alpha, dmap, box, max_coc, focus, apertures, backmost, level_step,
                       level_ratio, margin: int = 0) -> None:
    """Normalized level scatter of a plane with a disparity map, composited "over" each of
    `accs` through the matching one of `apertures` (the levels, their weights and each level's
    weighted colour are computed once for all of them).

    Work region: O, the output (the frame for the backmost plane, else the alpha box grown by
    the largest kernel), and E, O grown by that kernel again (the pixels that reach O; outside
    the frame colour, alpha and the CoC map are edge-replicated). A map that is a broadcast row
    or column (a ramp) keeps its levels as one row or column and is scattered by `_scatter_line`,
    a 2-D map by `_scatter_map`."""
    _, H, W = accs[0].shape
    cm = coc_radius(compact(np.asarray(dmap, dtype=np.float32)), focus, max_coc)
    smax = support_radius(max(abs(float(cm.min())), abs(float(cm.max()))))
    kept = margin if margin >= smax else 0  # the result is kept only inside this margin
    if backmost:
        oy0, oy1, ox0, ox1 = kept, H - kept, kept, W - kept
    else:
        oy0, oy1 = max(box[0] - smax, kept), min(box[1] + smax, H - kept)
        ox0, ox1 = max(box[2] - smax, kept), min(box[3] + smax, W - kept)
    if oy1 <= oy0 or ox1 <= ox0:
        return
    ey0, ey1, ex0, ex1 = oy0 - smax, oy1 + smax, ox0 - smax, ox1 + smax
    iy = np.clip(np.arange(ey0, ey1), 0, H - 1) if cm.shape[0] > 1 else np.zeros(1, np.intp)
    ix = np.clip(np.arange(ex0, ex1), 0, W - 1) if cm.shape[1] > 1 else np.zeros(1, np.intp)
    c_e = cm[np.ix_(iy, ix)]  # compact along broadcast axes
    one = backmost and is_one(alpha)

    def read(chans, y0, y1, x0, x1):
        """E[y0:y1, x0:x1]'s premultiplied colour (channels 0-2) and alpha (3), the channels
        `chans`, (len(chans), h, w)."""
        out = np.empty((len(chans), y1 - y0, x1 - x0), np.float32)
        a = None if one else grab(alpha, ey0 + y0, ey0 + y1, ex0 + x0, ex0 + x1, True)
        for j, ch in enumerate(chans):
            if ch == 3:
                out[j] = a
                continue
            grab(rgb[:, :, ch], ey0 + y0, ey0 + y1, ex0 + x0, ex0 + x1, True, out[j])
            if a is not None:
                out[j] *= a
        return out

    # the unnormalized sums over O: colour (and alpha unless the plane is the opaque backmost
    # one), straight into acc for the backmost plane (acc is still black)
    outs = [acc[:, oy0:oy1, ox0:ox1] if one else np.zeros((4, oy1 - oy0, ox1 - ox0), np.float32)
            for acc in accs]
    along = 0 if c_e.shape[1] == 1 else (1 if c_e.shape[0] == 1 else None)
    scatter = _scatter_map if along is None else _scatter_line
    w_accs = scatter(read, (ey1 - ey0, ex1 - ex0), c_e, smax, apertures, outs, level_step, level_ratio)
    oh, ow = oy1 - oy0, ox1 - ox0
    for acc, res, w_acc in zip(accs, outs, w_accs):
        np.maximum(w_acc, 1e-12, out=w_acc)
        inv = np.broadcast_to(np.reciprocal(w_acc, out=w_acc), (oh, ow))
        if one:
            res *= inv
            continue
        region = acc[:, oy0:oy1, ox0:ox1]
        keep = 1.0 - res[3] * inv
        for ch in range(3):
            region[ch] *= keep
            region[ch] += res[ch] * inv


def _level_weight(k0: np.ndarray, f: np.ndarray, k: int) -> np.ndarray:
    """Level k's linear weight of pixels with lower level index k0 and fraction f (float32)."""
    return np.where(k0 == k, 1.0 - f, 0.0).astype(np.float32) + np.where(k0 == k - 1, f, 0.0).astype(np.float32)


def _scatter_map(read, shape, c_e, smax, apertures, outs, level_step, level_ratio):
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
    rlo, rhi = k0c.min(axis=1), k0c.max(axis=1) + 1
    clo, chi = k0c.min(axis=0), k0c.max(axis=0) + 1
    for k, ck in enumerate(levels):
        rows = np.flatnonzero((rlo <= k) & (rhi >= k))
        cols = np.flatnonzero((clo <= k) & (chi >= k))
        if rows.size == 0 or cols.size == 0:
            continue
        s = support_radius(ck)
        # only pixels within s of O reach it: E is O grown by smax >= s
        y0, y1 = max(int(rows[0]), smax - s), min(int(rows[-1]) + 1, smax + oh + s)
        x0, x1 = max(int(cols[0]), smax - s), min(int(cols[-1]) + 1, smax + ow + s)
        if y1 <= y0 or x1 <= x0:
            continue
        wk = _level_weight(k0c[y0:y1, x0:x1], fc[y0:y1, x0:x1], k)
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


LINE_GROUP_BYTES = 64 << 20  # `_scatter_line` takes as many channels at once as fit in this (plane, spectra)


def _scatter_line(read, shape, c_e, smax, apertures, outs, level_step, level_ratio):
    """`_scatter_map` of a CoC map that varies along one axis only (c_e (he, 1) or (1, we): a
    ramp), with each pixel's disc weighted by the Jacobian of its parallax, 1 + p . grad(c); the
    weights are returned as a column or row.

    The kernels are shift-invariant along the other axis u, so E is transformed along u once
    (a real FFT of n_u >= E's length points: a kernel centred on 0 there wraps onto no output
    of O) and each level is convolved along its axis a in that domain: the strip of the level's
    pixels times its weight, an FFT of the strip plus the kernel's width, the product with the
    kernel's 2-D spectrum, the inverse. The levels' results add up in the u-spectrum and go back
    once. Small kernels (`fft.is_small`) are convolved directly instead, in space. The weight's
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
    linear = g is not None and float(g.max() - g.min()) <= 1e-6 * max(float(np.abs(g).max()), 1e-6)
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
        wk = _level_weight(k0[p0:p1], f[p0:p1], k)
        if not wk.any():
            continue
        gk = None if g is None else g[p0:p1]
        # per aperture, its passes (weight along a, kernel as (a, u)): K with the level's weight
        # and, where the slope varies, the first moment M with the weight times the slope (on a
        # linear ramp one pass, K + g M)
        passes_of = []
        for aperture in apertures:
            kk = kernel(aperture, float(ck))
            passes = [(wk, kk)]
            if gk is not None:
                mk = kernel_moments(aperture, float(ck))[u]
                if float(np.abs(mk).max()) > 1e-6:  # (a disc's identity level has centroid 0: nothing)
                    passes = [(wk, kk + np.float32(gk[0]) * mk)] if linear else [(wk, kk), (wk * gk, mk)]
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
    group = int(np.clip(LINE_GROUP_BYTES // (le_a * le_u * 4 + (le_a + lo_a) * nu2 * 8), 1, C))
    for c0 in range(0, C, group):
        chans = range(c0, min(c0 + group, C))
        x = read(chans, 0, shape[0], 0, shape[1])
        if a == 1:  # (G, a, u)
            x = np.stack([cv2.transpose(ch) for ch in x])
        # the group's sums in space, (G, lo_a, lo_u): the output itself for a vertical ramp
        res = [out[c0 : c0 + len(chans)] if a == 0 else np.zeros((len(chans), lo_a, lo_u), np.float32) for out in outs]
        for ck, s, p0, p1, q0, q1, j0, small, passes_of in plans:
            if not small:
                continue
            for aperture, passes, r in zip(apertures, passes_of, res):
                for wv, kn in passes:
                    cv = Convolver(ck, aperture, p1 - p0, le_u, k=kn)
                    cv.add_stack_into(x[:, p0:p1] * wv[:, None], r, p0 - smax - s, -smax - s)
        spec = None  # the group's spectrum along u, (G, le_a, nu2), once a level needs it
        accs = [None] * len(apertures)  # per aperture: the FFT levels' sum in the u-spectrum
        for ck, s, p0, p1, q0, q1, j0, small, passes_of in plans:
            if small:
                continue
            if spec is None:
                spec = sfft.rfft(x, n=n_u, axis=2)
            n_k = sfft.next_fast_len(p1 - p0 + 2 * s)
            fwd = {}  # per pass weight: the strip times it, transformed along a (n_k points)
            for i, passes in enumerate(passes_of):
                prod = None
                for m, (wv, kn) in enumerate(passes):
                    if m not in fwd:
                        buf = np.empty((len(chans), n_k, nu2), np.complex64)
                        np.multiply(spec[:, p0:p1], wv[:, None], out=buf[:, : p1 - p0])
                        buf[:, p1 - p0 :] = 0.0
                        fwd[m] = sfft.fft(buf, axis=1, overwrite_x=True)
                    ks = _line_spectrum(kn, s, n_u, n_k)
                    if prod is not None:
                        prod += fwd[m] * ks
                    elif i + 1 == len(passes_of):  # the last aperture: in place
                        prod = np.multiply(fwd[m], ks, out=fwd[m])
                    else:
                        prod = fwd[m] * ks
                back = sfft.ifft(prod, axis=1, overwrite_x=True)
                if accs[i] is None:
                    accs[i] = np.zeros((len(chans), lo_a, nu2), np.complex64)
                accs[i][:, q0:q1] += back[:, j0 : j0 + q1 - q0]
        del x, spec
        for i, (acc, r) in enumerate(zip(accs, res)):
            for j in range(len(chans) if acc is not None else 0):  # one channel at a time: memory
                r[j] += sfft.irfft(acc[j], n=n_u, axis=1)[:, smax : smax + lo_u]
            accs[i] = None
            if a == 1:
                for j, ch in enumerate(chans):
                    outs[i][ch] += cv2.transpose(r[j])
    return [w[:, None] if a == 0 else w[None, :] for w in w_accs]


def _line_spectrum(k: np.ndarray, s: int, n_u: int, n_k: int) -> np.ndarray:
    """The 2-D DFT of kernel k ((2s+1)^2, axes (a, u)) that `_scatter_line` multiplies by,
    (n_k, n_u // 2 + 1): an FFT of n_k points along a with the kernel starting at index 0, and
    a real FFT of n_u points along u with the kernel's centre at index 0 (its negative taps
    wrapped to the end)."""
    emb = np.zeros((2 * s + 1, n_u), np.float32)
    emb[:, : s + 1] = k[:, s:]
    emb[:, n_u - s :] = k[:, :s]
    return sfft.fft(sfft.rfft(emb, axis=1), n=n_k, axis=0)


def plane_box(plane, alpha: np.ndarray):
    """(y0, y1, x0, x1): the bounding box of a cutout's alpha > 0 (searched inside its `box`
    when it has one), or None when it is fully transparent."""
    if plane.box is None:
        return alpha_box(alpha)
    by0, by1, bx0, bx1 = (int(v) for v in plane.box)
    inner = alpha_box(alpha[by0:by1, bx0:bx1]) if by1 > by0 and bx1 > bx0 else None
    return None if inner is None else (by0 + inner[0], by0 + inner[1], bx0 + inner[2], bx0 + inner[3])


def kept_regions(box, s: int, H: int, W: int, margin: int = 0):
    """`cutout_regions`, or, when the planes go on `margin` >= s px past the part of the result
    that is kept: the box itself as input (nothing beyond the planes reaches what is kept) and
    its blur footprint clipped to that part."""
    if margin < s or margin == 0:
        return cutout_regions(box, s, H, W)
    y0, y1, x0, x1 = box
    return (y0, y1, x0, x1), (max(y0 - s, margin), min(y1 + s, H - margin), max(x0 - s, margin), min(x1 + s, W - margin))


def cutout_regions(box, s: int, H: int, W: int):
    """For a cutout's alpha box and a kernel of support radius s: the input box G (the alpha
    box, edge-replicated s px beyond each frame edge it touches) and the output box O (G's
    blur footprint clipped to the frame), each (y0, y1, x0, x1)."""
    y0, y1, x0, x1 = box
    gy0, gy1 = (-s if y0 == 0 else y0), (H + s if y1 == H else y1)
    gx0, gx1 = (-s if x0 == 0 else x0), (W + s if x1 == W else x1)
    return (gy0, gy1, gx0, gx1), (max(gy0 - s, 0), min(gy1 + s, H), max(gx0 - s, 0), min(gx1 + s, W))


def render_layered(planes, focus: float, max_coc: float, aperture, options) -> np.ndarray:
    """The layered render of validated planes (back to front): linear RGB (3, H, W) float32,
    the premultiplied composite over black. `options`: a dofsynth.render.RenderOptions (its
    level_step and level_ratio; its `margin`: the planes go on that many px past the part of
    the result the caller keeps, which is then all that is computed: the rest stays 0)."""
    return render_layered_each(planes, focus, max_coc, [aperture], options)[0]


def render_layered_each(planes, focus: float, max_coc: float, apertures, options) -> list[np.ndarray]:
    """`render_layered` of the same planes through each of `apertures` (the sub-aperture
    method's cells): a plane with a disparity map shares its levels' weights and weighted
    colours among them. The same values as one render per aperture."""
    H, W = planes[0].shape
    accs = [np.zeros((3, H, W), dtype=np.float32) for _ in apertures]  # planar: contiguous per-channel updates
    for i, plane in enumerate(planes):
        backmost = i == 0
        alpha = np.asarray(plane.alpha, dtype=np.float32)
        rgb = np.asarray(plane.rgb, dtype=np.float32)
        box = (0, H, 0, W) if backmost else plane_box(plane, alpha)
        if box is None:  # fully transparent: nothing to add
            continue
        d = plane.constant_disparity()
        if d is not None:
            for acc, aperture in zip(accs, apertures):
                _composite_constant(acc, rgb, alpha, box, coc_radius(d, focus, max_coc), aperture, backmost,
                                    options.margin)
        else:
            _composite_varying(accs, rgb, alpha, plane.disparity_map(), box, max_coc, focus, apertures,
                               backmost, options.level_step, options.level_ratio, options.margin)
    return accs
