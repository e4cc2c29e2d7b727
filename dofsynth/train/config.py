"""The training configuration: frozen dataclasses, one per TOML table, read by the one typed
reader (dofsynth.config).

A training recipe (recipes/train-*.toml) has the tables [data], [augment], [model], [depth],
[loss], [train] and [infer]; every key is optional and its default and range live on its field below.
A wrong type, a value out of range, an unknown table or key is refused with `ConfigError`
naming the file and the dotted key, so a typo never silently trains the wrong thing.
`dofsynth.train.data.resolve()` fills the two values that come from the data (`model.coc_ref`,
`infer.low_res_side`) and the result is written to RUN/config.toml and stored in every
checkpoint. Key table: docs/training.md.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path

import tomli_w

from dofsynth.config import IntRange, Range, error, key, parse_toml, read, read_text, table, to_plain
from dofsynth.render.look import Highlight
from dofsynth.shipped import recipe_path

dataclass_kw = dataclasses.dataclass(frozen=True, kw_only=True)

# The data recipe each shipped training config (recipes/) is sized for; docs/training.md has the table.
DATA_RECIPES = {"train-tiny.toml": "smoke.toml", "train-demo.toml": "demo.toml", "train-learn.toml": "learn.toml",
                "train-learn-real.toml": "learn-real.toml",
                "train-deeplens.toml": "deeplens-18k.toml", "train-depth-tiny.toml": "smoke.toml",
                "train-depth-learn.toml": "learn.toml", "train-depth.toml": "deeplens-18k.toml"}


# the keys that hold paths, per table: relative ones are taken from the config file's folder (`load`)
PATH_KEYS = {"augment": ("predicted_run",), "depth": ("weights", "rgbd", "mattes")}


@dataclass_kw
class DataConfig:
    color: str = key("srgb", choices=("srgb", "linear"))  # colour space the networks see and predict
    crop: int = key(256, lo=1)           # side of the square high-res training crop, px (multiple of 2**levels)
    levels: int = key(2, lo=1)           # the lens blur works at 1 / 2**levels of the crop; that many x2 upsamplings
    target: str = key("random")          # which DoF target of a sample: "random" or an index ("0", "1", ...)
    val_share: float = key(0.05, lo=0.0, hi=0.5)  # the last share of train samples (by index), held out for validation
    shuffle_buffer: int = key(64, lo=1)  # decoded crops held in the shuffle buffer (per DataLoader worker)
    batch_size: int = key(8, lo=1)       # per process (the global batch is batch_size * world size)
    num_workers: int = key(2, lo=0)      # DataLoader worker processes per training process
    exclude: str = key("rejected", choices=("rejected", "none"))  # leave out samples a review rejected
    #                                                             # (OUT/qa-marks.json, dofsynth qa apply)


@dataclass_kw
class AugmentConfig:
    """Depth corruption of the disparity the network sees (dofsynth.train.augment); probabilities
    are per sample (morphology: per foreground plane); a probability of 0 switches a kind off."""
    enabled: bool = key(True)
    morph_prob: float = key(0.5, lo=0.0, hi=1.0)                    # dilate or erode a plane's region
    morph_kernel: IntRange = key((3, 15), lo=1)                     # kernel side range, full-res px (odd)
    edge_blur_prob: float = key(0.0, lo=0.0, hi=1.0)                # Gaussian blur of the disparity map
    edge_blur_sigma: Range = key((0.5, 3.0), lo=0.0)                # px
    noise_prob: float = key(0.0, lo=0.0, hi=1.0)                    # additive Gaussian noise
    noise_std: Range = key((0.002, 0.02), lo=0.0)                   # disparity units
    quantize_prob: float = key(0.0, lo=0.0, hi=1.0)                 # round to a few levels (8-bit-like depth)
    quantize_levels: IntRange = key((16, 256), lo=2)
    shift_prob: float = key(0.0, lo=0.0, hi=1.0)                    # translate the whole map
    shift_max: int = key(2, lo=0)                                   # px, per axis
    # the errors of real monocular estimates (docs/training.md gives each kind's disparity MAE)
    swap_prob: float = key(0.0, lo=0.0, hi=1.0)                     # the two foreground planes' depths swapped
    fill_prob: float = key(0.0, lo=0.0, hi=1.0)                     # per plane: holes and gaps closed at its depth
    fill_kernel: IntRange = key((5, 31), lo=1)                      # closing kernel side range, px (odd)
    warp_prob: float = key(0.0, lo=0.0, hi=1.0)                     # a smooth random warp of the map
    warp_px: Range = key((2.0, 8.0), lo=0.0)                        # std of the displacement, px
    warp_cells: int = key(4, lo=1)                                  # its control grid, cells per side
    remap_prob: float = key(0.0, lo=0.0, hi=1.0)                    # d -> clip(scale * d^gamma + shift)
    remap_scale: Range = key((0.7, 1.3), lo=0.0)
    remap_shift: Range = key((-0.15, 0.15))
    remap_gamma: Range = key((0.6, 1.6), lo=0.0, lo_open=True)
    clean_prob: float = key(0.0, lo=0.0, hi=1.0)                   # items given the clean disparity (none of the above)
    # a depth network's own errors (dofsynth.train.estimates): per sample, instead of the kinds above
    predicted_prob: float = key(0.0, lo=0.0, hi=1.0)                # the estimate of predicted_run
    predicted_run: str = key("")                                    # a depth run folder ([train] task = "depth")


@dataclass_kw
class ModelConfig:
    kind: str = key("deeplens", choices=("deeplens", "hybrid"))  # the paper's networks, or the classical render
    #                                                       # from the given depth plus a learned correction
    feat_channels: int = key(8, lo=1)                       # per convolution of the per-channel extractor
    feat_dilations: tuple[int, ...] = key((1, 2, 4, 8), lo=1)  # one 3x3 conv each; c = feat_channels * len(...)
    kp_width: int = key(32, lo=1)                           # kernel predictor (a small U-Net) base width (hybrid:
    kp_depth: int = key(3, lo=0)                            # the correction's U-Net); its number of x2 downsamplings
    features: str = key("channel", choices=("channel", "joint"))  # per-colour conv stack (paper) or one RGB stack
    raw_feature: bool = key(False)                          # the image itself is one of the c features (+1)
    feat_init: str = key("random", choices=("random", "blur"))  # the feature convs' start: PyTorch's random
    #                                                       # init, or a cascade of box blurs of the image
    kernel: str = key("free", choices=("free", "blur"))      # "blur": kernels >= 0 summing to 1 (softmax)
    kernel_prior: str = key("none", choices=("none", "discs"))  # "discs": the kernel adds a learned table over
    #                                                       # s started as disc blurs of radius |s| coc_ref / 2**levels
    light: str = key("input", choices=("input", "boosted"))  # the lens-blur module on the images as given (paper), or
    #                                                       # in linear light, highlight-boosted as the targets were
    boost: tuple[float, ...] = key((Highlight.threshold, Highlight.gain, Highlight.power), lo=0.0)
    #                                                       # light = "boosted": threshold (sRGB), gain, power: the
    #                                                       # recipe's [render.highlight] (dofsynth.train.light)
    norm: str = key("batch", choices=("none", "batch", "group"))  # after each conv of the predictor / upsampler (measured best)
    up_width: int = key(16, lo=1)                           # guided upsampler feature width
    up_depth: int = key(0, lo=0)                            # U-Net levels of its low-res branch (0: two convs)
    coc_ref: float = key(0.0, lo=0.0)                       # r_max: max CoC radius (full-res px) of the largest
                                                            # aperture; 0 = the largest max_coc in the data
    identity: bool = key(True)                              # the output is the input where no blur reaches (by
                                                            # construction; false: the paper's network alone)
    gate: str = key("none", choices=("none", "edges"))      # hybrid: "edges" = its correction only within the
                                                            # blur's reach of an edge of the given depth
    near_shift: int = key(0, lo=0)                          # hybrid: px (at the data's size) by which two more
                                                            # classical renders grow and shrink the given depth's
                                                            # near regions, mixed in per pixel; 0 = none
    gate_margin: int = key(0, lo=0)                         # gate = "edges": px (at the data's size) the gate
                                                            # reaches past an edge's blur (as far as the depth's
                                                            # edges may be off: near_shift); 0 = the blur's reach


@dataclass_kw
class DepthConfig:
    """The depth-prediction network and its data ([train] task = "depth"; dofsynth.train.depth).
    Paths are relative to the config file."""
    backbone: str = key("resnet50", choices=("resnet50", "resnet18"))  # encoder: conv1 .. layer3 of it
    width: int = key(64, lo=4)              # channels of conv1 (64 = torchvision's; ImageNet weights need 64)
    weights: str = key("")                  # local torchvision ImageNet state_dict of the backbone; "" = random init
    decoder_width: int = key(256, lo=8)     # channels after pyramid pooling; halved at each x2 upsampling
    bins: tuple[int, ...] = key((1, 2, 4, 8), lo=1)  # pyramid pooling bin sizes
    gamma: float = key(1.0, lo=0.0)         # J_d = |D - D^g|_1 + gamma |S - S^g|_1
    shards: bool = key(True)                # train on --data's shards (their disparity and coverage)
    rgbd: str = key("")                     # folder of RGB-D pairs: rgb/NAME.(png|jpg...) + depth/NAME.(exr|png|npy)
    rgbd_quantity: str = key("depth", choices=("depth", "disparity"))  # what the rgbd depth files hold (any scale)
    mattes: str = key("")                   # matting set for segmentation: fg/NAME.* + alpha/NAME.* (alpha >= 0.5)
    seg_share: float = key(0.25, lo=0.0, hi=1.0)  # share of each batch drawn from `mattes` (when given)
    jitter: float = key(0.0, lo=0.0, hi=1.0)  # probability of a photometric jitter per training image (colour order,
                                              # saturation, contrast, brightness): depth from structure, not colour


@dataclass_kw
class LossConfig:
    alpha: float = key(1.5, lo=0.0)    # J = sum|e|^(alpha+1) / sum|e|^alpha
    beta: float = key(1.0, lo=0.0)     # loss = J(L) + beta * J(H)
    eps: float = key(1e-8, lo=0.0, lo_open=True)  # keeps J finite (and 0) when the error is zero
    kind: str = key("weighted", choices=("weighted", "j"))  # J with its weights held constant in the gradient
    #                                  # (every pixel pulled toward its target), or the paper's J (dofsynth.train.loss)
    l1: float = key(0.0, lo=0.0)       # optional extra weight of a plain L1 term (see dofsynth.train.loss)
    teacher: float = key(0.0, lo=0.0)  # weight of D(L, the classical render of the given depth, area-downsampled);
    #                                  # model.kind = "deeplens" only (dofsynth.train.loss)
    ssim: float = key(0.0, lo=0.0)     # weight of 1 - SSIM(H, target), SSIM as the evaluation's (dofsynth.train.loss)


@dataclass_kw
class TrainConfig:
    task: str = key("render", choices=("render", "depth"))  # the DoF networks, or the depth network ([depth])
    seed: int = key(0, lo=0)
    max_steps: int = key(20000, lo=0)
    lr: float = key(3e-4, lo=0.0, lo_open=True)
    min_lr: float = key(3e-5, lo=0.0)              # cosine decay ends here
    warmup_steps: int = key(200, lo=0)
    weight_decay: float = key(0.01, lo=0.0)
    betas: Range = key((0.9, 0.99), lo=0.0, hi=1.0)
    grad_clip: float = key(1.0, lo=0.0)            # 0 = off
    ema: float = key(0.999, lo=0.0, hi=0.9999)  # decay of the weights' moving average, which validation
    #                                              # scores and RUN/best.pt keeps (dofsynth.train.checkpoint); 0 = off
    log_interval: int = key(10, lo=1)
    eval_interval: int = key(1000, lo=0)           # 0 = never; validation is on the held-out data.val_share
    eval_batches: int = key(0, lo=0)               # 0 = the whole validation share
    checkpoint_interval: int = key(1000, lo=1)     # a checkpoint is also written at the last step
    dtype: str = key("bfloat16", choices=("bfloat16", "float16", "float32"))  # autocast dtype on CUDA
    compile: bool = key(False)                     # torch.compile the model (CUDA only)


@dataclass_kw
class InferConfig:
    low_res_side: int = key(0, lo=0)   # long side (px) of the lens-blur input at inference; 0 = image size / 2**levels


@dataclass_kw
class Config:
    data: DataConfig = table(DataConfig)
    augment: AugmentConfig = table(AugmentConfig)
    model: ModelConfig = table(ModelConfig)
    depth: DepthConfig = table(DepthConfig)
    loss: LossConfig = table(LossConfig)
    train: TrainConfig = table(TrainConfig)
    infer: InferConfig = table(InferConfig)

    def to_dict(self) -> dict:
        return to_plain(self)


def _check(cfg: Config, source: str) -> None:
    """The rules between keys."""
    d = cfg.data
    if d.crop % (2 ** d.levels):
        raise error(source, "data.crop", f"a multiple of 2**levels = {2 ** d.levels}", d.crop)
    if d.target != "random" and not d.target.isdigit():
        raise error(source, "data.target", "'random' or a target index", d.target)
    if cfg.augment.predicted_prob > 0 and not cfg.augment.predicted_run:
        raise error(source, "augment.predicted_run", "a depth run folder when augment.predicted_prob > 0",
                    cfg.augment.predicted_run)
    if cfg.model.gate != "none" and cfg.model.kind != "hybrid":
        raise error(source, "model.gate", "'none' unless model.kind = 'hybrid' (it gates the hybrid's correction)",
                    cfg.model.gate)
    if cfg.model.gate_margin and cfg.model.gate != "edges":
        raise error(source, "model.gate_margin", "0 unless model.gate = 'edges' (it widens that gate)",
                    cfg.model.gate_margin)
    if cfg.model.feat_init != "random" and cfg.model.kind != "deeplens":
        raise error(source, "model.feat_init", "'random' unless model.kind = 'deeplens' (the hybrid has no feature stack)",
                    cfg.model.feat_init)
    m = cfg.model
    if m.kernel_prior != "none" and (m.kind, m.feat_init, m.kernel) != ("deeplens", "blur", "free"):
        raise error(source, "model.kernel_prior", "'none' unless model.kind = 'deeplens', feat_init = 'blur' and "
                    "kernel = 'free' (the table is fitted to the blur-started features, and added to free kernels)",
                    m.kernel_prior)
    if cfg.loss.teacher and cfg.model.kind != "deeplens":
        raise error(source, "loss.teacher", "0 unless model.kind = 'deeplens' (it pulls the lens-blur module's output "
                    "toward the classical render)", cfg.loss.teacher)
    if m.light != "input" and (m.kind, cfg.data.color) != ("deeplens", "srgb"):
        raise error(source, "model.light", "'input' unless model.kind = 'deeplens' and data.color = 'srgb' (it "
                    "decodes the module's sRGB input and encodes its output)", m.light)
    if len(m.boost) != 3 or m.boost[0] >= 1:
        raise error(source, "model.boost", "[threshold < 1, gain, power]", list(m.boost))
    if cfg.model.near_shift and cfg.model.kind != "hybrid":
        raise error(source, "model.near_shift", "0 unless model.kind = 'hybrid' (the renders it mixes are the hybrid's input)",
                    cfg.model.near_shift)


def from_dict(d: dict, source: str = "<config>") -> Config:
    cfg = read(Config, d, source)
    _check(cfg, source)
    return cfg


def load(path: str | Path) -> Config:
    """Read a training config (TOML), or the shipped one of that name ("train-demo"); a
    missing file raises FileNotFoundError naming it."""
    path = recipe_path(path)
    cfg = from_dict(parse_toml(read_text(path, "training config"), str(path)), str(path))
    here = Path(path).resolve().parent
    for table_name, keys in PATH_KEYS.items():
        values = getattr(cfg, table_name)
        paths = {k: str(here / v) for k in keys if (v := getattr(values, k)) and not Path(v).is_absolute()}
        cfg = replace(cfg, table_name, **paths) if paths else cfg
    return cfg


def replace(cfg: Config, table_name: str, **kw) -> Config:
    """A copy of `cfg` with keys of one table changed (validated like a file)."""
    d = cfg.to_dict()
    d[table_name] = {**d[table_name], **kw}
    return from_dict(d, f"<{table_name} override>")


def to_toml(cfg: Config) -> str:
    """The configuration as TOML text (round-trips through `from_dict(tomllib.loads(...))`),
    written by tomli_w: any string (a path with a quote, a backslash or a newline) stays valid."""
    return tomli_w.dumps({table: {k: list(v) if isinstance(v, tuple) else v for k, v in values.items()}
                          for table, values in cfg.to_dict().items()})
