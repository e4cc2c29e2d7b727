"""generate: plan, determinism across workers, kill + resume, the lock, refusing a used folder."""
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from dofsynth.cli import main
from dofsynth.recipe import load_recipe, recipe_from_text
from dofsynth.generate import OutputNotEmptyError, ResumeError, generate, generate_shard, plan_split, render_one
from dofsynth.generate.plan import shard_task
from dofsynth.generate.worker import library_for
from dofsynth.generate.locks import OutputInUseError, OutputLock
from dofsynth.manifest import load_manifest
from dofsynth.shards import read_shard

ROOT = Path(__file__).resolve().parents[1]
SMOKE = ROOT / "recipes" / "smoke.toml"


@pytest.fixture(scope="module")
def recipe():
    return load_recipe(SMOKE)


def _files(out: Path) -> dict[str, bytes]:
    """Every file of a data set folder by relative path (hidden files included)."""
    return {str(p.relative_to(out)): p.read_bytes() for p in sorted(out.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def reference(recipe, tmp_path_factory):
    """The uninterrupted single-worker data set every other run must equal byte for byte."""
    out = tmp_path_factory.mktemp("ref") / "data"
    result = generate(recipe, out, workers=1, progress=False)
    return out, result


def test_plan_shards_consecutive_indices(recipe):
    size = recipe.shard_size
    for split in ("train", "test"):
        tasks = plan_split(recipe, split)
        n = recipe.samples.count(split)
        assert sum(t.samples for t in tasks) == n
        assert [t.first_index for t in tasks] == list(range(0, n, size))
        assert all(t.samples == size for t in tasks[:-1]) and 0 < tasks[-1].samples <= size
    short = plan_split(recipe, "train", limit=size + 1)
    assert [(t.first_index, t.samples) for t in short] == [(0, size), (size, 1)]
    assert plan_split(recipe, "train", limit=0) == []
    with pytest.raises(ValueError, match="plan has shards"):
        shard_task(recipe, "train", 99)
    with pytest.raises(ValueError, match="split 'val'"):
        plan_split(recipe, "val")


def test_reference_layout_and_manifest(recipe, reference):
    out, result = reference
    files = _files(out)
    assert "manifest.json" in files and ".lock" not in files and ".progress.jsonl" not in files
    assert not [f for f in files if ".tmp" in f]
    manifest = load_manifest(out)
    for split in ("train", "test"):
        block = manifest["splits"][split]
        assert block["samples"] == recipe.samples.count(split)
        for s in block["shards"]:
            assert s["path"] in files and len(files[s["path"]]) == s["bytes"]
            assert [k for k, _ in read_shard(out / s["path"])] == \
                [f"{split}-{i:07d}" for i in range(s["first_index"], s["first_index"] + s["samples"])]
    assert manifest["recipe"]["sha256"] == recipe.sha256 and manifest["recipe"]["text"] == recipe.text
    assert result.samples == result.generated_samples == manifest["totals"]["samples"]
    assert result.bytes == sum(len(v) for k, v in files.items() if k.endswith(".tar"))


def test_two_workers_give_identical_bytes(recipe, reference, tmp_path):
    out = tmp_path / "w2"
    generate(recipe, out, workers=2, progress=False)
    assert _files(out) == _files(reference[0])


def test_a_process_keeps_one_library_per_recipe(recipe, tmp_path):
    """`library_for` builds a recipe's library once per process (workers are handed their
    parent's); the same recipe text in another folder names other files: another library."""
    lib = library_for(recipe)
    assert library_for(recipe) is lib and library_for(recipe, object()) is lib
    (tmp_path / "smoke.toml").write_text(recipe.text, encoding="utf-8")
    moved = load_recipe(tmp_path / "smoke.toml")
    assert moved.sha256 == recipe.sha256 and library_for(moved) is not lib


def test_sample_alone_equals_sample_in_batch(recipe, reference, tmp_path):
    out = reference[0]
    library = library_for(recipe)
    k = recipe.samples.count("train") - 1
    shard = shard_task(recipe, "train", k // recipe.shard_size)
    batch = dict(read_shard(out / shard.path))
    key, alone = render_one(recipe, library, "train", k)
    assert batch[key] == alone
    info = generate_shard(recipe, tmp_path, "test", 0)  # one shard on its own, fresh library
    assert (tmp_path / info.path).read_bytes() == (out / info.path).read_bytes()


def test_limit_then_resume_equals_full_run(recipe, reference, tmp_path):
    out = tmp_path / "lim"
    lim = generate(recipe, out, limit=recipe.shard_size + 1, progress=False)
    assert lim.manifest["splits"]["train"]["samples"] == recipe.shard_size + 1
    assert lim.manifest["splits"]["train"]["limit"] == recipe.shard_size + 1
    ref = reference[0]
    # a limit keeps the first samples unchanged: the first (full) shard is identical
    assert (out / "train/train-000000.tar").read_bytes() == (ref / "train/train-000000.tar").read_bytes()
    (out / "train/train-000000.tar").unlink()                       # a lost shard
    (out / "test" / ".test-000000.tar.tmp-4242").write_bytes(b"half")  # a killed run's temp file
    res = generate(recipe, out, resume=True, progress=False)
    assert _files(out) == _files(ref)
    assert res.kept_shards >= 1 and "test/.test-000000.tar.tmp-4242" in res.removed


_SLOW_RUN = """
import sys, time
import dofsynth.shards as shards
_write = shards.ShardWriter.write
def slow(self, *a, **k):
    _write(self, *a, **k)
    time.sleep(0.6)
shards.ShardWriter.write = slow
from dofsynth.cli import main
sys.exit(main(sys.argv[1:]))
"""


def test_sigkill_midway_then_resume_is_byte_identical(recipe, reference, tmp_path):
    out = tmp_path / "killed"
    proc = subprocess.Popen([sys.executable, "-c", _SLOW_RUN, "generate", str(SMOKE), "--out", str(out), "--quiet"],
                            start_new_session=True, stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 600
        # kill when two shards are done and the third is half written
        while not ((out / "train" / "train-000001.tar").exists() and list((out / "train").glob(".train-000002.tar.tmp-*"))):
            assert proc.poll() is None, proc.stderr.read().decode()
            assert time.monotonic() < deadline, "the run never reached its third shard"
            time.sleep(0.01)
    finally:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    left = _files(out)
    assert "manifest.json" not in left and ".lock" in left and ".progress.jsonl" in left
    assert any(".tmp-" in name for name in left), sorted(left)
    # the dead run's lock file does not block; without --resume the folder is refused
    with pytest.raises(OutputNotEmptyError, match="--resume"):
        generate(recipe, out, progress=False)
    res = generate(recipe, out, resume=True, progress=False)
    assert res.kept_shards >= 2
    assert _files(out) == _files(reference[0])
    # resuming a finished data set renders nothing and changes nothing
    again = generate(recipe, out, resume=True, progress=False)
    assert again.generated_samples == 0 and _files(out) == _files(reference[0])


def test_corrupt_shard_is_regenerated_on_resume(recipe, reference, tmp_path):
    out = tmp_path / "corrupt"
    generate(recipe, out, progress=False)
    p = out / "train" / "train-000000.tar"
    data = bytearray(p.read_bytes())
    data[600] ^= 0xFF  # a flipped bit inside the first member: the manifest's sha256 catches it
    p.write_bytes(bytes(data))
    res = generate(recipe, out, resume=True, progress=False)
    assert res.generated_shards == 1
    assert _files(out) == _files(reference[0])


def test_split_by_split_then_resume_equals_all(recipe, reference, tmp_path):
    out = tmp_path / "bysplit"
    generate(recipe, out, splits=("test",), progress=False)
    assert set(load_manifest(out)["splits"]) == {"test"}
    generate(recipe, out, splits=("train",), resume=True, progress=False)
    assert _files(out) == _files(reference[0])


def test_second_concurrent_run_is_refused(recipe, tmp_path, capsys):
    out = tmp_path / "locked"
    with OutputLock(out):
        assert (out / ".lock").read_text().strip() == str(os.getpid())
        with pytest.raises(OutputInUseError) as err:
            generate(recipe, out, progress=False)
        assert str(out) in str(err.value) and str(os.getpid()) in str(err.value)
        assert main(["generate", str(SMOKE), "--out", str(out), "--quiet"]) == 2
        assert str(out) in capsys.readouterr().err
    assert not (out / ".lock").exists()
    generate(recipe, out, limit=1, progress=False)  # free again


def test_used_folder_is_refused_without_resume(recipe, tmp_path, capsys):
    out = tmp_path / "used"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    assert main(["generate", str(SMOKE), "--out", str(out), "--limit", "1", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert str(out) in err and "--resume" in err and "new --out" in err
    with pytest.raises(ResumeError, match="not a dofsynth data set"):
        generate(recipe, out, resume=True, progress=False)
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"]


def test_resume_with_another_recipe_is_refused(recipe, tmp_path):
    out = tmp_path / "other"
    generate(recipe, out, limit=1, progress=False)
    other = recipe_from_text(recipe.text.replace(f"seed = {recipe.seed}", f"seed = {recipe.seed + 1}"),
                             "other.toml", SMOKE.parent)
    assert other.sha256 != recipe.sha256
    with pytest.raises(ResumeError, match="sha256"):
        generate(other, out, resume=True, progress=False)


def test_cli_generate_with_summary(tmp_path, capsys):
    out, summary = tmp_path / "cli", tmp_path / "data_manifest" / "datasets" / "smoke.json"
    rc = main(["generate", str(SMOKE), "--out", str(out), "--split", "test", "--limit", "1",
               "--workers", "2", "--save-summary", str(summary)])
    assert rc == 0
    text = capsys.readouterr().out
    assert "samples/s" in text and "1 in 1 shards" in text
    s = json.loads(summary.read_text())
    assert s["splits"]["test"]["samples"] == 1 and "train" not in s["splits"]
    assert s["recipe"]["sha256"] == load_manifest(out)["recipe"]["sha256"]
    with pytest.raises(SystemExit):
        main(["generate", str(SMOKE), "--out", str(tmp_path / "x"), "--workers", "0"])
    assert "--workers" in capsys.readouterr().err


def test_webdataset_reads_the_whole_data_set(reference):
    wds = pytest.importorskip("webdataset")
    from dofsynth.record import decode_sample

    out = reference[0]
    manifest = load_manifest(out)
    for split, block in manifest["splits"].items():
        urls = [str(out / s["path"]) for s in block["shards"]]
        got = list(wds.WebDataset(urls, shardshuffle=False))
        assert [g["__key__"] for g in got] == [f"{split}-{i:07d}" for i in range(block["samples"])]
        for g in got:
            d = decode_sample(g)
            assert d["record"]["key"] == g["__key__"] and d["record"]["split"] == split


# ------------------------------------------------------------ --shards A:B and manifest merge
def _merge(*argv) -> int:
    return main(["manifest", "merge", *map(str, argv), "--quiet"])


def test_plan_prints_the_global_shard_numbers(recipe, capsys):
    assert main(["generate", str(SMOKE), "--plan"]) == 0
    text = capsys.readouterr().out
    n_train = len(plan_split(recipe, "train"))
    assert f"train --shards 0:{n_train}" in text and f"test  --shards {n_train}:" in text


def test_shard_ranges_then_merge_equal_a_full_run(recipe, reference, tmp_path):
    """A job array of ranges of K=1 and K=2 shards into one shared OUT, run in a shuffled order
    (the last range past the end of the plan is clipped), merged: the same folder as one run."""
    out = tmp_path / "array"
    total = len(plan_split(recipe, "train")) + len(plan_split(recipe, "test"))
    ranges = [(0, 1), (1, 3)] + [(i, i + 2) for i in range(3, total, 2)]
    for a, b in reversed(ranges):
        assert main(["generate", str(SMOKE), "--out", str(out), "--shards", f"{a}:{b}", "--resume", "--quiet"]) == 0
    parts = sorted(p.name for p in out.glob("manifest.part-*.json"))
    assert len(parts) == len(ranges) and f"manifest.part-000003-{min(5, total):06d}.json" in parts
    assert not (out / "manifest.json").exists()
    # a whole run, or a run of another recipe, cannot mix into a folder of ranges
    with pytest.raises(OutputNotEmptyError):
        generate(recipe, out, progress=False)
    other = recipe_from_text(recipe.text.replace(f"seed = {recipe.seed}", f"seed = {recipe.seed + 1}"),
                             "other.toml", SMOKE.parent)
    with pytest.raises(OutputNotEmptyError, match="another recipe"):
        generate(other, tmp_path / "array", shard_range=(0, 1), resume=True, progress=False)
    with pytest.raises(OutputNotEmptyError, match="overlaps"):
        generate(recipe, out, shard_range=(1, 2), progress=False)
    assert _merge(out) == 0
    assert _files(out) == _files(reference[0])


def test_shard_range_resume_after_kill_and_refusals(recipe, reference, tmp_path, capsys):
    out = tmp_path / "range"
    res = generate(recipe, out, shard_range=(1, 3), progress=False)
    assert res.shard_range == (1, 3) and res.part.name == "manifest.part-000001-000003.json"
    assert res.manifest["range"] == [1, 3] and [s["index"] for s in res.manifest["shards"]] == [1, 2]
    # the same range again needs --resume; with it, nothing is rendered
    assert main(["generate", str(SMOKE), "--out", str(out), "--shards", "1:3", "--quiet"]) == 2
    assert "--resume" in capsys.readouterr().err
    (out / "train" / "train-000002.tar").unlink()                      # lost ...
    (out / "train" / ".train-000001.tar.tmp-4242").write_bytes(b"x")   # ... and a dead attempt's temp
    (out / "train" / ".train-000000.tar.tmp-4243").write_bytes(b"y")   # another range's temp: not ours
    again = generate(recipe, out, shard_range=(1, 3), resume=True, progress=False)
    assert (again.kept_shards, again.generated_shards) == (1, 1)
    assert again.removed == ["train/.train-000001.tar.tmp-4242"]
    (out / "train" / ".train-000000.tar.tmp-4243").unlink()
    assert again.part.read_bytes() == res.part.read_bytes()
    with pytest.raises(ValueError, match="holds none"):
        generate(recipe, out, shard_range=(99, 100), progress=False)
    for bad in ("3:1", "x", "1-2"):
        assert main(["generate", str(SMOKE), "--out", str(out), "--shards", bad, "--quiet"]) == 2
        assert "--shards" in capsys.readouterr().err
    generate(recipe, out, shard_range=(0, 1), progress=False)
    generate(recipe, out, shard_range=(3, None), progress=False)
    assert _merge(out) == 0 and _files(out) == _files(reference[0])


def test_concurrent_disjoint_ranges_share_out_but_not_with_a_whole_run(recipe, tmp_path):
    from dofsynth.generate.locks import RangeLock

    out = tmp_path / "shared"
    with RangeLock(out, 0, 2):       # a running --shards 0:2 (say on another node)
        assert (out / ".lock.part-000000-000002").is_file()
        generate(recipe, out, shard_range=(2, 4), progress=False)          # disjoint: fine
        with pytest.raises(OutputInUseError, match="overlaps 0:2"):
            generate(recipe, out, shard_range=(1, 3), progress=False)
        with pytest.raises(OutputInUseError, match="same|being made"):
            generate(recipe, out, shard_range=(0, 2), resume=True, progress=False)
        with pytest.raises(OutputInUseError, match="--shards runs"):
            generate(recipe, out, resume=True, progress=False)
        assert _merge(out) == 2      # merging waits for the running ranges
        assert (out / ".lock").exists()  # still held (shared) by the running range
    assert not (out / ".lock").exists() and not (out / ".lock.part-000000-000002").exists()


def test_merge_refuses_overlaps_gaps_and_mixed_recipes(recipe, tmp_path, capsys):
    a, b, c = tmp_path / "a", tmp_path / "b", tmp_path / "c"
    pa = generate(recipe, a, shard_range=(0, 2), progress=False).part
    pb = generate(recipe, b, shard_range=(1, None), progress=False).part      # overlaps pa at shard 1
    pc = generate(recipe, c, shard_range=(3, None), progress=False).part      # leaves shard 2 out
    other = recipe_from_text(recipe.text.replace(f"seed = {recipe.seed}", f"seed = {recipe.seed + 1}"),
                             "other.toml", SMOKE.parent)
    pd = generate(other, tmp_path / "d", shard_range=(2, None), progress=False).part
    cases = [((pa, pb), ["overlap", pa.name, pb.name, "1:2"]),
             ((pc, pa), ["gap", "2:3", pa.name, pc.name]),
             ((pa,), ["gap", "2:4", pa.name]),
             ((pc,), ["gap", "0:3", pc.name]),
             ((pa, pd), ["mixed recipes", str(pa), str(pd)])]
    for parts, words in cases:
        assert _merge(*parts, "--out", tmp_path / "m" / "manifest.json") == 2
        err = capsys.readouterr().err
        assert all(w in err for w in words), (words, err)
    assert not (tmp_path / "m").exists() or not (tmp_path / "m" / "manifest.json").exists()
    # parts in one folder, with a shard missing there
    assert _merge(pa, "--keep-parts") == 2
    assert "gap" in capsys.readouterr().err
    shutil.copy(pc, a / pc.name)   # its shard test/test-000000.tar stays in c
    generate(recipe, a, shard_range=(2, 3), progress=False)
    assert _merge(a) == 2
    assert "test-000000.tar" in capsys.readouterr().err and pa.exists() and not (a / "manifest.json").exists()
    shutil.copytree(c / "test", a / "test", dirs_exist_ok=True)
    assert _merge(a) == 0 and not pa.exists() and load_manifest(a)["totals"]["shards"] == 4


def test_missing_ray_says_how_to_install(monkeypatch, tmp_path, capsys):
    from dofsynth.generate.executors import make_executor

    monkeypatch.setitem(sys.modules, "ray", None)   # import ray -> ImportError
    with pytest.raises(ValueError, match=r"pip install 'dofsynth\[ray\]'"):
        make_executor("ray")
    assert main(["generate", str(SMOKE), "--out", str(tmp_path / "o"), "--executor", "ray", "--quiet"]) == 2
    assert "pip install 'dofsynth[ray]'" in capsys.readouterr().err and not (tmp_path / "o").exists()


def test_skipped_assets_are_relative_to_the_recipe_folder(tmp_path, monkeypatch):
    """The same recipe and assets in two places give byte-identical manifests."""
    from conftest import RECIPE_TEMPLATE, noise_rgb, write_png

    manifests = []
    for where in (tmp_path / "one", tmp_path / "two" / "deeper"):
        write_png(where / "bg" / "a.png", noise_rgb(80, 96, 1))
        write_png(where / "bg" / "b.png", noise_rgb(80, 96, 2))
        (where / "bg" / "broken.png").write_bytes(b"not a png")
        text = RECIPE_TEMPLATE.format(size=32, backgrounds="bg", foregrounds="builtin", on_bad_asset="skip",
                                      verify="decode", manifest="")
        (where / "r.toml").write_text(text.replace("test = 2", "test = 0"), encoding="utf-8")
        monkeypatch.chdir(where)
        res = generate(load_recipe("r.toml"), "out", limit=1, progress=False)
        assert len(res.skipped_assets) == 1 and res.skipped_assets[0][0] == "bg/broken.png"
        assert str(tmp_path) not in json.dumps(res.manifest["skipped_assets"])
        manifests.append((where / "out" / "manifest.json").read_bytes())
    assert manifests[0] == manifests[1]


def test_two_range_processes_at_once_into_one_out(recipe, reference, tmp_path):
    """A job array for real: two processes write disjoint ranges into one OUT at the same time."""
    out = tmp_path / "jobarray"
    procs = [subprocess.Popen([sys.executable, "-c", _SLOW_RUN, "generate", str(SMOKE), "--out", str(out),
                               "--shards", rng, "--resume", "--quiet"], stderr=subprocess.PIPE)
             for rng in ("0:2", "2:4")]
    try:
        both, deadline = False, time.monotonic() + 600
        while not both and all(p.poll() is None for p in procs) and time.monotonic() < deadline:
            both = all((out / f".lock.part-{r}").exists() for r in ("000000-000002", "000002-000004"))
            time.sleep(0.01)
        errs = [p.communicate(timeout=600)[1].decode() for p in procs]
    finally:
        for p in procs:
            p.kill()
    assert [p.returncode for p in procs] == [0, 0], errs
    assert both, "the two ranges never ran at the same time"
    assert _merge(out) == 0
    assert _files(out) == _files(reference[0])


def test_process_settings_do_not_change_the_bytes(recipe, reference, tmp_path):
    """`generate --workers 1` sets itself up like a worker (one OpenCV thread, glibc malloc
    thresholds; DOFSYNTH_WORKER_MALLOC=default leaves glibc alone): the bytes are the same."""
    for setting in ("", "16,64", "default"):
        out = tmp_path / f"m{setting.replace(',', '-') or 'tuned'}"
        env = {**os.environ, "DOFSYNTH_WORKER_MALLOC": setting}
        subprocess.run([sys.executable, "-m", "dofsynth", "generate", str(SMOKE), "--out", str(out), "--workers", "1",
                        "--split", "test", "--quiet"], env=env, check=True, capture_output=True)
        ref = {k: v for k, v in _files(reference[0]).items() if k.startswith("test/")}
        assert {k: v for k, v in _files(out).items() if k.startswith("test/")} == ref


def test_the_reported_peak_memory_is_the_workers_not_the_callers(smoke_recipe, tmp_path):
    """`GenerateResult.peak_rss_mb` is the largest peak of the processes that rendered: with
    spawn workers, theirs, not the caller's (which here holds 200 MiB the workers never see)."""
    import numpy as np

    from dofsynth.generate import LocalExecutor
    from dofsynth.generate.worker import peak_rss_mb

    ballast = np.ones(200 * 2**20, np.uint8)   # touched: in this process's resident memory
    res = generate(smoke_recipe, tmp_path / "out", executor=LocalExecutor(2, in_process=False), progress=False)
    assert int(ballast[::4096].sum()) == ballast[::4096].size
    assert 0 < res.peak_rss_mb < peak_rss_mb() - 150, (res.peak_rss_mb, peak_rss_mb())


def test_the_library_file_is_mapped_by_the_workers_not_copied(tmp_path):
    """The pool's library file (`write_shared`) holds the arrays out of the pickle, page-aligned:
    `read_shared` gives the same object with its arrays in a copy-on-write mapping of the
    file (shared by the workers), read-only ones still read-only, a write changing neither
    the file nor another reader's copy, and all of it usable once the file is removed."""
    import numpy as np

    from dofsynth.generate.pool import read_shared, write_shared

    frozen = np.arange(3 * 5000, dtype=np.float32).reshape(3, 5000)
    frozen.setflags(write=False)
    obj = {"frozen": frozen, "open": np.ones((70, 90), np.uint8), "meta": ("a", 1.5, [2, 3])}
    path = tmp_path / "lib.pkl"
    write_shared(path, obj)
    first, second = read_shared(path), read_shared(path)
    path.unlink()
    for got in (first, second):
        assert got["meta"] == obj["meta"]
        for name in ("frozen", "open"):
            assert np.array_equal(got[name], obj[name]) and got[name].dtype == obj[name].dtype
            assert not got[name].flags.owndata  # the mapping's pages, not a copy
    assert not first["frozen"].flags.writeable and first["open"].flags.writeable
    first["open"][0, 0] = 7                     # copy-on-write: this reader's page only
    assert second["open"][0, 0] == 1 and first["open"][0, 0] == 7
