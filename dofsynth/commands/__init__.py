"""One module per `dofsynth` subcommand; each defines `register(subparsers)` (see dofsynth.cli).

Shared argparse value types live here, so every command words its errors the same way.
"""
from __future__ import annotations

import argparse
import math
import os
from pathlib import Path


def int_at_least(lo: int):
    """An argparse `type` for an integer >= lo."""

    def parse(text: str) -> int:
        try:
            v = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
        if v < lo:
            raise argparse.ArgumentTypeError(f"expected an integer >= {lo}, got {v}")
        return v

    return parse


def float_at_least(lo: float):
    """An argparse `type` for a finite number >= lo."""

    def parse(text: str) -> float:
        try:
            v = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
        if not math.isfinite(v) or v < lo:
            raise argparse.ArgumentTypeError(f"expected a finite number >= {lo:g}, got {text!r}")
        return v

    return parse


def output_file(out: str, image: str, name: str, suffixes: tuple[str, ...]):
    """The file an image command writes: `out` itself when it names a file with one of
    `suffixes`, or OUT/<image stem><name> when `out` is a folder (existing, or ending in /),
    created if needed, like the folder --out of the other commands."""
    path = Path(out)
    if path.is_dir() or out.endswith((os.sep, "/")):
        return path / f"{Path(image).stem}{name}"
    if path.suffix.lower() not in suffixes:
        raise ValueError(f"--out {out}: must be a folder or a file ending in {' or '.join(suffixes)}")
    return path
