"""Benchmark the DeepLens networks: the training step's and the data loader's samples/s side by
side, and render_photo time at 1024 and 2048 px.

    .venv/bin/python benchmarks/train.py [--config recipes/train-deeplens.toml] [--device cpu|cuda]

Uses the model and data sizes of the config (default: the DeepLens one) with random weights.
Training runs on random in-memory batches at the config's crop and batch (on CPU a few steps,
bf16 autocast on CUDA). The loader alone is the config's DataLoader (its num_workers worker
processes: decode, depth corruption, crop) over 48 samples of the config's data recipe
(docs/training.md) at its size, made on the spot with the built-in assets; it must run at
least 3x the training step's rate, so that training never waits for data. The paper quotes
0.7 s for a 2048 px result on its GPU.
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
from dofsynth.train.config import DATA_RECIPES, load, replace
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


def bench_loader(cfg, config_name: str, tmp: Path, n: int = 48) -> tuple[float, int, int]:
    """(samples/s, image side, workers) of the config's DataLoader over `n` samples of its
    data recipe (built-in assets): a whole epoch, worker start-up included (the second epoch,
    so the files are in the page cache)."""
    import re

    from dofsynth.generate import generate
    from dofsynth.recipe import recipe_from_text
    from dofsynth.train.data import make_loader, resolve

    path = ROOT / "recipes" / DATA_RECIPES.get(config_name, "demo.toml")
    text = re.sub(r'(?m)^(backgrounds|foregrounds) = "[^"]*"', r'\1 = "builtin"', path.read_text())
    text = re.sub(r"(?m)^max_upscale = .*$", "", text).replace("[assets]\n", "[assets]\nmax_upscale = 64.0\n", 1)
    text = re.sub(r"(?m)^samples = \{[^}]*\}", f"samples = {{ train = {n}, test = 0 }}", text)
    recipe = recipe_from_text(text, path.name, path.parent)
    generate(recipe, tmp / "data", workers=2, progress=False)
    cfg = replace(resolve(cfg, tmp / "data"), "data", val_share=0.0)
    ds, loader = make_loader(tmp / "data", "train", cfg, train=True, seed=0)
    rate = []
    for epoch in range(2):  # epoch 0 warms the page cache
        ds.set_epoch(epoch)
        t0, count = time.perf_counter(), 0
        for batch in loader:
            count += batch["image"].shape[0]
        rate.append(count / (time.perf_counter() - t0))
    return rate[-1], recipe.size, cfg.data.num_workers


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

    crop, batch = cfg.data.crop, cfg.data.batch_size
    sps = bench_training(cfg, args.device, crop, batch, 20 if cuda else 3)
    print(f"training step: {sps:.1f} samples/s ({crop} px crops, batch {batch}, levels {cfg.data.levels}"
          f"{', bf16 autocast' if cuda else ''})")

    with tempfile.TemporaryDirectory() as tmp:
        rate, size, workers = bench_loader(cfg, Path(args.config).name, Path(tmp))
        print(f"loader alone: {rate:.1f} samples/s ({size} px samples, {workers} DataLoader workers: "
              f"PNG/EXR decode, depth corruption, crop) = {rate / sps:.1f}x the training step")
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
