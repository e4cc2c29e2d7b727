"""Aperture shapes and their anti-aliased blur kernels (point-spread functions).

A kernel of signed radius `c` (pixels) is the image of a point light on the sensor: the aperture
shape scaled by `|c|`, each pixel weighted by the area of the shape inside it, normalized to sum
1. For `c < 0` the shape is point-reflected (matters only for odd-bladed polygons). The kernel
grows continuously with `|c|`; a radius below half a pixel is the identity (the whole shape lies
inside the centre pixel). `Polygon`'s radius is its circumradius (centre-to-vertex distance).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

# Sub-samples per pixel column for the midpoint rule along x; y is integrated exactly.
X_SUBSAMPLES = 64


def support_radius(radius: float) -> int:
    """Half-size in pixels of the kernel array for a shape of circumradius |radius| (pixels)."""
    r = abs(float(radius))
    return 0 if r < 0.5 else int(math.ceil(r - 0.5))


@dataclass(frozen=True)
class Disk:
    """A circular aperture; `radius` arguments are the disc radius in pixels."""

    def to_dict(self) -> dict:
        return {"kind": "disk"}

    def _halfplanes(self):
        return None

    def chord(self, x: np.ndarray, r: float) -> tuple[np.ndarray, np.ndarray]:
        """Vertical extent [ylo, yhi] of the shape of radius r (pixels) at abscissae x."""
        h = np.sqrt(np.maximum(r * r - x * x, 0.0))
        return -h, h

    def x_extent(self, r: float) -> tuple[float, float]:
        return -r, r

    def area(self, radius: float) -> float:
        return math.pi * float(radius) ** 2

    def coverage(self, radius: float) -> np.ndarray:
        return coverage(self, radius)

    def kernel(self, signed_radius: float) -> np.ndarray:
        return kernel(self, signed_radius)

    def contains(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Points (in units of the radius) inside the unit shape."""
        return x * x + y * y <= 1.0


@dataclass(frozen=True)
class Polygon:
    """A regular polygon aperture of `blades` sides; `rotation` in degrees turns the first vertex
    counter-clockwise from the +x axis (y pointing down the image rows). `radius` arguments are
    the circumradius in pixels."""

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

    def _halfplanes(self):
        """Unit edge normals (nx, ny) and the apothem of the unit-circumradius polygon."""
        n = self.blades
        ang = math.radians(self.rotation) + math.pi / n + 2 * math.pi * np.arange(n) / n
        return np.cos(ang), np.sin(ang), math.cos(math.pi / n)

    def chord(self, x: np.ndarray, r: float) -> tuple[np.ndarray, np.ndarray]:
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

    def x_extent(self, r: float) -> tuple[float, float]:
        n = self.blades
        xs = r * np.cos(math.radians(self.rotation) + 2 * math.pi * np.arange(n) / n)
        return float(xs.min()), float(xs.max())

    def area(self, radius: float) -> float:
        n = self.blades
        return 0.5 * n * float(radius) ** 2 * math.sin(2 * math.pi / n)

    def coverage(self, radius: float) -> np.ndarray:
        return coverage(self, radius)

    def kernel(self, signed_radius: float) -> np.ndarray:
        return kernel(self, signed_radius)

    def contains(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        nx, ny, apo = self._halfplanes()
        inside = np.ones(np.broadcast(x, y).shape, dtype=bool)
        for a, b in zip(nx, ny):
            inside &= a * x + b * y <= apo + 1e-12
        return inside


Aperture = Disk | Polygon


def from_dict(d: dict) -> Aperture:
    """Inverse of `to_dict`: {"kind": "disk"} or {"kind": "polygon", "blades": N, "rotation": deg}."""
    kind = d.get("kind") if isinstance(d, dict) else None
    if kind == "disk":
        return Disk()
    if kind == "polygon":
        return Polygon(blades=int(d.get("blades", 6)), rotation=float(d.get("rotation", 0.0)))
    raise ValueError(f"aperture: unknown aperture {d!r} (want kind 'disk' or 'polygon')")


Disk.from_dict = staticmethod(from_dict)
Polygon.from_dict = staticmethod(from_dict)


def parse_aperture(text: str) -> Aperture:
    """Parse the CLI form `disk`, `polygon:N` or `polygon:N:ROTATION_DEGREES`."""
    parts = text.strip().lower().split(":")
    try:
        if parts == ["disk"]:
            return Disk()
        if parts[0] == "polygon" and 2 <= len(parts) <= 3:
            return Polygon(blades=int(parts[1]), rotation=float(parts[2]) if len(parts) == 3 else 0.0)
    except ValueError as exc:
        raise ValueError(f"--aperture: {text!r}: {exc}") from exc
    raise ValueError(f"--aperture: {text!r} is not disk, polygon:N or polygon:N:ROT")


def coverage(aperture: Aperture, radius: float) -> np.ndarray:
    """Area (pixels^2) of the shape of radius |radius| inside each pixel, float64 (2S+1, 2S+1).

    Pixel (i, j) spans [j-S-0.5, j-S+0.5] x [i-S-0.5, i-S+0.5] around the shape's centre. Each
    column is integrated with the midpoint rule over X_SUBSAMPLES vertical chords, each chord
    clipped to the pixel rows exactly, so the result is continuous in the radius. Unnormalized:
    it sums to the shape's area (relative error below 1e-4 for radii above 1 px).
    """
    r = abs(float(radius))
    s = support_radius(r)
    n = 2 * s + 1
    if r == 0.0:
        out = np.zeros((n, n))
        return out
    # Sub-columns clipped to the shape's x-extent, each sampled at its clipped midpoint: exact
    # for straight edges between kinks (vertical edges included) and continuous in r.
    xmin, xmax = aperture.x_extent(r)
    cells = np.clip(np.arange(n * X_SUBSAMPLES + 1) / X_SUBSAMPLES - s - 0.5, xmin, xmax)
    width = np.diff(cells)
    lo, hi = aperture.chord(0.5 * (cells[1:] + cells[:-1]), r)
    on = width > 0  # sub-columns outside the shape: no chord (and no inf * 0)
    lo = np.where(on, lo, 0.0)
    hi = np.where(on, np.maximum(hi, lo), 0.0)
    # The chord [lo, hi] below pixel edge y_i has length clip(y_i, lo, hi) - lo, so pixel row i
    # gets H(y_{i+1}) - H(y_i), H(y) = sum over the column's sub-columns of width * clip(y, lo, hi)
    # = width * (lo + [lo < y] (y - lo) - [hi < y] (y - hi)). The sums over "v < y_i" come from one
    # bincount per column and a cumulative sum over the edges: O(n * X_SUBSAMPLES + n^2) work.
    column = np.repeat(np.arange(n), X_SUBSAMPLES)
    edges = np.arange(n + 1) - s - 0.5

    def below(v):  # per (column, edge i): sum of width and of width * v over sub-columns with v < y_i
        first = np.clip(np.floor(v + s + 0.5).astype(np.int64) + 1, 0, n + 1)  # first edge above v
        at = column * (n + 2) + first
        w_sum = np.bincount(at, width, n * (n + 2)).reshape(n, n + 2).cumsum(axis=1)[:, : n + 1]
        wv_sum = np.bincount(at, width * v, n * (n + 2)).reshape(n, n + 2).cumsum(axis=1)[:, : n + 1]
        return w_sum, wv_sum

    w_lo, wv_lo = below(lo)
    w_hi, wv_hi = below(hi)
    h = edges[None, :] * (w_lo - w_hi) - wv_lo + wv_hi  # H(y_i) less the constant sum of width * lo
    return np.diff(h, axis=1).T


@lru_cache(maxsize=512)
def _kernel_cached(aperture: Aperture, signed_radius: float) -> np.ndarray:
    if abs(signed_radius) < 0.5:
        k = np.ones((1, 1), dtype=np.float32)
    else:
        cov = coverage(aperture, signed_radius)
        k = (cov / cov.sum()).astype(np.float32)
        if signed_radius < 0:
            k = np.ascontiguousarray(k[::-1, ::-1])
    k.setflags(write=False)
    return k


def kernel(aperture: Aperture, signed_radius: float) -> np.ndarray:
    """Normalized float32 kernel (sums to 1) for a signed CoC radius in pixels (read-only array).

    The array is (2S+1, 2S+1) with S = support_radius; its centre is the point's own pixel. For a
    negative radius it is the point reflection of the positive one. Cached on the exact float.
    """
    r = float(signed_radius)
    if not math.isfinite(r):
        raise ValueError(f"signed_radius must be finite, got {signed_radius}")
    return _kernel_cached(aperture, r)
