"""The adaptive renderer: the layered render everywhere, 2 x 2 sub-aperture cells only where
the layered one errs.

The layered method (dofsynth.render.layered) errs by the covariance, over the aperture, of a
cutout's alpha and what lies behind it: near a blurred cutout's edge part of the aperture sees
the cutout and the rest what lies behind, which one blur per plane cannot tell apart. The
error vanishes where either is in focus, where the two share a CoC and where what lies behind
is flat (docs/rendering.md). `error_scores` bounds it per pixel and averages the bound over a
grid of TILE x TILE px tiles; `need_map` marks the tiles of highest bound, leaving layered
those whose bounds add up to at most ERROR_BUDGET a tile and any below MIN_SCORE;
`rectangles` gathers them into rectangles, each rendered through 2 x 2 cells of the aperture
by the sub-aperture composite (dofsynth.render.subaperture.render_cells) from the planes cut
to it plus a margin holding every pixel its result reads, and written over the layered result
there. Elsewhere the result is the layered method's, byte for byte. Deterministic: the same
planes give the same bytes.
"""
from __future__ import annotations

import math
from dataclasses import replace

import cv2
import numpy as np

from dofsynth.optics.aperture import Aperture
from dofsynth.optics.coc import coc_radius
from dofsynth.optics.kernel import support_radius
from dofsynth.render.layered import plane_box, render_layered
from dofsynth.render.subaperture import cells, coc_reach, compact_disparity, cut_planes, render_cells

TILE = 32           # px: the grid on which the cells are placed
RECT_COST = 4.0     # tiles: the cost of one more rendered rectangle, in tiles' area (`rectangles`)
MIN_SCORE = 3e-4    # tiles whose bound (`error_scores`: a mean square, linear light) is lower stay layered
ERROR_BUDGET = 3e-5  # the bound, in mean over the frame's tiles, left layered at most (`need_map`)
MIN_DIFFERENCE = 0.5  # px: a cutout and a plane behind it whose CoCs differ less count as alike
READ = 4            # px: the tiles' statistics are read on every READ-th pixel of every READ-th row


def _per_tile(x: np.ndarray, shape, t: int = TILE) -> np.ndarray:
    """(ty, tx): the mean of x (the kept frame, t px a tile) over each tile (edge-padded)."""
    ty, tx = shape
    h, w = x.shape
    x = np.pad(x, ((0, ty * t - h), (0, tx * t - w)), mode="edge")
    return x.reshape(ty, t, tx, t).mean(axis=(1, 3), dtype=np.float64)


def _lattice(a: np.ndarray, kept, box=None) -> np.ndarray:
    """a[kept] read on every READ-th pixel of every READ-th row; only inside `box` (y0, y1, x0,
    x1 of the frame) when given, 0 elsewhere (a cutout's colour is not read outside its box)."""
    y0, y1, x0, x1 = kept
    if box is None:
        return np.asarray(a[y0:y1:READ, x0:x1:READ], np.float32)
    out = np.zeros((-(-(y1 - y0) // READ), -(-(x1 - x0) // READ)) + a.shape[2:], np.float32)
    i0, i1 = -(-(max(box[0], y0) - y0) // READ), -(-(min(box[1], y1) - y0) // READ)
    j0, j1 = -(-(max(box[2], x0) - x0) // READ), -(-(min(box[3], x1) - x0) // READ)
    if i1 > i0 and j1 > j0:
        out[i0:i1, j0:j1] = a[y0 + i0 * READ : y0 + i1 * READ : READ, x0 + j0 * READ : x0 + j1 * READ : READ]
    return out


def _variance_over(x: np.ndarray, c) -> np.ndarray:
    """The variance of a lattice map x (`_lattice`) over a disc of radius |c| px about each of
    its points (c: a number, or a map of x's shape), read with a box of about the disc's area
    (at least 3 x 3 lattice points where |c| >= 0.5 px: a blur finer than the lattice is
    counted as one of 3 x 3); 0 where |c| < 0.5 px. A varying c is taken on box sides about
    1.5x apart, each point from its nearest."""
    c = np.abs(np.asarray(c, np.float32))
    out = np.zeros(x.shape, np.float32)
    if float(c.max()) < 0.5:
        return out
    sides = np.maximum(2 * np.round(c * (math.sqrt(math.pi) / 2 / READ)).astype(np.int32) + 1, 3)
    if c.ndim == 0:
        levels, pick = [int(sides)], None
    else:  # sides on levels 1.5x apart (odd), each point its nearest
        c = np.broadcast_to(c, x.shape)
        levels = sorted({int(v) for v in np.unique(sides[c >= 0.5])})
        grid = [levels[0]]
        for v in levels[1:]:
            if v > grid[-1] * 1.5:
                grid.append(v)
        levels = grid
        pick = np.abs(np.log(np.broadcast_to(sides, x.shape)[..., None] / np.array(levels, np.float32))).argmin(-1)
        pick[c < 0.5] = -1
    square = x * x
    for k, side in enumerate(levels):
        mean = cv2.blur(x, (side, side), borderType=cv2.BORDER_REPLICATE)
        var = np.maximum(cv2.blur(square, (side, side), borderType=cv2.BORDER_REPLICATE) - mean * mean, 0.0)
        if pick is None:
            return var
        np.copyto(out, var, where=pick == k)
    return out


def error_scores(planes, focus: float, max_coc: float, kept: tuple[int, int, int, int]) -> np.ndarray:
    """(ty, tx): a bound on the layered method's mean squared error (linear light, per channel)
    over each TILE x TILE tile of the kept part `kept` (y0, y1, x0, x1) of the frame.

    The layered method errs by the covariance, over the aperture, of a cutout's alpha and what
    lies behind it (docs/rendering.md), at most the product of their standard deviations. Per
    pixel, for a blurred cutout i (|c_i| >= 0.5 px) and a blurred plane j behind it whose CoC
    differs by MIN_DIFFERENCE or more: the variance of i's alpha over its CoC's disc times the
    variance over j's disc of what j shows (its premultiplied colour's largest channel, plus
    its alpha for a cutout: an edge of it is a change of what lies behind the planes in front);
    the largest over such pairs, averaged over the tile. Read on every READ-th pixel of every
    READ-th row (`_lattice`). 0 where one of the two is in focus or flat, and away from the
    cutout's edges: the layered method is exact there."""
    y0, y1, x0, x1 = kept
    shape = (-(-(y1 - y0) // TILE), -(-(x1 - x0) // TILE))
    cocs = [coc_radius(compact_disparity(p), focus, max_coc) for p in planes]
    boxes = [None] + [plane_box(p, np.asarray(p.alpha, np.float32)) for p in planes[1:]]  # None: all / nothing
    lat_coc = {}  # per plane: its CoC, a number or a lattice map

    def coc_of(j):
        if j not in lat_coc:
            c = cocs[j]
            lat_coc[j] = c if np.ndim(c) == 0 else _lattice(np.broadcast_to(c, planes[j].shape), kept)
        return lat_coc[j]

    shows: dict[int, np.ndarray] = {}  # per plane behind: the variance of what it shows over its CoC
    worst = None
    for i in range(1, len(planes)):
        if boxes[i] is None or float(np.max(np.abs(cocs[i]))) < 0.5:
            continue
        behind = None
        for j in range(i):
            diff = max(float(np.max(cocs[i])) - float(np.min(cocs[j])), float(np.max(cocs[j])) - float(np.min(cocs[i])))
            if float(np.max(np.abs(cocs[j]))) < 0.5 or diff < MIN_DIFFERENCE or (j > 0 and boxes[j] is None):
                continue
            if j not in shows:
                p = planes[j]
                a = _lattice(np.asarray(p.alpha, np.float32), kept, boxes[j])
                rgb = _lattice(np.asarray(p.rgb, np.float32), kept, boxes[j])
                v = np.maximum(np.maximum(rgb[:, :, 0], rgb[:, :, 1]), rgb[:, :, 2])
                if j > 0 or not np.all(a == 1.0):
                    v *= a
                shows[j] = _variance_over(v, coc_of(j))
                if j > 0:
                    shows[j] += _variance_over(a, coc_of(j))
            behind = shows[j] if behind is None else np.maximum(behind, shows[j])
        if behind is None or not behind.any():
            continue
        seen = _variance_over(_lattice(np.asarray(planes[i].alpha, np.float32), kept, boxes[i]), coc_of(i))
        seen[seen < 1e-6] = 0.0  # (float rounding inside and outside the cutout)
        pair = seen * behind
        worst = pair if worst is None else np.maximum(worst, pair)
    if worst is None:
        return np.zeros(shape)
    return _per_tile(worst, shape, TILE // READ)


def need_map(planes, focus: float, max_coc: float, kept: tuple[int, int, int, int]) -> np.ndarray:
    """(ty, tx) bool: the TILE x TILE tiles of `kept` that get 2 x 2 cells; the others keep the
    layered result. From the lowest `error_scores` bound up, tiles stay layered while their
    bounds add up to at most ERROR_BUDGET times the number of tiles (what they leave bounds the
    frame's mean squared error), and every tile whose bound is below MIN_SCORE stays layered.
    Ties go in row-major order (deterministic)."""
    scores = error_scores(planes, focus, max_coc, kept)
    flat = scores.ravel()
    order = np.argsort(flat, kind="stable")
    layered = np.empty(flat.size, bool)
    layered[order] = np.cumsum(flat[order]) <= ERROR_BUDGET * flat.size
    return (scores >= MIN_SCORE) & ~layered.reshape(scores.shape)


def rectangles(marked: np.ndarray, pad: float, fixed: float = RECT_COST) -> list[tuple[int, int, int, int]]:
    """Tile rectangles (ty0, ty1, tx0, tx1) that cover every marked tile, chosen for cost: a
    rectangle of h x w tiles costs (h + 2 pad)(w + 2 pad) + `fixed` (pad and fixed in tiles:
    the margin rendered around it, and the cost of one more render). Starting from the runs of
    marked tiles in each row, the pair whose union saves the most is merged until no union
    saves anything. Deterministic (ties go to the first pair in row-major order)."""
    rects = []
    for r in range(marked.shape[0]):
        cols = np.flatnonzero(marked[r])
        if cols.size:
            breaks = np.flatnonzero(np.diff(cols) > 1)
            for a, b in zip(np.r_[0, breaks + 1], np.r_[breaks, cols.size - 1]):
                rects.append((r, r + 1, int(cols[a]), int(cols[b]) + 1))
    if not rects:
        return []

    def cost(b):
        return (b[..., 1] - b[..., 0] + 2 * pad) * (b[..., 3] - b[..., 2] + 2 * pad) + fixed

    def union(b, others):
        return np.stack([np.minimum(b[..., 0], others[..., 0]), np.maximum(b[..., 1], others[..., 1]),
                         np.minimum(b[..., 2], others[..., 2]), np.maximum(b[..., 3], others[..., 3])], -1)

    # a merged rectangle is appended and the pair it replaces retired, so the live ones keep
    # their order: the pair merged is the first best one in row-major order of the live ones
    n = len(rects)
    size = 2 * n - 1  # every merge adds one
    box = np.zeros((size, 4), np.int64)
    box[:n] = rects
    own = np.zeros(size)
    own[:n] = cost(box[:n])
    saving = np.full((size, size), -np.inf)
    saving[:n, :n] = own[:n, None] + own[None, :n] - cost(union(box[:n, None], box[None, :n]))
    np.fill_diagonal(saving, -np.inf)
    live = list(range(n))
    while len(live) > 1:
        a, b = divmod(int(np.argmax(saving)), size)
        if saving[a, b] < 0:
            break
        saving[[a, b], :] = saving[:, [a, b]] = -np.inf
        live.remove(a)
        live.remove(b)
        box[n] = union(box[a], box[b])
        own[n] = cost(box[n])
        if live:
            saving[n, live] = saving[live, n] = own[live] + own[n] - cost(union(box[n][None], box[live]))
        live.append(n)
        n += 1
    return sorted((int(b[0]), int(b[1]), int(b[2]), int(b[3])) for b in box[live])


def render_adaptive(planes, focus: float, max_coc: float, aperture: Aperture, options) -> np.ndarray:
    """Adaptive render of validated planes (back to front): linear RGB (3, H, W) float32.
    `options`: a dofsynth.render.RenderOptions (its level_step, level_ratio and margin as for
    the layered method; inside the rectangles the levels are at least 1/8 apart relatively:
    they blur a part of the aperture, whose kernel changes less with the radius)."""
    out = render_layered(planes, focus, max_coc, aperture, options)
    H, W = planes[0].shape
    m = options.margin
    kept = (m, H - m, m, W - m)
    need = need_map(planes, focus, max_coc, kept)
    if not need.any():
        return out
    # a rectangle's pixels and one more each side (the composite's gradients) are computed, from
    # the planes cut to them plus the largest kernel's reach (edge pixels past the frame)
    pad = support_radius(max(coc_reach(p, focus, max_coc) for p in planes)) + 1
    sub = replace(options, level_ratio=max(options.level_ratio, 1 / 8))  # (render_cells sets its own margins)
    parts = cells(aperture, 2)
    for t0, t1, s0, s1 in rectangles(need, pad / TILE):
        y0, y1 = m + t0 * TILE, min(m + t1 * TILE, H - m)
        x0, x1 = m + s0 * TILE, min(m + s1 * TILE, W - m)
        cut = cut_planes(planes, y0 - pad, y1 + pad, x0 - pad, x1 + pad)
        img = render_cells(cut, focus, max_coc, parts, sub, inner=pad - 1)
        out[:, y0:y1, x0:x1] = img[:, pad : pad + y1 - y0, pad : pad + x1 - x0]
    return out
