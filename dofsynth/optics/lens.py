"""A thin lens behind a target: focal length, f-number, focus distance and sensor width, mapped
to dofsynth's two numbers (the focus disparity and max_coc).

The scene's depth range maps distance s to normalized disparity linearly in 1/s:
d = (1/s - 1/far) / (1/near - 1/far) (1 at `near`, 0 at `far`, which may be infinity). A thin
lens of focal length f and aperture diameter A = f / N focused at S images a point at s as a
disc of diameter A * f / (S - f) * |s - S| / s on the sensor (the standard circle-of-confusion
formula). In pixels of an image `width_px` wide on a sensor `sensor_width_mm` wide, its signed
radius is

    c = max_coc * (d - focus),  max_coc = (width_px / sensor_width_mm) * (A / 2) * f * S / (S - f)
                                          * (1/near - 1/far),   focus = d(S),

lengths in mm (1/near - 1/far in 1/mm), > 0 in front of the focal plane. So the renderer's
`c = max_coc * (d - focus)` is exactly a thin lens.
"""
from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True)
class ThinLens:
    focal_length_mm: float
    f_number: float
    sensor_width_mm: float = 36.0   # full frame
    near_m: float = 1.0              # the distance of disparity 1
    far_m: float = math.inf          # the distance of disparity 0

    def __post_init__(self):
        for name in ("focal_length_mm", "f_number", "sensor_width_mm", "near_m"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be a positive number, got {v}")
        if not self.far_m > self.near_m:
            raise ValueError(f"far_m must exceed near_m ({self.near_m}), got {self.far_m}")
        if self.near_m * 1000.0 <= self.focal_length_mm:
            raise ValueError(f"near_m {self.near_m} m is inside the focal length {self.focal_length_mm} mm")

    def _span(self) -> float:
        """1/near - 1/far, in 1/mm."""
        return 1.0 / (self.near_m * 1000.0) - (0.0 if math.isinf(self.far_m) else 1.0 / (self.far_m * 1000.0))

    def disparity(self, distance_m: float) -> float:
        """Normalized disparity of a distance (m) in the scene's range."""
        inv_far = 0.0 if math.isinf(self.far_m) else 1.0 / (self.far_m * 1000.0)
        return (1.0 / (distance_m * 1000.0) - inv_far) / self._span()

    def distance(self, disparity: float) -> float:
        """Distance (m) of a normalized disparity (inf at 0 when far is infinite)."""
        inv_far = 0.0 if math.isinf(self.far_m) else 1.0 / (self.far_m * 1000.0)
        inv = inv_far + float(disparity) * self._span()
        return math.inf if inv <= 0 else 1.0 / inv / 1000.0

    def max_coc(self, focus_distance_m: float, width_px: int) -> float:
        """CoC radius (px at `width_px`) at |disparity - focus| = 1 when focused at that distance."""
        f, s = self.focal_length_mm, focus_distance_m * 1000.0
        if not s > f:
            raise ValueError(f"focus distance {focus_distance_m} m is inside the focal length {f} mm")
        aperture = f / self.f_number
        focus_term = 1.0 if math.isinf(s) else s / (s - f)
        return (width_px / self.sensor_width_mm) * (aperture / 2.0) * f * focus_term * self._span()

    def target(self, focus_distance_m: float, width_px: int) -> tuple[float, float]:
        """(focus disparity, max_coc px) of a target focused at `focus_distance_m`."""
        return self.disparity(focus_distance_m), self.max_coc(focus_distance_m, width_px)

    def to_dict(self, focus_distance_m: float) -> dict:
        """The record's `lens` block of a target: numbers only (one JSON type in every record),
        an infinite distance written as 0, as the recipe's `far_m = 0` means infinity."""
        return {"focal_length_mm": self.focal_length_mm, "f_number": self.f_number,
                "sensor_width_mm": self.sensor_width_mm, "near_m": self.near_m,
                "far_m": 0.0 if math.isinf(self.far_m) else self.far_m,
                "focus_distance_m": 0.0 if math.isinf(focus_distance_m) else focus_distance_m}
