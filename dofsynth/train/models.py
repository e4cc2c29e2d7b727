"""The DeepLens networks: a lens-blur network at low resolution and a guided upsampler.

Shapes are (B, C, H, W). Images are in the colour space of [data] color (sRGB-encoded or linear,
[0, 1]-ish); `signed` is the signed disparity s = (d - focus) * max_coc / r_max = c / r_max, the
signed circle-of-confusion radius over the largest aperture's max CoC (dimensionless, about
[-1, 1]; 0 = in focus, > 0 in front of the focal plane). A smaller aperture r* is rendered by
feeding s * r*/r_max.

LensBlurNet (Wang et al. 2018, Sec. 4.2):
  F = Features(A): a stack of 3x3 convs with ReLU (dilations 1, 2, 4, 8 by default, so the
      features span blurs of many sizes), every layer's maps concatenated: F (B, 3, c, H, W).
      [model] features = "channel": the same stack on each colour channel alone (the paper);
      "joint": one stack on the RGB image whose maps are dealt out to the three colours in
      turn (the official code). raw_feature = true puts A_i itself first among the c features.
  K = KernelPredictor(A, s): a U-Net gives a per-pixel kernel of c weights (B, c, H, W);
      [model] kernel = "free" leaves them as they are, "blur" makes them non-negative with
      sum 1 (a softmax), so L is a per-pixel mix of the features, like a blur. [model]
      kernel_prior = "discs" adds a learned table T(s) started as disc blurs (kernel_table).
  L_i = sum_j K_j * F_ij: the lens-blurred image (B, 3, H, W); light = "boosted": of A in
      linear light, highlight-boosted, and L mapped back to sRGB (dofsynth.train.light).

GuidedUpsampler (Sec. 4.3), one x2 step with weights shared across steps, applied from the low
resolution to any size (the size chain halves it, rounding up, so every step is exact):
  features of the low-res (A, L, s), bilinearly upsampled, and of the high-res A give
  M_L = sigmoid(.), M_A = 1 - M_L (a convex blend, so in-focus pixels can keep the sharp image
  exactly): H = M_A * A + M_L * upsample(L). [model] up_depth > 0 makes its low-res branch a
  U-Net of that many levels (the official network's size). [model] norm = "batch" or "group"
  follows every conv of the kernel predictor and the upsampler (never the features).
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from dofsynth.optics.coc import coc_radius
from dofsynth.train.config import ModelConfig
from dofsynth.train.kernel_table import KernelTable
from dofsynth.train.light import BoostedLight
from dofsynth.train.reach import edge_weight, untouched


def signed_disparity(disparity, focus, max_coc, coc_ref: float):
    """The networks' depth input (numpy or torch): the signed CoC over the largest aperture's,
    c / r_max = (disparity - focus) * max_coc / coc_ref."""
    return coc_radius(disparity, focus, max_coc / coc_ref)


def size_chain(size: tuple[int, int], steps: int) -> list[tuple[int, int]]:
    """Sizes from the lowest to `size`: each is the next one halved, rounded up.
    size_chain((100, 60), 2) == [(25, 15), (50, 30), (100, 60)]."""
    sizes = [tuple(size)]
    for _ in range(steps):
        h, w = sizes[0]
        sizes.insert(0, ((h + 1) // 2, (w + 1) // 2))
    return sizes


def area_resize(x: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """Area (box-mean) downsample of (B, C, H, W) to `size`; exact block means for integer factors."""
    return x if tuple(x.shape[-2:]) == tuple(size) else F.adaptive_avg_pool2d(x, size)


def bilinear(x: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    return x if tuple(x.shape[-2:]) == tuple(size) else F.interpolate(
        x, size=size, mode="bilinear", align_corners=False)


NORMS, KERNELS, FEAT_INITS = ("none", "batch", "group"), ("free", "blur"), ("random", "blur")


def conv(cin: int, cout: int, dilation: int = 1, stride: int = 1) -> nn.Conv2d:
    """3x3 convolution that keeps the size (stride 1) or halves it rounding up (stride 2);
    replicate padding, so a flat image stays flat up to the border."""
    return nn.Conv2d(cin, cout, 3, stride=stride, padding=dilation, dilation=dilation,
                     padding_mode="replicate")


def block(cin: int, cout: int, norm: str = "none", stride: int = 1) -> nn.Sequential:
    """conv -> [normalisation] -> ReLU."""
    layers = [conv(cin, cout, stride=stride)]
    if norm == "batch":
        layers.append(nn.BatchNorm2d(cout))
    elif norm == "group":
        layers.append(nn.GroupNorm(8 if cout % 8 == 0 else 1, cout))
    elif norm != "none":
        raise ValueError(f"norm must be one of {NORMS}, got {norm!r}")
    return nn.Sequential(*layers, nn.ReLU())


class ChannelFeatures(nn.Module):
    """(B, 3, H, W) image -> (B, 3, c, H, W), c = channels * len(dilations) (+ 1 with raw):
    every layer's ReLU output, concatenated. joint=False: the same conv stack on each colour
    channel alone; joint=True: one stack on RGB with 3 * channels maps per layer, map k going
    to colour k % 3. raw=True: the colour channel itself is feature 0."""

    def __init__(self, channels: int = 8, dilations: tuple[int, ...] = (1, 2, 4, 8), *,
                 joint: bool = False, raw: bool = False, init: str = "random"):
        super().__init__()
        n = 3 if joint else 1
        cins = [n] + [n * channels] * (len(dilations) - 1)
        self.layers = nn.ModuleList(conv(ci, n * channels, d) for ci, d in zip(cins, dilations))
        self.joint, self.raw = joint, raw
        self.out_channels = channels * len(dilations) + int(raw)
        if init == "blur":
            self._blur_init(channels, n)
        elif init != "random":
            raise ValueError(f"init must be one of {FEAT_INITS}, got {init!r}")

    @torch.no_grad()
    def _blur_init(self, channels: int, n: int) -> None:
        """Map o of a layer starts as (1 - t) x its source + t x the 3x3 box mean of it at the
        layer's dilation, t = (o // n + 1) / channels, its source the same map of the layer before
        (its colour in the first): blurs of the image up to a std of sqrt(2/3 sum d^2) px, >= 0."""
        for layer in self.layers:
            w = torch.zeros_like(layer.weight)          # (out, in, 3, 3)
            for o in range(w.shape[0]):
                t, src = (o // n + 1) / channels, o % w.shape[1]  # (w.shape[1]: n, or every map)
                w[o, src] = t / 9
                w[o, src, 1, 1] += 1 - t
            layer.weight.copy_(w)
            layer.bias.zero_()

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        b, n, h, w = image.shape
        x = image if self.joint else image.reshape(b * n, 1, h, w)
        feats = []
        for layer in self.layers:
            x = F.relu(layer(x))
            feats.append(x)
        f = torch.cat(feats, dim=1)
        if self.joint:  # (B, 3k, H, W), map j*3 + i belongs to colour i
            f = f.reshape(b, -1, 3, h, w).transpose(1, 2)
        else:
            f = f.reshape(b, n, -1, h, w)
        if self.raw:
            f = torch.cat([image.unsqueeze(2), f], dim=2)
        return f


class KernelPredictor(nn.Module):
    """(B, 3, H, W) image and (B, 1, H, W) signed disparity -> (B, c, H, W) per-pixel weights.
    A U-Net (`UNet`, 4 input channels) with a 1x1 head."""

    def __init__(self, out_channels: int, width: int = 32, depth: int = 3, norm: str = "none"):
        super().__init__()
        self.body = UNet(4, width, depth, norm)
        self.head = nn.Conv2d(width, out_channels, 1)

    def forward(self, image: torch.Tensor, signed: torch.Tensor) -> torch.Tensor:
        return self.head(self.body(torch.cat([image, signed], dim=1)))


class UNet(nn.Module):
    """(B, cin, H, W) -> (B, width, H, W): `depth` stride-2 levels (widths width * 2**k) with
    skip connections; depth 0 is two convolutions."""

    def __init__(self, cin: int, width: int, depth: int, norm: str = "none"):
        super().__init__()
        widths = [width * 2**k for k in range(depth + 1)]
        self.stem = nn.Sequential(block(cin, width, norm), block(width, width, norm))
        self.down = nn.ModuleList(
            nn.Sequential(block(widths[k], widths[k + 1], norm, stride=2), block(widths[k + 1], widths[k + 1], norm))
            for k in range(depth))
        self.up = nn.ModuleList(block(widths[k + 1] + widths[k], widths[k], norm) for k in reversed(range(depth)))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = self.stem(x)
        skips = []
        for down in self.down:
            skips.append(x)
            x = down(x)
        for up, skip in zip(self.up, reversed(skips)):
            x = up(torch.cat([bilinear(x, skip.shape[-2:]), skip], dim=1))
        return x


class LensBlurNet(nn.Module):
    """(B, 3, h, w) low-res image, (B, 1, h, w) signed disparity -> (B, 3, h, w) blurred L.
    prior_px: with [model] kernel_prior = "discs", the px of disc radius per unit of s."""

    def __init__(self, feat_channels: int = 8, dilations: tuple[int, ...] = (1, 2, 4, 8),
                 kp_width: int = 32, kp_depth: int = 3, *, joint: bool = False, raw: bool = False,
                 kernel: str = "free", norm: str = "none", feat_init: str = "random", prior_px: float | None = None):
        super().__init__()
        if kernel not in KERNELS:
            raise ValueError(f"kernel must be one of {KERNELS}, got {kernel!r}")
        self.features = ChannelFeatures(feat_channels, dilations, joint=joint, raw=raw, init=feat_init)
        self.kernel = KernelPredictor(self.features.out_channels, kp_width, kp_depth, norm)
        self.blur = kernel == "blur"
        self.prior = None if prior_px is None else KernelTable(self.features, prior_px)
        if self.prior is not None:  # the untrained kernel is the table's
            nn.init.zeros_(self.kernel.head.weight), nn.init.zeros_(self.kernel.head.bias)

    def forward(self, image: torch.Tensor, signed: torch.Tensor) -> torch.Tensor:
        _check(image, 3, "image"), _check(signed, 1, "signed", image.shape[-2:])
        feats = self.features(image)          # (B, 3, c, h, w)
        k = self.kernel(image, signed)        # (B, c, h, w)
        k = k if self.prior is None else k + self.prior(signed)
        if self.blur:
            k = torch.softmax(k.float(), dim=1).to(feats.dtype)
        return (feats * k.unsqueeze(1)).sum(dim=2)


class GuidedUpsampler(nn.Module):
    """One upsampling step: low-res image, result and signed disparity (B, 3|3|1, h, w) plus the
    high-res image (B, 3, H, W) -> high-res result (B, 3, H, W) (any H, W; x2 in practice)."""

    def __init__(self, width: int = 16, depth: int = 0, norm: str = "none"):
        super().__init__()
        self.low = UNet(7, width, depth, norm)
        self.high = nn.Sequential(block(3, width, norm), block(width, width, norm))
        self.fuse = nn.Sequential(block(2 * width, width, norm), nn.Conv2d(width, 1, 1))

    def forward(self, image_lo, result_lo, signed_lo, image_hi, rows: int | None = None):
        """rows: the high-res convolutions in bands of that many rows (the same values up to
        float rounding; their intermediates for one band instead of a frame each)."""
        size = tuple(image_hi.shape[-2:])
        low = self.low(torch.cat([image_lo, result_lo, signed_lo], dim=1))
        if rows is None or rows >= size[0]:
            m_l = self._mask(bilinear(low, size), image_hi)
            return (1 - m_l) * image_hi + m_l * bilinear(result_lo, size)
        low, res = bilinear(low, size), bilinear(result_lo, size)
        out = torch.empty_like(image_hi)
        for r0 in range(0, size[0], rows):
            r1 = min(r0 + rows, size[0])
            a, b = max(r0 - HIGH_REACH, 0), min(r1 + HIGH_REACH, size[0])  # the rows its convs reach
            m_l = self._mask(low[:, :, a:b], image_hi[:, :, a:b])[:, :, r0 - a:r1 - a]
            out[:, :, r0:r1] = (1 - m_l) * image_hi[:, :, r0:r1] + m_l * res[:, :, r0:r1]
        return out

    def _mask(self, low: torch.Tensor, image_hi: torch.Tensor) -> torch.Tensor:
        """m_l, the fusion mask, from the upsampled low-res branch and the high-res image."""
        return torch.sigmoid(self.fuse(torch.cat([low, self.high(image_hi)], dim=1)))


HIGH_REACH = 3  # rows of the high-res image one output row of the upsampler depends on (three 3x3 convs)


class DeepLensNet(nn.Module):
    """Both networks: `forward(image, signed_lo, steps)` -> (L, H). image: (B, 3, H, W) high-res
    all-in-focus image. signed_lo: (B, 1, h, w) signed disparity at the lowest size of
    `size_chain((H, W), steps)`, or of `sizes` (lowest to (H, W)) if given. image_lo: optional
    (B, 3, h, w) low-res image (else area-downsampled here). Returns L (B, 3, h, w), the lens blur
    at low resolution, and H (B, 3, H, W) after `steps` guided x2 upsamplings. rows: the
    upsamplings' high-res part in bands of that many rows (`GuidedUpsampler.forward`). signed_hi
    (B, 1, H, W) and coc_px (px of CoC per unit of signed disparity at (H, W)): with [model]
    identity, H is the image itself wherever no blur reaches (`untouched`), by construction."""

    def __init__(self, cfg: ModelConfig, levels: int | None = None):  # [data] levels, for kernel_prior's px
        super().__init__()
        prior_px = (0.0 if levels is None else cfg.coc_ref / 2**levels) if cfg.kernel_prior == "discs" else None
        self.lens = LensBlurNet(cfg.feat_channels, tuple(cfg.feat_dilations), cfg.kp_width, cfg.kp_depth,
                                joint=cfg.features == "joint", raw=cfg.raw_feature, kernel=cfg.kernel,
                                norm=cfg.norm, feat_init=cfg.feat_init, prior_px=prior_px)
        self.up = GuidedUpsampler(cfg.up_width, cfg.up_depth, cfg.norm)
        self.identity, self.light = cfg.identity, (BoostedLight(*cfg.boost) if cfg.light == "boosted" else None)

    def forward(self, image: torch.Tensor, signed_lo: torch.Tensor, steps: int | None = None,
                image_lo: torch.Tensor | None = None, *, sizes: list | None = None,
                rows: int | None = None, signed_hi: torch.Tensor | None = None,
                coc_px: float = 0.0, classical: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        # classical: the hybrid's input (HybridNet), not used here
        if sizes is None:
            sizes = size_chain(tuple(image.shape[-2:]), steps)
        if tuple(sizes[-1]) != tuple(image.shape[-2:]):
            raise ValueError(f"sizes must end at the image size {tuple(image.shape[-2:])}, got {sizes[-1]}")
        steps = len(sizes) - 1
        _check(image, 3, "image"), _check(signed_lo, 1, "signed_lo", sizes[0])
        pyramid = [area_resize(image, s) for s in sizes]
        if image_lo is not None:
            _check(image_lo, 3, "image_lo", sizes[0])
            pyramid[0] = image_lo
        low = self.lens(pyramid[0], signed_lo) if self.light is None else self.light(self.lens, pyramid[0], signed_lo)
        result = low
        for k in range(steps):
            signed_k = bilinear(signed_lo, sizes[k])
            result = self.up(pyramid[k], result, signed_k, pyramid[k + 1], rows=rows)
        if self.identity and signed_hi is not None:  # where nothing is blurred the answer is the input
            result = torch.where(untouched(signed_hi, coc_px), image, result)
        return low, result


class HybridNet(nn.Module):
    """[model] kind = "hybrid" (in the spirit of BokehMe): `forward(image, signed_lo, steps, classical=C)`
    -> (L, H) with H = C + U(image, C, signed_hi), C the classical render from the same (possibly wrong)
    disparity and U a U-Net ([model] kp_width, kp_depth) whose last layer starts at zero: the untrained
    model *is* the classical renderer, and training learns where to correct it (depth edges, wrong
    depth, what a blurred foreground hides). L is H area-reduced to the lowest size (the same loss as
    DeepLensNet's), whose arguments it shares; [model] identity: H is the image where no blur reaches.
    [model] gate = "edges": the correction is weighted by `edge_weight` of signed_hi, so H is C where no
    depth edge is within the blur's reach (plus gate_margin px), fading out at that band's edge.
    [model] near_shift: C is (B, 9, H, W), the render and the renders from the depth with its near
    regions grown and shrunk (classical_stack); the correction adds m_g (C_g - C) + m_s (C_s - C),
    per-pixel weights of the head, so moving a blurred edge to where the image says it is, is a choice."""

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        self.alternatives = 2 if cfg.near_shift else 0  # the grown and the shrunk render
        self.body = UNet(7 + 3 * self.alternatives, cfg.kp_width, cfg.kp_depth, cfg.norm)
        self.head = nn.Conv2d(cfg.kp_width, 3 + self.alternatives, 1)
        nn.init.zeros_(self.head.weight), nn.init.zeros_(self.head.bias)
        self.identity = cfg.identity
        self.gate = cfg.gate == "edges"
        # the gate's margin in px per px of CoC scale: [model] gate_margin px at the data's size,
        # where coc_px = coc_ref (scaled with the CoC at inference, as near_shift is)
        if cfg.gate_margin and cfg.coc_ref <= 0:
            raise ValueError("[model] gate_margin needs model.coc_ref (> 0: training fills it in from the data)")
        self.margin_per_coc = cfg.gate_margin / cfg.coc_ref if cfg.gate_margin else 0.0
        self.local = cfg.norm != "group"  # each output depends on its neighbourhood only (eval mode)

    def forward(self, image: torch.Tensor, signed_lo: torch.Tensor, steps: int | None = None,
                image_lo: torch.Tensor | None = None, *, sizes: list | None = None, rows: int | None = None,
                signed_hi: torch.Tensor | None = None, coc_px: float = 0.0,
                classical: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        if classical is None:
            raise ValueError("the hybrid model needs the classical render of the image (classical=)")
        if self.gate and signed_hi is None:
            raise ValueError('[model] gate = "edges" needs the full-resolution disparity (signed_hi=, coc_px=)')
        sizes = size_chain(tuple(image.shape[-2:]), steps) if sizes is None else sizes
        _check(image, 3, "image"), _check(classical, 3 * (1 + self.alternatives), "classical", image.shape[-2:])
        signed = signed_hi if signed_hi is not None else bilinear(signed_lo, tuple(image.shape[-2:]))
        weight = edge_weight(signed_hi, coc_px, self.margin_per_coc * coc_px) if self.gate else None
        head = self._correction([image, classical, signed], rows,
                                None if weight is None else weight > 0)
        base = classical[:, :3]
        correction = head[:, :3]
        for k in range(self.alternatives):  # the per-pixel mix of each other render
            correction = correction + head[:, 3 + k : 4 + k] * (classical[:, 3 + 3 * k : 6 + 3 * k] - base)
        if weight is not None:
            correction = correction * weight
        result = base + correction
        if self.identity and signed_hi is not None:
            result = torch.where(untouched(signed_hi, coc_px), image, result)
        return area_resize(result, sizes[0]), result

    def _correction(self, parts: list[torch.Tensor], rows: int | None,
                    needed: torch.Tensor | None = None) -> torch.Tensor:
        """The U-Net's head, (B, 3 + alternatives, H, W), on its input (B, 7 + 3 alternatives,
        H, W) given as its parts along channels (concatenated a tile at a time: no copy of the
        frame), edge-padded to a multiple of the U-Net's stride (so each level is exactly half
        the one above, as in training's crops).
        With `rows` (inference: an eval-mode U-Net without group normalisation, whose outputs
        depend only on inputs within `unet_reach`), in tiles of about that many rows and
        columns (a multiple of the stride, at least 8x `unet_reach`), each computed with
        `unet_reach` more on every side: the same values up to float rounding, the activations
        of one band instead of a frame. `needed` (B, 1, H, W) bool: in each band only the runs
        of columns holding a needed pixel are computed (in steps of 8 strides; runs closer than
        two reaches merge, as their margins would overlap), the rest of the correction is 0."""
        h, w = parts[0].shape[-2:]
        depth = len(self.body.down)
        stride = 2**depth
        if h % stride or w % stride:  # every level exactly half the one above, as in training's crops
            parts = [F.pad(p, (0, -w % stride, 0, -h % stride), mode="replicate") for p in parts]
        H, W = parts[0].shape[-2:]
        reach = -(-unet_reach(depth) // stride) * stride
        step = -(-max(rows or H, 8 * reach) // stride) * stride
        if rows is None or not self.local or self.training or (step >= max(H, W) and needed is None):
            return self.head(self.body(torch.cat(parts, dim=1)))[:, :, :h, :w]
        out = parts[0].new_zeros((parts[0].shape[0], self.head.out_channels, h, w))
        for r0 in range(0, h, step):
            r1 = min(r0 + step, h)
            a, b = max(r0 - reach, 0), min(r1 + reach, H)
            cols = None if needed is None else needed[:, :, r0:r1].any(dim=2).any(dim=0)[0]
            for c0, c1 in _runs(cols, w, 8 * stride, 2 * reach):
                ca, cb = max(c0 - reach, 0), min(c1 + reach, W)
                part = self.head(self.body(torch.cat([p[:, :, a:b, ca:cb] for p in parts], dim=1)))
                out[:, :, r0:r1, c0:c1] = part[:, :, r0 - a : r1 - a, c0 - ca : c1 - ca]
        return out


def _runs(needed: torch.Tensor | None, w: int, step: int, gap: int = 0) -> list[tuple[int, int]]:
    """The column ranges [c0, c1) of runs of tiles `step` wide (the last one up to w) that hold
    a needed column (`needed` (w,) bool; None: all of them, one run); runs at most `gap`
    columns apart are one."""
    if needed is None:
        return [(0, w)]
    tiles = [bool(needed[c : c + step].any()) for c in range(0, w, step)]
    runs = []
    for i, on in enumerate(tiles):
        if on and runs and runs[-1][1] + gap >= i * step:
            runs[-1] = (runs[-1][0], min((i + 1) * step, w))
        elif on:
            runs.append((i * step, min((i + 1) * step, w)))
    return runs


def unet_reach(depth: int) -> int:
    """Rows of the input one output row of a UNet of `depth` levels depends on: 2 from the stem,
    2**(k-1) + 2**k on the way down to each level k and 2**k + 2**(k-1) on the way back up."""
    return 2 + 6 * (2**depth - 1)


def _check(x: torch.Tensor, channels: int, name: str, size=None) -> None:
    if x.ndim != 4 or x.shape[1] != channels:
        raise ValueError(f"{name} must be (B, {channels}, H, W), got {tuple(x.shape)}")
    if size is not None and tuple(x.shape[-2:]) != tuple(size):
        raise ValueError(f"{name} must be {tuple(size)} in size, got {tuple(x.shape[-2:])}")

