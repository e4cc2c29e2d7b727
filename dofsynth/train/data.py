"""Training data: a torch IterableDataset over the WebDataset shards of docs/FORMAT.md.

One item (all float32 tensors, channels first; s = 2**levels, crop side C, low-res side C/s):

    image      (3, C, C)      all-in-focus image A, high res
    image_lo   (3, C/s, C/s)  A area-downsampled by s (box mean of s x s pixels)
    signed_lo  (1, C/s, C/s)  signed disparity (d - focus) * max_coc / coc_ref of the *corrupted*
                              disparity d, area-downsampled; = c / r_max, the signed CoC radius
                              over the largest aperture's max CoC (about [-1, 1])
    target_lo  (3, C/s, C/s)  the DoF target, area-downsampled
    target     (3, C, C)      the DoF target (never corrupted)
    disparity  (1, C, C)      the corrupted disparity in [0, 1], high res (for baselines)
    focus, max_coc, target_index, key, corruption (JSON text of the sampled parameters)

Colour: with [data] color = "srgb" (the default, as in the paper) images stay sRGB-encoded in
[0, 1]; with "linear" they are decoded to linear light. Crops are aligned to multiples of s, so
the low-res crop is exactly the crop of the low-res image.

Shards are those OUT/manifest.json lists (read with dofsynth.shards, the generator's own tar
reader). Splitting: the shard list is shuffled per epoch (seed, epoch), then split across distributed
ranks and DataLoader workers through webdataset's `split_by_node` / `split_by_worker`; when
there are fewer shards than ranks x workers every reader opens every shard and keeps every
(ranks x workers)-th sample instead, so small data sets never leave a reader empty. A shuffle
buffer mixes samples. Everything random about a sample (target, crop, corruption) comes from
`np.random.default_rng([seed, epoch, split, index])`, so it does not depend on the number of
workers or ranks. Batches are not padded: the last batch of a worker may be smaller.
"""
from __future__ import annotations

import json
import random
from itertools import islice
from typing import Iterator
from pathlib import Path

import numpy as np
import torch
import webdataset as wds
from torch.utils.data import DataLoader, IterableDataset

from dofsynth.color import srgb_to_linear
from dofsynth.io import decode_exr, decode_image
from dofsynth.manifest import load_manifest, manifest_shard_infos
from dofsynth.optics.coc import coc_radius
from dofsynth.rng import SPLIT_ID
from dofsynth.shards import read_shard
from dofsynth.train.augment import corrupt_disparity, layers_from_record
from dofsynth.train.config import Config, replace


def find_shards(data_dir: str | Path, split: str) -> list[str]:
    """The paths of the shards of `split` that OUT/manifest.json lists, in sample order."""
    data_dir = Path(data_dir)
    infos = manifest_shard_infos(load_manifest(data_dir)).get(split, [])
    if not infos:
        raise FileNotFoundError(f"{data_dir}: the data set has no {split} split (is --data a dofsynth data set?)")
    return [str(data_dir / i.path) for i in sorted(infos, key=lambda i: i.first_index)]


def raw_samples(shards) -> Iterator[dict]:
    """Every sample of the shards as a webdataset-style dict: {"__key__": key, "__url__": the
    shard's path, suffix: bytes}."""
    for shard in shards:
        for key, members in read_shard(shard):
            yield {"__key__": key, "__url__": str(shard), **members}


def peek_records(shard: str | Path, limit: int = 256) -> list[dict]:
    """The JSON records of the first `limit` samples of one shard."""
    return [json.loads(s["json"]) for s in islice(raw_samples([shard]), limit)]


def area_downsample(x: np.ndarray, factor: int) -> np.ndarray:
    """Box-mean downsample of (H, W[, C]) by an integer factor (H, W multiples of it)."""
    h, w = x.shape[:2]
    if h % factor or w % factor:
        raise ValueError(f"size {h}x{w} is not a multiple of {factor}")
    return x.reshape(h // factor, factor, w // factor, factor, *x.shape[2:]).mean(axis=(1, 3))


def signed_disparity(disparity, focus: float, max_coc: float, coc_ref: float):
    """The network's depth input: the signed CoC over the largest aperture's, c / r_max =
    (disparity - focus) * max_coc / coc_ref."""
    return coc_radius(disparity, focus, max_coc / coc_ref)


def _chw(x: np.ndarray) -> torch.Tensor:
    x = x[:, :, None] if x.ndim == 2 else x
    return torch.from_numpy(np.ascontiguousarray(x.transpose(2, 0, 1), dtype=np.float32))


def sample_rng(seed: int, epoch: int, split: str, index: int) -> np.random.Generator:
    """The generator of everything random about one training item (target, crop, corruption)."""
    return np.random.default_rng([seed, epoch, SPLIT_ID[split], index])


def training_item(sample: dict, cfg: Config, rng: np.random.Generator, *, crop: int | None = None,
                  target: int | None = None) -> dict:
    """Decode one raw webdataset sample (member suffix -> bytes) into a training item; a sample
    that cannot be used (a member missing or undecodable, NaN or inf in it) raises ValueError
    naming its shard and key.

    crop: side of the aligned random crop (None: the whole image, trimmed to a multiple of
    2**levels). target: which DoF target (None: as [data] target says).
    """
    key = sample.get("__key__", "?")
    try:
        return _item(sample, key, cfg, rng, crop, target)
    except (ValueError, KeyError) as exc:
        what = f"missing member {exc}" if isinstance(exc, KeyError) else str(exc)
        raise ValueError(f"{sample.get('__url__', '<shard>')}: sample {key}: {what}") from exc


def _item(sample: dict, key: str, cfg: Config, rng, crop, target) -> dict:
    record = json.loads(sample["json"])
    n_targets = len(record["targets"])
    if target is None:
        target = int(rng.integers(n_targets)) if cfg.data.target == "random" else int(cfg.data.target)
    if not 0 <= target < n_targets:
        raise ValueError(f"target {target} requested, the sample has {n_targets}")
    image = decode_image(sample["aif.png"], f"{key}.aif.png")[:, :, :3]
    depth = decode_exr(sample["depth.exr"], f"{key}.depth.exr")
    if not np.isfinite(depth).all():
        raise ValueError(f"depth.exr holds {int((~np.isfinite(depth)).sum())} NaN or inf values")
    cover = decode_image(sample["cover.png"], f"{key}.cover.png")
    dof = decode_image(sample[f"dof.{target}.png"], f"{key}.dof.{target}.png")[:, :, :3]
    focus = float(record["targets"][target]["focus"])
    max_coc = float(record["targets"][target]["max_coc"])

    corrupted, params = corrupt_disparity(depth, layers_from_record(record, cover), cfg.augment, rng)

    s = 2 ** cfg.data.levels
    h, w = depth.shape
    if crop is None:
        y0, x0, ch, cw = 0, 0, h - h % s, w - w % s
    else:
        if h < crop or w < crop:
            raise ValueError(f"image {h}x{w} is smaller than the crop {crop}")
        y0 = s * int(rng.integers((h - crop) // s + 1))
        x0 = s * int(rng.integers((w - crop) // s + 1))
        ch = cw = crop
    win = (slice(y0, y0 + ch), slice(x0, x0 + cw))
    image, dof, corrupted = image[win], dof[win], corrupted[win]
    if cfg.data.color == "linear":
        image, dof = srgb_to_linear(image), srgb_to_linear(dof)
    signed_lo = signed_disparity(area_downsample(corrupted, s), focus, max_coc, cfg.model.coc_ref)
    return {
        "image": _chw(image), "image_lo": _chw(area_downsample(image, s)),
        "signed_lo": _chw(signed_lo),
        "target_lo": _chw(area_downsample(dof, s)), "target": _chw(dof),
        "disparity": _chw(corrupted),
        "focus": focus, "max_coc": max_coc, "target_index": target, "key": key,
        "shard": str(sample.get("__url__", "")),
        "corruption": json.dumps(params, sort_keys=True),
    }


class DofShards(IterableDataset):
    """Iterate decoded items (see the module docstring) over shards, once per epoch.

    train=True: shuffled shards and samples, random crops of [data] crop. train=False: shards
    in order, no shuffle buffer, still crops (deterministic: epoch 0 seeds) so items batch.
    Call `set_epoch(e)` before each pass to get that epoch's order, crops and corruptions.
    """

    def __init__(self, shards: list[str], cfg: Config, *, train: bool, seed: int, split: str):
        if cfg.model.coc_ref <= 0:
            raise ValueError("model.coc_ref must be resolved (> 0) before loading data; see config.resolve")
        self.shards, self.cfg, self.train, self.seed, self.split = list(shards), cfg, train, seed, split
        self.epoch = 0

    def set_epoch(self, epoch: int) -> None:
        self.epoch = int(epoch)

    def _raw_samples(self):
        shards = list(self.shards)
        if self.train:
            np.random.default_rng([self.seed, self.epoch, 7]).shuffle(shards)
        rank, world, worker, workers = wds.utils.pytorch_worker_info()
        readers, slot = world * workers, rank * workers + worker
        if len(shards) >= readers:
            return raw_samples(wds.split_by_worker(wds.split_by_node(iter(shards))))
        return (s for i, s in enumerate(raw_samples(shards)) if i % readers == slot)

    def __iter__(self):
        samples = iter(self._raw_samples())
        if self.train and self.cfg.data.shuffle_buffer > 1:
            rank, _, worker, _ = wds.utils.pytorch_worker_info()
            seed = int(np.random.SeedSequence([self.seed, self.epoch, rank, worker]).generate_state(1)[0])
            bufsize = self.cfg.data.shuffle_buffer
            samples = wds.shuffle(bufsize, min(bufsize, 64), rng=random.Random(seed))(samples)
        epoch = self.epoch if self.train else 0
        for raw in samples:
            index = json.loads(raw["json"])["index"]
            rng = sample_rng(self.seed, epoch, self.split, int(index))
            yield training_item(raw, self.cfg, rng, crop=self.cfg.data.crop)


def make_loader(data_dir: str | Path, split: str, cfg: Config, *, train: bool, seed: int,
                pin_memory: bool = False) -> tuple[DofShards, DataLoader]:
    """The dataset and a DataLoader of [data] batch_size / num_workers over OUT/<split>."""
    ds = DofShards(find_shards(data_dir, split), cfg, train=train, seed=seed, split=split)
    loader = DataLoader(ds, batch_size=cfg.data.batch_size, num_workers=cfg.data.num_workers,
                        pin_memory=pin_memory, generator=torch.Generator().manual_seed(seed))
    return ds, loader


def resolve(cfg: Config, data_dir: str | Path) -> Config:
    """Fill the config values that come from the data, reading only the JSON records of the
    first training shard: model.coc_ref = the largest max_coc seen (r_max, full-res px) and
    infer.low_res_side = the largest image side / 2**levels. Values already set are kept."""


    if cfg.model.coc_ref > 0 and cfg.infer.low_res_side > 0:
        return cfg
    shard = find_shards(data_dir, "train")[0]
    records = peek_records(shard)
    if not records:
        raise ValueError(f"{shard}: no sample records (.json members)")
    if cfg.model.coc_ref <= 0:
        coc = max(float(t["max_coc"]) for r in records for t in r["targets"])
        if coc <= 0:
            raise ValueError(f"{shard}: every target has max_coc 0; set [model] coc_ref")
        cfg = replace(cfg, "model", coc_ref=coc)
    if cfg.infer.low_res_side <= 0:
        side = max(max(r["size"]) for r in records)
        cfg = replace(cfg, "infer", low_res_side=max(1, side // 2 ** cfg.data.levels))
    return cfg
