"""Executors: who renders the shards of a `generate` run.

One small interface: `Executor.run(recipe, out, tasks, limits, on_samples, worker_lock)`
submits one call of the pure `generate_shard` (dofsynth.generate.worker) per `ShardTask` and
yields a `ShardDone` per finished shard, in any order. Everything else (the plan, the lock, the
progress file and bar, resume, the manifest and the summary) stays in dofsynth.generate.run,
the same for every executor.

- `LocalExecutor(workers)`: in this process (workers=1) or spawn worker processes
  (dofsynth.generate.pool) that take this process's asset library (built once per run) and
  die with it; progress is reported per sample.
- `RayExecutor(address, max_retries, max_in_flight)`: one Ray task per shard on a local or
  remote Ray cluster (`pip install 'dofsynth[ray]'`); a task whose worker dies (killed, out of
  memory, node lost) is retried up to `max_retries` times, the retry rewriting the shard from
  scratch (a shard reaches its final name only when complete, so a dead attempt leaves at most
  a temp file, which the driver removes). Progress is reported per finished shard. Every node
  must see `OUT` at the same path (a shared file system) and have the same dofsynth installed.
"""
from __future__ import annotations

import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator

from dofsynth.generate.plan import ShardTask
from dofsynth.generate.pool import run_pool
from dofsynth.generate.worker import generate_shard, library_for, peak_rss_mb, setup_process
from dofsynth.shards import ShardInfo

EXECUTORS = ("local", "ray")
RAY_INSTALL_HINT = "pip install 'dofsynth[ray]'  (or: pip install 'ray>=2.9')"

OnSamples = Callable[[str, int], None]   # (shard path, samples just written)


@dataclass(frozen=True)
class ShardDone:
    """A finished shard: its task, its ShardInfo, seconds inside `generate_shard`, and the
    peak resident memory (MiB, ru_maxrss) of the process that made it."""

    task: ShardTask
    info: ShardInfo
    seconds: float
    peak_rss_mb: float


class Executor:
    """Runs shard tasks; see the module docstring."""

    name = "executor"

    def describe(self) -> str:
        return self.name

    def prepare(self) -> None:
        """Connect or start up before `generate` touches OUT (a failure leaves OUT as it was)."""

    def close(self) -> None:
        """Release what `prepare` started."""

    def run(self, recipe, out: Path, tasks: list[ShardTask], limits: dict, on_samples: OnSamples | None = None,
            worker_lock: Path | None = None) -> Iterator[ShardDone]:
        """Make every task's shard in `out`; yield a ShardDone per finished shard. Calls
        `on_samples(path, n)` as samples are written (as often as the executor knows).
        Processes it starts on this machine hold a shared flock on `worker_lock` while they
        live (dofsynth.generate.locks). Raises ValueError for a user error inside a task (naming the
        shard), RuntimeError for a task that failed otherwise; when it returns or raises,
        nothing it started writes into `out` any more."""
        raise NotImplementedError


def _shard_error(task: ShardTask, exc: BaseException) -> Exception:
    if isinstance(exc, (ValueError, FileNotFoundError)):
        return ValueError(f"shard {task.path}: {exc}")
    return RuntimeError(f"shard {task.path} failed: {exc!r}")


# ----------------------------------------------------------------------------------- local
class LocalExecutor(Executor):
    """This machine: in-process for one worker (or one task), else a spawn process pool.
    `in_process=False` uses the pool even for one worker (a fresh process: benchmarks measure
    its peak memory)."""

    name = "local"

    def __init__(self, workers: int = 1, in_process: bool | None = None):
        if int(workers) != workers or workers < 1:
            raise ValueError(f"--workers must be an integer >= 1, got {workers}")
        self.workers = int(workers)
        self.in_process = in_process

    def describe(self) -> str:
        return f"local, {self.workers} worker{'s' if self.workers != 1 else ''}"

    def run(self, recipe, out, tasks, limits, on_samples=None, worker_lock=None):
        if self.in_process if self.in_process is not None else (self.workers == 1 or len(tasks) <= 1):
            yield from self._in_process(recipe, out, tasks, limits, on_samples)
        else:
            for t, info, seconds, rss in run_pool(self.workers, recipe, out, tasks, limits, on_samples, worker_lock):
                yield ShardDone(t, info, seconds, rss)

    @staticmethod
    def _in_process(recipe, out, tasks, limits, on_samples):
        library = library_for(recipe) if tasks else None
        for t in tasks:
            ts = time.perf_counter()
            try:
                info = generate_shard(recipe, out, t.split, t.index, limit=limits[t.split], library=library,
                                      on_sample=(lambda n, p=t.path: on_samples(p, n)) if on_samples else None)
            except (ValueError, FileNotFoundError) as exc:
                raise _shard_error(t, exc) from exc
            yield ShardDone(t, info, time.perf_counter() - ts, peak_rss_mb())


# ------------------------------------------------------------------------------------- ray
def ray_available() -> bool:
    try:
        import ray  # noqa: F401
    except ImportError:
        return False
    return True


def _ray_shard(recipe, library, out: str, split: str, index: int, limit: int | None,
               task_hook=None) -> tuple[ShardInfo, float, float]:
    """Ray task: (ShardInfo, seconds inside generate_shard, this worker's peak MiB so far).
    `library`: the driver's asset library (one object in Ray's store for all tasks), so no
    worker scans and hashes the asset folders again; the paths in it must be the same on every
    node (a shared file system), as the recipe's already are. `task_hook(split, index)` is
    called in the task after each sample is written (RayExecutor's `task_hook`)."""
    setup_process()  # a Ray worker process only runs such tasks
    t0 = time.perf_counter()
    on_sample = (lambda _n: task_hook(split, index)) if task_hook is not None else None
    info = generate_shard(recipe, out, split, index, limit=limit, library=library_for(recipe, library),
                          on_sample=on_sample)
    return info, time.perf_counter() - t0, peak_rss_mb()


class RayExecutor(Executor):
    """One Ray task per shard. `address`: None starts a local Ray instance for this run (unless
    Ray is already initialised in this process), "auto" or "HOST:PORT" joins a running cluster
    (`ray start --head`). `max_retries`: retries of a task whose worker died.
    `max_in_flight`: at most this many shard tasks submitted at once (None: all; Ray runs one
    per free CPU). `task_hook(split, shard_index)`: a picklable callable run inside each task
    after every sample it writes (fault injection, custom progress)."""

    name = "ray"

    def __init__(self, address: str | None = None, max_retries: int = 3, max_in_flight: int | None = None,
                 task_hook=None):
        if not ray_available():
            raise ValueError(f"--executor ray needs Ray, which is not installed; install it with: {RAY_INSTALL_HINT}")
        if int(max_retries) != max_retries or max_retries < 0:
            raise ValueError(f"--max-retries must be an integer >= 0, got {max_retries}")
        if max_in_flight is not None and (int(max_in_flight) != max_in_flight or max_in_flight < 1):
            raise ValueError(f"--workers must be an integer >= 1, got {max_in_flight}")
        self.address, self.max_retries, self.max_in_flight = address, int(max_retries), max_in_flight
        self.task_hook = task_hook

    def describe(self) -> str:
        return f"ray{' ' + self.address if self.address else ''}, max {self.max_retries} retries"

    _own = False

    def prepare(self) -> None:
        import ray

        if ray.is_initialized():
            return
        try:
            # Ray puts the driver's working folder first on its workers' sys.path: a folder there
            # named dofsynth/ (data, another checkout) would shadow this package. Every path a
            # task gets is absolute, so the driver joins from the folder that holds this package.
            here = os.getcwd()
            os.chdir(Path(__file__).resolve().parents[2])
            try:
                ray.init(address=self.address, include_dashboard=False, logging_level="WARNING")
            finally:
                os.chdir(here)
        except (ConnectionError, RuntimeError, ValueError) as exc:
            where = f"--address {self.address}" if self.address else "a local Ray instance"
            raise ValueError(f"--executor ray: cannot start or join {where}: {exc} (start a cluster with "
                             "`ray start --head`, then pass --address auto on that node)") from exc
        self._own = True

    def close(self) -> None:
        if self._own:
            import ray

            ray.shutdown()
            self._own = False

    def run(self, recipe, out, tasks, limits, on_samples=None, worker_lock=None):
        import ray

        self.prepare()
        remote = ray.remote(num_cpus=1, max_retries=self.max_retries, retry_exceptions=False)(_ray_shard)
        recipe_ref, library_ref = ray.put(recipe), ray.put(library_for(recipe))
        out = os.path.abspath(out)  # workers run elsewhere (another cwd, another node)
        window = self.max_in_flight or len(tasks) or 1
        todo, refs = list(tasks), {}
        try:
            def submit():
                while todo and len(refs) < window:
                    t = todo.pop(0)
                    refs[remote.remote(recipe_ref, library_ref, out, t.split, t.index, limits[t.split],
                                       self.task_hook)] = t

            submit()
            while refs:
                ready, _ = ray.wait(list(refs), num_returns=1)
                for ref in ready:
                    t = refs.pop(ref)
                    try:
                        info, seconds, rss = ray.get(ref)
                    except ray.exceptions.RayTaskError as exc:  # an exception inside generate_shard
                        raise _shard_error(t, getattr(exc, "cause", None) or exc) from exc
                    except ray.exceptions.RayError as exc:       # worker or node died, retries used up
                        raise RuntimeError(f"shard {t.path} failed after {self.max_retries} retries: {exc}; "
                                           "rerun with --resume to keep the finished shards") from exc
                    if on_samples is not None:
                        on_samples(t.path, info.samples)
                    yield ShardDone(t, info, seconds, rss)
                submit()
        finally:
            if refs:  # stopped early: cancel the rest and wait until none still writes into OUT
                for ref in refs:
                    try:
                        ray.cancel(ref, force=True)
                    except Exception:
                        pass
                try:
                    ray.wait(list(refs), num_returns=len(refs), timeout=30)
                except Exception:
                    pass


def make_executor(name: str = "local", *, workers: int | None = None, address: str | None = None,
                  max_retries: int = 3) -> Executor:
    """The executor the command line names. `workers`: local processes (default 1) or, for Ray,
    the most shard tasks in flight at once (default: all)."""
    if name == "local":
        if address is not None:
            raise ValueError("--address is for --executor ray")
        return LocalExecutor(1 if workers is None else workers)
    if name == "ray":
        return RayExecutor(address=address, max_retries=max_retries, max_in_flight=workers)
    raise ValueError(f"--executor {name!r}: expected one of {', '.join(EXECUTORS)}")
