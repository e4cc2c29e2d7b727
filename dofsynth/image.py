"""Array helpers for images: resampling and 8-bit quantisation (numpy + OpenCV, no colour
science; the transfer functions are in dofsynth.color)."""
from __future__ import annotations

import cv2
import numpy as np


def resize(img: np.ndarray, w: int, h: int, nearest: bool = False, out: np.ndarray | None = None) -> np.ndarray:
    """`img` (H, W[, C]) resampled to (h, w[, C]), a new array of its dtype (or written into
    `out`, which may be a view of a larger array): INTER_NEAREST with `nearest`, INTER_AREA when
    shrinking (neither side grows), INTER_LINEAR otherwise."""
    sh, sw = img.shape[:2]
    if (sw, sh) == (w, h):
        if out is None:
            return np.array(img, copy=True)
        out[...] = img
        return out
    if nearest:
        interp = cv2.INTER_NEAREST
    else:
        interp = cv2.INTER_AREA if (w <= sw and h <= sh) else cv2.INTER_LINEAR
    # a window of a larger image is read where it lies (OpenCV copies only layouts it cannot
    # take as they are, such as a flipped view)
    res = cv2.resize(img, (int(w), int(h)), dst=out, interpolation=interp)
    if out is None:
        return res.reshape(int(h), int(w), *img.shape[2:])
    if res is not out:  # (OpenCV made its own array: the view did not suit it)
        out[...] = res.reshape(out.shape)
    return out


def premultiply(rgb: np.ndarray, alpha: np.ndarray, box) -> np.ndarray:
    """(h, w, 4) float32 of the (x, y, w, h) `box` of straight colour `rgb` (H, W, 3) and
    `alpha` (H, W): colour x alpha, then alpha."""
    x, y, w, h = (int(v) for v in box)
    a = alpha[y:y + h, x:x + w, None]
    return np.concatenate([rgb[y:y + h, x:x + w] * a, a], axis=2, dtype=np.float32)


def halved_size(w: int, h: int) -> tuple[int, int]:
    """The (w, h) of `area_halve` of a (w, h) image: each side halved, rounded down, >= 1."""
    return max(1, w // 2), max(1, h // 2)


def area_halve(img: np.ndarray) -> np.ndarray:
    """`img` (H, W, C) area-resampled to `halved_size` (a new float32 array): one level of the
    pyramid that small placements are resampled from."""
    w, h = halved_size(img.shape[1], img.shape[0])
    out = cv2.resize(np.ascontiguousarray(img, dtype=np.float32), (w, h), interpolation=cv2.INTER_AREA)
    return out.reshape(h, w, *img.shape[2:])


def pyramid_level(size: tuple[int, int], target: tuple[int, int]) -> int:
    """The most halvings (`halved_size`) of a (w, h) `size` that keep it at least `target`
    (w, h) on both sides: the level to resample a shrinking image from (0 when it grows)."""
    level, (w, h) = 0, size
    while True:
        nw, nh = halved_size(w, h)
        if (nw, nh) == (w, h) or nw < target[0] or nh < target[1]:
            return level
        level, w, h = level + 1, nw, nh


def to_uint8(x: np.ndarray) -> np.ndarray:
    """Values in [0, 1] (clipped) to uint8 codes with round-half-up: floor(x * 255 + 0.5)."""
    return np.floor(np.clip(x, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def to_rgb8(img: np.ndarray) -> np.ndarray:
    """An image for display: (H, W[, C]) uint8 kept or [0, 1] floats quantised, grey
    replicated, alpha dropped -> (H, W, 3) uint8, contiguous."""
    img = np.asarray(img)
    if img.dtype != np.uint8:
        img = to_uint8(img)
    if img.ndim == 2:
        img = img[:, :, None]
    if img.shape[2] == 1:
        img = np.repeat(img, 3, axis=2)
    return np.ascontiguousarray(img[:, :, :3])
