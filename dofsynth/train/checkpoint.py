"""Checkpoints: one dict per file, as in nanoGPT.

    {"model": state_dict, "optimizer": state_dict, "step": int, "epoch": int, "batch": int,
     "config": Config.to_dict(), "rng": {"torch", "cuda", "python"}, "best_val": float|None,
     "format": 2}

`step` counts finished optimizer steps; (epoch, batch) is where the data stream stands, so a
resumed run continues with the next batch. Files are written through a temporary name, fsync
and a rename (dofsynth.files.AtomicFile), so RUN/ckpt.pt is always complete.
"""
from __future__ import annotations

import random
from pathlib import Path

import torch

from dofsynth.files import AtomicFile
from dofsynth.train.config import Config, from_dict
from dofsynth.train.depth import DepthNet
from dofsynth.train.models import DeepLensNet
from dofsynth.train.weights import first_line, load_weights_file

CHECKPOINT = "ckpt.pt"
FORMAT = 2  # 2: the networks' module names changed ([model] norm, up_depth, ...)


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


def save(path: str | Path, model, optimizer, step: int, epoch: int, batch: int, cfg: Config,
         best_val: float | None = None) -> None:
    """Write the checkpoint atomically (temp name, fsync, rename); refuses weights holding NaN
    or inf, so a good checkpoint is never replaced by a broken one."""
    path = Path(path)
    bad = [n for n, p in unwrap(model).state_dict().items() if p.is_floating_point() and not torch.isfinite(p).all()]
    if bad:
        raise ValueError(f"step {step}: not writing {path}: non-finite weights in {', '.join(bad[:3])}"
                         f"{', ...' if len(bad) > 3 else ''} (the last checkpoint is kept)")
    state = {"model": unwrap(model).state_dict(), "optimizer": optimizer.state_dict(),
             "step": step, "epoch": epoch, "batch": batch, "config": cfg.to_dict(),
             "rng": rng_states(), "best_val": best_val, "format": FORMAT}
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


def build_model(cfg: Config) -> DeepLensNet | DepthNet:
    """The untrained network of the config's [train] task."""
    return DepthNet(cfg.depth) if cfg.train.task == "depth" else DeepLensNet(cfg.model)


def load_model(run_dir: str | Path, device="cpu") -> tuple[DeepLensNet | DepthNet, Config]:
    """The trained model (eval mode, on `device`) and the config of RUN/ckpt.pt (a DeepLensNet,
    or a DepthNet when its [train] task is "depth")."""
    run_dir = Path(run_dir)
    path = run_dir / CHECKPOINT if run_dir.is_dir() else run_dir
    state = load(path)
    cfg = from_dict(state["config"], str(path))
    model = build_model(cfg)
    try:
        model.load_state_dict(state["model"])
    except RuntimeError as exc:
        raise ValueError(f"{path}: its weights do not fit the network its config describes: "
                         f"{first_line(exc)}") from None
    return model.to(device).eval(), cfg
