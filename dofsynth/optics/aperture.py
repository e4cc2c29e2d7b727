"""Aperture shapes, one registry of kinds.

An aperture is a convex shape of unit size centred on 0 (in units of the CoC radius, x to the
right, y down the image rows); its blur kernel for a signed radius is made in
dofsynth.optics.kernel. Every kind is one class here with `@register`: the recipe's
`render.aperture.kind`, the sample record (`to_dict` / `aperture_from_dict`), the command
line (`parse_aperture`: "disk", "polygon:N[:ROT]") and scene sampling (`from_rules`) all
consult `APERTURES`, so a new shape is one class.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from dofsynth.rng import draw_uniform

APERTURES: dict[str, type["Aperture"]] = {}


def register(cls):
    """Class decorator: add an aperture kind to `APERTURES` under its `kind`."""
    APERTURES[cls.kind] = cls
    return cls


class Aperture:
    """Base of the aperture kinds. A kind defines `kind`, the geometry (`chord`, `x_extent`,
    `area`, `contains`), its record form (`to_dict`, `from_params`), its command-line form
    (`parse(args)`) and how a scene draws it from the recipe (`from_rules(rules, rng)`)."""

    kind: ClassVar[str] = ""
    mirrored: ClassVar[bool] = False  # whether the unit shape is its own mirror image in x and in y

    def to_dict(self) -> dict:
        return {"kind": self.kind}

    @classmethod
    def from_params(cls, d: dict) -> "Aperture":
        return cls()

    @classmethod
    def parse(cls, args: list[str]) -> "Aperture":
        if args:
            raise ValueError(f"{cls.kind} takes no parameters")
        return cls()

    @classmethod
    def from_rules(cls, rules, rng: np.random.Generator) -> "Aperture":
        """The aperture of one scene from the recipe's [render.aperture] rules."""
        return cls()

    def chord(self, x: np.ndarray, r: float) -> tuple[np.ndarray, np.ndarray]:
        """Vertical extent [ylo, yhi] of the shape of radius r (pixels) at abscissae x."""
        raise NotImplementedError

    def x_extent(self, r: float) -> tuple[float, float]:
        raise NotImplementedError

    def area(self, radius: float) -> float:
        raise NotImplementedError

    def contains(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Points (in units of the radius) inside the unit shape."""
        raise NotImplementedError


@register
@dataclass(frozen=True)
class Disk(Aperture):
    """A circular aperture; `radius` arguments are the disc radius in pixels."""

    kind: ClassVar[str] = "disk"
    mirrored: ClassVar[bool] = True

    def chord(self, x, r):
        h = np.sqrt(np.maximum(r * r - x * x, 0.0))
        return -h, h

    def x_extent(self, r):
        return -r, r

    def area(self, radius):
        return math.pi * float(radius) ** 2

    def contains(self, x, y):
        return x * x + y * y <= 1.0


@register
@dataclass(frozen=True)
class Polygon(Aperture):
    """A regular polygon aperture of `blades` sides; `rotation` in degrees turns the first vertex
    counter-clockwise from the +x axis (y pointing down the image rows). `radius` arguments are
    the circumradius in pixels."""

    kind: ClassVar[str] = "polygon"
    blades: int = 6
    rotation: float = 0.0

    def __post_init__(self):
        if int(self.blades) != self.blades or self.blades < 3:
            raise ValueError(f"aperture blades must be an integer >= 3, got {self.blades}")
        if not math.isfinite(self.rotation):
            raise ValueError(f"aperture rotation must be finite, got {self.rotation}")
        object.__setattr__(self, "blades", int(self.blades))
        object.__setattr__(self, "rotation", float(self.rotation))

    def to_dict(self) -> dict:
        return {"kind": "polygon", "blades": self.blades, "rotation": self.rotation}

    @classmethod
    def from_params(cls, d):
        return cls(blades=int(d.get("blades", 6)), rotation=float(d.get("rotation", 0.0)))

    @classmethod
    def parse(cls, args):
        if not 1 <= len(args) <= 2:
            raise ValueError("polygon takes N or N:ROTATION_DEGREES")
        return cls(blades=int(args[0]), rotation=float(args[1]) if len(args) == 2 else 0.0)

    @classmethod
    def from_rules(cls, rules, rng):
        return cls(blades=rules.blades, rotation=draw_uniform(rng, *rules.rotation))

    def _halfplanes(self):
        """Unit edge normals (nx, ny) and the apothem of the unit-circumradius polygon."""
        n = self.blades
        ang = math.radians(self.rotation) + math.pi / n + 2 * math.pi * np.arange(n) / n
        return np.cos(ang), np.sin(ang), math.cos(math.pi / n)

    def chord(self, x, r):
        nx, ny, apo = self._halfplanes()
        lo = np.full(x.shape, -np.inf)
        hi = np.full(x.shape, np.inf)
        for a, b in zip(nx, ny):
            rhs = apo * r - a * x  # constraint b * y <= rhs
            if abs(b) < 1e-12:
                hi = np.where(rhs < 0, -np.inf, hi)
            elif b > 0:
                hi = np.minimum(hi, rhs / b)
            else:
                lo = np.maximum(lo, rhs / b)
        return lo, hi

    def x_extent(self, r):
        n = self.blades
        xs = r * np.cos(math.radians(self.rotation) + 2 * math.pi * np.arange(n) / n)
        return float(xs.min()), float(xs.max())

    def area(self, radius):
        n = self.blades
        return 0.5 * n * float(radius) ** 2 * math.sin(2 * math.pi / n)

    def contains(self, x, y):
        nx, ny, apo = self._halfplanes()
        inside = np.ones(np.broadcast(x, y).shape, dtype=bool)
        for a, b in zip(nx, ny):
            inside &= a * x + b * y <= apo + 1e-12
        return inside


def cat_eye_offset(shape: tuple[int, int], strength: float, gy=None, gx=None, margin: int = 0):
    """(oy, ox): the centre of the vignetting circle, in units of the aperture radius, at pixel
    rows gy / columns gx (default: every pixel) of planes of `shape`: `strength` times the
    position relative to the centre over the frame's half-diagonal (so |offset| = strength at
    the frame's corners, 0 at its centre); the frame is `shape` less `margin` px on each side."""
    h, w = shape
    if gy is None:
        gy, gx = np.mgrid[0:h, 0:w].astype(np.float64)
    half = 0.5 * math.hypot(h - 1 - 2 * margin, w - 1 - 2 * margin) or 1.0
    return strength * (gy - (h - 1) / 2) / half, strength * (gx - (w - 1) / 2) / half


def _kinds() -> str:
    return ", ".join(repr(k) for k in APERTURES)


def aperture_from_dict(d: dict) -> Aperture:
    """Inverse of `to_dict`: {"kind": "disk"} or {"kind": "polygon", "blades": N, "rotation": deg}."""
    cls = APERTURES.get(d.get("kind")) if isinstance(d, dict) else None
    if cls is None:
        raise ValueError(f"aperture: unknown aperture {d!r} (want kind {_kinds()})")
    return cls.from_params(d)


def parse_aperture(text: str) -> Aperture:
    """Parse the command-line form KIND[:PARAM...]: `disk`, `polygon:N` or `polygon:N:ROTATION_DEGREES`."""
    kind, *args = text.strip().lower().split(":")
    if kind not in APERTURES:
        raise ValueError(f"--aperture: {text!r} is not disk, polygon:N or polygon:N:ROT (kinds: {_kinds()})")
    try:
        return APERTURES[kind].parse(args)
    except ValueError as exc:
        raise ValueError(f"--aperture: {text!r}: {exc}") from exc
