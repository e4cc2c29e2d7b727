"""How wrong each depth-corruption kind makes the disparity: MAE against the clean map.

    .venv/bin/python benchmarks/depth_errors.py --data OUT [--split test] [--samples 60] [--predicted RUN] [--also TOML]

For the first N samples of a data set's split (e.g. the learning benchmark's, recipes/learn.toml),
every kind of dofsynth.train.augment alone at probability 1 with the default [augment] ranges
(`dofsynth eval --depth KIND`), the shipped train-learn setting, and `--depth realistic`, drawn
with the evaluation seed, and with --predicted the map a depth run predicts (`--depth
predicted:RUN`: fitted to the clean map's scale by the 5-knot spline) and with --also the
errors of a TOML file's [augment] table: mean, median and 90th
percentile of the per-sample disparity MAE. The DeepLens paper measured 0.116-0.199 for real
monocular estimators.
"""
from __future__ import annotations

import argparse
import json

import numpy as np

from dofsynth.codecs import decode_depth
from dofsynth.io import decode_image
from dofsynth.train.augment import corrupt_disparity, layers_from_record
from dofsynth.train.config import AugmentConfig
from dofsynth.train.segments import find_segments, raw_samples
from dofsynth.train.estimates import depth_predictor
from dofsynth.train.evaluate import DEPTH_KINDS, depth_corruption


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", required=True, help="a data set folder (dofsynth generate)")
    ap.add_argument("--split", default="test")
    ap.add_argument("--samples", type=int, default=60)
    ap.add_argument("--predicted", metavar="RUN", help="also the disparity this depth run predicts")
    ap.add_argument("--also", metavar="TOML", action="append", default=[],
                    help="also the errors of this file's [augment] table (e.g. benchmarks/depth-errors-real.toml); "
                         "may be given more than once")
    args = ap.parse_args()
    predict = depth_predictor(f"predicted:{args.predicted}", "cpu") if args.predicted else None
    samples = []
    for raw in raw_samples(find_segments(args.data, args.split), args.split):
        if len(samples) >= args.samples:
            break
        layers = layers_from_record(json.loads(raw["json"]), decode_image(raw["cover.png"], raw["__key__"]))
        clean = decode_depth(raw["depth.exr"], raw["__key__"])
        samples.append((clean, layers, predict(raw, clean) if predict else None))
    d0 = samples[0][0]
    print(f"{len(samples)} samples of {args.data}/{args.split}, {d0.shape[1]}x{d0.shape[0]} px")
    print("| --depth | MAE mean | median | 90th pct |\n|---|---|---|---|")
    for which in [*DEPTH_KINDS, "train-learn", "realistic", *args.also]:
        cfg = depth_corruption(which, AugmentConfig())
        maes = [float(np.abs(corrupt_disparity(d, layers, cfg, np.random.default_rng([12345, i]))[0] - d).mean())
                for i, (d, layers, _) in enumerate(samples)]
        print(f"| {which} | {np.mean(maes):.3f} | {np.median(maes):.3f} | {np.percentile(maes, 90):.3f} |")
    if predict:
        maes = [float(np.abs(p - d).mean()) for d, _, p in samples]
        print(f"| predicted:{args.predicted} | {np.mean(maes):.3f} | {np.median(maes):.3f} | "
              f"{np.percentile(maes, 90):.3f} |")


if __name__ == "__main__":
    main()
