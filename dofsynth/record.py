"""One sample as tar members (docs/FORMAT.md): render a scene, encode every file to bytes.

`render_sample(scene, library, recipe)` returns `{suffix: bytes}` for
`aif.png`, `depth.exr`, `cover.png`, `dof.0.png`, ..., `json`; `decode_sample` turns such a
dict (or a raw `webdataset` sample) back into arrays. The JSON record is the scene's own
parameters (`scene.to_dict()`) plus the schema version, renderer id and dofsynth version,
encoded canonically (sorted keys, Python's shortest round-trip float repr), so a sample is the
same bytes wherever and whenever it is rendered.

What the pixels are:
- `aif.png`: the all-in-focus composite `layers.aif` (linear), sRGB-encoded, 8 bit, un-boosted
  (encoded in row blocks, `layers.aif_rows`, before the planes are boosted).
- `dof.N.png`: `render_planes(planes, focus_N, max_coc_N, aperture)` with each plane's colour
  highlight-boosted first when the record's `options.highlight` is set; clipped to [0, 1],
  sRGB-encoded, 8 bit. (With `options.linear_light = false`, the naive baseline, the planes are
  sRGB-encoded before the blur and the result is stored as it is.)
- `depth.exr`: `layers.disparity` float32, channel Z, ZIP (lossless).
- `cover.png`: R = front plane alpha, G = middle plane alpha, B = 0 (8 bit, not sRGB-encoded).

Linear light goes to 8-bit sRGB with `color.linear_to_srgb8` (exact round-half-up of the sRGB
formula, table-driven); values in [0, 1] (cover) with `to_uint8`'s round-half-up.
"""
from __future__ import annotations

import json
import math
from dataclasses import replace

import cv2
import numpy as np

from dofsynth import __version__
from dofsynth.aperture import from_dict as aperture_from_dict
from dofsynth.color import highlight_boost, linear_to_srgb, linear_to_srgb8, to_uint8
from dofsynth.io import decode_exr, decode_image, encode_exr
from dofsynth.planes import Plane, alpha_box

SCHEMA_VERSION = 1
RENDERER_ID = "layered-v1"
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
    text = json.dumps(_plain(record), sort_keys=True, separators=(",", ":"), ensure_ascii=False, allow_nan=False)
    return (text + "\n").encode("utf-8")


def sample_record(scene) -> dict:
    """The JSON record of a scene: `scene.to_dict()` plus schema/renderer/version stamps."""
    rec = dict(scene.to_dict())
    rec["schema_version"] = SCHEMA_VERSION
    rec["renderer"] = RENDERER_ID
    rec["dofsynth_version"] = __version__
    return _plain(rec)


def _highlight(options: dict | None) -> dict | None:
    """The highlight-boost parameters of a record's `options`, or None when it is off."""
    h = (options or {}).get("highlight")
    if not h or (isinstance(h, dict) and h.get("enabled") is False):
        return None
    if h is True:
        return {}
    keys = ("threshold", "gain", "power")
    return {k: float(h[k]) for k in keys if k in h}


def boosted_planes(planes, highlight: dict | None) -> list[Plane]:
    """Planes with `color.highlight_boost` applied to their colour (unchanged when None)."""
    if highlight is None:
        return list(planes)
    return [replace(p, rgb=highlight_boost(p.rgb, **highlight)) for p in planes]


def _encode_bgr(bgr: np.ndarray, params) -> bytes:
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(bgr), list(params))
    if not ok:
        raise ValueError(f"PNG encoding failed for an array of shape {bgr.shape}")
    return buf.tobytes()


def encode_png8(img: np.ndarray) -> bytes:
    """(H, W, 3) values in [0, 1] (or uint8) -> 8-bit RGB PNG bytes with PNG_PARAMS."""
    arr = np.asarray(img)
    if arr.dtype != np.uint8:
        arr = to_uint8(arr)
    if arr.ndim != 3 or arr.shape[2] != 3:
        raise ValueError(f"PNG member must be (H, W, 3), got shape {arr.shape}")
    return _encode_bgr(cv2.cvtColor(np.ascontiguousarray(arr), cv2.COLOR_RGB2BGR), PNG_PARAMS)


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
        bgr[r0:r1] = linear_to_srgb8(rows(r0, r1))[:, :, ::-1]
    return _encode_bgr(bgr, PNG_PARAMS)


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
    return _encode_bgr(bgr, PNG_PARAMS)


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
    return _encode_bgr(bgr, COVER_PNG_PARAMS)


def render_sample(scene, library, recipe) -> dict[str, bytes]:
    """Render one scene to its tar members {suffix: bytes} (see the module docstring).

    Targets, aperture and highlight option are read from the scene's own record, so a sample
    can be re-rendered from its JSON alone; the recipe's `render.highlight` is the fallback when
    the record has no `options.highlight`.
    """
    from dofsynth.compose import scene_layers  # imported here: compose pulls in the asset code
    from dofsynth.render import render_planes

    record = sample_record(scene)
    layers = scene_layers(scene, library)
    planes = list(layers.planes)
    aperture = aperture_from_dict(record.get("aperture") or {"kind": "disk"})
    options = record.get("options")
    if not isinstance(options, dict) or "highlight" not in options:  # the scene did not record it
        h = recipe.render.highlight
        options = {"highlight": {"threshold": h.threshold, "gain": h.gain, "power": h.power} if h.enabled else None}
    linear_light = bool(options.get("linear_light", recipe.render.linear_light))
    # Encode the un-blurred members first and drop their arrays (peak memory at large sizes).
    members: dict[str, bytes] = {
        "aif.png": encode_srgb_png_rows(layers.aif_rows, *layers.disparity.shape),
        "depth.exr": encode_exr(np.asarray(layers.disparity, dtype=np.float32)),
        "cover.png": encode_alphas(planes[2].alpha, planes[1].alpha),
    }
    del layers
    highlight = _highlight(options)
    if linear_light and highlight is not None and all(p.rgb.flags.writeable for p in planes):
        # the planes are this call's own fresh arrays: boost in place (no frame-sized copies)
        for i, p in enumerate(planes):
            rgb = p.rgb
            if i > 0:  # a cutout's colour is 0 outside its alpha box (searched for if not given)
                box = p.box if p.box is not None else alpha_box(p.alpha)
                if box is None or box[1] <= box[0] or box[3] <= box[2]:
                    continue
                rgb = rgb[box[0]:box[1], box[2]:box[3]]
            highlight_boost(rgb, **highlight, out=rgb)
        blur_planes = planes
    else:
        blur_planes = boosted_planes(planes, highlight)
    if not linear_light:  # the naive baseline: blur sRGB-encoded values, store them as they are
        blur_planes = [replace(p, rgb=linear_to_srgb(p.rgb)) for p in blur_planes]
    del planes
    for n, t in enumerate(record["targets"]):
        if linear_light:  # planar (3, H, W): encoded in row blocks, no interleaved frame copy
            img = render_planes(blur_planes, float(t["focus"]), float(t["max_coc"]), aperture, planar=True)
            members[f"dof.{n}.png"] = encode_srgb_png_planar(img)
        else:
            img = render_planes(blur_planes, float(t["focus"]), float(t["max_coc"]), aperture)
            members[f"dof.{n}.png"] = encode_png8(np.clip(img, 0.0, 1.0))
        del img
    members["json"] = encode_record(record)
    return members


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
    depth = decode_exr(need("depth.exr"), f"{key}.depth.exr", channels="Z")
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
