"""The adaptive renderer: the layered render everywhere, sub-aperture parts only where the
layered one errs.

The layered method (dofsynth.render.layered) errs by the covariance, over the aperture, of a
cutout's alpha and what lies behind it: near a blurred cutout's edge part of the aperture sees
the cutout and the rest what lies behind, which one blur per plane cannot tell apart. The
error vanishes where either is in focus, where the two share a CoC and where what lies behind
is flat (docs/rendering.md). `error_scores` bounds it on a grid of TILE x TILE px tiles;
`need_map` marks the tiles whose bound reaches MIN_SCORE, each with the aperture parts its
edges ask for (`parts_for`: two halves split across the edges' direction; 2 x 2 cells for a
rectangle holding both directions);
`rectangles` gathers the marked tiles into rectangles, each rendered by the sub-aperture
composite (dofsynth.render.subaperture.render_cells) from the planes cut to it plus a margin
holding every pixel its result reads, and written over the layered result there. Elsewhere
the result is the layered method's, byte for byte. Deterministic: the same planes give the
same bytes.
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
from dofsynth.render.subaperture import cells, coc_reach, compact_disparity, cut_planes, halves, render_cells

TILE = 32           # px: the grid on which the aperture parts are chosen
RECT_COST = 4.0     # tiles: the cost of one more rendered rectangle, in tiles' area (`rectangles`)
MIN_SCORE = 0.005  # tiles whose error bound (`error_scores`) is lower keep the layered result
MIN_DIFFERENCE = 0.5  # px: a cutout and a plane behind it whose CoCs differ less count as alike
READ = 4            # px: the tiles' statistics are read on every READ-th pixel of every READ-th row


def _tiles_near(ys, xs, r: int, shape) -> np.ndarray:
    """(ty, tx) bool: the tiles within r px of one of the points (ys, xs) (px, from the grid's
    origin), found on an 8 px grid: a superset by at most 8 px."""
    g = TILE // 8
    ty, tx = shape
    fine = np.zeros((ty * g, tx * g), np.uint8)
    fine[np.clip(ys // 8, 0, ty * g - 1), np.clip(xs // 8, 0, tx * g - 1)] = 1
    k = 2 * int(math.ceil(r / 8)) + 1
    fine = cv2.dilate(fine, np.ones((k, k), np.uint8))
    return fine.reshape(ty, g, tx, g).any(axis=(1, 3))


def _per_tile(x: np.ndarray, shape, t: int = TILE) -> np.ndarray:
    """(ty, tx): the mean of x (the kept frame, t px a tile) over each tile (edge-padded)."""
    ty, tx = shape
    h, w = x.shape
    x = np.pad(x, ((0, ty * t - h), (0, tx * t - w)), mode="edge")
    return x.reshape(ty, t, tx, t).mean(axis=(1, 3), dtype=np.float64)


def _grown(t: np.ndarray, reach: float) -> np.ndarray:
    """A tile map averaged over the tiles within `reach` px (a box of whole tiles)."""
    r = int(math.ceil(reach / TILE))
    return cv2.blur(t, (2 * r + 1, 2 * r + 1), borderType=cv2.BORDER_REPLICATE) if r else t


def _tile_coc(c, kept, shape) -> np.ndarray:
    """(ty, tx): the largest |CoC| (px; a number or a compact map) over each tile and its neighbours."""
    if np.ndim(c) == 0:
        return np.full(shape, abs(float(c)))
    y0, y1, x0, x1 = kept
    ry, rx = (TILE if c.shape[0] > 1 else 1), (TILE if c.shape[1] > 1 else 1)  # a broadcast axis stays one
    c = np.abs(c)[slice(y0, y1) if ry > 1 else slice(None), slice(x0, x1) if rx > 1 else slice(None)]
    c = np.pad(c, ((0, shape[0] * ry - c.shape[0] if ry > 1 else 0), (0, shape[1] * rx - c.shape[1] if rx > 1 else 0)),
               mode="edge")
    t = np.broadcast_to(c.reshape(c.shape[0] // ry, ry, c.shape[1] // rx, rx).max(axis=(1, 3)), shape)
    return cv2.dilate(t.astype(np.float32), np.ones((3, 3), np.uint8), borderType=cv2.BORDER_REPLICATE)


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


def _spread(plane, box, kept, shape, reach: float) -> np.ndarray:
    """(ty, tx): the variance of what a plane shows over each tile grown by `reach` px: its
    premultiplied colour's largest channel (linear), plus its alpha for a cutout (`box`: its
    alpha box; an edge of it is a change of what lies behind the planes in front), read on
    every READ-th pixel (`_lattice`). box None: the backmost plane."""
    a = _lattice(np.asarray(plane.alpha, np.float32), kept, box)
    rgb = _lattice(np.asarray(plane.rgb, np.float32), kept, box)
    v = np.maximum(np.maximum(rgb[:, :, 0], rgb[:, :, 1]), rgb[:, :, 2])
    if box is not None or not np.all(a == 1.0):
        v *= a
    var = np.zeros(shape)
    for x in [v] if box is None else [v, a]:
        mean, square = (_grown(_per_tile(y, shape, TILE // READ), reach) for y in (x, x * x))
        var += np.maximum(square - mean * mean, 0.0)
    return var


def error_scores(planes, focus: float, max_coc: float, kept: tuple[int, int, int, int]) -> np.ndarray:
    """(ty, tx): a bound on the layered method's squared error in each TILE x TILE tile of the
    kept part `kept` (y0, y1, x0, x1) of the frame, up to a factor.

    The layered method errs by the covariance, over the aperture, of a cutout's alpha and what
    lies behind it (docs/rendering.md), at most the product of their deviations. For a blurred
    cutout i (|c_i| >= 0.5) within |c_i| + 2 px of one of its edges (a pixel with alpha > 0
    next to one with alpha < 1) and a blurred plane j behind it (|c_j| >= 0.5, the CoCs
    differing by MIN_DIFFERENCE or more), the score is A(1 - A), A the cutout's alpha averaged
    over |c_i| (the variance of a hard matte seen through the aperture), times the variance of
    what plane j shows over |c_j| (`_spread`); the largest over such pairs. 0 where one of the
    two is in focus or flat: the layered method is exact there."""
    y0, y1, x0, x1 = kept
    shape = (-(-(y1 - y0) // TILE), -(-(x1 - x0) // TILE))
    score = np.zeros(shape)
    cocs = [coc_radius(compact_disparity(p), focus, max_coc) for p in planes]
    reach = [float(np.max(np.abs(c))) for c in cocs]
    boxes = [None] + [plane_box(p, np.asarray(p.alpha, np.float32)) for p in planes[1:]]  # None: all / nothing
    varies: dict[int, np.ndarray] = {}  # per plane behind: its variance where it is blurred, 0 elsewhere
    for i in range(1, len(planes)):
        box = boxes[i]
        if reach[i] < 0.5 or box is None:
            continue
        alpha = np.asarray(planes[i].alpha, np.float32)
        behind = np.zeros(shape)  # the largest variance of a blurred plane behind it
        for j in range(i):
            diff = max(float(np.max(cocs[i])) - float(np.min(cocs[j])), float(np.max(cocs[j])) - float(np.min(cocs[i])))
            if reach[j] < 0.5 or diff < MIN_DIFFERENCE or (j > 0 and boxes[j] is None):
                continue
            if j not in varies:
                blurred = _tile_coc(cocs[j], kept, shape) >= 0.5
                varies[j] = np.where(blurred, _spread(planes[j], boxes[j], kept, shape, reach[j]), 0.0)
            behind = np.maximum(behind, varies[j])
        if not behind.any():
            continue
        # the edge pixels, found inside the box grown by one (a box that ends inside the frame
        # ends with alpha 0 next to it; one cut by the frame edge does not, and its cut is an edge)
        H, W = alpha.shape
        by0, by1, bx0, bx1 = box
        gy0, gy1, gx0, gx1 = max(by0 - 1, 0), min(by1 + 1, H), max(bx0 - 1, 0), min(bx1 + 1, W)
        a = alpha[gy0:gy1, gx0:gx1]
        edge = (a > 0) & (cv2.erode(a, np.ones((3, 3), np.uint8), borderType=cv2.BORDER_REPLICATE) < 1.0)
        ey, ex = np.nonzero(edge)
        band = _tiles_near(ey + gy0 - y0, ex + gx0 - x0, int(math.ceil(reach[i])) + 2, shape)
        mean = _grown(_per_tile(_lattice(alpha, kept), shape, TILE // READ), reach[i])
        score = np.maximum(score, np.where(band, np.clip(mean * (1.0 - mean), 0.0, 0.25) * behind, 0.0))
    return score


LAYERED, ACROSS_X, ACROSS_Y, GRID = 0, 1, 2, 3  # what a tile gets (`need_map`)


def parts_for(code: int, aperture: Aperture):
    """The aperture parts ((cell, share) pairs) for a `need_map` code: the left and right halves
    (ACROSS_X: for edges running up and down), the top and bottom halves (ACROSS_Y), or a 2 x 2
    grid (GRID: for a rectangle holding tiles of both directions)."""
    if code == ACROSS_X:
        return halves(aperture, "x")
    if code == ACROSS_Y:
        return halves(aperture, "y")
    return cells(aperture, 2)


def need_map(planes, focus: float, max_coc: float, kept: tuple[int, int, int, int]) -> np.ndarray:
    """(ty, tx) int: what each TILE x TILE tile of `kept` gets (as `error_scores`): LAYERED
    where the score is below MIN_SCORE (the layered result is kept); else the aperture split
    in two across the blurred cutouts' edges there: its left and right halves (ACROSS_X) where
    their alpha changes more along x than along y, else its top and bottom halves (ACROSS_Y).
    Each half sees one side of an edge across it; along the edge, within a half, the first
    moments of the second-order composite suffice."""
    score = error_scores(planes, focus, max_coc, kept)
    marked = score >= MIN_SCORE
    need = np.zeros(score.shape, np.int32)
    if not marked.any():
        return need
    gx, gy = np.zeros(score.shape), np.zeros(score.shape)
    for p in planes[1:]:
        reach = coc_reach(p, focus, max_coc)
        if reach < 0.5:
            continue
        a = _lattice(np.asarray(p.alpha, np.float32), kept)
        dx, dy = np.zeros_like(a), np.zeros_like(a)
        dx[:, 1:], dy[1:] = np.diff(a, axis=1) ** 2, np.diff(a, axis=0) ** 2
        gx += _grown(_per_tile(dx, score.shape, TILE // READ), reach)
        gy += _grown(_per_tile(dy, score.shape, TILE // READ), reach)
    need[marked] = np.where(gx[marked] >= gy[marked], ACROSS_X, ACROSS_Y)
    return need


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
    box = np.array(rects, np.float64)

    def cost(b):
        return (b[..., 1] - b[..., 0] + 2 * pad) * (b[..., 3] - b[..., 2] + 2 * pad) + fixed

    while len(box) > 1:
        lo = np.minimum(box[:, None, [0, 2]], box[None, :, [0, 2]])
        hi = np.maximum(box[:, None, [1, 3]], box[None, :, [1, 3]])
        union = np.stack([lo[..., 0], hi[..., 0], lo[..., 1], hi[..., 1]], axis=-1)
        own = cost(box)
        saving = own[:, None] + own[None, :] - cost(union)
        np.fill_diagonal(saving, -np.inf)
        k = int(np.argmax(saving))
        a, b = divmod(k, len(box))
        if saving[a, b] < 0:
            break
        merged = union[a, b]
        box = np.concatenate([np.delete(box, [a, b], axis=0), merged[None]])
    return sorted((int(b[0]), int(b[1]), int(b[2]), int(b[3])) for b in box)


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
    for t0, t1, s0, s1 in rectangles(need > 0, pad / TILE):
        codes = set(np.unique(need[t0:t1, s0:s1]).tolist()) - {LAYERED}
        code = codes.pop() if len(codes) == 1 else GRID  # one direction, or 2 x 2 cells for both
        y0, y1 = m + t0 * TILE, min(m + t1 * TILE, H - m)
        x0, x1 = m + s0 * TILE, min(m + s1 * TILE, W - m)
        cut = cut_planes(planes, y0 - pad, y1 + pad, x0 - pad, x1 + pad)
        img = render_cells(cut, focus, max_coc, parts_for(code, aperture), sub, inner=pad - 1)
        out[:, y0:y1, x0:x1] = img[:, pad : pad + y1 - y0, pad : pad + x1 - x0]
    return out
