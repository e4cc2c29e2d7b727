"""Each plane of a layered scene blurred through every cell of an aperture split (the
convolutions of the sub-aperture and adaptive methods, dofsynth.render.subaperture): the
backmost plane (`back_cells`: its premultiplied colour per cell) and each cutout
(`cutout_cells`: per cell its premultiplied colour, alpha and the alpha's first moments about
the cell's centroid, as the second-order composite takes them). Constant-disparity planes are
blurred for all cells in one batched FFT (`fft.convolve_stack`) within BATCH_MAX; planes with a
disparity map by the layered scatter per cell. With m > 0 (the planes go on m px past the part
computed, m at least every kernel's support radius) only rows and columns m .. -m are computed.
"""
from __future__ import annotations

import math
from dataclasses import replace
from functools import lru_cache

import numpy as np

from dofsynth.optics.aperture import Aperture
from dofsynth.optics.coc import coc_radius
from dofsynth.optics.kernel import kernel, kernel_moments, support_radius
from dofsynth.render.fft import Convolver, convolve_stack, copy_tile, is_small, stack_fits, trim_box, trimmed
from dofsynth.render.frame import grab, is_one
from dofsynth.render.layered import cutout_regions, render_layered_each
from dofsynth.render.planes import Plane


@lru_cache(maxsize=512)
def _cell_kernels(cell: Aperture, c: float) -> tuple[np.ndarray, tuple[int, int, int, int]]:
    """(3, kh, kw): the cell's kernel of CoC c and its alpha-moment kernels about the cell's
    centroid (Mx - cx K, My - cy K: K (p - p_cell) in effect; each sums to 0), cut to the
    kernel's non-zero box, which is returned (y0, x0, y1, x1) in the (2S+1)^2 array. A cell
    of a shape that is its own mirror image (`Aperture.mirrored`) lying left of (or above) the
    centre is its mirror cell's kernels flipped (the moment across the flip negated): one of
    the four 2 x 2 cells (one of two halves) is computed, the others equal it to rounding."""
    mirrored = getattr(getattr(cell, "base", None), "mirrored", False) and hasattr(cell, "x1")  # a grid cell of one
    flip_x = mirrored and cell.x1 <= 0.0
    flip_y = mirrored and cell.y1 <= 0.0
    if flip_x or flip_y:
        mirror = replace(cell, **({"x0": -cell.x1, "x1": -cell.x0} if flip_x else {}),
                         **({"y0": -cell.y1, "y1": -cell.y0} if flip_y else {}))
        ks, (y0, x0, y1, x1) = _cell_kernels(mirror, c)
        n = 2 * support_radius(c) + 1
        if flip_x:
            ks, (x0, x1) = ks[:, :, ::-1] * np.float32([1, -1, 1])[:, None, None], (n - x1, n - x0)
        if flip_y:
            ks, (y0, y1) = ks[:, ::-1, :] * np.float32([1, 1, -1])[:, None, None], (n - y1, n - y0)
        ks = np.ascontiguousarray(ks)
        ks.setflags(write=False)
        return ks, (y0, x0, y1, x1)
    k = kernel(cell, c)
    box = trim_box(k)
    centred = [m - np.float32(math.fsum(m.ravel().tolist())) * k for m in kernel_moments(cell, c)]
    return np.stack([trimmed(m, box) for m in [k] + centred]), box


_PAIRS = [(0, 0), (0, 1), (0, 2), (0, 3), (1, 3), (2, 3)]  # K * (colour * alpha, alpha), moments * alpha


def cutout_reach(box, s: int, H: int, W: int, m: int):
    """(G, O), each (y0, y1, x0, x1): the input box a cutout's blur of support radius s reads
    and the output box it lands in. m = 0: `cutout_regions` (the whole frame); m >= s (only
    rows and columns m .. -m are computed, the planes going on past them): O is the alpha box
    grown by s inside them, G the part of the alpha box that reaches O."""
    if m == 0:
        return cutout_regions(box, s, H, W)
    y0, y1, x0, x1 = box
    oy0, oy1, ox0, ox1 = max(y0 - s, m), min(y1 + s, H - m), max(x0 - s, m), min(x1 + s, W - m)
    return (max(y0, oy0 - s), min(y1, oy1 + s), max(x0, ox0 - s), min(x1, ox1 + s)), (oy0, oy1, ox0, ox1)


def _blur_into(out: np.ndarray, region, src: np.ndarray, ks: np.ndarray, pairs, start) -> None:
    """out (len(pairs), h, w), frame box `region` (y0, y1, x0, x1) += the full convolutions of
    src's channels by ks (`convolve_stack` pairs) whose output (0, 0) lands on frame pixel
    `start` (y, x): only the part inside the region is computed."""
    y0, y1, x0, x1 = region
    sy, sx = start
    a0, b0 = max(y0 - sy, 0), min(y1 - sy, src.shape[1] + ks.shape[1] - 1)
    a1, b1 = max(x0 - sx, 0), min(x1 - sx, src.shape[2] + ks.shape[2] - 1)
    if b0 > a0 and b1 > a1:
        out[:, sy + a0 - y0 : sy + b0 - y0, sx + a1 - x0 : sx + b1 - x0] += convolve_stack(
            src, ks, pairs, window=(a0, b0, a1, b1))


def _back_source(plane, g) -> np.ndarray:
    """(3, h, w) float32 over frame box g: the backmost plane's premultiplied colour (edge
    pixels past the frame; the colour itself where the plane is opaque)."""
    gy0, gy1, gx0, gx1 = g
    rgb, alpha = np.asarray(plane.rgb, np.float32), np.asarray(plane.alpha, np.float32)
    src = np.empty((3, gy1 - gy0, gx1 - gx0), np.float32)
    for ch in range(3):
        grab(rgb[:, :, ch], gy0, gy1, gx0, gx1, True, src[ch])
    if not is_one(alpha):
        src *= grab(alpha, gy0, gy1, gx0, gx1, True)
    return src


def _cutout_source(plane, g) -> np.ndarray:
    """(4, h, w) float32 over frame box g: the premultiplied colour and the alpha (edge pixels
    past the frame)."""
    gy0, gy1, gx0, gx1 = g
    a, rgb = np.asarray(plane.alpha, np.float32), np.asarray(plane.rgb, np.float32)
    src = np.empty((4, gy1 - gy0, gx1 - gx0), np.float32)
    grab(a, gy0, gy1, gx0, gx1, True, src[3])
    for ch in range(3):
        np.multiply(grab(rgb[:, :, ch], gy0, gy1, gx0, gx1, True), src[3], out=src[ch])
    return src


def _blur_cutout(plane, box, c: float, cell: Aperture, H: int, W: int, m: int = 0):
    """A constant-disparity cutout blurred by the cell's kernel over its footprint O (inside
    rows and columns m .. -m, `cutout_reach`): O and a (6, h, w) stack, the premultiplied
    colour (3), the alpha, and the alpha's first moments about the cell's centroid (2),
    E[a_p (p - p_cell)] over the cell's aperture points p."""
    s = support_radius(c)
    (gy0, gy1, gx0, gx1), (oy0, oy1, ox0, ox1) = cutout_reach(box, s, H, W, m)
    src = _cutout_source(plane, (gy0, gy1, gx0, gx1))
    out = np.zeros((6, oy1 - oy0, ox1 - ox0), np.float32)
    if s == 0:  # in focus: the plane itself (bit for bit), no spread over the cell
        out[:4] = src
        return (oy0, oy1, ox0, ox1), out
    ks, (ky0, kx0, _, _) = _cell_kernels(cell, c)
    if stack_fits(*src.shape[1:], *ks.shape[1:]):
        _blur_into(out, (oy0, oy1, ox0, ox1), src, ks, _PAIRS, (gy0 - s + ky0, gx0 - s + kx0))
    else:  # large: per channel, tiled (the trimmed kernels placed back in their (2S+1)^2 array)
        full = np.zeros((3, 2 * s + 1, 2 * s + 1), np.float32)
        full[:, ky0 : ky0 + ks.shape[1], kx0 : kx0 + ks.shape[2]] = ks
        convs = [Convolver(c, cell, *src.shape[1:], k=kk) for kk in full]
        for i, (kk, ch) in enumerate(_PAIRS):
            convs[kk].add_into(copy_tile(src[ch]), out[i], gy0 - s - oy0, gx0 - s - ox0)
    return (oy0, oy1, ox0, ox1), out


def _blur_back(plane, focus: float, max_coc: float, cell: Aperture, options, H: int, W: int, m: int = 0) -> np.ndarray:
    """The backmost plane through the cell: (3, H - 2m, W - 2m) premultiplied colour over rows
    and columns m .. -m. Constant disparity: one stacked FFT of them, edge-replicated as far
    as the cell's kernel reaches past the frame (only the valid part is computed); a map: the
    layered scatter."""
    d = plane.constant_disparity()
    c = None if d is None else coc_radius(d, focus, max_coc)
    s = 0 if c is None else support_radius(c)
    if s == 0:
        return _layered_inside([plane], focus, max_coc, [cell], options, m)[0]
    ks, (ky0, kx0, ky1, kx1) = _cell_kernels(cell, c)
    # frame pixel Y sees input rows Y + s - ky1 + 1 .. Y + s - ky0 (edge-replicated): the valid part
    y0, y1, x0, x1 = m + s + 1 - ky1, H - m + s - ky0, m + s + 1 - kx1, W - m + s - kx0
    if not stack_fits(y1 - y0, x1 - x0, 1, 1):  # a valid-mode FFT is the input's size
        return _layered_inside([plane], focus, max_coc, [cell], options, m)[0]
    src = _back_source(plane, (y0, y1, x0, x1))
    return np.ascontiguousarray(convolve_stack(src, ks[:1], [(0, 0), (0, 1), (0, 2)], valid=True))


def _layered_inside(planes, focus: float, max_coc: float, cells, options, m: int) -> list[np.ndarray]:
    """The layered render through each of `cells` of rows and columns m .. -m: (3, H - 2m,
    W - 2m) each (a disparity map's levels shared among them, `render_layered_each`)."""
    H, W = planes[0].shape
    return [acc[:, m : H - m, m : W - m] for acc in render_layered_each(planes, focus, max_coc, cells, replace(options, margin=m))]


def _blur_varying_cutout(plane, focus: float, max_coc: float, cell: Aperture, options, H: int, W: int, m: int = 0):
    """A cutout with a disparity map, blurred by the cell's kernels (the layered scatter): the
    box of rows and columns m .. -m and the stack of `_blur_cutout` there, with moments 0
    (none are known)."""
    clear = Plane(np.zeros((H, W, 3), np.float32), np.zeros((H, W), np.float32), focus)  # nothing, kept in focus
    ones = Plane(np.broadcast_to(np.ones(3, np.float32), (H, W, 3)), plane.alpha, plane.disparity, plane.box)
    out = np.zeros((6, H - 2 * m, W - 2 * m), np.float32)
    out[:3] = _layered_inside([clear, plane], focus, max_coc, [cell], options, m)[0]
    out[3] = _layered_inside([clear, ones], focus, max_coc, [cell], options, m)[0][0]
    return (m, H - m, m, W - m), out


def back_cells(back, focus: float, max_coc: float, parts, options, H: int, W: int, m: int = 0) -> list:
    """The backmost plane through each cell of `parts`: (3, H - 2m, W - 2m) each, over rows
    and columns m .. -m. Constant disparity and within BATCH_MAX: one batch (its channels
    transformed once for every cell's kernel)."""
    d = back.constant_disparity()
    c = None if d is None else coc_radius(d, focus, max_coc)
    s = 0 if c is None else support_radius(c)
    K = len(parts)
    h, w = H - 2 * m + 2 * s, W - 2 * m + 2 * s  # what they read
    if c is None:  # a disparity map: the layered scatter, each level's work shared by the cells
        return _layered_inside([back], focus, max_coc, [cell for cell, _ in parts], options, m)
    if s == 0 or K == 1 or 3 * K * h * w > BATCH_MAX or not stack_fits(h, w, 1, 1) or _direct(parts, c):
        return [_blur_back(back, focus, max_coc, cell, options, H, W, m) for cell, _ in parts]
    src = _back_source(back, (m - s, H - m + s, m - s, W - m + s))
    ks = _full_kernels(parts, c)[0::3]
    pairs = [(k, ch) for k in range(K) for ch in range(3)]
    return list(convolve_stack(src, ks, pairs, valid=True).reshape(K, 3, H - 2 * m, W - 2 * m))


def cutout_cells(plane, box, focus: float, max_coc: float, parts, options, H: int, W: int, m: int = 0,
                  front: bool = False):
    """A cutout through each cell of `parts`: [(region, stack, CoC)] per cell, as `_composite`
    takes them (frame coordinates, inside rows and columns m .. -m), and None. Constant
    disparity and within BATCH_MAX: one batch; then with `front` (nothing lies in front of
    it) its premultiplied colour is blurred once by the cells' kernels weighted by their
    shares (their weighted sum, by linearity: K - 1 fewer colour blurs) and returned in place
    of None, the stacks' colour left 0."""
    d = plane.constant_disparity()
    if d is None:
        cmap, out = coc_radius(plane.disparity_map(), focus, max_coc), []
        for cell, _ in parts:
            (y0, y1, x0, x1), st = _blur_varying_cutout(plane, focus, max_coc, cell, options, H, W, m)
            out.append(((y0, y1, x0, x1), st, cmap[y0:y1, x0:x1]))
        return out, None
    c = coc_radius(d, focus, max_coc)
    s = support_radius(c)
    K = len(parts)
    g, o = cutout_reach(box, s, H, W, m)
    h, w = g[1] - g[0], g[3] - g[2]
    if (s == 0 or K == 1 or 6 * K * (h + 2 * s) * (w + 2 * s) > BATCH_MAX or not stack_fits(h, w, 2 * s + 1, 2 * s + 1)
            or _direct(parts, c)):
        return [(*_blur_cutout(plane, box, c, cell, H, W, m), c) for cell, _ in parts], None
    out = np.zeros((K, 6, o[1] - o[0], o[3] - o[2]), np.float32)
    ks = _full_kernels(parts, c)
    src, start = _cutout_source(plane, g), (g[0] - s, g[2] - s)
    if not front:
        pairs = [(3 * k + kk, ch) for k in range(K) for kk, ch in _PAIRS]
        _blur_into(out.reshape(6 * K, *out.shape[2:]), o, src, ks, pairs, start)
        return [(o, out[k], c) for k in range(K)], None
    shares = np.array([w for _, w in parts], np.float32)
    summed = shares[0] * ks[0]  # kernel 3K: the shares' sum, in cell order (numpy, not a BLAS product)
    for share, k in zip(shares[1:], ks[3::3]):
        summed += share * k
    ks = np.concatenate([ks, summed[None]])
    pairs = [(3 * K, ch) for ch in range(3)] + [(3 * k + kk, ch) for k in range(K) for kk, ch in _PAIRS[3:]]
    blurs = np.zeros((3 + 3 * K, *out.shape[2:]), np.float32)
    _blur_into(blurs, o, src, ks, pairs, start)
    out[:, 3:] = blurs[3:].reshape(K, 3, *out.shape[2:])
    return [(o, out[k], c) for k in range(K)], (o, blurs[:3])


BATCH_MAX = 1 << 26  # float32 values a batched blur of one plane for all cells may hold (256 MiB)


def _direct(parts, c: float) -> bool:
    """Whether every cell's kernels of CoC c, cut to their non-zero box, are convolved directly
    (`fft.is_small`): then each cell goes on its own (its kernels are smaller than the batch's
    common (2S+1)^2 array, and direct convolution costs by the kernel's area)."""
    return all(is_small(*_cell_kernels(cell, c)[0].shape[1:]) for cell, _ in parts)


def _full_kernels(parts, c: float):
    """(3K, 2S+1, 2S+1) float32: per cell k of `parts`, its kernel of CoC c and its two
    centred alpha-moment kernels (`_cell_kernels`, placed back in the full (2S+1)^2 array)."""
    s = support_radius(c)
    out = np.zeros((3 * len(parts), 2 * s + 1, 2 * s + 1), np.float32)
    for k, (cell, _) in enumerate(parts):
        ks, (ky0, kx0, ky1, kx1) = _cell_kernels(cell, c)
        out[3 * k : 3 * k + 3, ky0:ky1, kx0:kx1] = ks
    return out
