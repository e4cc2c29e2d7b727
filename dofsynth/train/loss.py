"""The DeepLens normalized loss.

    J(X, Y) = sum |X - Y|^(a + 1) / (sum |X - Y|^a + eps),   a = 1.5 by default

a mean absolute error weighted by |X - Y|^a: large errors (missed blur at depth edges) count
more than an L1 loss would give them, and the value keeps the units of the images whatever the
batch or image size. When X == Y it is exactly 0 and its gradient is 0 (|e|^a with a >= 1 is
differentiable at 0), never NaN. Computed in float32 even under autocast.
The training loss is J(L, T_lo) + beta * J(H, T).

Note: J is a mean of |e| weighted by |e|^a, so adding errors smaller than J itself *lowers* J:
it fights the large errors and tolerates many small ones (PSNR can lag behind). [loss] l1 > 0
adds a plain mean absolute error term that also pushes the small errors down.
"""
from __future__ import annotations

import torch


def normalized_loss(x: torch.Tensor, y: torch.Tensor, alpha: float = 1.5, eps: float = 1e-8) -> torch.Tensor:
    """J over all elements of x and y (same shape) -> 0-d float32 tensor."""
    if x.shape != y.shape:
        raise ValueError(f"loss inputs differ in shape: {tuple(x.shape)} vs {tuple(y.shape)}")
    if alpha < 0:
        raise ValueError(f"alpha must be >= 0, got {alpha}")
    e = (x.float() - y.float()).abs()
    return (e ** (alpha + 1)).sum() / ((e ** alpha).sum() + eps)


def deeplens_loss(low, high, target_lo, target, alpha: float = 1.5, beta: float = 1.0,
                  eps: float = 1e-8, l1: float = 0.0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(total, J(L), J(H)) for L (B, 3, h, w) vs target_lo and H (B, 3, H, W) vs target.

    total = J(L) + beta * J(H), plus l1 * (mean|L - T_lo| + beta * mean|H - T|) when l1 > 0.
    """
    j_low = normalized_loss(low, target_lo, alpha, eps)
    j_high = normalized_loss(high, target, alpha, eps)
    total = j_low + beta * j_high
    if l1 > 0:
        total = total + l1 * ((low.float() - target_lo.float()).abs().mean()
                              + beta * (high.float() - target.float()).abs().mean())
    return total, j_low, j_high
