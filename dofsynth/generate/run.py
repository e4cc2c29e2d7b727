"""Make a data set: plan shards, render them (with an executor), write the manifest last.

`generate(recipe, out, ...)` is the one driver of a run, for the whole plan or (`shard_range`,
`--shards A:B`) a range of it. The plan is dofsynth.generate.plan's (train's shards, then
test's); executors (dofsynth.generate.executors: this process, a spawn pool, a Ray cluster)
only distribute the calls of the pure `generate_shard`; everything else is here, the same for
all of them:
- `OUT/.lock` (dofsynth.generate.locks) refuses a second concurrent run into OUT: a whole run holds it
  exclusively, `--shards` runs hold it shared plus `OUT/.lock.part-A-B` exclusively and refuse
  a live overlapping range;
- what OUT may hold, what `--resume` keeps and the temp files of a killed run:
  dofsynth.generate.folder;
- `OUT/.progress.jsonl` (`.progress.part-A-B.jsonl`) lists finished shards while running;
- `OUT/manifest.json` (a range: the partial manifest `OUT/manifest.part-A-B.json`, joined by
  `dofsynth manifest merge`) is written last, atomically; then the progress file is removed.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from pathlib import Path

from dofsynth import __version__
from dofsynth.files import remove_temp_files
from dofsynth.generate.executors import Executor, LocalExecutor
from dofsynth.generate.folder import (OutputNotEmptyError, check_shared_folder, entries, previous_state,
                                      remove_shard_temps, verify_existing)
from dofsynth.generate.plan import ShardTask, plan_shards, plan_split, split_size
from dofsynth.generate.locks import OutputLock, RangeLock
from dofsynth.generate.worker import library_for, portable, shard_usage
from dofsynth.manifest import build_manifest, with_bad_assets, write_manifest
from dofsynth.manifest.card import write_card
from dofsynth.manifest.names import MANIFEST_NAME, PROGRESS_NAME, part_name, progress_part_name
from dofsynth.manifest.parts import build_part, load_part, write_part
from dofsynth.manifest.progress import append_progress, read_progress, remove_progress, start_progress
from dofsynth.manifest.usage import Usage
from dofsynth.progress import bar as progress_bar
from dofsynth.progress import note
from dofsynth.rng import SPLITS
from dofsynth.shards import ShardInfo


@dataclass
class GenerateResult:
    out: Path
    manifest: dict               # manifest.json's content, or the partial manifest of a --shards run
    samples: int = 0             # samples in the finished data set (or range)
    shards: int = 0
    generated_samples: int = 0   # rendered by this run
    generated_shards: int = 0
    kept_shards: int = 0         # verified and kept by --resume
    removed: list[str] = field(default_factory=list)   # stale temp files and out-of-plan shards
    seconds: float = 0.0
    bytes: int = 0
    skipped_assets: list = field(default_factory=list)
    peak_rss_mb: float = 0.0     # largest peak resident memory of a process that rendered (0: none did)
    shard_seconds: float = 0.0   # time spent inside generate_shard, summed over workers
    executor: str = "local"
    shard_range: tuple[int, int] | None = None   # a --shards run: its range of the plan ...
    plan_shards: int = 0                          # ... of this many shards
    part: Path | None = None                      # ... and its partial manifest

    @property
    def samples_per_second(self) -> float:
        return self.generated_samples / self.seconds if self.seconds > 0 else 0.0

    @property
    def seconds_per_sample_per_worker(self) -> float:
        """Steady-state cost of one sample on one worker (no start-up, no library build)."""
        return self.shard_seconds / self.generated_samples if self.generated_samples else 0.0

    def summary_lines(self) -> list[str]:
        kept = f", {self.kept_shards} kept from before" if self.kept_shards else ""
        lines = [f"dofsynth generate: {self.out} ({self.executor})"]
        if self.shard_range is not None:
            a, b = self.shard_range
            lines.append(f"  range    shards {a}:{b} of {self.plan_shards}: partial manifest {self.part.name} "
                         f"(when all ranges are done: dofsynth manifest merge {self.out})")
        lines += [
            f"  samples  {self.samples} in {self.shards} shards ({self.generated_samples} rendered "
            f"in {self.generated_shards} shards{kept})",
            f"  time     {self.seconds:.1f} s" + (
                f", {self.samples_per_second:.2f} samples/s ({self.seconds_per_sample_per_worker:.3f} s per "
                "sample per worker)" if self.generated_samples else ": nothing left to render"),
            f"  size     {self.bytes / 1e6:.1f} MB",
            f"  skipped  {len(self.skipped_assets)} assets" + (":" if self.skipped_assets else ""),
        ]
        lines += [f"    {why if why.startswith(path) else f'{path}: {why}'}" for path, why in self.skipped_assets]
        if self.removed:
            lines.append(f"  removed  {len(self.removed)} stale files: " + ", ".join(self.removed[:5]))
        return lines


def _skipped_assets(library, recipe) -> list[list[str]]:
    """The library's skipped files as [path, reason], relative to the recipe's folder."""
    rel = portable(recipe)
    return [[rel(str(p)), rel(str(reason))] for p, reason in library.skipped]


def _bad_assets(done: list[ShardInfo]) -> dict[str, str]:
    """The asset files the shards' samples found bad when loading them."""
    total = Usage()
    for info in done:
        total.merge(Usage(info.usage))
    return total.bad


def _make(recipe, out: Path, executor, tasks: list[ShardTask], todo: list[ShardTask], limits: dict,
          record, progress: bool, worker_lock: Path) -> tuple[float, float]:
    """Render `todo` with `executor`, calling `record(info)` per finished shard, under one
    progress bar (dofsynth.progress) over all `tasks` (those already made count as done). Returns (largest peak MiB of the
    processes that rendered, seconds inside generate_shard summed over them)."""
    total = sum(t.samples for t in tasks)
    bar = progress_bar(total, f"generate {out.name}", initial=total - sum(t.samples for t in todo),
                       enabled=progress)
    size = {t.path: t.samples for t in todo}
    shown: dict[str, int] = {}

    def on_samples(path: str, n: int) -> None:  # never more than a shard's size (a Ray retry repeats)
        now = min(size.get(path, 0), shown.get(path, 0) + n)
        if now > shown.get(path, 0):
            bar.update(now - shown.get(path, 0))
        shown[path] = now

    peak, busy = 0.0, 0.0  # over the processes that rendered (this one only when it rendered)
    try:
        if todo:
            for d in executor.run(recipe, out, todo, limits, on_samples=on_samples, worker_lock=worker_lock):
                on_samples(d.task.path, d.task.samples)
                peak, busy = max(peak, d.peak_rss_mb), busy + d.seconds
                record(d.info)
                note(f"  {d.info.path}: {d.info.samples} samples, {d.info.bytes} bytes, {d.seconds:.1f} s")
    finally:
        bar.close()
    return peak, busy


class _Whole:
    """A run of the whole plan into OUT: manifest.json at the end."""

    def __init__(self, recipe, out: Path, splits, limit, resume: bool, assets: dict):
        self.recipe, self.out, self.splits, self.limit, self.resume = recipe, out, splits, limit, resume
        self.assets = assets
        self.progress = PROGRESS_NAME
        self.final = out / MANIFEST_NAME
        self.own = None  # every shard's temp files are this run's to remove

    def lock(self):
        return OutputLock(self.out)

    def check(self) -> None:
        """Refuse a used OUT without resume; the limits, tasks and known shards of the run."""
        found = entries(self.out)
        if found and not self.resume:
            raise OutputNotEmptyError(
                f"{self.out}: already holds files ({', '.join(found[:4])}{', ...' if len(found) > 4 else ''}); "
                "pass --resume to finish or extend that data set with the same recipe, or choose a new --out folder")
        self.limits, self.known = previous_state(self.out, self.recipe, self.assets) if self.resume else ({}, {})
        self.limits.update({s: self.limit for s in self.splits})
        self.plan_splits = [s for s in SPLITS if s in self.limits]
        self.limits = {s: self.limits[s] for s in self.plan_splits}
        self.tasks = [t for s in self.plan_splits for t in plan_split(self.recipe, s, self.limits[s])]
        self.header = {"recipe_sha256": self.recipe.sha256, "dofsynth_version": __version__, "limits": self.limits,
                       "assets": self.assets}
        self.plan_size = len(self.tasks)

    def remove_stale(self) -> list[str]:
        """Temp files of a killed run; with resume, shards the plan no longer has (a smaller --limit)."""
        out = self.out
        removed = [str(p.relative_to(out)) for p in remove_temp_files(out)] + remove_shard_temps(out)
        if self.resume:
            planned = {t.path for t in self.tasks}
            for s in self.plan_splits:
                for p in sorted((out / s).glob(f"{s}-*.tar")) if (out / s).is_dir() else []:
                    if f"{s}/{p.name}" not in planned:
                        p.unlink()
                        removed.append(f"{s}/{p.name}")
        return removed

    def write(self, done: list[ShardInfo], skipped) -> dict:
        shards = {s: [i for i in done if i.split == s] for s in self.plan_splits}
        manifest = build_manifest(self.recipe, shards, limits=self.limits,
                                  extra={"skipped_assets": skipped, "assets": self.assets})
        write_card(self.out, manifest)   # the card first: the manifest is the set's "finished" mark
        write_manifest(self.out, manifest)
        return manifest


class _Range:
    """A `--shards A:B` run: shards A..B-1 of the plan, the partial manifest at the end."""

    def __init__(self, recipe, out: Path, splits, limit, resume: bool, assets: dict, shard_range):
        self.recipe, self.out, self.resume, self.assets = recipe, out, resume, assets
        self.splits = [s for s in SPLITS if s in splits]
        self.limits = {s: limit for s in self.splits}
        self.plan = plan_shards(recipe, self.splits, limit)
        self.plan_size = total = len(self.plan)
        first, stop = shard_range
        if first < 0 or (stop is not None and stop <= first):
            raise ValueError(f"--shards {first}:{stop}: expected 0 <= A < B")
        stop = total if stop is None else min(stop, total)
        if first >= stop:
            raise ValueError(f"--shards {shard_range[0]}:{'' if shard_range[1] is None else shard_range[1]}: the "
                             f"plan of {recipe.path} ({'/'.join(self.splits)}, limit {limit}) has shards 0:{total}; "
                             "this range holds none")
        self.range = (first, stop)
        self.tasks = self.plan[first:stop]
        self.own = {t.path for t in self.tasks}
        self.header = {"recipe_sha256": recipe.sha256, "dofsynth_version": __version__, "limits": self.limits,
                       "range": [first, stop], "shards": total, "assets": assets}
        self.progress = progress_part_name(first, stop)
        self.final = out / part_name(first, stop)

    def lock(self):
        return RangeLock(self.out, *self.range)

    def check(self) -> None:
        check_shared_folder(self.out, self.recipe, self.header, self.tasks, self.resume)
        self.known: dict[str, ShardInfo] = {}
        if self.resume:
            if self.final.is_file():
                self.known.update({i.path: i for i in map(ShardInfo.from_dict, load_part(self.final)["shards"])})
            self.known.update({i.path: i for i in read_progress(self.out, self.progress)[1]})

    def remove_stale(self) -> list[str]:
        return remove_shard_temps(self.out, self.own)

    def write(self, done: list[ShardInfo], skipped) -> dict:
        plan_info = {"splits": self.splits, "limits": self.limits, "shards": self.plan_size,
                     "split_shards": {s: sum(1 for t in self.plan if t.split == s) for s in self.splits}}
        part = build_part(self.recipe, self.range, plan_info, done, extra={"skipped_assets": skipped, "assets": self.assets})
        write_part(self.out, part)
        return part


def _leave_nothing(out: Path, run, created: bool) -> None:
    """After a run that failed with no shard made or kept: remove what it wrote (its progress
    file, empty split folders, OUT itself if it made it), so the same command can run again,
    unless OUT holds shards of an earlier run (their hashes are in the progress file)."""
    shards = [p for s in SPLITS if (out / s).is_dir() for p in (out / s).iterdir()]
    if shards:
        return
    (out / run.progress).unlink(missing_ok=True)
    for s in SPLITS:
        if (out / s).is_dir():
            (out / s).rmdir()
    if created and out.is_dir() and not entries(out):
        for p in out.iterdir():  # stale lock files only
            p.unlink(missing_ok=True)
        out.rmdir()


def _executor_for(executor, workers):
    if executor is None:
        return LocalExecutor(workers)
    if not isinstance(executor, Executor):
        raise TypeError(f"executor must be a dofsynth.generate.executors.Executor, got {type(executor).__name__}")
    return executor


def generate(recipe, out, workers: int = 1, splits=SPLITS, limit: int | None = None, resume: bool = False,
             progress: bool = True, executor=None, shard_range: tuple[int, int | None] | None = None) -> GenerateResult:
    """Make (or with `resume`, finish or extend) the data set of `recipe` in folder `out`.

    `splits`: which splits to make; `limit`: at most this many samples per split (the first
    ones: sample i is the same with or without a limit, only the last shard may be shorter).
    With `resume`, splits an earlier run in `out` began are finished too (with their earlier
    limit unless listed in `splits`). `progress` shows a tqdm bar and prints a closing summary.
    `executor`: a dofsynth.generate.executors.Executor (default: `LocalExecutor(workers)`).
    `shard_range=(A, B)`: make only shards A..B-1 of the plan (`plan_shards(recipe, splits,
    limit)`; B None or past the end: to the end) and write the partial manifest
    `OUT/manifest.part-A-B.json` instead of `manifest.json` (see dofsynth.manifest.merge_parts).
    Returns a GenerateResult; raises OutputInUseError, OutputNotEmptyError or ResumeError (all
    ValueError) for the folder problems of dofsynth.generate.folder.
    """
    t0 = time.perf_counter()
    out = Path(out)
    executor = _executor_for(executor, workers)
    splits = tuple(splits)
    for s in splits:
        split_size(recipe, s, limit)  # validates split and limit
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {out}: exists and is not a folder")
    library = library_for(recipe)  # a bad asset folder stops the run here, before OUT is touched
    assets = {"sha256": library.fingerprint(), "files": library.listing(), "groups": library.groups}
    run = _Range(recipe, out, splits, limit, resume, assets, shard_range) if shard_range is not None else \
        _Whole(recipe, out, splits, limit, resume, assets)
    executor.prepare()  # e.g. join the Ray cluster, before OUT is touched
    created = not out.exists()
    done: list[ShardInfo] = []
    try:
        with run.lock() as lock:
            run.check()
            removed = run.remove_stale()
            todo: list[ShardTask] = []
            for t in run.tasks:  # the kept shards' hashes go into the new progress file...
                info = verify_existing(out, t, run.known) if resume else None
                if info is not None and info.usage is None:  # not recorded: read from its records
                    info = replace(info, usage=shard_usage(out / info.path, recipe, library))
                (done if info is not None else todo).append(info or t)
            kept = len(done)
            start_progress(out, run.header, run.progress, done)
            run.final.unlink(missing_ok=True)  # ...before the manifest that held them goes; rewritten last

            def record(info: ShardInfo) -> None:
                done.append(info)
                append_progress(out, info, run.progress)

            try:
                peak, busy = _make(recipe, out, executor, run.tasks, todo, run.limits, record, progress,
                                   lock.workers_path)
            finally:  # every worker has stopped: the temp files of dead or dropped attempts go
                removed += remove_shard_temps(out, run.own)
            skipped = _skipped_assets(library, recipe)
            manifest = run.write(done, skipped)
            remove_progress(out, run.progress)
    except BaseException:
        if not done:
            _leave_nothing(out, run, created)
        raise
    finally:
        executor.close()
    ranged = shard_range is not None
    result = GenerateResult(
        out=out, manifest=manifest, samples=sum(i.samples for i in done), shards=len(done),
        generated_samples=sum(t.samples for t in todo), generated_shards=len(todo), kept_shards=kept,
        removed=removed, seconds=time.perf_counter() - t0, bytes=sum(i.bytes for i in done),
        skipped_assets=with_bad_assets(skipped, _bad_assets(done)), peak_rss_mb=peak, shard_seconds=busy, executor=executor.describe(),
        shard_range=run.range if ranged else None, plan_shards=run.plan_size, part=run.final if ranged else None)
    if progress:
        print("\n".join(result.summary_lines()), flush=True)
    return result
