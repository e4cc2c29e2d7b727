"""Array helpers for images: resampling and 8-bit quantisation (numpy + OpenCV, no colour
science; the transfer functions are in dofsynth.color)."""
from __future__ import annotations

import cv2
import numpy as np


def resize(img: np.ndarray, w: int, h: int, nearest: bool = False) -> np.ndarray:
    """`img` (H, W[, C]) resampled to (h, w[, C]), a new array of its dtype: INTER_NEAREST with
    `nearest`, INTER_AREA when shrinking (neither side grows), INTER_LINEAR otherwise."""
    sh, sw = img.shape[:2]
    if (sw, sh) == (w, h):
        return np.array(img, copy=True)
    if nearest:
        interp = cv2.INTER_NEAREST
    else:
        interp = cv2.INTER_AREA if (w <= sw and h <= sh) else cv2.INTER_LINEAR
    out = cv2.resize(np.ascontiguousarray(img), (int(w), int(h)), interpolation=interp)
    return out.reshape(int(h), int(w), *img.shape[2:])


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
