"""Benchmark the DeepLens networks: training samples/s and render_photo time at 1024 and 2048 px.

    .venv/bin/python benchmarks/train.py [--config recipes/train-deeplens.toml] [--device cpu|cuda]

Uses the model sizes of the config (default: the DeepLens recipe) with random weights; training
runs on random in-memory batches (data loading is measured on its own, on 8 samples of the
512 px demo recipe made on the spot), at the config's crop on CUDA
(bf16 autocast) and at a 256 px crop, batch 4, on CPU so that the whole script takes about two
minutes there. The paper quotes 0.7 s for a 2048 px result on its GPU.
"""
from __future__ import annotations

import argparse
import tempfile
import time
from contextlib import nullcontext
from pathlib import Path

import numpy as np
import torch

from dofsynth.train import checkpoint
from dofsynth.train.config import load, replace
from dofsynth.train.infer import render_photo
from dofsynth.train.loss import deeplens_loss
from dofsynth.train.models import DeepLensNet

ROOT = Path(__file__).resolve().parents[1]


def sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def bench_training(cfg, device: str, crop: int, batch: int, steps: int) -> float:
    torch.manual_seed(0)
    model = DeepLensNet(cfg.model).to(device)
    opt = torch.optim.AdamW(model.parameters(), lr=1e-4)
    s = 2 ** cfg.data.levels
    image = torch.rand(batch, 3, crop, crop, device=device)
    signed = torch.rand(batch, 1, crop // s, crop // s, device=device) * 2 - 1
    target, target_lo = torch.rand_like(image), torch.rand(batch, 3, crop // s, crop // s, device=device)
    amp = torch.autocast("cuda", dtype=torch.bfloat16) if device.startswith("cuda") else nullcontext()
    times = []
    for i in range(steps + 2):  # two warm-up steps
        sync(device)
        t0 = time.perf_counter()
        with amp:
            low, high = model(image, signed, cfg.data.levels)
        loss, _, _ = deeplens_loss(low, high, target_lo, target)
        loss.backward()
        opt.step()
        opt.zero_grad(set_to_none=True)
        sync(device)
        if i >= 2:
            times.append(time.perf_counter() - t0)
    return batch / float(np.median(times))


def bench_loader(cfg, tmp: Path, n: int = 8) -> tuple[float, int]:
    """Samples/s of one loader process (decode, depth corruption, crop) on demo-recipe samples."""
    from dofsynth.recipe import load_recipe
    from dofsynth.generate import generate
    from dofsynth.train.data import DofShards, find_shards, resolve

    recipe = load_recipe(ROOT / "recipes" / "demo.toml")
    generate(recipe, tmp / "demo", splits=("train",), limit=n, progress=False)
    cfg = replace(cfg, "data", crop=min(cfg.data.crop, recipe.size), shuffle_buffer=1)
    cfg = resolve(replace(cfg, "model", coc_ref=0.0), tmp / "demo")
    ds = DofShards(find_shards(tmp / "demo", "train"), cfg, train=True, seed=0, split="train")
    t0 = time.perf_counter()
    count = sum(1 for _ in ds)
    return count / (time.perf_counter() - t0), recipe.size


def bench_inference(run_dir: Path, device: str, side: int, repeats: int) -> float:
    rng = np.random.default_rng(0)
    image = rng.random((side, side, 3), dtype=np.float32)
    disparity = np.tile(np.linspace(0, 1, side, dtype=np.float32), (side, 1))
    render_photo(run_dir, image[:64, :64], disparity[:64, :64], 0.5, device=device)  # load + warm up
    times = []
    for _ in range(repeats):
        sync(device)
        t0 = time.perf_counter()
        render_photo(run_dir, image, disparity, 0.5, device=device)
        sync(device)
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default=str(ROOT / "recipes" / "train-deeplens.toml"))
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    args = ap.parse_args()
    cfg = load(args.config)
    cuda = args.device.startswith("cuda")
    name = torch.cuda.get_device_name() if cuda else f"CPU, {torch.get_num_threads()} threads"
    print(f"device: {name}; torch {torch.__version__}; model config {args.config}")
    n_params = sum(p.numel() for p in DeepLensNet(cfg.model).parameters())
    print(f"parameters: {n_params:,} (c = {cfg.model.feat_channels * len(cfg.model.feat_dilations)})")

    crop, batch, steps = (cfg.data.crop, cfg.data.batch_size, 20) if cuda else (256, 4, 5)
    sps = bench_training(cfg, args.device, crop, batch, steps)
    print(f"training: {sps:.1f} samples/s ({crop} px crops, batch {batch}, levels {cfg.data.levels}"
          f"{', bf16 autocast' if cuda else ''})")

    with tempfile.TemporaryDirectory() as tmp:
        rate, size = bench_loader(cfg, Path(tmp))
        print(f"data loading: {rate:.1f} samples/s per loader process ({size} px samples: PNG/EXR decode, "
              f"depth corruption, crop)")
        if cfg.model.coc_ref <= 0 or cfg.infer.low_res_side <= 0:
            cfg = replace(replace(cfg, "model", coc_ref=32.0), "infer", low_res_side=256)
        model = DeepLensNet(cfg.model)
        checkpoint.save(Path(tmp) / checkpoint.CHECKPOINT, model, torch.optim.AdamW(model.parameters()),
                        0, 0, 0, cfg)
        for side in (1024, 2048):
            t = bench_inference(Path(tmp), args.device, side, repeats=5 if cuda else 2)
            steps_up = max(0, int(np.ceil(np.log2(side / cfg.infer.low_res_side) - 1e-9)))
            print(f"render_photo {side} x {side}: {t:.2f} s (lens blur at {side >> steps_up} px, "
                  f"{steps_up} x2 upsamplings, float32)")


if __name__ == "__main__":
    main()
