"""Read a finished data set folder (docs/FORMAT.md): its manifest, its shards, its samples.

A small reader for the QA tools (`sheet`, `stats`, `verify`, the HTML page) built on the
generator's own readers: dofsynth.manifest, dofsynth.shards (plain `tarfile`, no torch
import) and dofsynth.record.decode_sample. Nothing here writes into the data set.
"""
from __future__ import annotations

from pathlib import Path
from typing import Iterator

from dofsynth.manifest import ManifestError, load_manifest, manifest_shard_infos
from dofsynth.record import SampleDecodeError, decode_sample
from dofsynth.shards import ShardError, ShardInfo, read_shard

# Every error a damaged data set can raise while being read (all are ValueErrors naming the file).
READ_ERRORS = (ManifestError, ShardError, SampleDecodeError)


def load(out_dir: str | Path) -> dict:
    """The manifest of data set folder `out_dir`; FileNotFoundError names a missing folder."""
    out_dir = Path(out_dir)
    if not out_dir.is_dir():
        raise FileNotFoundError(f"{out_dir}: no such data set folder")
    return load_manifest(out_dir)


def manifest_splits(manifest: dict) -> list[str]:
    """Split names in the manifest, in its order."""
    return list(manifest["splits"])


def manifest_shards(manifest: dict, split: str) -> list[ShardInfo]:
    """The shards of `split` as the manifest lists them, in sample order (`.path` is relative
    to the data set folder)."""
    if split not in manifest["splits"]:
        raise ValueError(f"split {split!r} is not in the data set (it has {manifest_splits(manifest)})")
    return sorted(manifest_shard_infos({"splits": {split: manifest["splits"][split]}})[split],
                  key=lambda s: s.first_index)


def sample_count(out_dir: str | Path, splits=None) -> int | None:
    """How many samples the manifest lists (in `splits`, default all): a progress total; None
    when the manifest cannot be read (the command itself then says why)."""
    try:
        manifest = load(out_dir)
        return sum(int(manifest["splits"][s]["samples"]) for s in (splits or manifest_splits(manifest)))
    except (OSError, ValueError, KeyError, TypeError):
        return None


def split_keys(manifest: dict, split: str) -> list[str]:
    """Every sample key of `split` in index order, from the manifest alone."""
    return [k for sh in manifest_shards(manifest, split) for k in sh.keys()]


def iter_samples(out_dir: str | Path, split: str, decode: bool = True) -> Iterator[dict]:
    """Every sample of a split in manifest order: `record.decode_sample` dicts ({"key",
    "record", "aif", "depth", "cover", "dof"}), or with `decode=False` {"key", "members"}."""
    out_dir = Path(out_dir)
    for sh in manifest_shards(load(out_dir), split):
        for key, members in read_shard(out_dir / sh.path):
            yield decode_sample(members, key) if decode else {"key": key, "members": members}


def read_members_many(out_dir: str | Path, split: str, keys) -> dict[str, dict[str, bytes]]:
    """{key: {suffix: bytes}} for the given keys of `split`. Opens only the shards that hold
    them and reads only their members, so a few samples of a large data set come quickly."""
    out_dir = Path(out_dir)
    wanted = set(keys)
    found: dict[str, dict[str, bytes]] = {}
    for sh in manifest_shards(load(out_dir), split):
        here = wanted & set(sh.keys())
        if here:
            found.update(read_shard(out_dir / sh.path, keys=here))
    missing = [k for k in keys if k not in found]
    if missing:
        raise ValueError(f"{out_dir}: split {split!r} has no samples {missing[:5]}")
    return {k: found[k] for k in keys}


def read_samples(out_dir: str | Path, split: str, keys: list[str], progress=None) -> list[dict]:
    """Decode the samples with the given keys (returned in the order given); `progress(1)` is
    called per sample decoded."""
    raw = read_members_many(out_dir, split, keys)
    out = []
    for k in keys:
        out.append(decode_sample(raw.pop(k), k))
        if progress:
            progress(1)
    return out
