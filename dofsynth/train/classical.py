"""The classical renderer as the networks see it: the evaluation's baseline and the hybrid
model's input (dofsynth.train.models.HybridNet).

One plane, alpha 1, the given (possibly wrong) disparity map, rendered as a record's targets
were (dofsynth.render.look.render_photo with the record's Look: method and options, highlight
boost and inverse, chromatic scales, linear light or the naive baseline) through the record's
aperture; images are sRGB-encoded in [0, 1], (H, W, 3) float32.
"""
from __future__ import annotations

import json

import cv2
import numpy as np

from dofsynth.color import linear_to_srgb, srgb_to_linear
from dofsynth.io import unit_float
from dofsynth.optics.aperture import aperture_from_dict
from dofsynth.render.look import Look, render_photo


def look_of(record: dict) -> str:
    """What `classical_render` needs of a record (its aperture and options), as JSON text."""
    return json.dumps({"aperture": record["aperture"], "options": record.get("options", {})}, sort_keys=True)


# The look of a photo at inference (no record to take it from): a disc aperture, the default options.
PHOTO_LOOK = {"aperture": {"kind": "disk"}}


def classical_render(image: np.ndarray, disparity: np.ndarray, focus: float, max_coc: float,
                     record: dict, color: str = "srgb") -> np.ndarray:
    """The single-image classical render of `image` with the look of `record` (a sample record,
    `json.loads(look_of(record))` or PHOTO_LOOK); image and result in `color`: "srgb"
    (sRGB-encoded) or "linear"."""
    return _renders(image, [disparity], focus, max_coc, record, color)[0]


def _renders(image, maps, focus, max_coc, record, color) -> list[np.ndarray]:
    """`classical_render` of one image from each disparity of `maps`, the image decoded to
    linear light once."""
    image = np.asarray(image, np.float32)
    linear = srgb_to_linear(image) if color == "srgb" else image
    aperture, look = aperture_from_dict(record["aperture"]), Look.from_dict(record.get("options", {}))
    outs = [render_photo(linear, np.asarray(d, np.float32), focus, max_coc, aperture, look) for d in maps]
    return [linear_to_srgb(out) for out in outs] if color == "srgb" else outs


def near_shifted(disparity: np.ndarray, radius: int) -> tuple[np.ndarray, np.ndarray]:
    """The disparity (H, W) with its near regions (1 = nearest) grown and shrunk by `radius` px:
    its grey dilation and erosion by the disc of the pixels within `radius` (outside the frame
    counts as nothing)."""
    yy, xx = np.mgrid[-radius : radius + 1, -radius : radius + 1]
    disc = (yy**2 + xx**2 <= radius**2).astype(np.uint8)
    d = np.asarray(disparity, np.float32)
    return cv2.dilate(d, disc), cv2.erode(d, disc)


def classical_stack(image: np.ndarray, disparity: np.ndarray, focus: float, max_coc: float, record: dict,
                    color: str = "srgb", near_shift: int = 0) -> np.ndarray:
    """The hybrid model's classical input, (H, W, 3) or with `near_shift` > 0 px (H, W, 9): the
    classical render from `disparity`, then from it with its near regions grown and shrunk by
    that many px (`near_shifted`), where a depth estimate's edges are often displaced to; the
    arguments as `classical_render`'s."""
    if near_shift <= 0:
        return classical_render(image, disparity, focus, max_coc, record, color)
    maps = [disparity, *near_shifted(disparity, near_shift)]
    return np.concatenate(_renders(image, maps, focus, max_coc, record, color), axis=2)


def classical_input(item: dict, color: str, near_shift: int = 0) -> np.ndarray:
    """The hybrid model's input for a decoded training crop (dofsynth.train.data.decode_crop: its
    image codes, corrupted disparity, focus, max_coc and look): `classical_stack` from that
    disparity, in the networks' colour space ([data] color: "srgb" or "linear"; the codes are
    decoded to linear light once, and a linear result is not encoded to sRGB and back)."""
    image = unit_float(item["image"], item["key"])
    return classical_stack(srgb_to_linear(image) if color == "linear" else image, item["disparity"], item["focus"],
                           item["max_coc"], json.loads(item["look"]), color, near_shift)
