"""Split names and per-sample random generators.

Every random choice of sample `index` of `split` comes from one generator,
`default_rng(SeedSequence([recipe seed, SPLIT_ID[split], index]))`, so sample k is the same
whether drawn alone or in a batch, on any machine, with any worker count or resume.
"""
from __future__ import annotations

import numpy as np

SPLITS = ("train", "test")
SPLIT_ID = {"train": 0, "test": 1}


def check_split(split: str) -> str:
    if split not in SPLIT_ID:
        raise ValueError(f"split {split!r}: expected one of {', '.join(SPLITS)}")
    return split


def sample_key(split: str, index: int) -> str:
    """The key of sample `index` of `split` (tar member prefix, record `key`): "<split>-<index:07d>"."""
    return f"{split}-{index:07d}"


def sample_seed(recipe_seed: int, split: str, index: int) -> tuple[int, int, int]:
    """The SeedSequence entropy of one sample (recorded in its JSON as `seed`)."""
    check_split(split)
    if index < 0:
        raise ValueError(f"index must be >= 0, got {index}")
    return int(recipe_seed), SPLIT_ID[split], int(index)


def sample_rng(seed: tuple[int, ...]) -> np.random.Generator:
    """The generator of a sample's seed (`sample_seed`)."""
    return np.random.default_rng(np.random.SeedSequence(list(seed)))


def draw_uniform(rng: np.random.Generator, lo: float, hi: float) -> float:
    """A uniform draw from [lo, hi]; `lo` itself, drawing nothing, when the range is empty."""
    return float(lo if hi <= lo else rng.uniform(lo, hi))
