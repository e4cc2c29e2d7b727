"""What a rendering process does: keep the asset library of its recipe, render shards with the
pure `generate_shard`, and set itself up for that one job (`setup_process`).

`generate_shard(recipe, out, split, shard_index)`'s output depends on nothing but the recipe
(and the asset files it names), so sample i is the same bytes whatever the worker count, the
machine, the executor, the order shards finish in, or a resume.
"""
from __future__ import annotations

import json
import os
import resource
import sys
from pathlib import Path

from dofsynth import jit
from dofsynth.assets import AssetError, build_library
from dofsynth.generate.plan import shard_task
from dofsynth.manifest.usage import Usage
from dofsynth.rng import sample_key
from dofsynth.sample import render_sample
from dofsynth.scene import Scene, sample_scene
from dofsynth.shards import ShardInfo, ShardWriter, iter_members

_LIBRARY: dict = {"key": None, "library": None}


def library_for(recipe, library=None):
    """The asset library of `recipe`, built once per process and reused for every shard.
    `library`: one already built for this recipe, used unless this process has one (workers
    get their parent's: the asset folders are scanned and hashed once, not once per worker)."""
    key = (recipe.sha256, recipe.base_dir)  # the same text elsewhere names other files
    if _LIBRARY["key"] != key or _LIBRARY["library"] is None:
        _LIBRARY["library"], _LIBRARY["key"] = library if library is not None else build_library(recipe), key
    return _LIBRARY["library"]


def portable(recipe):
    """A function that writes the recipe's folder and its absolute asset folders in a text
    relative to the recipe's folder, so that manifests do not depend on where the recipe and
    its assets lie on this machine."""
    base = recipe.base_dir
    roots = {base} | {r for r in (recipe.assets.backgrounds, recipe.assets.foregrounds) if os.path.isabs(r)}
    subs = []
    for r in sorted(roots, key=len, reverse=True):  # longest first: an asset folder inside base
        rp = os.path.relpath(r, base)
        subs.append((r.rstrip(os.sep) + os.sep, "" if rp == "." else rp + os.sep))

    def rel(text: str) -> str:
        for a, b in subs:
            text = text.replace(a, b)
        return text

    return rel


def draw_and_render(recipe, library, split: str, index: int):
    """(scene, members, bad) of sample `index` of `split`: the scene sampled from its own seed
    and rendered. A file that fails to load under `on_bad_asset = "skip"` (found only now with
    `verify = "header"`) is left out and the scene drawn again from the same seed, so the
    sample depends on which files are bad, never on the order they were found in; `bad` maps
    each such asset's path to why (a warning names it too)."""
    bad: dict[str, str] = {}
    excluded: list[str] = []
    while True:
        scene = sample_scene(recipe, library, split, index, exclude=excluded)
        try:
            return scene, render_sample(scene, library), bad
        except AssetError as exc:
            if recipe.assets.on_bad_asset != "skip" or exc.asset_id is None or exc.asset_id in excluded:
                raise
            excluded.append(exc.asset_id)
            path = library[exc.asset_id].path
            if path not in _WARNED:
                _WARNED.add(path)
                print(f"dofsynth: warning: skipping asset {exc}", file=sys.stderr, flush=True)
            bad[path] = str(exc)


_WARNED: set[str] = set()  # assets this process has warned about


def render_one(recipe, library, split: str, index: int) -> tuple[str, dict[str, bytes]]:
    """(key, members) of sample `index` of `split` (`draw_and_render`)."""
    return sample_key(split, index), draw_and_render(recipe, library, split, index)[1]


def shard_usage(path, recipe, library) -> dict:
    """The Usage of a finished shard from its sample records (a kept shard whose usage was not
    recorded: made before a manifest was written, or by an older run of the same data set)."""
    usage, rel = Usage(), portable(recipe)
    for _, _, blob in iter_members(path, suffix="json"):
        scene = Scene.from_dict(json.loads(blob))
        bad = {library[i].path: library.failure(library[i]) or "failed to load" for i in scene.excluded}
        usage.add(scene, library, bad, rel)
    return usage.to_dict()


def generate_shard(recipe, out, split: str, shard_index: int, *, limit: int | None = None,
                   library=None, on_sample=None) -> ShardInfo:
    """Render shard `shard_index` of `split` to `OUT/<split>/<split>-NNNNNN.tar` (temp name,
    then rename) and return its ShardInfo (with the shard's Usage). The bytes depend only on
    the recipe (and its asset files), split, shard index and `limit` (which can shorten the
    last shard). `library` defaults to this process's cached one; `on_sample(1)` is called
    after each sample is written."""
    task = shard_task(recipe, split, shard_index, limit)
    library = library if library is not None else library_for(recipe)
    final = Path(out) / split / task.name
    usage, rel = Usage(), portable(recipe)
    with ShardWriter(final) as writer:
        for i in range(task.first_index, task.first_index + task.samples):
            scene, members, bad = draw_and_render(recipe, library, split, i)
            writer.write(sample_key(split, i), members)
            usage.add(scene, library, bad, rel)
            if on_sample is not None:
                on_sample(1)
    return ShardInfo(split=split, index=task.index, name=task.name, first_index=task.first_index,
                     samples=writer.samples, sha256=writer.sha256, bytes=writer.bytes, usage=usage.to_dict())


def peak_rss_mb() -> float:
    """This process's own peak resident memory in MiB: VmHWM of /proc/self/status on Linux
    (ru_maxrss there carries over the parent's peak through fork and exec, so a spawn worker of
    a large caller would report the caller's), else ru_maxrss."""
    try:
        with open("/proc/self/status", encoding="ascii") as f:
            for line in f:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024.0  # kB
    except (OSError, ValueError, IndexError):
        pass
    scale = 1024.0 * 1024.0 if sys.platform == "darwin" else 1024.0  # bytes on macOS, KiB elsewhere
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / scale


# glibc malloc settings of a rendering process (mallopt parameter numbers from malloc.h). By
# default glibc gives every block above a dynamic threshold (<= 32 MiB) its own mmap and hands
# freed heap tops above 2x that threshold back to the kernel, so each FFT tile, strip and frame
# of a sample comes back as fresh pages that are zeroed and faulted in again on first touch
# (0.1-0.45 s per 192 MiB at 4096 px on a VM). A worker does one thing, the same sample shape
# again and again: keeping blocks up to WORKER_MMAP_THRESHOLD (an RGB float32 frame at 4096
# px is 192 MiB) on the heap and up to WORKER_TRIM_THRESHOLD of free heap reuses those pages
# (docs/generate.md, "Speed"). Cutout frames, mostly zeros, are `compose.lazy_zeros` maps of
# their own, so calloc does not clear them in full on the heap.
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3
WORKER_MMAP_THRESHOLD = 256 << 20
WORKER_TRIM_THRESHOLD = 1024 << 20
MALLOC_ENV = "DOFSYNTH_WORKER_MALLOC"  # "default": leave glibc's settings; "MMAP_MIB,TRIM_MIB": these


def setup_process() -> None:
    """Set up this process for rendering shards and nothing else (a pool worker, a Ray task, or
    `generate --workers 1` itself): one OpenCV thread (one core per worker, no
    oversubscription), the malloc settings above (`keep_large_blocks`) and the compiled
    per-pixel passes (dofsynth.jit: about 0.6 CPU s once, 7-10 % less per sample). The bytes
    made do not depend on any of it."""
    import cv2

    cv2.setNumThreads(1)
    keep_large_blocks()
    jit.enable()


def keep_large_blocks() -> None:
    """On Linux with glibc, keep blocks up to WORKER_MMAP_THRESHOLD on the heap and up to
    WORKER_TRIM_THRESHOLD of free heap (above), unless DOFSYNTH_WORKER_MALLOC says otherwise
    ("default": glibc's own; "MMAP_MIB,TRIM_MIB"): for a process whose one job is rendering
    (generation workers, `dofsynth render`). Results do not depend on it."""
    setting = os.environ.get(MALLOC_ENV, "")
    if setting == "default" or not sys.platform.startswith("linux"):
        return
    import ctypes

    mmap_t, trim_t = WORKER_MMAP_THRESHOLD, WORKER_TRIM_THRESHOLD
    if setting:
        mmap_t, trim_t = (int(v) << 20 for v in setting.split(","))
    try:
        libc = ctypes.CDLL("libc.so.6")
    except OSError:  # not glibc (musl, ...): nothing to tune
        return
    libc.mallopt(_M_MMAP_THRESHOLD, mmap_t)
    libc.mallopt(_M_TRIM_THRESHOLD, trim_t)
