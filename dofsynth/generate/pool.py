"""The local process pool of `generate --workers N`: spawn workers, one pipe each, that render
the shards they are handed and die with their parent.

Fault behaviour, by design:
- Start-up arguments are small (the recipe and paths): the asset library is pickled once into
  a private temp file that each worker maps (`write_shared` / `read_shared`), so a worker that
  dies while starting never leaves the parent blocked writing a large pickle into its pipe.
  Its arrays (25 MB of pixels for the built-in assets) lie page-aligned outside the pickle and
  every worker's copy of the library uses them in place: one copy in the page cache for all
  workers, copied page by page only where one writes. The file is removed as soon as every
  worker has mapped it (the mappings outlive the name), so a parent killed while they render
  leaves nothing in the temp folder.
- The parent waits on every worker's pipe and process sentinel at once: a worker that dies
  at any moment (killed, out of memory) ends the run as soon as the parent is scheduled
  (0.2-0.5 s measured on 2 cores, docs/generate.md) with `WorkerDied` naming it and its
  shard; the other workers are terminated at once and joined before the run lets go of OUT's
  lock, so nothing writes into OUT after it.
- Workers die with their parent, from their first instant: their target is
  dofsynth.spawned.main, which arms a parent-death signal (SIGKILL; elsewhere a thread
  watching the parent's pid) before anything heavy is imported or unpickled, so a parent
  killed at any moment of the start-up leaves no worker behind. They also hold a shared flock on
  `<run lock>.workers`, which a later run of the same OUT checks (dofsynth.generate.locks), so the
  promise "no two runs write into OUT at once" holds even against a straggler.
- Workers ignore SIGINT: they start with it blocked (the parent blocks it while it spawns
  them, and a signal mask survives exec), so a Ctrl-C while they import stays pending, and
  they discard it by ignoring SIGINT before unblocking it. The parent holds its own Ctrl-C
  back until the workers are started, then stops the run and prints one line, however
  early the key was pressed.
"""
from __future__ import annotations

import mmap
import multiprocessing as mp
import os
import pickle
import shutil
import signal
import tempfile
import threading
import time
import traceback
from contextlib import contextmanager
from functools import partial
from multiprocessing import resource_tracker
from multiprocessing.connection import wait
from pathlib import Path

from dofsynth import spawned, stops
from dofsynth.generate.plan import ShardTask
from dofsynth.generate.worker import generate_shard, library_for, peak_rss_mb, setup_process


class WorkerDied(RuntimeError):
    """A worker process ended without finishing its shard (killed, out of memory, crashed)."""


def _worker_main(conn, recipe, out: str, library_path: str) -> None:
    """A worker's loop, run by dofsynth.spawned.main once the worker is bound to its
    parent: render the shards it is handed until it is told to stop (None)."""
    setup_process()
    library = library_for(recipe, read_shared(library_path))
    conn.send(("ready",))
    while (msg := conn.recv()) is not None:
        task, limit = msg
        t0 = time.perf_counter()
        try:
            info = generate_shard(recipe, out, task.split, task.index, limit=limit, library=library,
                                  on_sample=lambda n, p=task.path: conn.send(("sample", p, n)))
        except (ValueError, FileNotFoundError) as exc:  # a user error (a bad asset): named, not retried
            conn.send(("error", task.path, "user", str(exc)))
            return
        except BaseException as exc:
            conn.send(("error", task.path, "crash", "".join(traceback.format_exception_only(exc)).strip()))
            return
        conn.send(("done", task.path, info, time.perf_counter() - t0, peak_rss_mb()))


@contextmanager
def _sigint_deferred():
    """Spawn workers inside: they begin with SIGINT blocked (this thread's mask survives fork
    and exec), and a Ctrl-C meanwhile is held back and raised here on exit, so it can neither
    interrupt a half-started worker nor be lost. The mask alone is not enough in the parent:
    the kernel hands the signal to any thread not blocking it, so the handler defers it too.
    The resource tracker is started first, as its own start unblocks SIGINT."""
    resource_tracker.ensure_running()
    caught = []
    main = threading.current_thread() is threading.main_thread()
    old_handler = signal.signal(signal.SIGINT, lambda *_: caught.append(1)) if main else None
    old_mask = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        if main:
            signal.signal(signal.SIGINT, old_handler)
        signal.pthread_sigmask(signal.SIG_SETMASK, old_mask)
        if caught:
            signal.raise_signal(signal.SIGINT)


def _how_it_ended(p) -> str:
    code = p.exitcode
    if code is not None and code < 0:
        try:
            return f"killed by {signal.Signals(-code).name}"
        except ValueError:
            return f"killed by signal {-code}"
    return f"exit status {code}"


POOL_PREFIX = "dofsynth-pool-"  # temp folders holding a run's pickled library: dofsynth-pool-PID-*
_PAGE = mmap.ALLOCATIONGRANULARITY


def write_shared(path: str | os.PathLike, obj) -> None:
    """Pickle `obj` into a new file at `path` with its buffers (numpy arrays' data) out of band
    (pickle protocol 5), each at a page-aligned offset from 0, then the pickle and the buffers'
    spans, then that part's length (8 bytes, little-endian): what `read_shared` maps."""
    buffers: list = []
    meta = pickle.dumps(obj, protocol=5, buffer_callback=buffers.append)
    spans, offset = [], 0
    with open(path, "wb") as fh:
        for buf in buffers:
            raw = buf.raw()
            fh.seek(offset)
            fh.write(raw)
            spans.append((offset, raw.nbytes))
            offset += -(-raw.nbytes // _PAGE) * _PAGE
        fh.seek(offset)
        index = pickle.dumps((meta, spans), protocol=5)
        fh.write(index)
        fh.write(len(index).to_bytes(8, "little"))


def read_shared(path: str | os.PathLike):
    """The object `write_shared` wrote to `path`, its buffers in place in a private
    (copy-on-write) mapping of the file: processes that read the same file share those pages
    until one writes to them. The mapping stays valid after the file is removed."""
    with open(path, "rb") as fh:
        mm = mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_COPY)
    n = int.from_bytes(mm[-8:], "little")
    meta, spans = pickle.loads(mm[len(mm) - 8 - n : len(mm) - 8])
    view = memoryview(mm)
    return pickle.loads(meta, buffers=[view[o : o + k] for o, k in spans])


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's process
        return True
    return True


def pool_folder() -> str:
    """A new temp folder for this run's library, named after this process's pid. Folders of
    runs whose process is gone are removed first: a parent killed with SIGKILL before its
    workers had read the library cannot remove its own (25 MB with the built-in assets)."""
    for old in Path(tempfile.gettempdir()).glob(POOL_PREFIX + "*-*"):
        pid = old.name[len(POOL_PREFIX):].split("-", 1)[0]
        if pid.isdigit() and int(pid) != os.getpid() and not _alive(int(pid)):
            shutil.rmtree(old, ignore_errors=True)
    return tempfile.mkdtemp(prefix=f"{POOL_PREFIX}{os.getpid()}-")


def run_pool(workers: int, recipe, out, tasks: list[ShardTask], limits: dict, on_samples=None,
             worker_lock: str | os.PathLike | None = None):
    """Render `tasks` with `workers` spawn processes; yield (task, info, seconds, peak MiB) per
    finished shard. Raises ValueError for a user error in a shard, WorkerDied for a worker
    that died or crashed; on any exit every worker is stopped and joined first."""
    ctx = mp.get_context("spawn")
    n = min(workers, len(tasks))
    tmp = pool_folder()
    drop = partial(shutil.rmtree, tmp, ignore_errors=True)
    try:
        lib_path = Path(tmp) / "library.pkl"
        write_shared(lib_path, library_for(recipe))
        payload = pickle.dumps((_worker_main, (recipe, str(out), str(lib_path))))  # unpickled once bound
        procs, conns, finished = [], [], False
        try:
            with _sigint_deferred():
                for _ in range(n):
                    parent_end, child_end = ctx.Pipe()
                    p = ctx.Process(target=spawned.main, daemon=True, name="dofsynth-worker",
                                    args=(child_end, os.getpid(), None if worker_lock is None else str(worker_lock),
                                          payload))
                    p.start()
                    child_end.close()
                    procs.append(p)
                    conns.append(parent_end)
            yield from _dispatch(procs, conns, list(tasks), limits, on_samples, all_ready=drop)
            finished = True
        finally:
            _stop(procs, conns, finished)
    finally:
        drop()


def _dispatch(procs, conns, todo: list[ShardTask], limits: dict, on_samples, all_ready=None):
    """Hand out the shards and yield the finished ones; `all_ready()` is called once every
    worker has loaded the library (its temp file is then no longer needed: a run killed later
    leaves none behind)."""
    by_path = {t.path: t for t in todo}
    busy: dict[int, ShardTask | None] = {i: None for i in range(len(procs))}  # worker -> its shard
    idle: set[int] = set()
    ready: set[int] = set()
    left = len(todo)

    def handle(i, msg):
        """A worker's message; returns a finished shard's (task, info, seconds, MiB) or None."""
        nonlocal left
        kind = msg[0]
        if kind == "ready":
            idle.add(i)
            ready.add(i)
            if len(ready) == len(procs) and all_ready is not None:
                all_ready()
        elif kind == "sample":
            if on_samples is not None:
                on_samples(msg[1], msg[2])
        elif kind == "done":
            _, path, info, seconds, rss = msg
            busy[i] = None
            idle.add(i)
            left -= 1
            return by_path[path], info, seconds, rss
        elif msg[2] == "user":  # "error": a user error (a bad asset) names the shard
            raise ValueError(f"shard {msg[1]}: {msg[3]}")
        else:
            raise WorkerDied(f"a worker crashed making shard {msg[1]}: {msg[3]}")
        return None

    while left:
        stops.check()  # a Ctrl-C whose exception was lost on its way (dofsynth.stops) stops here
        for i in sorted(idle):
            if todo:
                t = todo.pop(0)
                conns[i].send((t, limits[t.split]))
                busy[i] = t
                idle.discard(i)
        for r in wait([*conns, *(p.sentinel for p in procs)], timeout=1.0):
            i = conns.index(r) if r in conns else next(k for k, p in enumerate(procs) if p.sentinel == r)
            while conns[i].poll():  # what it said before it ended comes first
                try:
                    done = handle(i, conns[i].recv())
                except (EOFError, OSError):
                    break
                if done is not None:
                    yield done
            if r not in conns and left:
                p = procs[i]
                p.join(0.1)
                task = busy.get(i)
                where = f"while making shard {task.path}" if task is not None else "while starting"
                raise WorkerDied(f"worker process {p.pid} died ({_how_it_ended(p)}) {where}")


def _stop(procs, conns, finished: bool) -> None:
    """End the workers and join them all, so that nothing writes into OUT after this returns:
    after a finished run they are told to stop (all idle); after a failure (a dead worker, an
    error, Ctrl-C) they are terminated at once (a shard in hand is dropped: a temp file at
    most), so the run ends as soon as it has noticed."""
    if finished:
        for c in conns:
            try:
                c.send(None)
            except (OSError, ValueError):
                pass
        deadline = time.monotonic() + 5.0
        for p in procs:
            p.join(max(0.0, deadline - time.monotonic()))
    for p in procs:
        if p.is_alive():
            p.terminate()
    for p in procs:
        p.join(5.0)
        if p.is_alive():
            p.kill()
            p.join()
    for c in conns:
        c.close()
