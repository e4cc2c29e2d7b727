"""Drawing primitives shared by the QA pictures (contact sheets, stats charts, HTML pages):
measured text, the disparity colour map and its scale bar, the coverage overlay. Plain numpy
+ OpenCV (`cv2.putText`); images are RGB uint8."""
from __future__ import annotations

import cv2
import numpy as np

from dofsynth.image import to_rgb8, to_uint8
from dofsynth.io import swap_rb

FONT = cv2.FONT_HERSHEY_SIMPLEX
BG = (24, 24, 24)            # sheet background (RGB)
FG = (235, 235, 235)         # text
DIM = (150, 150, 150)        # secondary text, ticks
COLORMAP = cv2.COLORMAP_TURBO
FRONT_TINT = (255, 40, 40)   # red
MIDDLE_TINT = (40, 255, 40)  # green


# ---------------------------------------------------------------- text and small drawing helpers
def text_size(text: str, scale: float = 0.45, thickness: int = 1) -> tuple[int, int, int]:
    """(width, ascent, descent) in pixels of `text` drawn with `put_text`."""
    (w, h), base = cv2.getTextSize(text, FONT, scale, thickness)
    return w, h, base


def fit_text(text: str, width: int, scale: float = 0.45) -> str:
    """`text`, shortened with '...' until it fits `width` pixels."""
    if text_size(text, scale)[0] <= width:
        return text
    while text and text_size(text + "...", scale)[0] > width:
        text = text[:-1]
    return text + "..." if text else ""


def put_text(img: np.ndarray, text: str, x: int, y_top: int, color=FG, scale: float = 0.45,
             thickness: int = 1, max_width: int | None = None) -> int:
    """Draw `text` with its top-left corner at (x, y_top); returns the drawn width. Text is
    shortened to `max_width` pixels when given, so labels never run into their neighbours."""
    if max_width is not None:
        text = fit_text(text, max_width, scale)
    w, h, _ = text_size(text, scale, thickness)
    cv2.putText(img, text, (int(x), int(y_top + h)), FONT, scale, color, thickness, cv2.LINE_AA)
    return w


def colorize_disparity(disparity: np.ndarray) -> np.ndarray:
    """Disparity in [0, 1] (H, W) -> RGB uint8 through the colour map (0 = far, 1 = near)."""
    q = to_uint8(np.nan_to_num(disparity, nan=0.0))
    return np.ascontiguousarray(swap_rb(cv2.applyColorMap(q, COLORMAP)))


def coverage_overlay(aif: np.ndarray, cover: np.ndarray, outline: int = 1) -> np.ndarray:
    """The image dimmed, the front coverage tinted red and the middle one green (each by its
    alpha), with an outline at alpha 0.5. `aif` (H, W, 3) uint8 or float, `cover` (H, W, 2)."""
    base = to_rgb8(aif).astype(np.float32) * 0.55
    front = np.clip(cover[:, :, 0], 0, 1)[:, :, None]
    middle = np.clip(cover[:, :, 1], 0, 1)[:, :, None]
    out = base * (1 - 0.5 * middle) + 0.5 * middle * np.float32(MIDDLE_TINT)
    out = out * (1 - 0.5 * front) + 0.5 * front * np.float32(FRONT_TINT)
    out = np.clip(out + 0.5, 0, 255).astype(np.uint8)
    for a, colour in ((cover[:, :, 1], MIDDLE_TINT), (cover[:, :, 0], FRONT_TINT)):
        mask = (a >= 0.5).astype(np.uint8)
        contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        cv2.drawContours(out, contours, -1, colour, outline, cv2.LINE_8)
    return out


def scale_bar(height: int, width: int = 12) -> np.ndarray:
    """(height, width, 3): the colour map from 1 (top) to 0 (bottom)."""
    ramp = np.linspace(1.0, 0.0, height, dtype=np.float32)[:, None]
    return colorize_disparity(np.repeat(ramp, width, axis=1))
