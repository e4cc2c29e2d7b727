"""The training configuration: frozen dataclasses, one per TOML table, loaded from a recipe.

A training recipe (recipes/train-*.toml) has the tables [data], [augment], [model], [loss],
[train] and [infer]; every key is optional and defaults to the values below. Unknown tables or
keys are refused with a message naming them, so a typo never silently trains the wrong thing.
`dofsynth.train.data.resolve()` fills the two values that come from the data (`model.coc_ref`, `infer.low_res_side`)
and the result is written to RUN/config.toml and stored in every checkpoint.
"""
from __future__ import annotations

import dataclasses
import tomllib
from dataclasses import dataclass, field
from pathlib import Path


@dataclass(frozen=True)
class DataConfig:
    color: str = "srgb"            # colour space the networks see and predict: "srgb" | "linear"
    crop: int = 256                # side of the square high-res training crop, px (multiple of 2**levels)
    levels: int = 2                # the lens blur works at 1 / 2**levels of the crop; that many x2 upsamplings
    target: str = "random"         # which DoF target of a sample: "random" or an index ("0", "1", ...)
    shuffle_buffer: int = 256      # samples held in the shuffle buffer (per DataLoader worker)
    batch_size: int = 8            # per process (the global batch is batch_size * world size)
    num_workers: int = 2           # DataLoader worker processes per training process


@dataclass(frozen=True)
class AugmentConfig:
    """Depth corruption of the disparity the network sees (dofsynth.augment); probabilities
    are per sample (morphology: per foreground plane); a probability of 0 switches a kind off."""
    enabled: bool = True
    morph_prob: float = 0.5                            # dilate or erode a plane's region
    morph_kernel: tuple[int, int] = (3, 15)            # kernel side range, full-res px (odd)
    edge_blur_prob: float = 0.0                        # Gaussian blur of the disparity map
    edge_blur_sigma: tuple[float, float] = (0.5, 3.0)  # px
    noise_prob: float = 0.0                            # additive Gaussian noise
    noise_std: tuple[float, float] = (0.002, 0.02)     # disparity units
    quantize_prob: float = 0.0                         # round to a few levels (8-bit-like depth)
    quantize_levels: tuple[int, int] = (16, 256)
    shift_prob: float = 0.0                            # translate the whole map
    shift_max: int = 2                                 # px, per axis


@dataclass(frozen=True)
class ModelConfig:
    feat_channels: int = 8                        # per convolution of the per-channel extractor
    feat_dilations: tuple[int, ...] = (1, 2, 4, 8)  # one 3x3 conv each; c = feat_channels * len(...)
    kp_width: int = 32                            # kernel predictor (a small U-Net) base width
    kp_depth: int = 3                             # its number of x2 downsamplings
    up_width: int = 16                            # guided upsampler feature width
    coc_ref: float = 0.0                          # r_max: max CoC radius (full-res px) of the largest
                                                  # aperture; 0 = the largest max_coc in the data


@dataclass(frozen=True)
class LossConfig:
    alpha: float = 1.5    # J = sum|e|^(alpha+1) / sum|e|^alpha
    beta: float = 1.0     # loss = J(L) + beta * J(H)
    eps: float = 1e-8     # keeps J finite (and 0) when the error is zero
    l1: float = 0.0       # optional extra weight of a plain L1 term (see dofsynth.train.loss)


@dataclass(frozen=True)
class TrainConfig:
    seed: int = 0
    max_steps: int = 20000
    lr: float = 3e-4
    min_lr: float = 3e-5             # cosine decay ends here
    warmup_steps: int = 200
    weight_decay: float = 0.01
    betas: tuple[float, float] = (0.9, 0.99)
    grad_clip: float = 1.0           # 0 = off
    log_interval: int = 10
    eval_interval: int = 1000        # 0 = never (evaluation uses the test split, if present)
    eval_batches: int = 4
    checkpoint_interval: int = 1000  # a checkpoint is also written at the last step
    dtype: str = "bfloat16"          # autocast dtype on CUDA: bfloat16 | float16 | float32
    compile: bool = False            # torch.compile the model (CUDA only)


@dataclass(frozen=True)
class InferConfig:
    low_res_side: int = 0   # long side (px) of the lens-blur input at inference; 0 = image size / 2**levels


@dataclass(frozen=True)
class Config:
    data: DataConfig = field(default_factory=DataConfig)
    augment: AugmentConfig = field(default_factory=AugmentConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    loss: LossConfig = field(default_factory=LossConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    infer: InferConfig = field(default_factory=InferConfig)

    def to_dict(self) -> dict:
        return {f.name: _plain(dataclasses.asdict(getattr(self, f.name))) for f in dataclasses.fields(self)}


_TABLES = {f.name: f.default_factory for f in dataclasses.fields(Config)}  # type: ignore[misc]


def _plain(d: dict) -> dict:
    return {k: list(v) if isinstance(v, tuple) else v for k, v in d.items()}


def _coerce(cls, table: str, raw: dict, source: str):
    names = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(raw) - set(names))
    if unknown:
        raise ValueError(f"{source}: unknown key(s) in [{table}]: {', '.join(unknown)} "
                         f"(known: {', '.join(sorted(names))})")
    kw = {}
    for k, v in raw.items():
        default = getattr(cls(), k)
        if isinstance(default, tuple):
            v = tuple(v)
        elif isinstance(default, bool):
            if not isinstance(v, bool):
                raise ValueError(f"{source}: [{table}] {k} must be true or false, got {v!r}")
        elif isinstance(default, float) and isinstance(v, int):
            v = float(v)
        elif isinstance(default, str):
            v = str(v)
        kw[k] = v
    return cls(**kw)


def from_dict(d: dict, source: str = "<config>") -> Config:
    unknown = sorted(set(d) - set(_TABLES))
    if unknown:
        raise ValueError(f"{source}: unknown table(s) {', '.join(unknown)} (known: {', '.join(_TABLES)})")
    parts = {name: _coerce(type(factory()), name, d.get(name, {}), source) for name, factory in _TABLES.items()}
    cfg = Config(**parts)
    validate(cfg, source)
    return cfg


def load(path: str | Path) -> Config:
    """Read a training recipe (TOML); a missing file raises FileNotFoundError naming it."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such training config")
    try:
        raw = tomllib.loads(path.read_text())
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"{path}: not valid TOML ({exc})") from exc
    return from_dict(raw, str(path))


def validate(cfg: Config, source: str = "<config>") -> None:
    d, a, t = cfg.data, cfg.augment, cfg.train
    if d.color not in ("srgb", "linear"):
        raise ValueError(f"{source}: [data] color must be 'srgb' or 'linear', got {d.color!r}")
    if d.levels < 1:
        raise ValueError(f"{source}: [data] levels must be >= 1, got {d.levels}")
    if d.crop <= 0 or d.crop % (2 ** d.levels):
        raise ValueError(f"{source}: [data] crop {d.crop} must be a positive multiple of 2**levels = {2 ** d.levels}")
    if d.target != "random" and not d.target.isdigit():
        raise ValueError(f"{source}: [data] target must be 'random' or a target index, got {d.target!r}")
    if d.batch_size < 1 or d.num_workers < 0 or d.shuffle_buffer < 1:
        raise ValueError(f"{source}: [data] batch_size, shuffle_buffer must be >= 1 and num_workers >= 0")
    for name in ("morph_prob", "edge_blur_prob", "noise_prob", "quantize_prob", "shift_prob"):
        if not 0.0 <= getattr(a, name) <= 1.0:
            raise ValueError(f"{source}: [augment] {name} must lie in [0, 1], got {getattr(a, name)}")
    for name in ("morph_kernel", "edge_blur_sigma", "noise_std", "quantize_levels"):
        lo, hi = getattr(a, name)
        if not 0 <= lo <= hi:
            raise ValueError(f"{source}: [augment] {name} must be [low, high] with 0 <= low <= high")
    if a.morph_kernel[0] < 1 or a.quantize_levels[0] < 2:
        raise ValueError(f"{source}: [augment] morph_kernel >= 1 and quantize_levels >= 2 required")
    if not cfg.model.feat_dilations or cfg.model.feat_channels < 1:
        raise ValueError(f"{source}: [model] feat_dilations must be non-empty and feat_channels >= 1")
    if t.dtype not in ("bfloat16", "float16", "float32"):
        raise ValueError(f"{source}: [train] dtype must be bfloat16, float16 or float32, got {t.dtype!r}")
    if cfg.loss.alpha < 0 or cfg.loss.beta < 0 or cfg.loss.l1 < 0 or cfg.loss.eps <= 0:
        raise ValueError(f"{source}: [loss] alpha, beta, l1 must be >= 0 and eps > 0")
    if t.max_steps < 0 or t.lr <= 0:
        raise ValueError(f"{source}: [train] max_steps must be >= 0 and lr > 0")


def replace(cfg: Config, table: str, **kw) -> Config:
    """A copy of `cfg` with keys of one table changed (validated)."""
    new = dataclasses.replace(cfg, **{table: dataclasses.replace(getattr(cfg, table), **kw)})
    validate(new)
    return new


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return repr(v)
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise TypeError(f"cannot write {type(v)} to TOML")


def to_toml(cfg: Config) -> str:
    """The configuration as TOML text (round-trips through `from_dict(tomllib.loads(...))`)."""
    lines = []
    for table, values in cfg.to_dict().items():
        lines.append(f"[{table}]")
        lines += [f"{k} = {_toml_value(v)}" for k, v in values.items()]
        lines.append("")
    return "\n".join(lines)
