"""The cost of one sample against the I/O floor, in CPU time, for one or more code trees side by side.

    .venv/bin/python benchmarks/per_sample.py                              # this tree, 24 samples per case
    git worktree add /tmp/base 583f735                                      # the code before a change
    .venv/bin/python benchmarks/per_sample.py --tree /tmp/base --tree .    # both, interleaved, one run
    .venv/bin/python benchmarks/per_sample.py --tree /tmp/base --tree . --method layered   # one method for all
    .venv/bin/python benchmarks/per_sample.py --tree /tmp/base --tree .:layered --tree .  # this tree twice

Each case renders the same samples of a recipe (each tree's own copy of it) at --size px (max CoC scaled from the recipe's
own size, so 32 px at 1024 px for recipes/deeplens-18k.toml): "built-in" is that recipe with
the built-in assets, "real" is recipes/shared-assets.toml on ../shared/assets (2 targets per
sample, the photos' estimated foregrounds cached on disk as in a second run). Every
(round, tree, case) runs in a fresh process with the tree first on sys.path, renders --warm
warm-up samples (4 by default, indices past the measured ones; the first reported apart as
`first`), then its share of the samples; the rounds
interleave trees and cases, so a slow spell of a shared machine hits them all.

Each process is set up as a generation worker is (`setup_process`: one OpenCV thread, the
workers' malloc settings, the compiled per-pixel passes of dofsynth.jit; BLAS and OpenMP
threads as this machine's environment sets them).
Per sample, in that process's own CPU time (`time.process_time`):
- `sample`: draw the scene, render, encode the members and write them as a one-sample shard
  (`render_one` and `write_shard`, what a worker does per sample);
- `floor`: what no renderer can avoid: decode the sample's asset files (built-in assets: their
  pixels as PNG files) and encode the same members again with that tree's own codecs and
  settings (the same bytes), then write the shard.
Columns: the mean over samples and its spread (standard deviation, min-max), the mean ratio
sample / floor, the first (warm-up) sample, and the process's own peak RSS (VmHWM).
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "assets"


def _recipe(case: str, size: int, samples: int, method: str = ""):
    """The case's recipe of the tree under test (the working folder: its own defaults, such as
    its render method, unless `method` names one), sized by benchmarks/generate.py's rules; its
    paths resolve here."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import generate as bench  # this tree's helpers; the recipe parser is the tree under test

    name = "deeplens-18k.toml" if case == "built-in" else "shared-assets.toml"
    text = (Path.cwd() / "recipes" / name).read_text(encoding="utf-8")
    recipe = bench.bench_recipe(text, size, samples) if case == "built-in" else bench.real_recipe(size, samples, text=text)
    return bench.with_method(recipe, method)


def _asset_bytes(library, record: dict) -> list[bytes]:
    """The encoded files of the sample's assets (built-in assets: their pixels as PNG)."""
    import cv2

    from dofsynth.assets import builtin as B

    out = []
    for ref in record["assets"].values():
        asset = library[ref["id"]]
        if asset.path.startswith("builtin:"):
            kind, name = asset.path.split(":", 1)[1].split("/", 1)
            pix = B.background_pixels(name) if kind == "bg" else np.dstack(B.foreground_pixels(name))
            out.append(cv2.imencode(".png", np.ascontiguousarray(pix[:, :, ::-1] if pix.shape[2] == 3 else pix))[1].tobytes())
        else:
            out += [Path(p).read_bytes() for p in (asset.path, getattr(asset, "alpha_path", None)) if p]
    return out


def _floor(library, key: str, members: dict[str, bytes], folder: Path) -> float:
    """CPU seconds to decode the sample's assets and encode and write its members again."""
    import cv2

    from dofsynth.codecs import decode_depth, encode_alphas, encode_depth, encode_png8
    from dofsynth.shards import write_shard

    record = json.loads(members["json"])
    files = _asset_bytes(library, record)
    png = {n: cv2.imdecode(np.frombuffer(b, np.uint8), cv2.IMREAD_UNCHANGED) for n, b in members.items() if n.endswith(".png")}
    exr = {n: decode_depth(b) for n, b in members.items() if n.endswith(".exr")}  # depth.exr alone here
    t = time.process_time()
    for data in files:
        cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    again = {}
    for name, arr in png.items():
        rgb = arr[:, :, ::-1]
        again[name] = encode_alphas(rgb[:, :, 0] / 255.0, rgb[:, :, 1] / 255.0) if name == "cover.png" else encode_png8(rgb)
    for name, arr in exr.items():
        again[name] = encode_depth(arr)
    again["json"] = members["json"]
    write_shard(folder / "floor.tar", [(key, again)])
    spent = time.process_time() - t
    if again.keys() != members.keys() or any(again[n] != members[n] for n in again):
        diff = [n for n in again if again.get(n) != members.get(n)]
        raise SystemExit(f"the floor's members are not the sample's bytes: {diff}")
    return spent


def child(case: str, size: int, total: int, indices: list[int], warm: list[int], method: str = "") -> dict:
    """One process's measurements (run with the tree under test first on sys.path): the samples
    `warm` first, unmeasured but the first of them (`first`), then `indices`."""
    from dofsynth.generate import render_one
    from dofsynth.generate.worker import library_for, setup_process
    from dofsynth.shards import write_shard

    setup_process()  # as in a generation worker: one OpenCV thread, malloc settings, compiled passes
    recipe = _recipe(case, size, total, method)
    library = library_for(recipe)
    out = {"sample": [], "floor": []}
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        for n, i in enumerate(warm):
            t = time.process_time()
            key, members = render_one(recipe, library, "train", i)
            write_shard(folder / "s.tar", [(key, members)])
            if n == 0:
                out["first"] = time.process_time() - t
        for i in indices:
            t = time.process_time()
            key, members = render_one(recipe, library, "train", i)
            write_shard(folder / "s.tar", [(key, members)])
            out["sample"].append(time.process_time() - t)
            out["floor"].append(_floor(library, key, members, folder))
    out["peak_mib"] = _own_peak_mib()
    return out


def _own_peak_mib() -> float:
    """This process's own peak RSS (VmHWM: ru_maxrss would carry over its parent's through fork
    and exec)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def _run_child(tree: Path, case: str, size: int, total: int, indices: list[int], warm: list[int], method: str = "") -> dict:
    code = ("import sys, json; sys.path.insert(0, sys.argv[1]); sys.path.insert(1, sys.argv[2]); "
            "import per_sample as p; print(json.dumps(p.child(sys.argv[3], int(sys.argv[4]), int(sys.argv[5]), "
            "json.loads(sys.argv[6]), json.loads(sys.argv[7]), sys.argv[8])))")
    # the environment a generation worker has: BLAS and OpenMP threads as the machine sets them
    # (this set OMP_NUM_THREADS=1 once, which hid what OpenBLAS threads spinning after each
    # product cost a worker: 0.08 CPU s a built-in sample before d8dbc2a)
    env = dict(os.environ)
    res = subprocess.run([sys.executable, "-c", code, str(tree), str(ROOT / "benchmarks"), case, str(size), str(total),
                          json.dumps(indices), json.dumps(warm), method], capture_output=True, text=True, env=env, cwd=tree)
    if res.returncode:
        raise SystemExit(f"{tree} {case}: the measuring process failed:\n{res.stderr[-3000:]}")
    return json.loads(res.stdout.strip().splitlines()[-1])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--tree", action="append",
                    help="a checkout of dofsynth to measure, DIR or DIR:METHOD (its samples rendered with METHOD); "
                         "repeat for side by side (default: this one)")
    ap.add_argument("--size", type=int, default=1024, help="frame size in px (default 1024)")
    ap.add_argument("--samples", type=int, default=24, help="samples per case and tree (default 24)")
    ap.add_argument("--rounds", type=int, default=3, help="processes per case and tree, interleaved (default 3)")
    ap.add_argument("--warm", type=int, default=4,
                    help="samples each process renders before it measures (default 4, at least 1: the first is reported "
                         "as `first`; indices past --samples): a "
                         "worker that has rendered a few has the CoC grid's kernels cached, as the marginal cost "
                         "of a sample in a long job assumes")
    ap.add_argument("--cases", nargs="+", default=["built-in", "real"], choices=["built-in", "real"])
    ap.add_argument("--method", default="", help="render every tree's samples with this method (default: each "
                    "tree's recipes' own)")
    args = ap.parse_args(argv)
    # (folder, method): "--tree DIR:METHOD" renders that tree's samples with METHOD
    trees = [(Path(t.split(":")[0]).resolve(), t.split(":")[1] if ":" in t else args.method)
             for t in (args.tree or [str(ROOT)])]
    cases = [c for c in args.cases if c != "real" or (SHARED / "SOURCES.md").is_file()]
    n_warm = max(args.warm, 1)  # (the first warm-up sample is reported as `first`)
    if len(cases) < len(args.cases):
        print(f"(no real-photo case: {SHARED} is missing)")
    print(f"cores: {os.cpu_count()}, load average: {' '.join(f'{x:.1f}' for x in os.getloadavg())}; "
          f"{args.size} px, {args.samples} samples per case in {args.rounds} interleaved processes, each after "
          f"{n_warm} warm-up samples", flush=True)
    if "real" in cases:  # the estimated foregrounds on disk first, as in any run after the first
        _run_child(trees[-1][0], "real", args.size, args.samples, list(range(args.samples)),
                   list(range(args.samples, args.samples + args.rounds * n_warm)), trees[-1][1])
    per = args.samples // args.rounds
    got = {(t, c): {"sample": [], "floor": [], "first": [], "peak_mib": 0.0} for t in trees for c in cases}
    for r in range(args.rounds):
        indices = list(range(r * per, (r + 1) * per if r < args.rounds - 1 else args.samples))
        warm = list(range(args.samples + r * n_warm, args.samples + (r + 1) * n_warm))  # past the measured ones
        for tree in trees:
            for case in cases:
                m = _run_child(tree[0], case, args.size, args.samples, indices, warm, tree[1])
                g = got[(tree, case)]
                g["sample"] += m["sample"]
                g["floor"] += m["floor"]
                g["first"].append(m["first"])
                g["peak_mib"] = max(g["peak_mib"], m["peak_mib"])
    print(f"{'tree':<28} {'case':<9} {'sample s':>9} {'sd':>6} {'min-max':>12} {'floor s':>8} {'ratio':>6} "
          f"{'first s':>8} {'peak MiB':>9} {'vs tree 1':>9}")
    for case in cases:
        base = statistics.fmean(got[(trees[0], case)]["sample"])
        for tree in trees:
            g = got[(tree, case)]
            s, f = g["sample"], g["floor"]
            mean, floor = statistics.fmean(s), statistics.fmean(f)
            name = str(tree[0])[-20:] + (f":{tree[1]}" if tree[1] else "")
            print(f"{name[-28:]:<28} {case:<9} {mean:>9.3f} {statistics.stdev(s):>6.3f} "
                  f"{min(s):>5.2f}-{max(s):<6.2f} {floor:>8.3f} {mean / floor:>6.2f} {statistics.fmean(g['first']):>8.2f} "
                  f"{g['peak_mib']:>9.0f} {mean / base:>9.2f}", flush=True)
    print("(CPU seconds per sample, mean over the samples; ratio: mean sample / mean floor; first: the first warm-up "
          "sample of each process; peak: the measuring process's own maximum RSS.)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
