"""Cat-eye (optical vignetting) inside each cell of the sub-aperture renderer.

A source point at frame position u sends its light through the part of the aperture inside
its clip circle (radius 1 about `cat_eye_offset(u)`, in aperture radii), spread evenly over
that part (docs/rendering.md). The circle moves with u, so the kernel varies over the frame.
It is interpolated: a grid of nodes t over the frame carries bilinear hats phi_t (they add up
to 1 at every position), and through cell k a source sends

    sum_t phi_t(u) s_kt K_kt,

K_kt the kernel of the cell clipped by node t's circle (`Clipped`, normalized) and s_kt that
part's share of the aperture inside the circle (adding up to 1 over the cells). So every source
keeps its light; at a node the cells' parts are the parts of one clipped aperture, so they join
without seams; between nodes the clip edge is the hats' blend of the neighbouring nodes' edges,
which `eye_plan` spaces so that, for the render's largest |CoC|, the edge moves at most
`EDGE_PX` px from one node to the next (fewer nodes where the grid would exceed `MAX_NODES`).
The nodes where a cell is whole share one convolution, and those where it is empty add nothing:
only the nodes where the circle cuts the cell cost a convolution of their own.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from dofsynth.optics.aperture import Aperture, cat_eye_offset
from dofsynth.optics.kernel import coverage

EDGE_PX = 1.0     # px the clip edge may move between neighbouring nodes (at the largest |CoC|)
MAX_NODES = 33    # nodes per side at most (odd) (the edge bound gives way beyond; cost grows with the cut nodes)
_COLUMNS = 512    # sub-columns per unit of x for the parts' areas (exact along y)
_EMPTY = 1e-6     # a share below this is left out (its light goes to the other cells)


@dataclass(frozen=True)
class Clipped(Aperture):
    """`base` inside the unit circle about (ox, oy) (units of the radius): what a stop in front
    of the lens leaves of it. Not a recipe kind: only cat-eye renders make these."""

    kind = "clipped"
    base: Aperture = None
    ox: float = 0.0
    oy: float = 0.0

    def chord(self, x, r):
        lo, hi = self.base.chord(x, r)
        dx = np.asarray(x, np.float64) / r - self.ox
        inside = np.abs(dx) <= 1.0
        half = np.sqrt(np.maximum(1.0 - dx * dx, 0.0)) * r
        lo, hi = np.maximum(lo, self.oy * r - half), np.minimum(hi, self.oy * r + half)
        return np.where(inside, lo, 0.0), np.where(inside, np.maximum(hi, lo), np.where(inside, lo, 0.0))

    def x_extent(self, r):
        a, b = self.base.x_extent(r)
        return max(a, (self.ox - 1.0) * r), min(b, (self.ox + 1.0) * r)

    def area(self, radius):
        return float(coverage(self, radius).sum())

    def contains(self, x, y):
        return self.base.contains(x, y) & ((x - self.ox) ** 2 + (y - self.oy) ** 2 <= 1.0)


def _clipped_areas(part: Aperture, ox: np.ndarray, oy: np.ndarray) -> np.ndarray:
    """Areas (unit radius) of `part` inside the unit circles about (ox, oy) (any shape): the
    chords' overlaps, exact along y, midpoint rule over _COLUMNS sub-columns per unit of x."""
    a, b = part.x_extent(1.0)
    if b <= a:
        return np.zeros(np.shape(ox))
    m = max(64, int(math.ceil((b - a) * _COLUMNS)))
    edges = np.linspace(a, b, m + 1)
    x, width = 0.5 * (edges[1:] + edges[:-1]), np.diff(edges)
    lo, hi = part.chord(x, 1.0)
    ox, oy = np.asarray(ox, np.float64)[..., None], np.asarray(oy, np.float64)[..., None]
    half = np.sqrt(np.maximum(1.0 - (x - ox) ** 2, 0.0))
    top, bottom = np.maximum(lo, oy - half), np.minimum(hi, oy + half)
    return (np.maximum(bottom - top, 0.0) * ((x - ox) ** 2 <= 1.0) * width).sum(axis=-1)


@dataclass(frozen=True)
class EyePlan:
    """The nodes of one cat-eye render: rows `gy` and columns `gx` (px of the planes), each
    node's clip offset (`ox`, `oy`, (Gy, Gx)), and per cell its shares (Gy, Gx) and whether
    the circle leaves it whole there."""

    gy: np.ndarray
    gx: np.ndarray
    ox: np.ndarray
    oy: np.ndarray
    shares: tuple
    whole: tuple

    def hats(self, ys: np.ndarray, xs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The hats along rows (Gy, len(ys)) and columns (Gx, len(xs)) at pixel positions
        `ys`, `xs` (clamped to the planes: what lies past them is their edge repeated)."""
        return _hat(self.gy, ys), _hat(self.gx, xs)


def _hat(g: np.ndarray, pos: np.ndarray) -> np.ndarray:
    """Bilinear hats of the nodes `g` (evenly spaced, first at 0 and last at the end) at `pos`."""
    p = np.clip(np.asarray(pos, np.float64), g[0], g[-1])
    if len(g) == 1:
        return np.ones((1, p.size))
    step = g[1] - g[0]
    return np.maximum(0.0, 1.0 - np.abs(p[None, :] - g[:, None]) / step)


def eye_plan(parts, shape: tuple[int, int], strength: float, margin: int, reach: float) -> EyePlan:
    """The nodes for cells `parts` ((cell, w) pairs), planes of `shape`, vignetting `strength`,
    `margin` px of the planes past the frame and the render's largest |CoC| `reach` (px)."""
    h, w = (int(v) for v in shape)
    half = 0.5 * math.hypot(h - 1 - 2 * margin, w - 1 - 2 * margin) or 1.0
    per_px = strength * max(float(reach), 1.0) / half / EDGE_PX  # edge px moved per px of frame

    def nodes(n):  # an odd count: the frame's centre, where the circle leaves the aperture whole, is a node
        count = min(MAX_NODES, max(3, int(math.ceil((n - 1) * per_px)) + 1)) if n > 1 else 1
        return np.linspace(0.0, n - 1.0, count + 1 - count % 2)

    gy, gx = nodes(h), nodes(w)
    oy, ox = cat_eye_offset((h, w), strength, *np.meshgrid(gy, gx, indexing="ij"), margin=margin)
    return _plan(tuple(cell for cell, _ in parts), gy.tobytes(), gx.tobytes(), oy.tobytes(), ox.tobytes(), oy.shape)


@lru_cache(maxsize=16)
def _plan(cells, gy, gx, oy, ox, shape) -> EyePlan:
    gy, gx = np.frombuffer(gy), np.frombuffer(gx)
    oy, ox = np.frombuffer(oy).reshape(shape), np.frombuffer(ox).reshape(shape)
    areas = np.stack([_clipped_areas(cell, ox, oy) for cell in cells])  # (cells, Gy, Gx)
    whole = np.stack([a >= (1.0 - 1e-9) * _clipped_areas(cell, np.zeros(1), np.zeros(1))[0]
                      for cell, a in zip(cells, areas)])
    shares = areas / np.maximum(areas.sum(axis=0), 1e-300)
    shares[shares < _EMPTY] = 0.0
    shares /= np.maximum(shares.sum(axis=0), 1e-300)
    for arr in (gy, gx, oy, ox, shares, whole):
        arr.setflags(write=False)
    return EyePlan(gy, gx, ox, oy, tuple(shares), tuple(whole))


def _span(h: np.ndarray) -> tuple[int, int]:
    """The first and one-past-last index where a hat is non-zero."""
    nz = np.flatnonzero(h > 0)
    return (int(nz[0]), int(nz[-1]) + 1) if nz.size else (0, 0)


def _interpolated(hy: np.ndarray, grid: np.ndarray, hx: np.ndarray) -> np.ndarray:
    """hy.T @ grid @ hx, float64 (h, w): node values `grid` (Gy, Gx) spread by the hats hy (Gy, h)
    and hx (Gx, w), each node row only over the rows its hat covers, summed in node order by
    numpy (not a BLAS product: one summation order on every machine, and no BLAS threads)."""
    along_x = np.zeros((grid.shape[0], hx.shape[1]))
    for j in range(grid.shape[1]):
        along_x += grid[:, j : j + 1] * hx[j]
    out = np.zeros((hy.shape[1], hx.shape[1]))
    for i in range(grid.shape[0]):
        r0, r1 = _span(hy[i])
        out[r0:r1] += hy[i, r0:r1, None] * along_x[i]
    return out


def groups(eye: EyePlan, k: int, cell: Aperture, hy: np.ndarray, hx: np.ndarray):
    """Cell k's parts for sources at the hats hy (Gy, h), hx (Gx, w): (aperture, (r0, r1, c0, c1),
    weights (r1 - r0, c1 - c0)) for the nodes where the cell is whole (one group, the cell
    itself) and for each node where the circle cuts it (the clipped cell, about that node)."""
    share, whole = eye.shares[k], eye.whole[k]
    kept = np.where(whole, share, 0.0)
    if kept.any():
        weights = _interpolated(hy, kept, hx).astype(np.float32)
        rows, cols = np.flatnonzero(weights.any(axis=1)), np.flatnonzero(weights.any(axis=0))
        if rows.size:
            r0, r1, c0, c1 = rows[0], rows[-1] + 1, cols[0], cols[-1] + 1
            yield cell, (r0, r1, c0, c1), weights[r0:r1, c0:c1]
    for i, j in zip(*np.nonzero((share > 0) & ~whole)):
        (r0, r1), (c0, c1) = _span(hy[i]), _span(hx[j])
        if r1 > r0 and c1 > c0:
            weights = (share[i, j] * np.outer(hy[i, r0:r1], hx[j, c0:c1])).astype(np.float32)
            yield _clipped(cell, float(eye.ox[i, j]), float(eye.oy[i, j])), (r0, r1, c0, c1), weights


@lru_cache(maxsize=4096)
def _clipped(cell: Aperture, ox: float, oy: float) -> Clipped:
    return Clipped(cell, ox, oy)
