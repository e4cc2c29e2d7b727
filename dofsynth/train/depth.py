"""The DeepLens depth-prediction module (Wang et al. 2018, Sec. 3.1): one photo in, normalized
disparity (1 = nearest) and a foreground segmentation out.

    DepthNet(cfg.depth)(image) -> (depth, seg), image (B, 3, H, W) sRGB in [0, 1], any H, W
        depth (B, 1, H, W): raw; `minmax` of it is the prediction D in [0, 1]
        seg   (B, 1, H, W): foreground probability S in [0, 1]

Encoder: ResNet-50 from conv1 to res4f (torchvision's conv1 .. layer3, same module names, so a
torchvision ImageNet state_dict loads as it is), its last stage atrous (dilation 2 instead of
stride 2), so features stay at 1/8 of the input. [depth] backbone = "resnet18" and a smaller
[depth] width give a small network for tests and CPU experiments. Then a pyramid pooling layer
(PSPNet; bins 1, 2, 4, 8), a decoder of three x2 bilinear upsamplings, each fused with the
encoder's features of that size (the last with the image), and two heads of three convolutions,
for depth and for segmentation. The images are standardised with ImageNet's mean and std inside.

Loss: J_d = |D - D^g|_1 + gamma |S - S^g|_1 (`depth_loss`), D and D^g both min-max normalized
per image (the paper: only the order of depths matters for DoF); a sample without depth (or
without a segmentation) contributes nothing to that term. Evaluation (`depth_errors`): MAE of
D, and MAE after the 5-knot linear-spline fit of D to D^g (Sec. 4.1, after Srinivasan et al.).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from dofsynth.train.config import DepthConfig
from dofsynth.train.models import area_resize, bilinear, block
from dofsynth.train.weights import load_weights_file, unwrap_state_dict

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
BLOCKS = {"resnet50": (3, 4, 6), "resnet18": (2, 2, 2)}  # residual blocks of conv2_x .. conv4_x


def _bn_conv(cin: int, cout: int, k: int, stride: int = 1, dilation: int = 1) -> nn.Conv2d:
    return nn.Conv2d(cin, cout, k, stride=stride, padding=dilation * (k // 2), dilation=dilation, bias=False)


class Bottleneck(nn.Module):
    """torchvision's ResNet-50 block (names conv1..3, bn1..3, downsample)."""
    expansion = 4

    def __init__(self, cin: int, planes: int, stride: int = 1, dilation: int = 1):
        super().__init__()
        cout = planes * self.expansion
        self.conv1, self.bn1 = _bn_conv(cin, planes, 1), nn.BatchNorm2d(planes)
        self.conv2, self.bn2 = _bn_conv(planes, planes, 3, stride, dilation), nn.BatchNorm2d(planes)
        self.conv3, self.bn3 = _bn_conv(planes, cout, 1), nn.BatchNorm2d(cout)
        self.downsample = (nn.Sequential(_bn_conv(cin, cout, 1, stride), nn.BatchNorm2d(cout))
                           if stride != 1 or cin != cout else None)

    def forward(self, x):
        y = F.relu(self.bn1(self.conv1(x)))
        y = F.relu(self.bn2(self.conv2(y)))
        y = self.bn3(self.conv3(y))
        return F.relu(y + (x if self.downsample is None else self.downsample(x)))


class BasicBlock(nn.Module):
    """torchvision's ResNet-18 block (names conv1..2, bn1..2, downsample)."""
    expansion = 1

    def __init__(self, cin: int, planes: int, stride: int = 1, dilation: int = 1):
        super().__init__()
        self.conv1, self.bn1 = _bn_conv(cin, planes, 3, stride, dilation), nn.BatchNorm2d(planes)
        self.conv2, self.bn2 = _bn_conv(planes, planes, 3, 1, dilation), nn.BatchNorm2d(planes)
        self.downsample = (nn.Sequential(_bn_conv(cin, planes, 1, stride), nn.BatchNorm2d(planes))
                           if stride != 1 or cin != planes else None)

    def forward(self, x):
        y = self.bn2(self.conv2(F.relu(self.bn1(self.conv1(x)))))
        return F.relu(y + (x if self.downsample is None else self.downsample(x)))


class Encoder(nn.Module):
    """conv1 .. layer3 of a torchvision ResNet, layer3 atrous: (B, 3, H, W) -> features at 1/2
    (conv1), 1/4 (layer1) and 1/8 (layer3) of the input."""

    def __init__(self, backbone: str = "resnet50", width: int = 64):
        super().__init__()
        unit = Bottleneck if backbone == "resnet50" else BasicBlock
        self.conv1, self.bn1 = nn.Conv2d(3, width, 7, stride=2, padding=3, bias=False), nn.BatchNorm2d(width)
        self.maxpool = nn.MaxPool2d(3, stride=2, padding=1)
        cin, layers = width, []
        # torchvision's replace_stride_with_dilation on layer3: its first block keeps dilation 1
        for k, (n, stride) in enumerate(zip(BLOCKS[backbone], (1, 2, 1))):
            planes = width * 2**k
            blocks = []
            for b in range(n):
                blocks.append(unit(cin, planes, stride if b == 0 else 1, 2 if (k == 2 and b > 0) else 1))
                cin = planes * unit.expansion
            layers.append(nn.Sequential(*blocks))
        self.layer1, self.layer2, self.layer3 = layers
        self.channels = (width, width * unit.expansion, cin)  # at 1/2, 1/4, 1/8

    def forward(self, x):
        x1 = F.relu(self.bn1(self.conv1(x)))
        x2 = self.layer1(self.maxpool(x1))
        return x1, x2, self.layer3(self.layer2(x2))


class PyramidPooling(nn.Module):
    """PSPNet's pyramid pooling: the features, average-pooled to b x b bins for every b, reduced
    by 1x1 convs to cin / len(bins), upsampled back and concatenated with the input."""

    def __init__(self, cin: int, bins: tuple[int, ...] = (1, 2, 4, 8)):
        super().__init__()
        c = max(1, cin // len(bins))
        self.bins = tuple(bins)
        self.reduce = nn.ModuleList(nn.Sequential(nn.Conv2d(cin, c, 1, bias=False), nn.BatchNorm2d(c), nn.ReLU())
                                    for _ in bins)
        self.out_channels = cin + c * len(bins)

    def forward(self, x):
        size = x.shape[-2:]
        return torch.cat([x] + [bilinear(r(F.adaptive_avg_pool2d(x, b)), size) for b, r in zip(self.bins, self.reduce)], 1)


def head(width: int) -> nn.Sequential:
    """Three convolutions: two 3x3 with ReLU, one 1x1 to a single map."""
    return nn.Sequential(block(width, width), block(width, width), nn.Conv2d(width, 1, 1))


class DepthNet(nn.Module):
    """Encoder -> pyramid pooling -> decoder (three x2 upsamplings with skips) -> two heads."""

    def __init__(self, cfg: DepthConfig):
        super().__init__()
        self.encoder = Encoder(cfg.backbone, cfg.width)
        self.ppm = PyramidPooling(self.encoder.channels[2], tuple(cfg.bins))
        w = cfg.decoder_width
        widths = (w, max(8, w // 2), max(8, w // 4), max(8, w // 8))  # at 1/8, 1/4, 1/2, 1/1
        self.bottleneck = block(self.ppm.out_channels, widths[0], "batch")
        skips = (self.encoder.channels[1], self.encoder.channels[0], 3)
        self.decoder = nn.ModuleList(block(widths[k] + skips[k], widths[k + 1], "batch") for k in range(3))
        self.depth_head, self.seg_head = head(widths[3]), head(widths[3])
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1), persistent=False)

    def forward(self, image: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        if image.ndim != 4 or image.shape[1] != 3:
            raise ValueError(f"image must be (B, 3, H, W), got {tuple(image.shape)}")
        x = (image - self.mean) / self.std
        x1, x2, x3 = self.encoder(x)
        y = self.bottleneck(self.ppm(x3))
        for dec, skip in zip(self.decoder, (x2, x1, x)):
            y = dec(torch.cat([bilinear(y, skip.shape[-2:]), skip], 1))
        return self.depth_head(y), torch.sigmoid(self.seg_head(y))


def load_backbone(model: DepthNet, path: str | Path) -> int:
    """Copy ImageNet weights into the encoder from a local torchvision state_dict file (e.g.
    resnet50-0676ba61.pth; never downloaded). Returns the number of tensors copied. A missing
    file raises FileNotFoundError, a file that is not such a state_dict or does not fit this
    backbone ValueError, both naming the file and what is wrong."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"[depth] weights {path}: no such file (give a torchvision ImageNet state_dict "
                                "of the backbone, e.g. resnet50-0676ba61.pth, or leave weights empty for "
                                "random initialisation)")
    state, how = unwrap_state_dict(load_weights_file(path, "a PyTorch state_dict file"))
    if not isinstance(state, dict):
        raise ValueError(f"[depth] weights {path}: holds a {type(state).__name__}, not a state_dict")
    own = model.encoder.state_dict()
    missing = [k for k in own if k not in state]
    wrong = [f"{k} {tuple(state[k].shape)} (need {tuple(v.shape)})" for k, v in own.items()
             if k in state and tuple(state[k].shape) != tuple(v.shape)]
    if missing or wrong:
        what = (f"{len(missing)} of {len(own)} backbone tensors missing (e.g. {', '.join(missing[:3])})" if missing
                else f"shapes differ: {', '.join(wrong[:3])}")
        raise ValueError(f"[depth] weights {path}: does not fit [depth] backbone/width: {what}"
                         f"{f' (after {how})' if how else ''}")
    model.encoder.load_state_dict({k: state[k] for k in own})
    return len(own)


def minmax(x: torch.Tensor, mask: torch.Tensor | None = None, eps: float = 1e-6) -> torch.Tensor:
    """Per-image min-max normalisation of (B, 1, H, W) to [0, 1] over the pixels of `mask`
    (all when None); a constant image becomes 0."""
    x = x.float()
    m = torch.ones_like(x, dtype=torch.bool) if mask is None else mask.bool()
    big = torch.finfo(x.dtype).max
    lo = torch.where(m, x, big).flatten(1).amin(1).view(-1, 1, 1, 1)
    hi = torch.where(m, x, -big).flatten(1).amax(1).view(-1, 1, 1, 1)
    return ((x - lo) / (hi - lo).clamp_min(eps)).clamp(0, 1)


def depth_mae(depth: torch.Tensor, batch: dict) -> torch.Tensor:
    """(B,) mean absolute error of each prediction, min-max normalized over its known pixels
    (batch["depth_valid"]), against batch["depth"] (normalized already), over those pixels."""
    valid = batch["depth_valid"] > 0.5
    err = (minmax(depth, valid) - batch["depth"].float()).abs() * valid
    return err.flatten(1).sum(1) / valid.flatten(1).sum(1).clamp_min(1)


def depth_loss(depth: torch.Tensor, seg: torch.Tensor, batch: dict, gamma: float = 1.0):
    """(J_d, depth term, segmentation term) of a mixed batch. Each term is the mean over the
    samples that have that supervision (batch["has_depth"], ["has_seg"], (B,) in {0, 1}) of
    the per-sample mean absolute error (depth: over batch["depth_valid"] pixels, prediction
    min-max normalized over them; batch["depth"] is normalized already); 0 without any."""
    err_d = depth_mae(depth, batch)
    err_s = (seg.float() - batch["seg"].float()).abs().flatten(1).mean(1)
    has_d, has_s = batch["has_depth"].float(), batch["has_seg"].float()
    j_d = (err_d * has_d).sum() / has_d.sum().clamp_min(1)
    j_s = (err_s * has_s).sum() / has_s.sum().clamp_min(1)
    return j_d + gamma * j_s, j_d, j_s


def spline_fit(pred: np.ndarray, gt: np.ndarray, knots: int = 5) -> np.ndarray:
    """The least-squares fit to `gt` of a linear spline of `pred` with `knots` evenly spaced
    knots over pred's range (Srinivasan et al. 2018), evaluated at pred: corrects scale, offset
    and a monotone (or inverted) warp of a relative depth map."""
    p, g = np.asarray(pred, np.float64).ravel(), np.asarray(gt, np.float64).ravel()
    lo, hi = p.min(), p.max()
    if hi - lo < 1e-9:
        return np.full(np.shape(pred), g.mean())
    t = (p - lo) / (hi - lo) * (knots - 1)
    k = np.minimum(t.astype(int), knots - 2)
    f = t - k
    basis = np.zeros((p.size, knots))
    rows = np.arange(p.size)
    basis[rows, k], basis[rows, k + 1] = 1 - f, f
    coef, *_ = np.linalg.lstsq(basis, g, rcond=None)
    return (basis @ coef).reshape(np.shape(pred))


def depth_errors(pred: np.ndarray, gt: np.ndarray, valid: np.ndarray | None = None) -> dict:
    """{"mae", "mae_spline", "mae_constant"} of a predicted map against normalized ground truth,
    both (H, W), over the `valid` pixels: the min-max normalized prediction, its 5-knot spline fit
    to gt, and the best constant map under this error (gt's median: the mean, which the spline's
    least-squares fit gives a flat prediction, is the best constant of the squared error only)."""
    v = np.ones(np.shape(gt), bool) if valid is None else np.asarray(valid, bool)
    p, g = np.asarray(pred, np.float64)[v], np.asarray(gt, np.float64)[v]
    span = p.max() - p.min()
    p_n = (p - p.min()) / span if span > 1e-9 else np.zeros_like(p)
    return {"mae": float(np.abs(p_n - g).mean()), "mae_spline": float(np.abs(spline_fit(p, g) - g).mean()),
            "mae_constant": float(np.abs(g - np.median(g)).mean())}


def predict_disparity(model: DepthNet, image_srgb: np.ndarray, side: int) -> np.ndarray:
    """(H, W) float32 normalized disparity in [0, 1] (1 = nearest) of an sRGB photo (H, W, 3)
    in [0, 1]: the network runs with the short side resized to `side` (the training scale),
    and its min-max normalized depth is resized back to (H, W)."""
    device = next(model.parameters()).device
    h, w = image_srgb.shape[:2]
    f = side / min(h, w)
    work = (max(8, round(h * f)), max(8, round(w * f)))
    x = torch.from_numpy(np.ascontiguousarray(np.asarray(image_srgb, np.float32).transpose(2, 0, 1)))[None].to(device)
    with torch.inference_mode():
        depth, _ = model(area_resize(x, work) if work[0] <= h else bilinear(x, work))
        d = bilinear(minmax(depth), (h, w)).clamp(0, 1)
    return d[0, 0].float().cpu().numpy()
