"""Split names and per-sample random generators.

Every random choice of sample `index` of `split` comes from one generator,
`default_rng(SeedSequence([recipe seed, SPLIT_ID[split], index]))`, so sample k is the same
whether drawn alone or in a batch, on any machine, with any worker count or resume.

Training draws from named streams of its seed (`stream_rng(seed, "item", epoch, split_id,
index)`): the stream's id comes second, so two streams never share a generator whatever
their keys, and each site names what it draws instead of a magic tag.
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


# The training streams (dofsynth.train): what each draws, and its id in the SeedSequence.
STREAMS = {
    "item": 1,          # one training item: target, crop, depth corruption (keys: epoch, split id, index)
    "shard_order": 2,   # the order of a training epoch's shard segments (keys: epoch)
    "shuffle": 3,       # a loader reader's shuffle buffer (keys: epoch, rank, worker)
    "depth_plan": 4,    # the depth trainer's batches of an epoch (keys: epoch)
    "depth_item": 5,    # one depth-training item's crop and augmentation (keys: epoch, batch, slot)
    "init": 6,          # the initial weights (no keys)
    "loader": 7,        # the torch DataLoader's own generator (no keys)
    "estimate": 8,      # whether a training item takes the depth run's estimate (keys: epoch, split id, index)
}


def stream_seed(seed: int, stream: str, *keys: int) -> np.random.SeedSequence:
    """The SeedSequence of one named training stream (STREAMS) of a run's `seed`."""
    if stream not in STREAMS:
        raise ValueError(f"unknown random stream {stream!r}; known: {', '.join(STREAMS)}")
    return np.random.SeedSequence([int(seed), STREAMS[stream], *(int(k) for k in keys)])


def stream_rng(seed: int, stream: str, *keys: int) -> np.random.Generator:
    """The numpy generator of one named training stream (STREAMS) of a run's `seed`."""
    return np.random.default_rng(stream_seed(seed, stream, *keys))


def stream_int(seed: int, stream: str, *keys: int) -> int:
    """A 63-bit integer seed of one named stream (for torch's generators)."""
    return int(stream_seed(seed, stream, *keys).generate_state(2, np.uint64)[0] >> np.uint64(1))


def draw_uniform(rng: np.random.Generator, lo: float, hi: float) -> float:
    """A uniform draw from [lo, hi]; `lo` itself, drawing nothing, when the range is empty."""
    return float(lo if hi <= lo else rng.uniform(lo, hi))
