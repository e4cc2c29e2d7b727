"""Depth corruption (dofsynth.augment): each kind does what it says, is seeded and replayable."""
from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from dofsynth.train.augment import (DepthLayers, apply_corruption, record_background, corrupt_disparity,
                              layers_from_record, morph_mask, sample_corruption)
from dofsynth.train.config import AugmentConfig

OFF = AugmentConfig(morph_prob=0.0)
H = W = 40
BG, MID, FRONT = 0.1, 0.5, 0.8


def scene():
    """Background 0.1, a middle square (rows/cols 10..29) at 0.5, a front square (16..23) at 0.8
    inside it, and a second front square (2..5) over the background."""
    mid = np.zeros((H, W), bool)
    mid[10:30, 10:30] = True
    front = np.zeros((H, W), bool)
    front[16:24, 16:24] = True
    front[2:6, 2:6] = True
    d = np.full((H, W), BG, np.float32)
    d[mid], d[front] = MID, FRONT
    return d, DepthLayers(np.full((H, W), BG, np.float32), ((mid, MID), (front, FRONT)))


def params(**kw):
    p = {"morph": [None, None], "shift": None, "edge_blur": None, "noise": None, "quantize": None,
         "swap": False, "fill": [None, None], "warp": None, "remap": None}
    p.update(kw)
    return p


def test_no_corruption_is_the_identity_and_the_input_is_untouched():
    d, layers = scene()
    before = d.copy()
    out, p = corrupt_disparity(d, layers, AugmentConfig(enabled=False), np.random.default_rng(0))
    assert np.array_equal(out, d) and np.array_equal(d, before)
    assert p == params()
    out, _ = corrupt_disparity(d, layers, OFF, np.random.default_rng(0))
    assert np.array_equal(out, d)


def test_dilating_the_front_plane_spreads_its_disparity_over_what_is_behind():
    d, layers = scene()
    out = apply_corruption(d, layers, params(morph=[None, {"op": "dilate", "kernel": 5}]))
    front = layers.planes[1][0]
    grown = morph_mask(front, "dilate", 5)
    assert np.all(out[front] == FRONT)
    assert np.all(out[grown] == FRONT) and (grown & ~front).sum() > 0
    assert np.array_equal(out[~grown], d[~grown])          # nothing else changes
    assert out[16, 14] == FRONT and out[3, 7] == FRONT       # over the middle plane and the background


def test_eroding_takes_the_disparity_behind_each_pixel():
    d, layers = scene()
    out = apply_corruption(d, layers, params(morph=[None, {"op": "erode", "kernel": 3}]))
    front = layers.planes[1][0]
    kept = morph_mask(front, "erode", 3)
    assert np.all(out[kept] == FRONT)
    lost = front & ~kept
    mid = layers.planes[0][0]
    assert np.all(out[lost & mid] == MID) and (lost & mid).sum() > 0      # the inner square: middle behind
    assert np.all(out[lost & ~mid] == BG) and (lost & ~mid).sum() > 0     # the corner square: background behind


def test_the_middle_plane_never_paints_over_the_front_one():
    d, layers = scene()
    out = apply_corruption(d, layers, params(morph=[{"op": "dilate", "kernel": 9}, None]))
    front = layers.planes[1][0]
    assert np.all(out[front] == FRONT)
    assert out[8, 15] == MID and out[3, 3] == FRONT   # grew outward; the corner front square stays
    eroded = apply_corruption(d, layers, params(morph=[{"op": "erode", "kernel": 9}, None]))
    assert np.all(eroded[front] == FRONT) and eroded[10, 10] == BG


def test_an_eroded_middle_shows_the_background_under_an_eroded_front():
    d, layers = scene()
    p = params(morph=[{"op": "erode", "kernel": 21}, {"op": "erode", "kernel": 3}])
    out = apply_corruption(d, layers, p)
    # the middle square (20 px) vanishes under a 21 px erosion, so the front's lost rim shows background
    assert out[16, 16] == BG and out[20, 20] == FRONT


def test_shift_blur_noise_and_quantization():
    d, layers = scene()
    shifted = apply_corruption(d, layers, params(shift=[1, -2]))     # dy = 1, dx = -2
    assert np.array_equal(shifted[1:, :-2], d[:-1, 2:])
    blurred = apply_corruption(d, layers, params(edge_blur=2.0))
    assert np.abs(np.diff(blurred, axis=1)).max() < 0.5 * np.abs(np.diff(d, axis=1)).max()
    assert np.isclose(blurred[35, 35], BG, atol=1e-4)              # flat areas keep their value
    noisy = apply_corruption(d, layers, params(noise={"std": 0.01, "seed": 3}))
    assert 0.007 < np.std(noisy - d) < 0.013
    assert np.array_equal(noisy, apply_corruption(d, layers, params(noise={"std": 0.01, "seed": 3})))
    q = apply_corruption(d + np.float32(0.013), layers, params(quantize=11))
    assert np.allclose(q * 10, np.round(q * 10), atol=1e-5) and np.abs(q - d - 0.013).max() <= 0.05 + 1e-6
    assert q.dtype == np.float32 and q.min() >= 0 and q.max() <= 1


def test_sampling_is_seeded_json_able_and_replays_exactly():
    d, layers = scene()
    cfg = AugmentConfig(morph_prob=1.0, edge_blur_prob=0.5, noise_prob=0.5, quantize_prob=0.5, shift_prob=0.5,
                        swap_prob=0.5, fill_prob=0.5, warp_prob=0.5, remap_prob=0.5)
    a, pa = corrupt_disparity(d, layers, cfg, np.random.default_rng([7, 1]))
    b, pb = corrupt_disparity(d, layers, cfg, np.random.default_rng([7, 1]))
    assert np.array_equal(a, b) and pa == pb
    assert np.array_equal(apply_corruption(d, layers, json.loads(json.dumps(pa))), a)
    kinds = {k for s in range(40) for k, v in sample_corruption(2, cfg, np.random.default_rng(s)).items()
             if (any(v) if isinstance(v, list) else v)}
    assert kinds == {"morph", "edge_blur", "noise", "quantize", "shift", "swap", "fill", "warp", "remap"}
    ops = {m["op"] for s in range(40) for m in sample_corruption(2, cfg, np.random.default_rng(s))["morph"]}
    kernels = {m["kernel"] for s in range(40) for m in sample_corruption(2, cfg, np.random.default_rng(s))["morph"]}
    assert ops == {"dilate", "erode"} and kernels <= set(range(3, 16, 2)) and len(kernels) > 3


def test_switching_one_kind_off_leaves_the_others_draws_alone():
    cfg = AugmentConfig(morph_prob=1.0, noise_prob=1.0, shift_prob=1.0)
    cfg_no_morph = AugmentConfig(morph_prob=0.0, noise_prob=1.0, shift_prob=1.0)
    for s in range(5):
        a = sample_corruption(2, cfg, np.random.default_rng(s))
        b = sample_corruption(2, cfg_no_morph, np.random.default_rng(s))
        assert b["morph"] == [None, None] and a["noise"] == b["noise"] and a["shift"] == b["shift"]


def test_a_clean_share_leaves_that_share_of_items_uncorrupted_and_the_others_as_they_were():
    """[augment] clean_prob: about that share of the draws corrupts nothing (the item trains on
    the clean disparity); every other draw is what it was without the key."""
    d, layers = scene()
    cfg = AugmentConfig(morph_prob=1.0, warp_prob=1.0, remap_prob=1.0)
    shared = dataclasses.replace(cfg, clean_prob=0.3)
    clean = 0
    for s in range(200):
        a = sample_corruption(2, cfg, np.random.default_rng(s))
        b = sample_corruption(2, shared, np.random.default_rng(s))
        if b["warp"] is None:
            clean += 1
            assert b == sample_corruption(2, AugmentConfig(enabled=False), np.random.default_rng(s))
            assert np.array_equal(apply_corruption(d, layers, b), d)
        else:
            assert a == b
    assert 40 <= clean <= 80  # 30 % of 200, binomial sd 6.5


def test_layers_from_a_record_and_its_cover_image():
    rec = {"key": "k", "background": {"mode": "ramp", "b0": 0.0, "b1": 0.4, "direction": "vertical"},
           "front": {"disparity": 0.9}, "middle": {"disparity": 0.6}}
    cover = np.zeros((4, 5, 3), np.float32)
    cover[0, 0, 0], cover[1, 1, 1] = 1.0, 0.7
    layers = layers_from_record(rec, cover)
    (mid, dm), (front, df) = layers.planes
    assert (dm, df) == (0.6, 0.9) and front.sum() == 1 and front[0, 0] and mid.sum() == 1 and mid[1, 1]
    bg = layers.background          # vertical: b0 at the bottom edge, b1 at the top edge
    assert np.allclose(bg[:, 0], [0.4, 0.4 * 2 / 3, 0.4 / 3, 0.0]) and np.allclose(bg[0], 0.4)
    horiz = record_background({"background": {"mode": "ramp", "b0": 0.0, "b1": 0.4,
                                                 "direction": "horizontal"}}, (2, 4))
    assert np.allclose(horiz[0], [0.0, 0.4 / 3, 0.4 * 2 / 3, 0.4])
    with pytest.raises(ValueError, match="mode"):
        record_background({"background": {"mode": "spiral", "b0": 0.1, "b1": 0.0}}, (2, 2))
    with pytest.raises(ValueError, match="morphology"):
        morph_mask(np.ones((3, 3), bool), "open", 3)


def test_the_kinds_of_real_estimates_swap_fill_warp_and_remap():
    d, layers = scene()
    swapped = apply_corruption(d, layers, params(swap=True))
    assert swapped[20, 20] == MID and swapped[12, 12] == FRONT and swapped[3, 3] == MID and swapped[35, 35] == BG
    # a front plane of two bars with a 3 px gap: a closing of 7 px fills the gap at the front's depth
    bars = np.zeros((H, W), bool)
    bars[5:35, 5:12] = bars[5:35, 15:22] = True
    d2 = np.where(bars, np.float32(FRONT), np.float32(BG)).astype(np.float32)
    two = DepthLayers(np.full((H, W), BG, np.float32), ((np.zeros((H, W), bool), MID), (bars, FRONT)))
    filled = apply_corruption(d2, two, params(fill=[None, 7]))
    assert (filled[8:32, 12:15] == FRONT).all() and filled[20, 30] == BG and filled[2, 13] == BG
    assert np.array_equal(apply_corruption(d2, two, params(fill=[None, 1])), d2)   # a 1 px closing changes nothing
    # a warp moves values (nearest: no new ones), smoothly, by about its std
    warped = apply_corruption(d, layers, params(warp={"px": 2.0, "cells": 2, "seed": 5}))
    assert set(np.unique(warped)) <= set(np.unique(d)) and not np.array_equal(warped, d)
    assert abs(int((warped == FRONT).sum()) - int((d == FRONT).sum())) < 0.5 * (d == FRONT).sum()
    assert np.array_equal(apply_corruption(d, layers, params(warp={"px": 0.0, "cells": 2, "seed": 5})), d)
    # the remap by hand: 1.3 * d^0.5 - 0.1
    remapped = apply_corruption(d, layers, params(remap={"scale": 1.3, "shift": -0.1, "gamma": 0.5}))
    assert np.isclose(remapped[35, 35], 1.3 * BG ** 0.5 - 0.1, atol=1e-6)       # 0.311
    assert np.isclose(remapped[12, 12], 1.3 * MID ** 0.5 - 0.1, atol=1e-6)      # 0.819
    assert remapped[20, 20] == 1.0                                  # 1.3 * 0.894 - 0.1 = 1.063: clipped


def _smoke_depths(smoke_set) -> list:
    """(clean disparity, layers) of every sample of the smoke set (train, then test)."""
    from dofsynth.codecs import decode_depth
    from dofsynth.io import decode_image
    from dofsynth.train.segments import find_segments, raw_samples

    samples = []
    for split in ("train", "test"):
        for raw in raw_samples(find_segments(smoke_set, split), split):
            cover = decode_image(raw["cover.png"], "cover")
            samples.append((decode_depth(raw["depth.exr"], "depth"), layers_from_record(json.loads(raw["json"]), cover)))
    return samples


def _mae(samples, which: str) -> float:
    """The mean disparity MAE of `dofsynth eval --depth which` on (disparity, layers) samples,
    drawn with the evaluation seed."""
    from dofsynth.train.evaluate import depth_corruption

    cfg = depth_corruption(which, AugmentConfig())
    return float(np.mean([np.abs(corrupt_disparity(d, lay, cfg, np.random.default_rng([12345, i]))[0] - d).mean()
                          for i, (d, lay) in enumerate(samples)]))


def test_realistic_depth_is_as_wrong_as_a_monocular_estimate(smoke_set):
    """`--depth realistic` on the real generator's samples: a disparity MAE in 0.10-0.20, as the
    DeepLens paper measured for real estimators (0.116-0.199); each kind alone stays below it."""
    samples = _smoke_depths(smoke_set)
    realistic = _mae(samples, "realistic")
    assert len(samples) == 8 and 0.10 <= realistic <= 0.20
    assert _mae(samples, "gt") == 0.0 and all(_mae(samples, kind) < realistic for kind in ("morph", "warp", "remap", "fill"))


def test_the_real_photo_benchmarks_errors_are_realistic_tripled(smoke_set):
    """benchmarks/depth-errors-real.toml (the real-photo lens-blur benchmark's depth errors) is
    `--depth realistic` with every pixel size three times as large and nothing else changed, as
    its header says; `dofsynth eval --depth FILE` takes it, and it makes the depth more wrong."""
    import dataclasses
    from pathlib import Path

    from dofsynth.train.evaluate import depth_corruption

    path = str(Path(__file__).resolve().parents[1] / "benchmarks" / "depth-errors-real.toml")
    realistic = depth_corruption("realistic", AugmentConfig())
    errors = depth_corruption(path, AugmentConfig())
    px = {"morph_kernel", "fill_kernel", "warp_px", "edge_blur_sigma"}  # the sizes in pixels
    for f in dataclasses.fields(AugmentConfig):
        mine, theirs = getattr(errors, f.name), getattr(realistic, f.name)
        if f.name in px:  # (odd kernel sides stay odd)
            assert tuple(mine) == tuple(3 * v for v in theirs), f.name
        else:
            assert mine == theirs, f.name
    samples = _smoke_depths(smoke_set)
    assert _mae(samples, path) > _mae(samples, "realistic")
