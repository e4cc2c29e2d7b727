"""The layered depth-of-field renderer: blur each plane on its own, composite back to front.

`render_planes(planes, focus, max_coc)` returns linear RGB (H, W, 3) float32. Each plane's
premultiplied (colour * alpha, alpha) is blurred with the aperture kernel of its signed CoC
radius `c = max_coc * (disparity - focus)` in pixels (see dofsynth.aperture), then the blurred
planes are composited with "over". The backmost plane extends past the frame by edge
replication; the others are zero outside it.

Constant-disparity planes are convolved exactly (FFT, kernel transform cached; cv2 for tiny
kernels), cropped to the plane's alpha bounding box plus the kernel radius. Planes whose
disparity varies use a normalized scatter: the signed CoC is split into evenly spaced levels
`c_k` at most `level_step` pixels apart; each pixel is shared between its two neighbouring levels
with linear weights `w_k`, and `out = sum_k K_k * (w_k P) / sum_k K_k * w_k` (the denominator is the
same scatter applied to ones). A constant map is one level, i.e. the exact constant result. The
only approximation is the linear interpolation of kernels between levels (docs/rendering.md).
No torch here: this module is on the data-generation path.
"""
from __future__ import annotations

import math
from functools import lru_cache

import cv2
import numpy as np
import scipy.fft as sfft

from dofsynth.aperture import Aperture, Disk, Polygon, kernel, support_radius
from dofsynth.planes import Plane, validate_planes

# Kernels with support radius up to this many pixels (11x11) go through cv2.filter2D (direct,
# 2-6x faster there, measured), larger ones via FFT (cv2 switches to its own slower DFT beyond).
SMALL_KERNEL = 5
METHODS = ("layered", "exact")


@lru_cache(maxsize=16)  # each entry is up to a frame of complex64
def _kernel_fft(aperture: Aperture, signed_radius: float, n0: int, n1: int) -> np.ndarray:
    """rfft2 of the kernel placed with its centre at (0, 0) on an (n0, n1) torus."""
    k = kernel(aperture, signed_radius)
    s = k.shape[0] // 2
    buf = np.zeros((n0, n1), dtype=np.float32)
    buf[: 2 * s + 1, : 2 * s + 1] = k
    buf = np.roll(buf, (-s, -s), axis=(0, 1))
    out = sfft.rfft2(buf)
    out.setflags(write=False)
    return out


def convolve(x: np.ndarray, signed_radius: float, aperture: Aperture) -> np.ndarray:
    """Convolve a (C, h, w) float32 stack with the kernel of `signed_radius` pixels.

    The result has x's shape and positions. Values within S = support_radius of the border are
    correct only if x holds zeros (or the wanted extension) in that margin: the caller pads.
    """
    s = support_radius(signed_radius)
    if s == 0:
        return x.copy()
    k = kernel(aperture, signed_radius)
    c, h, w = x.shape
    if s <= SMALL_KERNEL:
        flipped = np.ascontiguousarray(k[::-1, ::-1])
        return np.stack(
            [cv2.filter2D(x[i], -1, flipped, borderType=cv2.BORDER_CONSTANT) for i in range(c)]
        )
    n0, n1 = sfft.next_fast_len(h, real=True), sfft.next_fast_len(w, real=True)
    spec = sfft.rfft2(x, s=(n0, n1), axes=(1, 2))
    spec *= _kernel_fft(aperture, float(signed_radius), n0, n1)
    return sfft.irfft2(spec, s=(n0, n1), axes=(1, 2))[:, :h, :w].astype(np.float32, copy=False)


def _bbox(mask: np.ndarray) -> tuple[int, int, int, int] | None:
    rows = np.flatnonzero(mask.any(axis=1))
    if rows.size == 0:
        return None
    cols = np.flatnonzero(mask.any(axis=0))
    return int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1


def _premultiplied(plane: Plane) -> np.ndarray:
    """(4, H, W) float32: R*a, G*a, B*a, a."""
    a = np.asarray(plane.alpha, dtype=np.float32)
    rgb = np.asarray(plane.rgb, dtype=np.float32)
    return np.concatenate([np.moveaxis(rgb, 2, 0) * a, a[None]], axis=0)


def _blur_constant(pm: np.ndarray, c: float, aperture: Aperture, backmost: bool):
    """Blur a constant-CoC plane. Returns (block (4, h, w), y0, x0): the frame region it covers."""
    _, H, W = pm.shape
    s = support_radius(c)
    if s == 0:
        return pm, 0, 0
    if backmost:
        padded = np.pad(pm, ((0, 0), (s, s), (s, s)), mode="edge")
        return convolve(padded, c, aperture)[:, s : s + H, s : s + W], 0, 0
    bb = _bbox(pm[3] > 0)
    if bb is None:
        return pm[:, :0, :0], 0, 0
    y0, y1, x0, x1 = bb
    padded = np.pad(pm[:, y0:y1, x0:x1], ((0, 0), (s, s), (s, s)))
    out = convolve(padded, c, aperture)
    ty0, tx0 = y0 - s, x0 - s
    cy0, cx0 = max(ty0, 0), max(tx0, 0)
    cy1, cx1 = min(y1 + s, H), min(x1 + s, W)
    return out[:, cy0 - ty0 : cy1 - ty0, cx0 - tx0 : cx1 - tx0], cy0, cx0


def level_weights(cmap: np.ndarray, level_step: float):
    """CoC levels (pixels) c_k = c_min + k * level_step covering [c_min, c_max], and for each pixel
    its lower level index k0 and the weight f of level k0+1 (1 - f goes to level k0).

    Anchoring the levels at c_min with a fixed step keeps the result continuous in focus, max_coc
    and the map (a new top level enters with weight 0); a constant map is a single level.
    """
    cmin, cmax = float(cmap.min()), float(cmap.max())
    if cmax == cmin:
        return np.array([cmin]), np.zeros(cmap.shape, np.int32), np.zeros(cmap.shape, np.float32)
    n = max(int(math.ceil((cmax - cmin) / level_step)), 1) + 1
    levels = cmin + level_step * np.arange(n)
    t = (cmap.astype(np.float64) - cmin) / level_step
    k0 = np.clip(np.floor(t), 0, n - 2).astype(np.int32)
    f = np.clip(t - k0, 0.0, 1.0).astype(np.float32)
    return levels, k0, f


def _blur_varying(pm, cmap, aperture, backmost, level_step, alpha_one):
    """Normalized level scatter of a plane with per-pixel CoC `cmap` (pixels)."""
    _, H, W = pm.shape
    smax = support_radius(max(abs(float(cmap.min())), abs(float(cmap.max()))))
    if backmost:
        oy0, oy1, ox0, ox1 = 0, H, 0, W
    else:
        bb = _bbox(pm[3] > 0)
        if bb is None:
            return pm[:, :0, :0], 0, 0
        oy0, oy1 = max(bb[0] - smax, 0), min(bb[1] + smax, H)
        ox0, ox1 = max(bb[2] - smax, 0), min(bb[3] + smax, W)
    # E: the output region O grown by smax; outside the frame, colour is edge-replicated for the
    # backmost plane and zero otherwise; the CoC map is always edge-replicated.
    ey0, ey1, ex0, ex1 = oy0 - smax, oy1 + smax, ox0 - smax, ox1 + smax
    iy = np.clip(np.arange(ey0, ey1), 0, H - 1)
    ix = np.clip(np.arange(ex0, ex1), 0, W - 1)
    c_e = cmap[np.ix_(iy, ix)]
    p_e = pm[:, iy[:, None], ix[None, :]]
    if not backmost:
        inside = ((np.arange(ey0, ey1) >= 0) & (np.arange(ey0, ey1) < H))[:, None] & (
            (np.arange(ex0, ex1) >= 0) & (np.arange(ex0, ex1) < W)
        )[None, :]
        p_e = p_e * inside
    # Channels scattered: premultiplied RGB, alpha (unless it is 1, then it equals the weight), weight.
    nch = 4 if alpha_one else 5
    he, we = c_e.shape
    acc = np.zeros((nch, he, we), dtype=np.float32)
    levels, k0, f = level_weights(c_e, level_step)
    # Level k touches pixels with k0 in {k-1, k}: a superset box from per-row/column ranges.
    rlo, rhi = k0.min(axis=1), k0.max(axis=1) + 1
    clo, chi = k0.min(axis=0), k0.max(axis=0) + 1
    for k, ck in enumerate(levels):
        rows = np.flatnonzero((rlo <= k) & (rhi >= k))
        cols = np.flatnonzero((clo <= k) & (chi >= k))
        if rows.size == 0 or cols.size == 0:
            continue
        y0, y1, x0, x1 = int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1
        ksub, fsub = k0[y0:y1, x0:x1], f[y0:y1, x0:x1]
        wsub = np.where(ksub == k, 1.0 - fsub, 0.0).astype(np.float32)
        wsub += np.where(ksub == k - 1, fsub, 0.0)
        if not wsub.any():
            continue
        s = support_radius(ck)
        x = np.zeros((nch, y1 - y0 + 2 * s, x1 - x0 + 2 * s), dtype=np.float32)
        x[:3, s : s + y1 - y0, s : s + x1 - x0] = p_e[:3, y0:y1, x0:x1] * wsub
        if not alpha_one:
            x[3, s : s + y1 - y0, s : s + x1 - x0] = p_e[3, y0:y1, x0:x1] * wsub
        x[-1, s : s + y1 - y0, s : s + x1 - x0] = wsub
        out = convolve(x, float(ck), aperture)
        ty0, tx0 = y0 - s, x0 - s
        cy0, cx0 = max(ty0, 0), max(tx0, 0)
        cy1, cx1 = min(y1 + s, he), min(x1 + s, we)
        acc[:, cy0:cy1, cx0:cx1] += out[:, cy0 - ty0 : cy1 - ty0, cx0 - tx0 : cx1 - tx0]
    o = acc[:, oy0 - ey0 : oy1 - ey0, ox0 - ex0 : ox1 - ex0]
    den = np.maximum(o[-1], 1e-12)
    res = np.empty((4,) + den.shape, dtype=np.float32)
    res[:3] = o[:3] / den
    res[3] = 1.0 if alpha_one else o[3] / den
    return res, oy0, ox0


def render_planes(
    planes,
    focus: float,
    max_coc: float,
    aperture: Aperture = Disk(),
    *,
    method: str = "layered",
    level_step: float = 0.5,
    samples: int | None = None,
) -> np.ndarray:
    """Render a layered scene with shallow depth of field; linear RGB (H, W, 3) float32.

    planes: dofsynth.planes.Plane, back to front (disparity in [0, 1], 1 = nearest). focus: the
    in-focus disparity. max_coc: CoC radius in pixels at |disparity - focus| = 1. aperture: Disk()
    or Polygon(...). method: "layered" (per-plane blur, fast) or "exact" (aperture sampling with
    occlusion per sample, slow; `samples` = aperture points, None = enough for <= 0.5 px steps).
    level_step: largest CoC gap in pixels between the levels of a varying-disparity plane.
    The result is the premultiplied composite over black (opaque if the backmost plane is).
    """
    planes = list(planes)
    validate_planes(planes, focus, max_coc)
    if not isinstance(aperture, (Disk, Polygon)):
        raise ValueError(f"aperture must be Disk() or Polygon(...), got {aperture!r}")
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    if not (math.isfinite(level_step) and level_step > 0):
        raise ValueError(f"level_step must be a positive number of pixels, got {level_step}")
    if samples is not None and (
        isinstance(samples, bool) or not isinstance(samples, (int, np.integer)) or samples < 1
    ):
        raise ValueError(f"samples must be a positive integer or None, got {samples}")
    if method == "exact":
        from dofsynth.exact import render_exact

        return render_exact(planes, focus, max_coc, aperture, samples=samples)
    H, W = planes[0].shape
    acc = np.zeros((4, H, W), dtype=np.float32)
    for i, plane in enumerate(planes):
        backmost = i == 0
        pm = _premultiplied(plane)
        d = plane.constant_disparity()
        if d is not None:
            block, y0, x0 = _blur_constant(pm, float(max_coc) * (d - float(focus)), aperture, backmost)
        else:
            cmap = np.float32(max_coc) * (plane.disparity_map() - np.float32(focus))
            alpha_one = backmost and bool(np.all(pm[3] == 1.0))  # then alpha == the weight
            block, y0, x0 = _blur_varying(pm, cmap, aperture, backmost, level_step, alpha_one)
        h, w = block.shape[1:]
        if h == 0 or w == 0:
            continue
        region = acc[:, y0 : y0 + h, x0 : x0 + w]
        region *= 1.0 - block[3]
        region += block
    return np.ascontiguousarray(np.moveaxis(acc[:3], 0, 2))
