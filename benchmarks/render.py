"""Benchmark of render_planes on one core: a three-plane 1024x1024 scene, max CoC 32 px; and,
with --generation, where one generated sample's time goes (scene, compose, highlight boost and
its inverse, render, encoding, tar write) at the sizes given, each stage without the stages it
calls.

Scene: an opaque background with a sloped disparity ramp (0.05 at the top to 0.35 at the
bottom), two soft-edged cutouts at disparity 0.5 and 0.85 (discs of radius 220 and 180 px with
a 4 px alpha ramp). Focus on each of the three depths in turn. Each render uses a focus jittered
by 1e-4 so no kernel comes from the cache (as in data generation, where every sample differs).
The naive baseline is a per-pixel gather in plain numpy (each output pixel sums its window times
the kernel of its own CoC), timed on six 32x32 crops spread over the scene and scaled by pixel count.

Run: `.venv/bin/python benchmarks/render.py [--size N] [--repeat K]`.
     `.venv/bin/python benchmarks/render.py --generation [--sizes 1024 4096] [--samples 8]
     [--method layered]`: recipes/deeplens-18k.toml with the built-in assets at each size (max
     CoC scaled; its own method unless --method names one), samples 0..N-1 after --warm warm-up
     samples (4) in a process set up as a generation worker, each stage timed by wrapping the
     function that does it: the kernels (their computation, or their cache's answer) and the
     kernels' spectra at each FFT's size apart from the rest of the render; medians and means
     over the samples, wall and CPU seconds.
     `.venv/bin/python benchmarks/render.py --levels`: the level-spacing error table.
     `.venv/bin/python benchmarks/render.py --methods`: the layered and sub-aperture modes
     against the exact mode (PSNR and time as a multiple of the layered one's, side by side)
     on 64 px scenes: soft discs over a flat background, over a steep ramp, and two
     overlapping out-of-focus foregrounds; max CoC 10 and 20 px, focus 0, 0.5, 1. Times are
     medians of 7 renders at the same focus (kernels cached: the renderers' own cost); with
     --cat-eye S the sub-aperture and exact modes vignette (--exact-samples N for a fine exact mode).
     `.venv/bin/python benchmarks/render.py --cat-eye-cost --sizes 256 512 1024`: CPU time of
     3 x 3 sub-aperture renders with cat-eye 0.5 and 1 against without it.
     `.venv/bin/python benchmarks/render.py --methods --real 4 --compare adaptive subaperture:2
     --reference-dir DIR`: the first 4 training scenes of recipes/shared-assets.toml at --size
     px, max CoC --max-coc, 4 focuses each, against the exact mode (kept in DIR: minutes each);
     PSNR of the render and of the target, CPU time against the layered method.
"""
from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMEXPR_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402
import scipy.fft  # noqa: E402

from dofsynth.optics import Disk, Polygon, kernel, support_radius  # noqa: E402
from dofsynth.render.planes import Plane  # noqa: E402
from dofsynth.render import render_planes  # noqa: E402

MAX_COC = 32.0


def scene(n: int, rng: np.random.Generator) -> list[Plane]:
    def texture():
        t = cv2.GaussianBlur(rng.random((n, n, 3), dtype=np.float32), (0, 0), 2.0)
        return np.clip((t - 0.5) * 4 + 0.5, 0, 1).astype(np.float32)

    yy, xx = np.mgrid[0:n, 0:n].astype(np.float32)
    ramp = (0.05 + 0.30 * yy / (n - 1)).astype(np.float32)
    bg = Plane(texture(), np.ones((n, n), np.float32), ramp)

    def cutout(cy, cx, r, d):
        a = np.clip((r - np.hypot(yy - cy * n, xx - cx * n)) / 4.0, 0, 1).astype(np.float32)
        return Plane(texture(), a, d)

    return [bg, cutout(0.35, 0.35, 0.215 * n, 0.5), cutout(0.65, 0.62, 0.176 * n, 0.85)]


def naive_gather(planes, focus, max_coc, aperture, y0, x0, size):
    """Per-pixel gather in plain numpy over a size x size crop; linear RGB (size, size, 3)."""
    acc = np.zeros((size, size, 4), np.float64)
    for i, p in enumerate(planes):
        pm = np.concatenate([p.rgb * p.alpha[:, :, None], p.alpha[:, :, None]], axis=2)
        dmap = p.disparity_map()
        s_max = support_radius(max_coc)
        pad = np.pad(pm, ((s_max, s_max), (s_max, s_max), (0, 0)), mode="edge" if i == 0 else "constant")
        out = np.zeros((size, size, 4))
        for y in range(y0, y0 + size):
            for x in range(x0, x0 + size):
                k = kernel(aperture, float(max_coc * (dmap[y, x] - focus)))
                s = k.shape[0] // 2
                win = pad[y + s_max - s : y + s_max + s + 1, x + s_max - s : x + s_max + s + 1]
                out[y - y0, x - x0] = np.tensordot(k[::-1, ::-1], win, axes=([0, 1], [0, 1]))
        acc = out + (1 - out[:, :, 3:4]) * acc
    return acc[:, :, :3]


def timed(fn, repeat):
    times = []
    for i in range(repeat):
        t = time.perf_counter()
        fn(i)
        times.append(time.perf_counter() - t)
    return statistics.median(times), times


# (stage, module whose name is wrapped, name): the names as the modules that call them see them
# (a stage's time excludes the stages timed inside it: "encode aif+dof" is the sRGB codes
# around "PNG deflate")
STAGES = (("scene", "dofsynth.generate.worker", "sample_scene"), ("compose", "dofsynth.sample", "scene_layers"),
          ("highlight boost, inverse", "dofsynth.render.look", "boost"),
          ("highlight boost, inverse", "dofsynth.render.look", "unboost"), ("render", "dofsynth.render.look", "render_planes"),
          ("encode aif+dof", "dofsynth.record", "encode_srgb_png_rows"),
          ("encode aif+dof", "dofsynth.record", "encode_srgb_png_planar"),  # dof.N.png (planar render)
          ("encode aif+dof", "dofsynth.record", "encode_png8"), ("PNG deflate", "dofsynth.codecs", "encode_png_rgb"),
          ("encode cover", "dofsynth.record", "encode_alphas"), ("encode depth", "dofsynth.record", "encode_depth"),
          ("kernels", "dofsynth.render.fft", "kernel"), ("kernels", "dofsynth.render.scatter", "kernel"),
          ("kernels", "dofsynth.render.scatter", "kernel_moments"), ("kernels", "dofsynth.render.cellblur", "kernel"),
          ("kernels", "dofsynth.render.cellblur", "kernel_moments"),
          ("kernel spectra", "dofsynth.render.fft", "_kernel_spectrum"),
          ("kernel spectra", "dofsynth.render.scatter", "line_spectrum"))


def generation_stages(sizes, samples: int, method: str = "", warm: int = 4) -> None:
    """Per-stage wall/CPU time of dofsynth.generate.worker.render_one plus the tar write, in a
    process set up as a generation worker, after `warm` samples (a worker in a long job has its
    CoC grid's kernels cached)."""
    import importlib
    import tempfile
    from pathlib import Path

    from dofsynth.generate.worker import library_for, render_one, setup_process
    from generate import bench_recipe, with_method  # this folder's generation benchmark: the same recipe
    from dofsynth.shards import write_shard

    acc: dict[str, list[float]] = {}
    active: list[str] = []  # the stages being timed, innermost last: a stage's time excludes its inner ones

    def wrap(stage, module, name):
        mod = importlib.import_module(module)
        fn = getattr(mod, name, None)
        if fn is None:
            raise SystemExit(f"benchmarks/render.py: {module}.{name} is gone; update STAGES")
        if getattr(fn, "_timed", False):
            return

        def timed_fn(*a, **k):
            t0, c0 = time.perf_counter(), time.process_time()
            active.append(stage)
            try:
                return fn(*a, **k)
            finally:
                active.pop()
                dw, dc = time.perf_counter() - t0, time.process_time() - c0
                w, c = acc.get(stage, (0.0, 0.0))
                acc[stage] = [w + dw, c + dc]
                if active:  # the outer stage did not spend this time itself
                    w, c = acc.get(active[-1], (0.0, 0.0))
                    acc[active[-1]] = [w - dw, c - dc]

        timed_fn._timed = True
        setattr(mod, name, timed_fn)

    setup_process()  # one OpenCV thread, the workers' malloc settings, the compiled passes
    for stage, module, name in STAGES:
        wrap(stage, module, name)
    root = Path(__file__).resolve().parents[1]
    base = (root / "recipes" / "deeplens-18k.toml").read_text(encoding="utf-8")
    import dofsynth

    print(f"dofsynth from {Path(dofsynth.__file__).parent}; load average {os.getloadavg()[0]:.2f}")
    for size in sizes:
        recipe = with_method(bench_recipe(base, size, samples + warm), method)
        library = library_for(recipe)
        for i in range(samples, samples + warm):  # warm-up (the CoC grid's kernels, FFT plans, memory)
            render_one(recipe, library, "train", i)
        rows = []
        with tempfile.TemporaryDirectory() as tmp:
            for i in range(samples):
                acc.clear()
                t0, c0 = time.perf_counter(), time.process_time()
                key, members = render_one(recipe, library, "train", i)
                t1, c1 = time.perf_counter(), time.process_time()
                write_shard(Path(tmp) / f"{i}.tar", [(key, members)])
                acc["tar write"] = [time.perf_counter() - t1, time.process_time() - c1]
                acc["total"] = [time.perf_counter() - t0, time.process_time() - c0]
                acc["MB / sample"] = [sum(map(len, members.values())) / 1e6] * 2
                rows.append(dict(acc))
        print(f"{size} px, {recipe.render.method}, {samples} samples   median: wall s   cpu s     mean: cpu s  share")
        names = list(dict.fromkeys([s for s, _, _ in STAGES] + ["tar write", "total", "MB / sample"]))
        total = statistics.fmean(r["total"][1] for r in rows)
        for stage in names:
            w = statistics.median(r.get(stage, (0.0, 0.0))[0] for r in rows)
            c = statistics.median(r.get(stage, (0.0, 0.0))[1] for r in rows)
            mean = statistics.fmean(r.get(stage, (0.0, 0.0))[1] for r in rows)
            share = f"{100 * mean / total:5.1f} %" if stage not in ("total", "MB / sample") else ""
            print(f"  {stage:24s} {w:19.4f} {c:8.4f} {mean:16.4f} {share}", flush=True)


def level_errors() -> None:
    """The level-spacing error table of docs/rendering.md: kodim01 (../shared/assets) and white
    noise, vertical ramp CoC -28.8 .. -12.8 px, against level_step=0.05 with fixed steps; and
    each setting's CPU time per render (median of 7, its kernels cached by a render before)."""
    from pathlib import Path

    from dofsynth.io import load_linear_rgba
    from dofsynth.render.levels import level_grid

    photo = Path(__file__).resolve().parents[2] / "shared" / "assets" / "bg" / "kodak_kodim01.png"
    img, _ = load_linear_rgba(photo)
    h, w = img.shape[:2]
    ramp = np.broadcast_to(np.linspace(0.1, 0.6, h, dtype=np.float32)[:, None], (h, w))
    noise = np.random.default_rng(0).random((h, w, 3), dtype=np.float32)
    print("| image | level_step | level_ratio | levels | max abs error | mean abs error | CPU s |")
    for name, im in (("kodim01", img), ("white noise", noise)):
        planes = [Plane(im, np.ones((h, w), np.float32), ramp)]
        ref = render_planes(planes, 1.0, 32.0, level_step=0.05, level_ratio=0.0)
        for step, ratio in ((1.0, 0.0), (0.5, 0.0), (0.25, 0.0), (0.5, 1 / 32), (0.5, 1 / 16)):
            e = np.abs(render_planes(planes, 1.0, 32.0, level_step=step, level_ratio=ratio) - ref)
            cpu = []
            for _ in range(7):
                t = time.process_time()
                render_planes(planes, 1.0, 32.0, level_step=step, level_ratio=ratio)
                cpu.append(time.process_time() - t)
            print(f"| {name} | {step} | {ratio:.4g} | {level_grid(-28.8, -12.8, step, ratio).size} "
                  f"| {e.max():.1e} | {e.mean():.1e} | {statistics.median(cpu):.3f} |", flush=True)


def method_scenes(n: int = 64) -> dict:
    """The small scenes of the method comparison: soft discs over a flat textured background,
    the same over a steep ramp, and two overlapping out-of-focus foregrounds."""
    rng = np.random.default_rng(7)
    bg = cv2.resize(rng.random((n // 4, n // 4, 3)).astype(np.float32), (n, n), interpolation=cv2.INTER_NEAREST)
    yy, xx = np.mgrid[0:n, 0:n]
    disc = lambda cy, cx, r: np.clip(r - np.hypot(yy - cy, xx - cx), 0, 1).astype(np.float32)  # noqa: E731
    colour = lambda c: np.zeros((n, n, 3), np.float32) + np.float32(c)  # noqa: E731
    one = np.ones((n, n), np.float32)
    ramp = np.broadcast_to(np.linspace(0.0, 0.45, n, dtype=np.float32)[:, None], (n, n))
    fg = [Plane(colour([0.9, 0.3, 0.1]), disc(n * 0.5, n * 0.4, n * 0.22), 0.7),
          Plane(colour([0.1, 0.8, 0.3]), disc(n * 0.6, n * 0.65, n * 0.14), 0.95)]
    return {"soft discs, flat background": [Plane(bg, one, 0.1)] + fg,
            "soft discs, steep ramp": [Plane(bg, one, ramp)] + fg,
            "two overlapping foregrounds": [Plane(bg, one, 0.0), Plane(colour([0.9, 0.9, 0.2]), disc(n * 0.5, n * 0.45, n * 0.3), 0.8),
                                            Plane(colour([0.2, 0.3, 0.9]), disc(n * 0.5, n * 0.6, n * 0.25), 1.0)]}


def method_table(cocs=(10.0, 20.0), focuses=(0.0, 0.5, 1.0), cells=(2, 3, 4), n: int = 64, cat_eye: float = 0.0,
                 samples: int | None = None) -> None:
    """PSNR (dB) of the layered and sub-aperture modes against the exact mode (`samples`
    aperture points, None: its default), and their time as a multiple of the layered method's,
    side by side, on `method_scenes(n)`; with `cat_eye` the sub-aperture and exact modes
    vignette with that strength (the layered column is then its unvignetted render, for scale)."""
    def psnr(a, b):
        return 10 * np.log10(1.0 / max(float(np.mean((a - b) ** 2)), 1e-20))

    head = " | ".join(["layered"] + [f"{c}x{c} cells (time)" for c in cells])
    print(f"| scene | max CoC | focus | {head} | exact time |\n|" + "---|" * (5 + len(cells)))
    eye = {"cat_eye": cat_eye} if cat_eye else {}
    for name, planes in method_scenes(n).items():
        for coc in cocs:
            for focus in focuses:
                t0 = time.perf_counter()
                exact = render_planes(planes, focus, coc, Disk(), method="exact", samples=samples, **eye)
                te = time.perf_counter() - t0
                tl, _ = timed(lambda i: render_planes(planes, focus, coc, Disk()), 7)
                row = [f"{psnr(render_planes(planes, focus, coc, Disk()), exact):.1f}"]
                for c in cells:
                    ts, _ = timed(lambda i: render_planes(planes, focus, coc, Disk(), method="subaperture", cells=c, **eye), 7)
                    sub = render_planes(planes, focus, coc, Disk(), method="subaperture", cells=c, **eye)
                    row.append(f"{psnr(sub, exact):.1f} ({ts / tl:.1f}x)")
                print(f"| {name} | {coc:g} | {focus:g} | " + " | ".join(row) + f" | {te / tl:.0f}x |", flush=True)


def real_scenes(size: int = 1024, count: int = 3, coc: float = 32.0):
    """Train scenes 0..count-1 of recipes/shared-assets.toml (the real photos and mattes of
    ../shared/assets) at `size` px, every target at max CoC `coc`: {name: (planes prepared for
    the blur, on their canvas; margin px; focuses; the recipe's Look)}. The focuses: on the
    background (its mean disparity), the middle plane, halfway to the front plane, and the
    front plane."""
    import re
    from pathlib import Path

    from generate import ROOT, _at_size
    from dofsynth.generate.worker import library_for, sample_scene
    from dofsynth.sample import SampleRender

    text = (ROOT / "recipes" / "shared-assets.toml").read_text(encoding="utf-8")
    at512 = coc * 512 / size
    text = re.sub(r"(?m)^max_coc = .*$", f"max_coc = [{at512}, {at512}]", text)
    recipe = _at_size(text, "methods-real", size, count, 1, 512, 2.0)
    library = library_for(recipe)
    out = {}
    for i in range(count):
        scene = sample_scene(recipe, library, "train", i)
        s = SampleRender(scene, library)
        planes = s._prepared()
        f0, f1 = planes[2].constant_disparity(), planes[1].constant_disparity()
        back = float(np.mean(np.asarray(planes[0].disparity, np.float32)))
        kind = "flat" if planes[0].constant_disparity() is not None else "ramp"
        name = f"{scene.key} ({kind} background; " + ", ".join(Path(a.path).stem for a in scene.assets.values()) + ")"
        out[name] = (planes, s._layers.margin, (round(back, 3), round(f1, 3), round((f0 + f1) / 2, 3), round(f0, 3)),
                     scene.options.look)
    return out


def reference_path(reference_dir, planes, scene: str, size: int, coc: float, focus: float):
    """Where `real_method_table` keeps an exact render (None without a folder): named by the
    exact mode's renderer id, the scene, size, max CoC, focus and a digest of the planes'
    contents (a change in how assets load, a matte or a crop, makes a new reference)."""
    import hashlib
    from pathlib import Path

    from dofsynth.render import METHODS

    if not reference_dir:
        return None
    digest = hashlib.sha1()
    for p in planes:
        for a in (p.rgb, p.alpha, p.disparity):
            digest.update(np.ascontiguousarray(np.asarray(a, np.float32)).tobytes())
    key = f"exact-{METHODS['exact'].renderer_id}-{scene.split()[0]}-{size}-{coc:g}-{focus:.4f}-{digest.hexdigest()[:12]}.npy"
    return Path(reference_dir) / key


def real_method_table(size: int, count: int, coc: float, methods, repeat: int = 5, reference_dir=None) -> None:
    """PSNR (dB, over the frame) of `methods` (names of METHODS, or "subaperture:N" for N x N
    cells) against the exact mode on `real_scenes`: of the render (linear light, highlights
    boosted) and of the target made from it (the boost's inverse, clipped to [0, 1]: what a
    sample holds). Their CPU time as a multiple of the layered method's: medians of `repeat`
    renders, interleaved, each with its own focus jitter (1e-4 steps) so no kernel comes from
    the cache (as in generation); the spread (min-max) beside it. Exact renders are kept in
    `reference_dir` when given (they take minutes each)."""

    from dofsynth.render import METHODS
    from dofsynth.render.look import restore

    def psnr(a, b):
        return 10 * np.log10(1.0 / max(float(np.mean((a - b) ** 2)), 1e-20))

    def target(img, look):
        return np.clip(restore(img.copy(), look), 0.0, 1.0)

    def render(planes, m, focus, name):
        kw = {}
        if name.startswith("subaperture:"):
            name, kw = "subaperture", {"cells": int(name.split(":")[1])}
        if "margin" in METHODS[name].options:
            kw["margin"] = m
        return render_planes(planes, focus, coc, Disk(), method=name, planar=True, **kw)

    names = ["layered"] + [m for m in methods if m != "layered"]
    print(f"{size} px scenes of recipes/shared-assets.toml, max CoC {coc:g} px; times: CPU s, median of {repeat} "
          "(min-max), interleaved, kernels not cached")
    print("| scene | focus | " + " | ".join(f"{n} dB (render / target)" for n in names) + " | layered s | "
          + " | ".join(f"{n} / layered" for n in names[1:]) + " |\n|" + "---|" * (3 + 2 * len(names) - 1))
    totals = {n: 0.0 for n in names}  # the medians added over the rows
    for scene, (planes, m, focuses, look) in real_scenes(size, count, coc).items():
        H, W = planes[0].shape
        frame = (slice(None), slice(m, H - m), slice(m, W - m))
        for focus in focuses:
            ref = None
            path = reference_path(reference_dir, planes, scene, size, coc, focus)
            if path is not None and path.exists():
                ref = np.load(path)
            if ref is None:
                ref = render(planes, m, focus, "exact")[frame]
                if path is not None:
                    path.parent.mkdir(parents=True, exist_ok=True)
                    np.save(path, ref)
            quality = []
            for n in names:
                img = render(planes, m, focus, n)[frame]
                quality.append(f"{psnr(img, ref):.1f} / {psnr(target(img, look), target(ref, look)):.1f}")
            times = {n: [] for n in names}
            sign = 1 if focus < 0.5 else -1  # (a focus stays in [0, 1])
            for i in range(repeat):
                for k, n in enumerate(names):
                    t = time.process_time()
                    render(planes, m, focus + sign * 1e-4 * (i * len(names) + k + 1), n)
                    times[n].append(time.process_time() - t)
            lay = statistics.median(times["layered"])
            for n in names:
                totals[n] += statistics.median(times[n])
            ratios = []
            for n in names[1:]:
                r = [a / b for a, b in zip(times[n], times["layered"])]
                ratios.append(f"{statistics.median(r):.2f}x ({min(r):.2f}-{max(r):.2f})")
            print(f"| {scene} | {focus:g} | " + " | ".join(quality)
                  + f" | {lay:.2f} ({min(times['layered']):.2f}-{max(times['layered']):.2f}) | " + " | ".join(ratios) + " |",
                  flush=True)
    print("all rows: " + ", ".join(f"{n} {totals[n]:.2f} s ({totals[n] / totals['layered']:.2f}x)" for n in names))


def cat_eye_cost(sizes=(256, 512, 1024), strengths=(0.5, 1.0), repeat: int = 3) -> None:
    """CPU seconds of the sub-aperture mode (3 x 3 cells) with cat-eye, against the same
    without it and the layered method, on `scene(n)` (max CoC 32 px at 1024, scaled with the
    size), focus 0.5; medians of `repeat` renders, kernels not cached (jittered focus)."""
    print("| size | max CoC | layered | 3x3 cells | 3x3 + cat-eye " + " | 3x3 + cat-eye ".join(f"{s:g}" for s in strengths)
          + " |\n|" + "---|" * (4 + len(strengths)))
    for n in sizes:
        planes = scene(n, np.random.default_rng(np.random.SeedSequence(2024)))
        coc = MAX_COC * n / 1024

        def cpu(**kw):
            times = []
            for i in range(repeat):
                t = time.process_time()
                render_planes(planes, 0.5 + 1e-4 * (i + 1), coc, Disk(), **kw)
                times.append(time.process_time() - t)
            return statistics.median(times)

        row = [cpu(), cpu(method="subaperture", cells=3)] + [cpu(method="subaperture", cells=3, cat_eye=s) for s in strengths]
        print(f"| {n} px | {coc:g} px | " + " | ".join(f"{v:.2f} s" for v in row) + " |", flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=1024)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--generation", action="store_true", help="per-stage time of generated samples instead")
    ap.add_argument("--sizes", type=int, nargs="+", default=[1024], help="with --generation or --cat-eye-cost")
    ap.add_argument("--samples", type=int, default=8, help="with --generation or --cat-eye-cost")
    ap.add_argument("--method", default="", help="with --generation: render with this method (default: the recipe's)")
    ap.add_argument("--warm", type=int, default=4, help="with --generation: warm-up samples before measuring (default 4, at least 1)")
    ap.add_argument("--levels", action="store_true", help="the level-spacing error table instead")
    ap.add_argument("--methods", action="store_true",
                    help="layered and sub-aperture against the exact mode (PSNR, time) on small scenes instead")
    ap.add_argument("--cat-eye", type=float, default=0.0, help="with --methods: vignetting strength (0..1)")
    ap.add_argument("--exact-samples", type=int, default=None,
                    help="with --methods: the exact mode's aperture points (its cat's-eye edges are quantized to them)")
    ap.add_argument("--cat-eye-cost", action="store_true",
                    help="CPU time of 3x3 sub-aperture renders with cat-eye against without it, at --sizes")
    ap.add_argument("--method-size", type=int, default=64, help="with --methods: the scenes' size in px")
    ap.add_argument("--cocs", type=float, nargs="+", default=[10.0, 20.0], help="with --methods: max CoC values")
    ap.add_argument("--focuses", type=float, nargs="+", default=[0.0, 0.5, 1.0], help="with --methods: focus values")
    ap.add_argument("--cells", type=int, nargs="+", default=[2, 3, 4], help="with --methods: cells per side")
    ap.add_argument("--real", type=int, default=0, metavar="N",
                    help="with --methods: N scenes of recipes/shared-assets.toml at --size px, max CoC --max-coc, "
                         "each at 4 focuses, instead of the small synthetic scenes")
    ap.add_argument("--max-coc", type=float, default=MAX_COC, help="with --methods --real: max CoC (px at --size)")
    ap.add_argument("--compare", nargs="+", default=["adaptive"],
                    help="with --methods --real: methods beside layered (a METHODS name or subaperture:N)")
    ap.add_argument("--reference-dir", default=None,
                    help="with --methods --real: a folder to keep the exact renders in (minutes each) and reuse them from")
    args = ap.parse_args()
    cv2.setNumThreads(1)
    if args.levels:
        level_errors()
        return
    if args.methods and args.real:
        with scipy.fft.set_workers(1):
            real_method_table(args.size, args.real, args.max_coc, args.compare, args.repeat, args.reference_dir)
        return
    if args.methods:
        with scipy.fft.set_workers(1):
            method_table(tuple(args.cocs), tuple(args.focuses), tuple(args.cells), args.method_size, args.cat_eye,
                         args.exact_samples)
        return
    if args.cat_eye_cost:
        with scipy.fft.set_workers(1):
            cat_eye_cost(tuple(args.sizes), repeat=min(args.repeat, 3))
        return
    if args.generation:
        with scipy.fft.set_workers(1):
            generation_stages(args.sizes, args.samples, args.method, max(args.warm, 1))
        return
    n = args.size
    planes = scene(n, np.random.default_rng(np.random.SeedSequence(2024)))
    print(f"render_planes, {n}x{n}, 3 planes (sloped background ramp + 2 soft cutouts), max_coc {MAX_COC}")
    print("one core: OMP/MKL/OPENBLAS threads 1, cv2.setNumThreads(1), scipy.fft workers 1")
    render_planes(planes, 0.5, MAX_COC)  # warm-up: imports, FFT plans
    results = {}
    for name, focus, aperture in (
        ("focus on middle cutout (0.5)", 0.5, Disk()),
        ("focus on front cutout (0.85)", 0.85, Disk()),
        ("focus on background top (0.05)", 0.05, Disk()),
        ("focus 0.5, hexagon aperture", 0.5, Polygon(6, 15.0)),
    ):
        with scipy.fft.set_workers(1):
            med, times = timed(lambda i: render_planes(planes, focus + 1e-4 * (i + 1), MAX_COC, aperture), args.repeat)
        results[name] = med
        print(f"  {name:34s} {med:6.3f} s/render (median of {args.repeat}; all: "
              + ", ".join(f"{t:.3f}" for t in times) + ")")
    with scipy.fft.set_workers(1):
        warm, _ = timed(lambda i: render_planes(planes, 0.5, MAX_COC), args.repeat)
    print(f"  {'same scene again (kernels cached)':34s} {warm:6.3f} s/render")
    crop = 32
    corners = [(int(fy * n) - crop // 2, int(fx * n) - crop // 2) for fy in (0.25, 0.5, 0.75) for fx in (0.25, 0.75)]
    t = time.perf_counter()
    for y0, x0 in corners:
        naive_gather(planes, 0.5, MAX_COC, Disk(), y0, x0, crop)
    naive_crop = time.perf_counter() - t
    naive_full = naive_crop * (n * n) / (len(corners) * crop * crop)
    ref = render_planes(planes, 0.5, MAX_COC)
    print(f"naive per-pixel numpy gather: {naive_crop:.2f} s on {len(corners)} crops of {crop}x{crop} spread "
          f"over the scene -> {naive_full:.0f} s for {n}x{n} (scaled by pixel count, not run in full)")
    med = results["focus on middle cutout (0.5)"]
    print(f"speed-up over the naive gather (focus 0.5): {naive_full / med:.0f}x")
    gathered = naive_gather(planes, 0.5, MAX_COC, Disk(), 0, n // 2 - 8, 16)
    diff = np.abs(gathered - ref[:16, n // 2 - 8 : n // 2 + 8]).max()
    print(f"(sanity: gather vs render on a 16x16 crop of the ramp, max |diff| = {diff:.4f}; "
          "they differ by design where the CoC varies: gather vs normalized scatter)")


if __name__ == "__main__":
    main()
