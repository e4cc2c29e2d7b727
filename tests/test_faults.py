"""Faults injected from outside, as a scheduler, the OOM killer or a full disk would: every run
ends promptly with one line and a non-zero status, leaves no worker behind and no temp file,
and `--resume` then gives the bytes of an uninterrupted run."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from dofsynth.generate import generate
from dofsynth.recipe import load_recipe

from conftest import write_png

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def recipe_path(tmp_path_factory) -> Path:
    """The smoke recipe at 256 px in shards of 3 (6 train + 3 test): shards take long enough
    to be caught while they are written."""
    text = (ROOT / "recipes" / "smoke.toml").read_text(encoding="utf-8")
    for a, b in (("size = 64 ", "size = 256 "), ("shard_size = 2", "shard_size = 3"),
                 ("samples = { train = 6, test = 2 }", "samples = { train = 6, test = 3 }")):
        assert a in text
        text = text.replace(a, b)
    path = tmp_path_factory.mktemp("recipe") / "faults.toml"
    path.write_text(text, encoding="utf-8")
    return path


@pytest.fixture(scope="module")
def reference(recipe_path, tmp_path_factory) -> dict[str, bytes]:
    out = tmp_path_factory.mktemp("ref") / "data"
    generate(load_recipe(recipe_path), out, progress=False)
    return _files(out)


def _files(out: Path) -> dict[str, bytes]:
    return {str(p.relative_to(out)): p.read_bytes() for p in sorted(out.rglob("*")) if p.is_file()}


def _start(*args) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "dofsynth", *map(str, args)], cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _generate(recipe_path, out, *more) -> subprocess.Popen:
    return _start("generate", recipe_path, "--out", out, "--quiet", *more)


def _children(pid: int) -> list[int]:
    """Live worker processes (multiprocessing spawn children) of `pid`."""
    out = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
            cmd = (stat.parent / "cmdline").read_bytes()
        except (OSError, IndexError):
            continue
        if int(fields[1]) == pid and fields[0] != "Z" and b"spawn_main" in cmd:
            out.append(int(stat.parent.name))
    return out


def _alive(pid: int) -> bool:
    """Running (not a zombie waiting for init to reap it)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (OSError, IndexError):
        return False
    return state != "Z"


def _until(cond, timeout: float, step: float = 0.005):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        got = cond()
        if got:
            return got
        time.sleep(step)
    return None


def _temps(out: Path) -> list[Path]:
    """Every temp file in OUT (dofsynth.files' scheme)."""
    return [p for p in out.rglob(".*") if ".tmp-" in p.name]


def _shard_temps(out: Path) -> list[Path]:
    """Shards being written (`<split>/.<name>.tar.tmp-<pid of the writer>`)."""
    return [p for p in out.glob("*/.*.tar.tmp-*")]


def _ended(proc: subprocess.Popen, timeout: float = 300.0) -> tuple[int, str]:
    try:
        _, err = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        pytest.fail(f"the run did not end within {timeout} s of the fault")
    return proc.returncode, err


def _one_line(err: str) -> str:
    lines = [l for l in err.splitlines() if l.strip()]
    assert len(lines) == 1, err
    return lines[0]


def _resume_equals(recipe_path, out, reference) -> None:
    proc = _generate(recipe_path, out, "--resume", "--workers", "2")
    rc, err = _ended(proc, 600)
    assert rc == 0, err
    assert _files(out) == reference


@pytest.mark.parametrize("when", ["while starting", "mid-shard"])
def test_a_dead_worker_ends_the_run_promptly_and_resume_is_identical(recipe_path, reference, tmp_path, when):
    out = tmp_path / "out"
    proc = _generate(recipe_path, out, "--workers", "2")
    if when == "while starting":  # a worker is killed before it has imported anything
        victim = _until(lambda: _children(proc.pid), 300)
        assert victim
        victim = victim[0]
    else:  # killed while writing a shard (its temp file names its pid)
        temp = _until(lambda: _shard_temps(out), 300)
        assert temp, "no shard was ever being written"
        victim = int(temp[0].name.rsplit("-", 1)[1])
    os.kill(victim, signal.SIGKILL)
    t0 = time.monotonic()
    rc, err = _ended(proc)
    assert time.monotonic() - t0 < 60, "the run took more than 60 s to notice its dead worker (a hang)"
    line = _one_line(err)
    assert rc == 1 and f"worker process {victim} died (killed by SIGKILL)" in line and "--resume" in line, line
    assert not _children(proc.pid) and not _temps(out)
    _resume_equals(recipe_path, out, reference)


@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGTERM])
def test_the_parent_stopped_takes_its_workers_with_it(recipe_path, reference, tmp_path, sig):
    out = tmp_path / "out"
    proc = _generate(recipe_path, out, "--workers", "2")
    assert _until(lambda: _shard_temps(out), 300), "no shard was ever being written"
    workers = _children(proc.pid)
    assert workers
    proc.send_signal(sig)
    rc, err = _ended(proc)
    assert _until(lambda: not any(_alive(w) for w in workers), 30, 0.05), "workers outlived their parent"
    if sig == signal.SIGTERM:  # handled like Ctrl-C: an orderly stop
        line = _one_line(err)
        assert rc == 143 and "terminated (SIGTERM)" in line and "--resume" in line, line
        assert not _temps(out) and not (out / ".lock").exists()
    _resume_equals(recipe_path, out, reference)


def test_a_resume_killed_while_it_verifies_keeps_the_hashes(recipe_path, reference, tmp_path):
    """The recorded hashes stay until the verified ones are written: a corrupted shard found
    by one resume is remade by the next, however early the first one was killed."""
    out = _materialise(reference, tmp_path / "out")
    bad = out / "train" / "train-000001.tar"
    data = bytearray(bad.read_bytes())
    data[len(data) // 2] ^= 0xFF  # inside a PNG member: the tar still reads, the hash does not
    bad.write_bytes(bytes(data))
    proc = _generate(recipe_path, out, "--resume")
    assert _until(lambda: (out / ".lock").exists(), 300)
    proc.send_signal(signal.SIGKILL)
    proc.communicate()
    _resume_equals(recipe_path, out, reference)


def _materialise(files: dict[str, bytes], out: Path) -> Path:
    for rel, blob in files.items():
        (out / rel).parent.mkdir(parents=True, exist_ok=True)
        (out / rel).write_bytes(blob)
    return out


def test_a_resume_that_dies_after_verifying_leaves_no_corrupt_shard_behind(recipe_path, reference, tmp_path):
    """Deterministically: the rendering step fails at once, after the verification."""
    from dofsynth.generate import Executor

    class Dies(Executor):
        def run(self, *args, **kw):
            raise RuntimeError("the machine went away")
            yield

    out = _materialise(reference, tmp_path / "out")
    bad = out / "test" / "test-000000.tar"
    data = bytearray(bad.read_bytes())
    data[len(data) // 2] ^= 0xFF
    bad.write_bytes(bytes(data))
    recipe = load_recipe(recipe_path)
    with pytest.raises(RuntimeError, match="went away"):
        generate(recipe, out, resume=True, executor=Dies(), progress=False)
    assert not bad.exists()  # found corrupt: deleted, to be remade
    generate(recipe, out, resume=True, progress=False)
    assert _files(out) == reference


def test_a_resume_with_another_asset_library_is_refused_naming_the_change(tmp_path):
    from conftest import RECIPE_TEMPLATE, noise_rgb

    for i in range(2):
        write_png(tmp_path / "bg" / f"b{i}.png", noise_rgb(80, 96, i))
    text = RECIPE_TEMPLATE.format(size=32, backgrounds="bg", foregrounds="builtin", on_bad_asset="stop",
                                  verify="decode", manifest="")
    (tmp_path / "r.toml").write_text(text, encoding="utf-8")
    out = tmp_path / "out"
    proc = _start("generate", tmp_path / "r.toml", "--out", out, "--limit", "2", "--quiet")
    assert _ended(proc, 600)[0] == 0
    before = _files(out)
    write_png(tmp_path / "bg" / "b9.png", noise_rgb(80, 96, 9))  # one photo more
    rc, err = _ended(_start("generate", tmp_path / "r.toml", "--out", out, "--resume", "--quiet"), 600)
    line = _one_line(err)
    assert rc == 2 and "another asset library: 1 (bg/b9) added, 0 removed, 0 changed" in line, line
    assert _files(out) == before


def test_an_exr_asset_with_nan_is_skipped_by_name(tmp_path, write_recipe):
    from dofsynth.assets import build_library
    from dofsynth.io import write_exr

    from conftest import noise_rgb

    for i in range(2):
        write_png(tmp_path / "bg" / f"b{i}.png", noise_rgb(80, 96, i))
    img = np.full((80, 96, 3), 0.5, np.float32)
    img[10, 20, 1] = np.nan
    write_exr(tmp_path / "bg" / "nan.exr", img)
    big = np.full((80, 96, 3), 0.5, np.float32)
    big[3, 4, 0] = 1e30
    write_exr(tmp_path / "bg" / "huge.exr", big)
    lib = build_library(load_recipe(write_recipe(backgrounds="bg", on_bad_asset="skip")))
    skipped = dict(lib.skipped)
    assert [a.id for a in lib.backgrounds] == ["bg/b0", "bg/b1"]
    assert "NaN or inf" in skipped[str(tmp_path / "bg" / "nan.exr")]
    assert "beyond" in skipped[str(tmp_path / "bg" / "huge.exr")]


def test_a_full_disk_ends_the_run_with_one_line_and_it_resumes(tmp_path):
    disk = tmp_path / "disk"
    disk.mkdir()
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=160k", "tmpfs", str(disk)], capture_output=True)
    if mounted.returncode != 0:
        pytest.skip(f"cannot mount a small tmpfs here: {mounted.stderr.decode().strip() or 'not permitted'}")
    try:
        smoke = ROOT / "recipes" / "smoke.toml"
        out = disk / "out"
        rc, err = _ended(_start("generate", smoke, "--out", out, "--quiet"), 600)
        line = _one_line(err)
        assert rc == 1 and "No space left on device" in line and "--resume" in line, line
        assert not _temps(out)
        subprocess.run(["mount", "-o", "remount,size=20m", str(disk)], check=True)
        rc, err = _ended(_start("generate", smoke, "--out", out, "--resume", "--quiet"), 600)
        assert rc == 0, err
        ref = tmp_path / "ref"
        generate(load_recipe(smoke), ref, progress=False)
        assert _files(out) == _files(ref)
    finally:
        subprocess.run(["umount", "-l", str(disk)], capture_output=True)


# ------------------------------------------------------------------------------ training
def _train_setup(tmp_path, **train):
    from test_train_data import make_dataset

    from dofsynth.train.config import to_toml
    from test_train_data import tiny_config

    data = make_dataset(tmp_path / "data", n_train=8, n_test=2, size=48, per_shard=4)
    cfg = tiny_config(train=train)
    (tmp_path / "cfg.toml").write_text(to_toml(cfg), encoding="utf-8")
    return data, tmp_path / "cfg.toml", tmp_path / "run"


def _rewrite_recorded(data: Path, shard: Path, samples) -> None:
    """Write `samples` as `shard` and record its new hash and size in the manifest."""
    import json

    from dofsynth.files import canonical_json
    from dofsynth.shards import write_shard

    _, sha, nbytes = write_shard(shard, samples)
    manifest = json.loads((data / "manifest.json").read_text())
    for block in manifest["splits"].values():
        for s in block["shards"]:
            if data / s["path"] == shard:
                s["sha256"], s["bytes"] = sha, nbytes
    (data / "manifest.json").write_bytes(canonical_json(manifest, indent=1))


def test_a_nan_shard_stops_training_by_name_and_the_checkpoint_stays(tmp_path):
    from dofsynth.codecs import encode_depth
    from dofsynth.shards import read_shard

    data, cfg, run = _train_setup(tmp_path, max_steps=4, checkpoint_interval=2, eval_interval=0)
    rc, err = _ended(_start("train", cfg, "--data", data, "--run", run, "--steps", "2"), 600)
    assert rc == 0, err
    good = (run / "ckpt.pt").read_bytes()
    shard = data / "train" / "train-000001.tar"
    samples = list(read_shard(shard))
    key, members = samples[1]
    depth = np.full((48, 48), np.nan, np.float32)
    samples[1] = (key, {**members, "depth.exr": encode_depth(depth)})
    _rewrite_recorded(data, shard, samples)   # a set made with NaN: its manifest agrees with it
    rc, err = _ended(_start("train", cfg, "--data", data, "--run", run), 600)
    line = _one_line(err)
    assert rc == 2 and str(shard) in line and key in line and "NaN" in line, err
    assert (run / "ckpt.pt").read_bytes() == good


def test_a_non_finite_loss_names_the_batch_and_keeps_the_checkpoint():
    import torch

    from dofsynth.train.loop import check_finite

    batch = {"key": ["train-0000001", "train-0000002"], "shard": ["a.tar", "b.tar"],
             "image": torch.zeros(2, 3, 4, 4), "target": torch.zeros(2, 3, 4, 4), "signed_lo": torch.zeros(2, 1, 2, 2)}
    batch["signed_lo"][1, 0, 0, 0] = float("inf")
    check_finite(torch.tensor(0.5), batch, 9, 8)
    with pytest.raises(ValueError, match=r"step 10: the loss is nan \(NaN or inf in the inputs of train-0000002 "
                                         r"\(b.tar\)\); the checkpoint of step 8 is kept"):
        check_finite(torch.tensor(float("nan")), batch, 9, 8)


def test_a_training_run_killed_before_its_first_log_row_resumes(tmp_path):
    data, cfg, run = _train_setup(tmp_path, max_steps=6, log_interval=1000, checkpoint_interval=2, eval_interval=0)
    proc = _start("train", cfg, "--data", data, "--run", run)
    assert _until(lambda: (run / "log.csv").exists(), 600), "the run wrote no log.csv in 10 minutes"
    proc.send_signal(signal.SIGKILL)
    proc.communicate()
    rc, err = _ended(_start("train", cfg, "--data", data, "--run", run), 600)
    assert rc == 0, err
    rows = (run / "log.csv").read_text().splitlines()
    assert rows[0].startswith("step,") and rows[-1].startswith("6,"), rows


@pytest.mark.parametrize("workers", [2, 6])
def test_ctrl_c_while_workers_start_prints_one_line(recipe_path, tmp_path, workers):
    """A terminal's Ctrl-C reaches the whole process group: the workers, still starting, must
    not print a traceback each; the run stops with one line naming --resume. With more workers
    than cores the key comes while the parent is still spawning the later ones."""
    import os

    long = tmp_path / "long.toml"   # enough samples that the run cannot end before the signal
    long.write_text(recipe_path.read_text().replace("samples = { train = 6, test = 3 }",
                                                    "samples = { train = 60, test = 3 }"))
    out = tmp_path / "out"
    proc = subprocess.Popen([sys.executable, "-m", "dofsynth", "generate", str(long), "--out", str(out),
                             "--quiet", "--workers", str(workers)], cwd=ROOT, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True,
                            preexec_fn=_as_from_a_terminal)
    assert _until(lambda: _children(proc.pid), 300, 0.01), "no worker started"
    os.killpg(proc.pid, signal.SIGINT)
    rc, err = _ended(proc)
    line = _one_line(err)
    assert rc == 130 and "interrupted" in line and "--resume" in line, line
    assert "Traceback" not in err


# ------------------------------------------------------------------------------ start-up
def _session_procs(sid: int) -> list[int]:
    """Live (not zombie) processes of session `sid`: a run started with start_new_session,
    its workers and the multiprocessing resource tracker."""
    out = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except (OSError, IndexError):
            continue
        if int(fields[3]) == sid and fields[0] != "Z":
            out.append(int(stat.parent.name))
    return out


def _long_recipe(recipe_path, tmp_path) -> Path:
    long = tmp_path / "long.toml"   # enough samples that the run cannot end before the signal
    long.write_text(recipe_path.read_text().replace("samples = { train = 6, test = 3 }",
                                                    "samples = { train = 60, test = 3 }"))
    return long


def _as_from_a_terminal() -> None:
    """In the child, before exec: SIGINT and SIGTERM with their default actions and unblocked,
    as a shell on a terminal starts a program. A test run may have inherited them otherwise
    (started in the background: SIGINT ignored; by a supervisor: signals blocked), and an
    inherited block would make `_holds_stop_signals` true before dofsynth's own line runs."""
    for s in (signal.SIGINT, signal.SIGTERM):
        signal.signal(s, signal.SIG_DFL)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT, signal.SIGTERM})


def _holds_stop_signals(pid: int) -> bool:
    """Whether process `pid` runs dofsynth (it has exec'd: the forked test process before it
    has the test's own handlers) and blocks or catches both SIGINT and SIGTERM (/proc/PID/status)."""
    try:
        if b"-m\0dofsynth" not in Path(f"/proc/{pid}/cmdline").read_bytes():
            return False
        fields = dict(line.split(":", 1) for line in Path(f"/proc/{pid}/status").read_text().splitlines() if ":" in line)
    except OSError:
        return False
    held = int(fields.get("SigBlk", "0").strip(), 16) | int(fields.get("SigCgt", "0").strip(), 16)
    want = (1 << (signal.SIGINT - 1)) | (1 << (signal.SIGTERM - 1))
    return held & want == want


def _session_run(*args, env=None) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "dofsynth", *map(str, args)], cwd=ROOT, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True, preexec_fn=_as_from_a_terminal,
                            env=env)


@pytest.mark.parametrize("phase", ["0.2 s", "0.6 s", "1.2 s", "workers importing", "workers rendering"])
def test_a_parent_killed_at_any_start_up_phase_leaves_no_process(recipe_path, tmp_path, phase):
    """SIGKILL of the parent while it imports, builds the library, spawns its workers, while
    they import and while they render: 2 s later nothing of the run is left (workers are
    bound to their parent before their heavy imports; the resource tracker follows them), and
    once both workers render, not the library's temp file either (removed when they had read it)."""
    out, temp = tmp_path / "out", tmp_path / "temp"
    temp.mkdir()
    proc = _session_run("generate", _long_recipe(recipe_path, tmp_path), "--out", out, "--quiet", "--workers", "2",
                        env={**os.environ, "TMPDIR": str(temp)})
    if phase == "workers importing":
        assert _until(lambda: _children(proc.pid), 300, 0.002), "no worker started"
    elif phase == "workers rendering":  # both of them: each has loaded the library
        assert _until(lambda: len(_shard_temps(out)) == 2, 300), "the two workers never rendered at once"
    else:
        time.sleep(float(phase.split()[0]))
    os.kill(proc.pid, signal.SIGKILL)
    proc.communicate()
    t0 = time.monotonic()
    left = _until(lambda: not _session_procs(proc.pid), 2.0, 0.02)
    assert left, f"{_session_procs(proc.pid)} still running {time.monotonic() - t0:.1f} s after the parent died"
    if phase == "workers rendering":
        assert not list(temp.glob("dofsynth-pool-*")), "the library's temp folder outlived the run"


def test_a_library_folder_left_by_a_killed_run_is_removed_by_the_next(tmp_path, monkeypatch):
    """A parent killed with SIGKILL before its workers had read the library cannot remove its
    temp folder; the next run removes every such folder whose process is gone, and leaves a
    live run's (and any folder not named after a pid) alone."""
    import tempfile

    from dofsynth.generate import pool

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    dead = int(subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True,
                              text=True, check=True).stdout)
    stale = tmp_path / f"dofsynth-pool-{dead}-k1ll"
    stale.mkdir()
    (stale / "library.pkl").write_bytes(b"\0" * 1024)
    live = tmp_path / f"dofsynth-pool-{os.getppid()}-l1ve"
    live.mkdir()
    unnamed = tmp_path / "dofsynth-pool-x1y2z3"
    unnamed.mkdir()
    new = Path(pool.pool_folder())
    assert not stale.exists() and live.exists() and unnamed.exists()
    assert new.parent == tmp_path and new.name.startswith(f"dofsynth-pool-{os.getpid()}-")


@pytest.mark.parametrize("delay", [0.1, 0.5, 1.0, 2.0])
@pytest.mark.parametrize("sig,rc,word", [(signal.SIGINT, 130, "interrupted"), (signal.SIGTERM, 143, "terminated")])
def test_an_early_signal_ends_the_run_with_one_line(recipe_path, tmp_path, delay, sig, rc, word):
    """Ctrl-C or SIGTERM while the command line still imports its commands, builds the library
    or starts workers: one line, exit 130 / 143, no traceback. `delay` counts from dofsynth's
    first line (the entry point holds both signals from there): before it the interpreter is
    still starting, where no program can handle a signal, and that can take long on a busy
    machine."""
    proc = _session_run("generate", _long_recipe(recipe_path, tmp_path), "--out", tmp_path / "out", "--quiet",
                        "--workers", "2")
    assert _until(lambda: _holds_stop_signals(proc.pid), 120), "dofsynth never started"
    time.sleep(delay)
    os.killpg(proc.pid, sig)
    got, err = _ended(proc)
    assert got == rc and "Traceback" not in err, (got, err)
    assert word in _one_line(err)


def test_a_billion_sample_recipe_is_refused_by_name_and_the_plan_costs_no_memory(tmp_path):
    text = (ROOT / "recipes" / "smoke.toml").read_text()
    huge = tmp_path / "huge.toml"
    huge.write_text(text.replace("samples = { train = 6, test = 2 }", "samples = { train = 1000000000, test = 2 }"))
    big = tmp_path / "big.toml"   # the most the sample keys address, in shards of 1000
    big.write_text(text.replace("samples = { train = 6, test = 2 }", "samples = { train = 10000000, test = 2 }")
                   .replace("shard_size = 2", "shard_size = 1000"))
    # the peak RSS of this process image (VmHWM; ru_maxrss would count the forked test process)
    probe = ("import sys; from dofsynth.cli import main; rc = main(sys.argv[1:]); "
             "print('maxrss_kb', [l.split()[1] for l in open('/proc/self/status') if l.startswith('VmHWM')][0]); "
             "sys.exit(rc)")
    for recipe, want_rc in ((huge, 2), (big, 0)):
        t0 = time.monotonic()
        proc = subprocess.run([sys.executable, "-c", probe, "generate", str(recipe), "--plan"], cwd=ROOT,
                              capture_output=True, text=True, timeout=600)
        seconds = time.monotonic() - t0
        assert proc.returncode == want_rc, proc.stderr
        rss_mb = int(proc.stdout.split("maxrss_kb")[1].split()[0]) / 1024
        assert rss_mb < 300, rss_mb
        if recipe == huge:
            line = _one_line(proc.stderr)
            assert "samples.train" in line and "10000000" in line and "--resume" not in line, line
        else:
            assert "--shards 0:10000" in proc.stdout and "10000000 samples" in proc.stdout, proc.stdout
        assert seconds < 60, seconds   # a hang detector: it answers in about a second


# ------------------------------------------------------------------------------ hostile files
def _png_chunk(kind: bytes, data: bytes) -> bytes:
    import struct
    import zlib

    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def _png_of_size(w: int, h: int, rows: int = 1) -> bytes:
    import struct
    import zlib

    idat = zlib.compress(b"\x00" * (w + 1) * rows, 9)  # a bomb: huge pixels from a few bytes
    return (b"\x89PNG\r\n\x1a\n" + _png_chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 0, 0, 0, 0))
            + _png_chunk(b"IDAT", idat) + _png_chunk(b"IEND", b""))


@pytest.mark.parametrize("kind", ["bomb", "wide", "bad crc", "truncated"])
def test_a_hostile_png_is_one_line_naming_it(tmp_path, kind):
    from dofsynth.io import write_exr

    data = {"bomb": _png_of_size(50000, 50000, rows=64), "wide": _png_of_size(2_000_000, 4),
            "bad crc": _png_of_size(64, 64)[:-5] + b"\x00\x00\x00\x00\x00",
            "truncated": _png_of_size(64, 64, rows=64)[:70]}[kind]
    photo = tmp_path / "photo.png"
    photo.write_bytes(data)
    depth = tmp_path / "d.exr"
    write_exr(depth, np.full((8, 8), 0.5, np.float32))
    rc, err = _ended(_start("render", photo, "--depth", depth, "--focus", "0.5", "--max-coc", "2",
                            "--out", tmp_path / "o.png"))
    line = _one_line(err)
    assert rc == 2 and str(photo) in line and "libpng" not in err, err


def test_a_crafted_pickle_given_as_model_never_runs(tmp_path):
    """The payload would create a file while it is unpickled; a weights-only load refuses it."""
    import pickle

    import torch

    from dofsynth.io import write_exr, write_png

    flag = tmp_path / "pwned"

    class Payload:
        def __reduce__(self):
            return (os.system, (f"touch {flag}",))

    run = tmp_path / "run"
    run.mkdir()
    torch.save({"model": Payload(), "config": {}, "format": 2}, run / "ckpt.pt")
    raw = tmp_path / "raw.pt"
    raw.write_bytes(pickle.dumps(Payload()))
    text = tmp_path / "notes.txt"
    text.write_text("not a checkpoint\n")
    photo, depth = tmp_path / "p.png", tmp_path / "d.exr"
    write_png(photo, np.full((16, 16, 3), 0.5, np.float32))
    write_exr(depth, np.full((16, 16), 0.5, np.float32))
    for model in (run, raw, text):
        rc, err = _ended(_start("render", photo, "--depth", depth, "--focus", "0.5", "--model", model,
                                "--out", tmp_path / "o.png"))
        line = _one_line(err)
        assert rc == 2 and "not a dofsynth checkpoint" in line, err
        assert not flag.exists(), f"loading {model} ran its payload"


@pytest.mark.parametrize("wrap", ["plain", "model", "state_dict", "module.", "model+module."])
def test_depth_weights_in_common_wrappers_load_and_junk_is_one_line(tmp_path, wrap):
    import torch

    from dofsynth.train.config import DepthConfig
    from dofsynth.train.depth import DepthNet, load_backbone

    cfg = DepthConfig(backbone="resnet18", width=8, decoder_width=16)
    model = DepthNet(cfg)
    sd = {k: v.clone() + 1.0 if v.is_floating_point() else v for k, v in model.encoder.state_dict().items()}
    state = {f"module.{k}": v for k, v in sd.items()} if wrap.endswith("module.") else sd
    if wrap.startswith(("model", "state_dict")):
        state = {wrap.split("+")[0]: state, "epoch": 3}
    path = tmp_path / "w.pth"
    torch.save(state, path)
    fresh = DepthNet(cfg)
    assert load_backbone(fresh, path) == len(sd)
    got = fresh.encoder.state_dict()
    assert all(torch.equal(got[k], sd[k]) for k in sd)
    junk = tmp_path / "junk.pth"
    junk.write_bytes(b"PK\x03\x04" + b"\x00" * 64)
    for bad in (junk, tmp_path / "w.txt"):
        if bad.suffix == ".txt":
            bad.write_text("hello")
        with pytest.raises(ValueError) as info:
            load_backbone(fresh, bad)
        assert "\n" not in str(info.value) and str(bad) in str(info.value) and "weights_only" not in str(info.value)


# ------------------------------------------------------------------------------ kept shards
def test_a_damaged_shard_that_was_never_recorded_is_remade_on_resume(recipe_path, reference, tmp_path, monkeypatch):
    """Killed between a shard's rename and its progress line, then the shard damaged: the resume
    cannot prove its bytes, so it remakes it (the old code kept it on its sample keys and wrote
    its bad hash into the manifest)."""
    import dofsynth.generate.run as run_mod

    real = run_mod.append_progress
    state = {"n": 0}

    def killed_after_the_rename(out, info, *a, **k):
        state["n"] += 1
        if state["n"] == 2:      # the second shard is renamed; its line never written
            raise KeyboardInterrupt
        return real(out, info, *a, **k)

    monkeypatch.setattr(run_mod, "append_progress", killed_after_the_rename)
    out = tmp_path / "out"
    with pytest.raises(KeyboardInterrupt):
        generate(load_recipe(recipe_path), out, progress=False)
    monkeypatch.setattr(run_mod, "append_progress", real)
    recorded = (out / ".progress.jsonl").read_text()
    unrecorded = [p for p in (out / "train").glob("*.tar") if p.name not in recorded]
    assert len(unrecorded) == 1
    data = bytearray(unrecorded[0].read_bytes())
    data[2000] ^= 0xFF                      # inside the first member's data: the keys still read
    unrecorded[0].write_bytes(bytes(data))
    generate(load_recipe(recipe_path), out, resume=True, progress=False)
    assert _files(out) == reference


@pytest.mark.parametrize("workers", [0, 2])
def test_training_stops_on_a_shard_whose_hash_differs(tmp_path, workers):
    """A member that decodes to the same pixels but other bytes (another zlib level): nothing
    in training would notice, the hash does, in the training process or a loader worker."""
    from dofsynth.io import decode_image, encode_png
    from dofsynth.shards import read_shard, write_shard

    data, cfg, run = _train_setup(tmp_path, max_steps=2, checkpoint_interval=2, eval_interval=0)
    cfg.write_text(cfg.read_text().replace("num_workers = 0", f"num_workers = {workers}"))
    shard = data / "train" / "train-000001.tar"
    samples = list(read_shard(shard))
    key, members = samples[-1]
    aif = decode_image(members["aif.png"], "aif.png", raw=True)
    samples[-1] = (key, {**members, "aif.png": encode_png(aif, compression=9)})
    write_shard(shard, samples)
    rc, err = _ended(_start("train", cfg, "--data", data, "--run", run, "--quiet"), 600)
    line = _one_line(err)
    assert rc == 2 and str(shard) in line and "sha256" in line, err


def test_symlinks_in_asset_folders_are_followed_and_listed(tmp_path, tiny_bg_dir, tiny_cutouts, write_recipe, capsys):
    """The rule: links to files and folders are followed and listed; a folder link back into
    the tree is not walked twice (no loop, no file twice)."""
    from dofsynth.assets import build_library
    from dofsynth.cli import main

    outside = tmp_path / "elsewhere"
    write_png(outside / "linked-file.png", np.full((90, 100, 3), 0.3, np.float32))
    write_png(outside / "folder" / "in-linked-folder.png", np.full((96, 96, 3), 0.6, np.float32))
    (tiny_bg_dir / "lf.png").symlink_to(outside / "linked-file.png")
    (tiny_bg_dir / "ld").symlink_to(outside / "folder", target_is_directory=True)
    (tiny_bg_dir / "sub" / "loop").symlink_to(tiny_bg_dir, target_is_directory=True)
    recipe_file = write_recipe(backgrounds=tiny_bg_dir, foregrounds=tiny_cutouts)
    lib = build_library(load_recipe(recipe_file))
    ids = {a.id for a in lib.backgrounds}
    assert {"bg/lf", "bg/ld/in-linked-folder"} <= ids and len(ids) == 7   # 5 files + 2 reached by links
    listed = {Path(p).name: t for p, t in lib.links}
    assert listed["lf.png"] == str((outside / "linked-file.png").resolve()) and "ld" in listed and "loop" in listed
    assert main(["assets", "check", str(recipe_file)]) == 0
    out = capsys.readouterr().out
    assert "followed 3 symbolic links" in out and "lf.png ->" in out
