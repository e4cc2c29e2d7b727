"""Read a finished data set folder (docs/FORMAT.md): its manifest, its shards, its samples.

A small, dependency-light reader for the QA tools (`sheet`, `stats`, `verify`): shards are
read with `tarfile` (no torch import), members are grouped by sample key, and a sample is
decoded into arrays. Nothing here writes into the data set.
"""
from __future__ import annotations

import json
import tarfile
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import numpy as np

from dofsynth.io import decode_exr, decode_image

MANIFEST = "manifest.json"


class DatasetError(ValueError):
    """A data set folder that cannot be read; the message names the file."""


@dataclass(frozen=True)
class ShardInfo:
    """One shard as the manifest lists it."""

    split: str
    name: str          # path relative to the data set folder, e.g. "train/train-000000.tar"
    first_index: int
    samples: int
    sha256: str | None
    bytes: int | None


def load_manifest(out_dir: str | Path) -> dict:
    """The parsed `OUT/manifest.json` (raw dict); errors name the file."""
    path = Path(out_dir) / MANIFEST
    if not Path(out_dir).is_dir():
        raise FileNotFoundError(f"{out_dir}: no such data set folder")
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no manifest (an unfinished or foreign folder?)")
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise DatasetError(f"{path}: not valid JSON ({exc})") from exc
    if not isinstance(data, dict):
        raise DatasetError(f"{path}: expected a JSON object at the top level")
    return data


def _splits_block(manifest: dict) -> dict:
    splits = manifest.get("splits")
    if isinstance(splits, dict):
        return splits
    if isinstance(splits, list):  # [{"name": "train", "shards": [...]}, ...]
        return {s["name"]: s for s in splits if isinstance(s, dict) and "name" in s}
    raise DatasetError("manifest.json: no 'splits' object")


def manifest_splits(manifest: dict) -> list[str]:
    """Split names in the manifest, in its order."""
    return list(_splits_block(manifest))


def _first(d: dict, *names, default=None):
    for n in names:
        if n in d:
            return d[n]
    return default


def manifest_shards(manifest: dict, split: str) -> list[ShardInfo]:
    """The shards of `split` as listed by the manifest, in order."""
    block = _splits_block(manifest)
    if split not in block:
        raise ValueError(f"split {split!r} is not in the data set (it has {manifest_splits(manifest)})")
    entry = block[split]
    shards = entry.get("shards", []) if isinstance(entry, dict) else entry
    out = []
    for s in shards:
        name = str(_first(s, "path", "name", "file"))
        if "/" not in name:
            name = f"{split}/{name}"
        out.append(ShardInfo(
            split=split,
            name=name,
            first_index=int(_first(s, "first_index", "first", "start", default=0)),
            samples=int(_first(s, "samples", "count", "num_samples", "sample_count", default=0)),
            sha256=_first(s, "sha256", "hash"),
            bytes=_first(s, "bytes", "size", "size_bytes"),
        ))
    return out


def split_keys(manifest: dict, split: str) -> list[str]:
    """Every sample key of `split` in index order, from the manifest alone."""
    keys = []
    for sh in manifest_shards(manifest, split):
        keys += [f"{split}-{i:07d}" for i in range(sh.first_index, sh.first_index + sh.samples)]
    return keys


def split_member(name: str) -> tuple[str, str]:
    """'train-0000042.dof.1.png' -> ('train-0000042', 'dof.1.png')."""
    base = name.rsplit("/", 1)[-1]
    key, _, suffix = base.partition(".")
    return key, suffix


def iter_shard(path: str | Path) -> Iterator[tuple[str, dict[str, bytes]]]:
    """Yield (key, {suffix: bytes}) for each sample of a tar shard, in file order.

    Raises `DatasetError` (naming the shard) on an unreadable or truncated tar.
    """
    path = Path(path)
    current, members = None, {}
    try:
        with tarfile.open(path, "r:") as tar:
            for info in tar:
                if not info.isfile():
                    continue
                key, suffix = split_member(info.name)
                if current is not None and key != current:
                    yield current, members
                    members = {}
                current = key
                fh = tar.extractfile(info)
                data = fh.read() if fh is not None else b""
                if len(data) != info.size:
                    raise DatasetError(f"{path}: member {info.name} is truncated")
                members[suffix] = data
    except (tarfile.TarError, EOFError, OSError) as exc:
        raise DatasetError(f"{path}: unreadable tar ({exc})") from exc
    if current is not None:
        yield current, members


def decode_members(members: dict[str, bytes], key: str = "<sample>") -> dict:
    """Decode one sample's members into arrays.

    Returns {"key", "record" (the JSON dict), "aif" (H, W, 3) float32 sRGB in [0, 1],
    "depth" (H, W) float32 disparity, "cover" (H, W, 2) float32 front/middle alpha,
    "dof" [(H, W, 3) float32 sRGB, ...] ordered by target index}. Errors name the member.
    """
    def need(suffix):
        if suffix not in members:
            raise DatasetError(f"{key}: missing member {key}.{suffix}")
        return members[suffix]

    try:
        record = json.loads(need("json").decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise DatasetError(f"{key}.json: not valid JSON ({exc})") from exc
    aif = decode_image(need("aif.png"), f"{key}.aif.png")[:, :, :3]
    depth = decode_exr(need("depth.exr"), f"{key}.depth.exr", channels="Z")
    cover = decode_image(need("cover.png"), f"{key}.cover.png")
    cover = cover[:, :, :2] if cover.shape[2] >= 2 else np.repeat(cover, 2, axis=2)
    dof_idx = sorted(int(s.split(".")[1]) for s in members if s.startswith("dof.") and s.endswith(".png"))
    if dof_idx != list(range(len(dof_idx))):
        raise DatasetError(f"{key}: DoF targets are not numbered 0..N-1 (found {dof_idx})")
    dof = [decode_image(members[f"dof.{i}.png"], f"{key}.dof.{i}.png")[:, :, :3] for i in dof_idx]
    return {"key": key, "record": record, "aif": aif, "depth": depth, "cover": cover, "dof": dof}


def iter_samples(out_dir: str | Path, split: str, decode: bool = True) -> Iterator[dict]:
    """Every sample of a split in manifest order: decoded dicts (see `decode_members`), or with
    `decode=False` {"key", "members"} with the raw bytes."""
    out_dir = Path(out_dir)
    for sh in manifest_shards(load_manifest(out_dir), split):
        for key, members in iter_shard(out_dir / sh.name):
            yield decode_members(members, key) if decode else {"key": key, "members": members}


def read_samples(out_dir: str | Path, split: str, keys: list[str]) -> list[dict]:
    """Decode the samples with the given keys (in the order given), opening only their shards."""
    out_dir = Path(out_dir)
    manifest = load_manifest(out_dir)
    wanted = set(keys)
    found: dict[str, dict] = {}
    for sh in manifest_shards(manifest, split):
        idx = {f"{split}-{i:07d}" for i in range(sh.first_index, sh.first_index + sh.samples)}
        if not idx & wanted:
            continue
        for key, members in iter_shard(out_dir / sh.name):
            if key in wanted:
                found[key] = decode_members(members, key)
    missing = [k for k in keys if k not in found]
    if missing:
        raise DatasetError(f"{out_dir}: samples not found in split {split!r}: {missing[:5]}")
    return [found[k] for k in keys]
