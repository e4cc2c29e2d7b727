"""The depth benchmark: the small depth-prediction network learns the order of depths of the
learn set's scenes in a few CPU minutes.

    .venv/bin/python benchmarks/learn_depth.py [--out out/learn-bench]

Data: the learning benchmark's set (recipes/learn.toml: 256 px, 2000 train + 100 test samples
of the built-in assets), generated into OUT/data or reused. Runs (recipes/train-depth-learn.toml,
in OUT/runs/depth-<name>, reused when finished):
  "shards + mattes"  the shards' disparity and coverage, plus the segmentation term on the
                     mattes of ../shared/assets (fg/ + alpha/) where they are present;
  "shards only"      without the mattes;
  "shards only, colour jitter"   [depth] jitter = 0.8: random colour order, saturation,
                     contrast and brightness, so depth must come from structure, not colour.
Then MAE of the min-max normalized disparity, raw and after the paper's 5-knot linear-spline fit
to the ground truth, for the untrained network, each run and the best constant map (the
ground truth's median), on two sets: the held-out validation share of the train split (new
scenes of the training assets) and the test split (scenes of assets never seen in training:
recipes split the assets). Every size is printed.
"""
from __future__ import annotations

import argparse
import io
import re
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from learn import make_data  # noqa: E402  (the learning benchmark's data set)

from dofsynth.train import checkpoint  # noqa: E402
from dofsynth.train.config import load, replace  # noqa: E402
from dofsynth.train.evaluate import evaluate_depth  # noqa: E402
from dofsynth.train.loop import train  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "recipes" / "train-depth-learn.toml"
MATTES = ROOT.parent / "shared" / "assets"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default=str(ROOT / "out" / "learn-bench"))
    args = ap.parse_args()
    out = Path(args.out)
    torch.set_num_threads(2)
    data = make_data(out)
    base = load(CONFIG)
    runs = {"shards only": base, "shards only, colour jitter": replace(base, "depth", jitter=0.8)}
    if (MATTES / "alpha").is_dir():
        runs = {"shards + mattes": replace(base, "depth", mattes=str(MATTES)), **runs}
    else:
        print(f"no mattes at {MATTES}: the segmentation term uses the shards' coverage alone")
    print(f"network: {base.depth.backbone} width {base.depth.width}, decoder {base.depth.decoder_width}, "
          f"{sum(p.numel() for p in checkpoint.build_model(base).parameters()):,} parameters; crop "
          f"{base.data.crop} px, batch {base.data.batch_size}, {base.train.max_steps} steps")
    def scores(model, cfg) -> list[dict]:  # (validation, test) tables
        return [evaluate_depth(model, cfg, out, data, split=split, part=part, write=False)["table"]
                for split, part in (("train", "val"), ("test", "all"))]

    rows = []
    torch.manual_seed(base.train.seed)
    rows.append(("untrained", scores(checkpoint.build_model(base).eval(), base)))
    for name, cfg in runs.items():
        folder = out / "runs" / ("depth-" + re.sub(r"[^a-z0-9]+", "-", name))
        t0 = time.perf_counter()
        train(cfg, data, folder, device="cpu", out=io.StringIO())
        print(f"  trained {name!r} in {time.perf_counter() - t0:.0f} s (0 s: reused)", flush=True)
        rows.append((name, scores(*checkpoint.load_model(folder))))
    n_val, n_test = rows[0][1][0][0]["n"], rows[0][1][1][0]["n"]
    print(f"\nnormalized disparity MAE, raw / after the 5-knot spline fit; validation: {n_val} held-out "
          f"train scenes (training assets), test: {n_test} scenes of unseen assets\n")
    print("| | validation MAE | validation MAE, spline | test MAE | test MAE, spline |\n|---|---|---|---|---|")
    for name, (val, test) in rows:
        print(f"| {name} | {val[0]['mae']:.4f} | {val[0]['mae_spline']:.4f} | {test[0]['mae']:.4f} | {test[0]['mae_spline']:.4f} |")
    val, test = rows[0][1][0][1], rows[0][1][1][1]
    print(f"| constant (the best flat map: the median) | {val['mae']:.4f} | {val['mae_spline']:.4f} | {test['mae']:.4f} | {test['mae_spline']:.4f} |")


if __name__ == "__main__":
    main()
