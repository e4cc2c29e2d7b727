"""Anti-aliased blur kernels (point-spread functions) of the aperture shapes.

A kernel of signed radius `c` (pixels) is what a pixel's light becomes on the sensor: the
aperture shape scaled by `|c|`, integrated against the bilinear tent of each kernel pixel,
K[n] = integral over the shape of tent(n - x) dx, normalized to sum 1. The tent (the box of the
source pixel convolved with the box of the sensor pixel) makes the kernel the exact blur of a
scene that is constant over each pixel, seen by pixels that integrate over their area; it is
also what warping by bilinear resampling averages to (dofsynth.render.exact). For `c < 0` the
shape is point-reflected (matters only for odd-bladed polygons). The kernel grows continuously
from the identity at `c = 0`. `Polygon`'s radius is its circumradius (centre-to-vertex distance).
`coverage` is the plain area of the shape in each pixel (aperture sampling, area shares).
"""
from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

from dofsynth.optics.aperture import Aperture

# Sub-samples per pixel column for the midpoint rule along x; y is integrated exactly. The
# tent-weighted kernels need fewer: their integrand is continuous across pixel edges.
X_SUBSAMPLES = 64
TENT_X_SUBSAMPLES = 16


def support_radius(radius: float) -> int:
    """Half-size in pixels of the kernel array for a shape of circumradius |radius| (pixels):
    the tent of pixel n reaches the shape when |n| < |radius| + 1."""
    r = abs(float(radius))
    return 0 if r == 0.0 else int(math.ceil(r))


def _cover_half(r: float) -> int:
    """Half-size of the `coverage` array: the pixels the shape itself touches."""
    return 0 if r < 0.5 else int(math.ceil(r - 0.5))


def coverage(aperture: Aperture, radius: float) -> np.ndarray:
    """Area (pixels^2) of the shape of radius |radius| inside each pixel, float64 (2S+1, 2S+1),
    S = ceil(|radius| - 0.5) (0 below half a pixel): the pixels the shape touches.

    Pixel (i, j) spans [j-S-0.5, j-S+0.5] x [i-S-0.5, i-S+0.5] around the shape's centre. Each
    column is integrated with the midpoint rule over X_SUBSAMPLES vertical chords, each chord
    clipped to the pixel rows exactly, so the result is continuous in the radius. Unnormalized:
    it sums to the shape's area (relative error below 1e-4 for radii above 1 px).
    """
    r = abs(float(radius))
    s = _cover_half(r)
    n = 2 * s + 1
    if r == 0.0:
        out = np.zeros((n, n))
        return out
    # Sub-columns clipped to the shape's x-extent, each sampled at its clipped midpoint: exact
    # for straight edges between kinks (vertical edges included) and continuous in r.
    xmin, xmax = aperture.x_extent(r)
    cells = np.clip(np.arange(n * X_SUBSAMPLES + 1) / X_SUBSAMPLES - s - 0.5, xmin, xmax)
    width = np.diff(cells)
    lo, hi = aperture.chord(0.5 * (cells[1:] + cells[:-1]), r)
    on = width > 0  # sub-columns outside the shape: no chord (and no inf * 0)
    lo = np.where(on, lo, 0.0)
    hi = np.where(on, np.maximum(hi, lo), 0.0)
    # The chord [lo, hi] below pixel edge y_i has length clip(y_i, lo, hi) - lo, so pixel row i
    # gets H(y_{i+1}) - H(y_i), H(y) = sum over the column's sub-columns of width * clip(y, lo, hi)
    # = width * (lo + [lo < y] (y - lo) - [hi < y] (y - hi)). The sums over "v < y_i" come from one
    # bincount per column and a cumulative sum over the edges: O(n * X_SUBSAMPLES + n^2) work.
    column = np.repeat(np.arange(n), X_SUBSAMPLES)
    edges = np.arange(n + 1) - s - 0.5

    def below(v):  # per (column, edge i): sum of width and of width * v over sub-columns with v < y_i
        first = np.clip(np.floor(v + s + 0.5).astype(np.int64) + 1, 0, n + 1)  # first edge above v
        at = column * (n + 2) + first
        w_sum = np.bincount(at, width, n * (n + 2)).reshape(n, n + 2).cumsum(axis=1)[:, : n + 1]
        wv_sum = np.bincount(at, width * v, n * (n + 2)).reshape(n, n + 2).cumsum(axis=1)[:, : n + 1]
        return w_sum, wv_sum

    w_lo, wv_lo = below(lo)
    w_hi, wv_hi = below(hi)
    h = edges[None, :] * (w_lo - w_hi) - wv_lo + wv_hi  # H(y_i) less the constant sum of width * lo
    return np.diff(h, axis=1).T


def _tent_integral(t: np.ndarray) -> np.ndarray:
    """The integral of the tent max(0, 1 - |s|) from -inf to t: 0.5 (t + 1)^2 below 0 and
    1 - 0.5 (1 - t)^2 above, i.e. 0.5 + t - 0.5 t |t| (t clipped to [-1, 1])."""
    t = np.clip(t, -1.0, 1.0)
    return 0.5 + t - 0.5 * t * np.abs(t)


def _tent_moment_integral(t: np.ndarray) -> np.ndarray:
    """The integral of s * max(0, 1 - |s|) from -inf to t (0 again beyond 1: the tent is even)."""
    t = np.clip(t, -1.0, 1.0)
    return t * t * (0.5 - np.abs(t) / 3.0) - 1.0 / 6.0  # t^2/2 -+ t^3/3 - 1/6 on either side of 0


@lru_cache(maxsize=2)
def _tent_terms(aperture: Aperture, r: float):
    """The factors of the tent integrals over the shape of radius r > 0, per kernel offset
    (rows) and sub-column (columns): offsets o, t = o - y at the chords' ends (a at the top,
    b at the bottom), the exact integral along y and the midpoint rule along x, and the
    sub-columns' centres. Kept for the last two radii: a kernel and then its moments (the
    level scatter asks for both) share them."""
    s = support_radius(r)
    xmin, xmax = aperture.x_extent(r)
    m = max(256, int(math.ceil((xmax - xmin) * TENT_X_SUBSAMPLES)))  # at least 256: small shapes too
    edges = np.linspace(xmin, xmax, m + 1)
    x, width = 0.5 * (edges[1:] + edges[:-1]), np.diff(edges)
    lo, hi = aperture.chord(x, r)
    hi = np.maximum(hi, lo)
    offs = np.arange(-s, s + 1, dtype=np.float64)[:, None]
    a, b = offs - hi[None, :], offs - lo[None, :]  # t = offset - y over the chord
    along_y = _tent_integral(b) - _tent_integral(a)  # (2S+1, m)
    along_x = np.maximum(0.0, 1.0 - np.abs(offs - x[None, :])) * width[None, :]  # (2S+1, m)
    out = (offs, a, b, along_y, along_x, x)
    for arr in out:
        arr.setflags(write=False)
    return out


def tent_weights(aperture: Aperture, radius: float) -> np.ndarray:
    """K[i, j] = integral over the shape of radius |radius| of tent(j - S - x) tent(i - S - y),
    float64 (2S+1, 2S+1), S = support_radius, unnormalized (it sums to the shape's area). Along
    y each chord is integrated exactly (the tent's antiderivative); along x by the midpoint rule
    over TENT_X_SUBSAMPLES sub-columns per pixel of the shape's x-extent (at least 256), so it
    is continuous in r."""
    r = abs(float(radius))
    if r == 0.0:
        return np.ones((1, 1))
    offs, _, _, along_y, along_x, x = _tent_terms(aperture, r)
    return _tent_product(along_y, along_x, x, offs)


def _tent_product(left: np.ndarray, right: np.ndarray, x: np.ndarray, offs: np.ndarray) -> np.ndarray:
    """left @ right.T for (2S+1, m) factors whose `right` is 0 wherever its tent does not reach
    (|offs[o] - x_j| >= 1): each output column summed over the sub-columns its tent covers (about
    2 * TENT_X_SUBSAMPLES of the m), by numpy, not BLAS: a fixed summation order on every
    machine (BLAS picks its kernels by CPU), 40-80x fewer products, and no BLAS threads left
    spinning after the call (0.6-0.8 CPU s of a fresh process's 2048 px render went to them)."""
    o = offs[:, 0]
    lo = np.searchsorted(x, o - 1.0, side="right")
    hi = np.searchsorted(x, o + 1.0, side="left")
    out = np.empty((left.shape[0], right.shape[0]))
    for j, (a, b) in enumerate(zip(lo, hi)):
        np.sum(left[:, a:b] * right[j, a:b], axis=1, out=out[:, j])
    return out


@lru_cache(maxsize=512)
def _kernel_cached(aperture: Aperture, signed_radius: float) -> np.ndarray:
    w = tent_weights(aperture, signed_radius)
    k = (w / w.sum()).astype(np.float32)
    if signed_radius < 0:
        k = np.ascontiguousarray(k[::-1, ::-1])
    k.setflags(write=False)
    return k


def kernel(aperture: Aperture, signed_radius: float) -> np.ndarray:
    """Normalized float32 kernel (sums to 1) for a signed CoC radius in pixels (read-only array).

    The array is (2S+1, 2S+1) with S = support_radius; its centre is the point's own pixel. For a
    negative radius it is the point reflection of the positive one. Cached on the exact float.
    """
    r = float(signed_radius)
    if not math.isfinite(r):
        raise ValueError(f"signed_radius must be finite, got {signed_radius}")
    return _kernel_cached(aperture, r)


@lru_cache(maxsize=512)
def _moments_cached(aperture: Aperture, signed_radius: float) -> tuple[np.ndarray, np.ndarray]:
    r = abs(signed_radius)
    rr = r if r > 0.0 else 1.0
    offs, a, b, along_y, along_x, x = _tent_terms(aperture, rr)
    y_mom = (offs * along_y - (_tent_moment_integral(b) - _tent_moment_integral(a))) / rr  # y = offset - t
    total = float(np.sum(along_y.sum(axis=0) * along_x.sum(axis=0)))  # the kernel's sum, without the kernel
    mx = _tent_product(along_y, along_x * (x / rr)[None, :], x, offs) / total
    my = _tent_product(y_mom, along_x, x, offs) / total
    if r == 0.0:  # the identity: its one pixel carries the whole shape, whose centroid it holds
        mx, my = np.full((1, 1), mx.sum()), np.full((1, 1), my.sum())
    out = []
    for m in (mx, my):
        m = m.astype(np.float32)
        if signed_radius < 0:  # the kernel's reflection: the same aperture points, mirrored pixels
            m = np.ascontiguousarray(m[::-1, ::-1])
        m.setflags(write=False)
        out.append(m)
    return out[0], out[1]


def kernel_moments(aperture: Aperture, signed_radius: float) -> tuple[np.ndarray, np.ndarray]:
    """(Mx, My), float32 of the kernel's shape (read-only): the first moments of the aperture
    coordinate p = (x, y) / r (units of the radius; x right, y down, before the reflection of a
    negative radius) that each kernel pixel carries, with the kernel's normalization. So
    sum(Mx) is the shape's centroid x, and Mx / K the mean p_x of the aperture points whose
    light lands on that pixel (where a plain u / c is wrong within a pixel of the rim and at
    small radii, which the tent blurs). Cached on the exact float."""
    r = float(signed_radius)
    if not math.isfinite(r):
        raise ValueError(f"signed_radius must be finite, got {signed_radius}")
    return _moments_cached(aperture, r)
