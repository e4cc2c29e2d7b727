"""Benchmark `dofsynth generate` at large sizes: time per sample, peak memory per worker, and the
speed-up from 1 to 2 local workers, all in one run.

    .venv/bin/python benchmarks/generate.py                       # 1024, 2048, 4096 px: about 3 minutes
    .venv/bin/python benchmarks/generate.py --sizes 1024 --samples 4 --scaling 0:0
    .venv/bin/python benchmarks/generate.py --sizes 512 1024 --floor   # plus the I/O floor

The built-in case is recipes/deeplens-18k.toml (1 target per scene, max CoC 32 px at 1024 px)
with the built-in assets, its size set to each --sizes value and max CoC scaled with it, the
same --samples samples at every size, one sample per shard (so both workers of a 2-worker run
have work). The real-photo case is recipes/shared-assets.toml (2 targets, the photos, mattes
and estimated foregrounds of ../shared/assets) at --real-sizes, with the per-worker asset cache
("real") and without it ("real, no cache": every sample decodes its photos, as with a library
of thousands). Every run uses fresh spawn worker processes (also for 1 worker), so a worker's
peak memory belongs to that case alone. Columns:
- `s/sample`: time inside `generate_shard` per sample with 1 worker (scene, layers, render,
  encode, write): the steady-state cost per core, the mean of --repeat runs (the cases
  interleaved; `runs` gives their range); `ratio`: for the built-in case its ratio to the
  first size, beside `px ratio`, the ratio of pixel counts (target: time grows no faster than
  the pixels); for the real photos, the ratio to the built-in case at the same size.
- `peak MiB/worker`: largest own peak RSS (VmHWM, `dofsynth.generate.worker.peak_rss_mb`) measured inside a worker (1- and 2-worker runs), against
  the 1.5 GB (1536 MiB) target.
- `w=2 steady`: (s/sample per worker at w=1) / (s/sample per worker at w=2) * 2, the speed-up of
  2 workers without starting them (a few samples are too few to judge it end to end).
- `--scaling SIZE:SAMPLES` (default 1024:96, shards of 2): the 1 -> 2 worker speed-up end to
  end, over a run long enough that starting the workers (spawning, importing, taking this
  process's asset library: 0.5-0.9 s here, and about 0.6 s loading the compiled
  passes of dofsynth.jit) weighs little, as in a real job; it also prints that
  start-up (and the idle tail of the run).
- `--malloc default`: the workers keep glibc's own malloc settings (before/after comparisons of
  `dofsynth.generate.worker.setup_process`).
- `--floor`: the I/O floor, encoding the same decoded arrays to PNG/EXR/JSON and writing a tar.
On a machine whose cores are shared with other jobs the 2-worker numbers mostly show the load.
"""
from __future__ import annotations

import argparse
import contextlib
import dataclasses
import os
import re
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from dofsynth.generate import LocalExecutor, generate, render_one  # noqa: E402
from dofsynth.generate.worker import MALLOC_ENV, WORKER_MMAP_THRESHOLD, WORKER_TRIM_THRESHOLD, library_for  # noqa: E402
from dofsynth.assets.library import CACHE_ENV  # noqa: E402
from dofsynth.recipe import recipe_from_text  # noqa: E402

TARGET_MIB = 1536


def _at_size(text: str, name: str, size: int, samples: int, shard_size: int, coc_size: int, max_upscale: float):
    """A recipe's text at `size` px, `samples` train samples only, max CoC scaled from the
    recipe's own `coc_size` px, assets magnified up to `max_upscale` (a benchmark, not a data set)."""
    t = re.sub(r"(?m)^size = \d+", f"size = {size}", text)
    t = re.sub(r"(?m)^shard_size = \d+", f"shard_size = {shard_size}", t)
    t = re.sub(r"(?m)^samples = \{[^}]*\}", f"samples = {{ train = {samples}, test = 0 }}", t)
    t = re.sub(r"(?m)^max_upscale = .*$", "", t).replace("[assets]\n", f"[assets]\nmax_upscale = {max_upscale}\n", 1)
    t = re.sub(r"(?m)^max_coc = \[([\d.]+), ([\d.]+)\]",
               lambda m: f"max_coc = [{float(m.group(1)) * size / coc_size}, {float(m.group(2)) * size / coc_size}]", t)
    return recipe_from_text(t, f"{name}-{size}.toml", ROOT / "recipes")


def bench_recipe(base_text: str, size: int, samples: int, shard_size: int = 1):
    """The base recipe (max CoC given at 1024 px) at `size` px with built-in assets, `samples`
    train only. The built-in photos are small: magnified up to 64x at large sizes."""
    t = re.sub(r'(?m)^(backgrounds|foregrounds) = "[^"]*"', r'\1 = "builtin"', base_text)
    t = re.sub(r"(?m)^manifest = .*$", "", t)
    return _at_size(t, "bench", size, samples, shard_size, 1024, 64.0)


def real_recipe(size: int, samples: int, shard_size: int = 1, text: str | None = None):
    """recipes/shared-assets.toml (the real photos and mattes in ../shared/assets; max CoC given
    at 512 px) at `size` px, `samples` train only. Its Kodak backgrounds are 768x512, so they may
    be magnified up to 2x."""
    if text is None:  # (or that recipe's text from another tree: its paths resolve here)
        text = (ROOT / "recipes" / "shared-assets.toml").read_text(encoding="utf-8")
    return _at_size(text, "bench-real", size, samples, shard_size, 512, 2.0)


def with_method(recipe, method: str):
    """The recipe with its samples rendered by `method` (a METHODS name); its own when empty."""
    if not method:
        return recipe
    return dataclasses.replace(recipe, render=dataclasses.replace(recipe.render, method=method))


def io_floor(recipe, n: int, folder: Path) -> float:
    """Seconds per sample to encode the decoded arrays again and write them as one tar."""
    from dofsynth.io import encode_exr
    from dofsynth.codecs import encode_alphas, encode_png8
    from dofsynth.record import decode_sample, encode_record
    from dofsynth.shards import write_shard

    library = library_for(recipe)
    samples = [render_one(recipe, library, "train", i) for i in range(n)]
    decoded = [decode_sample(m, k) for k, m in samples]
    t0 = time.perf_counter()
    out = []
    for (key, _), d in zip(samples, decoded):
        members = {"aif.png": encode_png8(d["aif"]), "depth.exr": encode_exr(d["depth"]),
                   "cover.png": encode_alphas(d["cover"][..., 0], d["cover"][..., 1]), "json": encode_record(d["record"])}
        members.update({f"dof.{i}.png": encode_png8(img) for i, img in enumerate(d["dof"])})
        out.append((key, members))
    write_shard(folder / "floor.tar", out)
    return (time.perf_counter() - t0) / n


@contextlib.contextmanager
def _environ(env: dict):
    """`env` set in os.environ (which spawn workers inherit) for the block."""
    old = {k: os.environ.get(k) for k in env}
    os.environ.update(env)
    try:
        yield
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def run(recipe, out: Path, workers: int):
    """`generate` with `workers` fresh spawn workers (also for 1: peak memory per size)."""
    return generate(recipe, out, executor=LocalExecutor(workers, in_process=False), progress=False)


def _size_samples(text: str) -> tuple[int, int] | None:
    size, _, n = text.partition(":")
    try:
        size, n = int(size), int(n)
    except ValueError:
        raise argparse.ArgumentTypeError(f"want SIZE:SAMPLES, e.g. 1024:96, got {text!r}") from None
    return (size, n) if size > 0 and n > 0 else None


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--recipe", type=Path, default=ROOT / "recipes" / "deeplens-18k.toml")
    ap.add_argument("--sizes", type=int, nargs="+", default=[1024, 2048, 4096])
    ap.add_argument("--samples", type=int, default=4,
                    help="samples per run, the same ones at every size (default 4; even, so 2 workers share them)")
    ap.add_argument("--repeat", type=int, default=5,
                    help="1-worker runs per size, the sizes interleaved; s/sample is their mean, the range shown (default 5: "
                         "runs interleaved so a slow spell of a shared machine hits every case)")
    ap.add_argument("--real-sizes", type=int, nargs="*", default=[1024], metavar="SIZE",
                    help="sizes of the real-photo case, recipes/shared-assets.toml on ../shared/assets "
                         "(default 1024; none: skip it)")
    ap.add_argument("--floor", action="store_true", help="also measure the I/O floor (in this process)")
    ap.add_argument("--malloc", default=None, metavar="SETTING",
                    help="the workers' glibc malloc setting (DOFSYNTH_WORKER_MALLOC): 'default' = glibc's own, "
                         "'MMAP_MIB,TRIM_MIB'; unset = the worker settings of dofsynth.generate.worker")
    ap.add_argument("--scaling", type=_size_samples, default=(1024, 96), metavar="SIZE:SAMPLES",
                    help="the 1 -> 2 worker run: SAMPLES samples at SIZE px (default 1024:96, about 35 s: long "
                         "enough that starting the workers weighs little); 0:0 skips it")
    args = ap.parse_args(argv)
    if args.malloc is not None:
        os.environ[MALLOC_ENV] = args.malloc  # spawn workers inherit it
    setting = os.environ.get(MALLOC_ENV) or (f"{WORKER_MMAP_THRESHOLD >> 20},{WORKER_TRIM_THRESHOLD >> 20}"
                                             " (mmap threshold, trim threshold MiB)")
    base = args.recipe.read_text(encoding="utf-8")
    print(f"cores: {os.cpu_count()}, load average: {' '.join(f'{x:.1f}' for x in os.getloadavg())}, "
          f"worker malloc: {setting}")
    # (case, size, recipe, environment of its workers); real photos: warm per-worker asset cache,
    # and none (DOFSYNTH_ASSET_CACHE_MIB=0: every sample decodes, as with a library of thousands)
    cases = [("built-in", size, bench_recipe(base, size, args.samples), {}) for size in args.sizes]
    if not (ROOT.parent / "shared" / "assets" / "SOURCES.md").is_file():
        print(f"(no real-photo case: {ROOT.parent / 'shared' / 'assets'} is missing)")
    else:
        for size in args.real_sizes:
            real = real_recipe(size, args.samples)
            for sample in range(args.samples):  # the estimated foregrounds on disk, as in a second run
                render_one(real, library_for(real), "train", sample)
            cases += [("real", size, real, {}), ("real, no cache", size, real, {CACHE_ENV: "0"})]
    per: dict[int, list[float]] = {i: [] for i in range(len(cases))}
    peak: dict[int, float] = {i: 0.0 for i in range(len(cases))}
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(args.repeat):  # cases interleaved: a slow spell of the machine hits them all
            for i, (_, size, recipe, env) in enumerate(cases):
                with _environ(env):
                    res = run(recipe, Path(tmp) / f"w1-{i}-{r}", 1)
                per[i].append(res.seconds_per_sample_per_worker)
                peak[i] = max(peak[i], res.peak_rss_mb)
    first = args.sizes[0]
    print(f"{'case':<15} {'size':>5} {'n':>3} {'s/sample':>9} {'runs':>13} {'ratio':>6} {'px ratio':>8} "
          f"{'peak MiB/worker':>16} {'w=2 steady':>11}" + (f" {'floor s':>8}" if args.floor else ""), flush=True)
    builtin = {size: statistics.fmean(per[i]) for i, (case, size, _, _) in enumerate(cases) if case == "built-in"}
    for i, (case, size, recipe, env) in enumerate(cases):
        with tempfile.TemporaryDirectory() as tmp, _environ(env):
            w2 = run(recipe, Path(tmp) / "w2", 2)
            floor = io_floor(recipe, min(args.samples, 2), Path(tmp)) if args.floor else None
        med = statistics.fmean(per[i])
        ratio = med / builtin[first] if case == "built-in" else med / builtin.get(size, float("nan"))
        px = f"{(size / first) ** 2:8.2f}" if case == "built-in" else f"{'':8}"
        top = max(peak[i], w2.peak_rss_mb)
        flag = "" if top <= TARGET_MIB else " !"
        steady = 2 * med / w2.seconds_per_sample_per_worker
        spread = f"{min(per[i]):.3f}-{max(per[i]):.3f}"
        print(f"{case:<15} {size:>5} {args.samples:>3} {med:>9.3f} {spread:>13} {ratio:>6.2f} {px} {top:>14.0f}{flag:2s} "
              f"{steady:>11.2f}" + (f" {floor:>8.3f}" if floor is not None else ""), flush=True)
    print(f"(s/sample: mean over --repeat 1-worker runs of the wall time inside generate_shard; CPU time per sample "
          f"against the I/O floor: benchmarks/per_sample.py. ratio: built-in, to "
          f"{first} px (target: <= px ratio, time growing no faster than the pixel count); real, to built-in at "
          f"the same size. Peak target <= {TARGET_MIB} MiB per worker; '!' marks a case over it.)")
    if args.scaling:
        size, n = args.scaling
        recipe = bench_recipe(base, size, n, shard_size=2)
        with tempfile.TemporaryDirectory() as tmp:
            runs = {w: run(recipe, Path(tmp) / f"w{w}", w) for w in (1, 2)}
        speed = runs[2].samples_per_second / runs[1].samples_per_second
        steady = 2 * runs[1].seconds_per_sample_per_worker / runs[2].seconds_per_sample_per_worker
        start = " ".join(f"w={w} {r.seconds - r.shard_seconds / w:.1f} s" for w, r in runs.items())
        print(f"\n1 -> 2 local workers, {n} samples at {size} px (shards of 2), end to end: "
              f"w=1 {runs[1].samples_per_second:.2f} samples/s ({runs[1].seconds:.1f} s), "
              f"w=2 {runs[2].samples_per_second:.2f} samples/s ({runs[2].seconds:.1f} s): speed-up {speed:.2f} "
              f"(target >= 1.8); steady {steady:.2f}. Start-up and tail (wall - shard time / workers): {start}.",
              flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
