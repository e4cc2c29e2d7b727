"""Which samples a split holds: OUT/manifest.json's shards as Segments (runs of consecutive
sample indices of one shard file), a train split cut into its fit and validation parts
([data] val_share: the last share by index), less the samples a review rejected; and their
raw members, each shard checked against its manifest sha256 the first time a process reads it.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

from dofsynth.manifest import load_manifest, manifest_shard_infos
from dofsynth.qa.marks import rejected
from dofsynth.rng import sample_key
from dofsynth.shards import read_shard
from dofsynth.train.config import Config

PARTS = ("all", "fit", "val")  # a whole split; train without / only its validation share


@dataclass(frozen=True)
class Segment:
    """Consecutive samples [lo, hi) (indices) of one shard file, and the file's sha256 in the
    manifest (checked the first time a process reads the file)."""
    path: str
    lo: int
    hi: int
    sha256: str | None = None


_CHECKED: set[tuple[str, str]] = set()  # (shard path, sha256) this process has read whole and found right

def held_out(n: int, val_share: float) -> int:
    """How many of n train samples the validation share holds (at least 1 when share > 0 and n >= 2)."""
    return 0 if val_share <= 0 or n < 2 else min(n - 1, max(1, round(n * val_share)))


def excluded(cfg: Config, data_dir: str | Path) -> set[str]:
    """The sample keys `[data] exclude` leaves out of data set `data_dir`: those a review
    rejected (OUT/qa-marks.json), or none."""
    return rejected(data_dir) if cfg.data.exclude == "rejected" else set()


def find_segments(data_dir: str | Path, split: str, part: str = "all", val_share: float = 0.0,
                  exclude=()) -> list[Segment]:
    """The samples of `split` (its `part`, see PARTS) that OUT/manifest.json lists, in index
    order, less the keys in `exclude` (the validation share is cut before they are left out,
    so a review does not move samples between training and validation)."""
    data_dir = Path(data_dir)
    infos = sorted(manifest_shard_infos(load_manifest(data_dir)).get(split, []), key=lambda i: i.first_index)
    if not infos:
        raise FileNotFoundError(f"{data_dir}: the data set has no {split} split (is --data a dofsynth data set?)")
    n = sum(i.samples for i in infos)
    cut = n - held_out(n, val_share)
    lo, hi = {"all": (0, n), "fit": (0, cut), "val": (cut, n)}[part]
    segs = [Segment(str(data_dir / i.path), max(lo, i.first_index), min(hi, i.first_index + i.samples), i.sha256)
            for i in infos]
    segs = [s for s in segs if s.hi > s.lo]
    drop = sorted(int(k.rsplit("-", 1)[1]) for k in exclude if k.startswith(f"{split}-"))
    if drop:  # each segment cut around the left-out indices inside it
        kept = []
        for s in segs:
            bounds = [s.lo] + [b for i in drop if s.lo <= i < s.hi for b in (i, i + 1)] + [s.hi]
            kept += [dataclasses.replace(s, lo=a, hi=b) for a, b in zip(bounds[::2], bounds[1::2]) if b > a]
        segs = kept
    if not segs:
        raise FileNotFoundError(f"{data_dir}: the {split} split has no {part} samples (val_share {val_share})")
    return segs


def raw_samples(shards, split: str | None = None) -> Iterator[dict]:
    """Every sample of the shards (paths, or Segments with `split` given) as a webdataset-style
    dict: {"__key__": key, "__url__": the shard's path, suffix: bytes}. A Segment's shard is
    checked against its manifest sha256 the first time this process reads it (read whole,
    hashed as it streams; a damaged shard raises ShardError naming it at its end, so even a
    member that is never drawn stops the run), then read as needed."""
    for shard in shards:
        keys, sha = None, None
        if isinstance(shard, Segment):
            keys = {sample_key(split, i) for i in range(shard.lo, shard.hi)}
            sha = shard.sha256 if (shard.path, shard.sha256) not in _CHECKED else None
            shard = shard.path
        for key, members in read_shard(shard, keys, sha256=sha):
            yield {"__key__": key, "__url__": str(shard), **members}
        if sha:
            _CHECKED.add((str(shard), sha))
