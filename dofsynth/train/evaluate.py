"""Evaluate a trained run on the test split, next to the classical renderer.

For every test sample and every one of its DoF targets, the same corrupted disparity (the
training corruption with a fixed evaluation seed) goes to
  - "network":   the run's DeepLensNet on the whole image (lens blur at 1/2**levels, then
                 guided upsampling), and
  - "classical": dofsynth.render.render_planes on the image as a single plane
                 (alpha = 1, disparity = the corrupted map), with the sample's aperture shape,
and, as a floor, "all-in-focus" (the input itself). PSNR and SSIM (skimage.metrics, sRGB in
[0, 1], data_range 1) are taken against the rendered target. The table is printed and written
to RUN/eval.csv (one row per method) and RUN/eval.json (the table and every item).
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

from dofsynth.color import linear_to_srgb, srgb_to_linear
from dofsynth.files import atomic_write_bytes, canonical_json, csv_text
from dofsynth.optics.aperture import aperture_from_dict
from dofsynth.render import Plane, render_planes
from dofsynth.train.checkpoint import load_model
from dofsynth.train.data import find_shards, raw_samples, sample_rng, training_item

METHODS = ("network", "classical", "all-in-focus")


def _hwc(t: torch.Tensor) -> np.ndarray:
    return t.detach().float().cpu().numpy().transpose(1, 2, 0)


def classical_render(image_linear: np.ndarray, disparity: np.ndarray, focus: float, max_coc: float,
                     record: dict) -> np.ndarray:
    """The single-image classical render: one plane, alpha 1, the given disparity map, the
    sample's aperture."""
    plane = Plane(image_linear, alpha=np.ones(disparity.shape, np.float32), disparity=disparity)
    return render_planes([plane], focus, max_coc, aperture_from_dict(record["aperture"]))


def _metrics(pred_srgb: np.ndarray, target_srgb: np.ndarray) -> dict:
    pred = np.clip(pred_srgb, 0.0, 1.0).astype(np.float64)
    ref = target_srgb.astype(np.float64)
    side = min(ref.shape[:2])
    win = 7 if side >= 7 else max(1, side - (1 - side % 2))  # SSIM needs an odd window <= the side
    return {"psnr": float(peak_signal_noise_ratio(ref, pred, data_range=1.0)),
            "ssim": float(structural_similarity(ref, pred, data_range=1.0, channel_axis=2, win_size=win))}


def evaluate_run(run_dir: str | Path, data_dir: str | Path, *, split: str = "test", limit: int | None = None,
                 classical: bool = True, seed: int = 12345, device: str | None = None) -> dict:
    """Score every target of the first `limit` samples of `split`; returns
    {"table": [{"method", "psnr", "ssim", "n"}], "items": [...]} and writes RUN/eval.{csv,json}."""
    run_dir = Path(run_dir)
    device = device or ("cuda" if torch.cuda.is_available() else "cpu")
    model, cfg = load_model(run_dir, device)
    to_srgb = (lambda x: x) if cfg.data.color == "srgb" else linear_to_srgb
    items = []
    for n, raw in enumerate(raw_samples(find_shards(data_dir, split))):
        if limit is not None and n >= limit:
            break
        record = json.loads(raw["json"])
        for t in range(len(record["targets"])):
            item = training_item(raw, cfg, sample_rng(seed, t, split, int(record["index"])), crop=None, target=t)
            target = to_srgb(_hwc(item["target"]))
            image = _hwc(item["image"])
            with torch.inference_mode():
                _, high = model(item["image"][None].to(device), item["signed_lo"][None].to(device),
                                cfg.data.levels, item["image_lo"][None].to(device))
            outputs = {"network": to_srgb(_hwc(high[0])), "all-in-focus": to_srgb(image)}
            if classical:
                linear = srgb_to_linear(image) if cfg.data.color == "srgb" else image
                rendered = classical_render(linear, _hwc(item["disparity"])[:, :, 0], item["focus"],
                                            item["max_coc"], record)
                outputs["classical"] = linear_to_srgb(rendered)
            for method, out in outputs.items():
                items.append({"key": item["key"], "target": t, "method": method, **_metrics(out, target)})
    if not items:
        raise ValueError(f"{data_dir}/{split}: no samples to evaluate")
    table = []
    for method in METHODS:
        rows = [r for r in items if r["method"] == method]
        if rows:
            table.append({"method": method, "psnr": float(np.mean([r["psnr"] for r in rows])),
                          "ssim": float(np.mean([r["ssim"] for r in rows])), "n": len(rows)})
    result = {"split": split, "seed": seed, "table": table, "items": items}
    atomic_write_bytes(run_dir / "eval.csv", csv_text(["method", "psnr", "ssim", "n"], table).encode())
    atomic_write_bytes(run_dir / "eval.json", canonical_json(result, indent=1))
    return result


def format_table(result: dict) -> str:
    lines = [f"{'method':<14} {'PSNR dB':>8} {'SSIM':>7} {'n':>5}"]
    lines += [f"{r['method']:<14} {r['psnr']:>8.2f} {r['ssim']:>7.4f} {r['n']:>5}" for r in result["table"]]
    return "\n".join(lines)
