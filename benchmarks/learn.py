"""The learning benchmark: the DeepLens findings reproduced at a scale a 2-core CPU trains in
under an hour.

    .venv/bin/python benchmarks/learn.py [--out out/learn-bench] [--part all|networks|main]
    .venv/bin/python benchmarks/learn.py --part real [--seeds 3] [--limit N] [--only gated] [--depth predicted:RUN]
    .venv/bin/python benchmarks/learn.py --part real --errors benchmarks/depth-errors-real.toml --only "shifted 10 px, 1200"

1. Data: recipes/learn.toml (the demo recipe at 256 px, max CoC up to 8 px, built-in assets),
   2000 train + 100 test samples, generated into OUT/data (kept and reused when present).
2. Networks (--part networks): the shipped recipes/train-learn.toml, the paper's network, each
   option of the official DeepLens code switched on alone and all together, for half the
   steps; scored on the validation share (held out of train, the same inputs for all), never
   on the test split, which is what the shipped defaults were chosen by.
3. Main (--part main): recipes/train-learn.toml as shipped (c = 32), c = 8 and 16, and c = 32
   trained on clean depth; then one table on the test split, everyone given the same
   corrupted depth (the [augment] setting of recipes/train-learn.toml, drawn with the
   evaluation seed): the trained network, the classical renderer (one image, the options that
   made the targets), the all-in-focus input; PSNR, SSIM and PSNR in the band within max CoC
   of a depth edge; then the config's loss against it plus an L1 term. The validation PSNR
   curve of the main run is printed too.
4. Real photos (--part real, apart from all; issue #25): recipes/learn-real.toml (the real
   photos and mattes of ../shared/assets at 512x341 px, max CoC 12-24 px, train and test split
   by asset; 400 + 40 scenes, 2 targets each) into OUT/data-real; recipes/train-learn-real.toml
   (the hybrid model, 128 px crops, trained on the depth errors of `eval --depth realistic`),
   the paper's networks on the same data (c = 32, and the paper's ablations: c = 8 and 16, and
   trained on the clean depth), the hybrid in linear light ([data] color), the
   hybrid trained for 1200 steps instead of 400, and so trained with its correction gated to
   the band around the given depth's edges ([model] gate = "edges"), also for 2400 steps and
   with its U-Net one level deeper (kp_depth 4, 1200 steps), and given two more classical renders
   of the depth with its near regions grown and shrunk by 10 px ([model] near_shift = 10, 1200
   steps; also without the identity rule, by 30 px, and with its gate reaching 10 px further,
   [model] gate_margin = 10, also with an SSIM term, [loss] ssim = 1), each trained with --seeds
   seeds;
   one table on
   the test split, everyone given the same realistic depth: PSNR and SSIM overall, in the edge
   band, outside it and where no blur reaches (the target is the input), the mean of the seeds
   and their range (--depth: another disparity, e.g. predicted:RUN, a depth run's estimates;
   given one, also the gated hybrid trained with half its items given RUN's estimates of the
   train scenes, [augment] predicted_prob = 0.5; --errors FILE: the depth errors of FILE's
   [augment] table instead of realistic, trained on and given to everyone, e.g.
   benchmarks/depth-errors-real.toml, realistic with its pixel sizes tripled: disparity MAE
   0.11 on this test split against realistic's 0.092, inside the 0.10-0.20 of real estimators).
   About 2-4 minutes per run of 400 steps, 10-14 of 1200, 22 of 2400 (2 cores), 6 hours in all.
Every size (image, crops, low resolution, steps, batch, parameters) is printed. Runs go to
OUT/runs/<config hash>; a finished run is reused (delete it to train again).
"""
from __future__ import annotations

import argparse
import csv
import dataclasses
import hashlib
import io
import json
import time
from pathlib import Path

import torch

from dofsynth import progress
from dofsynth.generate import generate
from dofsynth.manifest import load_manifest
from dofsynth.recipe import load_recipe
from dofsynth.train.config import Config, load, replace
from dofsynth.train.evaluate import evaluate_run
from dofsynth.train.loop import train
from dofsynth.train import checkpoint
from dofsynth.train.checkpoint import build_model
from dofsynth.train.data import resolve

ROOT = Path(__file__).resolve().parents[1]
RECIPE = ROOT / "recipes" / "learn.toml"
CONFIG = ROOT / "recipes" / "train-learn.toml"

PAPER = {"features": "channel", "raw_feature": False, "kernel": "free", "norm": "none", "up_width": 16, "up_depth": 0}
NETWORKS = {  # [model] settings: the paper's network, then each official-code option alone, all of them
    "shipped (the default)": {},
    "paper": PAPER,
    "joint+raw features": {**PAPER, "features": "joint", "raw_feature": True},
    "blur kernels": {**PAPER, "kernel": "blur"},
    "batch norm": {**PAPER, "norm": "batch"},
    "large upsampler": {**PAPER, "up_width": 32, "up_depth": 3},
    "all official": {"features": "joint", "raw_feature": True, "kernel": "blur", "norm": "batch",
                     "up_width": 32, "up_depth": 3},
}


def make_data(out: Path, recipe: Path = RECIPE, name: str = "data") -> Path:
    data = out / name
    try:
        load_manifest(data)
        return data
    except FileNotFoundError:
        pass
    t0 = time.perf_counter()
    generate(load_recipe(recipe), data, workers=2, progress=False)
    print(f"generated {recipe.name} into {data} in {time.perf_counter() - t0:.0f} s")
    return data


def run_key(cfg) -> str:
    """The hash that names a run's folder: of the config's keys that differ from their defaults,
    so a key added later (at its default: the same training) keeps every earlier run."""
    default = Config().to_dict()
    changed = {t: {k: v for k, v in vals.items() if v != default[t][k]} for t, vals in cfg.to_dict().items()}
    return hashlib.sha256(json.dumps(changed, sort_keys=True, default=list).encode()).hexdigest()[:12]


def run(name: str, cfg, data: Path, out: Path) -> Path:
    """Train `cfg` into OUT/runs/<run_key> (reused when finished: the same config under two
    names trains once); returns the folder."""
    folder = out / "runs" / run_key(cfg)
    params = f"{sum(p.numel() for p in build_model(resolve(cfg, data)).parameters()):,} parameters"
    if (folder / "ckpt.pt").is_file() and checkpoint.load(folder / "ckpt.pt")["step"] >= cfg.train.max_steps:
        print(f"  {name!r}: {cfg.train.max_steps} steps, trained before ({params}; {folder})", flush=True)
        return folder
    t0 = time.perf_counter()
    log = io.StringIO()
    train(cfg, data, folder, device="cpu", out=log)
    print(f"  trained {name!r}: {cfg.train.max_steps} steps in {time.perf_counter() - t0:.0f} s ({params})", flush=True)
    return folder


def score(folder: Path, data: Path) -> dict:
    """The test table of a run, everyone given the corrupted depth of recipes/train-learn.toml."""
    return {r["method"]: r for r in evaluate_run(folder, data, depth=str(CONFIG), device="cpu")["table"]}


def row(name: str, r: dict, c: int | None = None) -> str:
    cs = f" {c:>4} |" if c is not None else ""
    return f"| {name:<26} |{cs} {r['psnr']:>6.2f} | {r['ssim']:.4f} | {r['psnr_edge']:>6.2f} |"


def channels(cfg) -> int:
    return cfg.model.feat_channels * len(cfg.model.feat_dilations) + int(cfg.model.raw_feature)


def last_val(folder: Path) -> dict:
    with open(folder / "log.csv") as fh:
        rows = [r for r in csv.DictReader(fh) if r["val_psnr"]]
    return {"val_psnr": float(rows[-1]["val_psnr"]), "val_loss": float(rows[-1]["val_loss"])}


def part_networks(base, data: Path, out: Path) -> None:
    steps = base.train.max_steps // 2
    print(f"\n## Network options ({steps} steps each; validation share, the training corruption)\n")
    lines = ["| network                    | parameters | val PSNR dB | val loss |", "|---|---|---|---|"]
    for name, kw in NETWORKS.items():
        cfg = replace(replace(base, "model", **kw), "train", max_steps=steps, checkpoint_interval=steps,
                      eval_interval=steps)
        v = last_val(run(f"net {name}", cfg, data, out))
        n = sum(p.numel() for p in build_model(cfg).parameters())
        lines.append(f"| {name:<26} | {n:>10,} | {v['val_psnr']:>11.2f} | {v['val_loss']:.4f} |")
    print("\n".join(lines), flush=True)


def part_main(base, data: Path, out: Path) -> None:
    print(f"\n## Main runs ({base.train.max_steps} steps each)\n")
    main_run = run("c=32 corrupted", base, data, out)
    table = score(main_run, data)
    print("\n### Test split, everyone given the same corrupted depth\n")
    print("| method                     | PSNR dB | SSIM | edge dB |\n|---|---|---|---|")
    for method in ("network", "classical", "all-in-focus"):
        print(row(method if method != "network" else f"network (c = {channels(base)})", table[method]))

    print("\n### Feature channels c (trained and tested on corrupted depth)\n")
    print("| run                        |    c | PSNR dB | SSIM | edge dB |\n|---|---|---|---|---|")
    for fc in (2, 4, 8):
        cfg = replace(base, "model", feat_channels=fc)
        folder = main_run if fc == base.model.feat_channels else run(f"c={channels(cfg)} corrupted", cfg, data, out)
        print(row(f"feat_channels {fc}", score(folder, data)["network"], channels(cfg)))

    print("\n### Trained on clean vs corrupted depth (tested on corrupted depth)\n")
    clean = run("c=32 clean", replace(base, "augment", enabled=False), data, out)
    print("| trained on                 | PSNR dB | SSIM | edge dB |\n|---|---|---|---|")
    print(row("corrupted depth", table["network"]))
    print(row("clean depth", score(clean, data)["network"]))

    loss, whose = {"j": ("J", "the paper's"), "weighted": ("weighted J", "the default")}[base.loss.kind]
    print(f"\n### The loss: {loss} ({whose}) vs the same plus an L1 term (loss.l1 = 1; tested on corrupted depth)\n")
    l1 = run("c=32 corrupted, + L1", replace(base, "loss", l1=1.0), data, out)
    print("| loss                       | PSNR dB | SSIM | edge dB |\n|---|---|---|---|")
    print(row(f"{loss} ({whose})", table["network"]))
    print(row(f"{loss} + L1", score(l1, data)["network"]))

    print("\n### Validation PSNR of the main run (held-out share of train)\n")
    with open(main_run / "log.csv") as fh:
        curve = [(r["step"], r["val_psnr"]) for r in csv.DictReader(fh) if r["val_psnr"]]
    print("  ".join(f"step {s}: {float(p):.2f} dB" for s, p in curve))


REAL_RECIPE = ROOT / "recipes" / "learn-real.toml"
REAL_CONFIG = ROOT / "recipes" / "train-learn-real.toml"
# the paper's two networks on the same data, at the size of recipes/train-learn.toml's
DEEPLENS = {"kind": "deeplens", "feat_channels": 8, "kp_width": 16, "kp_depth": 3,
            "up_width": 16}
LONG = 1200  # steps of the longer hybrid runs
LONGER = 2400  # steps of the longest gated one, and of the longest paper networks
PAPER_LR = 2e-3  # peak learning rate of the paper networks' longest runs
NEAR_SHIFT = 10  # px: [model] near_shift of the hybrid given grown and shrunk renders
WIDE_SHIFT = 30  # px: the same for errors three times as wide (benchmarks/depth-errors-real.toml)
# with --depth predicted:RUN, the share of training items given RUN's estimates (the rest: the realistic
# errors); RUN trained on these train scenes, so its estimates of them are better than of the test's
ESTIMATE_SHARE = 0.5
CLEAN_SHARE = 0.25  # [augment] clean_prob of the hybrid trained with a share of clean depth
METRICS = [("psnr", "PSNR"), ("ssim", "SSIM")]
REGION_NAMES = [("", "overall"), ("_edge", "edge band"), ("_out", "outside it"), ("_same", "target = input")]


def spread(values: list[float], digits: int) -> str:
    """The mean of the seeds' values and their range."""
    if len(values) == 1:
        return f"{values[0]:.{digits}f}"
    return f"{sum(values) / len(values):.{digits}f} ({min(values):.{digits}f}-{max(values):.{digits}f})"


def part_real(out: Path, seeds: list[int], limit: int | None, only: str = "", depth: str = "realistic",
              errors: Path | None = None) -> None:
    """The lens-blur benchmark of issue #25: recipes/learn-real.toml (real photos, split by
    asset, max CoC 12-24 px), the hybrid model and the paper's networks trained with each seed
    on realistic depth errors; everyone given the same realistic depth on the test split.
    `only`: just the models whose names hold it (with the classical and all-in-focus rows);
    `depth`: the disparity everyone is given (`dofsynth eval --depth`); `errors`: a TOML file
    whose [augment] table replaces the config's (the depth errors trained on)."""
    recipe, base = load_recipe(REAL_RECIPE), load(REAL_CONFIG)
    if errors is not None:
        base = replace(base, "augment", **dataclasses.asdict(load(errors).augment))
    data = make_data(out, REAL_RECIPE, "data-real")
    d = base.data
    h, w = recipe.frame
    print(f"\n## Real photos: {REAL_RECIPE.name}, {w}x{h} px, max CoC {recipe.focus.max_coc[0]:g}-"
          f"{recipe.focus.max_coc[1]:g} px, {recipe.samples.train} train ({d.val_share:.0%} held out for validation) + "
          f"{recipe.samples.test} test scenes x {recipe.focus.targets_per_scene} targets, split by asset")
    print(f"training: {REAL_CONFIG.name}, {d.crop} px crops, batch {d.batch_size}, {base.train.max_steps} steps, "
          f"lr {base.train.lr:g}, depth errors of {errors or '[augment] (= eval --depth realistic)'}, seeds {seeds}; "
          f"test: {'all' if limit is None else limit} scenes, depth {depth}, evaluation seed 12345")
    paper = replace(base, "model", **DEEPLENS)
    blur_started = replace(paper, "model", feat_init="blur")  # its features started as blurs, not at random
    disc_started = replace(blur_started, "model", kernel_prior="discs")  # and its kernels as disc blurs of s
    boosted = replace(disc_started, "model", light="boosted")  # and run in linear light, highlights boosted
    longest = dict(lr=PAPER_LR, min_lr=PAPER_LR / 10)
    gated = replace(base, "model", gate="edges")

    def steps(cfg, n: int):
        return replace(cfg, "train", max_steps=n, checkpoint_interval=n)

    kinds = {"hybrid": base, "deeplens (paper networks)": paper,
             # the paper's ablations of its networks: c = 8 and 16 feature channels (c = 32 above),
             # and trained on the clean depth (tested, as all, on the realistic errors)
             **{f"deeplens, c = {4 * fc}": replace(paper, "model", feat_channels=fc) for fc in (2, 4)},
             "deeplens, trained on clean depth": replace(paper, "augment", enabled=False),
             # its feature convolutions started as a cascade of box blurs ([model] feat_init)
             "deeplens, features started as blurs": blur_started,
             # the same six times as long, at the peak learning rate of recipes/train-learn.toml (2e-3)
             f"deeplens, features started as blurs, {LONGER} steps": steps(replace(blur_started, "train", **longest), LONGER),
             # and its kernel started as the disc blur of the given depth ([model] kernel_prior)
             "deeplens, kernels started as disc blurs": disc_started,
             f"deeplens, kernels started as disc blurs, {LONGER} steps": steps(replace(disc_started, "train", **longest), LONGER),
             # the same in the light the targets are blurred in ([model] light)
             "deeplens, in the targets' light": boosted,
             f"deeplens, in the targets' light, {LONGER} steps": steps(replace(boosted, "train", **longest), LONGER),
             "hybrid, color = linear": replace(base, "data", color="linear"),
             f"hybrid, {LONG} steps": steps(base, LONG),
             **{f"hybrid gated to the edge bands, {n} steps": steps(gated, n) for n in (LONG, LONGER)},
             # its U-Net one level deeper: twice the reach (an edge band is up to 2 x 24 px wide)
             f"hybrid gated, U-Net depth {base.model.kp_depth + 1}, {LONG} steps":
                 steps(replace(gated, "model", kp_depth=base.model.kp_depth + 1), LONG),
             # given two more renders, the given depth's near regions grown and shrunk by as much as
             # the realistic errors displace an edge ([augment] morph_kernel: up to 21 px wide)
             f"hybrid gated, near regions shifted {NEAR_SHIFT} px, {LONG} steps":
                 steps(replace(gated, "model", near_shift=NEAR_SHIFT), LONG),
             # shifted as far as benchmarks/depth-errors-real.toml displaces an edge (its
             # morph_kernel: up to 63 px wide)
             f"hybrid gated, near regions shifted {WIDE_SHIFT} px, {LONG} steps":
                 steps(replace(gated, "model", near_shift=WIDE_SHIFT), LONG),
             # and with its gate reaching as far past an edge's blur as the renders move the edge
             # ([model] gate_margin): a correction that picks a moved edge is not cut off there
             f"hybrid gated, near regions shifted {NEAR_SHIFT} px, gate {NEAR_SHIFT} px wider, {LONG} steps":
                 steps(replace(gated, "model", near_shift=NEAR_SHIFT, gate_margin=NEAR_SHIFT), LONG),
             # and with an SSIM term in its loss ([loss] ssim = 1): blending renders where it is unsure
             # gains PSNR outside the band but lowers local contrast there, which J barely sees
             f"hybrid gated, near regions shifted {NEAR_SHIFT} px, gate {NEAR_SHIFT} px wider, SSIM term, {LONG} steps":
                 steps(replace(replace(gated, "model", near_shift=NEAR_SHIFT, gate_margin=NEAR_SHIFT), "loss", ssim=1.0),
                       LONG),
             # and without the identity rule: where the given depth's CoC is under 0.5 px the
             # classical render's slight blur (a 0.4 px kernel keeps 69 % of a pixel) stays
             f"hybrid gated, near regions shifted {NEAR_SHIFT} px, identity off, {LONG} steps":
                 steps(replace(gated, "model", near_shift=NEAR_SHIFT, identity=False), LONG),
             # and trained with a share of its items given the clean depth ([augment] clean_prob):
             # always given wrong depth, it learns to distrust every edge, also one that is right
             f"hybrid gated, near regions shifted {NEAR_SHIFT} px, {CLEAN_SHARE:.0%} of the items clean, {LONG} steps":
                 steps(replace(replace(gated, "model", near_shift=NEAR_SHIFT), "augment", clean_prob=CLEAN_SHARE),
                       LONG)}
    if depth.startswith("predicted:"):  # given an estimator's depth: also trained on it, half of the items
        estimates = dict(predicted_prob=ESTIMATE_SHARE, predicted_run=str(Path(depth[len("predicted:"):]).resolve()))
        kinds[f"hybrid gated, trained on the estimates (half the items), {LONG} steps"] = steps(replace(
            gated, "augment", **estimates), LONG)
        kinds[f"deeplens, in the targets' light, trained on the estimates (half the items), {LONGER} steps"] = steps(
            replace(replace(boosted, "train", **longest), "augment", **estimates), LONGER)
    if only:
        kinds = {k: v for k, v in kinds.items() if only in k}
    tables: dict[str, list[dict]] = {}
    for name, cfg in kinds.items():
        for seed in seeds:
            folder = run(f"{name}, seed {seed}", replace(cfg, "train", seed=seed), data, out)
            t0 = time.perf_counter()
            result = evaluate_run(folder, data, depth=depth, limit=limit, device="cpu")
            table = {r["method"]: r for r in result["table"]}
            print(f"  evaluated in {time.perf_counter() - t0:.0f} s (the given disparity's MAE "
                  f"{result['depth_mae']:.3f})", flush=True)
            tables.setdefault(name, []).append(table["network"])
            for method in ("classical", "all-in-focus"):  # the same for every run: the same inputs
                tables.setdefault(method, [table[method]])
    header = "| method | " + " | ".join(f"{m} {r}" for r_, r in REGION_NAMES for _, m in METRICS) + " |"
    print(f"\n### Test split, everyone given the same depth ({depth}; mean of the seeds, range)\n")
    print(header + "\n|" + "---|" * (1 + len(REGION_NAMES) * len(METRICS)))
    for name, rows in tables.items():
        cells = []
        for r_, _ in REGION_NAMES:
            for m, _ in METRICS:
                vals = [row[f"{m}{r_}"] for row in rows if row.get(f"{m}{r_}") is not None]
                cells.append(spread(vals, 2 if m == "psnr" else 4) if vals else "-")
        print(f"| {name} | " + " | ".join(cells) + " |", flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=ROOT / "out" / "learn-bench")
    ap.add_argument("--part", choices=("all", "networks", "main", "real"), default="all",
                    help="real: the lens-blur benchmark on real photos (recipes/learn-real.toml), not part of all")
    ap.add_argument("--seeds", type=int, default=3, help="with --part real: training seeds per model (default 3)")
    ap.add_argument("--limit", type=int, default=None, help="with --part real: test scenes scored (default all)")
    ap.add_argument("--only", default="", help="with --part real: only the models whose names hold this text")
    ap.add_argument("--depth", default=None,
                    help="with --part real: the disparity everyone is given (dofsynth eval --depth; default "
                         "realistic, or the --errors file), e.g. predicted:RUN for a depth run's estimates")
    ap.add_argument("--errors", type=Path, default=None,
                    help="with --part real: a TOML file whose [augment] table is the depth errors the networks "
                         "train on and, unless --depth says otherwise, everyone is given (default the config's, "
                         "= realistic), e.g. benchmarks/depth-errors-real.toml")
    ap.add_argument("--threads", type=int, default=2, help="torch threads (default 2)")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    progress.set_verbosity(quiet=True)  # the training bars; this script prints its own lines
    if args.part == "real":
        depth = args.depth or (str(args.errors) if args.errors else "realistic")
        part_real(args.out, list(range(args.seeds)), args.limit, args.only, depth, args.errors)
        return
    recipe, base = load_recipe(RECIPE), load(CONFIG)
    data = make_data(args.out)
    d = base.data
    print(f"data: {RECIPE.name}, {recipe.size} px, max CoC {recipe.focus.max_coc[0]:g}-{recipe.focus.max_coc[1]:g} px, "
          f"{recipe.samples.train} train ({d.val_share:.0%} held out for validation) + {recipe.samples.test} test")
    print(f"training: {CONFIG.name}, {d.crop} px crops, lens blur at 1/{2 ** d.levels} ({d.crop >> d.levels} px "
          f"crops, {recipe.size >> d.levels} px whole images), batch {d.batch_size}, {base.train.max_steps} steps, "
          f"c = {channels(base)}, torch {torch.__version__}, {args.threads} threads")
    if args.part in ("all", "networks"):
        part_networks(base, data, args.out)
    if args.part in ("all", "main"):
        part_main(base, data, args.out)


if __name__ == "__main__":
    main()
