"""The sample record's schema and the pixel checks of one decoded sample (docs/FORMAT.md):
`check_record_schema(record)` (the shipped JSON Schema, validated with `jsonschema`) and
`check_pixels(sample)` return lists of problems.

The disparity map must agree with the record: opaque front/middle pixels carry that plane's
disparity within DEPTH_TOL, bare background pixels the flat value or the recomputed ramp
within RAMP_TOL.
"""
from __future__ import annotations

import math
from functools import lru_cache

import jsonschema
import numpy as np

from dofsynth.codecs import SCHEMA_VERSION
from dofsynth.compose import COVER_THRESHOLD
from dofsynth.optics.aperture import APERTURES
from dofsynth.record import record_schema
from dofsynth.render.planes import background_disparity

DEPTH_TOL = 1e-6
RAMP_TOL = 1e-5


def _path(error) -> str:
    parts = [f"[{p}]" if isinstance(p, int) else f".{p}" for p in error.absolute_path]
    return "".join(parts).lstrip(".") or "record"


@lru_cache(maxsize=1)
def _validator():
    schema = record_schema()
    return jsonschema.Draft202012Validator(schema)


def _non_finite(obj, where: str = "") -> list[str]:
    """Paths of NaN / inf numbers (Python's json reads them; JSON Schema's bounds let NaN by)."""
    if isinstance(obj, dict):
        return [p for k, v in obj.items() for p in _non_finite(v, f"{where}.{k}" if where else str(k))]
    if isinstance(obj, list):
        return [p for i, v in enumerate(obj) for p in _non_finite(v, f"{where}[{i}]")]
    return [where] if isinstance(obj, float) and not math.isfinite(obj) else []


def check_record_schema(rec) -> list[str]:
    """Problems with a record against its JSON Schema (dofsynth/record.schema.json: keys, one
    JSON type per field, value ranges), then what a schema cannot say: numbers are finite, a
    ramp has a direction, the aperture is a registered kind."""
    made = rec.get("schema_version") if isinstance(rec, dict) else None
    if isinstance(made, int) and not isinstance(made, bool) and made < SCHEMA_VERSION:
        return [f"schema_version {made}: made by an older dofsynth; this one checks schema {SCHEMA_VERSION} "
                "(docs/FORMAT.md says what changed; such records still read and re-render)"]
    errs = [f"{_path(e)}: {e.message}" for e in sorted(_validator().iter_errors(rec), key=lambda e: list(e.absolute_path))]
    errs += [f"{p}: must be a finite number" for p in _non_finite(rec)]
    if errs or not isinstance(rec, dict):
        return errs
    if rec["background"]["mode"] == "ramp" and rec["background"]["direction"] == "none":
        errs.append("background.direction must be horizontal or vertical for a ramp")
    if rec["aperture"]["kind"] not in APERTURES:
        errs.append(f"aperture.kind must be one of {', '.join(APERTURES)}, got {rec['aperture']['kind']!r}")
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
