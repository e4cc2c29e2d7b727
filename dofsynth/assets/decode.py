"""One asset and its pixels: the `Asset` record, `AssetError`, and the decoding and checks that
scanning and loading share (size, alpha, colour to linear light)."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from dofsynth.color import srgb8_to_linear, srgb_to_linear
from dofsynth.io import decode_exr, decode_image, unit_float

MIN_SIDE = 64
KINDS = ("background", "foreground")
# Float assets (EXR, float TIFF) hold linear light: a colour above this is no photo (a bright
# sun in an HDR photo is about 1e3-1e4) but a broken file; NaN and inf never pass.
MAX_LINEAR = 65504.0  # the largest half float


class AssetError(ValueError):
    """A bad or changed asset; the message names the file and the problem. `asset_id`: the
    library's id of the asset, where a loader knows it (generation can then draw another)."""

    def __init__(self, message: str, asset_id: str | None = None):
        super().__init__(message)
        self.asset_id = asset_id


@dataclass(frozen=True)
class Asset:
    id: str                          # "bg/REL" or "fg/REL" (REL: path under the root, no suffix); builtin:...
    kind: str                        # "background" | "foreground"
    path: str                        # absolute path, or "builtin:bg/NAME"
    sha256: str                      # of the file bytes (builtin: of the generated pixels)
    size: tuple[int, int]            # (w, h)
    licence: str = "unknown"
    alpha_path: str | None = None    # fg/ + alpha/ layout: the alpha file
    alpha_sha256: str | None = None
    bbox: tuple[int, int, int, int] | None = None  # (x, y, w, h) where alpha > 0; None = whole image
    cut: tuple[str, ...] = ()        # sides ("top", "bottom", "left", "right") where the matte is cut by the photo's border
    thumb: np.ndarray | None = field(default=None, compare=False, repr=False)  # uint8 alpha of the extent, long side <= THUMB
    phash: int | None = None         # 64-bit perceptual hash of the photo (dofsynth.assets.similar)

    @property
    def extent(self) -> tuple[int, int, int, int]:
        """(x, y, w, h) of the part of the image that is placed: the alpha's bbox, or all."""
        return self.bbox if self.bbox is not None else (0, 0, self.size[0], self.size[1])


def is_exr(path: str) -> bool:
    return path.lower().endswith(".exr")


def decode_asset(data: bytes, path: str, codes: bool = False) -> np.ndarray:
    """(H, W, C) pixels of an asset file: float32 (sRGB-encoded [0, 1] for 8/16-bit files,
    the stored values for EXR); with `codes`, 8-bit files come back as their uint8 codes (RGB(A)
    order), so the loaders linearize through the exact 256-entry table. AssetError names a bad
    file: unreadable, or a float file with NaN, inf or values out of range (`check_values`)."""
    try:
        if is_exr(path):
            img = decode_exr(data, path, channels=None)
        else:
            raw = decode_image(data, path, raw=True)
            if codes and raw.dtype == np.uint8:
                return raw
            float_file = raw.dtype.kind == "f"
            img = unit_float(raw, path)
            if not float_file:
                return img
    except ValueError as exc:
        raise AssetError(str(exc)) from exc
    check_values(img, path)
    return img


def check_values(img: np.ndarray, path: str) -> None:
    """Refuse the pixels of a float file that no photo or matte has: NaN, inf, a colour above
    MAX_LINEAR, an alpha (the last of 2 or 4 channels) outside [0, 1]."""
    c = img.shape[2]
    bad = ~np.isfinite(img)
    if bad.any():
        y, x, ch = (int(v[0]) for v in np.nonzero(bad))
        raise AssetError(f"{path}: {int(bad.sum())} NaN or inf values (first at x={x}, y={y}, channel {ch})")
    colour = img[:, :, : c - 1] if c in (2, 4) else img
    if colour.size and float(np.abs(colour).max()) > MAX_LINEAR:
        raise AssetError(f"{path}: colour values up to {float(np.abs(colour).max()):.3g}, beyond {MAX_LINEAR:g}: "
                         "not an image of light")
    if c in (2, 4):
        a = img[:, :, c - 1]
        lo, hi = float(a.min()), float(a.max())
        if lo < -1e-3 or hi > 1.0 + 1e-3:
            raise AssetError(f"{path}: alpha outside [0, 1] (from {lo:.4g} to {hi:.4g})")


def image_header(path: str) -> tuple[int, int, int]:
    """(w, h, channels) from the file header only."""
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(path)
    if inp is None:
        raise AssetError(f"{path}: not a readable image ({oiio.geterror().strip()})")
    try:
        spec = inp.spec()
        return spec.width, spec.height, spec.nchannels
    finally:
        inp.close()


def check_size(path: str, w: int, h: int) -> None:
    if min(w, h) < MIN_SIDE:
        raise AssetError(f"{path}: tiny image ({w}x{h}); need at least {MIN_SIDE} px on each side")


def alpha_of(img: np.ndarray, path: str, is_cutout: bool) -> np.ndarray:
    """The alpha channel of a cutout (RGBA or grey + alpha), or of a matte file (its alpha
    channel if it has one, else its first channel)."""
    c = img.shape[2]
    if is_cutout:
        if c not in (2, 4):
            raise AssetError(f"{path}: foreground without alpha ({c} channels; need RGBA or grey+alpha, "
                             f"or put it in fg/ with its matte in alpha/)")
        return img[:, :, c - 1]
    return img[:, :, c - 1] if c in (2, 4) else img[:, :, 0]


def alpha_bbox(alpha: np.ndarray, path: str) -> tuple[int, int, int, int]:
    """Refuse a non-finite or empty alpha; return the bbox (x, y, w, h) of alpha > 0."""
    if not np.all(np.isfinite(alpha)):
        raise AssetError(f"{path}: alpha contains NaN or inf")
    on = alpha > 0
    if not on.any():
        raise AssetError(f"{path}: empty alpha (fully transparent)")
    rows, cols = np.flatnonzero(on.any(axis=1)), np.flatnonzero(on.any(axis=0))
    return int(cols[0]), int(rows[0]), int(cols[-1] - cols[0] + 1), int(rows[-1] - rows[0] + 1)


THUMB = 64          # long side of an alpha thumbnail, px
CUT_ALPHA = 4 / 255  # a matte at least this opaque on a border of its photo goes on past it...
CUT_MIN = 4          # ...where that holds for at least this many pixels of the border line
SIDES = ("top", "bottom", "left", "right")


def cut_sides(alpha: np.ndarray) -> tuple[str, ...]:
    """The sides of the photo at which its matte is cut: where the matte is non-zero on its
    border line (alpha >= CUT_ALPHA, above matting noise of a few codes, on CUT_MIN pixels or
    more), opaque like a portrait cut at the chest or soft like hair strands or a veil that run
    off the photo. Such an object must touch the frame's edge there, never float."""
    on = np.asarray(alpha) >= CUT_ALPHA
    lines = {"top": on[0], "bottom": on[-1], "left": on[:, 0], "right": on[:, -1]}
    return tuple(k for k in SIDES if int(lines[k].sum()) >= CUT_MIN)


def area_thumb(alpha: np.ndarray, bbox: tuple[int, int, int, int]) -> np.ndarray:
    """The alpha inside `bbox` reduced by box means to a long side of at most THUMB px, uint8,
    in integer arithmetic (the same on every machine): what scene sampling estimates occlusion
    from."""
    x, y, w, h = bbox
    a = np.asarray(alpha)[y:y + h, x:x + w]
    a = np.rint(a * 255).astype(np.uint32) if a.dtype != np.uint8 else a.astype(np.uint32)
    f = max(w, h) / THUMB
    tw, th = (max(1, round(w / f)), max(1, round(h / f))) if f > 1 else (w, h)
    rows = (np.arange(th) * h) // th
    cols = (np.arange(tw) * w) // tw
    sums = np.add.reduceat(np.add.reduceat(a, rows, axis=0), cols, axis=1)
    counts = np.diff(np.append(rows, h))[:, None] * np.diff(np.append(cols, w))[None, :]
    return ((sums + counts // 2) // counts).astype(np.uint8)


def unit_alpha(a: np.ndarray) -> np.ndarray:
    """An alpha channel as float32 in [0, 1] (uint8 codes / 255)."""
    return a.astype(np.float32) / 255.0 if a.dtype == np.uint8 else a


FLATTEN_ONTO = {"black": 0.0, "grey": srgb_to_linear(np.float32(0.5)).item(), "white": 1.0}


def background_alpha(img: np.ndarray, path: str, policy: str) -> np.ndarray | None:
    """A background's alpha in [0, 1] where it has transparent pixels, None where it has none
    (no alpha channel, or alpha 1 everywhere); with `policy` "bad" such a background is refused
    (it would show whatever its transparent pixels hold)."""
    c = img.shape[2]
    if c not in (2, 4):
        return None
    a = unit_alpha(img[:, :, c - 1])
    clear = a < 1
    if not clear.any():
        return None
    if policy == "bad":
        raise AssetError(f"{path}: a background with transparent pixels ({clear.mean():.1%} of it has alpha < 1); "
                         "make it opaque, or set assets.transparent_background to black, grey or white to flatten it")
    return np.clip(a, 0.0, 1.0)


def flatten(rgb: np.ndarray, img: np.ndarray, path: str, policy: str) -> np.ndarray:
    """A background's colour with its transparency dealt with (`background_alpha`): as it is
    when opaque, else composited onto black, grey or white (`policy`)."""
    a = background_alpha(img, path, policy)
    if a is None:
        return rgb
    return (rgb * a[..., None] + np.float32(FLATTEN_ONTO[policy]) * (1 - a[..., None])).astype(np.float32)


def colour_linear(img: np.ndarray, path: str) -> np.ndarray:
    """The colour channels of decoded pixels as linear-light RGB float32 (grey replicated)."""
    c = img.shape[2]
    colour = img[:, :, :1] if c in (1, 2) else img[:, :, :3]
    if colour.shape[2] == 1:
        colour = np.repeat(colour, 3, axis=2)
    if colour.dtype == np.uint8:
        return srgb8_to_linear(colour)
    if is_exr(path):
        return np.clip(colour, 0.0, None).astype(np.float32)
    return srgb_to_linear(colour)
