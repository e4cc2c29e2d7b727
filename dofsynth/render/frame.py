"""Frame helpers of the layered renderer: boxes of a frame read past its edges, broadcast maps
kept compact, blocks added where they fall inside a destination."""
from __future__ import annotations

import numpy as np


def is_one(alpha: np.ndarray) -> bool:
    """Whether an alpha map is 1 everywhere (a broadcast scalar is read once)."""
    if alpha.ndim == 2 and alpha.strides == (0, 0):  # a broadcast scalar
        return float(alpha.flat[0]) == 1.0
    return bool(np.all(alpha == 1.0))


def compact(m: np.ndarray) -> np.ndarray:
    """The smallest array that broadcasts back to `m`: a broadcast row or column stays one, and
    so does a map whose rows (or columns) are all equal, however it is stored."""
    if m.strides[0] == 0 or (m.shape[0] > 1 and np.array_equal(m, np.broadcast_to(m[:1], m.shape))):
        m = m[:1]
    if m.strides[1] == 0 or (m.shape[1] > 1 and np.array_equal(m, np.broadcast_to(m[:, :1], m.shape))):
        m = m[:, :1]
    return m


def grab(a: np.ndarray, y0: int, y1: int, x0: int, x1: int, edge: bool,
          out: np.ndarray | None = None) -> np.ndarray:
    """a[y0:y1, x0:x1] of a 2-D frame array (or (H, W, 3)) for a box that may leave the frame:
    outside it, the edge pixel (edge=True) or 0. A view when the box lies inside; with `out`
    (the box's shape, any strides) every value is written there instead and `out` returned."""
    H, W = a.shape[:2]
    cy0, cy1, cx0, cx1 = max(y0, 0), min(y1, H), max(x0, 0), min(x1, W)
    if out is None:
        if (cy0, cy1, cx0, cx1) == (y0, y1, x0, x1):
            return a[y0:y1, x0:x1]
        out = np.empty((y1 - y0, x1 - x0) + a.shape[2:], a.dtype)
    if cy1 <= cy0 or cx1 <= cx0:  # wholly outside the frame
        if edge:
            iy, ix = np.clip(np.arange(y0, y1), 0, H - 1), np.clip(np.arange(x0, x1), 0, W - 1)
            out[...] = a[iy[:, None], ix[None, :]]
        else:
            out[...] = 0.0
        return out
    t, l, h, w = cy0 - y0, cx0 - x0, cy1 - cy0, cx1 - cx0
    out[t : t + h, l : l + w] = a[cy0:cy1, cx0:cx1]
    if edge:  # columns first, then whole rows: the corners take the corner pixel
        out[t : t + h, :l] = out[t : t + h, l : l + 1]
        out[t : t + h, l + w :] = out[t : t + h, l + w - 1 : l + w]
        out[:t] = out[t : t + 1]
        out[t + h :] = out[t + h - 1 : t + h]
    else:
        out[t : t + h, :l] = 0.0
        out[t : t + h, l + w :] = 0.0
        out[:t] = 0.0
        out[t + h :] = 0.0
    return out


def add_clipped(dst: np.ndarray, y0: int, x0: int, block: np.ndarray) -> None:
    """dst[..., y0:, x0:] += block, for the part of the block that lies inside dst (over the
    last two axes; leading axes broadcast)."""
    H, W = dst.shape[-2:]
    h, w = block.shape[-2:]
    cy0, cx0, cy1, cx1 = max(y0, 0), max(x0, 0), min(y0 + h, H), min(x0 + w, W)
    if cy1 > cy0 and cx1 > cx0:
        dst[..., cy0:cy1, cx0:cx1] += block[..., cy0 - y0 : cy1 - y0, cx0 - x0 : cx1 - x0]
