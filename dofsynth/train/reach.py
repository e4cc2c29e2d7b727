"""Where the blur reaches, as masks of the signed disparity at full resolution: `untouched`,
the pixels no blur reaches (the networks' [model] identity keeps the input there, and
evaluation's "same" region), and `edge_weight`, the nearness of a depth edge (the hybrid's
[model] gate = "edges"). Shapes (B, 1, H, W); `signed` as in dofsynth.train.models, its CoC
`signed * coc_px` px."""
from __future__ import annotations

import math

import cv2
import numpy as np
import torch
import torch.nn.functional as F


def _spread_reach(reach: torch.Tensor, steps: int) -> torch.Tensor:
    """`steps` times reach = max(reach, its 3 x 3 maximum - 1) ((B, 1, h, w) float32): on the
    CPU by cv2.dilate in place (20-30x faster than max_pool2d there), else by max_pool2d; the
    same values (a maximum and a subtraction of 1, exact in float32)."""
    if steps <= 0:
        return reach
    if reach.device.type != "cpu":
        for _ in range(steps):
            reach = torch.maximum(reach, F.max_pool2d(reach, 3, stride=1, padding=1) - 1.0)
        return reach
    out = reach.detach().to(torch.float32).contiguous().clone()
    box = np.ones((3, 3), np.uint8)
    for plane in out.numpy().reshape(-1, *out.shape[-2:]):
        grown = np.empty_like(plane)
        for _ in range(steps):
            cv2.dilate(plane, box, dst=grown)  # outside the frame counts as nothing (its default border)
            grown -= 1.0
            np.maximum(plane, grown, out=plane)
    return out


@torch.no_grad()
def untouched(signed: torch.Tensor, coc_px: float) -> torch.Tensor:
    """(B, 1, H, W) bool: the pixels no blur reaches. A pixel's CoC is |signed| * coc_px px; one
    of 0.5 px or more spreads its pixel up to c + 1 px away (the kernel's anti-aliased rim), and
    a pixel is untouched when it is under 0.5 px itself and no such spread reaches it. Reach
    spreads by chessboard distance, on cells of f x f px where it is long (f chosen for at most
    16 steps; a cell's reach counts one cell more): the test errs on the side of touched."""
    c = signed.float().abs() * float(coc_px)
    reach = torch.where(c >= 0.5, c + 1.0, torch.zeros_like(c))
    longest = float(reach.max()) if reach.numel() else 0.0
    f = 2 ** max(0, math.ceil(math.log2(longest / 16))) if longest > 16 else 1
    if f > 1:  # in cells: the reach of a cell's farthest-reaching pixel, plus the cell's own extent
        cell = F.max_pool2d(reach, f, stride=f, ceil_mode=True)
        reach = torch.where(cell > 0, cell / f + 1.0, 0.0)
    reach = _spread_reach(reach, math.ceil(float(reach.max())) if reach.numel() else 0)
    free = reach <= 0
    if f > 1:
        h, w = signed.shape[-2:]
        free = free.repeat_interleave(f, dim=-2).repeat_interleave(f, dim=-1)[..., :h, :w]
    return free


@torch.no_grad()
def edge_weight(signed: torch.Tensor, coc_px: float) -> torch.Tensor:
    """(B, 1, H, W) float32 in [0, 1]: how near the pixels lie to a depth edge of `signed` (its
    CoC is signed * coc_px px). A pixel whose CoC differs by 1 px or more from one of its 8
    neighbours' lies on an edge, which reaches r = the larger |CoC| of that 3 x 3 + 1 px around
    it; at chessboard distance d the weight is (r - d) / (R / 2), at most 1, R the image's
    longest reach: 1 near the edges, falling linearly to 0 where their reach ends (no seam)."""
    c = signed.float() * float(coc_px)
    hi, lo = F.max_pool2d(c, 3, 1, 1), -F.max_pool2d(-c, 3, 1, 1)
    reach = torch.where(hi - lo >= 1.0, torch.maximum(hi.abs(), lo.abs()) + 1.0, torch.zeros_like(c))
    spread = _spread_reach(reach, math.ceil(float(reach.max())) if reach.numel() else 0)
    ramp = torch.clamp(reach.amax(dim=(-2, -1), keepdim=True) / 2, min=1.0)
    return torch.clamp(spread / ramp, 0.0, 1.0)
