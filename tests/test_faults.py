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


def _ended(proc: subprocess.Popen, timeout: float = 20.0) -> tuple[int, str]:
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
    rc, err = _ended(proc, 60)
    assert rc == 0, err
    assert _files(out) == reference


@pytest.mark.parametrize("when", ["while starting", "mid-shard"])
def test_a_dead_worker_ends_the_run_promptly_and_resume_is_identical(recipe_path, reference, tmp_path, when):
    out = tmp_path / "out"
    proc = _generate(recipe_path, out, "--workers", "2")
    if when == "while starting":  # a worker is killed before it has imported anything
        victim = _until(lambda: _children(proc.pid), 30)
        assert victim
        victim = victim[0]
    else:  # killed while writing a shard (its temp file names its pid)
        temp = _until(lambda: _shard_temps(out), 60)
        assert temp, "no shard was ever being written"
        victim = int(temp[0].name.rsplit("-", 1)[1])
    os.kill(victim, signal.SIGKILL)
    t0 = time.monotonic()
    rc, err = _ended(proc)
    assert time.monotonic() - t0 < 10, "the run took more than 10 s to notice its dead worker"
    line = _one_line(err)
    assert rc == 1 and f"worker process {victim} died (killed by SIGKILL)" in line and "--resume" in line, line
    assert not _children(proc.pid) and not _temps(out)
    _resume_equals(recipe_path, out, reference)


@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGTERM])
def test_the_parent_stopped_takes_its_workers_with_it(recipe_path, reference, tmp_path, sig):
    out = tmp_path / "out"
    proc = _generate(recipe_path, out, "--workers", "2")
    assert _until(lambda: _shard_temps(out), 60), "no shard was ever being written"
    workers = _children(proc.pid)
    assert workers
    proc.send_signal(sig)
    rc, err = _ended(proc)
    assert _until(lambda: not any(_alive(w) for w in workers), 5, 0.05), "workers outlived their parent"
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
    assert _until(lambda: (out / ".lock").exists(), 30)
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
    assert _ended(proc, 60)[0] == 0
    before = _files(out)
    write_png(tmp_path / "bg" / "b9.png", noise_rgb(80, 96, 9))  # one photo more
    rc, err = _ended(_start("generate", tmp_path / "r.toml", "--out", out, "--resume", "--quiet"), 60)
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
        rc, err = _ended(_start("generate", smoke, "--out", out, "--quiet"), 60)
        line = _one_line(err)
        assert rc == 1 and "No space left on device" in line and "--resume" in line, line
        assert not _temps(out)
        subprocess.run(["mount", "-o", "remount,size=20m", str(disk)], check=True)
        rc, err = _ended(_start("generate", smoke, "--out", out, "--resume", "--quiet"), 60)
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


def test_a_nan_shard_stops_training_by_name_and_the_checkpoint_stays(tmp_path):
    from dofsynth.codecs import encode_depth
    from dofsynth.shards import read_shard, write_shard

    data, cfg, run = _train_setup(tmp_path, max_steps=4, checkpoint_interval=2, eval_interval=0)
    rc, err = _ended(_start("train", cfg, "--data", data, "--run", run, "--steps", "2"), 120)
    assert rc == 0, err
    good = (run / "ckpt.pt").read_bytes()
    shard = data / "train" / "train-000001.tar"
    samples = list(read_shard(shard))
    key, members = samples[1]
    depth = np.full((48, 48), np.nan, np.float32)
    samples[1] = (key, {**members, "depth.exr": encode_depth(depth)})
    write_shard(shard, samples)
    rc, err = _ended(_start("train", cfg, "--data", data, "--run", run), 120)
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
    assert _until(lambda: (run / "log.csv").exists(), 60)
    proc.send_signal(signal.SIGKILL)
    proc.communicate()
    rc, err = _ended(_start("train", cfg, "--data", data, "--run", run), 120)
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
                            # a test run started in the background inherits SIGINT ignored; a terminal's does not
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    assert _until(lambda: _children(proc.pid), 60, 0.01), "no worker started"
    os.killpg(proc.pid, signal.SIGINT)
    rc, err = _ended(proc)
    line = _one_line(err)
    assert rc == 130 and "interrupted" in line and "--resume" in line, line
    assert "Traceback" not in err
