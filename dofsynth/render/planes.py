"""The layered scene as the renderer sees it: planes listed back to front.

Each plane holds linear-light colour `rgb` (H, W, 3) float32 (straight, not premultiplied),
coverage `alpha` (H, W) in [0, 1] and normalized `disparity` in [0, 1] (1 = nearest): either
a float (a plane of constant disparity) or an (H, W) map.

`box` (optional, (y0, y1, x0, x1)): the plane's alpha is 0 outside rows y0:y1 and columns
x0:x1. The layered renderer then reads colour and alpha only inside it (no search for the
alpha's bounding box, validation of rgb and alpha only there); `compose.scene_layers` sets it
to the tight box of alpha > 0. None: the whole frame is looked at.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dofsynth.optics.coc import MAX_COC_PER_SIDE


@dataclass(frozen=True)
class Plane:
    rgb: np.ndarray
    alpha: np.ndarray
    disparity: np.ndarray | float
    box: tuple[int, int, int, int] | None = None

    @property
    def shape(self) -> tuple[int, int]:
        return self.rgb.shape[:2]

    def constant_disparity(self) -> float | None:
        """The plane's disparity if it is the same everywhere, else None."""
        d = self.disparity
        if np.isscalar(d) or np.ndim(d) == 0:
            return float(d)
        lo, hi = _min_max(np.asarray(d))
        return lo if lo == hi else None

    def disparity_map(self) -> np.ndarray:
        d = self.disparity
        if np.ndim(d) == 0:
            return np.full(self.shape, float(d), dtype=np.float32)
        return np.asarray(d, dtype=np.float32)


def alpha_box(alpha: np.ndarray) -> tuple[int, int, int, int] | None:
    """(y0, y1, x0, x1): the bounding box of alpha > 0 (a `Plane.box`), or None when alpha is
    0 everywhere."""
    on = np.asarray(alpha) > 0
    rows = np.flatnonzero(on.any(axis=1))
    if rows.size == 0:
        return None
    cols = np.flatnonzero(on[rows[0] : rows[-1] + 1].any(axis=0))
    return int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1


_BLOCK_BYTES = 1 << 20  # _min_max reads this much at a time: its second pass finds it in cache


def _min_max(arr: np.ndarray) -> tuple[float, float]:
    """(min, max) of an array (NaN propagates), (0, 0) when empty. A broadcast axis is read
    once, and a large array in row blocks: min and max of each block, so that the frame goes
    through memory once (at 4096 px a whole-frame min then max read 192 MiB twice)."""
    if arr.ndim and arr.size:
        arr = arr[tuple(slice(0, 1) if st == 0 else slice(None) for st in arr.strides)]
    if not arr.size:
        return 0.0, 0.0
    if arr.ndim < 2 or arr.nbytes <= _BLOCK_BYTES:
        return float(np.min(arr)), float(np.max(arr))
    step = max(_BLOCK_BYTES // (arr[0].size * arr.itemsize), 1)
    lo, hi = [], []
    for r in range(0, arr.shape[0], step):
        block = arr[r : r + step]
        lo.append(np.min(block))
        hi.append(np.max(block))
    return float(np.min(lo)), float(np.max(hi))


def _range(name: str, arr: np.ndarray) -> tuple[float, float]:
    """(min, max) of an array, refusing NaN and inf: NaN propagates through min, inf shows in
    min or max."""
    lo, hi = _min_max(arr)
    if not (np.isfinite(lo) and np.isfinite(hi)):
        raise ValueError(f"{name} contains NaN or inf")
    return lo, hi


def validate_planes(planes, focus: float, max_coc: float, use_boxes: bool = True, values: bool = True) -> None:
    """Refuse bad renderer input with a message that names the argument. A plane's `box` is
    checked against the frame; with `use_boxes` its rgb and alpha are checked only inside it
    (what the layered renderer reads), else everywhere. `values=False` leaves out the pass over
    the arrays' values (finite, in range): for planes already checked so (shapes, boxes and the
    scalars are always checked)."""
    planes = list(planes)
    if not planes:
        raise ValueError("planes: need at least one plane")
    if not np.isfinite(focus) or not 0.0 <= focus <= 1.0:
        raise ValueError(f"focus must be a disparity in [0, 1], got {focus}")
    if not np.isfinite(max_coc) or max_coc < 0:
        raise ValueError(f"max_coc must be a finite radius in pixels >= 0, got {max_coc}")
    shape = None
    for i, p in enumerate(planes):
        if i == 0 and np.ndim(p.rgb) == 3 and max_coc > MAX_COC_PER_SIDE * max(np.shape(p.rgb)[:2]):
            side = max(np.shape(p.rgb)[:2])
            raise ValueError(f"max_coc {max_coc:g} px is more than {MAX_COC_PER_SIDE} x the image's long side "
                             f"({side} px): no lens blurs that much, and its kernel would not fit in memory")
        rgb, alpha = np.asarray(p.rgb), np.asarray(p.alpha)
        if rgb.ndim != 3 or rgb.shape[2] != 3:
            raise ValueError(f"planes[{i}].rgb must be (H, W, 3), got shape {rgb.shape}")
        shape = shape or rgb.shape[:2]
        if rgb.shape[:2] != shape:
            raise ValueError(f"planes[{i}].rgb has shape {rgb.shape[:2]}, planes[0] has {shape}")
        if alpha.shape != shape:
            raise ValueError(f"planes[{i}].alpha must be {shape}, got shape {alpha.shape}")
        d = np.asarray(p.disparity)
        if d.ndim != 0 and d.shape != shape:
            raise ValueError(f"planes[{i}].disparity must be a float or {shape}, got shape {d.shape}")
        inside = (slice(None), slice(None))
        box = p.box
        if box is not None:
            if (len(box) != 4 or not all(isinstance(v, (int, np.integer)) for v in box)
                    or not (0 <= box[0] <= box[1] <= shape[0] and 0 <= box[2] <= box[3] <= shape[1])):
                raise ValueError(f"planes[{i}].box must be (y0, y1, x0, x1) inside the {shape} frame, got {box}")
            if use_boxes:
                inside = (slice(int(box[0]), int(box[1])), slice(int(box[2]), int(box[3])))
        if not values:
            continue
        (rgb_lo, _), (a_lo, a_hi), (d_lo, d_hi) = (_range(f"planes[{i}].{name}", arr) for name, arr in
                                                   (("rgb", rgb[inside]), ("alpha", alpha[inside]), ("disparity", d)))
        if a_lo < 0 or a_hi > 1:
            raise ValueError(f"planes[{i}].alpha must lie in [0, 1], got [{a_lo}, {a_hi}]")
        if d_lo < 0 or d_hi > 1:
            raise ValueError(f"planes[{i}].disparity must lie in [0, 1], got [{d_lo}, {d_hi}]")
        if rgb_lo < 0:
            raise ValueError(f"planes[{i}].rgb must be linear light >= 0, got min {rgb_lo}")


def background_disparity(mode: str, b0: float, b1: float, direction: str | None, h: int, w: int) -> np.ndarray:
    """(H, W) float32 disparity of the background. "flat": b0 everywhere (0 in sampled scenes);
    "ramp" + "horizontal": b0 at the left pixel column, linear to b1 at the right column;
    "ramp" + "vertical": b0 at the bottom pixel row, linear to b1 at the top row. (A ramp of
    h = 1 or w = 1 is its row or column: what a broadcast plane holds.)"""
    if mode == "flat":
        return np.full((h, w), b0, dtype=np.float32)
    if mode != "ramp":
        raise ValueError(f"background mode must be 'flat' or 'ramp', got {mode!r}")
    if direction == "horizontal":
        t = np.linspace(0.0, 1.0, w) if w > 1 else np.zeros(1)
        row = b0 + (b1 - b0) * t
        return np.ascontiguousarray(np.broadcast_to(row[None, :], (h, w)), dtype=np.float32)
    if direction == "vertical":
        t = np.linspace(1.0, 0.0, h) if h > 1 else np.zeros(1)  # 1 at the top row, 0 at the bottom
        col = b0 + (b1 - b0) * t
        return np.ascontiguousarray(np.broadcast_to(col[:, None], (h, w)), dtype=np.float32)
    raise ValueError(f"ramp direction must be 'horizontal' or 'vertical', got {direction!r}")
