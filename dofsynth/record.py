"""The members of one sample (docs/FORMAT.md) as bytes, and back: the JSON record, the PNG and
EXR encoders with their fixed settings, and `decode_sample`.

dofsynth.sample renders a scene into `{suffix: bytes}` for `aif.png`, `depth.exr`,
`cover.png`, `dof.0.png`, ..., `json` with these encoders; `decode_sample` turns such a dict
(or a raw `webdataset` sample) back into arrays. The JSON record is the scene's own parameters
(`scene.to_dict()`) plus the schema version, renderer id and dofsynth version, encoded
canonically (sorted keys, Python's shortest round-trip float repr), so a sample is the same
bytes wherever and whenever it is rendered.

What the pixels are:
- `aif.png`: the all-in-focus composite (linear), sRGB-encoded, 8 bit, un-boosted.
- `dof.N.png`: target N rendered from the planes (dofsynth.sample); clipped to [0, 1],
  sRGB-encoded, 8 bit.
- `depth.exr`: `layers.disparity` float32, one channel named `disparity` (schema >= 3; older
  shards: `Z`, which OpenEXR and OpenImageIO define as distance, so it was renamed), ZIP
  (lossless), with header attributes stating the quantity and its convention (DEPTH_ATTRIBUTES).
- `cover.png`: R = front plane alpha, G = middle plane alpha, B = 0 (8 bit, not sRGB-encoded).

The image members (aif, dof) carry a PNG sRGB chunk (rendering intent perceptual); cover
does not (its codes are coverage, not colour).

Linear light goes to 8-bit sRGB with `color.linear_to_srgb8` (exact round-half-up of the sRGB
formula, table-driven); values in [0, 1] (cover) with `to_uint8`'s round-half-up.
"""
from __future__ import annotations

import json
import math
import struct
import zlib

import cv2
import numpy as np

from dofsynth import __version__
from dofsynth.color import linear_to_srgb8
from dofsynth.files import canonical_json
from dofsynth.image import to_uint8
from dofsynth.optics.coc import coc_radius
from dofsynth.io import decode_exr, decode_image, encode_exr, encode_png_bgr, swap_rb

SCHEMA_VERSION = 3  # 2: assets' colour; objects' anchored, visible and rejected;
#                    3: depth.exr channel "disparity" (was "Z") with attributes; sRGB chunks
RENDERERS = {"layered": "layered-v5", "subaperture": "subaperture-v3", "exact": "exact-v1"}
RENDERER_ID = RENDERERS["layered"]  # v2: highlights blurred as boosted light and mapped back (dofsynth.highlight);
#                             v3: cutouts edge-replicated past the frame edges they reach;
#                             v4 (subaperture v2): kernels integrate the shape against the pixel tent,
#                             and a ramp's scatter carries the Jacobian of its parallax;
#                             v5 (subaperture v3): the Jacobian weighs each kernel pixel by the mean
#                             aperture point landing there (kernel_moments), polygon kernels are
#                             convolved over their non-zero box; cells composite to second order
# zlib settings of the PNG members, chosen by measurement at 1024 px (docs/rendering.md):
# - images (aif, dof): level 1, one fixed Paeth row filter, Huffman-only coding. libpng no longer
#   tries all five filters per row, and Paeth residuals of photos have few long matches, so
#   Huffman coding alone is within 1.5% of the size of the old adaptive/Z_RLE setting at 0.6x
#   its time.
# - cover (mostly flat alpha): level 1, fixed Up filter, Z_RLE: the same size as before, 3x faster.
# The bytes depend on these settings: changing them changes every shard.
PNG_COMPRESSION = 1
PNG_PARAMS = (cv2.IMWRITE_PNG_COMPRESSION, PNG_COMPRESSION, cv2.IMWRITE_PNG_STRATEGY,
              cv2.IMWRITE_PNG_STRATEGY_HUFFMAN_ONLY, cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FILTER_PAETH)
COVER_PNG_PARAMS = (cv2.IMWRITE_PNG_COMPRESSION, PNG_COMPRESSION, cv2.IMWRITE_PNG_STRATEGY,
                    cv2.IMWRITE_PNG_STRATEGY_RLE, cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FILTER_UP)

DEPTH_CHANNEL = "disparity"
DEPTH_CHANNELS = (DEPTH_CHANNEL, "Z")  # what readers accept: schema >= 3, then older shards
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


# What a sample holds: the manifest's `format.members` and the table in docs/FORMAT.md (a test
# keeps them equal). Sizes are (H, W) = the record's `size`.
MEMBERS = [
    {"name": "aif.png", "type": "PNG", "dtype": "uint8", "channels": "RGB", "range": "0-255",
     "meaning": "all-in-focus image, sRGB-encoded (sRGB chunk)"},
    {"name": "depth.exr", "type": "EXR", "dtype": "float32", "channels": DEPTH_CHANNEL, "range": "0-1",
     "meaning": "normalized disparity, 1 = nearest, 0 = infinity (older shards: channel Z)"},
    {"name": "cover.png", "type": "PNG", "dtype": "uint8", "channels": "RGB", "range": "0-255",
     "meaning": "coverage of each plane as placed, before blur: R = front, G = middle, B = 0 (not sRGB)"},
    {"name": "dof.N.png", "type": "PNG", "dtype": "uint8", "channels": "RGB", "range": "0-255",
     "meaning": "DoF target N = 0, 1, ..., sRGB-encoded (sRGB chunk); focus and max_coc in targets[N]"},
    {"name": "json", "type": "JSON", "dtype": "utf-8", "channels": "-", "range": "-",
     "meaning": "the sample record: the scene's parameters, sorted keys"},
    {"name": "coc.N.exr", "type": "EXR", "dtype": "float32", "channels": "coc", "range": "px",
     "meaning": "optional (render.members coc): signed CoC radius of target N, max_coc * (disparity - focus)"},
    {"name": "layer.K.exr", "type": "EXR", "dtype": "float32", "channels": "R, G, B, A, disparity", "range": "linear",
     "meaning": "optional (render.members layers): plane K = 0 background, 1 middle, 2 front before blur"},
    {"name": "dp.N.left.png", "type": "PNG", "dtype": "uint8", "channels": "RGB", "range": "0-255",
     "meaning": "optional (render.members dual_pixel): target N through the left half of the aperture, sRGB"},
    {"name": "dp.N.right.png", "type": "PNG", "dtype": "uint8", "channels": "RGB", "range": "0-255",
     "meaning": "optional (render.members dual_pixel): target N through the right half of the aperture, sRGB"},
]
CONVENTIONS = {
    "disparity": "normalized disparity in [0, 1]: 1 = nearest, 0 = infinity",
    "coc": "signed circle-of-confusion radius in px = max_coc * (disparity - focus), > 0 in front of focus",
    "max_coc": "px at the stored size (halve it with the image)",
    "colour": "PNG images are sRGB-encoded; blur and compositing happened in linear light, float32",
    "paths": "shard paths are relative to the data set folder",
}


def format_description() -> dict:
    """What the manifest says about its samples: members, conventions, record schema, renderer."""
    return {"members": MEMBERS, "conventions": CONVENTIONS, "record_schema_version": SCHEMA_VERSION,
            "renderer": RENDERER_ID}


def exr_handler(key: str, data: bytes):
    """A webdataset decoder handler for the EXR members: `wds.WebDataset(url).decode("rgb",
    exr_handler)` yields depth.exr as (H, W) float32 disparity (any schema), coc.N.exr as (H, W)
    float32 px, layer.K.exr as (H, W, 5) float32 R, G, B, A, disparity and other EXRs as
    (H, W, C); None for other members (the next handler's)."""
    if not key.lower().endswith("exr"):
        return None
    name = key.rsplit("/", 1)[-1]
    if name.startswith("depth.") or ".depth." in name:
        return decode_depth(data, name)
    if name.startswith("coc.") or ".coc." in name:
        return decode_exr(data, name, channels="coc")
    return decode_exr(data, name, channels=None)


class SampleDecodeError(ValueError):
    """A sample whose members cannot be decoded; the message names the member."""


def _plain(obj):
    """JSON-ready copy: numpy scalars/arrays to Python, tuples to lists; NaN/inf refused."""
    if isinstance(obj, dict):
        return {str(k): _plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_plain(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _plain(obj.tolist())
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        f = float(obj)
        if not math.isfinite(f):
            raise ValueError(f"sample record holds a non-finite number {f}")
        return f
    return obj


def encode_record(record: dict) -> bytes:
    """Canonical JSON bytes: sorted keys, compact separators, UTF-8, trailing newline."""
    return canonical_json(_plain(record))


def sample_record(scene) -> dict:
    """The JSON record of a scene: `scene.to_dict()` plus schema/renderer/version stamps."""
    rec = dict(scene.to_dict())
    rec["schema_version"] = SCHEMA_VERSION
    rec["renderer"] = RENDERERS[scene.options.method]
    rec["dofsynth_version"] = __version__
    return _plain(rec)


def encode_png8(img: np.ndarray) -> bytes:
    """(H, W, 3) values in [0, 1] (or uint8) -> 8-bit RGB PNG bytes with PNG_PARAMS."""
    arr = np.asarray(img)
    if arr.dtype != np.uint8:
        arr = to_uint8(arr)
    if arr.ndim != 3 or arr.shape[2] != 3:
        raise ValueError(f"PNG member must be (H, W, 3), got shape {arr.shape}")
    return with_srgb_chunk(encode_png_bgr(swap_rb(arr), PNG_PARAMS))


def encode_srgb_png(linear: np.ndarray) -> bytes:
    """Linear RGB -> clip [0, 1] -> 8-bit sRGB (`linear_to_srgb8`, exact) -> PNG bytes."""
    linear = np.asarray(linear)
    if linear.ndim != 3 or linear.shape[2] != 3:
        raise ValueError(f"PNG member must be (H, W, 3), got shape {linear.shape}")
    return encode_srgb_png_rows(lambda r0, r1: linear[r0:r1], *linear.shape[:2])


def encode_srgb_png_rows(rows, h: int, w: int) -> bytes:
    """Like `encode_srgb_png` for an (h, w, 3) linear image given block by block by
    `rows(r0, r1)`: the sRGB codes go straight into the BGR buffer the encoder takes, so no
    frame-sized float temporaries (the same bytes)."""
    bgr = np.empty((h, w, 3), np.uint8)
    for r0 in range(0, h, _ROWS):
        r1 = min(r0 + _ROWS, h)
        bgr[r0:r1] = swap_rb(linear_to_srgb8(rows(r0, r1)))
    return with_srgb_chunk(encode_png_bgr(bgr, PNG_PARAMS))


_ROWS = 64  # rows per block of the sRGB encode


def encode_srgb_png_planar(linear: np.ndarray) -> bytes:
    """`encode_srgb_png` of a planar (3, H, W) linear image (`render_planes(..., planar=True)`):
    each channel's row block is encoded where it lies (contiguous) and written into its BGR
    slot (the same bytes, no interleaved float copy)."""
    linear = np.asarray(linear)
    if linear.ndim != 3 or linear.shape[0] != 3:
        raise ValueError(f"planar PNG member must be (3, H, W), got shape {linear.shape}")
    _, h, w = linear.shape
    bgr = np.empty((h, w, 3), np.uint8)
    codes = np.empty((min(_ROWS, h), w), np.uint8)
    for r0 in range(0, h, _ROWS):
        r1 = min(r0 + _ROWS, h)
        for ch in range(3):
            linear_to_srgb8(linear[ch, r0:r1], out=codes[: r1 - r0])
            bgr[r0:r1, :, 2 - ch] = codes[: r1 - r0]
    return with_srgb_chunk(encode_png_bgr(bgr, PNG_PARAMS))


def encode_cover(cover: np.ndarray) -> bytes:
    """(H, W, 2) front/middle alpha in [0, 1] -> 8-bit RGB PNG (R front, G middle, B 0)."""
    cover = np.asarray(cover, dtype=np.float32)
    if cover.ndim != 3 or cover.shape[2] != 2:
        raise ValueError(f"cover must be (H, W, 2), got shape {cover.shape}")
    return encode_alphas(cover[:, :, 0], cover[:, :, 1])


def encode_alphas(front: np.ndarray, middle: np.ndarray) -> bytes:
    """The cover PNG straight from the two (H, W) alphas (same bytes as `encode_cover`)."""
    front, middle = np.asarray(front), np.asarray(middle)
    if front.ndim != 2 or front.shape != middle.shape:
        raise ValueError(f"cover alphas must be two (H, W) maps, got shapes {front.shape}, {middle.shape}")
    bgr = np.zeros(front.shape + (3,), np.uint8)
    for r in range(0, front.shape[0], 128):  # row blocks: small, cache-resident temporaries
        bgr[r:r + 128, :, 2] = to_uint8(front[r:r + 128])
        bgr[r:r + 128, :, 1] = to_uint8(middle[r:r + 128])
    return encode_png_bgr(bgr, COVER_PNG_PARAMS)


def decode_sample(members: dict[str, bytes], key: str | None = None) -> dict:
    """Decode one sample's members (bare suffix keys; a `webdataset` sample's "__key__" and
    other "_"-prefixed entries are used for the key or ignored).

    Returns {"key", "record" (dict), "aif" (H, W, 3) float32 sRGB in [0, 1], "depth" (H, W)
    float32 disparity, "cover" (H, W, 2) float32 front/middle alpha, "dof" [(H, W, 3) float32
    sRGB, ...] in target order}. Errors name the member.
    """
    key = key or members.get("__key__") or "<sample>"
    if isinstance(key, bytes):
        key = key.decode()

    def need(suffix: str) -> bytes:
        if suffix not in members:
            raise SampleDecodeError(f"{key}: missing member {key}.{suffix}")
        return members[suffix]

    try:
        record = json.loads(need("json").decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise SampleDecodeError(f"{key}.json: not valid JSON ({exc})") from exc
    aif = decode_image(need("aif.png"), f"{key}.aif.png")
    cover = decode_image(need("cover.png"), f"{key}.cover.png")
    try:
        depth = decode_depth(need("depth.exr"), f"{key}.depth.exr")
    except ValueError as exc:
        raise SampleDecodeError(str(exc)) from exc
    dof_ids = sorted(int(s.split(".")[1]) for s in members
                     if s.startswith("dof.") and s.endswith(".png") and s.split(".")[1].isdigit())
    if dof_ids != list(range(len(dof_ids))):
        raise SampleDecodeError(f"{key}: DoF targets must be numbered 0..N-1, found {dof_ids}")
    n_targets = len(record.get("targets", dof_ids))
    if n_targets != len(dof_ids):
        raise SampleDecodeError(f"{key}: record lists {n_targets} targets but {len(dof_ids)} dof.N.png members exist")
    dof = [decode_image(members[f"dof.{i}.png"], f"{key}.dof.{i}.png")[:, :, :3] for i in dof_ids]
    for name, arr in [("aif.png", aif), ("cover.png", cover)] + [(f"dof.{i}.png", d) for i, d in enumerate(dof)]:
        if arr.shape[:2] != depth.shape:
            raise SampleDecodeError(f"{key}.{name}: size {arr.shape[:2]} differs from depth.exr {depth.shape}")
    return {"key": key, "record": record, "aif": aif[:, :, :3], "depth": depth,
            "cover": np.ascontiguousarray(cover[:, :, :2]), "dof": dof}
