"""The training losses of the DoF networks: the paper's normalized loss J and the default, J's
weighting with every pixel pulled toward its target.

    J(X, Y) = sum |e|^(a + 1) / (sum |e|^a + eps),   e = X - Y,   a = 1.5 by default

J is a mean absolute error weighted by |e|^a: large errors (missed blur at depth edges) count
more than in an L1 loss, and the value keeps the units of the images whatever the batch or
image size. It is 0 with zero gradient (never NaN) when X == Y. But its gradient at pixel i has
the sign of (a + 1)|e_i| - a J: every error below a J / (a + 1) (0.6 J) is pushed *up*, so a
network trained on J alone spreads a uniform error over every pixel (docs/training.md).

`[loss] kind = "weighted"` (the default) has J's value and its weights, held constant in the
gradient: sum w |e| / (sum w + eps) with w = |e|^a not differentiated, so the gradient at pixel
i is w_i sign(e_i) / (sum w + eps), toward the target at every pixel, largest at the largest
errors; its only minimum is X == Y. `[loss] l1 > 0` adds a plain mean absolute error, which
keeps pulling where the errors (and so their weights) are small. `kind = "j"`: the paper's J.
All computed in float32 even under autocast. The training loss is D(L, T_lo) + beta * D(H, T)
(+ the L1 term), D being J or its weighted form.

`[loss] teacher > 0` adds teacher * D(L, C_lo): C_lo is the classical render of the *given*
(possibly wrong) depth at full resolution, area-downsampled as T_lo is. It is a function of what
the network sees, where T (made from the true depth) is not, so it pulls the lens-blur module
toward the blur the depth implies rather than toward a hedge; it moves L's minimum off T_lo by
design (H's minimum stays at T).

`[loss] ssim > 0` adds ssim * (1 - SSIM(H, T)), SSIM as `skimage.metrics.structural_similarity`
computes it by default (7 x 7 uniform windows, sample covariances, data range 1, the mean over
the windows inside the image and over the channels), which the evaluation reports: a correction
that blends renders where it is unsure lowers local contrast and structure, which the
absolute errors of D barely see. 1 - SSIM is 0 at H == T.
"""
from __future__ import annotations

import torch

KINDS = ("weighted", "j")


def normalized_loss(x: torch.Tensor, y: torch.Tensor, alpha: float = 1.5, eps: float = 1e-8,
                    fixed_weights: bool = False) -> torch.Tensor:
    """J over all elements of x and y (same shape) -> 0-d float32 tensor. fixed_weights: the
    weights |e|^alpha are held constant in the gradient (the same value)."""
    if x.shape != y.shape:
        raise ValueError(f"loss inputs differ in shape: {tuple(x.shape)} vs {tuple(y.shape)}")
    if alpha < 0:
        raise ValueError(f"alpha must be >= 0, got {alpha}")
    e = (x.float() - y.float()).abs()
    w = e.detach() ** alpha if fixed_weights else e ** alpha
    return (w * e).sum() / (w.sum() + eps)


SSIM_WIN = 7  # skimage's default window (px)
SSIM_C1, SSIM_C2 = 0.01**2, 0.03**2  # its constants for data range 1


def ssim(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Mean SSIM of (B, C, H, W) images in [0, 1] as skimage's structural_similarity computes it
    with its defaults and data_range 1 (uniform 7 x 7 windows, sample covariances; the mean over
    every window inside the image, channel and image) -> 0-d float32 tensor."""
    if x.shape != y.shape:
        raise ValueError(f"ssim inputs differ in shape: {tuple(x.shape)} vs {tuple(y.shape)}")
    if min(x.shape[-2:]) < SSIM_WIN:
        raise ValueError(f"ssim needs images of at least {SSIM_WIN} x {SSIM_WIN} px, got {tuple(x.shape[-2:])}")
    x, y = x.float(), y.float()

    def mean(t: torch.Tensor) -> torch.Tensor:  # over each 7 x 7 window inside the image
        return torch.nn.functional.avg_pool2d(t, SSIM_WIN, stride=1)

    n = SSIM_WIN * SSIM_WIN
    mx, my = mean(x), mean(y)
    vx = (mean(x * x) - mx * mx) * (n / (n - 1))
    vy = (mean(y * y) - my * my) * (n / (n - 1))
    cxy = (mean(x * y) - mx * my) * (n / (n - 1))
    s = ((2 * mx * my + SSIM_C1) * (2 * cxy + SSIM_C2)) / ((mx * mx + my * my + SSIM_C1) * (vx + vy + SSIM_C2))
    return s.mean()


def deeplens_loss(low, high, target_lo, target, alpha: float = 1.5, beta: float = 1.0,
                  eps: float = 1e-8, l1: float = 0.0, kind: str = "j", teacher: float = 0.0,
                  teacher_lo=None, ssim_weight: float = 0.0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(total, D(L), D(H)) for L (B, 3, h, w) vs target_lo and H (B, 3, H, W) vs target, D being
    J (kind "j") or J with its weights held constant (kind "weighted"; the same values).

    total = D(L) + beta * D(H), plus l1 * (mean|L - T_lo| + beta * mean|H - T|) when l1 > 0,
    plus teacher * D(L, teacher_lo) when teacher > 0 (teacher_lo shaped as L), plus
    ssim_weight * (1 - ssim(H, T)) when ssim_weight > 0.
    """
    if kind not in KINDS:
        raise ValueError(f"loss kind {kind!r}: expected one of {', '.join(KINDS)}")
    fixed = kind == "weighted"
    j_low = normalized_loss(low, target_lo, alpha, eps, fixed)
    j_high = normalized_loss(high, target, alpha, eps, fixed)
    total = j_low + beta * j_high
    if l1 > 0:
        total = total + l1 * ((low.float() - target_lo.float()).abs().mean()
                              + beta * (high.float() - target.float()).abs().mean())
    if teacher > 0:
        if teacher_lo is None:
            raise ValueError("loss.teacher > 0 needs the low-resolution classical render (teacher_lo)")
        total = total + teacher * normalized_loss(low, teacher_lo, alpha, eps, fixed)
    if ssim_weight > 0:
        total = total + ssim_weight * (1.0 - ssim(high, target))
    return total, j_low, j_high
