"""Checkpoints: one dict per file, as in nanoGPT.

    RUN/ckpt.pt  {"model": state_dict, "optimizer": state_dict, "step": int, "epoch": int,
                  "batch": int, "config": Config.to_dict(), "rng": {"torch", "cuda", "python"},
                  "best_score": float|None, "ema": state_dict|None, "format": 2}
    RUN/best.pt  {"model": state_dict, "config": ..., "step": int, "val": {name: value}, "format": 2}

`step` counts finished optimizer steps; (epoch, batch) is where the data stream stands, so a
resumed run continues with the next batch. `ema` is the moving average of the weights
([train] ema; `Ema`), which is what validation scores. best.pt holds the weights (the average
when there is one) of the best validation so far (`better`): what `load_model` gives for a run
folder when it exists, else ckpt.pt's average, else its weights. Files are written through a
temporary name, fsync and a rename (dofsynth.files.AtomicFile), so each is always complete.
"""
from __future__ import annotations

import copy
import random
from pathlib import Path

import torch

from dofsynth.files import AtomicFile
from dofsynth.train.config import Config, from_dict
from dofsynth.train.depth import DepthNet
from dofsynth.train.models import DeepLensNet, HybridNet
from dofsynth.train.weights import first_line, load_weights_file

CHECKPOINT = "ckpt.pt"
BEST = "best.pt"
FORMAT = 2  # 2: the networks' module names changed ([model] norm, up_depth, ...)


class Ema:
    """An exponential moving average of a model's weights (buffers, e.g. batch-norm statistics,
    copied as they are): after step t, p_ema += (1 - d) (p - p_ema) with d = min(decay,
    (1 + t) / (10 + t)), so early averages are not dominated by the random initial weights."""

    def __init__(self, model: torch.nn.Module, decay: float):
        self.decay = decay
        self.module = copy.deepcopy(model).eval().requires_grad_(False)

    @torch.no_grad()
    def update(self, model: torch.nn.Module, step: int) -> None:
        d = min(self.decay, (1 + step) / (10 + step))
        for e, p in zip(self.module.parameters(), model.parameters()):
            e.lerp_(p.detach(), 1.0 - d)
        for e, b in zip(self.module.buffers(), model.buffers()):
            e.copy_(b)


def better(val: dict, best: float | None) -> tuple[bool, float]:
    """Whether a validation result beats the best so far, and the new best: the PSNR of the
    DoF networks (higher), the disparity MAE of the depth network (lower)."""
    score = val["val_psnr"] if "val_psnr" in val else -val["val_mae"]
    return (best is None or score > best), (score if best is None else max(best, score))


def rng_states() -> dict:
    return {"torch": torch.get_rng_state(), "python": random.getstate(),
            "cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else None}


def set_rng_states(states: dict) -> None:
    torch.set_rng_state(states["torch"])
    random.setstate(states["python"])
    if states.get("cuda") is not None and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(states["cuda"])


def unwrap(model: torch.nn.Module) -> torch.nn.Module:
    """The plain module inside DistributedDataParallel and/or torch.compile wrappers."""
    model = getattr(model, "module", model)
    return getattr(model, "_orig_mod", model)


def _finite(model, path: Path, step: int) -> dict:
    """The model's state_dict; refuses weights holding NaN or inf, so a good file is never
    replaced by a broken one."""
    weights = unwrap(model).state_dict()
    bad = [n for n, p in weights.items() if p.is_floating_point() and not torch.isfinite(p).all()]
    if bad:
        raise ValueError(f"step {step}: not writing {path}: non-finite weights in {', '.join(bad[:3])}"
                         f"{', ...' if len(bad) > 3 else ''} (the last checkpoint is kept)")
    return weights


def save(path: str | Path, model, optimizer, step: int, epoch: int, batch: int, cfg: Config,
         best_score: float | None = None, ema: Ema | None = None) -> None:
    """Write the checkpoint atomically (temp name, fsync, rename)."""
    path = Path(path)
    state = {"model": _finite(model, path, step), "optimizer": optimizer.state_dict(),
             "step": step, "epoch": epoch, "batch": batch, "config": cfg.to_dict(),
             "rng": rng_states(), "best_score": best_score, "format": FORMAT,
             "ema": None if ema is None else ema.module.state_dict()}
    with AtomicFile(path) as fh:
        torch.save(state, fh)


def save_best(path: str | Path, model, step: int, cfg: Config, val: dict) -> None:
    """RUN/best.pt: the weights that scored `val` at `step` (atomically)."""
    state = {"model": _finite(model, Path(path), step), "config": cfg.to_dict(), "step": step,
             "val": val, "format": FORMAT}
    with AtomicFile(path) as fh:
        torch.save(state, fh)


def load(path: str | Path, map_location="cpu") -> dict:
    """A dofsynth checkpoint (the module docstring's dict), loaded without executing code."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no checkpoint")
    state = load_weights_file(path, "a dofsynth checkpoint (ckpt.pt of a training run)", map_location)
    if not isinstance(state, dict) or not {"model", "config", "format"} <= set(state):
        kind = type(state).__name__ if not isinstance(state, dict) else f"a dict with keys {sorted(state)[:4]}"
        raise ValueError(f"{path}: not a dofsynth checkpoint (ckpt.pt of a training run): it holds {kind}")
    if state.get("format") != FORMAT:
        raise ValueError(f"{path}: checkpoint format {state.get('format')}, expected {FORMAT}")
    return state


def build_model(cfg: Config) -> DeepLensNet | HybridNet | DepthNet:
    """The untrained network of the config's [train] task (and [model] kind)."""
    if cfg.train.task == "depth":
        return DepthNet(cfg.depth)
    return HybridNet(cfg.model) if cfg.model.kind == "hybrid" else DeepLensNet(cfg.model, cfg.data.levels)


def weights_path(run: str | Path) -> Path:
    """The file a run is used from: RUN/best.pt when validation chose one, else RUN/ckpt.pt;
    a file as it is."""
    run = Path(run)
    if not run.is_dir():
        return run
    return run / BEST if (run / BEST).is_file() else run / CHECKPOINT


def load_model(run_dir: str | Path, device="cpu") -> tuple[DeepLensNet | DepthNet, Config]:
    """The trained model (eval mode, on `device`) and its config, from `weights_path(run_dir)`
    (a DeepLensNet, or a DepthNet when its [train] task is "depth"): the moving average of the
    weights where the file holds one."""
    path = weights_path(run_dir)
    state = load(path)
    cfg = from_dict(state["config"], str(path))
    model = build_model(cfg)
    try:
        model.load_state_dict(state.get("ema") or state["model"])
    except RuntimeError as exc:
        raise ValueError(f"{path}: its weights do not fit the network its config describes: "
                         f"{first_line(exc)}") from None
    return model.to(device).eval(), cfg
