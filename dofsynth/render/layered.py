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
broadcast row or column). A constant map is one level, i.e. the exact constant result. For a
ramp (a broadcast row or column) each pixel's disc is also weighted by the Jacobian of its
parallax, 1 + p . grad(c) for the aperture point p it reaches (`kernel_moments`): what a thin lens
gathers from a slanted plane, which a plain scatter lacks. The approximations are the linear
interpolation of kernels between levels and the first-order Jacobian (docs/rendering.md).
No torch here: this module is on the data-generation path.
"""
from __future__ import annotations

import numpy as np

from dofsynth.optics.coc import coc_radius
from dofsynth.optics.kernel import kernel, kernel_moments, support_radius
from dofsynth.render.fft import Convolver, copy_tile
from dofsynth.render.frame import add_clipped, compact, grab, is_one
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
    the frame colour, alpha and the CoC map are edge-replicated). A map that is a broadcast row or column (a ramp) keeps its
    levels as one row or column."""
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
    he, we = ey1 - ey0, ex1 - ex0
    iy = np.clip(np.arange(ey0, ey1), 0, H - 1) if cm.shape[0] > 1 else np.zeros(1, np.intp)
    ix = np.clip(np.arange(ex0, ex1), 0, W - 1) if cm.shape[1] > 1 else np.zeros(1, np.intp)
    c_e = cm[np.ix_(iy, ix)]  # compact along broadcast axes
    levels, k0c, fc = level_weights(c_e, level_step, level_ratio)
    one = backmost and is_one(alpha)
    # A map constant along x (or y) has weights constant along it: the weight channel's blur
    # is then a 1-D convolution with the kernel's projection (no FFT), kept as a column/row.
    along = 0 if c_e.shape[1] == 1 else (1 if c_e.shape[0] == 1 else None)
    # The slope of a ramp's CoC (px per px), for the Jacobian weight; None for 2-D maps.
    slope = None
    if along is not None and c_e.size > 1:
        line = c_e[:, 0] if along == 0 else c_e[0]
        g = np.clip(np.gradient(line.astype(np.float64)), -MAX_SLOPE, MAX_SLOPE).astype(np.float32)
        slope = g[:, None] if along == 0 else g[None, :]
        slope = slope if np.any(slope) else None
    # Accumulators over O, per aperture: premultiplied colour (straight into acc for the
    # backmost plane: acc is still black), alpha (not for an opaque backmost plane) and weight.
    oh, ow = oy1 - oy0, ox1 - ox0
    cols = [acc[:, oy0:oy1, ox0:ox1] if backmost else np.zeros((3, oh, ow), np.float32) for acc in accs]
    a_accs = [None if backmost else np.zeros((oh, ow), np.float32) for _ in accs]
    w_accs = [np.zeros((oh, 1) if along == 0 else (1, ow) if along == 1 else (oh, ow), np.float32) for _ in accs]
    # Level k touches pixels with k0 in {k-1, k}: a superset box from per-row/column ranges.
    rlo, rhi = k0c.min(axis=1), k0c.max(axis=1) + 1
    clo, chi = k0c.min(axis=0), k0c.max(axis=0) + 1
    if rlo.size == 1:
        rlo, rhi = np.broadcast_to(rlo, he), np.broadcast_to(rhi, he)
    if clo.size == 1:
        clo, chi = np.broadcast_to(clo, we), np.broadcast_to(chi, we)
    for k, ck in enumerate(levels):
        rows = np.flatnonzero((rlo <= k) & (rhi >= k))
        cols_k = np.flatnonzero((clo <= k) & (chi >= k))
        if rows.size == 0 or cols_k.size == 0:
            continue
        s = support_radius(ck)
        # only pixels within s of O reach it: E is O grown by smax >= s
        y0, y1 = max(int(rows[0]), smax - s), min(int(rows[-1]) + 1, smax + oh + s)
        x0, x1 = max(int(cols_k[0]), smax - s), min(int(cols_k[-1]) + 1, smax + ow + s)
        if y1 <= y0 or x1 <= x0:
            continue
        sub = (slice(y0, y1) if k0c.shape[0] > 1 else slice(None), slice(x0, x1) if k0c.shape[1] > 1 else slice(None))
        ksub, fsub = k0c[sub], fc[sub]  # compact along a broadcast axis
        wsub = np.where(ksub == k, 1.0 - fsub, 0.0).astype(np.float32)
        wsub += np.where(ksub == k - 1, fsub, 0.0)
        if not wsub.any():
            continue
        # frame coordinates of the strip, and where its blur lands in O
        fy0, fy1, fx0, fx1 = y0 + ey0, y1 + ey0, x0 + ex0, x1 + ex0
        ty0, tx0 = fy0 - s - oy0, fx0 - s - ox0
        a_sub = None if one else grab(alpha, fy0, fy1, fx0, fx1, True)
        g = None if slope is None else slope[sub]
        sources = {}  # per pass weight (the level's, or times the slope): weight, alpha weight, weighted colour

        def source(which):
            if which not in sources:
                wk = wsub if which == 0 else wsub * g
                wa = np.broadcast_to(wk if one else wk * a_sub, (y1 - y0, x1 - x0))
                src = np.empty((3, y1 - y0, x1 - x0), np.float32)
                for ch in range(3):  # each channel read once, then weighted
                    grab(rgb[:, :, ch], fy0, fy1, fx0, fx1, True, src[ch])
                    src[ch] *= wa
                sources[which] = wk, wa, src
            return sources[which]

        for aperture, col, a_acc, w_acc in zip(apertures, cols, a_accs, w_accs):
            kk = kernel(aperture, float(ck))
            passes = [(kk, 0)]
            if g is not None:  # the Jacobian's first-order term: the p-moment kernel times the slope
                mk = kernel_moments(aperture, float(ck))[1 - along]
                if float(np.abs(mk).max()) > 1e-6:  # (a disc's identity level has centroid 0: nothing)
                    if float(g.max() - g.min()) <= 1e-6 * max(float(np.abs(g).max()), 1e-6):
                        passes = [(kk + np.float32(g.flat[0]) * mk, 0)]  # a linear ramp: one pass, K + g M
                    else:
                        passes.append((mk, 1))
            for kp, which in passes:  # weight, alpha and colour of each pass
                cv = Convolver(float(ck), aperture, y1 - y0, x1 - x0, k=kp)
                wk, wa, src = source(which)
                if along == 0:
                    add_clipped(w_acc, ty0, 0, np.convolve(wk[:, 0], cv.k.sum(axis=1))[:, None])
                elif along == 1:
                    add_clipped(w_acc, 0, tx0, np.convolve(wk[0], cv.k.sum(axis=0))[None, :])
                else:
                    cv.add_into(copy_tile(wk), w_acc, ty0, tx0)
                if a_acc is not None:
                    cv.add_into(copy_tile(wa), a_acc, ty0, tx0)
                cv.add_stack_into(src, col, ty0, tx0)
    for acc, col, a_acc, w_acc in zip(accs, cols, a_accs, w_accs):
        np.maximum(w_acc, 1e-12, out=w_acc)
        inv = np.reciprocal(w_acc, out=w_acc)
        if backmost:
            col *= inv[None]
            continue
        a_acc *= inv
        inv = np.broadcast_to(inv, (oh, ow))
        region = acc[:, oy0:oy1, ox0:ox1]
        keep = 1.0 - a_acc
        for ch in range(3):
            col[ch] *= inv
            region[ch] *= keep
            region[ch] += col[ch]


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
