"""The exact (slow) layered renderer: sample the aperture, composite per sample, average.

For each aperture point p (a point of the unit shape, in units of the CoC radius) the sensor
point x sees the plane point x' with x = x' + p * c(x'), c the signed CoC in pixels. Each plane
is warped accordingly (a sub-pixel shift for a constant plane; for a varying map x' is found by
fixed-point iteration x' <- x - p * c(x')), the warped planes are composited back to front with
"over", and the composites are averaged over p. This handles partial occlusion at depth edges
exactly (up to the aperture sampling and bilinear resampling), which the per-plane blur cannot.
"""
from __future__ import annotations

import math

import cv2
import numpy as np

from dofsynth.optics.aperture import Aperture, cat_eye_offset
from dofsynth.optics.coc import coc_radius
from dofsynth.optics.kernel import coverage
from dofsynth.render.frame import compact
from dofsynth.render.planes import alpha_box

FIXED_POINT_ITERATIONS = 5


def aperture_samples(aperture: Aperture, max_abs_coc: float, samples: int | None = None):
    """Points (px, py) of the unit aperture on a regular grid centred on 0 and their weights.

    Grid spacing h = 0.5 / max_abs_coc by default (neighbouring points' displacements differ by at
    most 0.5 px), or sqrt(area / samples) when `samples` is given. Each point's weight is the area
    of the shape inside its grid cell (so the set integrates the shape like the kernels do).
    Returns px, py, weights, h and each point's share of its grid cell inside the shape.
    """
    unit_area = aperture.area(1.0)
    if samples is not None:
        h = math.sqrt(unit_area / samples)
    else:
        h = 0.5 / max(float(max_abs_coc), 0.5)
    w = coverage(aperture, 1.0 / h)
    s = w.shape[0] // 2
    iy, ix = np.nonzero(w > 0)
    px, py = (ix - s) * h, (iy - s) * h
    wt = w[iy, ix] / w.sum()
    return px.astype(np.float32), py.astype(np.float32), wt, h, np.minimum(w[iy, ix], 1.0)


def inside_clip(x, y, oy, ox, h: float, share: float):
    """The part of an aperture point's light (grid cell of side h at (x, y), `share` of it inside
    the shape) that the clip circle of radius 1 about (ox, oy) lets through: the cell's share
    inside the circle, linear in the distance across it within h / 2, taken as nested with the
    shape's (min, over the shape's share), so a circle along the shape's own rim clips nothing
    (a hard inside test quantizes the cat's eye's edge to the sampling)."""
    d = np.sqrt((y - oy) ** 2 + (x - ox) ** 2)
    return (np.minimum(np.clip(0.5 + (1.0 - d) / h, 0.0, 1.0), share) / share).astype(np.float32)


def _source(cmap, px, py, gx, gy):
    """Where sensor pixels (gx: a (1, w) row of columns, gy: an (h, 1) column of rows) see a
    plane of CoC `cmap` through aperture point p: x' with x = x' + p c(x'). `cmap` (px): a
    number; a ramp kept as one row or column (`frame.compact`), solved along its own axis by
    fixed-point iteration x' <- x - p c(x') (np.interp, edge-clamped); or a full map, iterated
    the same way with bilinear edge-replicated lookups. (mx, my) broadcast to (h, w)."""
    if np.ndim(cmap) == 0:
        return gx - px * cmap, gy - py * cmap
    h, w = cmap.shape
    if h == 1 or w == 1:  # a ramp: c depends on x alone (a row) or on y alone (a column)
        line, along, step = (cmap[0], gx[0], px) if h == 1 else (cmap[:, 0], gy[:, 0], py)
        grid, q = np.arange(line.size, dtype=np.float64), along.astype(np.float64)
        c = np.interp(q, grid, line)
        for _ in range(FIXED_POINT_ITERATIONS):
            c = np.interp(q - step * c, grid, line)
        c = c.astype(np.float32)[None, :] if h == 1 else c.astype(np.float32)[:, None]
        return gx - px * c, gy - py * c
    gx, gy = np.broadcast_arrays(gx, gy)
    c = cmap[gy.astype(np.intp), gx.astype(np.intp)]  # start from c at the sensor point
    mx, my = gx - px * c, gy - py * c
    for _ in range(FIXED_POINT_ITERATIONS):
        c = cv2.remap(cmap, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        mx, my = gx - px * c, gy - py * c
    return mx, my


def _warp(src, mx, my, dst=None):
    """`src` (H, W[, C]) sampled at source positions (mx, my) (broadcasting to the output's
    (h, w)), bilinear, edge-replicated beyond the frame as in the layered renderer."""
    mx, my = np.broadcast_arrays(mx, my)
    return cv2.remap(src, np.ascontiguousarray(mx, np.float32), np.ascontiguousarray(my, np.float32),
                     cv2.INTER_LINEAR, dst=dst, borderMode=cv2.BORDER_REPLICATE)


_FLUSH = 64  # aperture points summed in float32 before they are added to the float64 total


def render_exact(planes, focus: float, max_coc: float, aperture: Aperture, options) -> np.ndarray:
    """Aperture-sampled render of validated planes; linear RGB (3, H, W) float32. `options`: a
    dofsynth.render.RenderOptions (its `samples`: aperture points, None = 0.5 px steps; its
    `cat_eye`: the vignetting strength).

    Cat-eye: a plane's light through aperture point p counts only where p lies inside the clip
    circle of the plane point it comes from (`cat_eye_offset` at that source position, clamped
    to the frame as the planes are replicated beyond it), divided by the share of the aperture
    inside that circle: each source point keeps its light (what is in focus is untouched) and
    spreads it over its clipped disc; occlusion (1 - alpha) is not clipped.

    Slow: cost grows with the number of aperture points (about pi * (2 * max|c|)^2 for a disk
    by default), each a warp of the backmost plane over the frame and of each cutout over its
    alpha box grown by its largest CoC (nothing of it lands further). Meant as the reference
    for the faster renderers and for small images.
    """
    H, W = planes[0].shape
    rows, cols = np.arange(H, dtype=np.float32)[:, None], np.arange(W, dtype=np.float32)[None, :]
    prepared = []  # (premultiplied colour [+ alpha], CoC, region it lands in)
    cmax = 0.0
    for i, plane in enumerate(planes):
        a = np.asarray(plane.alpha, np.float32)
        d = plane.constant_disparity()
        c = (np.float32(coc_radius(d, focus, max_coc)) if d is not None
             else coc_radius(compact(np.asarray(plane.disparity_map(), np.float32)), focus, max_coc))
        reach = float(np.max(np.abs(c)))
        cmax = max(cmax, reach)
        rgb = np.asarray(plane.rgb, np.float32)
        if i == 0:  # the backmost plane: only its colour counts (it is composited over black)
            prepared.append((np.ascontiguousarray(rgb * a[:, :, None]), c, (0, H, 0, W)))
            continue
        box = alpha_box(a)
        if box is None:
            continue
        r = int(math.ceil(reach)) + 2
        region = (max(box[0] - r, 0), min(box[1] + r, H), max(box[2] - r, 0), min(box[3] + r, W))
        pm = np.concatenate([rgb * a[:, :, None], a[:, :, None]], axis=2)
        prepared.append((np.ascontiguousarray(pm), c, region))
    px, py, wt, h, share = aperture_samples(aperture, cmax, options.samples)
    strength = options.cat_eye
    if strength:  # the share of the aperture inside each frame position's clip circle (a map)
        oy, ox = cat_eye_offset((H, W), strength, margin=options.margin)
        area = np.zeros((H, W), np.float32)
        for x, y, w, f in zip(px, py, wt, share):
            area += np.float32(w) * inside_clip(x, y, oy, ox, h, f)
    acc = np.zeros((H, W, 3), np.float64)
    part = np.zeros((H, W, 3), np.float32)
    comp = np.empty((H, W, 3), np.float32)
    for n, (x, y, w, f) in enumerate(zip(px, py, wt, share)):
        for k, (pm, c, (y0, y1, x0, x1)) in enumerate(prepared):
            mx, my = _source(c, x, y, cols[:, x0:x1], rows[y0:y1])
            if k == 0:
                colour = _warp(pm, mx, my, dst=comp)
            else:
                warped = _warp(pm, mx, my)
                colour, a = warped[:, :, :3], warped[:, :, 3:4]
            if strength:  # the light counts where p lies in the clip circle of its source point
                sx, sy = (np.clip(v, lo, hi) for v, lo, hi in ((mx, 0, W - 1), (my, 0, H - 1)))  # replicated beyond
                sx, sy = np.broadcast_arrays(sx, sy)
                oy, ox = cat_eye_offset((H, W), strength, sy, sx, options.margin)
                inside = inside_clip(x, y, oy, ox, h, f) / np.maximum(_warp(area, sx, sy), 1e-12)
                colour *= inside.astype(np.float32)[:, :, None]
            if k:
                under = comp[y0:y1, x0:x1]
                under *= 1.0 - a
                under += colour
        cv2.scaleAdd(comp, float(w), part, dst=part)
        if (n + 1) % _FLUSH == 0 or n + 1 == len(px):
            acc += part
            part[...] = 0.0
    return np.ascontiguousarray(acc.transpose(2, 0, 1), dtype=np.float32)
