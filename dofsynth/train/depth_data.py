"""Training data of the depth network: mixed batches of depth samples and segmentation samples.

Sources ([depth] table of the config):
  shards  dofsynth's own data set (--data): the all-in-focus image, its disparity (depth.exr)
          and its foreground coverage (cover.png: front or middle plane >= 0.5): both terms.
  rgbd    a folder of RGB-D pairs, rgb/NAME.(png|jpg|tif|webp|exr) + depth/NAME.(exr|png|tif|npy),
          e.g. a phone's portrait-mode exports: depth (any unit; 0, negative or non-finite =
          unknown) or disparity (any scale), as [depth] rgbd_quantity says. Depth term only.
  mattes  a matting set in the fg/NAME.* + alpha/NAME.* layout: segmentation = alpha >= 0.5.
          Segmentation term only.
Depth becomes disparity (1 / depth) and every map is min-max normalized over its known pixels
(again over the crop), as the paper normalises both prediction and ground truth.

One item (float32 tensors, C = [data] crop): image (3, C, C) sRGB in [0, 1]; depth (1, C, C)
normalized disparity; depth_valid (1, C, C) 1 where known; seg (1, C, C) in {0, 1};
has_depth, has_seg (0-d, 1 when the item has that supervision); key (the file or sample).
Every image is resized so that its short side is C, then cropped to C x C (training: a random
crop, a random horizontal flip and, with probability [depth] jitter, random colours;
evaluation: the centre).

Batches: each training batch takes round(batch_size * seg_share) items from `mattes` (when
given) and the rest from the depth sources, each in a per-epoch permutation (the shorter list
wraps around); batch g of an epoch is the same items, crops and flips whatever the number of
ranks or DataLoader workers (rng [seed, epoch, g, slot]); ranks take every world-th batch, all
the same number. `set_epoch(e, skip_batches=k)` resumes an epoch at its batch k.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from torch.utils.data import DataLoader, IterableDataset

from dofsynth.color import linear_to_srgb
from dofsynth.image import resize
from dofsynth.io import decode_image, normalize_disparity, read_depth, read_image, unit_float
from dofsynth.codecs import decode_depth
from dofsynth.rng import sample_key, stream_rng
from dofsynth.shards import member_index, read_members
from dofsynth.train.config import Config
from dofsynth.train.data import process_slot, quiet_worker
from dofsynth.train.segments import excluded, find_segments

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".webp", ".exr")
DEPTH_SUFFIXES = (".exr", ".png", ".tif", ".tiff", ".npy")


@dataclass(frozen=True)
class Item:
    """One training sample: kind "shard" (path = shard, other = sample key), "rgbd" (path =
    the RGB file, other = its depth file) or "matte" (path = fg file, other = alpha file);
    a shard's sha256 in the manifest (checked when a process first indexes the shard)."""
    kind: str
    path: str
    other: str
    sha256: str | None = None


def pair_files(root: str | Path, a: str, b: str, b_suffixes: tuple[str, ...]) -> list[tuple[Path, Path]]:
    """(root/a/NAME.x, root/b/NAME.y) for every NAME in both folders; a file of one without a
    partner in the other, or a missing folder, raises ValueError naming it."""
    root = Path(root)
    for sub in (a, b):
        if not (root / sub).is_dir():
            raise FileNotFoundError(f"{root}: no {sub}/ folder (expected {a}/NAME.* + {b}/NAME.*)")

    def stems(sub, suffixes):
        return {p.stem: p for p in sorted((root / sub).iterdir()) if p.suffix.lower() in suffixes}

    left, right = stems(a, IMAGE_SUFFIXES), stems(b, b_suffixes)
    lone = [str(left[s]) for s in sorted(set(left) - set(right))] + [str(right[s]) for s in sorted(set(right) - set(left))]
    if lone:
        raise ValueError(f"{root}: {len(lone)} file(s) without a partner in {a}/ or {b}/, e.g. {lone[0]}")
    if not left:
        raise ValueError(f"{root}: no image files in {a}/ ({', '.join(IMAGE_SUFFIXES)})")
    return [(left[s], right[s]) for s in sorted(left)]


def shard_items(data_dir: str | Path, split: str, part: str, val_share: float, exclude=()) -> list[Item]:
    return [Item("shard", seg.path, sample_key(split, i), seg.sha256)
            for seg in find_segments(data_dir, split, part, val_share, exclude) for i in range(seg.lo, seg.hi)]


def sources(cfg: Config, data_dir: str | Path | None, part: str) -> tuple[list[Item], list[Item]]:
    """(depth items, segmentation items) of the config's sources for the train split's `part`
    ("fit" for training, "val" for validation: the shards' held-out share alone)."""
    d = cfg.depth
    depth = (shard_items(data_dir, "train", part, cfg.data.val_share, excluded(cfg, data_dir))
             if d.shards and data_dir else [])
    if part == "val":
        return depth, []
    if d.rgbd:
        depth += [Item("rgbd", str(r), str(z)) for r, z in pair_files(d.rgbd, "rgb", "depth", DEPTH_SUFFIXES)]
    seg = [Item("matte", str(f), str(a)) for f, a in pair_files(d.mattes, "fg", "alpha", IMAGE_SUFFIXES)] if d.mattes else []
    if not depth and not seg:
        raise ValueError("the depth network has no training data: set [depth] shards with --data, rgbd or mattes")
    return depth, seg


def _rgb(img: np.ndarray) -> np.ndarray:
    img = img[:, :, :3] if img.shape[2] >= 3 else np.repeat(img[:, :, :1], 3, axis=2)
    return np.clip(img, 0.0, 1.0).astype(np.float32)


def _same_size(a: np.ndarray, b: np.ndarray, pa, pb) -> None:
    if a.shape[:2] != b.shape[:2]:
        raise ValueError(f"{pb} is {b.shape[1]}x{b.shape[0]} but {pa} is {a.shape[1]}x{a.shape[0]}")


def load_item(item: Item, quantity: str = "depth", index_cache: dict | None = None) -> dict:
    """Full-size arrays of one item: image (H, W, 3) sRGB; depth, valid (H, W) or None; seg
    (H, W) or None. A bad file raises ValueError naming it."""
    if item.kind == "shard":
        cache = {} if index_cache is None else index_cache
        if item.path not in cache:
            cache[item.path] = member_index(item.path, item.sha256)  # read whole and hashed, once
        if item.other not in cache[item.path]:
            raise ValueError(f"{item.path}: no sample {item.other}")
        m = read_members(item.path, cache[item.path][item.other])
        name = f"{item.path}: sample {item.other}"
        image = unit_float(decode_image(m["aif.png"], f"{name}.aif.png", raw=True), name)[:, :, :3]
        depth, valid = normalize_disparity(decode_depth(m["depth.exr"], f"{name}.depth.exr"), "disparity")
        cover = decode_image(m["cover.png"], f"{name}.cover.png", raw=True)
        return {"image": image, "depth": depth, "valid": valid,
                "seg": (np.maximum(cover[:, :, 0], cover[:, :, 1]) >= 128).astype(np.float32)}
    image = _rgb(read_image(item.path))
    if Path(item.path).suffix.lower() == ".exr":  # linear light: the network sees sRGB
        image = linear_to_srgb(image)
    if item.kind == "rgbd":
        z = read_depth(item.other)
        _same_size(image, z, item.path, item.other)
        depth, valid = normalize_disparity(z, quantity)
        return {"image": image, "depth": depth, "valid": valid, "seg": None}
    alpha = read_image(item.other)
    _same_size(image, alpha, item.path, item.other)
    return {"image": image, "depth": None, "valid": None, "seg": (alpha[:, :, -1] >= 0.5).astype(np.float32)}


def jitter_colour(image: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A random photometric change of an sRGB (H, W, 3) image in [0, 1]: the colour channels in
    a random order, saturation x [0.4, 1.6], contrast x [0.7, 1.3] about the mean, brightness x
    [0.7, 1.3]; clipped to [0, 1]."""
    x = image[:, :, rng.permutation(3)]
    grey = x.mean(axis=2, keepdims=True)
    x = grey + (x - grey) * rng.uniform(0.4, 1.6)
    m = x.mean()
    x = (m + (x - m) * rng.uniform(0.7, 1.3)) * rng.uniform(0.7, 1.3)
    return np.clip(x, 0.0, 1.0).astype(np.float32)


def fit_crop(x: dict, side: int, rng: np.random.Generator | None, jitter: float = 0.0) -> dict:
    """Resize so that the short side is `side`, crop side x side (random with `rng`, else the
    centre), flip horizontally at random and, with probability `jitter`, change the colours
    (`jitter_colour`; both only with `rng`): the tensors of an item."""
    h, w = x["image"].shape[:2]
    f = side / min(h, w)
    nh, nw = max(side, round(h * f)), max(side, round(w * f))
    y0 = int(rng.integers(nh - side + 1)) if rng is not None else (nh - side) // 2
    x0 = int(rng.integers(nw - side + 1)) if rng is not None else (nw - side) // 2
    flip = rng is not None and rng.random() < 0.5
    win = (slice(y0, y0 + side), slice(x0, x0 + side))

    def fit(a):
        a = resize(a, nw, nh)[win]
        return np.ascontiguousarray(a[:, ::-1] if flip else a, dtype=np.float32)

    if x["depth"] is not None:
        known = fit(x["valid"].astype(np.float32))
        depth = np.where(known > 0.5, fit(x["depth"] * x["valid"]) / np.maximum(known, 1e-6), 0.0)
        valid = known > 0.5
        has_depth = valid.sum() >= 16 and np.ptp(depth[valid]) > 1e-3
        if has_depth:  # normalized again over the crop, as the prediction is
            lo, hi = depth[valid].min(), depth[valid].max()
            depth = np.where(valid, (depth - lo) / (hi - lo), 0.0)
    else:
        depth = valid = np.zeros((side, side), np.float32)
        has_depth = False
    seg = (fit(x["seg"]) >= 0.5) if x["seg"] is not None else np.zeros((side, side), bool)

    def t(a):
        a = np.asarray(a, np.float32)
        return torch.from_numpy(np.ascontiguousarray(a.transpose(2, 0, 1) if a.ndim == 3 else a[None]))

    image = fit(x["image"])
    if rng is not None and jitter > 0 and rng.random() < jitter:
        image = jitter_colour(image, rng)
    return {"image": t(image), "depth": t(depth), "depth_valid": t(valid), "seg": t(seg),
            "has_depth": torch.tensor(float(has_depth)), "has_seg": torch.tensor(float(x["seg"] is not None))}


class DepthMix(IterableDataset):
    """Mixed batches of depth and segmentation items (see the module docstring)."""

    def __init__(self, depth_items: list[Item], seg_items: list[Item], cfg: Config, *, train: bool, seed: int,
                 rank: int | None = None, world: int | None = None):
        self.depth_items, self.seg_items, self.cfg = list(depth_items), list(seg_items), cfg
        self.train, self.seed, self.rank, self.world = train, seed, rank, world
        self.epoch, self.skip_batches = 0, 0
        self._index: dict = {}

    def set_epoch(self, epoch: int, skip_batches: int = 0) -> None:
        self.epoch, self.skip_batches = int(epoch), int(skip_batches)

    def _split(self) -> tuple[int, int]:
        """(depth, segmentation) items per training batch."""
        b = self.cfg.data.batch_size
        if not self.seg_items:
            return b, 0
        if not self.depth_items:
            return 0, b
        n_seg = min(b - 1, max(1, round(b * self.cfg.depth.seg_share)))
        return b - n_seg, n_seg

    def plan(self, epoch: int) -> list[list[Item]]:
        """Every batch of the epoch, all ranks together, in order."""
        b = self.cfg.data.batch_size
        if not self.train:
            return [self.depth_items[i:i + b] for i in range(0, len(self.depth_items), b)]
        rng = stream_rng(self.seed, "depth_plan", epoch)
        n_d, n_s = self._split()
        lists = [(n, [items[i] for i in rng.permutation(len(items))]) for n, items in
                 ((n_d, self.depth_items), (n_s, self.seg_items)) if n]
        count = max(math.ceil(len(items) / n) for n, items in lists)
        return [[items[(g * n + q) % len(items)] for n, items in lists for q in range(n)] for g in range(count)]

    def __iter__(self):
        rank, world, worker, workers = process_slot(self.rank, self.world)
        plan = self.plan(self.epoch)
        mine = (plan[rank::world][: len(plan) // world] if self.train else plan[rank::world])
        for j in range(self.skip_batches + worker, len(mine), workers):
            g = rank + world * j
            for q, item in enumerate(mine[j]):
                rng = stream_rng(self.seed, "depth_item", self.epoch, g, q) if self.train else None
                try:
                    x = load_item(item, self.cfg.depth.rgbd_quantity, self._index)
                except (KeyError, ValueError) as exc:
                    what = f"missing member {exc}" if isinstance(exc, KeyError) else str(exc)
                    raise ValueError(f"{item.path}: {what}") from exc
                yield {**fit_crop(x, self.cfg.data.crop, rng, self.cfg.depth.jitter), "key": f"{item.path}:{item.other}"}


def make_depth_loader(data_dir, cfg: Config, *, train: bool, seed: int, part: str = "fit",
                      pin_memory: bool = False) -> tuple[DepthMix, DataLoader]:
    """The dataset and a DataLoader of [data] batch_size / num_workers (as make_loader)."""
    depth, seg = sources(cfg, data_dir, part)
    if not depth and not seg:
        raise FileNotFoundError(f"no {part} samples for the depth network (validation uses the shards' "
                                "held-out share: [depth] shards with --data)")
    ds = DepthMix(depth, seg, cfg, train=train, seed=seed)
    workers = cfg.data.num_workers
    loader = DataLoader(ds, batch_size=cfg.data.batch_size, num_workers=workers, pin_memory=pin_memory,
                        prefetch_factor=4 if workers else None, worker_init_fn=quiet_worker)
    return ds, loader
