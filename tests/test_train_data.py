"""The shard loader (dofsynth.train.data); also home of `make_dataset`, the tiny synthetic data
set (docs/FORMAT.md) that the other test_train_* files import."""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from dofsynth.io import decode_image, encode_png
from dofsynth.codecs import decode_depth, encode_depth
from dofsynth.manifest import assemble_manifest, write_manifest
from dofsynth.record import format_description
from dofsynth.shards import ShardInfo, shard_name, write_shard
from dofsynth.train.config import Config, from_dict
from dofsynth.train.data import DofShards, area_downsample, make_loader, resolve, sample_rng, training_item
from dofsynth.train.segments import find_segments, raw_samples

TINY = {
    "data": {"crop": 32, "levels": 1, "batch_size": 4, "num_workers": 0, "shuffle_buffer": 8},
    "augment": {"morph_prob": 0.5, "morph_kernel": [3, 5]},
    "model": {"feat_channels": 4, "kp_width": 8, "kp_depth": 2, "up_width": 8},
    "train": {"max_steps": 4, "lr": 3e-3, "warmup_steps": 1, "log_interval": 1, "eval_interval": 2,
              "eval_batches": 1, "checkpoint_interval": 2},
}


def tiny_config(**tables) -> Config:
    d = {k: dict(v) for k, v in TINY.items()}
    for table, kw in tables.items():
        d.setdefault(table, {}).update(kw)
    return from_dict(d)


def blur_target(aif: np.ndarray, disparity: np.ndarray, focus: float, max_coc: float) -> np.ndarray:
    """A simple stand-in for a DoF render: per pixel, mix the image and a Gaussian blur of it by
    the CoC size |c| / max_coc (enough for shape tests and for the overfit test)."""
    blurred = cv2.GaussianBlur(aif, (0, 0), sigmaX=max(0.5, max_coc / 2), borderType=cv2.BORDER_REFLECT)
    w = np.clip(np.abs(disparity - focus) * 2.0, 0.0, 1.0)[:, :, None]
    return (1 - w) * aif + w * blurred


def make_sample(split: str, index: int, size: int, seed: int = 0, grain: int = 4) -> dict:
    """One sample's members (FORMAT.md): background texture (random values in blocks of about
    `grain` px) on a ramp or flat plane, a middle rectangle and a front disk, two DoF targets."""
    rng = np.random.default_rng([seed, index, len(split)])
    h = w = size
    noise = rng.random((h // grain, w // grain, 3)).astype(np.float32)
    bg = cv2.resize(noise, (w, h), interpolation=cv2.INTER_CUBIC).clip(0, 1)
    yy, xx = np.mgrid[0:h, 0:w]
    mid = ((np.abs(yy - h * rng.uniform(0.3, 0.7)) < h / 5) & (np.abs(xx - w * rng.uniform(0.3, 0.7)) < w / 4))
    cy, cx, r = h * rng.uniform(0.3, 0.7), w * rng.uniform(0.3, 0.7), size / 6
    front = (yy - cy) ** 2 + (xx - cx) ** 2 < r**2
    ramp = index % 2 == 0
    b0, b1 = 0.1, 0.3
    record = {
        "schema_version": 1, "key": f"{split}-{index:07d}", "split": split, "index": index,
        "seed": [seed, 0, index], "size": [h, w],
        "assets": {}, "aperture": {"kind": "disk"}, "options": {}, "renderer": "test",
        "background": {"mode": "ramp" if ramp else "flat", "b0": b0, "b1": b1 if ramp else b0,
                       "direction": "horizontal" if ramp else None, "crop": [0, 0, w, h], "flip": False},
        "middle": {"disparity": 0.5, "scale": 1.0, "x": 0, "y": 0, "flip": False},
        "front": {"disparity": 0.8, "scale": 1.0, "x": 0, "y": 0, "flip": False},
        "targets": [{"focus": 0.8, "max_coc": 4.0}, {"focus": 0.2, "max_coc": 2.0}],
    }
    xs = np.linspace(0.0, 1.0, w)
    depth = np.broadcast_to(b0 + (b1 - b0) * xs if ramp else np.full(w, b0), (h, w)).astype(np.float32).copy()
    depth[mid], depth[front] = 0.5, 0.8
    aif = bg.copy()
    aif[mid] = [0.9, 0.2, 0.1]
    aif[front] = rng.random(3)
    cover = np.zeros((h, w, 3), np.float32)
    cover[:, :, 0], cover[:, :, 1] = front, mid
    members = {"aif.png": encode_png(aif), "depth.exr": encode_depth(depth),
               "cover.png": encode_png(cover), "json": json.dumps(record, sort_keys=True).encode()}
    for n, t in enumerate(record["targets"]):
        members[f"dof.{n}.png"] = encode_png(blur_target(aif, depth, t["focus"], t["max_coc"]))
    return members


def make_dataset(out: Path, n_train: int = 8, n_test: int = 2, size: int = 32, per_shard: int | list = 4,
                 grain: int = 4) -> Path:
    """A tiny data set: OUT/{train,test}/<split>-NNNNNN.tar of `size` px samples and the
    manifest.json that lists them (docs/FORMAT.md). per_shard: samples per shard, or the train
    split's shard sizes in order."""
    shards: dict[str, list[ShardInfo]] = {}
    for split, n in (("train", n_train), ("test", n_test)):
        sizes = per_shard if isinstance(per_shard, list) and split == "train" else None
        if sizes is None:
            step = per_shard if isinstance(per_shard, int) else max(per_shard)
            sizes = [min(step, n - s0) for s0 in range(0, n, step)]
        starts = np.cumsum([0] + sizes[:-1]).tolist()
        for k, (s0, count) in enumerate(zip(starts, sizes)):
            name = shard_name(split, k)
            ids = range(s0, s0 + count)
            count, sha, nbytes = write_shard(out / split / name,
                                             ((f"{split}-{i:07d}", make_sample(split, i, size, grain=grain)) for i in ids))
            shards.setdefault(split, []).append(ShardInfo(split, k, name, s0, count, sha, nbytes))
    text = (f'name = "tiny"\nseed = 0\nsize = {size}\nsamples = {{ train = {n_train}, test = {n_test} }}\n'
            '[assets]\nbackgrounds = "builtin"\nforegrounds = "builtin"\n[focus]\nmax_coc = [2.0, 4.0]\n')
    recipe = {"text": text, "sha256": "0" * 64, "path": None, "name": "tiny"}
    write_manifest(out, assemble_manifest(recipe, {"train": n_train, "test": n_test}, shards, format_description()))
    return out


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory) -> Path:
    return make_dataset(tmp_path_factory.mktemp("data"), n_train=12, n_test=2, size=48, per_shard=4)


def test_resolve_reads_coc_ref_and_low_res_side_from_the_data(data_dir):
    cfg = resolve(tiny_config(), data_dir)
    assert cfg.model.coc_ref == 4.0 and cfg.infer.low_res_side == 24
    kept = resolve(tiny_config(model={"coc_ref": 8.0}, infer={"low_res_side": 10}), data_dir)
    assert kept.model.coc_ref == 8.0 and kept.infer.low_res_side == 10
    # [model] light = "boosted" must assume the highlight boost the data's targets were made with
    assert resolve(tiny_config(model={"light": "boosted"}), data_dir).model.boost == (0.9, 4.0, 2.0)
    with pytest.raises(ValueError, match=r"boost = \[0.9, 3.0, 2.0\].*\[0.9, 4.0, 2.0\]"):
        resolve(tiny_config(model={"light": "boosted", "boost": [0.9, 3.0, 2.0]}), data_dir)


def _with_recipe_text(data_dir: Path, folder: Path, extra: str) -> Path:
    """A copy of data_dir's manifest whose recipe has `extra` TOML appended (all resolve reads)."""
    manifest = json.loads((data_dir / "manifest.json").read_text())
    manifest["recipe"]["text"] += extra
    folder.mkdir()
    (folder / "manifest.json").write_text(json.dumps(manifest))
    return folder


def test_resolve_matches_the_boost_to_the_data_and_refuses_srgb_blurred_data(data_dir, tmp_path):
    off = _with_recipe_text(data_dir, tmp_path / "off", "[render.highlight]\nenabled = false\n")
    # targets made without the boost: the lens module's boost must have gain 0
    assert resolve(tiny_config(model={"light": "boosted", "boost": [0.9, 0.0, 2.0]}), off).model.boost == (0.9, 0.0, 2.0)
    with pytest.raises(ValueError, match=r"boost = \[0.9, 4.0, 2.0\].*\[0.9, 0.0, 2.0\]"):
        resolve(tiny_config(model={"light": "boosted"}), off)
    naive = _with_recipe_text(data_dir, tmp_path / "naive", "[render]\nlinear_light = false\n")
    assert resolve(tiny_config(), naive).model.coc_ref == 4.0  # the paper's sRGB module takes such data
    with pytest.raises(ValueError, match=r"naive.*blurred in sRGB"):
        resolve(tiny_config(model={"light": "boosted"}), naive)


def test_items_have_the_documented_shapes_ranges_and_exact_low_res(data_dir):
    cfg = resolve(tiny_config(), data_dir)
    _, loader = make_loader(data_dir, "train", cfg, train=True, seed=0)
    batch = next(iter(loader))
    assert batch["image"].shape == (4, 3, 32, 32) and batch["target"].shape == (4, 3, 32, 32)
    for k in ("image_lo", "target_lo"):
        assert batch[k].shape == (4, 3, 16, 16)
    assert batch["signed_lo"].shape == (4, 1, 16, 16) and batch["disparity"].shape == (4, 1, 32, 32)
    for k in ("image", "image_lo", "target", "target_lo", "disparity"):
        assert batch[k].dtype == torch.float32 and 0.0 <= batch[k].min() and batch[k].max() <= 1.0
    # low res = exact 2x2 block means; signed = (corrupted d - focus) * max_coc / coc_ref
    assert torch.allclose(batch["image_lo"], torch.nn.functional.avg_pool2d(batch["image"], 2), atol=1e-6)
    expect = (torch.nn.functional.avg_pool2d(batch["disparity"], 2) - batch["focus"].view(-1, 1, 1, 1)) \
        * (batch["max_coc"] / cfg.model.coc_ref).view(-1, 1, 1, 1)
    assert torch.allclose(batch["signed_lo"], expect.float(), atol=1e-5)
    assert batch["signed_lo"].abs().max() <= 1.0


def _raw(data_dir, index=0):
    return next(raw_samples(find_segments(data_dir, "train"), "train"))


def test_target_choice_crop_alignment_and_the_target_is_never_corrupted(data_dir):
    cfg = resolve(tiny_config(data={"target": "1"}, augment={"morph_prob": 1.0, "noise_prob": 1.0}), data_dir)
    raw = _raw(data_dir)
    full = training_item(raw, cfg, sample_rng(0, 0, "train", 0))
    assert full["target_index"] == 1 and full["image"].shape == (3, 48, 48)
    truth = decode_image(raw["dof.1.png"])
    assert np.array_equal(full["target"].numpy().transpose(1, 2, 0), truth)
    clean = torch.from_numpy(decode_depth(raw["depth.exr"]))
    assert not torch.equal(full["disparity"][0], clean)  # the input is corrupted ...
    crop = training_item(raw, cfg, sample_rng(0, 3, "train", 0), crop=32)
    # ... the crop is aligned to 2**levels: it is found at an even offset of the full target
    t = full["target"]
    hits = [(y, x) for y in range(0, 17) for x in range(0, 17)
            if torch.equal(t[:, y:y + 32, x:x + 32], crop["target"])]
    assert hits and all(y % 2 == 0 and x % 2 == 0 for y, x in hits)
    with pytest.raises(ValueError, match="target 5"):
        training_item(raw, cfg, sample_rng(0, 0, "train", 0), target=5)


def test_random_target_choice_uses_every_target_and_is_seeded(data_dir):
    cfg = resolve(tiny_config(), data_dir)
    raw = _raw(data_dir)
    picks = [training_item(raw, cfg, sample_rng(0, e, "train", 0))["target_index"] for e in range(12)]
    again = [training_item(raw, cfg, sample_rng(0, e, "train", 0))["target_index"] for e in range(12)]
    assert set(picks) == {0, 1} and picks == again


def _keys(data_dir, cfg, workers, epoch=0, rank=None, world=None, part="all", skip=0, batch=None):
    ds = DofShards(find_segments(data_dir, "train", part, cfg.data.val_share), cfg, train=True, seed=0,
                   split="train", rank=rank, world=world)
    ds.set_epoch(epoch, skip_batches=skip)
    loader = torch.utils.data.DataLoader(ds, batch_size=batch, num_workers=workers)
    if batch is None:
        return [item["key"] for item in loader]
    return [list(b["key"]) for b in loader]


@pytest.mark.parametrize("shards_per_split", [4, 12])  # 3 shards, or 1 shard (< workers)
def test_workers_split_the_data_without_duplicates(tmp_path, shards_per_split):
    data = make_dataset(tmp_path, n_train=12, n_test=0, size=32, per_shard=shards_per_split)
    cfg = resolve(tiny_config(), data)
    keys = _keys(data, cfg, workers=2)
    assert sorted(keys) == [f"train-{i:07d}" for i in range(12)]
    assert _keys(data, cfg, workers=0, epoch=1) != _keys(data, cfg, workers=0, epoch=0)  # reshuffled per epoch


def test_ranks_get_equal_shares_when_shards_do_not_divide_evenly(tmp_path):
    """Shards of 24, 16 and 16 samples over 3 ranks: 18 each (56 // 3), no sample twice, and
    per epoch different samples are left over."""
    data = make_dataset(tmp_path, n_train=56, n_test=0, size=16, per_shard=[24, 16, 16])
    cfg = resolve(tiny_config(data={"crop": 16, "val_share": 0.0}), data)
    for epoch in (0, 1):
        seen = [_keys(data, cfg, workers=0, rank=r, world=3, epoch=epoch) for r in range(3)]
        assert [len(k) for k in seen] == [18, 18, 18]
        flat = [k for ks in seen for k in ks]
        assert len(set(flat)) == 54
    two_workers = [_keys(data, cfg, workers=2, rank=r, world=3) for r in range(3)]
    assert [len(k) for k in two_workers] == [18, 18, 18]  # 9 per worker


def test_a_resumed_epoch_continues_where_each_rank_stopped(tmp_path):
    """Skipping k batches yields exactly the rest of the uninterrupted epoch, on every rank,
    with a shuffle buffer and two DataLoader workers."""
    data = make_dataset(tmp_path, n_train=40, n_test=0, size=16, per_shard=[24, 16])
    cfg = resolve(tiny_config(data={"crop": 16, "val_share": 0.0, "batch_size": 3, "shuffle_buffer": 5}), data)
    for rank in range(2):
        full = _keys(data, cfg, workers=2, rank=rank, world=2, epoch=1, batch=3)
        assert len(full) == 8  # 20 samples per rank, 10 per worker: batches of 3, 3, 3, 1 each
        for k in (1, 3, 6):
            assert _keys(data, cfg, workers=2, rank=rank, world=2, epoch=1, batch=3, skip=k) == full[k:]


def test_the_validation_share_is_held_out_of_training(tmp_path):
    data = make_dataset(tmp_path, n_train=20, n_test=2, size=16, per_shard=8)
    cfg = resolve(tiny_config(data={"crop": 16, "val_share": 0.25}), data)
    fit = set(_keys(data, cfg, workers=0, part="fit"))
    val = set(_keys(data, cfg, workers=0, part="val"))
    assert val == {f"train-{i:07d}" for i in range(15, 20)} and not fit & val and len(fit) == 15


def test_missing_data_names_the_folder_and_the_split(tmp_path, data_dir):
    with pytest.raises(FileNotFoundError, match=f"{tmp_path}.*no manifest"):
        find_segments(tmp_path, "train")
    with pytest.raises(FileNotFoundError, match="has no val split"):
        find_segments(data_dir, "val")


def test_area_downsample_is_the_block_mean():
    x = np.arange(16, dtype=np.float32).reshape(4, 4)
    assert np.array_equal(area_downsample(x, 2), np.array([[2.5, 4.5], [10.5, 12.5]], np.float32))
    with pytest.raises(ValueError, match="multiple"):
        area_downsample(np.zeros((5, 4)), 2)


def test_linear_colour_decodes_images_and_targets_to_linear_light(data_dir):
    from dofsynth.color import srgb_to_linear

    raw = _raw(data_dir)
    srgb = training_item(raw, resolve(tiny_config(), data_dir), sample_rng(0, 0, "train", 0))
    lin = training_item(raw, resolve(tiny_config(data={"color": "linear"}), data_dir), sample_rng(0, 0, "train", 0))
    for k in ("image", "target"):
        assert torch.allclose(lin[k], torch.from_numpy(srgb_to_linear(srgb[k].numpy())), atol=1e-6)
    assert torch.equal(lin["signed_lo"], srgb["signed_lo"])


def test_the_recorded_corruption_replays_the_disparity_the_network_saw(data_dir):
    from dofsynth.train.augment import apply_corruption, layers_from_record

    cfg = resolve(tiny_config(augment={"morph_prob": 1.0, "shift_prob": 1.0, "noise_prob": 1.0}), data_dir)
    raw = _raw(data_dir)
    item = training_item(raw, cfg, sample_rng(0, 0, "train", 0))
    params = json.loads(item["corruption"])
    assert all(m is not None for m in params["morph"]) and params["shift"] and params["noise"]
    layers = layers_from_record(json.loads(raw["json"]), decode_image(raw["cover.png"]))
    replay = apply_corruption(decode_depth(raw["depth.exr"]), layers, params)
    assert np.array_equal(replay, item["disparity"][0].numpy())
