"""Exact linear convolution of float32 channels with an aperture kernel, shared by every
blurred plane: `Convolver(signed_radius, aperture, h, w).add_into(tile, dst, oy, ox)`.

Small kernels (support radius <= SMALL_KERNEL) go through cv2.filter2D; larger ones through
float32 FFTs (scipy.fft, next_fast_len sizes), one channel and one tile at a time, taken
axis by axis: the real transform along rows runs only over the input rows that hold data
(once, even where overlap-save bands overlap) and its inverse only over the rows kept. Large
inputs run as overlap-save over full-width bands of rows (docs/rendering.md). The result
equals a float64 direct convolution to float32 rounding, tiled or not.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import scipy.fft as sfft

from dofsynth.optics.aperture import Aperture
from dofsynth.optics.kernel import kernel, support_radius
from dofsynth.render.frame import add_clipped

# Kernels with support radius up to this many pixels (11x11) go through cv2.filter2D (direct,
# 2-6x faster there, measured), larger ones via FFT (cv2 switches to its own slower DFT beyond).
SMALL_KERNEL = 5


def is_small(kh: int, kw: int) -> bool:
    """Whether a (kh, kw) kernel (its non-zero box) is convolved directly (cv2.filter2D)."""
    return max(kh, kw) <= 2 * SMALL_KERNEL + 1


def filtered(pad: np.ndarray, flipped: np.ndarray) -> np.ndarray:
    """The convolutions of a stack of blocks (C, hp, wp) by a kernel (given flipped, (eh + 1,
    ew + 1)) where every tap lies inside the block, (C, hp - eh, wp - ew), by one cv2.filter2D
    over the blocks stacked (the outputs kept read only their own block): a block holding its
    input with eh rows and ew columns of zeros on every side gives the input's full
    convolution. Small kernels only (cv2 turns to its DFT past 11 x 11); a 1 x 1 identity
    kernel returns `pad` itself."""
    eh, ew = flipped.shape[0] - 1, flipped.shape[1] - 1
    if not (eh or ew):  # a 1 x 1 kernel: the identity, or a scale (a moment kernel at radius 0)
        return pad if flipped[0, 0] == 1.0 else pad * flipped[0, 0]
    C, hp, wp = pad.shape
    ay, ax = eh // 2, ew // 2
    out = cv2.filter2D(pad.reshape(C * hp, wp), -1, flipped, anchor=(ax, ay),
                       borderType=cv2.BORDER_CONSTANT).reshape(pad.shape)
    return out[:, ay : ay + hp - eh, ax : ax + wp - ew]


def _kernel_spectrum(k: np.ndarray, n0: int, n1: int) -> np.ndarray:
    """rfft2 over an (n0, n1) grid of the kernel placed at the grid's top-left corner: rows
    first (only 2S+1 of them are non-zero), then columns (complex64)."""
    part = sfft.rfft(k, n=n1, axis=1)
    return sfft.fft(part, n=n0, axis=0)


@dataclass(frozen=True)
class Tiling:
    """How large FFT convolutions are cut: once the padded height exceeds `above`, overlap-save
    bands with an FFT height of next_fast_len(max(rows, s_factor * S)), each as wide as the
    input up to `wide` padded columns (wider inputs are also cut into column tiles of about
    wide / 2). The FFT's cost per pixel grows with its size (cache misses), least so along the
    contiguous rows: short full-width bands beat square tiles (docs/rendering.md). The result
    does not depend on the tiling beyond float32 rounding."""

    above: int = 1536
    rows: int = 768
    wide: int = 4700
    s_factor: int = 4


TILING = Tiling()


class Convolver:
    """Linear convolution of (h, w) float32 channels with one kernel, sharing its spectrum.

    The full convolution is (h + 2S, w + 2S): input pixel (i, j) spreads over output rows
    i .. i + 2S and columns j .. j + 2S (output (i + S, j + S) is its centre), so the input needs
    no zero margin. `add_into` adds the part of it that lands in a destination. Small kernels
    use cv2.filter2D, large ones float32 FFTs (next_fast_len sizes, one channel and one tile at a
    time) taken axis by axis: the real transform along rows runs only over the input rows that
    hold data (once, even where bands overlap) and its inverse only over the rows kept.

    Only the kernel's non-zero bounding box is convolved (same result, placed the same way):
    a polygon's kernel has empty rows, a sub-aperture cell's fills a small part of its
    (2S+1)^2 array, and then takes the direct path or smaller FFTs."""

    def __init__(self, signed_radius: float, aperture: Aperture, h: int, w: int, tiling: Tiling = TILING,
                 k: np.ndarray | None = None):
        self.s = support_radius(signed_radius)
        k = kernel(aperture, signed_radius) if k is None else k  # k: another kernel of that size
        self.k = k
        box = trim_box(k)
        self.ky0, self.kx0 = box[:2]  # the kernel used starts there in the (2S+1)^2 array
        k = trimmed(k, box)
        self.used = k
        self.eh, self.ew = k.shape[0] - 1, k.shape[1] - 1  # the full convolution's growth per axis
        self.h, self.w = h, w
        self.direct = is_small(*k.shape)
        self.ty, self.tx = h, w
        if self.direct:
            self.flipped = np.ascontiguousarray(k[::-1, ::-1])
        else:
            if w + self.ew > tiling.wide:
                self.tx = sfft.next_fast_len(max(tiling.wide // 2, tiling.s_factor * (self.ew // 2)),
                                             real=True) - self.ew
            if h + self.eh > tiling.above:
                self.ty = sfft.next_fast_len(max(tiling.rows, tiling.s_factor * (self.eh // 2)),
                                             real=True) - self.eh
            self.n0 = sfft.next_fast_len(self.ty + self.eh, real=True)
            self.n1 = sfft.next_fast_len(self.tx + self.ew, real=True)
            self.spec = _kernel_spectrum(k, self.n0, self.n1)

    def _direct(self, tile, i0: int, i1: int, j0: int, j1: int) -> np.ndarray:
        """Full convolution of input[i0:i1, j0:j1] by cv2.filter2D (small kernels); the block
        is written straight into the middle of its zero-padded buffer."""
        eh, ew = self.eh, self.ew
        pad = np.zeros((1, i1 - i0 + 2 * eh, j1 - j0 + 2 * ew), np.float32)
        tile(i0, i1, j0, j1, pad[0, eh : eh + i1 - i0, ew : ew + j1 - j0])
        return filtered(pad, self.flipped)[0]

    def add_into(self, tile, dst: np.ndarray, oy: int, ox: int) -> None:
        """dst[oy + p, ox + q] += full[p, q] where it lies inside dst; the input comes from
        `tile(y0, y1, x0, x1, out)`, which writes input[y0:y1, x0:x1] into `out` (a float32
        view of that shape: the FFT's padded buffer, so the input is copied once). Overlap-save:
        only the part of `full` inside dst is computed, in output tiles of (ty, tx), each from
        the input reaching it."""
        H, W = dst.shape
        oy, ox = oy + self.ky0, ox + self.kx0
        eh, ew = self.eh, self.ew
        rows = list(_spans(max(-oy, 0), min(H - oy, self.h + eh), self.h, eh, self.ty))
        for q0, q1, j0, j1 in _spans(max(-ox, 0), min(W - ox, self.w + ew), self.w, ew, self.tx):
            if not self.direct:
                self._add_bands(tile, dst, oy, ox + q0, rows, q1 - q0, q0 - j0, j0, j1)
                continue
            for p0, p1, i0, i1 in rows:
                block = self._direct(tile, i0, i1, j0, j1)
                dst[oy + p0 : oy + p1, ox + q0 : ox + q1] += block[p0 - i0 : p1 - i0, q0 - j0 : q1 - j0]

    def add_stack_into(self, src: np.ndarray, dst: np.ndarray, oy: int, ox: int) -> None:
        """`add_into` for each channel of src (C, h, w) into dst (C, H, W). Small kernels: one
        cv2.filter2D over the channels stacked (`filtered`), the same values as channel by
        channel."""
        if not self.direct:
            for c in range(src.shape[0]):
                self.add_into(copy_tile(src[c]), dst[c], oy, ox)
            return
        C, h, w = src.shape
        eh, ew = self.eh, self.ew
        pad = np.zeros((C, h + 2 * eh, w + 2 * ew), np.float32)
        pad[:, eh : eh + h, ew : ew + w] = src
        add_clipped(dst, oy + self.ky0, ox + self.kx0, filtered(pad, self.flipped))

    def _add_bands(self, tile, dst, oy, ox, rows, width, skip, j0, j1) -> None:
        """One column tile by FFT: for each band (p0, p1, i0, i1) of `rows`, output rows p0 .. p1
        (columns skip .. skip + width of the block) from input rows i0 .. i1, columns j0 .. j1.
        Rows first: each input row's real transform is taken once (bands share the kernel's
        height less one rows), and the inverse one only for the rows kept."""
        n0, n1, eh = self.n0, self.n1, self.eh
        real = np.empty((n0, n1), np.float32)  # a band's new input rows, zero-padded to n1
        half = np.empty((n0, n1 // 2 + 1), np.complex64)  # the band's row spectra, zero-padded to n0
        shared, shared0 = half[:0], 0  # row spectra the next band reuses, from input row shared0
        for p0, p1, i0, i1 in rows:
            lo = max(i0, shared0 + shared.shape[0])  # rows before lo were transformed already
            if lo > i0:
                half[: lo - i0] = shared[i0 - shared0 :]
            if i1 > lo:
                tile(lo, i1, j0, j1, real[: i1 - lo, : j1 - j0])
                real[: i1 - lo, j1 - j0 :] = 0.0
                half[lo - i0 : i1 - i0] = sfft.rfft(real[: i1 - lo], axis=1)
            half[i1 - i0 :] = 0.0
            shared0 = max(i0, p1 - eh)  # the next band's input starts at its p0 - eh = p1 - eh
            shared = half[shared0 - i0 : i1 - i0].copy()
            spec = sfft.fft(half, axis=0, overwrite_x=True)
            spec *= self.spec
            spec = sfft.ifft(spec, axis=0, overwrite_x=True)
            out = sfft.irfft(spec[p0 - i0 : p1 - i0], n=n1, axis=1)
            dst[oy + p0 : oy + p1, ox : ox + width] += out[:, skip : skip + width]


def trim_box(k: np.ndarray) -> tuple[int, int, int, int]:
    """(y0, x0, y1, x1): the bounding box of a kernel's non-zero taps (all of it when none)."""
    if not k.any():
        return 0, 0, k.shape[0], k.shape[1]
    rows, cols = np.flatnonzero(k.any(axis=1)), np.flatnonzero(k.any(axis=0))
    return int(rows[0]), int(cols[0]), int(rows[-1]) + 1, int(cols[-1]) + 1


def trimmed(k: np.ndarray, box: tuple[int, int, int, int] | None = None) -> np.ndarray:
    """The kernel cut to `box` (default its non-zero bounding box, `trim_box`)."""
    y0, x0, y1, x1 = trim_box(k) if box is None else box
    return k[y0:y1, x0:x1]


STACK_FFT_MAX = 2048 * 2048  # padded FFT area up to which `convolve_stack` is used (memory)
STACK_GROUP_BYTES = 2 << 20  # `convolve_stack` inverts up to 4 pairs per call within this many bytes of spectra


def stack_fits(h: int, w: int, kh: int, kw: int) -> bool:
    """Whether `convolve_stack` takes inputs (h, w) and kernels (kh, kw) in one FFT."""
    return (h + kh - 1) * (w + kw - 1) <= STACK_FFT_MAX


def convolve_stack(x: np.ndarray, kernels: np.ndarray, pairs, valid: bool = False, window=None) -> np.ndarray:
    """Linear convolutions of channels of x (C, h, w) with kernels (K, kh, kw), float32:
    pairs[i] = (kernel index, channel index). The full convolutions (len(pairs), h + kh - 1,
    w + kw - 1); with `window` = (y0, y1, x0, x1) only those rows and columns of them (inside
    the full convolution); with `valid` the outputs that every kernel tap reaches inside x
    ((len(pairs), h - kh + 1, w - kw + 1), the window (kh - 1, h, kw - 1, w)). The circular
    FFT is only as large as the window needs (its outputs must not wrap onto the window:
    n >= max(input, full - y0, y1) per axis), so a window costs less than the full result.
    For a few small channels, where the per-channel `Convolver` spends most of its time around
    the transforms. The channels' transforms in one call; the kernels' in one call up to
    2 STACK_GROUP_BYTES of spectra, else one at a time; the pairs' products and inverses up to
    4 per call within STACK_GROUP_BYTES. All at once is fastest while the arrays stay in the
    cache, one at a time beyond (measured from 120 x 192 to 432 x 288: 24 inverses at once took
    2.5x as long as one by one and 4 at a time 8-16 % less; 13 kernels at once half the time
    up to 225 x 320, 1.2x at 432 x 288). Equal to direct convolution to float32 rounding
    (tested)."""
    h, w = x.shape[1:]
    kh, kw = kernels.shape[1:]
    if valid:
        window = (kh - 1, h, kw - 1, w)
    y0, y1, x0, x1 = (0, h + kh - 1, 0, w + kw - 1) if window is None else window
    if is_small(kh, kw):  # direct, as `Convolver` takes them
        return _direct_stack(x, kernels, pairs, (y0, y1, x0, x1))
    n0 = sfft.next_fast_len(max(h, h + kh - 1 - y0, y1), real=True)
    n1 = sfft.next_fast_len(max(w, w + kw - 1 - x0, x1), real=True)
    spec = sfft.rfft2(x, s=(n0, n1))
    if len(kernels) * spec[0].nbytes <= 2 * STACK_GROUP_BYTES:  # = rfft2, without the zero rows' transforms
        kspec = sfft.fft(sfft.rfft(kernels, n=n1, axis=-1), n=n0, axis=-2)
    else:  # large: one at a time (the batch leaves the cache)
        kspec = [sfft.fft(sfft.rfft(k, n=n1, axis=-1), n=n0, axis=-2) for k in kernels]
    out = np.empty((len(pairs), y1 - y0, x1 - x0), np.float32)
    group = int(np.clip(STACK_GROUP_BYTES // max(spec[0].nbytes, 1), 1, 4))  # pairs per inverse call
    prod = np.empty((group,) + spec.shape[1:], spec.dtype)
    for g0 in range(0, len(pairs), group):  # a few pairs at a time: their products and inverses stay in cache
        part = pairs[g0 : g0 + group]
        for i, (k, c) in enumerate(part):
            np.multiply(kspec[k], spec[c], out=prod[i])
        out[g0 : g0 + len(part)] = sfft.irfft2(prod[: len(part)], s=(n0, n1), overwrite_x=True)[:, y0:y1, x0:x1]
    return out


def _direct_stack(x: np.ndarray, kernels: np.ndarray, pairs, window) -> np.ndarray:
    """`convolve_stack` of small kernels by cv2.filter2D: each kernel once over the channels
    it takes, stacked (`filtered`), over the input rows and columns the window reads."""
    h, w = x.shape[1:]
    eh, ew = kernels.shape[1] - 1, kernels.shape[2] - 1
    y0, y1, x0, x1 = window
    # full output (p, q) reads input rows p - eh .. p, columns q - ew .. q (zeros past x): the
    # window's rows y0 - eh .. y1 - 1 and columns x0 - ew .. x1 - 1, placed in a zeroed block
    channels = list(dict.fromkeys(c for _, c in pairs))
    block = np.zeros((len(channels), y1 - y0 + eh, x1 - x0 + ew), np.float32)
    r0, r1, c0, c1 = max(y0 - eh, 0), min(y1, h), max(x0 - ew, 0), min(x1, w)
    if r1 > r0 and c1 > c0:
        block[:, r0 - y0 + eh : r1 - y0 + eh, c0 - x0 + ew : c1 - x0 + ew] = x[channels, r0:r1, c0:c1]
    out = np.empty((len(pairs), y1 - y0, x1 - x0), np.float32)
    for k in dict.fromkeys(k for k, _ in pairs):
        at = [i for i, (kk, _) in enumerate(pairs) if kk == k]
        rows = [channels.index(pairs[i][1]) for i in at]
        src = block if rows == list(range(len(channels))) else block[rows]
        out[at] = filtered(src, np.ascontiguousarray(kernels[k, ::-1, ::-1]))
    return out


def copy_tile(a: np.ndarray):
    """The `_Conv.add_into` tile callback that reads the input from array `a` (any strides)."""
    return lambda y0, y1, x0, x1, out: np.copyto(out, a[y0:y1, x0:x1])


def convolve(x: np.ndarray, signed_radius: float, aperture: Aperture) -> np.ndarray:
    """Convolve a (C, h, w) float32 stack with the kernel of `signed_radius` pixels.

    The result has x's shape and positions. Values within S = support_radius of the border are
    correct only if x holds zeros (or the wanted extension) in that margin: the caller pads.
    """
    s = support_radius(signed_radius)
    c, h, w = x.shape
    conv = Convolver(signed_radius, aperture, h, w)
    out = np.zeros((c, h, w), np.float32)
    for i in range(c):
        conv.add_into(copy_tile(x[i]), out[i], -s, -s)
    return out


def _spans(lo: int, hi: int, n: int, s2: int, step: int):
    """Overlap-save along one axis: output ranges [p0, p1) of a full convolution (length
    n + s2, s2 = the kernel's length less one) covering [lo, hi) in steps of `step`, each with
    the input range [i0, i1) that reaches it (input i lands on outputs i .. i + s2). step >= n:
    one span, all input."""
    if hi <= lo:
        return
    if step >= n:
        yield lo, hi, 0, n
        return
    for p0 in range(lo, hi, step):
        p1 = min(p0 + step, hi)
        i0, i1 = max(p0 - s2, 0), min(p1, n)
        if i1 > i0:
            yield p0, p1, i0, i1
