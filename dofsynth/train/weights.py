"""Loading weight files that someone hands in (`--model` runs, resumed checkpoints, `[depth]
weights`): never with pickle's code execution, and with one-line errors that name the file.

`torch.load(..., weights_only=True)` unpickles only tensors, numbers, strings and containers:
a crafted file cannot run code while it is read. Common wrappers of a state_dict (a training
checkpoint's "state_dict" / "model" entry, DistributedDataParallel's "module." prefix) are
unwrapped by `unwrap_state_dict`, which says what it took off.
"""
from __future__ import annotations

import pickle
import warnings
from pathlib import Path

import torch


def load_weights_file(path: str | Path, what: str, map_location="cpu"):
    """torch.load of a file someone hands in, with pickle's code execution refused
    (`weights_only=True`: tensors, numbers, strings and containers only). Any failure is a
    one-line ValueError that names the file, says it is not `what` and why, in one line."""
    path = Path(path)
    with open(path, "rb") as fh:
        head = fh.read(4)
    if not (head.startswith(b"PK\x03\x04") or head[:1] == b"\x80"):
        raise ValueError(f"{path}: not {what}: not a PyTorch file (neither a torch.save zip archive nor a pickle; "
                         f"it starts with {head!r})")
    try:
        with warnings.catch_warnings():  # torch warns about foreign pickle protocols on stderr
            warnings.simplefilter("ignore")
            return torch.load(path, map_location=map_location, weights_only=True)
    except pickle.UnpicklingError as exc:
        why = ("it holds Python objects other than tensors and plain data, which are never unpickled here"
               if "weights_only" in str(exc).lower() or "weights only" in str(exc).lower() else first_line(exc))
    except Exception as exc:  # torch raises many kinds (RuntimeError, KeyError, EOFError, ...) for foreign files
        why = f"{type(exc).__name__}: {first_line(exc)}" if isinstance(exc, (KeyError, IndexError)) else first_line(exc)
        why = why.split(". ")[0]  # torch's advice after the first sentence is for its own users
    raise ValueError(f"{path}: not {what}: {why}") from None


def first_line(exc: BaseException) -> str:
    """The first non-empty line of an exception's text (torch's errors run over many lines)."""
    text = str(exc).strip()
    return text.splitlines()[0].strip() if text else type(exc).__name__


WRAPPERS = ("state_dict", "model", "model_state_dict", "module", "net", "weights")


def unwrap_state_dict(state) -> tuple[object, str]:
    """(state_dict, what was unwrapped) of weights saved in a common wrapper: a training
    checkpoint {"state_dict" | "model" | ...: {...}} and/or the "module." prefix that
    DistributedDataParallel and DataParallel add to every name."""
    how = []
    while isinstance(state, dict) and not any(torch.is_tensor(v) for v in state.values()):
        inner = next((k for k in WRAPPERS if isinstance(state.get(k), dict)), None)
        if inner is None:
            break
        state, how = state[inner], how + [f'the "{inner}" entry']
    if isinstance(state, dict) and state and all(isinstance(k, str) and k.startswith("module.") for k in state):
        state, how = {k[len("module."):]: v for k, v in state.items()}, how + ['the "module." prefix']
    return state, " and ".join(how)
