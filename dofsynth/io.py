"""Reading and writing the file formats of dofsynth: sRGB images (PNG, JPEG, TIFF, WebP) and
float32 images and depth (OpenEXR), to paths and to bytes (for tar shard members).

Images come back as float32 in [0, 1], still sRGB-encoded, shaped (H, W, C) with C in
{1, 2, 3, 4} in RGB(A) order (`raw=True`: the stored integer codes instead); `load_linear_rgba`
converts to linear light. EXR files hold linear values (images) or normalized disparity
(depth). Files are written atomically (dofsynth.files).
"""
from __future__ import annotations

import io
import os
import zlib
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import OpenEXR

from dofsynth.color import srgb_to_linear
from dofsynth.files import atomic_write_bytes
from dofsynth.image import to_uint8

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".webp", ".exr")


class ImageReadError(ValueError):
    """An image file that cannot be decoded; the message names the file."""


def swap_rb(img: np.ndarray) -> np.ndarray:
    """RGB(A) <-> BGR(A), OpenCV's channel order (a view); grey images as (H, W, 1)."""
    if img.ndim == 2:
        return img[:, :, None]
    if img.shape[2] == 3:
        return img[:, :, ::-1]
    if img.shape[2] == 4:
        return img[:, :, [2, 1, 0, 3]]
    return img


def unit_float(img: np.ndarray, name: str) -> np.ndarray:
    """Stored codes as float32: uint8 / 255, uint16 / 65535, floats as they are."""
    if img.dtype == np.uint8:
        return img.astype(np.float32) / 255.0
    if img.dtype == np.uint16:
        return img.astype(np.float32) / 65535.0
    if img.dtype in (np.float32, np.float64, np.float16):
        return img.astype(np.float32)
    raise ImageReadError(f"{name}: unsupported pixel type {img.dtype}")


MAX_DECODE_PIXELS = 1 << 30   # OpenCV's own limit (CV_IO_MAX_IMAGE_PIXELS); more is a bomb, not a photo
MAX_DECODE_SIDE = 1_000_000   # libpng's default user limit per side
_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def check_png(data: bytes, name: str) -> None:
    """Walk a PNG's chunks before libpng sees them, so that what libpng would report on stderr
    in a line of its own (and OpenCV in several) is one ImageReadError naming the file: a
    truncated file, a chunk whose CRC fails, an IHDR that is not an image, or a size past
    MAX_DECODE_PIXELS (a decompression bomb). A zlib stream that is broken while its CRCs hold
    is left to libpng."""
    n, pos, seen_ihdr, view = len(data), 8, False, memoryview(data)
    while True:
        if pos + 12 > n:
            raise ImageReadError(f"{name}: not a readable image (truncated PNG: {n} bytes, no IEND chunk)")
        length = int.from_bytes(data[pos:pos + 4], "big")
        kind = data[pos + 4:pos + 8]
        end = pos + 12 + length
        chunk = f"chunk {kind.decode('latin-1')} at byte {pos}"
        if length > 0x7FFFFFFF or end > n:
            raise ImageReadError(f"{name}: not a readable image (truncated PNG: {chunk} runs past the end)")
        if zlib.crc32(view[pos + 4:end - 4]) != int.from_bytes(data[end - 4:end], "big"):
            raise ImageReadError(f"{name}: not a readable image (corrupt PNG: {chunk} fails its CRC)")
        if not seen_ihdr:
            if kind != b"IHDR" or length != 13:
                raise ImageReadError(f"{name}: not a readable image (corrupt PNG: no IHDR chunk first)")
            w, h = int.from_bytes(data[pos + 8:pos + 12], "big"), int.from_bytes(data[pos + 12:pos + 16], "big")
            if not (0 < w <= MAX_DECODE_SIDE and 0 < h <= MAX_DECODE_SIDE) or w * h > MAX_DECODE_PIXELS:
                raise ImageReadError(f"{name}: not a readable image (a PNG of {w}x{h} pixels, more than the "
                                     f"{MAX_DECODE_PIXELS} pixels or {MAX_DECODE_SIDE} per side dofsynth decodes: a "
                                     "decompression bomb, not a photo)")
            seen_ihdr = True
        if kind == b"IEND":
            return
        pos = end


def decode_image(data: bytes, name: str = "<bytes>", raw: bool = False) -> np.ndarray:
    """Decode PNG/JPEG/TIFF/WebP bytes (8 or 16 bit) to (H, W, C), RGB(A) order: float32 in
    [0, 1], or with `raw` the stored codes (uint8, uint16 or float) as a contiguous array.
    A file that cannot be decoded is one ImageReadError line naming it (PNGs: `check_png`)."""
    if data[:8] == _PNG_SIGNATURE:
        check_png(data, name)
    buf = np.frombuffer(data, dtype=np.uint8)
    try:
        img = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED) if buf.size else None
    except cv2.error as exc:  # OpenCV's text runs over lines: its message part, in one
        why = " ".join((exc.err or str(exc)).split())
        raise ImageReadError(f"{name}: not a readable image ({why})") from None
    if img is None:
        raise ImageReadError(f"{name}: not a readable image (corrupt, truncated or unknown format)")
    img = np.ascontiguousarray(swap_rb(img))
    return img if raw else unit_float(img, name)


def read_image(path: str | os.PathLike) -> np.ndarray:
    """Read an image file to float32 (H, W, C) in [0, 1] (EXR: the stored values)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file")
    if path.suffix.lower() == ".exr":
        return read_exr(path, channels=None)
    return decode_image(path.read_bytes(), str(path))


def load_linear_rgba(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray | None]:
    """Read any supported image as linear-light RGB (H, W, 3) float32 and its alpha (or None).

    Grey images are replicated to RGB; 8/16-bit files are sRGB-decoded, EXR is taken as linear.
    """
    img = read_image(path)
    c = img.shape[2]
    alpha = img[:, :, c - 1].copy() if c in (2, 4) else None
    colour = img[:, :, :1] if c in (1, 2) else img[:, :, :3]
    colour = np.repeat(colour, 3, axis=2) if colour.shape[2] == 1 else colour
    linear = colour if Path(path).suffix.lower() == ".exr" else srgb_to_linear(colour)
    return np.ascontiguousarray(linear, dtype=np.float32), alpha


@dataclass(frozen=True)
class PngSettings:
    """How an 8-bit PNG is compressed: zlib `level` (0-9), zlib `strategy` and one fixed row
    `filter` for every row. The bytes depend on all three (and on zlib), not on the encoder."""

    level: int = 3
    strategy: str = "default"   # "default" | "huffman" (Huffman-only) | "rle"
    filter: str | None = None   # "none" | "sub" | "up" | "avg" | "paeth"; None: libpng's adaptive choice

    def cv2_params(self) -> list[int]:
        out = [cv2.IMWRITE_PNG_COMPRESSION, self.level, cv2.IMWRITE_PNG_STRATEGY, _CV2_STRATEGY[self.strategy]]
        return out + ([cv2.IMWRITE_PNG_FILTER, _CV2_FILTER[self.filter]] if self.filter else [])


_CV2_STRATEGY = {"default": cv2.IMWRITE_PNG_STRATEGY_DEFAULT, "huffman": cv2.IMWRITE_PNG_STRATEGY_HUFFMAN_ONLY,
                 "rle": cv2.IMWRITE_PNG_STRATEGY_RLE}
_CV2_FILTER = {"none": cv2.IMWRITE_PNG_FILTER_NONE, "sub": cv2.IMWRITE_PNG_FILTER_SUB, "up": cv2.IMWRITE_PNG_FILTER_UP,
               "avg": cv2.IMWRITE_PNG_FILTER_AVG, "paeth": cv2.IMWRITE_PNG_FILTER_PAETH}
_ZLIB_STRATEGY = {"default": 0, "huffman": 2, "rle": 3}           # zlib's Z_* constants
_LIBPNG_FILTER = {"none": 0x08, "sub": 0x10, "up": 0x20, "avg": 0x40, "paeth": 0x80}  # libpng's PNG_FILTER_*


def png_backend() -> str:
    """The encoder `encode_png_rgb` uses: "imagecodecs" (libpng called directly: the same bytes
    as OpenCV's, measured 0.78-0.87x its CPU time) where installed, else "cv2"; the
    DOFSYNTH_PNG environment variable forces one (tests compare them)."""
    want = os.environ.get("DOFSYNTH_PNG", "")
    if want not in ("", "cv2", "imagecodecs"):
        raise ValueError(f"DOFSYNTH_PNG={want!r}: want cv2 or imagecodecs")
    if want != "cv2":
        try:
            import imagecodecs  # noqa: F401
            return "imagecodecs"
        except ImportError:
            if want:
                raise
    return "cv2"


def encode_png_rgb(img: np.ndarray, settings: PngSettings = PngSettings()) -> bytes:
    """PNG bytes of an (H, W) grey or (H, W, C) RGB(A) uint8 / uint16 array with `settings`."""
    arr = np.ascontiguousarray(img)
    if settings.filter and png_backend() == "imagecodecs":  # (an adaptive filter: OpenCV's own choice)
        import imagecodecs

        return bytes(imagecodecs.png_encode(arr, level=settings.level, strategy=_ZLIB_STRATEGY[settings.strategy],
                                            filter=_LIBPNG_FILTER[settings.filter]))
    return encode_png_bgr(swap_rb(arr) if arr.ndim == 3 else arr, settings.cv2_params())


def encode_png_bgr(bgr: np.ndarray, params=(cv2.IMWRITE_PNG_COMPRESSION, 3)) -> bytes:
    """PNG bytes of an array already in OpenCV's channel order (grey, BGR or BGRA; uint8 or
    uint16) with the given cv2.imwrite parameters."""
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(bgr), list(params))
    if not ok:
        raise ValueError(f"PNG encoding failed for an array of shape {bgr.shape}")
    return buf.tobytes()


def encode_png(img: np.ndarray, compression: int = 3) -> bytes:
    """Encode an image to PNG bytes. Float input is taken as sRGB-encoded [0, 1] and stored as
    8 bit; uint8 and uint16 are stored as they are. (H, W) or (H, W, C), C in {1, 3, 4}, RGB(A)."""
    arr = np.asarray(img)
    if arr.dtype not in (np.uint8, np.uint16):
        arr = to_uint8(arr)
    return encode_png_bgr(swap_rb(arr) if arr.ndim == 3 else arr, (cv2.IMWRITE_PNG_COMPRESSION, compression))


def encode_exr(image, channel: str = "Y", attributes: dict | None = None) -> bytes:
    """Encode float32 pixels as a ZIP-compressed (lossless) EXR: an (H, W) map as one channel
    named `channel`, an (H, W, 3|4) image as channels R, G, B(, A), or a dict {name: (H, W)}
    as those channels; `attributes` (str or float values) go into the header. (OpenEXR's "Z"
    means distance from the camera: not for disparity, see dofsynth.record.encode_depth.)"""
    if isinstance(image, dict):  # OpenEXR writes non-contiguous arrays wrongly: always copy
        chans = {k: np.ascontiguousarray(v, dtype=np.float32) for k, v in image.items()}
        if len({v.shape for v in chans.values()}) != 1 or next(iter(chans.values())).ndim != 2:
            raise ValueError("EXR channels must be (H, W) maps of one size")
    elif (arr := np.asarray(image, dtype=np.float32)).ndim == 2:
        chans = {channel: np.ascontiguousarray(arr)}
    elif arr.ndim == 3 and arr.shape[2] in (3, 4):
        # OpenEXR writes non-contiguous arrays wrongly: copy each channel out.
        chans = {k: np.ascontiguousarray(arr[:, :, i]) for i, k in enumerate("RGBA"[: arr.shape[2]])}
    else:
        raise ValueError(f"EXR pixels must be (H, W) or (H, W, 3|4), got shape {arr.shape}")
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage, **(attributes or {})}
    out = io.BytesIO()
    OpenEXR.File(header, chans).write(out)
    return out.getvalue()


def _exr_channels(data, name: str) -> dict:
    try:
        return OpenEXR.File(io.BytesIO(data) if isinstance(data, bytes) else data).channels()
    except Exception as exc:  # OpenEXR raises plain RuntimeErrors on malformed files
        raise ImageReadError(f"{name}: not a readable EXR file ({exc})") from exc


def decode_exr(data: bytes | io.IOBase, name: str = "<bytes>", channels: str | tuple | None = None) -> np.ndarray:
    """Decode EXR bytes. With `channels` a name (or a tuple of names: the first present) return
    that channel as float32 (H, W); with None, all channels as (H, W, C) float32 in R, G, B, A
    order where present."""
    chans = _exr_channels(data, name)
    if channels is not None:
        names = (channels,) if isinstance(channels, str) else tuple(channels)
        for c in names:
            if c in chans:
                return np.ascontiguousarray(chans[c].pixels, dtype=np.float32)
        raise ImageReadError(f"{name}: EXR has no channel {' or '.join(map(repr, names))} (has {sorted(chans)})")
    # OpenEXR groups R, G, B(, A) into one "RGB(A)" entry of (H, W, C) pixels; colour first
    colour = ("RGBA", "RGB", "R", "G", "B", "A")
    order = [k for k in colour if k in chans] + sorted(k for k in chans if k not in colour)
    planes = [p[:, :, None] if p.ndim == 2 else p for p in (chans[k].pixels for k in order)]
    return np.ascontiguousarray(np.concatenate(planes, axis=2), dtype=np.float32)


def read_exr(path: str | os.PathLike, channels: str | tuple | None = None) -> np.ndarray:
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file")
    return decode_exr(path.read_bytes(), str(path), channels)


DEPTH_CHANNELS = ("disparity", "Z")  # dofsynth's depth member (schema >= 3), then older shards' and others'


def read_depth(path: str | os.PathLike) -> np.ndarray:
    """Read a disparity map as float32 (H, W): an EXR's 'disparity', 'Z' or only channel, or an
    8/16-bit grey image scaled to [0, 1] (grey stored as RGB is taken if its channels are
    equal), or a 2-D .npy array. A colour image is refused (ImageReadError): it is not a depth map."""
    path = Path(path)
    if path.suffix.lower() == ".npy":
        if not path.is_file():
            raise FileNotFoundError(f"{path}: no such file")
        try:
            z = np.load(path, allow_pickle=False)
        except ValueError as exc:
            raise ImageReadError(f"{path}: not a readable .npy array ({exc})") from None
        z = z[..., 0] if z.ndim == 3 and z.shape[2] == 1 else z
        if z.ndim != 2 or not np.issubdtype(z.dtype, np.number):
            raise ImageReadError(f"{path}: a depth map must be a 2-D numeric array, got {z.dtype} {z.shape}")
        return np.ascontiguousarray(z, dtype=np.float32)
    if path.suffix.lower() == ".exr":
        if not path.is_file():
            raise FileNotFoundError(f"{path}: no such file")
        f = _exr_channels(path.read_bytes(), str(path))
        name = next((c for c in DEPTH_CHANNELS if c in f), next(iter(f)) if len(f) == 1 else None)
        px = None if name is None else f[name].pixels
        if px is None or px.ndim != 2:
            raise ImageReadError(f"{path}: an EXR with channels {', '.join(sorted(f))} is an image, not a depth map "
                                 "(one channel, or one named disparity or Z)")
        return np.ascontiguousarray(px, dtype=np.float32)
    img = read_image(path)
    grey = img[:, :, 0]
    if img.shape[2] >= 3 and not (np.array_equal(grey, img[:, :, 1]) and np.array_equal(grey, img[:, :, 2])):
        raise ImageReadError(f"{path}: a colour image, not a depth map (a grey image, or an EXR of one channel)")
    return np.ascontiguousarray(grey, dtype=np.float32)


DEPTH_MAP_KINDS = ("normalized", "disparity", "depth")


def normalize_disparity(z: np.ndarray, kind: str) -> tuple[np.ndarray, np.ndarray]:
    """(normalized disparity in [0, 1], known mask), both (H, W), of a map of `kind`:
    "normalized" (already disparity in [0, 1]: kept), "disparity" (any scale or offset, e.g. a
    monocular network's relative inverse depth) or "depth" (any unit: 1 / z where z > 0); the
    last two are min-max normalized over their known (finite; depth: > 0) pixels, the paper's
    normalisation. Unknown pixels become 0 (infinity)."""
    if kind not in DEPTH_MAP_KINDS:
        raise ValueError(f"depth kind must be one of {', '.join(DEPTH_MAP_KINDS)}, got {kind!r}")
    z = np.asarray(z, np.float64)
    valid = np.isfinite(z) & (z > 0 if kind == "depth" else True)
    if kind == "normalized":
        return np.where(valid, z, 0.0).astype(np.float32), valid
    disp = np.where(valid, 1.0 / np.where(valid, z, 1.0), 0.0) if kind == "depth" else np.where(valid, z, 0.0)
    if valid.any():
        lo, hi = disp[valid].min(), disp[valid].max()
        disp = np.where(valid, (disp - lo) / (hi - lo) if hi > lo else 0.0, 0.0)
    return disp.astype(np.float32), valid


def write_png(path: str | os.PathLike, img: np.ndarray) -> None:
    atomic_write_bytes(path, encode_png(img))


def write_exr(path: str | os.PathLike, image: np.ndarray) -> None:
    """Write a depth map (H, W) or a linear image (H, W, 3|4) as EXR, atomically."""
    atomic_write_bytes(path, encode_exr(image))
