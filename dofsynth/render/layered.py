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
convolved along the ramp in that spectrum (`scatter.scatter_line`); each pixel's disc is also weighted by the Jacobian of its
parallax, 1 + p . grad(c) for the aperture point p it reaches (`kernel_moments`): what a thin lens
gathers from a slanted plane, which a plain scatter lacks. The approximations are the linear
interpolation of kernels between levels and the first-order Jacobian (docs/rendering.md).
No torch here: this module is on the data-generation path.
"""
from __future__ import annotations

import numpy as np

from dofsynth.optics.coc import coc_radius
from dofsynth.optics.kernel import support_radius
from dofsynth.render.fft import Convolver, copy_tile
from dofsynth.render.frame import compact, grab, is_one
from dofsynth.render.planes import alpha_box
from dofsynth.render.scatter import scatter_line, scatter_map

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


def _composite_varying(accs, rgb, alpha, dmap, box, max_coc, focus, apertures, backmost, level_step,
                       level_ratio, margin: int = 0) -> None:
    """Normalized level scatter of a plane with a disparity map, composited "over" each of
    `accs` through the matching one of `apertures` (the levels, their weights and each level's
    weighted colour are computed once for all of them).

    Work region: O, the output (the frame for the backmost plane, else the alpha box grown by
    the largest kernel), and E, O grown by that kernel again (the pixels that reach O; outside
    the frame colour, alpha and the CoC map are edge-replicated). A map that is a broadcast row
    or column (a ramp) keeps its levels as one row or column and is scattered by `scatter.scatter_line`,
    a 2-D map by `scatter.scatter_map`."""
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

    def read(chans, y0, y1, x0, x1, out=None):
        """E[y0:y1, x0:x1]'s premultiplied colour (channels 0-2) and alpha (3), the channels
        `chans`, (len(chans), h, w): written into `out` when given (any strides)."""
        if out is None:
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
    scatter = scatter_map if along is None else scatter_line
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
