"""The sub-aperture renderer: the aperture cut into cells, the planes composited per cell to
second order, the cells' images added.

The aperture (a unit shape, dofsynth.optics.aperture) is divided by an n x n grid over
[-1, 1]^2 into cells. For each cell k, every plane is blurred by the part of the aperture
kernel inside that cell (`Cell`, normalized: a shift-invariant kernel whose offset from the
centre is the cell's parallax), the planes are composited back to front with "over" keeping
the covariance of alpha and background over the cell's aperture points (`render_cell`), and
the cells' composites are added with weights w_k, the share of the aperture's area in the cell.
A cell then sees what lies behind a blurred foreground edge from its own side of the lens,
which one blur of the whole aperture cannot. With one cell it is the layered method (the same
bytes); as cells shrink it tends to the exact method (dofsynth.render.exact). Cost: about the
number of cells that meet the aperture times the layered method's (docs/rendering.md).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from functools import lru_cache

import numpy as np

from dofsynth.optics.aperture import Aperture
from dofsynth.optics.coc import coc_radius
from dofsynth.optics.kernel import coverage, kernel, kernel_moments, support_radius
from dofsynth.render.cateye import eye_plan, groups
from dofsynth.render.fft import Convolver, convolve_stack, copy_tile, stack_fits, trim_box, trimmed
from dofsynth.render.frame import add_clipped, compact, grab, is_one
from dofsynth.render.layered import cutout_regions, plane_box, render_layered
from dofsynth.render.planes import Plane

_AREA_RADIUS = 64.0  # px: the cells' area shares are measured on coverages of this radius


@dataclass(frozen=True)
class Cell(Aperture):
    """The part of `base` inside the box [x0, x1] x [y0, y1] (units of the radius). Not a
    recipe kind: only the sub-aperture renderer makes these."""

    kind = "cell"
    base: Aperture = None
    x0: float = -1.0
    x1: float = 1.0
    y0: float = -1.0
    y1: float = 1.0

    def chord(self, x, r):
        lo, hi = self.base.chord(x, r)
        inside = (x >= self.x0 * r) & (x <= self.x1 * r)
        lo, hi = np.maximum(lo, self.y0 * r), np.minimum(hi, self.y1 * r)
        return np.where(inside, lo, 0.0), np.where(inside, np.maximum(hi, lo), np.where(inside, lo, 0.0))

    def x_extent(self, r):
        a, b = self.base.x_extent(r)
        return max(a, self.x0 * r), min(b, self.x1 * r)

    def area(self, radius):
        return float(coverage(self, radius).sum())

    def contains(self, x, y):
        return self.base.contains(x, y) & (x >= self.x0) & (x <= self.x1) & (y >= self.y0) & (y <= self.y1)


@lru_cache(maxsize=64)
def cells(aperture: Aperture, n: int) -> tuple[tuple[Cell, float], ...]:
    """The n x n cells of the aperture that hold part of it, each with its area share (sum 1)."""
    edges = np.linspace(-1.0, 1.0, n + 1)
    total = float(coverage(aperture, _AREA_RADIUS).sum())
    out = []
    for i in range(n):
        for j in range(n):
            c = Cell(aperture, float(edges[j]), float(edges[j + 1]), float(edges[i]), float(edges[i + 1]))
            a, b = c.x_extent(1.0)
            if b <= a:
                continue
            w = float(coverage(c, _AREA_RADIUS).sum()) / total
            if w > 1e-9:
                out.append((c, w))
    s = math.fsum(w for _, w in out)
    return tuple((c, w / s) for c, w in out)


@lru_cache(maxsize=64)
def halves(aperture: Aperture, axis: str = "x") -> tuple[tuple[Cell, float], tuple[Cell, float]]:
    """The two halves of the aperture with their area shares: left (x < 0) and right (x > 0),
    the two views of a dual-pixel sensor, whose weighted sum is the whole aperture's image; or
    with axis "y", top (y < 0) and bottom (y > 0)."""
    total = float(coverage(aperture, _AREA_RADIUS).sum())
    if axis == "x":
        first, second = Cell(aperture, -1.0, 0.0, -1.0, 1.0), Cell(aperture, 0.0, 1.0, -1.0, 1.0)
    elif axis == "y":
        first, second = Cell(aperture, -1.0, 1.0, -1.0, 0.0), Cell(aperture, -1.0, 1.0, 0.0, 1.0)
    else:
        raise ValueError(f"axis must be 'x' or 'y', got {axis!r}")
    w = float(coverage(first, _AREA_RADIUS).sum()) / total
    return (first, w), (second, 1.0 - w)


def whole(options):
    """`options` for a layered render of every pixel: the composite per cell takes gradients
    across the whole frame, so no part of it may be left out (RenderOptions.margin)."""
    return replace(options, margin=0) if options.margin else options


def _p_gradient(x: np.ndarray, c) -> np.ndarray:
    """(2, ...) d/dp_x, d/dp_y of a plane seen through aperture point p, from its image x
    (..., H, W) and its CoC c (px; a number or a map broadcasting to (H, W)): it moves by p c,
    so d/dp = -c d/dx (central differences, one-sided at the edges: np.gradient's, which with
    the stack it needs took 9x as long at 300 px, measured)."""
    out = np.empty((2,) + x.shape, np.float32)
    for i, axis in ((0, -1), (1, -2)):
        g, n = np.moveaxis(out[i], axis, 0), x.shape[axis]
        v = np.moveaxis(x, axis, 0)
        if n < 2:
            g[...] = 0.0
            continue
        np.subtract(v[2:], v[:-2], out=g[1:-1])
        g[1:-1] *= 0.5
        np.subtract(v[1], v[0], out=g[0])
        np.subtract(v[-1], v[-2], out=g[-1])
    out *= -np.asarray(c, np.float32)
    return out


@lru_cache(maxsize=512)
def _cell_kernels(cell: Cell, c: float) -> tuple[np.ndarray, tuple[int, int, int, int]]:
    """(3, kh, kw): the cell's kernel of CoC c and its alpha-moment kernels about the cell's
    centroid (Mx - cx K, My - cy K: K (p - p_cell) in effect; each sums to 0), cut to the
    kernel's non-zero box, which is returned (y0, x0, y1, x1) in the (2S+1)^2 array."""
    k = kernel(cell, c)
    box = trim_box(k)
    centred = [m - np.float32(math.fsum(m.ravel().tolist())) * k for m in kernel_moments(cell, c)]
    return np.stack([trimmed(m, box) for m in [k] + centred]), box


_PAIRS = [(0, 0), (0, 1), (0, 2), (0, 3), (1, 3), (2, 3)]  # K * (colour * alpha, alpha), moments * alpha


def _blur_cutout(plane, box, c: float, cell: Cell, H: int, W: int):
    """A constant-disparity cutout blurred by the cell's kernel over its footprint O: O and a
    (6, h, w) stack, the premultiplied colour (3), the alpha, and the alpha's first moments
    about the cell's centroid (2), E[a_p (p - p_cell)] over the cell's aperture points p."""
    rgb, alpha = np.asarray(plane.rgb, np.float32), np.asarray(plane.alpha, np.float32)
    s = support_radius(c)
    (gy0, gy1, gx0, gx1), (oy0, oy1, ox0, ox1) = cutout_regions(box, s, H, W)
    src = np.empty((4, gy1 - gy0, gx1 - gx0), np.float32)
    grab(alpha, gy0, gy1, gx0, gx1, True, src[3])
    for ch in range(3):
        np.multiply(grab(rgb[:, :, ch], gy0, gy1, gx0, gx1, True), src[3], out=src[ch])
    out = np.zeros((6, oy1 - oy0, ox1 - ox0), np.float32)
    if s == 0:  # in focus: the plane itself (bit for bit), no spread over the cell
        out[:4] = src
        return (oy0, oy1, ox0, ox1), out
    ks, (ky0, kx0, _, _) = _cell_kernels(cell, c)
    if stack_fits(*src.shape[1:], *ks.shape[1:]):
        add_clipped(out, gy0 - s + ky0 - oy0, gx0 - s + kx0 - ox0, convolve_stack(src, ks, _PAIRS))
    else:  # large: per channel, tiled (the trimmed kernels placed back in their (2S+1)^2 array)
        full = np.zeros((3, 2 * s + 1, 2 * s + 1), np.float32)
        full[:, ky0 : ky0 + ks.shape[1], kx0 : kx0 + ks.shape[2]] = ks
        convs = [Convolver(c, cell, *src.shape[1:], k=kk) for kk in full]
        for i, (kk, ch) in enumerate(_PAIRS):
            convs[kk].add_into(copy_tile(src[ch]), out[i], gy0 - s - oy0, gx0 - s - ox0)
    return (oy0, oy1, ox0, ox1), out


def _blur_back(plane, focus: float, max_coc: float, cell: Cell, options, H: int, W: int) -> np.ndarray:
    """The backmost plane through the cell: (3, H, W) premultiplied colour. Constant disparity:
    one stacked FFT of the frame, edge-replicated as far as the cell's kernel reaches beyond
    it, of which only the frame is kept; a map: the layered scatter."""
    d = plane.constant_disparity()
    c = None if d is None else coc_radius(d, focus, max_coc)
    s = 0 if c is None else support_radius(c)
    if s == 0:
        return render_layered([plane], focus, max_coc, cell, whole(options))
    ks, (ky0, kx0, ky1, kx1) = _cell_kernels(cell, c)
    # frame pixel Y sees input rows Y + s - ky1 + 1 .. Y + s - ky0 (edge-replicated): the valid part
    y0, y1, x0, x1 = s + 1 - ky1, H + s - ky0, s + 1 - kx1, W + s - kx0
    if not stack_fits(y1 - y0, x1 - x0, 1, 1):  # a valid-mode FFT is the input's size
        return render_layered([plane], focus, max_coc, cell, whole(options))
    rgb, alpha = np.asarray(plane.rgb, np.float32), np.asarray(plane.alpha, np.float32)
    src = np.empty((3, y1 - y0, x1 - x0), np.float32)
    for ch in range(3):
        grab(rgb[:, :, ch], y0, y1, x0, x1, True, src[ch])
    if not is_one(alpha):
        src *= grab(alpha, y0, y1, x0, x1, True)
    return np.ascontiguousarray(convolve_stack(src, ks[:1], [(0, 0), (0, 1), (0, 2)], valid=True))


def _blur_varying_cutout(plane, focus: float, max_coc: float, cell: Cell, options, H: int, W: int):
    """A cutout with a disparity map, blurred by the cell's kernels (the layered scatter): the
    frame and the stack of `_blur_cutout`, with moments 0 (none are known)."""
    clear = Plane(np.zeros((H, W, 3), np.float32), np.zeros((H, W), np.float32), 0.0)
    ones = Plane(np.broadcast_to(np.ones(3, np.float32), (H, W, 3)), plane.alpha, plane.disparity, plane.box)
    out = np.zeros((6, H, W), np.float32)
    out[:3] = render_layered([clear, plane], focus, max_coc, cell, whole(options))
    out[3] = render_layered([clear, ones], focus, max_coc, cell, whole(options))[0]
    return (0, H, 0, W), out


def compact_disparity(plane):
    """The plane's disparity: a number when it is constant, else its map kept compact."""
    d = plane.constant_disparity()
    return d if d is not None else compact(np.asarray(plane.disparity_map(), np.float32))


def coc_reach(plane, focus: float, max_coc: float) -> float:
    """The plane's largest |CoC| (px)."""
    return float(np.max(np.abs(coc_radius(compact_disparity(plane), focus, max_coc))))


def _composite(R: np.ndarray, c_back, layers) -> np.ndarray:
    """The cutouts composited "over" R (3, H, W), the backmost plane through one cell (in
    place), to second order in the aperture point p within the cell: the mean of a_p R_p over
    the cell is a R - Cov(a, R), and Cov(a, R) = E[a_p (p - p_cell)] . dR/dp, the alpha's first
    moments (`kernel_moments`, exact for a hard edge) times R's gradient in p (carried along the
    composite: d/dp of over(P, R) = dP - R da + (1 - a) dR). `layers`: per cutout, back to
    front, (its region (y0, y1, x0, x1), its stack of `_blur_cutout` there, its CoC: a number
    or its map over the region); c_back: the backmost plane's CoC (a number or a map)."""
    G = None
    c = c_back
    for i, ((y0, y1, x0, x1), st, c_next) in enumerate(layers):
        if G is None:
            G = _p_gradient(R, c)
        c = c_next
        r, g = R[:, y0:y1, x0:x1], G[:, :, y0:y1, x0:x1]
        pm, a, m = st[:3], st[3], st[4:]
        cov = m[0] * g[0]
        cov += m[1] * g[1]
        if i < len(layers) - 1:  # the gradient in p of the new composite, for the planes in front
            d_st = _p_gradient(st[:4], c)
            d_st[:, :3] -= r[None] * d_st[:, 3:4]
            d_st[:, :3] += (1.0 - a) * g
            g[...] = d_st[:, :3]
        r *= 1.0 - a
        r += pm
        r -= cov
    return R


def _cutouts(planes):
    """The cutouts that add something (alpha not 0 everywhere), each with its alpha box."""
    boxes = [(p, plane_box(p, np.asarray(p.alpha, np.float32))) for p in planes[1:]]
    return [(p, box) for p, box in boxes if box is not None]


def _back_cells(back, focus: float, max_coc: float, parts, options, H: int, W: int) -> list:
    """The backmost plane through each cell of `parts`: (3, H, W) each. Constant disparity and
    within BATCH_MAX: one batch (its channels transformed once for every cell's kernel)."""
    d = back.constant_disparity()
    c = None if d is None else coc_radius(d, focus, max_coc)
    s = 0 if c is None else support_radius(c)
    K = len(parts)
    if c is None or s == 0 or K == 1 or 3 * K * (H + 2 * s) * (W + 2 * s) > BATCH_MAX or not stack_fits(H + 2 * s, W + 2 * s, 1, 1):
        return [_blur_back(back, focus, max_coc, cell, options, H, W) for cell, _ in parts]
    rgb, alpha = np.asarray(back.rgb, np.float32), np.asarray(back.alpha, np.float32)
    src = np.empty((3, H + 2 * s, W + 2 * s), np.float32)
    for ch in range(3):
        grab(rgb[:, :, ch], -s, H + s, -s, W + s, True, src[ch])
    if not is_one(alpha):
        src *= grab(alpha, -s, H + s, -s, W + s, True)
    ks = _full_kernels(parts, c)[0::3]
    return list(convolve_stack(src, ks, [(k, ch) for k in range(K) for ch in range(3)], valid=True).reshape(K, 3, H, W))


def _cutout_cells(plane, box, focus: float, max_coc: float, parts, options, H: int, W: int) -> list:
    """A cutout through each cell of `parts`: (region, stack, CoC) each, as `_composite` takes
    them. Constant disparity and within BATCH_MAX: one batch."""
    d = plane.constant_disparity()
    if d is None:
        cmap, out = coc_radius(plane.disparity_map(), focus, max_coc), []
        for cell, _ in parts:
            (y0, y1, x0, x1), st = _blur_varying_cutout(plane, focus, max_coc, cell, options, H, W)
            out.append(((y0, y1, x0, x1), st, cmap[y0:y1, x0:x1]))
        return out
    c = coc_radius(d, focus, max_coc)
    s = support_radius(c)
    K = len(parts)
    (gy0, gy1, gx0, gx1), (oy0, oy1, ox0, ox1) = cutout_regions(box, s, H, W)
    h, w = gy1 - gy0, gx1 - gx0
    if s == 0 or K == 1 or 6 * K * (h + 2 * s) * (w + 2 * s) > BATCH_MAX or not stack_fits(h, w, 2 * s + 1, 2 * s + 1):
        return [(*_blur_cutout(plane, box, c, cell, H, W), c) for cell, _ in parts]
    a, rgb = np.asarray(plane.alpha, np.float32), np.asarray(plane.rgb, np.float32)
    src = np.empty((4, h, w), np.float32)
    grab(a, gy0, gy1, gx0, gx1, True, src[3])
    for ch in range(3):
        np.multiply(grab(rgb[:, :, ch], gy0, gy1, gx0, gx1, True), src[3], out=src[ch])
    out = np.zeros((K, 6, oy1 - oy0, ox1 - ox0), np.float32)
    pairs = [(3 * k + kk, ch) for k in range(K) for kk, ch in _PAIRS]
    full = convolve_stack(src, _full_kernels(parts, c), pairs)
    add_clipped(out.reshape(6 * K, *out.shape[2:]), gy0 - s - oy0, gx0 - s - ox0, full)
    return [((oy0, oy1, ox0, ox1), out[k], c) for k in range(K)]


BATCH_MAX = 1 << 26  # float32 values a batched blur of one plane for all cells may hold (256 MiB)


def _full_kernels(parts, c: float):
    """(3K, 2S+1, 2S+1) float32: per cell k of `parts`, its kernel of CoC c and its two
    centred alpha-moment kernels (`_cell_kernels`, placed back in the full (2S+1)^2 array)."""
    s = support_radius(c)
    out = np.zeros((3 * len(parts), 2 * s + 1, 2 * s + 1), np.float32)
    for k, (cell, _) in enumerate(parts):
        ks, (ky0, kx0, ky1, kx1) = _cell_kernels(cell, c)
        out[3 * k : 3 * k + 3, ky0:ky1, kx0:kx1] = ks
    return out


def render_cells(planes, focus: float, max_coc: float, parts, options) -> np.ndarray:
    """The planes (back to front) seen through each cell of `parts` ((cell, share) pairs),
    each cell's image weighted by its share and added: linear RGB (3, H, W). Each plane is
    blurred by every cell's kernel (constant-disparity planes in one batch: `_back_cells`,
    `_cutout_cells`), then per cell composited (`_composite`): what makes few cells accurate
    where a blurred edge occludes a blurred background."""
    H, W = planes[0].shape
    back = planes[0]
    R = _back_cells(back, focus, max_coc, parts, options, H, W)
    layers = [_cutout_cells(p, box, focus, max_coc, parts, options, H, W) for p, box in _cutouts(planes)]
    c_back = coc_radius(compact_disparity(back), focus, max_coc)
    acc = np.zeros((3, H, W), np.float32)
    for k, (_, w) in enumerate(parts):
        img = _composite(R[k], c_back, [plane[k] for plane in layers])
        img *= np.float32(w)
        acc += img
    return acc


def render_cell(planes, focus: float, max_coc: float, cell: Cell, options) -> np.ndarray:
    """The planes (back to front) seen through one cell of the aperture: linear RGB (3, H, W)."""
    return render_cells(planes, focus, max_coc, ((cell, 1.0),), options)


def cut_planes(planes, y0: int, y1: int, x0: int, x1: int) -> list[Plane]:
    """The planes cut to rows y0:y1, columns x0:x1 of the frame (views; boxes moved with them,
    an empty one where a box misses the cut)."""
    out = []
    for p in planes:
        d = p.disparity if np.ndim(p.disparity) == 0 else np.broadcast_to(p.disparity, p.shape)[y0:y1, x0:x1]
        box = None
        if p.box is not None:
            by0, by1, bx0, bx1 = p.box
            box = (max(by0, y0) - y0, max(min(by1, y1) - y0, 0), max(bx0, x0) - x0, max(min(bx1, x1) - x0, 0))
        out.append(Plane(np.asarray(p.rgb)[y0:y1, x0:x1], np.asarray(p.alpha)[y0:y1, x0:x1], d, box))
    return out


def _weighted(planes, weights: np.ndarray, r0: int, c0: int, y0: int, y1: int, x0: int, x1: int):
    """The planes cut to rows y0:y1, columns x0:x1, their colour times `weights` (placed at rows
    r0, columns c0 of the frame; 0 elsewhere in the cut)."""
    w = np.zeros((y1 - y0, x1 - x0, 1), np.float32)
    w[r0 - y0 : r0 - y0 + weights.shape[0], c0 - x0 : c0 - x0 + weights.shape[1], 0] = weights
    return [replace(p, rgb=np.asarray(p.rgb, np.float32) * w) for p in cut_planes(planes, y0, y1, x0, x1)]


def render_subaperture(planes, focus: float, max_coc: float, aperture: Aperture, options) -> np.ndarray:
    """Sub-aperture render of validated planes (back to front): linear RGB (3, H, W) float32.
    `options`: a dofsynth.render.RenderOptions (its `cells`: n for an n x n grid; `cat_eye`:
    the vignetting strength; the layered method's level_step and level_ratio per cell).

    With cat_eye > 0 each cell is cut further by the clip circle (dofsynth.render.cateye):
    per part of it (the cell where the circle leaves it whole; the cell clipped about each grid
    node where the circle cuts it), the planes' colours times that part's share of each source
    point's light are composited through the part, on the cut of the frame the part's sources
    reach (occlusion stays unclipped), and everything is added: each source point keeps its
    light, spread evenly over its clipped aperture, as in the exact method."""
    n = options.cells
    if n == 1 and not options.cat_eye:
        return render_layered(planes, focus, max_coc, aperture, options)
    parts = cells(aperture, n)
    if not options.cat_eye:
        return render_cells(planes, focus, max_coc, parts, options)
    H, W = planes[0].shape
    reach = max(coc_reach(p, focus, max_coc) for p in planes)
    plan = eye_plan(parts, (H, W), options.cat_eye, options.margin, reach)
    hy, hx = plan.hats(np.arange(H), np.arange(W))
    s = 2 * support_radius(reach)  # what a part's sources reach, and the planes that reach it
    acc = np.zeros((3, H, W), np.float32)
    for k, (cell, _) in enumerate(parts):
        for part, (r0, r1, c0, c1), weights in groups(plan, k, cell, hy, hx):
            y0, y1, x0, x1 = max(r0 - s, 0), min(r1 + s, H), max(c0 - s, 0), min(c1 + s, W)
            cut = _weighted(planes, weights, r0, c0, y0, y1, x0, x1)
            acc[:, y0:y1, x0:x1] += render_cell(cut, focus, max_coc, part, options)
    return acc
