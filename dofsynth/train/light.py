"""[model] light = "boosted": the paper's lens-blur module run in the light the targets were blurred in.

The targets are rendered in linear light with near-white pixels highlight-boosted before the blur
and the boost inverted after it (dofsynth.render.highlight), so a blurred lamp becomes a bright
disc. A blur of the sRGB codes, which the paper's module makes, cannot do either: on the learning
benchmark's test split the classical renderer made that way is 2.6 dB (linear light) plus 4.3 dB
(the boost) further from the targets away from depth edges (docs/training.md). With this option
the module's input is decoded to linear light and boosted, and its output is un-boosted and
encoded back to sRGB:  L = encode(B^-1(lens(B(decode(A_lo)), s))).

Here B(x) = x g(m), m = max(R, G, B), g = 1 + gain * clip((m - T) / (1 - T), 0, 1) ** power, T
the linear value of the sRGB level `threshold`: the render's boost with its exact curve (the
render uses a 256-knot interpolant of it; on a photo the two differ by under 2e-5, tested).
B^-1 finds m from max(y) = m g(m) by bisection and differentiates through that root
implicitly. Beyond [0, 1] the sRGB encoding goes on as straight lines (slopes 12.92 below 0,
and its slope at 1 above it), so an out-of-range output still has a gradient toward its target.
"""
from __future__ import annotations

import torch
from torch import nn

BISECTIONS = 40  # halvings of [T, 1]: below float32's resolution


def srgb_decode(x: torch.Tensor) -> torch.Tensor:
    """IEC 61966-2-1 decoding of sRGB values, clipped to [0, 1] first."""
    x = x.clamp(0.0, 1.0)
    return torch.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)


def srgb_encode(x: torch.Tensor) -> torch.Tensor:
    """IEC 61966-2-1 encoding of linear values, continued as straight lines outside [0, 1]."""
    curve = 1.055 * x.clamp(0.0031308, 1.0) ** (1 / 2.4) - 0.055
    return torch.where(x <= 0.0031308, 12.92 * x, torch.where(x <= 1.0, curve, 1.0 + (1.055 / 2.4) * (x - 1.0)))


class BoostedLight(nn.Module):
    """`forward(lens, image, signed)` = encode(B^-1(lens(B(decode(image)), signed))) for sRGB
    images (B, 3, h, w); threshold (sRGB level), gain and power as the recipe's [render.highlight]."""

    def __init__(self, threshold: float = 0.9, gain: float = 4.0, power: float = 2.0):
        super().__init__()
        self.t = float(srgb_decode(torch.tensor(threshold, dtype=torch.float64)))
        self.gain, self.power = float(gain), float(power)

    def _s(self, m: torch.Tensor) -> torch.Tensor:
        return ((m - self.t) / (1.0 - self.t)).clamp(0.0, 1.0)

    def gain_of(self, m: torch.Tensor) -> torch.Tensor:
        """g(m), the factor of a pixel whose largest channel is m (linear)."""
        return 1.0 + self.gain * self._s(m) ** self.power

    def boost(self, x: torch.Tensor) -> torch.Tensor:
        return x * self.gain_of(x.amax(dim=1, keepdim=True))

    def unboost(self, y: torch.Tensor) -> torch.Tensor:
        """B^-1(y): m g(m) = max(y) solved for m (T <= m <= 1; below T and above 1 + gain it is
        linear), then y scaled by m / max(y); differentiable in y."""
        h = y.amax(dim=1, keepdim=True)
        top = 1.0 + self.gain
        with torch.no_grad():
            lo, hi = torch.full_like(h, self.t), torch.ones_like(h)
            for _ in range(BISECTIONS):
                mid = 0.5 * (lo + hi)
                below = mid * self.gain_of(mid) < h
                lo, hi = torch.where(below, mid, lo), torch.where(below, hi, mid)
            m0 = 0.5 * (lo + hi)
            dg = self.gain * self.power * self._s(m0).clamp_min(1e-12) ** (self.power - 1) / (1.0 - self.t)
            slope = self.gain_of(m0) + m0 * dg  # (m g(m))' at the root, >= 1
            f0 = m0 * self.gain_of(m0)
        m = m0 + (h - f0) / slope  # = m0 in value; d m / d h = 1 / (m g(m))'
        m = torch.where(h <= self.t, h, torch.where(h >= top, h / top, m))
        ratio = torch.where(h > self.t, m / torch.where(h > self.t, h, torch.ones_like(h)), torch.ones_like(h))
        return y * ratio

    def forward(self, lens: nn.Module, image: torch.Tensor, signed: torch.Tensor) -> torch.Tensor:
        return srgb_encode(self.unboost(lens(self.boost(srgb_decode(image)), signed)))
