"""The shard plan of a run: per split, shards of `recipe.shard_size` consecutive sample indices
(the last may be shorter), `limit` capping the samples of each split; the global plan is
train's shards, then test's (`--shards A:B` numbers them)."""
from __future__ import annotations

import re
from dataclasses import dataclass

from dofsynth.rng import SPLITS, check_split, sample_key
from dofsynth.shards import shard_name


@dataclass(frozen=True)
class ShardTask:
    """One shard of the plan: samples first_index .. first_index + samples - 1 of `split`."""

    split: str
    index: int
    first_index: int
    samples: int

    @property
    def name(self) -> str:
        return shard_name(self.split, self.index)

    @property
    def path(self) -> str:
        return f"{self.split}/{self.name}"

    def keys(self) -> list[str]:
        return [sample_key(self.split, i) for i in range(self.first_index, self.first_index + self.samples)]


def split_size(recipe, split: str, limit: int | None = None) -> int:
    """Samples of `split` in the data set: the recipe's count, capped by `limit`."""
    check_split(split)
    n = int(recipe.samples.count(split))
    if limit is not None:
        if int(limit) != limit or limit < 0:
            raise ValueError(f"--limit must be an integer >= 0, got {limit}")
        n = min(n, int(limit))
    return n


def shard_count(recipe, split: str, limit: int | None = None) -> int:
    """How many shards `split` has in the plan (arithmetic: no task list is built)."""
    return -(-split_size(recipe, split, limit) // int(recipe.shard_size))


def plan_split(recipe, split: str, limit: int | None = None) -> list[ShardTask]:
    n, size = split_size(recipe, split, limit), int(recipe.shard_size)
    return [ShardTask(split, k, first, min(size, n - first)) for k, first in enumerate(range(0, n, size))]


def plan_shards(recipe, splits=SPLITS, limit: int | None = None) -> list[ShardTask]:
    """Every shard of the requested splits, in split then shard order."""
    return [t for s in splits for t in plan_split(recipe, s, limit)]


def shard_task(recipe, split: str, shard_index: int, limit: int | None = None) -> ShardTask:
    tasks = plan_split(recipe, split, limit)
    if not 0 <= shard_index < len(tasks):
        raise ValueError(f"shard {shard_index} of split {split!r}: the plan has shards 0..{len(tasks) - 1}")
    return tasks[shard_index]


def parse_shard_range(text: str) -> tuple[int, int | None]:
    """"A:B" (half-open, B > A >= 0) or "A:" (to the end of the plan) -> (A, B or None)."""
    m = re.fullmatch(r"\s*(\d+)\s*:\s*(\d*)\s*", str(text))
    if not m:
        raise ValueError(f"--shards {text!r}: expected A:B (shards A .. B-1 of the plan, e.g. 0:10) or A:")
    a, b = int(m[1]), (int(m[2]) if m[2] else None)
    if b is not None and b <= a:
        raise ValueError(f"--shards {text}: B must be greater than A (half-open range A:B)")
    return a, b
