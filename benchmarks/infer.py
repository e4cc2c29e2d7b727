"""`render --model` inference: CPU time, wall time and peak memory at 1024 and 2048 px, each size
in a fresh process (its own peak RSS), with the model as `dofsynth render --model` runs it
(`dofsynth.train.infer.for_inference`, bands of BAND_ROWS rows) and as trained (the plain
module, whole frames), and the largest difference between the two results.

    .venv/bin/python benchmarks/infer.py [--config recipes/train-deeplens.toml] [--threads 2]
    .venv/bin/python benchmarks/infer.py --config recipes/train-learn-real.toml [--gate] [--near-shift 10] [--gate-margin 10]   # the hybrid
    .venv/bin/python benchmarks/infer.py --run RUN --photo IMAGE --depth DEPTH [--focus 0.9] [--sizes 2048]    # a trained run

Random weights of the config's model (the paper's networks, or the hybrid: its classical render,
its U-Net at full resolution, with --gate the edge weight of `[model] gate = "edges"`, with
--near-shift its two more classical renders of `[model] near_shift`, with --gate-margin its gate
that much wider) (batch
normalisation given random statistics, so folding it is exercised); a random photo and a
portrait's disparity (`portrait_disparity`: a near subject in focus before a receding
background). Peak RSS is the process's own maximum (VmHWM), model, photo and result included.

With --run, a trained run (either kind) renders a real photo and its disparity map (normalized,
of the photo's aspect ratio: any file `dofsynth render --depth` reads; or a depth run's
estimate, made before the timing, its network then counted in the peak), both at each size's
long side, as `dofsynth render --model` runs it: a real depth map's soft edges cost the
hybrids' classical render more than the portrait's hard silhouette does.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


FOCUS = 0.9  # on the subject of `portrait_disparity`


def portrait_disparity(side: int):
    """A portrait's depth, (side, side) float32: the background a ramp from 0.05 (top) to 0.35
    (bottom), a near subject (an ellipse 0.44 x 0.7 of the frame, a bit below its centre) at
    0.9, in focus: a silhouette with the largest CoC step at its edge, as `render --model` meets
    in use (a plain ramp has no depth edge, so a gated hybrid would skip all its U-Net)."""
    import numpy as np

    yy, xx = (np.mgrid[0:side, 0:side] + 0.5) / side
    disparity = (0.05 + 0.3 * yy).astype(np.float32)
    disparity[((xx - 0.5) / 0.22) ** 2 + ((yy - 0.55) / 0.35) ** 2 <= 1.0] = 0.9
    return disparity


def _timed(model, cfg, image, disparity, focus: float) -> dict:
    """{"cpu", "wall", "peak_mib", "out"} of one render after a 64 px warm-up, in this process."""
    import time

    from dofsynth.generate.worker import peak_rss_mb
    from dofsynth.train import infer

    infer.render_with(model, cfg, image[:64, :64], disparity[:64, :64], focus)  # warm up
    t, wall = time.process_time(), time.perf_counter()
    out = infer.render_with(model, cfg, image, disparity, focus)
    return {"cpu": time.process_time() - t, "wall": time.perf_counter() - wall, "peak_mib": peak_rss_mb(), "out": out}


def measure_run(run: str, photo: str, depth: str, focus: float, side: int, threads: int) -> dict:
    """One render of a trained run on a real photo in this process, as `measure` (prepared)."""
    import cv2
    import numpy as np
    import torch

    from dofsynth.generate.worker import keep_large_blocks
    from dofsynth.io import load_linear_rgba, read_depth
    from dofsynth.train import infer
    from dofsynth.train.checkpoint import load_model

    torch.set_num_threads(threads)
    rgb, _ = load_linear_rgba(photo)
    h, w = rgb.shape[:2]
    size = (side, round(side * h / w)) if w >= h else (round(side * w / h), side)  # (width, height)
    rgb = cv2.resize(rgb, size, interpolation=cv2.INTER_AREA if max(h, w) > side else cv2.INTER_CUBIC).clip(0, None)
    if Path(depth).is_dir():  # a depth network's run: its estimate, as `render --model` makes it
        disparity = infer.predict_depth(depth, rgb)
    else:
        disparity = cv2.resize(np.asarray(read_depth(depth), np.float32), size, interpolation=cv2.INTER_LINEAR)
    model, cfg = load_model(run, "cpu")
    keep_large_blocks()
    model = infer.for_inference(model.eval())
    return {**_timed(model, cfg, rgb, disparity, focus), "kind": cfg.model.kind}


def measure(config: str, side: int, threads: int, prepared: bool, keys: dict | None = None) -> dict:
    """One render in this process: {"cpu", "wall", "peak_mib", "out"} (out: the result)."""

    import numpy as np
    import torch
    from torch import nn

    from dofsynth.train import infer
    from dofsynth.train.checkpoint import build_model
    from dofsynth.train.config import load, replace

    torch.set_num_threads(threads)
    cfg = load(config)
    if keys:  # [model] keys set on top of the config's
        cfg = replace(cfg, "model", **keys)
    if cfg.model.coc_ref <= 0 or cfg.infer.low_res_side <= 0:  # what training fills in from its data
        from dofsynth.recipe import load_recipe

        recipe = load_recipe(ROOT / "recipes" / "learn-real.toml")  # the data recipes/train-learn-real.toml trains on
        cfg = replace(cfg, "model", coc_ref=cfg.model.coc_ref or float(recipe.focus.max_coc[1]))
        cfg = replace(cfg, "infer", low_res_side=cfg.infer.low_res_side or recipe.size // 2 ** cfg.data.levels)
    torch.manual_seed(0)
    model = build_model(cfg).eval()
    if hasattr(model, "head"):  # the hybrid's last layer starts at 0: give its correction a value
        nn.init.uniform_(model.head.weight, -0.01, 0.01)
    for m in model.modules():
        if isinstance(m, nn.BatchNorm2d):
            m.running_mean.uniform_(-0.1, 0.1), m.running_var.uniform_(0.5, 1.5), m.weight.data.uniform_(0.8, 1.2)
    if prepared:  # as `dofsynth render --model` runs it: its malloc settings, the prepared model
        from dofsynth.generate.worker import keep_large_blocks

        keep_large_blocks()
        model = infer.for_inference(model)
    else:
        infer.BAND_ROWS = None  # the whole frame at every step
    rng = np.random.default_rng(0)
    image = rng.random((side, side, 3), dtype=np.float32)
    return _timed(model, cfg, image, portrait_disparity(side), FOCUS)


def _in_child(call: str, *args) -> dict:
    """`call` (Python using `b`, this module, and `argv`, the string args) in a fresh process: the
    dict it prints as JSON."""
    code = f"import sys, json, numpy as np; sys.path.insert(0, sys.argv[1]); import infer as b; argv = sys.argv[2:]; {call}"
    res = subprocess.run([sys.executable, "-c", code, str(ROOT / "benchmarks"), *map(str, args)], capture_output=True,
                         text=True, cwd=ROOT)
    if res.returncode:
        raise SystemExit(res.stderr[-3000:])
    return json.loads(res.stdout.strip().splitlines()[-1])


def _child(config: str, side: int, threads: int, prepared: bool, save: str, model: dict) -> dict:
    return _in_child("r = b.measure(argv[0], int(argv[1]), int(argv[2]), argv[3] == '1', json.loads(argv[5])); "
                     "np.save(argv[4], r.pop('out')); print(json.dumps(r))",
                     config, side, threads, "1" if prepared else "0", save, json.dumps(model))


def _child_run(run: str, photo: str, depth: str, focus: float, side: int, threads: int) -> dict:
    return _in_child("r = b.measure_run(*argv[:3], float(argv[3]), int(argv[4]), int(argv[5])); r.pop('out'); "
                     "print(json.dumps(r))", run, photo, depth, focus, side, threads)


def main(argv=None) -> int:
    import tempfile

    import numpy as np

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--config", default=str(ROOT / "recipes" / "train-deeplens.toml"))
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--sizes", type=int, nargs="+", default=[1024, 2048])
    ap.add_argument("--gate", action="store_true", help='the hybrid with [model] gate = "edges"')
    ap.add_argument("--near-shift", type=int, default=0, help="the hybrid with [model] near_shift = N (px)")
    ap.add_argument("--gate-margin", type=int, default=0, help="with --gate: [model] gate_margin = N (px)")
    ap.add_argument("--run", help="a trained run (either kind): render --photo with it, one fresh process a size")
    ap.add_argument("--photo", help="with --run: the photo (resized to each size's long side)")
    ap.add_argument("--depth", help="with --run: its normalized disparity (a file `dofsynth render --depth` reads, "
                    "such as a matte), or a depth network's run to estimate it")
    ap.add_argument("--focus", type=float, default=FOCUS, help=f"with --run: the focus disparity (default {FOCUS})")
    args = ap.parse_args(argv)
    if args.run:
        if not (args.photo and args.depth):
            ap.error("--run needs --photo and --depth")
        print("| size | run | CPU s | wall s | peak MiB |\n|---|---|---|---|---|")
        for side in args.sizes:
            r = _child_run(args.run, args.photo, args.depth, args.focus, side, args.threads)
            print(f"| {side} | {Path(args.run).name} ({r['kind']}) | {r['cpu']:.2f} | {r['wall']:.2f} | "
                  f"{r['peak_mib']:.0f} |", flush=True)
        print(f"({args.threads} threads; {args.photo}, {args.depth}, focus {args.focus}; CPU s: process time of "
              "one render after a 64 px warm-up; peak: the process's maximum RSS)")
        return 0
    model = {**({"gate": "edges"} if args.gate else {}), **({"near_shift": args.near_shift} if args.near_shift else {}),
             **({"gate_margin": args.gate_margin} if args.gate_margin else {})}
    print("| size | model | CPU s | wall s | peak MiB | max difference |\n|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        for side in args.sizes:
            rows = {}
            for prepared in (False, True):
                save = str(Path(tmp) / f"{side}-{int(prepared)}.npy")
                rows[prepared] = (_child(args.config, side, args.threads, prepared, save, model), np.load(save))
            diff = float(np.abs(rows[True][1] - rows[False][1]).max())
            for prepared, name in ((False, "as trained, whole frames"), (True, "render --model (for_inference, bands)")):
                r = rows[prepared][0]
                print(f"| {side} | {name} | {r['cpu']:.2f} | {r['wall']:.2f} | {r['peak_mib']:.0f} | "
                      f"{diff:.1e} |" if prepared else f"| {side} | {name} | {r['cpu']:.2f} | {r['wall']:.2f} | "
                      f"{r['peak_mib']:.0f} | |", flush=True)
    print(f"({args.threads} threads; CPU s: process time of one render; peak: the process's maximum RSS)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
