"""Depth corruption: make the clean disparity of a synthetic sample look like an estimated one.

DeepLens trains its lens-blur network on disparity that is deliberately wrong near object
boundaries, so that at test time it tolerates the errors of a depth estimator: each foreground
plane's region is dilated or eroded by a random kernel. Dilated pixels take that plane's
disparity; eroded-away pixels take the disparity of what lies behind. Further kinds, off by
default: a Gaussian blur of the map (soft edges), additive noise, quantization (8-bit-like
depth) and a small shift of the whole map; and the errors that make real monocular estimates
wrong by a disparity MAE of 0.1-0.2 (docs/training.md measures each): the two foreground
planes' depths swapped (wrong order), each plane's holes and gaps filled with its own disparity
(a closing: the background between hair strands or limbs comes out at the object's depth), a
smooth random warp of the whole map (boundaries displaced by several pixels, bent), and a
monotone remap of the normalized disparity d -> clip(scale * d^gamma + shift).

Only the disparity the network *sees* is corrupted; the targets stay as rendered. Everything
here is numpy/cv2 (no torch) and takes an explicit `rng`. As elsewhere in dofsynth, parameters
are sampled first (`sample_corruption`, a JSON-able dict) and then applied
(`apply_corruption`), so a record of the parameters replays the corruption exactly.
Every random kind draws from its own child generator, so switching one kind off does not change
what the others sample.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from dofsynth.render.planes import background_disparity

MORPH_OPS = ("dilate", "erode")


@dataclass(frozen=True)
class DepthLayers:
    """The layered disparity of a sample, back to front.

    background: (H, W) float32 disparity of the background plane (no foreground).
    planes: [(mask, disparity), ...] foreground planes back to front; mask (H, W) bool is where
        the plane covers the pixel (alpha > 0.5), disparity its constant disparity in [0, 1].
    """
    background: np.ndarray
    planes: tuple[tuple[np.ndarray, float], ...]


def record_background(record: dict, shape: tuple[int, int]) -> np.ndarray:
    """The background disparity map (H, W) of a sample record's `background` block
    (docs/FORMAT.md), as the generator made it (dofsynth.render.planes.background_disparity)."""
    bg = record["background"]
    return background_disparity(bg["mode"], float(bg["b0"]), float(bg["b1"]), bg.get("direction"), *shape)


def layers_from_record(record: dict, cover: np.ndarray) -> DepthLayers:
    """Layers from a record and its cover image (H, W, >=2) in [0, 1]: R = front alpha,
    G = middle alpha (docs/FORMAT.md). Planes come back to front: middle, then front."""
    h, w = cover.shape[:2]
    planes = (
        (cover[:, :, 1] > 0.5, float(record["middle"]["disparity"])),
        (cover[:, :, 0] > 0.5, float(record["front"]["disparity"])),
    )
    return DepthLayers(record_background(record, (h, w)), planes)


def _odd_between(rng: np.random.Generator, lo: int, hi: int) -> int:
    odds = np.arange(lo | 1, hi + 1, 2)
    return int(rng.choice(odds)) if odds.size else int(lo | 1)


def sample_corruption(n_planes: int, cfg, rng: np.random.Generator) -> dict:
    """Sample corruption parameters (a JSON-able dict) for a sample with `n_planes` foreground
    planes. `cfg` is a dofsynth.train.config.AugmentConfig (or anything with its fields)."""
    params: dict = {"morph": [None] * n_planes, "shift": None, "edge_blur": None, "noise": None,
                    "quantize": None, "swap": False, "fill": [None] * n_planes, "warp": None, "remap": None}
    if not cfg.enabled:
        return params
    r_morph, r_shift, r_blur, r_noise, r_quant = rng.spawn(5)
    r_swap, r_fill, r_warp, r_remap = rng.spawn(4)  # after the first five: their draws stay as they were
    (r_clean,) = rng.spawn(1)  # after those: the same again
    if cfg.clean_prob > 0 and r_clean.random() < cfg.clean_prob:  # this item keeps the clean disparity
        return params
    params["swap"] = n_planes == 2 and bool(r_swap.random() < cfg.swap_prob)
    for i in range(n_planes):
        if r_fill.random() < cfg.fill_prob:
            params["fill"][i] = _odd_between(r_fill, *cfg.fill_kernel)
    if r_warp.random() < cfg.warp_prob:
        params["warp"] = {"px": float(r_warp.uniform(*cfg.warp_px)), "cells": int(cfg.warp_cells),
                          "seed": int(r_warp.integers(2**31))}
    if r_remap.random() < cfg.remap_prob:
        params["remap"] = {"scale": float(r_remap.uniform(*cfg.remap_scale)),
                           "shift": float(r_remap.uniform(*cfg.remap_shift)),
                           "gamma": float(r_remap.uniform(*cfg.remap_gamma))}
    for i in range(n_planes):
        if r_morph.random() < cfg.morph_prob:
            op = MORPH_OPS[int(r_morph.integers(2))]
            params["morph"][i] = {"op": op, "kernel": _odd_between(r_morph, *cfg.morph_kernel)}
    if r_shift.random() < cfg.shift_prob and cfg.shift_max > 0:
        params["shift"] = [int(v) for v in r_shift.integers(-cfg.shift_max, cfg.shift_max + 1, size=2)]
    if r_blur.random() < cfg.edge_blur_prob:
        params["edge_blur"] = float(r_blur.uniform(*cfg.edge_blur_sigma))
    if r_noise.random() < cfg.noise_prob:
        params["noise"] = {"std": float(r_noise.uniform(*cfg.noise_std)),
                           "seed": int(r_noise.integers(2**31))}
    if r_quant.random() < cfg.quantize_prob:
        params["quantize"] = int(r_quant.integers(cfg.quantize_levels[0], cfg.quantize_levels[1] + 1))
    return params


def morph_mask(mask: np.ndarray, op: str, kernel: int) -> np.ndarray:
    """Dilate or erode a bool mask with an elliptical (disk-like) kernel of side `kernel` px."""
    se = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (kernel, kernel))
    m = mask.astype(np.uint8)
    if op == "dilate":
        out = cv2.dilate(m, se, borderType=cv2.BORDER_CONSTANT, borderValue=0)
    elif op == "erode":
        out = cv2.erode(m, se, borderType=cv2.BORDER_REPLICATE)
    else:
        raise ValueError(f"morphology op must be one of {MORPH_OPS}, got {op!r}")
    return out.astype(bool)


def apply_corruption(disparity: np.ndarray, layers: DepthLayers, params: dict) -> np.ndarray:
    """Apply sampled corruption parameters to a clean disparity map (H, W) float32 in [0, 1].

    Order: plane depths swapped, plane morphology and filling (back to front), shift, warp,
    edge blur, remap, noise, quantization; the result is clipped to [0, 1]. The input is not
    modified. Parameters of kinds added later may be missing (older records): off.
    """
    d = np.array(disparity, dtype=np.float32, copy=True)
    if d.ndim != 2 or d.shape != layers.background.shape:
        raise ValueError(f"disparity must be (H, W) = {layers.background.shape}, got {d.shape}")
    morph = params.get("morph") or [None] * len(layers.planes)
    if len(morph) != len(layers.planes):
        raise ValueError(f"params['morph'] has {len(morph)} entries for {len(layers.planes)} planes")
    fill = params.get("fill") or [None] * len(layers.planes)
    depths = [pd for _, pd in layers.planes]
    if params.get("swap"):  # wrong order: each plane seen at the other's depth
        depths = depths[::-1]
    behind = layers.background.astype(np.float32)
    for i, ((mask, _), plane_d, m, k) in enumerate(zip(layers.planes, depths, morph, fill)):
        new_mask = mask if m is None else morph_mask(mask, m["op"], int(m["kernel"]))
        if k is not None:
            new_mask = new_mask | morph_mask(morph_mask(new_mask, "dilate", int(k)), "erode", int(k))
        in_front = np.zeros_like(mask)
        for later_mask, _ in layers.planes[i + 1:]:
            in_front |= later_mask
        if params.get("swap"):
            d[mask & ~in_front] = plane_d
        d[new_mask & ~mask & ~in_front] = plane_d  # grown (dilated, filled)
        shrunk = mask & ~new_mask & ~in_front
        d[shrunk] = behind[shrunk]
        behind = np.where(new_mask, np.float32(plane_d), behind)
    if params.get("shift"):
        dy, dx = params["shift"]
        mat = np.float32([[1, 0, dx], [0, 1, dy]])
        d = cv2.warpAffine(d, mat, (d.shape[1], d.shape[0]), flags=cv2.INTER_NEAREST,
                           borderMode=cv2.BORDER_REPLICATE)
    if params.get("warp"):
        d = _warp(d, **params["warp"])
    if params.get("edge_blur"):
        d = cv2.GaussianBlur(d, (0, 0), sigmaX=float(params["edge_blur"]), borderType=cv2.BORDER_REFLECT)
    if params.get("remap"):
        r = params["remap"]
        d = r["scale"] * np.clip(d, 0.0, 1.0) ** np.float32(r["gamma"]) + np.float32(r["shift"])
    if params.get("noise"):
        n = params["noise"]
        d = d + np.random.default_rng(n["seed"]).normal(0.0, n["std"], d.shape).astype(np.float32)
    if params.get("quantize"):
        q = int(params["quantize"]) - 1
        d = np.round(np.clip(d, 0.0, 1.0) * q) / q
    return np.clip(d, 0.0, 1.0).astype(np.float32)


def _warp(d: np.ndarray, px: float, cells: int, seed: int) -> np.ndarray:
    """The map resampled (nearest: edges stay sharp) through a smooth random displacement: normal
    offsets of std `px` pixels on a (cells + 1)^2 grid over the frame, bicubically interpolated."""
    h, w = d.shape
    grid = np.random.default_rng(seed).normal(0.0, px, (2, cells + 1, cells + 1)).astype(np.float32)
    fx, fy = (cv2.resize(g, (w, h), interpolation=cv2.INTER_CUBIC) for g in grid)
    xs, ys = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    return cv2.remap(d, xs + fx, ys + fy, cv2.INTER_NEAREST, borderMode=cv2.BORDER_REPLICATE)


def corrupt_disparity(disparity: np.ndarray, layers: DepthLayers, cfg, rng: np.random.Generator
                      ) -> tuple[np.ndarray, dict]:
    """Sample and apply a corruption: returns (corrupted (H, W) float32, params)."""
    params = sample_corruption(len(layers.planes), cfg, rng)
    return apply_corruption(disparity, layers, params), params
