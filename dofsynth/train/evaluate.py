"""Evaluate a trained run on a test split, next to the classical renderer.

For every sample and every one of its DoF targets, the same disparity goes to
  - "network":   the run's DeepLensNet on the whole image (lens blur at 1/2**levels, then
                 guided upsampling), and
  - "classical": dofsynth.render.look.render_photo on the image as a single plane (alpha = 1,
                 disparity = the given map) with the Look that made the targets (the
                 sample's aperture, method and options, highlight boost, linear light or not),
and, as a floor, "all-in-focus" (the input itself). Which disparity (`depth`): "gt" (the
clean one), "run" (the run's own training corruption), "realistic" (the kinds of real estimates
together, `REALISTIC`: disparity MAE about 0.14), one corruption kind alone at probability 1
with the default ranges of [augment] (see `DEPTH_KINDS`), a TOML file whose [augment] table is
the setting (a shipped training config by name too, e.g. "train-learn"), always drawn with the
evaluation seed, so runs trained differently are scored on the same inputs; or
"predicted:RUN", what the depth network of run RUN predicts from the all-in-focus image, on the
clean map's scale (`depth_predictor`). The given disparity's MAE against the clean one is
recorded (`depth_mae`). PSNR and SSIM (skimage.metrics, sRGB in [0, 1],
data_range 1) are taken against the rendered target, over the frame and in three regions:
the band within the target's max CoC of a depth edge of the clean disparity ("edge"), where a
single-image renderer fails; the rest of the frame ("out"); and where no blur reaches by the
clean depth ("same": the target is the input there, `reach.untouched`). The table is printed
and written to RUN/eval.csv and RUN/eval.json.

A depth run ([train] task = "depth") is scored by `evaluate_depth` instead: the MAE of its
normalized disparity against the split's (min-max normalized) disparity, raw and after the
paper's 5-knot linear-spline fit (dofsynth.train.depth.depth_errors), beside the best constant.
"""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import cv2
import numpy as np
import torch
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

from dofsynth.color import linear_to_srgb
from dofsynth.files import atomic_write_bytes, canonical_json, csv_text
from dofsynth.io import decode_image, normalize_disparity
from dofsynth.codecs import decode_depth
from dofsynth.train.checkpoint import load_model
from dofsynth.train.classical import classical_render
from dofsynth.train.config import AugmentConfig, load
from dofsynth.train.data import full_res_signed, sample_rng, training_item
from dofsynth.train.segments import excluded, find_segments, raw_samples
from dofsynth.train.depth import depth_errors, predict_disparity
from dofsynth.train.estimates import PREDICTED, check_depth_run, depth_predictor
from dofsynth.train.reach import untouched

METHODS = ("network", "classical", "all-in-focus")
DEPTH_KINDS = {"morph": "morph_prob", "edge_blur": "edge_blur_prob", "noise": "noise_prob",
               "quantize": "quantize_prob", "shift": "shift_prob", "swap": "swap_prob", "fill": "fill_prob",
               "warp": "warp_prob", "remap": "remap_prob"}
# [augment] of `depth = "realistic"`: the errors of monocular estimates together, at a disparity MAE
# like theirs (0.116-0.199 in the DeepLens paper; docs/training.md measures this setting and each kind)
REALISTIC = {"morph_prob": 0.5, "morph_kernel": (3, 21), "swap_prob": 0.15, "fill_prob": 0.5, "warp_prob": 0.8,
             "remap_prob": 1.0, "edge_blur_prob": 0.5, "edge_blur_sigma": (0.5, 2.0)}
EDGE_STEP = 0.02  # a depth edge: neighbouring disparities differ by more (ramps change far less per pixel)


def depth_corruption(depth: str, run_augment: AugmentConfig) -> AugmentConfig:
    """The corruption named by `depth` (see the module docstring) as an AugmentConfig; for
    "predicted:RUN" none (`depth_predictor` gives the map), once RUN is found to hold weights."""
    if depth.startswith(PREDICTED):
        check_depth_run(depth[len(PREDICTED):], f"depth {depth!r}")
        return AugmentConfig(enabled=False)
    if depth == "gt":
        return AugmentConfig(enabled=False)
    if depth == "run":
        return run_augment
    off = {f: 0.0 for f in DEPTH_KINDS.values()}
    if depth in DEPTH_KINDS:
        return dataclasses.replace(AugmentConfig(), **{**off, DEPTH_KINDS[depth]: 1.0})
    if depth == "realistic":
        return dataclasses.replace(AugmentConfig(), **{**off, **REALISTIC})
    try:
        return load(depth).augment  # a TOML file, or a shipped training config by name
    except FileNotFoundError:
        raise ValueError(f"depth must be gt, run, realistic, one of {', '.join(DEPTH_KINDS)}, predicted:RUN (a "
                         f"depth run), a .toml file with an [augment] table or a shipped training config's "
                         f"name, got {depth!r}") from None


def _hwc(t: torch.Tensor) -> np.ndarray:
    return t.detach().float().cpu().numpy().transpose(1, 2, 0)


def edge_band(disparity: np.ndarray, radius: float) -> np.ndarray:
    """(H, W) bool: the pixels within `radius` px of a depth edge of the clean disparity."""
    d = np.asarray(disparity, np.float32)
    edge = np.zeros(d.shape, bool)
    dy, dx = np.abs(np.diff(d, axis=0)) > EDGE_STEP, np.abs(np.diff(d, axis=1)) > EDGE_STEP
    edge[:-1] |= dy
    edge[1:] |= dy
    edge[:, :-1] |= dx
    edge[:, 1:] |= dx
    r = max(1, int(np.ceil(radius)))
    se = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
    return cv2.dilate(edge.astype(np.uint8), se) > 0


REGIONS = ("edge", "out", "same")  # the edge band, the rest of the frame, where no blur reaches (target = input)
FIELDS = ["method", "psnr", "ssim"] + [f"{m}_{r}" for r in REGIONS for m in ("psnr", "ssim")] + ["n"]


PSNR_CAP = 100.0  # dB: what identical pixels score (PSNR is infinite there)


def _psnr(ref: np.ndarray, pred: np.ndarray) -> float:
    if np.array_equal(ref, pred):
        return PSNR_CAP
    return min(float(peak_signal_noise_ratio(ref, pred, data_range=1.0)), PSNR_CAP)


def _metrics(pred_srgb: np.ndarray, target_srgb: np.ndarray, band: np.ndarray, same: np.ndarray) -> dict:
    """PSNR and SSIM over the frame, and in each region of REGIONS (`band`; outside it; `same`,
    where no blur reaches by the clean depth, so the target is the input): PSNR over its pixels
    (at most PSNR_CAP), SSIM the mean of the SSIM map (7 px windows, the channels' mean) over
    them; None for an empty region."""
    pred = np.clip(pred_srgb, 0.0, 1.0).astype(np.float64)
    ref = target_srgb.astype(np.float64)
    side = min(ref.shape[:2])
    win = 7 if side >= 7 else max(1, side - (1 - side % 2))  # SSIM needs an odd window <= the side
    ssim, smap = structural_similarity(ref, pred, data_range=1.0, channel_axis=2, win_size=win, full=True)
    smap = smap.mean(axis=2)
    out = {"psnr": _psnr(ref, pred), "ssim": float(ssim)}
    for name, mask in zip(REGIONS, (band, ~band, same)):
        on = mask.any()
        out[f"psnr_{name}"] = _psnr(ref[mask], pred[mask]) if on else None
        out[f"ssim_{name}"] = float(smap[mask].mean()) if on else None
    return out


def evaluate_run(run_dir: str | Path, data_dir: str | Path, *, split: str = "test", limit: int | None = None,
                 classical: bool = True, depth: str = "run", seed: int = 12345, device: str | None = None,
                 write: bool = True) -> dict:
    """Score every target of the first `limit` samples of `split`, everyone given the disparity
    `depth` names; returns {"table": [{"method", "psnr", "ssim", "psnr_edge", "ssim_edge",
    "psnr_out", "ssim_out", "psnr_same", "ssim_same", "n"}] (FIELDS), "items":
    [...]} and writes RUN/eval.{csv,json} (unless write=False)."""
    run_dir = Path(run_dir)
    device = device or ("cuda" if torch.cuda.is_available() else "cpu")
    model, cfg = load_model(run_dir, device)
    if cfg.train.task == "depth":
        return evaluate_depth(model, cfg, run_dir, data_dir, split=split, limit=limit, write=write)
    augment = depth_corruption(depth, cfg.augment)
    predictor = depth_predictor(depth, device)
    to_srgb = (lambda x: x) if cfg.data.color == "srgb" else linear_to_srgb
    items = []
    for n, raw in enumerate(raw_samples(find_segments(data_dir, split, exclude=excluded(cfg, data_dir)), split)):
        if limit is not None and n >= limit:
            break
        record = json.loads(raw["json"])
        clean = decode_depth(raw["depth.exr"], f"{raw['__key__']}.depth.exr")
        given = predictor(raw, clean) if predictor else None
        for t in range(len(record["targets"])):
            rng = sample_rng(seed, t, split, int(record["index"]))
            item = training_item(raw, cfg, rng, crop=None, target=t, augment=augment, disparity=given)
            target = to_srgb(_hwc(item["target"]))
            image = to_srgb(_hwc(item["image"]))
            truth = clean[: target.shape[0], : target.shape[1]]  # (the item is trimmed to a multiple of 2**levels)
            disparity = _hwc(item["disparity"])[:, :, 0]  # what everyone is given
            depth_mae = float(np.abs(disparity - truth).mean())
            band = edge_band(truth, item["max_coc"])
            signed = torch.from_numpy(truth - np.float32(item["focus"]))
            same = untouched(signed[None, None], float(item["max_coc"]))[0, 0].numpy()  # no blur reaches, by the clean depth
            with torch.inference_mode():
                one = {k: (v[None].to(device) if torch.is_tensor(v) else [v]) for k, v in item.items()
                       if k in ("image", "signed_lo", "image_lo", "disparity", "focus", "max_coc", "classical")}
                _, high = model(one["image"], one["signed_lo"], cfg.data.levels, one["image_lo"],
                                **full_res_signed(one, cfg))
            outputs = {"network": to_srgb(_hwc(high[0])), "all-in-focus": image}
            if classical:
                outputs["classical"] = classical_render(image, disparity, item["focus"], item["max_coc"], record)
            for method, out in outputs.items():
                items.append({"key": item["key"], "target": t, "method": method, **_metrics(out, target, band, same),
                              "depth_mae": depth_mae})
    if not items:
        raise ValueError(f"{data_dir}/{split}: no samples to evaluate")
    table = []
    for method in METHODS:
        rows = [r for r in items if r["method"] == method]
        if rows:  # means over the targets (a region's over those that have it)
            means = {}
            for f in FIELDS[1:-1]:
                vals = [r[f] for r in rows if r[f] is not None]
                means[f] = float(np.mean(vals)) if vals else None
            table.append({"method": method, **means, "n": len(rows)})
    result = {"split": split, "seed": seed, "depth": depth, "table": table, "items": items,
              "depth_mae": float(np.mean([r["depth_mae"] for r in items]))}  # the given disparity's, against the clean
    if write:
        atomic_write_bytes(run_dir / "eval.csv", csv_text(FIELDS, table).encode())
        atomic_write_bytes(run_dir / "eval.json", canonical_json(result, indent=1))
    return result


DEPTH_FIELDS = ["method", "mae", "mae_spline", "n"]


def evaluate_depth(model, cfg, run_dir: str | Path, data_dir: str | Path, *, split: str = "test",
                   limit: int | None = None, write: bool = True, part: str = "all") -> dict:
    """Score a depth network on the first `limit` samples of `split` (its `part`: "val" is the
    train split's held-out [data] val_share; whole images at the training scale); returns {"kind": "depth", "table": [{"method", "mae", "mae_spline", "n"}],
    "items": [...]} (methods "network" and "constant") and writes RUN/eval.{csv,json}."""
    items = []
    segments = find_segments(data_dir, split, part, cfg.data.val_share, excluded(cfg, data_dir))
    for n, raw in enumerate(raw_samples(segments, split)):
        if limit is not None and n >= limit:
            break
        key = raw["__key__"]
        gt = decode_depth(raw["depth.exr"], f"{key}.depth.exr")
        if np.ptp(gt) < 1e-6:
            continue  # a flat scene has no depth order to predict
        image = decode_image(raw["aif.png"], f"{key}.aif.png")[:, :, :3]
        pred = predict_disparity(model, image, cfg.data.crop)
        items.append({"key": key, **depth_errors(pred, normalize_disparity(gt, "disparity")[0])})
    if not items:
        raise ValueError(f"{data_dir}/{split}: no samples with a depth range to evaluate")
    mean = {k: float(np.mean([r[k] for r in items])) for k in ("mae", "mae_spline", "mae_constant")}
    table = [{"method": "network", "mae": mean["mae"], "mae_spline": mean["mae_spline"], "n": len(items)},
             {"method": "constant", "mae": mean["mae_constant"], "mae_spline": mean["mae_constant"], "n": len(items)}]
    result = {"kind": "depth", "split": split, "table": table, "items": items}
    if write:
        atomic_write_bytes(Path(run_dir) / "eval.csv", csv_text(DEPTH_FIELDS, table).encode())
        atomic_write_bytes(Path(run_dir) / "eval.json", canonical_json(result, indent=1))
    return result


def format_table(result: dict) -> str:
    if result.get("kind") == "depth":
        lines = ["normalized disparity, mean absolute error (the constant: the best flat map)",
                 f"{'method':<14} {'MAE':>7} {'MAE spline':>11} {'n':>5}"]
        lines += [f"{r['method']:<14} {r['mae']:>7.4f} {r['mae_spline']:>11.4f} {r['n']:>5}" for r in result["table"]]
        return "\n".join(lines)
    mae = f" (disparity MAE {result['depth_mae']:.3f})" if result.get("depth_mae") is not None else ""
    lines = [f"depth given: {result.get('depth', 'run')}{mae}; regions: edge = within max CoC of a depth edge, "
             "out = the rest, same = where the target is the input",
             f"{'method':<14} {'PSNR dB':>8} {'SSIM':>7}" + "".join(f" {r + ' dB':>8} {r + ' SSIM':>10}" for r in REGIONS)
             + f" {'n':>5}"]
    for r in result["table"]:
        cells = "".join(f" {r[f'psnr_{g}']:>8.2f} {r[f'ssim_{g}']:>10.4f}" if r.get(f"psnr_{g}") is not None
                        else f" {'-':>8} {'-':>10}" for g in REGIONS)
        lines.append(f"{r['method']:<14} {r['psnr']:>8.2f} {r['ssim']:>7.4f}{cells} {r['n']:>5}")
    return "\n".join(lines)
