"""Colour transfer functions and the highlight boost.

All images in files are sRGB-encoded; every blur and composite happens in linear light
(float32). Functions here are pure and vectorised over any array shape.
"""
from __future__ import annotations

import numpy as np


def srgb_to_linear(x: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1 sRGB decoding of values in [0, 1] (float32 out)."""
    x = np.asarray(x, dtype=np.float32)
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4).astype(np.float32)


def linear_to_srgb(x: np.ndarray) -> np.ndarray:
    """sRGB encoding of linear values; input is clipped to [0, 1] first (float32 out)."""
    x = np.clip(np.asarray(x, dtype=np.float32), 0.0, 1.0)
    return np.where(x <= 0.0031308, x * 12.92, 1.055 * x ** (1 / 2.4) - 0.055).astype(np.float32)


def to_uint8(srgb: np.ndarray) -> np.ndarray:
    """Quantise sRGB-encoded values in [0, 1] to uint8 with round-half-up."""
    return np.floor(np.clip(srgb, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def highlight_boost(
    linear: np.ndarray, threshold: float = 0.9, gain: float = 4.0, power: float = 2.0
) -> np.ndarray:
    """Turn near-white pixels into brighter-than-white light before blurring.

    With `m = max(R, G, B)` of the *sRGB-encoded* pixel and `t = threshold`, every channel of
    the linear pixel is multiplied by `1 + gain * s(m) ** power`, where
    `s(m) = clip((m - t) / (1 - t), 0, 1)`. Pixels darker than `t` are unchanged; a pure white
    pixel becomes `1 + gain` times brighter, so after blurring a small highlight still
    saturates and spreads into a visible bokeh disc. The boost is continuous in the pixel value.
    """
    if not 0.0 <= threshold < 1.0:
        raise ValueError(f"highlight threshold must be in [0, 1), got {threshold}")
    if gain < 0 or power <= 0:
        raise ValueError(f"highlight gain must be >= 0 and power > 0, got {gain}, {power}")
    linear = np.asarray(linear, dtype=np.float32)
    m = linear_to_srgb(linear.max(axis=-1, keepdims=True))
    s = np.clip((m - threshold) / (1.0 - threshold), 0.0, 1.0)
    return (linear * (1.0 + gain * s**power)).astype(np.float32)
