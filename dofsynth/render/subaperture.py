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
from dofsynth.optics.kernel import coverage, support_radius
from dofsynth.render.cateye import eye_plan, groups
from dofsynth.render.cellblur import back_cells, cutout_cells, cutout_reach
from dofsynth.render.frame import compact, grab
from dofsynth.render.layered import plane_box, render_layered
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
    front, (its region (y0, y1, x0, x1), its stack of `cellblur.cutout_cells` there, its CoC:
    a number or its map over the region); c_back: the backmost plane's CoC (a number or a
    map)."""
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


def render_cells(planes, focus: float, max_coc: float, parts, options, inner: int = 0) -> np.ndarray:
    """The planes (back to front) seen through each cell of `parts` ((cell, share) pairs),
    each cell's image weighted by its share and added: linear RGB (3, H, W). Each plane is
    blurred by every cell's kernel (constant-disparity planes in one batch: cellblur's
    `back_cells`, `cutout_cells`), then per cell composited (`_composite`): what makes few
    cells accurate where a blurred edge occludes a blurred background. `inner` > 0: the planes
    go on that many px past the part computed (rows and columns inner .. -inner; the rest stays
    0), at least every plane's kernel support radius; its outermost pixels take one-sided
    gradients."""
    H, W = planes[0].shape
    m = inner
    back = planes[0]
    R = back_cells(back, focus, max_coc, parts, options, H, W, m)

    def reaches(p, box) -> bool:  # whether any of the cutout's blur lands on what is computed
        y0, y1, x0, x1 = cutout_reach(box, support_radius(coc_reach(p, focus, max_coc)), H, W, m)[1]
        return y1 > y0 and x1 > x0

    cutouts = [(p, box) for p, box in _cutouts(planes) if not m or reaches(p, box)]
    layers, front = [], None
    for i, (p, box) in enumerate(cutouts):
        cuts, summed = cutout_cells(p, box, focus, max_coc, parts, options, H, W, m, front=i == len(cutouts) - 1)
        layers.append([((y0 - m, y1 - m, x0 - m, x1 - m), st, c) for (y0, y1, x0, x1), st, c in cuts])
        front = summed  # (only the frontmost can give one)
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
        d = p.disparity
        if np.ndim(d):
            d = grab(np.broadcast_to(d, p.shape), y0, y1, x0, x1, True)
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
