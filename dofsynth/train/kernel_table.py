"""[model] kernel_prior = "discs": the lens-blur network's per-pixel kernel started as a disc blur.

The paper's lens-blur module renders L_i = sum_j K_j F_ij, its kernel K predicted from the image
and the signed disparity s (dofsynth.train.models.LensBlurNet). Trained for minutes, K does not
learn to pick the blur that s asks for (docs/training.md). With this prior K = U(A, s) + T(s):
T is a learned table of c weights per knot of s (33 knots over [-1, 1], linear between them,
constant beyond), started at the weights that make sum_j T_j(s) F_j the disc blur of radius
|s| * px_per_s px; the U-Net's head starts at zero. So the untrained module is a disc-blur
renderer from the given depth, and training learns where to depart from it.

The weights are fitted once, when the model is built, for its own features (they must be
linear then: feat_init = "blur"): least squares with sum w = 1 (a flat image stays flat), on
an image of 1/f noise, which has the spectrum of natural images. On a photo the fitted mix is
within 40-46 dB of the disc blur for radii of 0.5-18 px (dilations 1-8, 8 maps each).
"""
from __future__ import annotations

import cv2
import numpy as np
import torch
from torch import nn

from dofsynth.optics.aperture import Disk
from dofsynth.optics.kernel import kernel

KNOTS = 33  # over s in [-1, 1]: a knot every 1/16 of the largest blur
NOISE_SIDE, NOISE_MARGIN = 192, 24  # the fitting image (px) and what is left out at its border
RIDGE = 1e-6  # relative to the mean diagonal of the normal equations


def pink_noise(side: int, rng: np.random.Generator) -> np.ndarray:
    """(side, side) float32 noise in [0, 1] with a 1/f amplitude spectrum, as natural images have."""
    fy, fx = np.meshgrid(np.fft.fftfreq(side), np.fft.fftfreq(side), indexing="ij")
    amplitude = 1.0 / np.maximum(np.hypot(fy, fx), 1.0 / side)
    x = np.real(np.fft.ifft2(np.fft.fft2(rng.standard_normal((side, side))) * amplitude))
    return ((x - x.min()) / (x.max() - x.min())).astype(np.float32)


@torch.no_grad()
def disc_weights(features: nn.Module, radii: np.ndarray) -> np.ndarray:
    """(len(radii), c) float32: for each radius (px), the weights w (sum 1) that make
    sum_j w_j F_j closest to the disc blur of that radius, F = `features` ((B, 3, H, W) ->
    (B, 3, c, H, W), each colour filtered alone) of 1/f noise; least squares with a small ridge."""
    noise = pink_noise(NOISE_SIDE, np.random.default_rng(0))
    feats = features(torch.from_numpy(noise)[None, None].repeat(1, 3, 1, 1))[0, 0].double().numpy()
    m = NOISE_MARGIN
    a = feats[:, m:-m, m:-m].reshape(feats.shape[0], -1).T       # (pixels, c)
    c = a.shape[1]
    gram = a.T @ a
    gram += RIDGE * np.trace(gram) / c * np.eye(c)
    kkt = np.block([[2 * gram, np.ones((c, 1))], [np.ones((1, c)), np.zeros((1, 1))]])
    out = np.empty((len(radii), c))
    for i, r in enumerate(radii):
        target = noise if r <= 0 else cv2.filter2D(noise, -1, kernel(Disk(), float(r)), borderType=cv2.BORDER_REPLICATE)
        rhs = np.concatenate([2 * a.T @ target[m:-m, m:-m].ravel().astype(np.float64), [1.0]])
        out[i] = np.linalg.solve(kkt, rhs)[:c]
    return out.astype(np.float32)


class KernelTable(nn.Module):
    """T(s): (B, 1, H, W) signed disparity -> (B, c, H, W) kernel weights, linear between KNOTS
    knots over s in [-1, 1] (constant beyond), started as `disc_weights` of radius |s| * px_per_s."""

    def __init__(self, features: nn.Module, px_per_s: float):
        super().__init__()
        if px_per_s <= 0:
            raise ValueError('[model] kernel_prior = "discs" needs the blur per unit of signed disparity: '
                             "model.coc_ref > 0 (training fills it in from the data) and [data] levels")
        s = np.linspace(-1.0, 1.0, KNOTS)
        self.table = nn.Parameter(torch.from_numpy(disc_weights(features, np.abs(s) * px_per_s)))

    def forward(self, signed: torch.Tensor) -> torch.Tensor:
        u = (signed[:, 0].clamp(-1.0, 1.0) + 1.0) * ((KNOTS - 1) / 2)   # knot coordinate, (B, H, W)
        i = u.detach().floor().clamp(max=KNOTS - 2)
        t = (u - i).unsqueeze(1)
        i = i.long()
        lo = self.table[i].permute(0, 3, 1, 2)                            # (B, c, H, W)
        hi = self.table[i + 1].permute(0, 3, 1, 2)
        return lo + t * (hi - lo)
