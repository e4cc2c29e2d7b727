"""Apply a trained run to any photo and disparity map, at any resolution.

    render_photo(run_dir, image_linear, disparity, focus, aperture=1.0) -> linear RGB (H, W, 3)
    predict_depth(run_dir, image_linear) -> normalized disparity (H, W)   (a depth run)

The lens blur runs at exactly the training low-resolution scale: the photo is area-resized so
that its long side is [infer] low_res_side (the training image side / 2**levels), so a blur
covers the same fraction of the picture as in training, whatever the photo's size. Then guided
upsamplings (shared weights) bring the result back to exactly (H, W): x2 steps while they fit,
and a last step of ratio in (1, 2] onto (H, W) (`inference_sizes`). A photo smaller than
low_res_side is enlarged to it first and the result area-reduced back.

aperture = r*/r_max in (0, 1]: the signed disparity fed to the network is
(disparity - focus) * aperture (the network was trained with c / r_max). Inference runs in
float32 under torch.inference_mode, on CUDA when available, with a copy of the model made for
it (`for_inference`: batch normalisation folded into its convolutions, channels-last memory)
and the upsamplings' full-resolution part in bands of BAND_ROWS rows: the same result within
float rounding (tested within 1e-5) at about half the CPU time and a fraction of the memory.
"""
from __future__ import annotations

import copy
import math
from pathlib import Path

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F
from torch.nn.utils.fusion import fuse_conv_bn_eval

from dofsynth.color import linear_to_srgb, srgb_to_linear
from dofsynth.optics.coc import coc_radius
from dofsynth.train.checkpoint import load_model, weights_path
from dofsynth.train.classical import PHOTO_LOOK, classical_stack
from dofsynth.train.depth import predict_disparity
from dofsynth.train.models import area_resize, bilinear

_MODELS: dict = {}
BAND_ROWS = 256  # rows per band of an upsampling's full-resolution part (memory: one band, not a frame)


def edge_conv(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None, d: int = 1) -> torch.Tensor:
    """A stride-1 3 x 3 convolution with replicate padding (dilation d), computed as the
    zero-padded convolution (padded inside oneDNN: no padded copy of the input, which took
    about 40 % of the convolution's time at 2048 px) with its d border rows and columns on
    each side redone from replicate-padded strips of the input: the same values up to float
    rounding (tested)."""
    def strip(part, pad):
        return F.conv2d(F.pad(part, pad, mode="replicate"), weight, bias, dilation=d)

    h, w = x.shape[-2:]
    if h <= 2 * d or w <= 2 * d:
        return strip(x, (d, d, d, d))
    out = F.conv2d(x, weight, bias, padding=d, dilation=d)
    out[..., :d, :] = strip(x[..., : 2 * d, :], (d, d, d, 0))
    out[..., h - d :, :] = strip(x[..., h - 2 * d :, :], (d, d, 0, d))
    out[..., :, :d] = strip(x[..., :, : 2 * d], (d, 0, d, d))
    out[..., :, w - d :] = strip(x[..., :, w - 2 * d :], (0, d, d, d))
    return out


class EdgeConv(nn.Module):
    """A replicate-padded stride-1 3 x 3 nn.Conv2d as `edge_conv` (the same weights)."""

    def __init__(self, conv: nn.Conv2d):
        super().__init__()
        self.weight, self.bias, self.d = conv.weight, conv.bias, conv.dilation[0]

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return edge_conv(x, self.weight, self.bias, self.d)


def _edge_convs(module: nn.Module) -> None:
    """Every stride-1 3 x 3 replicate-padded convolution under `module` made an EdgeConv."""
    for name, child in module.named_children():
        if (isinstance(child, nn.Conv2d) and child.padding_mode == "replicate" and child.kernel_size == (3, 3)
                and child.stride == (1, 1) and child.padding == child.dilation and child.groups == 1):
            setattr(module, name, EdgeConv(child))
        else:
            _edge_convs(child)


def for_inference(model: nn.Module) -> nn.Module:
    """A copy of an eval-mode model for inference: each convolution followed by batch
    normalisation becomes one convolution with the normalisation folded in (the same function
    up to float rounding), replicate-padded convolutions pad without copying (`EdgeConv`),
    ReLUs work in place, and tensors use channels-last memory (the layout oneDNN convolves
    fastest on CPU). Training and checkpoints use the model as it is."""
    model = copy.deepcopy(model).eval()
    for seq in [m for m in model.modules() if isinstance(m, nn.Sequential)]:
        items = list(seq)
        for i, (a, b) in enumerate(zip(items, items[1:])):
            if isinstance(a, nn.Conv2d) and isinstance(b, nn.BatchNorm2d):
                seq[i], seq[i + 1] = fuse_conv_bn_eval(a, b), nn.Identity()
        for i, m in enumerate(seq):
            if isinstance(m, nn.ReLU):
                seq[i] = nn.ReLU(inplace=True)
    _edge_convs(model)
    return model.to(memory_format=torch.channels_last)


def cached_model(run_dir: str | Path, device: str):
    """load_model, cached by (checkpoint path, its mtime, device)."""
    path = weights_path(run_dir)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no trained model (run `dofsynth train` first)")
    key = (str(path.resolve()), path.stat().st_mtime_ns, device)
    if key not in _MODELS:
        if len(_MODELS) >= 2:  # a depth run and a DoF run at most
            _MODELS.clear()
        model, cfg = load_model(path, device)
        _MODELS[key] = (for_inference(model), cfg)
    return _MODELS[key]


def upsampling_steps(side: int, low_res_side: int) -> int:
    """The number n of guided upsamplings from `low_res_side` to `side`: the least n with
    low_res_side * 2**n >= side."""
    return max(0, math.ceil(math.log2(side / low_res_side) - 1e-9)) if side > low_res_side else 0


def inference_sizes(size: tuple[int, int], low_res_side: int) -> list[tuple[int, int]]:
    """Sizes from the lens-blur input (long side exactly `low_res_side`, the aspect of `size`)
    to `size` (H, W >= that): x2 steps, the last one onto `size` (ratio in (1, 2])."""
    h, w = size
    f = low_res_side / max(h, w)
    low = (max(1, round(h * f)), max(1, round(w * f)))
    n = upsampling_steps(max(h, w), low_res_side)
    return [(low[0] * 2**k, low[1] * 2**k) for k in range(n)] + [(h, w)] if n else [(h, w)]


def render_photo(run_dir: str | Path, image_linear: np.ndarray, disparity: np.ndarray, focus: float,
                 aperture: float = 1.0, *, device: str | None = None) -> np.ndarray:
    """Shallow depth of field for a photo with the networks of `run_dir`.

    image_linear: (H, W, 3) linear RGB >= 0. disparity: (H, W) normalized disparity in [0, 1]
    (1 = nearest). focus: the in-focus disparity. aperture: r*/r_max in (0, 1].
    Returns linear RGB (H, W, 3) float32.
    """
    image = np.asarray(image_linear, dtype=np.float32)
    disp = np.asarray(disparity, dtype=np.float32)
    if image.ndim != 3 or image.shape[2] != 3:
        raise ValueError(f"image_linear must be (H, W, 3), got shape {image.shape}")
    if disp.shape != image.shape[:2]:
        raise ValueError(f"disparity must be {image.shape[:2]}, got shape {disp.shape}")
    if not (np.all(np.isfinite(image)) and np.all(np.isfinite(disp))):
        raise ValueError("image_linear and disparity must be finite")
    if not (math.isfinite(focus) and 0.0 <= focus <= 1.0):
        raise ValueError(f"focus must be a disparity in [0, 1], got {focus}")
    if not (math.isfinite(aperture) and 0.0 < aperture <= 1.0):
        raise ValueError(f"aperture (r*/r_max) must lie in (0, 1], got {aperture}")
    model, cfg = run_of(run_dir, "render", device)
    return render_with(model, cfg, image, disp, focus, aperture)


def default_device() -> str:
    return "cuda" if torch.cuda.is_available() else "cpu"


def run_task(run_dir: str | Path) -> str:
    """The [train] task of a run: "render" (the DoF networks) or "depth". Loads the model where
    `run_of` will use it, so the cache serves both."""
    return cached_model(run_dir, default_device())[1].train.task


def run_of(run_dir: str | Path, task: str, device: str | None = None):
    """(model, config) of a run of `task`; a run of the other task raises ValueError."""
    model, cfg = cached_model(run_dir, device or default_device())
    if cfg.train.task != task:
        what = {"render": "the DoF networks", "depth": "the depth network"}
        raise ValueError(f"{run_dir}: a run of {what[cfg.train.task]}, not of {what[task]}")
    return model, cfg


def predict_depth(run_dir: str | Path, image_linear: np.ndarray, *, device: str | None = None) -> np.ndarray:
    """(H, W) float32 normalized disparity (1 = nearest) of a photo, linear RGB (H, W, 3), by
    the depth network of `run_dir` (at its training scale: short side [data] crop)."""
    image = np.asarray(image_linear, dtype=np.float32)
    if image.ndim != 3 or image.shape[2] != 3 or not np.all(np.isfinite(image)):
        raise ValueError(f"image_linear must be finite (H, W, 3), got shape {image.shape}")
    model, cfg = run_of(run_dir, "depth", device)
    return predict_disparity(model, linear_to_srgb(np.clip(image, 0.0, 1.0)), cfg.data.crop)


def render_with(model, cfg, image: np.ndarray, disp: np.ndarray, focus: float, aperture: float = 1.0) -> np.ndarray:
    """`render_photo` with a loaded model (a DeepLensNet and its Config), on the model's device;
    the arguments are not checked again."""
    device = next(model.parameters()).device

    net_in = linear_to_srgb(image) if cfg.data.color == "srgb" else np.maximum(image, 0.0)
    # (H, W, 3) as a (1, 3, H, W) channels-last view: the model's layout, no copy
    x = torch.from_numpy(np.ascontiguousarray(net_in, dtype=np.float32)).permute(2, 0, 1)[None].to(device)
    d = torch.from_numpy(np.ascontiguousarray(disp))[None, None].to(device)
    h, w = image.shape[:2]
    low_side = cfg.infer.low_res_side
    work = (h, w)
    if max(h, w) < low_side:  # enlarge so that the lens blur still sees its training scale
        f = low_side / max(h, w)
        work = (max(1, round(h * f)), max(1, round(w * f)))
        x, d = bilinear(x, work), bilinear(d, work)
    sizes = inference_sizes(work, low_side)
    signed = coc_radius(d, focus, aperture)  # (disparity - focus) * r*/r_max at full resolution
    signed_lo = area_resize(signed, sizes[0])
    # px of CoC per unit of signed disparity at `work`: r_max at the training size (the lens
    # blur's low resolution times 2**levels)
    coc_px = cfg.model.coc_ref * max(work) / (low_side * 2 ** cfg.data.levels)
    classical = None
    if cfg.model.kind == "hybrid":  # its input: the classical render(s) at `work`, in the network's colours
        # rendered in linear light from what the network sees: at the photo's size the linear
        # photo itself (what its sRGB input decodes back to), not encoded and decoded again
        srgb = cfg.data.color == "srgb"
        if work == (h, w):
            lin = np.clip(image, 0.0, 1.0) if srgb else net_in
        else:
            lin = x[0].permute(1, 2, 0).float().cpu().numpy()
            lin = srgb_to_linear(np.clip(lin, 0.0, 1.0)) if srgb else lin
        # [model] near_shift is px at the training size: scaled to `work` as the CoC is
        shift = max(1, round(cfg.model.near_shift * coc_px / cfg.model.coc_ref)) if cfg.model.near_shift else 0
        out = classical_stack(lin, d[0, 0].float().cpu().numpy(), focus, coc_px * aperture, PHOTO_LOOK, "linear", shift)
        del lin  # (not held through the networks: peak memory)
        out = linear_to_srgb(out) if srgb else out
        classical = torch.from_numpy(np.ascontiguousarray(out)).permute(2, 0, 1)[None].to(device)
    with torch.inference_mode():
        _, out = model(x, signed_lo, sizes=sizes, rows=BAND_ROWS, signed_hi=signed, coc_px=coc_px,
                       classical=classical)
        out = area_resize(out, (h, w)).float()
    out = out[0].permute(1, 2, 0).cpu().numpy()
    if cfg.data.color == "srgb":
        return srgb_to_linear(np.clip(out, 0.0, 1.0))
    return np.maximum(out, 0.0).astype(np.float32)
