"""The codecs of a sample's members, with the fixed settings that make their bytes: 8-bit sRGB
PNG images (with an sRGB chunk), the cover PNG, and the float32 EXR maps (depth, CoC, layers).

Linear light goes to 8-bit sRGB with `color.linear_to_srgb8` (exact round-half-up of the sRGB
formula, table-driven); values in [0, 1] (cover) with `to_uint8`'s round-half-up. The image
members carry a PNG sRGB chunk (rendering intent perceptual); cover does not (its codes are
coverage, not colour). Which member uses which codec: the member table, dofsynth.record.MEMBERS.
"""
from __future__ import annotations

import struct
import zlib

import cv2
import numpy as np

from dofsynth.color import linear_to_srgb8
from dofsynth.image import to_uint8
from dofsynth.io import DEPTH_CHANNELS, PngSettings, decode_exr, encode_exr, encode_png_rgb
from dofsynth.optics.coc import coc_radius

SCHEMA_VERSION = 6  # 2: assets' colour; objects' anchored, visible and rejected;
#                    3: depth.exr channel "disparity" (was "Z") with attributes; sRGB chunks;
#                    4: every field one JSON type in every record (record.schema.json): anchored,
#                       rejected and excluded joined strings, a flat background's direction "none";
#                       dual-pixel views add up to the target, which no longer changes with them;
#                    5: targets blur what the photo holds past the frame edge: background margin, real
#                    6: assets' matte: a photo's near-opaque matte loads as opaque (assets.opaque_from)
# zlib settings of the PNG members, chosen by measurement at 1024 px (docs/rendering.md):
# - images (aif, dof): level 1, one fixed Paeth row filter, Huffman-only coding. libpng no longer
#   tries all five filters per row, and Paeth residuals of photos have few long matches, so
#   Huffman coding alone is within 1.5% of the size of the old adaptive/Z_RLE setting at 0.6x
#   its time.
# - cover (mostly flat alpha): level 1, fixed Up filter, Z_RLE: the same size as before, 3x faster.
# The bytes depend on these settings: changing them changes every shard. Either encoder
# (dofsynth.io.png_backend) writes the same bytes.
PNG_SETTINGS = PngSettings(level=1, strategy="huffman", filter="paeth")
COVER_PNG_SETTINGS = PngSettings(level=1, strategy="rle", filter="up")

DEPTH_CHANNEL = DEPTH_CHANNELS[0]  # "disparity"; readers accept "Z" too (schema < 3 and other tools)
DEPTH_ATTRIBUTES = {  # header attributes of depth.exr: what a reader needs, independent of focus
    "dofsynth:quantity": "normalized disparity",
    "dofsynth:convention": "1 = nearest plane of the scene, 0 = infinity; not a distance",
    "dofsynth:range": "[0, 1]",
    "dofsynth:coc": "signed circle-of-confusion radius in px = max_coc * (disparity - focus), "
                    "max_coc and focus per target in the sample record",
    "dofsynth:schema_version": str(SCHEMA_VERSION),
}
_SRGB_CHUNK = struct.pack(">I", 1) + b"sRGB\x00" + struct.pack(">I", zlib.crc32(b"sRGB\x00"))


def with_srgb_chunk(png: bytes) -> bytes:
    """PNG bytes with an sRGB chunk (intent 0, perceptual) right after IHDR."""
    if png[12:16] != b"IHDR":
        raise ValueError("not a PNG stream starting with IHDR")
    end = 8 + 8 + struct.unpack(">I", png[8:12])[0] + 4
    return png[:end] + _SRGB_CHUNK + png[end:]


def encode_coc(disparity: np.ndarray, focus: float, max_coc: float) -> bytes:
    """The optional `coc.N.exr` member: the signed CoC radius in px of target N at every pixel,
    max_coc * (disparity - focus) of the depth member (> 0 in front of the focal plane),
    channel `coc`, with the target's focus and max_coc in the header."""
    c = coc_radius(np.asarray(disparity, dtype=np.float32), float(focus), float(max_coc))
    return encode_exr(np.asarray(c, np.float32), "coc", {
        "dofsynth:quantity": "signed circle-of-confusion radius, px at the stored size",
        "dofsynth:convention": "max_coc * (disparity - focus); > 0 in front of the focal plane, 0 in focus",
        "dofsynth:focus": float(focus), "dofsynth:max_coc": float(max_coc)})


def encode_layer(rgb: np.ndarray, alpha: np.ndarray, disparity) -> bytes:
    """The optional `layer.K.exr` member (K = 0 background, 1 middle, 2 front): the plane as the
    renderer saw it, before blur and highlight boost: linear straight colour R, G, B, coverage A
    and its normalized disparity (a map for the background, a constant for a cutout)."""
    h, w = alpha.shape
    d = np.broadcast_to(np.asarray(disparity, dtype=np.float32), (h, w))
    return encode_exr({"R": rgb[:, :, 0], "G": rgb[:, :, 1], "B": rgb[:, :, 2], "A": alpha, "disparity": d}, "", {
        "dofsynth:quantity": "one plane: linear straight colour (RGB), coverage (A), normalized disparity",
        "dofsynth:convention": "disparity 1 = nearest, 0 = infinity; planes composite back to front with over"})


def encode_depth(disparity: np.ndarray) -> bytes:
    """The depth member: (H, W) float32 normalized disparity, channel `disparity`, with
    DEPTH_ATTRIBUTES in the header."""
    return encode_exr(np.asarray(disparity, dtype=np.float32), DEPTH_CHANNEL, DEPTH_ATTRIBUTES)


def decode_depth(data: bytes, name: str = "<depth.exr>") -> np.ndarray:
    """(H, W) float32 disparity of a depth member, of any schema (channel disparity or Z)."""
    return decode_exr(data, name, channels=DEPTH_CHANNELS)



def encode_png8(img: np.ndarray) -> bytes:
    """(H, W, 3) values in [0, 1] (or uint8) -> 8-bit RGB PNG bytes with PNG_SETTINGS."""
    arr = np.asarray(img)
    if arr.dtype != np.uint8:
        arr = to_uint8(arr)
    if arr.ndim != 3 or arr.shape[2] != 3:
        raise ValueError(f"PNG member must be (H, W, 3), got shape {arr.shape}")
    return with_srgb_chunk(encode_png_rgb(arr, PNG_SETTINGS))


def encode_srgb_png_rows(rows, h: int, w: int) -> bytes:
    """Linear RGB -> clip [0, 1] -> 8-bit sRGB (`linear_to_srgb8`, exact) -> PNG bytes, of an
    (h, w, 3) linear image given block by block by `rows(r0, r1)`: the sRGB codes go straight
    into the BGR buffer the encoder takes, so no frame-sized float temporaries."""
    rgb = np.empty((h, w, 3), np.uint8)
    for r0 in range(0, h, _ROWS):
        r1 = min(r0 + _ROWS, h)
        rgb[r0:r1] = linear_to_srgb8(rows(r0, r1))
    return with_srgb_chunk(encode_png_rgb(rgb, PNG_SETTINGS))


_ROWS = 64  # rows per block of the sRGB encode


def encode_srgb_png_planar(linear: np.ndarray) -> bytes:
    """`encode_srgb_png_rows` of a planar (3, H, W) linear image (`render_planes(..., planar=True)`):
    each channel's row block is encoded where it lies (contiguous) and written into its BGR
    slot (the same bytes, no interleaved float copy)."""
    linear = np.asarray(linear)
    if linear.ndim != 3 or linear.shape[0] != 3:
        raise ValueError(f"planar PNG member must be (3, H, W), got shape {linear.shape}")
    _, h, w = linear.shape
    rgb = np.empty((h, w, 3), np.uint8)
    codes = np.empty((3, min(_ROWS, h), w), np.uint8)
    for r0 in range(0, h, _ROWS):
        r1 = min(r0 + _ROWS, h)
        for ch in range(3):
            linear_to_srgb8(linear[ch, r0:r1], out=codes[ch, : r1 - r0])
        block = rgb[r0:r1]  # interleaved by cv2.merge: one pass, not three strided copies
        merged = cv2.merge([codes[0, : r1 - r0], codes[1, : r1 - r0], codes[2, : r1 - r0]], dst=block)
        if not np.shares_memory(merged, block):
            block[...] = merged
    return with_srgb_chunk(encode_png_rgb(rgb, PNG_SETTINGS))


def encode_alphas(front: np.ndarray, middle: np.ndarray) -> bytes:
    """The cover PNG of the two (H, W) alphas in [0, 1]: 8-bit RGB, R front, G middle, B 0."""
    front, middle = np.asarray(front), np.asarray(middle)
    if front.ndim != 2 or front.shape != middle.shape:
        raise ValueError(f"cover alphas must be two (H, W) maps, got shapes {front.shape}, {middle.shape}")
    rgb = np.zeros(front.shape + (3,), np.uint8)
    for r in range(0, front.shape[0], 128):  # row blocks: small, cache-resident temporaries
        rgb[r:r + 128, :, 0] = to_uint8(front[r:r + 128])
        rgb[r:r + 128, :, 1] = to_uint8(middle[r:r + 128])
    return encode_png_rgb(rgb, COVER_PNG_SETTINGS)
