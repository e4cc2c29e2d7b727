"""The sample record's schema and the pixel checks of one decoded sample (docs/FORMAT.md):
`check_record_schema(record)` and `check_pixels(sample)` return lists of problems.

The disparity map must agree with the record: opaque front/middle pixels carry that plane's
disparity within DEPTH_TOL, bare background pixels the flat value or the recomputed ramp
within RAMP_TOL.
"""
from __future__ import annotations

import math

import numpy as np

from dofsynth.assets.decode import SIDES
from dofsynth.compose import COVER_THRESHOLD
from dofsynth.optics.aperture import APERTURES
from dofsynth.codecs import SCHEMA_VERSION
from dofsynth.render.planes import background_disparity

DEPTH_TOL = 1e-6
RAMP_TOL = 1e-5
ROLES = ("background", "front", "middle")


_NUM = (int, float)


def _is_num(v) -> bool:
    return isinstance(v, _NUM) and not isinstance(v, bool) and math.isfinite(v)


def _is_int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _unit(v) -> bool:
    return _is_num(v) and 0.0 <= v <= 1.0


def check_record_schema(rec) -> list[str]:
    """Problems with a record's keys, types and value ranges (docs/FORMAT.md)."""
    if not isinstance(rec, dict):
        return ["record is not a JSON object"]
    errs: list[str] = []

    def want(obj, name, pred, what, prefix=""):
        if not isinstance(obj, dict) or name not in obj:
            errs.append(f"missing key {prefix}{name}")
            return False
        if not pred(obj[name]):
            errs.append(f"{prefix}{name} must be {what}, got {obj[name]!r}")
            return False
        return True

    want(rec, "schema_version", lambda v: v == SCHEMA_VERSION, str(SCHEMA_VERSION))
    want(rec, "key", lambda v: isinstance(v, str) and "." not in v, "a string without dots")
    want(rec, "split", lambda v: isinstance(v, str), "a string")
    want(rec, "index", lambda v: _is_int(v) and v >= 0, "an integer >= 0")
    want(rec, "seed", lambda v: isinstance(v, list) and v and all(_is_int(x) and x >= 0 for x in v),
         "a list of integers >= 0")
    want(rec, "size", lambda v: isinstance(v, list) and len(v) == 2 and all(_is_int(x) and x > 0 for x in v),
         "[H, W] positive integers")
    if want(rec, "assets", lambda v: isinstance(v, dict), "an object"):
        for role in ROLES:
            p = f"assets.{role}."
            if want(rec["assets"], role, lambda v: isinstance(v, dict), "an object", "assets."):
                a = rec["assets"][role]
                want(a, "id", lambda v: isinstance(v, str) and v, "a non-empty string", p)
                want(a, "sha256", lambda v: isinstance(v, str) and len(v) == 64, "a hex sha256", p)
                want(a, "path", lambda v: isinstance(v, str), "a string", p)
                want(a, "colour", lambda v: v == "file" or (isinstance(v, str) and v.startswith("estimated:")),
                     "'file' or 'estimated:<estimator>'", p)
    if want(rec, "background", lambda v: isinstance(v, dict), "an object"):
        b, p = rec["background"], "background."
        want(b, "mode", lambda v: v in ("flat", "ramp"), "'flat' or 'ramp'", p)
        want(b, "b0", _unit, "a number in [0, 1]", p)
        want(b, "b1", _unit, "a number in [0, 1]", p)
        want(b, "direction", lambda v: v in ("horizontal", "vertical", None), "'horizontal', 'vertical' or null", p)
        want(b, "crop", lambda v: isinstance(v, list) and len(v) == 4 and all(_is_num(x) for x in v),
             "[x, y, w, h]", p)
        want(b, "flip", lambda v: isinstance(v, bool), "a boolean", p)
        if b.get("mode") == "ramp" and b.get("direction") is None:
            errs.append("background.direction must be set for a ramp")
    for role in ("front", "middle"):
        if want(rec, role, lambda v: isinstance(v, dict), "an object"):
            o, p = rec[role], f"{role}."
            want(o, "disparity", _unit, "a number in [0, 1]", p)
            want(o, "scale", lambda v: _is_num(v) and v > 0, "a number > 0", p)
            want(o, "x", _is_num, "a number", p)
            want(o, "y", _is_num, "a number", p)
            want(o, "flip", lambda v: isinstance(v, bool), "a boolean", p)
            want(o, "anchored", lambda v: isinstance(v, list) and set(v) <= set(SIDES) and len(set(v)) == len(v),
                 "a list of distinct sides (top, bottom, left, right)", p)
            want(o, "visible", _unit, "a number in [0, 1]", p)
            want(o, "rejected", lambda v: isinstance(v, list) and all(isinstance(x, str) for x in v),
                 "a list of asset ids", p)
    if want(rec, "targets", lambda v: isinstance(v, list) and len(v) > 0, "a non-empty list"):
        for i, t in enumerate(rec["targets"]):
            p = f"targets[{i}]."
            if not isinstance(t, dict):
                errs.append(f"targets[{i}] must be an object")
                continue
            want(t, "focus", _unit, "a number in [0, 1]", p)
            want(t, "max_coc", lambda v: _is_num(v) and v >= 0, "a number >= 0", p)
    if want(rec, "aperture", lambda v: isinstance(v, dict), "an object"):
        ap = rec["aperture"]
        if want(ap, "kind", lambda v: v in APERTURES, " or ".join(map(repr, APERTURES)), "aperture."):
            if ap["kind"] == "polygon":
                want(ap, "blades", lambda v: _is_int(v) and v >= 3, "an integer >= 3", "aperture.")
                want(ap, "rotation", _is_num, "a number", "aperture.")
    want(rec, "options", lambda v: isinstance(v, dict), "an object")
    want(rec, "excluded", lambda v: isinstance(v, list) and all(isinstance(x, str) for x in v), "a list of asset ids")
    want(rec, "renderer", lambda v: isinstance(v, str), "a string")
    want(rec, "dofsynth_version", lambda v: isinstance(v, str), "a string")
    return errs


# ---------------------------------------------------------------- pixels
def expected_background(bg: dict, shape: tuple[int, int]) -> np.ndarray:
    """The background plane's disparity map recomputed from the record's `background` block
    with the generator's own `render.planes.background_disparity` (flat: b0 everywhere; horizontal
    ramp: b0 at the left column to b1 at the right; vertical: b0 at the bottom row to b1 at
    the top)."""
    h, w = shape
    return background_disparity(bg["mode"], float(bg["b0"]), float(bg["b1"]), bg.get("direction"), h, w)


# a stored cover <= CLEAR certainly lies below the compositor's coverage threshold and one
# >= OPAQUE certainly above (8-bit quantisation is 1/510 either way)
CLEAR, OPAQUE = COVER_THRESHOLD - 0.01, COVER_THRESHOLD + 0.01


def check_pixels(sample: dict) -> list[str]:
    """Problems with a decoded sample's arrays against its (schema-valid) record."""
    rec, errs = sample["record"], []
    h, w = rec["size"]
    arrays = [("aif.png", sample["aif"]), ("depth.exr", sample["depth"]), ("cover.png", sample["cover"])]
    arrays += [(f"dof.{i}.png", d) for i, d in enumerate(sample["dof"])]
    for name, arr in arrays:
        if arr.shape[:2] != (h, w):
            errs.append(f"{name} is {arr.shape[1]}x{arr.shape[0]}, the record says {w}x{h}")
    if len(sample["dof"]) != len(rec["targets"]):
        errs.append(f"{len(sample['dof'])} DoF images for {len(rec['targets'])} targets")
    if errs:
        return errs
    depth = sample["depth"]
    if not np.all(np.isfinite(depth)):
        return [f"depth.exr has {int(np.sum(~np.isfinite(depth)))} NaN/inf pixels"]
    if depth.min() < 0 or depth.max() > 1:
        errs.append(f"depth.exr values outside [0, 1]: [{depth.min():.6g}, {depth.max():.6g}]")
    front, middle = sample["cover"][:, :, 0], sample["cover"][:, :, 1]
    f0, f1 = float(rec["front"]["disparity"]), float(rec["middle"]["disparity"])
    regions = [
        ("front", front >= OPAQUE, np.float32(f0), DEPTH_TOL),
        ("middle", (front <= CLEAR) & (middle >= OPAQUE), np.float32(f1), DEPTH_TOL),
    ]
    bare = (front <= CLEAR) & (middle <= CLEAR)
    bg = expected_background(rec["background"], (h, w))
    regions.append((f"{rec['background']['mode']} background", bare, bg, RAMP_TOL))
    for label, mask, want, tol in regions:
        if not mask.any():
            continue
        want_px = want[mask] if np.ndim(want) else np.full(int(mask.sum()), want, np.float32)
        err = np.abs(depth[mask].astype(np.float64) - want_px.astype(np.float64))
        bad = err > tol
        if bad.any():
            ys, xs = np.nonzero(mask)
            j = int(np.argmax(err))
            errs.append(f"depth disagrees with the record on {int(bad.sum())} {label} pixels "
                        f"(worst at x={xs[j]}, y={ys[j]}: {depth[ys[j], xs[j]]:.6g}, expected "
                        f"{float(want_px[j]):.6g})")
    return errs
