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
from dofsynth.render.frame import compact, grab, is_one
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


def _cutout_reach(box, s: int, H: int, W: int, m: int):
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


def _blur_cutout(plane, box, c: float, cell: Cell, H: int, W: int, m: int = 0):
    """A constant-disparity cutout blurred by the cell's kernel over its footprint O (inside
    rows and columns m .. -m, `_cutout_reach`): O and a (6, h, w) stack, the premultiplied
    colour (3), the alpha, and the alpha's first moments about the cell's centroid (2),
    E[a_p (p - p_cell)] over the cell's aperture points p."""
    s = support_radius(c)
    (gy0, gy1, gx0, gx1), (oy0, oy1, ox0, ox1) = _cutout_reach(box, s, H, W, m)
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


def _blur_back(plane, focus: float, max_coc: float, cell: Cell, options, H: int, W: int, m: int = 0) -> np.ndarray:
    """The backmost plane through the cell: (3, H - 2m, W - 2m) premultiplied colour over rows
    and columns m .. -m. Constant disparity: one stacked FFT of them, edge-replicated as far
    as the cell's kernel reaches past the frame (only the valid part is computed); a map: the
    layered scatter."""
    d = plane.constant_disparity()
    c = None if d is None else coc_radius(d, focus, max_coc)
    s = 0 if c is None else support_radius(c)
    if s == 0:
        return _layered_inside([plane], focus, max_coc, cell, options, m)
    ks, (ky0, kx0, ky1, kx1) = _cell_kernels(cell, c)
    # frame pixel Y sees input rows Y + s - ky1 + 1 .. Y + s - ky0 (edge-replicated): the valid part
    y0, y1, x0, x1 = m + s + 1 - ky1, H - m + s - ky0, m + s + 1 - kx1, W - m + s - kx0
    if not stack_fits(y1 - y0, x1 - x0, 1, 1):  # a valid-mode FFT is the input's size
        return _layered_inside([plane], focus, max_coc, cell, options, m)
    rgb, alpha = np.asarray(plane.rgb, np.float32), np.asarray(plane.alpha, np.float32)
    src = np.empty((3, y1 - y0, x1 - x0), np.float32)
    for ch in range(3):
        grab(rgb[:, :, ch], y0, y1, x0, x1, True, src[ch])
    if not is_one(alpha):
        src *= grab(alpha, y0, y1, x0, x1, True)
    return np.ascontiguousarray(convolve_stack(src, ks[:1], [(0, 0), (0, 1), (0, 2)], valid=True))


def _layered_inside(planes, focus: float, max_coc: float, cell: Cell, options, m: int) -> np.ndarray:
    """The layered render through the cell of rows and columns m .. -m: (3, H - 2m, W - 2m)."""
    H, W = planes[0].shape
    return render_layered(planes, focus, max_coc, cell, replace(options, margin=m))[:, m : H - m, m : W - m]


def _blur_varying_cutout(plane, focus: float, max_coc: float, cell: Cell, options, H: int, W: int, m: int = 0):
    """A cutout with a disparity map, blurred by the cell's kernels (the layered scatter): the
    box of rows and columns m .. -m and the stack of `_blur_cutout` there, with moments 0
    (none are known)."""
    clear = Plane(np.zeros((H, W, 3), np.float32), np.zeros((H, W), np.float32), focus)  # nothing, kept in focus
    ones = Plane(np.broadcast_to(np.ones(3, np.float32), (H, W, 3)), plane.alpha, plane.disparity, plane.box)
    out = np.zeros((6, H - 2 * m, W - 2 * m), np.float32)
    out[:3] = _layered_inside([clear, plane], focus, max_coc, cell, options, m)
    out[3] = _layered_inside([clear, ones], focus, max_coc, cell, options, m)[0]
    return (m, H - m, m, W - m), out


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


def _back_cells(back, focus: float, max_coc: float, parts, options, H: int, W: int, m: int = 0) -> list:
    """The backmost plane through each cell of `parts`: (3, H - 2m, W - 2m) each, over rows
    and columns m .. -m. Constant disparity and within BATCH_MAX: one batch (its channels
    transformed once for every cell's kernel)."""
    d = back.constant_disparity()
    c = None if d is None else coc_radius(d, focus, max_coc)
    s = 0 if c is None else support_radius(c)
    K = len(parts)
    h, w = H - 2 * m + 2 * s, W - 2 * m + 2 * s  # what they read
    if c is None or s == 0 or K == 1 or 3 * K * h * w > BATCH_MAX or not stack_fits(h, w, 1, 1):
        return [_blur_back(back, focus, max_coc, cell, options, H, W, m) for cell, _ in parts]
    rgb, alpha = np.asarray(back.rgb, np.float32), np.asarray(back.alpha, np.float32)
    src = np.empty((3, h, w), np.float32)
    for ch in range(3):
        grab(rgb[:, :, ch], m - s, H - m + s, m - s, W - m + s, True, src[ch])
    if not is_one(alpha):
        src *= grab(alpha, m - s, H - m + s, m - s, W - m + s, True)
    ks = _full_kernels(parts, c)[0::3]
    pairs = [(k, ch) for k in range(K) for ch in range(3)]
    return list(convolve_stack(src, ks, pairs, valid=True).reshape(K, 3, H - 2 * m, W - 2 * m))


def _cutout_cells(plane, box, focus: float, max_coc: float, parts, options, H: int, W: int, m: int = 0,
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
    g, o = _cutout_reach(box, s, H, W, m)
    h, w = g[1] - g[0], g[3] - g[2]
    if s == 0 or K == 1 or 6 * K * (h + 2 * s) * (w + 2 * s) > BATCH_MAX or not stack_fits(h, w, 2 * s + 1, 2 * s + 1):
        return [(*_blur_cutout(plane, box, c, cell, H, W, m), c) for cell, _ in parts], None
    out = np.zeros((K, 6, o[1] - o[0], o[3] - o[2]), np.float32)
    ks = _full_kernels(parts, c)
    src, start = _cutout_source(plane, g), (g[0] - s, g[2] - s)
    if not front:
        pairs = [(3 * k + kk, ch) for k in range(K) for kk, ch in _PAIRS]
        _blur_into(out.reshape(6 * K, *out.shape[2:]), o, src, ks, pairs, start)
        return [(o, out[k], c) for k in range(K)], None
    shares = np.array([w for _, w in parts], np.float32)
    ks = np.concatenate([ks, np.tensordot(shares, ks[0::3], axes=1)[None]])  # kernel 3K: the shares' sum
    pairs = [(3 * K, ch) for ch in range(3)] + [(3 * k + kk, ch) for k in range(K) for kk, ch in _PAIRS[3:]]
    blurs = np.zeros((3 + 3 * K, *out.shape[2:]), np.float32)
    _blur_into(blurs, o, src, ks, pairs, start)
    out[:, 3:] = blurs[3:].reshape(K, 3, *out.shape[2:])
    return [(o, out[k], c) for k in range(K)], (o, blurs[:3])


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


def render_cells(planes, focus: float, max_coc: float, parts, options, inner: int = 0) -> np.ndarray:
    """The planes (back to front) seen through each cell of `parts` ((cell, share) pairs),
    each cell's image weighted by its share and added: linear RGB (3, H, W). Each plane is
    blurred by every cell's kernel (constant-disparity planes in one batch: `_back_cells`,
    `_cutout_cells`), then per cell composited (`_composite`): what makes few cells accurate
    where a blurred edge occludes a blurred background. `inner` > 0: the planes go on that
    many px past the part computed (rows and columns inner .. -inner; the rest stays 0), at
    least every plane's kernel support radius; its outermost pixels take one-sided gradients."""
    H, W = planes[0].shape
    m = inner
    back = planes[0]
    R = _back_cells(back, focus, max_coc, parts, options, H, W, m)
    cutouts = _cutouts(planes)
    if m:  # those that reach what is computed
        cutouts = [(p, box) for p, box in cutouts
                   if (o := _cutout_reach(box, support_radius(coc_reach(p, focus, max_coc)), H, W, m)[1])[1] > o[0]
                   and o[3] > o[2]]
    layers, front = [], None
    for i, (p, box) in enumerate(cutouts):
        cuts, summed = _cutout_cells(p, box, focus, max_coc, parts, options, H, W, m, front=i == len(cutouts) - 1)
        layers.append([((y0 - m, y1 - m, x0 - m, x1 - m), st, c) for (y0, y1, x0, x1), st, c in cuts])
        front = summed if summed is not None else front
    c_back = coc_radius(compact_disparity(back), focus, max_coc)
    if m and np.ndim(c_back):
        c_back = c_back[slice(m, H - m) if c_back.shape[0] > 1 else slice(None),
                        slice(m, W - m) if c_back.shape[1] > 1 else slice(None)]  # (compact along broadcast axes)
    acc = np.zeros((3, H, W), np.float32)
    inside = acc[:, m : H - m, m : W - m]
    for k, (_, w) in enumerate(parts):
        img = _composite(R[k], c_back, [plane[k] for plane in layers])
        img *= np.float32(w)
        inside += img
    if front is not None:  # the frontmost cutout's colour, blurred once for all cells
        (y0, y1, x0, x1), colour = front
        inside[:, y0 - m : y1 - m, x0 - m : x1 - m] += colour
    return acc


def render_cell(planes, focus: float, max_coc: float, cell: Cell, options) -> np.ndarray:
    """The planes (back to front) seen through one cell of the aperture: linear RGB (3, H, W)."""
    return render_cells(planes, focus, max_coc, ((cell, 1.0),), options)


def cut_planes(planes, y0: int, y1: int, x0: int, x1: int) -> list[Plane]:
    """The planes cut to rows y0:y1, columns x0:x1 of the frame: views where the cut lies
    inside it; past its edges every plane goes on as its edge pixels do (copies), as the
    renderers extend them, and so does a box that touches that edge (boxes are moved with the
    cut; empty where one misses it)."""
    H, W = planes[0].shape
    h, w = y1 - y0, x1 - x0
    out = []
    for p in planes:
        d = p.disparity if np.ndim(p.disparity) == 0 else grab(np.broadcast_to(p.disparity, p.shape), y0, y1, x0, x1, True)
        box = None
        if p.box is not None:
            by0, by1, bx0, bx1 = p.box
            box = (0 if by0 <= 0 else min(max(by0 - y0, 0), h), h if by1 >= H else min(max(by1 - y0, 0), h),
                   0 if bx0 <= 0 else min(max(bx0 - x0, 0), w), w if bx1 >= W else min(max(bx1 - x0, 0), w))
        out.append(Plane(grab(np.asarray(p.rgb), y0, y1, x0, x1, True), grab(np.asarray(p.alpha), y0, y1, x0, x1, True),
                         d, box))
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
    if not options.cat_eye:  # with a margin past every kernel's reach, only the frame and a pixel more (gradients)
        m = options.margin
        inner = m - 1 if m > 1 and m - 1 >= support_radius(max(coc_reach(p, focus, max_coc) for p in planes)) else 0
        acc = render_cells(planes, focus, max_coc, parts, options, inner)
        if inner:
            H, W = planes[0].shape  # the one-pixel ring computed past the frame: 0, as the layered method leaves it
            acc[:, [inner, H - m], :] = 0.0
            acc[:, :, [inner, W - m]] = 0.0
        return acc
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
