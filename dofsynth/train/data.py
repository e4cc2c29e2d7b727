"""Training data: a torch IterableDataset over the shards of docs/FORMAT.md.

One item (all float32 tensors, channels first; s = 2**levels, crop side C, low-res side C/s):

    image      (3, C, C)      all-in-focus image A, high res
    image_lo   (3, C/s, C/s)  A area-downsampled by s (box mean of s x s pixels)
    signed_lo  (1, C/s, C/s)  signed disparity (d - focus) * max_coc / coc_ref of the *corrupted*
                              disparity d, area-downsampled; = c / r_max, the signed CoC radius
                              over the largest aperture's max CoC (about [-1, 1])
    target_lo  (3, C/s, C/s)  the DoF target, area-downsampled
    target     (3, C, C)      the DoF target (never corrupted)
    disparity  (1, C, C)      the corrupted disparity in [0, 1], high res (for baselines)
    classical  (3, C, C)      [model] kind = "hybrid" only: the classical render from it; (9, C, C)
                              with [model] near_shift (classical.classical_stack)
    teacher_lo (3, C/s, C/s)  [loss] teacher > 0 only: the classical render from it, area-downsampled
    focus, max_coc, target_index, key, shard, corruption (JSON text of the sampled parameters)

Colour: with [data] color = "srgb" (the default, as in the paper) images stay sRGB-encoded in
[0, 1]; with "linear" they are decoded to linear light. Crops are aligned to multiples of s, so
the low-res crop is exactly the crop of the low-res image. PNGs are cropped as stored codes and
only the crop is converted to float.

Which samples: OUT/manifest.json lists the shards and their sample indices. [data] val_share
holds out the last share of the train split (by index) for validation ("val"); training reads
the rest ("fit"). Splitting: per epoch the shard order is shuffled (seed, epoch); the samples in
that order are cut into equal contiguous shares, one per (rank, DataLoader worker), the few left
over dropped, so every rank makes the same number of batches (evaluation keeps every sample and
shares them as evenly as possible). A reader opens only the shards its share touches. Each
reader decodes and crops a sample before its shuffle buffer ([data] shuffle_buffer crops of
about 10 * C**2 bytes each), so memory does not grow with the image size. Everything random
about a sample (target, crop, corruption) comes from its own stream, `stream_rng(seed, "item",
epoch, split id, index)` (dofsynth.rng.STREAMS), so it does not depend on the number of workers
or ranks. A resumed epoch starts at its batch on every rank (`set_epoch(epoch, skip_batches=k)`):
the skipped samples are not decoded, and what follows is what the uninterrupted run would read.
"""
from __future__ import annotations

import dataclasses
import json
import random
import signal
from itertools import islice
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist
import webdataset as wds
from torch.utils.data import DataLoader, IterableDataset, get_worker_info

from dofsynth.color import srgb_to_linear
from dofsynth.io import decode_image, unit_float
from dofsynth.manifest import load_manifest, recipe_from_manifest
from dofsynth.codecs import decode_depth
from dofsynth.rng import SPLIT_ID, stream_int, stream_rng
from dofsynth.train.augment import corrupt_disparity, layers_from_record
from dofsynth.train.classical import classical_input, look_of
from dofsynth.train.config import Config, replace
from dofsynth.train.estimates import Estimates
from dofsynth.train.models import signed_disparity
from dofsynth.train.segments import Segment, excluded, find_segments, raw_samples


def area_downsample(x: np.ndarray, factor: int) -> np.ndarray:
    """Box-mean downsample of (H, W[, C]) by an integer factor (H, W multiples of it)."""
    h, w = x.shape[:2]
    if h % factor or w % factor:
        raise ValueError(f"size {h}x{w} is not a multiple of {factor}")
    return x.reshape(h // factor, factor, w // factor, factor, *x.shape[2:]).mean(axis=(1, 3))


def _chw(x: np.ndarray) -> torch.Tensor:
    x = x[:, :, None] if x.ndim == 2 else x
    return torch.from_numpy(np.ascontiguousarray(x.transpose(2, 0, 1), dtype=np.float32))


def sample_rng(seed: int, epoch: int, split: str, index: int) -> np.random.Generator:
    """The generator of everything random about one training item (target, crop, corruption)."""
    return stream_rng(seed, "item", epoch, SPLIT_ID[split], index)


def training_item(sample: dict, cfg: Config, rng: np.random.Generator, *, crop: int | None = None,
                  target: int | None = None, augment=None, disparity: np.ndarray | None = None) -> dict:
    """Decode one raw webdataset sample (member suffix -> bytes) into a training item; a sample
    that cannot be used (a member missing or undecodable, NaN or inf in it) raises ValueError
    naming its shard and key.

    crop: side of the aligned random crop (None: the whole image, trimmed to a multiple of
    2**levels). target: which DoF target (None: as [data] target says). augment: the
    corruption (an AugmentConfig; None: the config's [augment]). disparity: a map (H, W) given
    instead of the sample's, corrupted or not (an estimate's: `dofsynth eval --depth
    predicted:RUN`).
    """
    return finish_item(decode_crop(sample, cfg, rng, crop=crop, target=target, augment=augment,
                                   disparity=disparity), cfg)


def decode_crop(sample: dict, cfg: Config, rng, *, crop: int | None, target: int | None = None,
                augment=None, disparity: np.ndarray | None = None) -> dict:
    """The compact half of `training_item`: the chosen target, the corrupted (or given)
    disparity and the crop, as stored codes (images) and float32 (disparity); what the shuffle
    buffer holds."""
    key = sample.get("__key__", "?")
    try:
        return _decode_crop(sample, key, cfg, rng, crop, target, cfg.augment if augment is None else augment,
                            disparity)
    except (ValueError, KeyError) as exc:
        what = f"missing member {exc}" if isinstance(exc, KeyError) else str(exc)
        raise ValueError(f"{sample.get('__url__', '<shard>')}: sample {key}: {what}") from exc


def _decode_crop(sample: dict, key: str, cfg: Config, rng, crop, target, augment, given=None) -> dict:
    record = json.loads(sample["json"])
    n_targets = len(record["targets"])
    if target is None:
        target = int(rng.integers(n_targets)) if cfg.data.target == "random" else int(cfg.data.target)
    if not 0 <= target < n_targets:
        raise ValueError(f"target {target} requested, the sample has {n_targets}")
    depth = decode_depth(sample["depth.exr"], f"{key}.depth.exr")
    if not np.isfinite(depth).all():
        raise ValueError(f"depth.exr holds {int((~np.isfinite(depth)).sum())} NaN or inf values")
    if given is not None:
        if np.shape(given) != depth.shape:
            raise ValueError(f"the disparity given is {np.shape(given)}, depth.exr {depth.shape}")
        corrupted, params = np.asarray(given, np.float32), {"given": True}
    else:
        cover = decode_image(sample["cover.png"], f"{key}.cover.png")
        corrupted, params = corrupt_disparity(depth, layers_from_record(record, cover), augment, rng)

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
    codes = {}
    for name, member in (("image", "aif.png"), ("target", f"dof.{target}.png")):
        img = decode_image(sample[member], f"{key}.{member}", raw=True)
        if img.shape[:2] != (h, w):
            raise ValueError(f"{member} is {img.shape[1]}x{img.shape[0]}, depth.exr {w}x{h}")
        codes[name] = np.ascontiguousarray(img[win][:, :, :3])
    t = record["targets"][target]
    return {**codes, "disparity": np.ascontiguousarray(corrupted[win]), "focus": float(t["focus"]),
            "max_coc": float(t["max_coc"]), "target_index": target, "key": key,
            "shard": str(sample.get("__url__", "")), "corruption": json.dumps(params, sort_keys=True),
            "look": look_of(record)}


def full_res_signed(b: dict, cfg) -> dict:
    """The networks' keywords signed_hi (the signed disparity of the batch's corrupted
    disparity at full resolution), coc_px (r_max: full-resolution px per unit of it) and, for
    the hybrid, classical (its render from that disparity)."""
    focus, max_coc = (torch.as_tensor(b[k], dtype=torch.float32, device=b["disparity"].device).reshape(-1, 1, 1, 1)
                      for k in ("focus", "max_coc"))
    signed = signed_disparity(b["disparity"], focus, max_coc, cfg.model.coc_ref)
    return {"signed_hi": signed, "coc_px": cfg.model.coc_ref, "classical": b.get("classical")}


def finish_item(c: dict, cfg: Config) -> dict:
    """A `decode_crop` result as the float32 tensors of a training item."""
    s = 2 ** cfg.data.levels
    image, dof = unit_float(c["image"], c["key"]), unit_float(c["target"], c["key"])
    if cfg.data.color == "linear":
        image, dof = srgb_to_linear(image), srgb_to_linear(dof)
    corrupted = c["disparity"]
    signed_lo = signed_disparity(area_downsample(corrupted, s), c["focus"], c["max_coc"], cfg.model.coc_ref)
    extra = {}
    if cfg.model.kind == "hybrid":
        extra["classical"] = _chw(classical_input(c, cfg.data.color, cfg.model.near_shift))
    if cfg.loss.teacher > 0:
        extra["teacher_lo"] = _chw(area_downsample(classical_input(c, cfg.data.color), s))
    return {**extra,
        "image": _chw(image), "image_lo": _chw(area_downsample(image, s)),
        "signed_lo": _chw(signed_lo),
        "target_lo": _chw(area_downsample(dof, s)), "target": _chw(dof),
        "disparity": _chw(corrupted),
        **{k: c[k] for k in ("focus", "max_coc", "target_index", "key", "shard", "corruption")},
    }


def process_slot(rank: int | None = None, world: int | None = None) -> tuple[int, int, int, int]:
    """(rank, world, worker, workers) of the calling process: torch.distributed's rank and world
    size when initialised (else the arguments, else 0 and 1), the DataLoader worker's id."""
    if rank is None or world is None:
        rank, world = (dist.get_rank(), dist.get_world_size()) if dist.is_available() and dist.is_initialized() else (0, 1)
    info = get_worker_info()
    return rank, world, (info.id if info else 0), (info.num_workers if info else 1)


def share(segments: list[Segment], start: int, stop: int) -> list[Segment]:
    """Positions [start, stop) of the samples of `segments` taken in order, as segments."""
    out, pos = [], 0
    for seg in segments:
        n = seg.hi - seg.lo
        a, b = max(start, pos), min(stop, pos + n)
        if b > a:
            out.append(dataclasses.replace(seg, lo=seg.lo + a - pos, hi=seg.lo + b - pos))
        pos += n
    return out


class DofShards(IterableDataset):
    """Iterate decoded items (see the module docstring) over segments of a split, once per epoch.

    train=True: shuffled shard order and samples, random crops of [data] crop, equal shares.
    train=False: index order, no shuffle buffer, deterministic crops (epoch 0 seeds), every
    sample once across all readers. Call `set_epoch(e, skip_batches=k)` before each pass.
    rank/world: for tests; by default torch.distributed's.
    """

    def __init__(self, segments: list[Segment], cfg: Config, *, train: bool, seed: int, split: str,
                 rank: int | None = None, world: int | None = None, estimates: str | Path | None = None):
        if cfg.model.coc_ref <= 0:
            raise ValueError("model.coc_ref must be resolved (> 0) before loading data; see config.resolve")
        if cfg.augment.predicted_prob > 0 and estimates is None:
            raise ValueError("augment.predicted_prob > 0: the depth estimates file is needed "
                             "(dofsynth.train.estimates.write_estimates)")
        self.segments, self.cfg, self.train, self.seed, self.split = list(segments), cfg, train, seed, split
        self.rank, self.world = rank, world
        self.estimates = Estimates(estimates) if cfg.augment.predicted_prob > 0 else None
        self.epoch, self.skip_batches = 0, 0

    def set_epoch(self, epoch: int, skip_batches: int = 0) -> None:
        self.epoch, self.skip_batches = int(epoch), int(skip_batches)

    def __len__(self) -> int:
        """Samples per epoch across all readers of this process (train: after the equal cut)."""
        _, world, _, workers = process_slot(self.rank, self.world)
        n = sum(s.hi - s.lo for s in self.segments)
        return (n // (world * workers)) * workers if self.train else n

    def _mine(self) -> tuple[list[Segment], int, int, int, int]:
        """(this reader's segments, its share size, rank, reader id, workers). The DataLoader
        takes batch k of an epoch from worker k % workers and always starts with worker 0, so
        after skip_batches the workers play the readers rotated by that many."""
        rank, world, worker, workers = process_slot(self.rank, self.world)
        worker = (worker + self.skip_batches) % workers
        segs = list(self.segments)
        if self.train:
            order = stream_rng(self.seed, "shard_order", self.epoch).permutation(len(segs))
            segs = [segs[i] for i in order]
        n, readers, slot = sum(s.hi - s.lo for s in segs), world * workers, rank * workers + worker
        if self.train:
            m = n // readers
            start, stop = slot * m, (slot + 1) * m
        else:
            start, stop = n * slot // readers, n * (slot + 1) // readers
        return share(segs, start, stop), stop - start, rank, worker, workers

    def __iter__(self):
        segs, m, rank, worker, workers = self._mine()
        batch = self.cfg.data.batch_size
        done = sum(1 for i in range(self.skip_batches) if i % workers == worker)  # batches this worker made
        skip = min(m, done * batch)
        epoch = self.epoch if self.train else 0
        crop = self.cfg.data.crop

        def compact(pos_raw):
            pos, raw = pos_raw
            if pos in skipped:  # will be dropped: not decoded
                return pos, None
            index = int(json.loads(raw["json"])["index"])
            return pos, decode_crop(raw, self.cfg, sample_rng(self.seed, epoch, self.split, index), crop=crop,
                                    disparity=self._estimate(raw["__key__"], epoch, index))

        shuffled = self.train and self.cfg.data.shuffle_buffer > 1
        seed = stream_int(self.seed, "shuffle", self.epoch, rank, worker)
        order = list(self._shuffle(iter(range(m)), seed)) if shuffled else range(m)  # counts alone decide it
        skipped = set(order[:skip])
        stream = map(compact, enumerate(raw_samples(segs, self.split)))
        if shuffled:
            stream = self._shuffle(stream, seed)
        for _, c in islice(stream, skip, None):
            yield finish_item(c, self.cfg)

    def _estimate(self, key: str, epoch: int, index: int) -> np.ndarray | None:
        """The depth run's estimate of the sample, with probability [augment] predicted_prob
        (its own stream), else None: the corruption kinds then make the disparity."""
        p = self.cfg.augment.predicted_prob
        if p <= 0 or stream_rng(self.seed, "estimate", epoch, SPLIT_ID[self.split], index).random() >= p:
            return None
        return self.estimates(key)

    def _shuffle(self, items, seed: int):
        size = self.cfg.data.shuffle_buffer
        return wds.shuffle(size, min(size, 64), rng=random.Random(seed))(items)


def from_workers(loader):
    """Iterate a DataLoader; an error raised in one of its worker processes comes out as the
    error itself, whose message names the file and sample (torch re-raises it wrapped in the
    worker's traceback, which is no one-line message)."""
    it = iter(loader)
    while True:
        try:
            batch = next(it)
        except StopIteration:
            return
        except Exception as exc:
            text = str(exc)
            if not (text.startswith("Caught ") and "Original Traceback" in text):
                raise
            last = text.rstrip().splitlines()[-1]
            try:
                plain = type(exc)(last.split(": ", 1)[1] if ": " in last else last)
            except Exception:  # an error type that takes other arguments: leave it as torch gave it
                raise exc from None
            raise plain from None
        yield batch


def quiet_worker(_worker_id: int) -> None:
    """DataLoader workers leave Ctrl-C to the training process (one line, not a traceback each)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def make_loader(data_dir: str | Path, split: str, cfg: Config, *, train: bool, seed: int, part: str = "all",
                pin_memory: bool = False, estimates: str | Path | None = None) -> tuple[DofShards, DataLoader]:
    """The dataset and a DataLoader of [data] batch_size / num_workers over a split's `part`
    (estimates: the depth estimates file, with [augment] predicted_prob > 0)."""
    segs = find_segments(data_dir, split, part, cfg.data.val_share, excluded(cfg, data_dir))
    ds = DofShards(segs, cfg, train=train, seed=seed, split=split, estimates=estimates)
    workers = cfg.data.num_workers
    loader = DataLoader(ds, batch_size=cfg.data.batch_size, num_workers=workers, pin_memory=pin_memory,
                        prefetch_factor=4 if workers else None, worker_init_fn=quiet_worker,
                        generator=torch.Generator().manual_seed(stream_int(seed, "loader")))
    return ds, loader


def data_facts(recipe) -> tuple[float, int]:
    """(r_max, long side) of a data set's recipe (`recipe_from_manifest`): the high end of
    focus.max_coc (full-res px) and the output size (px)."""
    return float(recipe.focus.max_coc[1]), int(recipe.size)


def resolve(cfg: Config, data_dir: str | Path) -> Config:
    """Fill the config values that come from the data (its manifest's recipe): model.coc_ref =
    the largest max_coc the recipe can draw (r_max, full-res px) and infer.low_res_side = the
    image side / 2**levels. Values already set are kept. [model] light = "boosted" is refused
    unless [model] boost is the recipe's highlight boost."""
    boosted = cfg.model.light == "boosted"
    if not boosted and cfg.model.coc_ref > 0 and cfg.infer.low_res_side > 0:
        return cfg
    recipe = recipe_from_manifest(load_manifest(data_dir), data_dir)  # (read once)
    if boosted:
        render = recipe.render
        if not render.linear_light:
            raise ValueError(f"{data_dir}: its targets are blurred in sRGB (render.linear_light = false), so "
                             "[model] light = 'boosted' does not apply")
        hl = render.highlight
        want = (hl.threshold, hl.gain, hl.power) if hl.enabled else (cfg.model.boost[0], 0.0, cfg.model.boost[2])
        if tuple(cfg.model.boost) != want:
            raise ValueError(f"{data_dir}: [model] boost = {list(cfg.model.boost)}, but the data's recipe boosts "
                             f"highlights with {list(want)} ([render.highlight]); set [model] boost to that")
    coc, side = data_facts(recipe)
    if cfg.model.coc_ref <= 0:
        if coc <= 0:
            raise ValueError(f"{data_dir}: the recipe's focus.max_coc is 0 everywhere; set [model] coc_ref")
        cfg = replace(cfg, "model", coc_ref=coc)
    if cfg.infer.low_res_side <= 0:
        cfg = replace(cfg, "infer", low_res_side=max(1, side // 2 ** cfg.data.levels))
    return cfg
