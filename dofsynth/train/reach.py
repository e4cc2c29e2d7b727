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


_BOX3 = np.ones((3, 3), np.uint8)  # the 3 x 3 neighbourhood of cv2.dilate and cv2.erode


def _max_min3(c: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The 3 x 3 maximum and minimum of (B, 1, h, w) float32, outside the frame ignored: on the
    CPU by cv2.dilate and cv2.erode (10x less CPU time than max_pool2d at 2048 px), else by
    max_pool2d; the same values."""
    if c.device.type != "cpu":
        return F.max_pool2d(c, 3, 1, 1), -F.max_pool2d(-c, 3, 1, 1)
    c = c.contiguous()
    hi, lo = torch.empty_like(c), torch.empty_like(c)
    shape = (-1, *c.shape[-2:])
    for plane, big, small in zip(c.numpy().reshape(shape), hi.numpy().reshape(shape), lo.numpy().reshape(shape)):
        cv2.dilate(plane, _BOX3, dst=big)  # beyond the frame: nothing (their default borders)
        cv2.erode(plane, _BOX3, dst=small)
    return hi, lo


CHAMFER_WORK = 40_000  # steps x width above which a plane spreads by two raster passes (measured)


def _spread_reach(reach: torch.Tensor, steps: int) -> torch.Tensor:
    """`steps` times reach = max(reach, its 3 x 3 maximum - 1) ((B, 1, h, w) float32, >= 0).
    On the CPU by cv2.dilate in place (20-30x faster than max_pool2d there), or, once the steps
    reach the largest value (the spread is complete: max over q of reach(q) - chessboard
    distance) on a wide plane, by two raster passes (`_chamfer`: 4x faster at 2048 px); else by
    max_pool2d. The same values every way (maxima, and subtractions of whole numbers exact in
    float32 or float64)."""
    if steps <= 0:
        return reach
    if reach.device.type != "cpu":
        for _ in range(steps):
            reach = torch.maximum(reach, F.max_pool2d(reach, 3, stride=1, padding=1) - 1.0)
        return reach
    out = reach.detach().to(torch.float32).contiguous().clone()
    for plane in out.numpy().reshape(-1, *out.shape[-2:]):
        if steps * plane.shape[1] > CHAMFER_WORK and steps >= math.ceil(float(plane.max())):
            plane[...] = _chamfer(plane)
            continue
        grown = np.empty_like(plane)
        for _ in range(steps):
            cv2.dilate(plane, _BOX3, dst=grown)  # outside the frame counts as nothing (its default border)
            grown -= 1.0
            np.maximum(plane, grown, out=plane)
    return out


def _chamfer(reach: np.ndarray) -> np.ndarray:
    """max over q of reach(q) - chessboard distance(p, q), for reach (h, w) >= 0: a forward pass
    (each pixel from its upper three and left neighbours) and a backward one (lower three and
    right), exact for the chessboard distance (Rosenfeld and Pfaltz 1966). Along a row the
    pass is a running maximum of reach + column index; in float64, so every value is exact."""
    f = reach.astype(np.float64)
    h, w = f.shape
    col = np.arange(w, dtype=np.float64)
    near = np.empty(w)

    def from_row(row, other):  # row = max(row, (3-neighbour maximum of the other row) - 1)
        np.maximum(other[1:], other[:-1], out=near[1:])
        near[0] = other[0]
        np.maximum(near[:-1], other[1:], out=near[:-1])
        np.subtract(near, 1.0, out=near)
        np.maximum(row, near, out=row)

    for r in range(h):
        if r:
            from_row(f[r], f[r - 1])
        f[r] = np.maximum.accumulate(f[r] + col) - col
    for r in range(h - 1, -1, -1):
        if r < h - 1:
            from_row(f[r], f[r + 1])
        f[r] = np.maximum.accumulate((f[r] - col)[::-1])[::-1] + col
    return f.astype(np.float32)


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
def edge_weight(signed: torch.Tensor, coc_px: float, margin: float = 0.0) -> torch.Tensor:
    """(B, 1, H, W) float32 in [0, 1]: how near the pixels lie to a depth edge of `signed` (its
    CoC is signed * coc_px px). A pixel whose CoC differs by 1 px or more from one of its 8
    neighbours' lies on an edge, which reaches r = the larger |CoC| of that 3 x 3 + 1 px +
    `margin` px around it; at chessboard distance d the weight is (r - d) / (R / 2), at most 1,
    R the image's longest reach: 1 near the edges, falling linearly to 0 where their reach ends
    (no seam)."""
    c = signed.float() * float(coc_px)
    hi, lo = _max_min3(c)
    reach = torch.where(hi - lo >= 1.0, torch.maximum(hi.abs(), lo.abs()) + (1.0 + float(margin)),
                        torch.zeros_like(c))
    spread = _spread_reach(reach, math.ceil(float(reach.max())) if reach.numel() else 0)
    ramp = torch.clamp(reach.amax(dim=(-2, -1), keepdim=True) / 2, min=1.0)
    return torch.clamp(spread / ramp, 0.0, 1.0)
