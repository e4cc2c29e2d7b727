"""The sub-aperture renderer: the aperture cut into cells, the layered method per cell, the
cells' images added.

The aperture (a unit shape, dofsynth.optics.aperture) is divided by an n x n grid over
[-1, 1]^2 into cells. For each cell k, every plane is blurred by the part of the aperture
kernel inside that cell (`Cell`, normalized: a shift-invariant kernel whose offset from the
centre is the cell's parallax), the planes are composited back to front with "over", and the
cells' composites are added with weights w_k, the share of the aperture's area in the cell.
A cell then sees what lies behind a blurred foreground edge from its own side of the lens,
which one blur of the whole aperture cannot. With one cell it is the layered method (the same
bytes); as cells shrink it tends to the exact method (dofsynth.render.exact). Cost: about the
number of cells that meet the aperture times the layered method's.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np

from dofsynth.optics.aperture import Aperture, cat_eye_offset
from dofsynth.optics.kernel import coverage
from dofsynth.render.layered import render_layered

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
def halves(aperture: Aperture) -> tuple[tuple[Cell, float], tuple[Cell, float]]:
    """The left (x < 0) and right (x > 0) halves of the aperture with their area shares: the
    two views of a dual-pixel sensor, whose weighted sum is the whole aperture's image."""
    total = float(coverage(aperture, _AREA_RADIUS).sum())
    left, right = Cell(aperture, -1.0, 0.0, -1.0, 1.0), Cell(aperture, 0.0, 1.0, -1.0, 1.0)
    wl = float(coverage(left, _AREA_RADIUS).sum()) / total
    return (left, wl), (right, 1.0 - wl)


CAT_EYE_GRID = 9      # frame positions per side where the cells' weights are measured, then interpolated
CAT_EYE_POINTS = 24   # sample points per side of a cell for its share inside the vignetting circle


def cat_eye_weights(cell: Cell, shape: tuple[int, int], strength: float) -> np.ndarray:
    """(H, W) float32: the share of the aperture's area that lies in `cell` and inside the
    vignetting circle (radius 1 about cat_eye_offset), measured by points on a grid of
    CAT_EYE_GRID x CAT_EYE_GRID frame positions and interpolated bilinearly (smooth)."""
    h, w = shape
    t = (np.arange(CAT_EYE_POINTS) + 0.5) / CAT_EYE_POINTS
    px = cell.x0 + (cell.x1 - cell.x0) * t
    py = cell.y0 + (cell.y1 - cell.y0) * t
    py, px = np.meshgrid(py, px, indexing="ij")
    inside = cell.base.contains(px, py)
    unit = (cell.x1 - cell.x0) * (cell.y1 - cell.y0) / CAT_EYE_POINTS**2 / cell.base.area(1.0)
    gy = np.linspace(0, h - 1, CAT_EYE_GRID)
    gx = np.linspace(0, w - 1, CAT_EYE_GRID)
    oy, ox = cat_eye_offset(shape, strength, *np.meshgrid(gy, gx, indexing="ij"))
    d2 = (py[None, None] - oy[..., None, None]) ** 2 + (px[None, None] - ox[..., None, None]) ** 2
    coarse = ((d2 <= 1.0) & inside).sum(axis=(2, 3)) * unit
    return cv2.resize(coarse.astype(np.float32), (w, h), interpolation=cv2.INTER_LINEAR)


def render_subaperture(planes, focus: float, max_coc: float, aperture: Aperture, options) -> np.ndarray:
    """Sub-aperture render of validated planes (back to front): linear RGB (3, H, W) float32.
    `options`: a dofsynth.render.RenderOptions (its `cells`: n for an n x n grid; `cat_eye`:
    the vignetting strength; the layered method's level_step and level_ratio per cell).

    With cat_eye > 0 each cell's weight varies over the frame (cat_eye_weights) and the sum is
    normalized by the weights, so what is in focus keeps its brightness."""
    n = options.cells
    if n == 1 and not options.cat_eye:
        return render_layered(planes, focus, max_coc, aperture, options)
    acc = norm = None
    for cell, w in cells(aperture, n):
        img = render_layered(planes, focus, max_coc, cell, options)
        wk = np.float32(w) if not options.cat_eye else cat_eye_weights(cell, img.shape[1:], options.cat_eye)
        if acc is None:
            acc, norm = img * wk, wk
        else:
            acc += wk * img
            norm = norm + wk
    if options.cat_eye:
        acc /= np.maximum(norm, 1e-12)
    return acc
