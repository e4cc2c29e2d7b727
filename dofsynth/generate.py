"""Make a data set: plan shards, render them (with an executor), write the manifest last.

The plan: per split, shards of `recipe.shard_size` consecutive sample indices (the last may be
shorter); `limit` caps the samples of each split. A shard is made by the pure function
`generate_shard(recipe, out, split, shard_index)`, whose output depends on nothing but the
recipe (and the asset files it names), so sample i is the same bytes whatever the worker
count, the machine, the executor, the order shards finish in, or a resume. Executors
(`dofsynth.executors`: this process, a spawn pool, a Ray cluster) only distribute those calls;
everything else is here, the same for all of them.

The global shard plan of a run is `plan_shards(recipe, splits, limit)`: train's shards, then
test's. `shard_range=(A, B)` (`--shards A:B`) makes only shards A..B-1 of it and writes the
partial manifest `OUT/manifest.part-A-B.json`; disjoint ranges may run at once into one OUT
(a job array on a shared file system); `dofsynth manifest merge OUT` joins the parts into the
manifest.json a single run writes.

Safety of the output folder `OUT`:
- `OUT/.lock` (fcntl.flock, `dofsynth.locks`) refuses a second concurrent run into OUT: a whole run holds it
  exclusively (its pid inside), `--shards` runs hold it shared plus `OUT/.lock.part-A-B`
  exclusively, and refuse a live overlapping range.
- Without `resume`, an OUT holding anything is refused (never silently mixed); a `--shards`
  run accepts only the work of other ranges of the same recipe and plan.
- Shards appear under their final names only when complete; leftover temp files of a killed
  run (or of a killed Ray task) are removed; `OUT/.progress.jsonl` (`.progress.part-A-B.jsonl`)
  lists finished shards while running.
- With `resume`, shards already there are verified (sha256 against the progress file or old
  manifest, else their sample keys) and kept; the rest are made; a resumed data set is
  byte-identical to an uninterrupted one.
- `OUT/manifest.json` (or the partial manifest) is written last, atomically; then the progress
  file is removed.
"""
from __future__ import annotations

import os
import re
import resource
import time
from dataclasses import dataclass, field
from pathlib import Path

from dofsynth import __version__
from dofsynth.locks import LOCK_NAME, OutputInUseError, OutputLock, RangeLock
from dofsynth.manifest import (MANIFEST_NAME, PART_RE, PROGRESS_NAME, PROGRESS_PART_RE, append_progress,
                               build_manifest, build_part, load_manifest, load_part, manifest_shard_infos,
                               part_name, progress_part_name, read_progress, remove_progress, start_progress,
                               write_manifest, write_part)
from dofsynth.shards import (TEMP_MARK, ShardError, ShardInfo, ShardWriter, is_temp_name, remove_temp_files,
                             sample_key, shard_keys, shard_name, sha256_file)

SPLITS = ("train", "test")


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
_WORKER: dict = {"sha": None, "library": None}


def _library_for(recipe, library=None):
    """The asset library of `recipe`, built once per process and reused for every shard.
    `library`: one already built for this recipe, used unless this process has one (workers
    get their parent's: the asset folders are scanned and hashed once, not once per worker)."""
    key = (recipe.sha256, getattr(recipe, "base_dir", ""))  # the same text elsewhere names other files
    if _WORKER["sha"] != key or _WORKER["library"] is None:
        if library is None:
            from dofsynth.assets import build_library

            library = build_library(recipe)
        _WORKER["library"], _WORKER["sha"] = library, key
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


# ------------------------------------------------------------------------------- the run
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
    peak_rss_mb: float = 0.0     # largest worker (or this process) peak resident memory
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
            f"  skipped  {len(self.skipped_assets)} assets" + (
                ": " + ", ".join(str(a) for a in self.skipped_assets[:5]) if self.skipped_assets else ""),
        ]
        if self.removed:
            lines.append(f"  removed  {len(self.removed)} stale files: " + ", ".join(self.removed[:5]))
        return lines


def _skipped_assets(library, recipe=None) -> list:
    """The library's skipped files as [path, reason] lists, with the recipe's folder and its
    asset folders written relative to the recipe's folder (`base_dir`), so that the manifest
    does not depend on where the recipe and assets lie on this machine."""
    skipped = getattr(library, "skipped", None) or []
    rel = _relativizer(recipe)
    out = []
    for s in skipped:
        if hasattr(s, "to_dict"):
            s = s.to_dict()
        elif isinstance(s, (tuple, list)):
            s = [rel(str(x)) for x in s]
        elif not isinstance(s, dict):
            s = rel(str(s))
        out.append(s)
    return out


def _relativizer(recipe):
    base = str(getattr(recipe, "base_dir", "") or "")
    if not base:
        return lambda text: text
    assets = getattr(recipe, "assets", None)
    roots = {base} | {str(r) for r in (getattr(assets, "backgrounds", None), getattr(assets, "foregrounds", None))
                      if r and os.path.isabs(str(r))}
    subs = []
    for r in sorted(roots, key=len, reverse=True):  # longest first: an asset folder inside base
        rp = os.path.relpath(r, base)
        subs.append((r.rstrip(os.sep) + os.sep, "" if rp == "." else rp + os.sep))

    def rel(text: str) -> str:
        for a, b in subs:
            text = text.replace(a, b)
        return text

    return rel


def _entries(out: Path) -> list[str]:
    return sorted(p.name for p in out.iterdir() if p.name != LOCK_NAME) if out.is_dir() else []


def _previous_state(out: Path, recipe) -> tuple[dict[str, int | None], dict[str, ShardInfo]]:
    """For --resume: the per-split limits of the earlier run and the shards it recorded."""
    header, progressed = read_progress(out)
    manifest = load_manifest(out) if (out / MANIFEST_NAME).is_file() else None
    if header is None and manifest is None:
        leftovers = [n for n in _entries(out) if not n.startswith(".")]
        if any(PART_RE.match(n) for n in leftovers):
            raise ResumeError(f"{out}: holds partial manifests of --shards runs ({', '.join(leftovers[:3])}...); "
                              f"finish those ranges with --shards A:B --resume and join them with "
                              f"`dofsynth manifest merge {out}`, or choose a new --out folder")
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


def _remove_temps(out: Path, paths: set[str] | None = None) -> list[str]:
    """Delete leftover shard temp files ("<split>/.<name>.tmp-<pid>") of the shards `paths`
    ("train/train-000001.tar", ...), or of every shard if None (only with OUT's exclusive lock).
    A killed run, or a task killed mid-shard and retried by Ray, leaves them."""
    removed = []
    for s in SPLITS:
        folder = out / s
        if not folder.is_dir():
            continue
        for p in sorted(folder.iterdir()):
            if not (p.is_file() and is_temp_name(p.name)):
                continue
            final = p.name[1:].split(TEMP_MARK)[0].split(".tmp")[0]
            if paths is None or f"{s}/{final}" in paths:
                p.unlink(missing_ok=True)
                removed.append(f"{s}/{p.name}")
    return removed


def _make(recipe, out: Path, executor, tasks: list[ShardTask], todo: list[ShardTask], limits: dict,
          record, progress: bool) -> tuple[float, float]:
    """Render `todo` with `executor`, calling `record(info)` per finished shard, under one tqdm
    bar over all `tasks` (those already made count as done). Returns (largest peak MiB of the
    processes that rendered, seconds inside generate_shard summed over them)."""
    total = sum(t.samples for t in tasks)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=total, initial=total - sum(t.samples for t in todo), unit="sample",
                   desc=f"generate {out.name}", dynamic_ncols=True, smoothing=0.1)
    size = {t.path: t.samples for t in todo}
    shown: dict[str, int] = {}

    def on_samples(path: str, n: int) -> None:  # never more than a shard's size (a Ray retry repeats)
        now = min(size.get(path, 0), shown.get(path, 0) + n)
        if bar is not None and now > shown.get(path, 0):
            bar.update(now - shown.get(path, 0))
        shown[path] = now

    peak, busy = peak_rss_mb(), 0.0
    try:
        if todo:
            for d in executor.run(recipe, out, todo, limits, on_samples=on_samples,
                                  on_submitted=lambda: _library_for(recipe)):
                on_samples(d.task.path, d.task.samples)
                peak, busy = max(peak, d.peak_rss_mb), busy + d.seconds
                record(d.info)
    finally:
        if bar is not None:
            bar.close()
    return peak, busy


def _executor_for(executor, workers):
    from dofsynth.executors import Executor, LocalExecutor

    if executor is None:
        return LocalExecutor(workers)
    if not isinstance(executor, Executor):
        raise TypeError(f"executor must be a dofsynth.executors.Executor, got {type(executor).__name__}")
    return executor


def parse_shard_range(text: str) -> tuple[int, int | None]:
    """"A:B" (half-open, B > A >= 0) or "A:" (to the end of the plan) -> (A, B or None)."""
    m = re.fullmatch(r"\s*(\d+)\s*:\s*(\d*)\s*", str(text))
    if not m:
        raise ValueError(f"--shards {text!r}: expected A:B (shards A .. B-1 of the plan, e.g. 0:10) or A:")
    a, b = int(m[1]), (int(m[2]) if m[2] else None)
    if b is not None and b <= a:
        raise ValueError(f"--shards {text}: B must be greater than A (half-open range A:B)")
    return a, b


def generate(recipe, out, workers: int = 1, splits=SPLITS, limit: int | None = None, resume: bool = False,
             progress: bool = True, executor=None, shard_range: tuple[int, int | None] | None = None) -> GenerateResult:
    """Make (or with `resume`, finish or extend) the data set of `recipe` in folder `out`.

    `splits`: which splits to make; `limit`: at most this many samples per split (the first
    ones: sample i is the same with or without a limit, only the last shard may be shorter).
    With `resume`, splits an earlier run in `out` began are finished too (with their earlier
    limit unless listed in `splits`). `progress` shows a tqdm bar and prints a closing summary.
    `executor`: a `dofsynth.executors.Executor` (default: `LocalExecutor(workers)`).
    `shard_range=(A, B)`: make only shards A..B-1 of the plan (`plan_shards(recipe, splits,
    limit)`: train's shards, then test's; B None or past the end: to the end) and write the
    partial manifest `OUT/manifest.part-A-B.json` instead of `manifest.json` (see
    `dofsynth.manifest.merge_parts`). Returns a GenerateResult; raises OutputInUseError,
    OutputNotEmptyError or ResumeError (all ValueError) for the folder problems described in
    the module docstring.
    """
    t0 = time.perf_counter()
    out = Path(out)
    executor = _executor_for(executor, workers)
    splits = tuple(splits)
    for s in splits:
        split_size(recipe, s, limit)  # validates split and limit
    if out.exists() and not out.is_dir():
        raise ValueError(f"--out {out}: exists and is not a folder")
    executor.prepare()  # e.g. join the Ray cluster, before OUT is touched
    try:
        if shard_range is not None:
            return _generate_range(recipe, out, executor, splits, limit, resume, progress, shard_range, t0)
        return _generate_all(recipe, out, executor, splits, limit, resume, progress, t0)
    finally:
        executor.close()


def _generate_all(recipe, out: Path, executor, splits, limit, resume, progress, t0) -> GenerateResult:
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

        removed = [str(p.relative_to(out)) for p in remove_temp_files(out)] + _remove_temps(out)
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

        def record(info: ShardInfo) -> None:
            done[info.split].append(info)
            append_progress(out, info)

        peak, busy = _make(recipe, out, executor, tasks, todo, limits, record, progress)
        removed += _remove_temps(out)  # of attempts that died and were retried
        skipped = _skipped_assets(_library_for(recipe), recipe)
        manifest = build_manifest(recipe, done, limits={s: limits[s] for s in plan_splits},
                                  extra={"skipped_assets": skipped})
        write_manifest(out, manifest)
        remove_progress(out)

    result = GenerateResult(
        out=out, manifest=manifest, samples=manifest["totals"]["samples"], shards=manifest["totals"]["shards"],
        generated_samples=sum(t.samples for t in todo), generated_shards=len(todo), kept_shards=kept,
        removed=removed, seconds=time.perf_counter() - t0, bytes=manifest["totals"]["bytes"],
        skipped_assets=skipped, peak_rss_mb=peak, shard_seconds=busy, executor=executor.describe(),
        plan_shards=len(tasks))
    if progress:
        print("\n".join(result.summary_lines()), flush=True)
    return result


# ------------------------------------------------------------------- a range of the plan
def _range_header(recipe, limits: dict, first: int, stop: int, total: int) -> dict:
    return {"recipe_sha256": recipe.sha256, "dofsynth_version": __version__, "limits": limits,
            "range": [first, stop], "shards": total}


def _check_shared_folder(out: Path, recipe, header: dict, tasks: list[ShardTask], resume: bool) -> None:
    """What a --shards run accepts in OUT: other ranges of the same recipe and plan (their
    shards, partial manifests, progress and lock files), and, with `resume`, its own earlier
    work. Refuses the rest, naming it."""
    first, stop = header["range"]
    same = ("recipe_sha256", "dofsynth_version", "limits", "shards")
    for name in _entries(out):
        p = out / name
        if name in SPLITS and p.is_dir() or name.startswith(LOCK_NAME) or is_temp_name(name):
            continue  # temp files: another range's part or progress file being written
        m = PART_RE.match(name) or PROGRESS_PART_RE.match(name)
        if m:
            a, b = int(m[1]), int(m[2])
            if PART_RE.match(name):
                part = load_part(p)
                other = {"recipe_sha256": part["recipe"]["sha256"], "dofsynth_version": part["dofsynth_version"],
                         "limits": part["plan"]["limits"], "shards": part["plan"]["shards"]}
            else:
                other = read_progress(out, name)[0]
                if other is None:
                    continue
            if other.get("recipe_sha256") != header["recipe_sha256"]:
                raise OutputNotEmptyError(f"{out}: holds {name}, made from another recipe (sha256 "
                                          f"{str(other.get('recipe_sha256'))[:12]}..., not {recipe.path}); one folder "
                                          "holds one data set: choose another --out")
            if any(other.get(k) != header[k] for k in same):
                raise OutputNotEmptyError(f"{out}: holds {name}, of another plan (dofsynth version, --split or --limit "
                                          "differ); every --shards run into one OUT needs the same recipe and options")
            if (a, b) == (first, stop):
                if not resume:
                    raise OutputNotEmptyError(f"{out}: shards {a}:{b} were made or begun here before ({name}); pass "
                                              "--resume to verify and finish them")
            elif a < stop and first < b:
                raise OutputNotEmptyError(f"{out}: --shards {first}:{stop} overlaps {name} (shards {a}:{b}); the "
                                          "ranges of one data set must be disjoint")
            continue
        if name == MANIFEST_NAME:
            raise OutputNotEmptyError(f"{out}: holds a finished data set ({MANIFEST_NAME}); choose a new --out folder")
        if name == PROGRESS_NAME:
            raise OutputNotEmptyError(f"{out}: a whole run (without --shards) began here ({PROGRESS_NAME}); finish it "
                                      "with --resume and no --shards, or choose a new --out folder")
        raise OutputNotEmptyError(f"{out}: holds {name}, which is not part of a dofsynth data set made with "
                                  "--shards; choose a new --out folder")
    if not resume:
        for t in tasks:
            if (out / t.path).exists():
                raise OutputNotEmptyError(f"{out}: {t.path} (in --shards {first}:{stop}) exists already; pass "
                                          "--resume to verify and keep it")


def _generate_range(recipe, out: Path, executor, splits, limit, resume, progress, shard_range, t0) -> GenerateResult:
    splits = [s for s in SPLITS if s in splits]
    limits = {s: limit for s in splits}
    plan = plan_shards(recipe, splits, limit)
    total = len(plan)
    first, stop = shard_range
    if first < 0 or (stop is not None and stop <= first):
        raise ValueError(f"--shards {first}:{stop}: expected 0 <= A < B")
    stop = total if stop is None else min(stop, total)
    if first >= stop:
        raise ValueError(f"--shards {shard_range[0]}:{'' if shard_range[1] is None else shard_range[1]}: the plan "
                         f"of {recipe.path} ({'/'.join(splits)}, limit {limit}) has shards 0:{total}; this range "
                         "holds none")
    tasks = plan[first:stop]
    own = {t.path for t in tasks}
    header = _range_header(recipe, limits, first, stop, total)
    pname, prog = part_name(first, stop), progress_part_name(first, stop)
    with RangeLock(out, first, stop):
        _check_shared_folder(out, recipe, header, tasks, resume)
        known: dict[str, ShardInfo] = {}
        if resume:
            if (out / pname).is_file():
                known.update({i.path: i for i in map(ShardInfo.from_dict, load_part(out / pname)["shards"])})
            known.update({i.path: i for i in read_progress(out, prog)[1]})
        removed = _remove_temps(out, own)
        start_progress(out, header, prog)
        (out / pname).unlink(missing_ok=True)  # rewritten last
        done: list[ShardInfo] = []
        todo: list[ShardTask] = []
        for t in tasks:
            info = _verify_existing(out, t, known) if resume else None
            if info is not None:
                done.append(info)
                append_progress(out, info, prog)
            else:
                todo.append(t)
        kept = len(done)

        def record(info: ShardInfo) -> None:
            done.append(info)
            append_progress(out, info, prog)

        peak, busy = _make(recipe, out, executor, tasks, todo, limits, record, progress)
        removed += _remove_temps(out, own)
        skipped = _skipped_assets(_library_for(recipe), recipe)
        plan_info = {"splits": splits, "limits": limits, "shards": total,
                     "split_shards": {s: sum(1 for t in plan if t.split == s) for s in splits}}
        part = build_part(recipe, (first, stop), plan_info, done, extra={"skipped_assets": skipped})
        path = write_part(out, part)
        remove_progress(out, prog)

    result = GenerateResult(
        out=out, manifest=part, samples=sum(i.samples for i in done), shards=len(done),
        generated_samples=sum(t.samples for t in todo), generated_shards=len(todo), kept_shards=kept,
        removed=removed, seconds=time.perf_counter() - t0, bytes=sum(i.bytes for i in done),
        skipped_assets=skipped, peak_rss_mb=peak, shard_seconds=busy, executor=executor.describe(),
        shard_range=(first, stop), plan_shards=total, part=path)
    if progress:
        print("\n".join(result.summary_lines()), flush=True)
    return result
