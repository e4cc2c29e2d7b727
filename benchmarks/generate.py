"""Benchmark `dofsynth generate`: samples/s at 512 and 1024 px with 1 and 2 workers, and the
time per sample against the I/O floor (encoding and writing the same files), in one run.

    .venv/bin/python benchmarks/generate.py                 # about 2-3 minutes on 2 cores
    .venv/bin/python benchmarks/generate.py --sizes 512 --samples 4

The recipe is recipes/deeplens-18k.toml (1 target per scene, max CoC 32 px at 1024 px) with the
built-in assets, its size set to each --sizes value and max CoC scaled with it. Numbers:
- `s/sample (1 proc)`: steady-state time of one sample in this process (scene, layers, render,
  encode), the library already built: seconds per sample per core.
- `floor`: encoding the same decoded arrays to PNG/EXR/JSON and writing them as a tar shard;
  `ratio` = s/sample / floor.
- `w=N samples/s`: end to end `generate(..., workers=N)` including the library build and, for
  N > 1, starting the spawn workers (2-3 s), so it understates the steady state for few samples;
  `s/sample/worker` beside it is the time inside `generate_shard` per sample, per worker (the
  steady-state cost per core when workers <= cores; it rises when the cores are shared).
- `peak MiB`: the largest worker's peak resident memory (ru_maxrss).
"""
from __future__ import annotations

import argparse
import re
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from dofsynth.config import recipe_from_text  # noqa: E402
from dofsynth.generate import _library_for, generate, render_one  # noqa: E402
from dofsynth.io import encode_exr  # noqa: E402
from dofsynth.record import decode_sample, encode_cover, encode_png8, encode_record  # noqa: E402
from dofsynth.shards import write_shard  # noqa: E402


def bench_recipe(base_text: str, size: int, samples: int, shard_size: int):
    """The base recipe at `size` px with built-in assets, max CoC scaled, `samples` train only."""
    t = base_text
    t = re.sub(r"(?m)^size = \d+", f"size = {size}", t)
    t = re.sub(r"(?m)^shard_size = \d+", f"shard_size = {shard_size}", t)
    t = re.sub(r"(?m)^samples = \{[^}]*\}", f"samples = {{ train = {samples}, test = 0 }}", t)
    t = re.sub(r'(?m)^(backgrounds|foregrounds) = "[^"]*"', r'\1 = "builtin"', t)
    t = re.sub(r"(?m)^manifest = .*$", "", t)

    def scale(m):
        lo, hi = (float(x) * size / 1024 for x in m.group(1, 2))
        return f"max_coc = [{lo}, {hi}]"

    t = re.sub(r"(?m)^max_coc = \[([\d.]+), ([\d.]+)\]", scale, t)
    return recipe_from_text(t, f"bench-{size}.toml", ROOT / "recipes")


def io_floor(samples: list[tuple[str, dict[str, bytes]]], folder: Path) -> float:
    """Seconds per sample to encode the decoded arrays again and write them as one tar."""
    decoded = [decode_sample(m, k) for k, m in samples]
    t0 = time.perf_counter()
    out = []
    for (key, _), d in zip(samples, decoded):
        members = {"aif.png": encode_png8(d["aif"]), "depth.exr": encode_exr(d["depth"]),
                   "cover.png": encode_cover(d["cover"]), "json": encode_record(d["record"])}
        members.update({f"dof.{i}.png": encode_png8(img) for i, img in enumerate(d["dof"])})
        out.append((key, members))
    write_shard(folder / "floor.tar", out)
    return (time.perf_counter() - t0) / len(samples)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--recipe", type=Path, default=ROOT / "recipes" / "deeplens-18k.toml")
    ap.add_argument("--sizes", type=int, nargs="+", default=[512, 1024])
    ap.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--samples", type=int, default=0, help="samples per measurement (default 8 at <= 512 px, else 6)")
    args = ap.parse_args(argv)
    base = args.recipe.read_text(encoding="utf-8")
    print(f"{'size':>5} {'s/sample (1 proc)':>18} {'floor s':>8} {'ratio':>6} "
          + " ".join(f"{'w=' + str(w) + ' samples/s':>15} {'s/sample/worker':>15}" for w in args.workers)
          + f" {'peak MiB':>9}")
    for size in args.sizes:
        n = args.samples or (8 if size <= 512 else 6)
        recipe = bench_recipe(base, size, n, max(1, n // max(args.workers)))
        library = _library_for(recipe)
        render_one(recipe, library, "train", 0)  # warm caches (kernels, FFT plans)
        t0 = time.perf_counter()
        samples = [render_one(recipe, library, "train", i) for i in range(n)]
        per_sample = (time.perf_counter() - t0) / n
        rates, peak = [], 0.0
        with tempfile.TemporaryDirectory() as tmp:
            floor = io_floor(samples, Path(tmp))
            for w in args.workers:
                res = generate(recipe, Path(tmp) / f"w{w}", workers=w, progress=False)
                rates.append((res.samples_per_second, res.seconds_per_sample_per_worker))
                peak = max(peak, res.peak_rss_mb)
        print(f"{size:>5} {per_sample:>18.3f} {floor:>8.3f} {per_sample / floor:>6.1f} "
              + " ".join(f"{r:>15.2f} {c:>15.3f}" for r, c in rates) + f" {peak:>9.0f}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
