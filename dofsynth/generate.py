"""Make a data set: plan shards, render them (in worker processes), write the manifest last.

The plan: per split, shards of `recipe.shard_size` consecutive sample indices (the last may be
shorter); `limit` caps the samples of each split. A shard is made by the pure function
`generate_shard(recipe, out, split, shard_index)`, whose output depends on nothing but the
recipe (and the asset files it names), so sample i is the same bytes whatever the worker
count, the machine, the order shards finish in, or a resume. Any executor can call it; here
it runs in-process (`workers=1`) or in a `spawn` process pool, each worker building the asset
library once.

Safety of the output folder `OUT`:
- `OUT/.lock` (fcntl.flock, holder pid inside) refuses a second concurrent run into OUT.
- Without `resume`, an OUT holding anything is refused (never silently mixed).
- Shards appear under their final names only when complete; leftover temp files of a killed
  run are removed at the start; `OUT/.progress.jsonl` lists finished shards while running.
- With `resume`, shards already there are verified (sha256 against the progress file or old
  manifest, else their sample keys) and kept; the rest are made; a resumed data set is
  byte-identical to an uninterrupted one.
- `OUT/manifest.json` is written last, atomically; then the progress file is removed.
"""
from __future__ import annotations

import fcntl
import multiprocessing as mp
import os
import queue as queue_mod
import resource
import time
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from dataclasses import dataclass, field
from pathlib import Path

from dofsynth import __version__
from dofsynth.manifest import (MANIFEST_NAME, PROGRESS_NAME, append_progress, build_manifest, load_manifest,
                               manifest_shard_infos, read_progress, remove_progress, start_progress,
                               write_manifest)
from dofsynth.shards import (ShardError, ShardInfo, ShardWriter, remove_temp_files, sample_key, shard_keys,
                             shard_name, sha256_file)

SPLITS = ("train", "test")
LOCK_NAME = ".lock"


class OutputInUseError(ValueError):
    """Another run holds the output folder's lock."""


class OutputNotEmptyError(ValueError):
    """The output folder already holds files and `resume` was not asked for."""


class ResumeError(ValueError):
    """The output folder cannot be resumed with this recipe."""


# ---------------------------------------------------------------------------------- the plan
@dataclass(frozen=True)
class ShardTask:
    """One shard of the plan: samples first_index .. first_index + samples - 1 of `split`."""

    split: str
    index: int
    first_index: int
    samples: int

    @property
    def name(self) -> str:
        return shard_name(self.split, self.index)

    @property
    def path(self) -> str:
        return f"{self.split}/{self.name}"

    def keys(self) -> list[str]:
        return [sample_key(self.split, i) for i in range(self.first_index, self.first_index + self.samples)]


def split_size(recipe, split: str, limit: int | None = None) -> int:
    """Samples of `split` in the data set: the recipe's count, capped by `limit`."""
    if split not in SPLITS:
        raise ValueError(f"split {split!r}: expected one of {', '.join(SPLITS)}")
    n = int(recipe.samples.count(split))
    if limit is not None:
        if int(limit) != limit or limit < 0:
            raise ValueError(f"--limit must be an integer >= 0, got {limit}")
        n = min(n, int(limit))
    return n


def plan_split(recipe, split: str, limit: int | None = None) -> list[ShardTask]:
    n, size = split_size(recipe, split, limit), int(recipe.shard_size)
    return [ShardTask(split, k, first, min(size, n - first)) for k, first in enumerate(range(0, n, size))]


def plan_shards(recipe, splits=SPLITS, limit: int | None = None) -> list[ShardTask]:
    """Every shard of the requested splits, in split then shard order."""
    return [t for s in splits for t in plan_split(recipe, s, limit)]


def shard_task(recipe, split: str, shard_index: int, limit: int | None = None) -> ShardTask:
    tasks = plan_split(recipe, split, limit)
    if not 0 <= shard_index < len(tasks):
        raise ValueError(f"shard {shard_index} of split {split!r}: the plan has shards 0..{len(tasks) - 1}")
    return tasks[shard_index]


# ------------------------------------------------------------------------- making one shard
_WORKER: dict = {"sha": None, "library": None, "recipe": None, "queue": None}


def _library_for(recipe):
    """The asset library of `recipe`, built once per process and reused for every shard."""
    if _WORKER["sha"] != recipe.sha256 or _WORKER["library"] is None:
        from dofsynth.assets import build_library

        _WORKER["library"] = build_library(recipe)
        _WORKER["sha"] = recipe.sha256
    return _WORKER["library"]


def render_one(recipe, library, split: str, index: int) -> tuple[str, dict[str, bytes]]:
    """(key, members) of sample `index` of `split`: the scene sampled from its own seed."""
    from dofsynth.record import render_sample
    from dofsynth.scene import sample_scene

    scene = sample_scene(recipe, library, split, index)
    return sample_key(split, index), render_sample(scene, library, recipe)


def generate_shard(recipe, out, split: str, shard_index: int, *, limit: int | None = None,
                   library=None, on_sample=None) -> ShardInfo:
    """Render shard `shard_index` of `split` to `OUT/<split>/<split>-NNNNNN.tar` (temp name,
    then rename) and return its ShardInfo. Pure in the sense that matters: the bytes depend
    only on the recipe, split, shard index and `limit` (which can shorten the last shard).
    `library` defaults to this process's cached one; `on_sample(1)` is called per sample."""
    task = shard_task(recipe, split, shard_index, limit)
    library = library if library is not None else _library_for(recipe)
    final = Path(out) / split / task.name
    with ShardWriter(final) as writer:
        for i in range(task.first_index, task.first_index + task.samples):
            writer.write(*render_one(recipe, library, split, i))
            if on_sample is not None:
                on_sample(1)
    return ShardInfo(split=split, index=task.index, name=task.name, first_index=task.first_index,
                     samples=writer.samples, sha256=writer.sha256, bytes=writer.bytes)


def peak_rss_mb() -> float:
    """This process's peak resident memory in MiB (ru_maxrss, KiB on Linux)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _init_worker(recipe, q) -> None:
    import cv2

    cv2.setNumThreads(1)  # one core per worker: no oversubscription
    _WORKER["recipe"], _WORKER["queue"] = recipe, q
    _library_for(recipe)


def _worker_shard(out: str, split: str, shard_index: int, limit: int | None) -> tuple[ShardInfo, float, float]:
    """Pool task: (ShardInfo, seconds spent on the shard, this worker's peak MiB so far)."""
    q = _WORKER["queue"]
    t0 = time.perf_counter()
    info = generate_shard(_WORKER["recipe"], out, split, shard_index, limit=limit,
                          on_sample=(lambda n: q.put(n)) if q is not None else None)
    return info, time.perf_counter() - t0, peak_rss_mb()


# ------------------------------------------------------------------------------ the lock
class OutputLock:
    """`OUT/.lock`: an exclusive, non-blocking fcntl.flock holding the owner's pid.

    The file is removed on release. A lock file left by a killed run is not a lock (the kernel
    drops flock locks with their process), so it never blocks a later run.
    """

    def __init__(self, out: str | os.PathLike):
        self.out = Path(out)
        self.path = self.out / LOCK_NAME
        self.fd: int | None = None

    def acquire(self) -> "OutputLock":
        self.out.mkdir(parents=True, exist_ok=True)
        while True:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                holder = os.read(fd, 64).decode(errors="replace").strip() or "unknown"
                os.close(fd)
                raise OutputInUseError(
                    f"{self.out}: another dofsynth run (pid {holder}) is writing into this folder "
                    f"(it holds {self.path}); wait for it to finish or choose another --out") from None
            try:  # the holder we waited on may have unlinked the file: lock the live one
                same = os.stat(self.path).st_ino == os.fstat(fd).st_ino
            except FileNotFoundError:
                same = False
            if same:
                break
            os.close(fd)
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
        os.fsync(fd)
        self.fd = fd
        return self

    def release(self) -> None:
        if self.fd is None:
            return
        try:
            self.path.unlink(missing_ok=True)
            fcntl.flock(self.fd, fcntl.LOCK_UN)
        finally:
            os.close(self.fd)
            self.fd = None

    def __enter__(self) -> "OutputLock":
        return self.acquire()

    def __exit__(self, *exc) -> None:
        self.release()


# ------------------------------------------------------------------------------- the run
@dataclass
class GenerateResult:
    out: Path
    manifest: dict
    samples: int = 0             # samples in the finished data set
    shards: int = 0
    generated_samples: int = 0   # rendered by this run
    generated_shards: int = 0
    kept_shards: int = 0         # verified and kept by --resume
    removed: list[str] = field(default_factory=list)   # stale temp files and out-of-plan shards
    seconds: float = 0.0
    bytes: int = 0
    skipped_assets: list = field(default_factory=list)
    peak_rss_mb: float = 0.0     # largest worker (or this process) peak resident memory
    shard_seconds: float = 0.0   # time spent inside generate_shard, summed over workers

    @property
    def samples_per_second(self) -> float:
        return self.generated_samples / self.seconds if self.seconds > 0 else 0.0

    @property
    def seconds_per_sample_per_worker(self) -> float:
        """Steady-state cost of one sample on one worker (no start-up, no library build)."""
        return self.shard_seconds / self.generated_samples if self.generated_samples else 0.0

    def summary_lines(self) -> list[str]:
        kept = f", {self.kept_shards} kept from before" if self.kept_shards else ""
        lines = [
            f"dofsynth generate: {self.out}",
            f"  samples  {self.samples} in {self.shards} shards ({self.generated_samples} rendered "
            f"in {self.generated_shards} shards{kept})",
            f"  time     {self.seconds:.1f} s, {self.samples_per_second:.2f} samples/s "
            f"({self.seconds_per_sample_per_worker:.3f} s per sample per worker)",
            f"  size     {self.bytes / 1e6:.1f} MB",
            f"  skipped  {len(self.skipped_assets)} assets" + (
                ": " + ", ".join(str(a) for a in self.skipped_assets[:5]) if self.skipped_assets else ""),
        ]
        if self.removed:
            lines.append(f"  removed  {len(self.removed)} stale files: " + ", ".join(self.removed[:5]))
        return lines


def _skipped_assets(library) -> list:
    skipped = getattr(library, "skipped", None) or []
    out = []
    for s in skipped:
        if hasattr(s, "to_dict"):
            s = s.to_dict()
        elif isinstance(s, (tuple, list)):
            s = [str(x) for x in s]
        elif not isinstance(s, dict):
            s = str(s)
        out.append(s)
    return out


def _entries(out: Path) -> list[str]:
    return sorted(p.name for p in out.iterdir() if p.name != LOCK_NAME) if out.is_dir() else []


def _previous_state(out: Path, recipe) -> tuple[dict[str, int | None], dict[str, ShardInfo]]:
    """For --resume: the per-split limits of the earlier run and the shards it recorded."""
    header, progressed = read_progress(out)
    manifest = load_manifest(out) if (out / MANIFEST_NAME).is_file() else None
    if header is None and manifest is None:
        leftovers = [n for n in _entries(out) if not n.startswith(".")]
        if leftovers:
            raise ResumeError(f"{out}: holds {', '.join(leftovers[:5])} but no {PROGRESS_NAME} or {MANIFEST_NAME}: "
                              "not a dofsynth data set; choose a new --out folder")
        return {}, {}
    prev_sha = (header or {}).get("recipe_sha256") or manifest["recipe"]["sha256"]
    if prev_sha != recipe.sha256:
        raise ResumeError(f"{out}: was made from a recipe with sha256 {prev_sha[:12]}..., not {recipe.path} "
                          f"({recipe.sha256[:12]}...); resume with the same recipe or choose a new --out folder")
    prev_version = (header or {}).get("dofsynth_version") or manifest["dofsynth_version"]
    if prev_version != __version__:
        raise ResumeError(f"{out}: was made by dofsynth {prev_version}, this is {__version__} (samples would "
                          "differ); choose a new --out folder")
    limits: dict[str, int | None] = {}
    known: dict[str, ShardInfo] = {}
    if manifest is not None:
        limits.update({s: b.get("limit") for s, b in manifest["splits"].items()})
        for infos in manifest_shard_infos(manifest).values():
            known.update({i.path: i for i in infos})
    if header is not None:
        limits.update(header.get("limits", {}))
        known.update({i.path: i for i in progressed})
    return limits, known


def _verify_existing(out: Path, task: ShardTask, known: dict[str, ShardInfo]) -> ShardInfo | None:
    """The ShardInfo of an already-written shard that matches the plan, or None."""
    final = out / task.path
    if not final.is_file():
        return None
    sha, nbytes = sha256_file(final)
    info = ShardInfo(task.split, task.index, task.name, task.first_index, task.samples, sha, nbytes)
    rec = known.get(task.path)
    if rec is not None and (rec.first_index, rec.samples) == (task.first_index, task.samples):
        return info if (rec.sha256, rec.bytes) == (sha, nbytes) else None
    try:  # not recorded (killed between rename and progress line): check its sample keys
        return info if shard_keys(final) == task.keys() else None
    except ShardError:
        return None


def generate(recipe, out, workers: int = 1, splits=SPLITS, limit: int | None = None, resume: bool = False,
             progress: bool = True) -> GenerateResult:
    """Make (or with `resume`, finish or extend) the data set of `recipe` in folder `out`.

    `splits`: which splits to make; `limit`: at most this many samples per split (the first
    ones: sample i is the same with or without a limit, only the last shard may be shorter).
    With `resume`, splits an earlier run in `out` began are finished too (with their earlier
    limit unless listed in `splits`). `progress` shows a tqdm bar and prints a closing summary.
    Returns a GenerateResult; raises OutputInUseError, OutputNotEmptyError or ResumeError (all
    ValueError) for the folder problems described in the module docstring.
    """
    t0 = time.perf_counter()
    out = Path(out)
    if int(workers) != workers or workers < 1:
        raise ValueError(f"--workers must be an integer >= 1, got {workers}")
    splits = tuple(splits)
    for s in splits:
        split_size(recipe, s, limit)  # validates split and limit
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {out}: exists and is not a folder")

    with OutputLock(out):
        entries = _entries(out)
        if entries and not resume:
            raise OutputNotEmptyError(
                f"{out}: already holds files ({', '.join(entries[:4])}{', ...' if len(entries) > 4 else ''}); "
                "pass --resume to finish or extend that data set with the same recipe, or choose a new --out folder")
        limits, known = _previous_state(out, recipe) if resume else ({}, {})
        limits.update({s: limit for s in splits})
        plan_splits = [s for s in SPLITS if s in limits]
        tasks = [t for s in plan_splits for t in plan_split(recipe, s, limits[s])]

        removed = [str(p.relative_to(out)) for d in [out] + [out / s for s in SPLITS] for p in remove_temp_files(d)]
        start_progress(out, {"recipe_sha256": recipe.sha256, "dofsynth_version": __version__,
                             "limits": {s: limits[s] for s in plan_splits}})
        (out / MANIFEST_NAME).unlink(missing_ok=True)  # rewritten last

        done: dict[str, list[ShardInfo]] = {s: [] for s in plan_splits}
        todo: list[ShardTask] = []
        for t in tasks:
            info = _verify_existing(out, t, known) if resume else None
            if info is not None:
                done[t.split].append(info)
                append_progress(out, info)
            else:
                todo.append(t)
        if resume:  # shards of planned splits that the plan no longer has (a smaller --limit)
            planned = {t.path for t in tasks}
            for s in plan_splits:
                for p in sorted((out / s).glob(f"{s}-*.tar")) if (out / s).is_dir() else []:
                    if f"{s}/{p.name}" not in planned:
                        p.unlink()
                        removed.append(f"{s}/{p.name}")
        kept = sum(len(v) for v in done.values())

        in_process = workers == 1 or len(todo) <= 1
        library = _library_for(recipe) if todo and in_process else None
        total = sum(t.samples for t in tasks)
        bar = None
        if progress:
            from tqdm import tqdm

            bar = tqdm(total=total, initial=total - sum(t.samples for t in todo), unit="sample",
                       desc=f"generate {out.name}", dynamic_ncols=True, smoothing=0.1)
        peak, busy = peak_rss_mb(), 0.0
        try:
            if in_process:
                for t in todo:
                    ts = time.perf_counter()
                    info = generate_shard(recipe, out, t.split, t.index, limit=limits[t.split], library=library,
                                          on_sample=bar.update if bar else None)
                    busy += time.perf_counter() - ts
                    done[t.split].append(info)
                    append_progress(out, info)
                peak = max(peak, peak_rss_mb())
            elif todo:
                rss, busy = _run_pool(recipe, out, todo, limits, min(workers, len(todo)), done, bar)
                peak = max(peak, rss)
        finally:
            if bar is not None:
                bar.close()

        if library is None:
            library = _library_for(recipe)
        skipped = _skipped_assets(library)
        manifest = build_manifest(recipe, done, limits={s: limits[s] for s in plan_splits},
                                  extra={"skipped_assets": skipped})
        write_manifest(out, manifest)
        remove_progress(out)

    result = GenerateResult(
        out=out, manifest=manifest, samples=manifest["totals"]["samples"], shards=manifest["totals"]["shards"],
        generated_samples=sum(t.samples for t in todo), generated_shards=len(todo), kept_shards=kept,
        removed=removed, seconds=time.perf_counter() - t0, bytes=manifest["totals"]["bytes"],
        skipped_assets=skipped, peak_rss_mb=peak, shard_seconds=busy)
    if progress:
        print("\n".join(result.summary_lines()), flush=True)
    return result


def _run_pool(recipe, out: Path, todo: list[ShardTask], limits, workers: int, done, bar) -> tuple[float, float]:
    """Render `todo` in a spawn process pool and record each finished shard.
    Returns (largest worker peak MiB, seconds spent in shards summed over workers)."""
    ctx = mp.get_context("spawn")
    q = ctx.Queue() if bar is not None else None
    peak, busy = 0.0, 0.0
    ex = ProcessPoolExecutor(max_workers=workers, mp_context=ctx, initializer=_init_worker, initargs=(recipe, q))
    try:
        futures = {ex.submit(_worker_shard, str(out), t.split, t.index, limits[t.split]): t for t in todo}
        _library_for(recipe)  # for the manifest's skipped-asset list, while the workers start
        pending = set(futures)
        while pending:
            finished, pending = wait(pending, timeout=0.25, return_when=FIRST_COMPLETED)
            _drain(q, bar)
            for f in finished:
                t = futures[f]
                try:
                    info, seconds, rss = f.result()
                except Exception as exc:
                    if isinstance(exc, (ValueError, FileNotFoundError)):
                        raise ValueError(f"shard {t.path}: {exc}") from exc
                    raise RuntimeError(f"shard {t.path} failed: {exc!r}") from exc
                peak, busy = max(peak, rss), busy + seconds
                done[t.split].append(info)
                append_progress(out, info)
    except BaseException:
        ex.shutdown(wait=False, cancel_futures=True)
        raise
    ex.shutdown(wait=True)
    _drain(q, bar)
    if bar is not None and bar.n != bar.total:
        bar.n = bar.total
        bar.refresh()
    return peak, busy


def _drain(q, bar) -> None:
    while q is not None:
        try:
            n = q.get_nowait()
        except (queue_mod.Empty, OSError, ValueError):
            return
        if bar is not None:
            bar.update(n)
