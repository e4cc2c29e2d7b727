"""--executor ray on a real local Ray cluster (2 CPUs): byte-identical to the local executor,
retries after a worker is SIGKILLed mid-shard, --shards ranges on Ray merged with local ones."""
import os
import signal
import sys
from pathlib import Path

import pytest
import ray  # the optional extra: pip install -e '.[test,ray]'
from ray import cloudpickle

from dofsynth.cli import main
from dofsynth.generate import generate
from dofsynth.generate.executors import RayExecutor
from dofsynth.manifest import load_manifest
from dofsynth.recipe import load_recipe

ROOT = Path(__file__).resolve().parents[1]
SMOKE = ROOT / "recipes" / "smoke.toml"


def _files(out: Path) -> dict[str, bytes]:
    return {str(p.relative_to(out)): p.read_bytes() for p in sorted(out.rglob("*")) if p.is_file()}


class KillOnce:
    """Injected into the Ray tasks (RayExecutor's task_hook): after a sample of the shard armed by
    <folder>/<split>-<shard:06d>.kill, claim the file and SIGKILL the worker (the retry goes on)."""

    def __init__(self, folder: Path):
        self.folder = str(folder)

    def __call__(self, split: str, index: int) -> None:
        try:
            (Path(self.folder) / f"{split}-{index:06d}.kill").unlink()  # only one attempt dies
        except FileNotFoundError:
            return
        os.kill(os.getpid(), signal.SIGKILL)


cloudpickle.register_pickle_by_value(sys.modules[__name__])  # workers need not import this module


@pytest.fixture(scope="module")
def kill_dir(tmp_path_factory):
    """Arm KillOnce by creating <kill_dir>/<split>-<shard>.kill."""
    return tmp_path_factory.mktemp("kill")


@pytest.fixture(scope="module")
def cluster():
    """A local 2-CPU cluster. Ray waits a fixed 30 s for its raylet to register; on a machine
    at load 30-40 that is not always enough, so start-up is tried again (up to 4 times, 2 min
    or more) before the tests fail."""
    for attempt in range(4):
        try:
            ray.init(num_cpus=2, include_dashboard=False, logging_level="WARNING", log_to_driver=False)
            break
        except Exception as exc:  # Ray raises a bare Exception for a start-up timeout
            ray.shutdown()
            if "timed out during startup" not in str(exc) or attempt == 3:
                raise
    yield
    ray.shutdown()


@pytest.fixture(scope="module")
def recipe():
    return load_recipe(SMOKE)


@pytest.fixture(scope="module")
def reference(recipe, tmp_path_factory):
    out = tmp_path_factory.mktemp("ref") / "data"
    generate(recipe, out, progress=False)
    return _files(out)


def test_ray_run_is_byte_identical_to_local(cluster, recipe, reference, tmp_path):
    res = generate(recipe, tmp_path / "ray", executor=RayExecutor(), progress=False)
    assert res.executor.startswith("ray") and res.generated_shards == res.shards == 4
    assert _files(tmp_path / "ray") == reference
    assert res.peak_rss_mb > 0 and res.shard_seconds > 0


def test_worker_killed_mid_shard_is_retried(cluster, kill_dir, recipe, reference, tmp_path):
    arm = kill_dir / "train-000001.kill"
    arm.touch()
    res = generate(recipe, tmp_path / "killed", executor=RayExecutor(max_retries=2, task_hook=KillOnce(kill_dir)),
                   progress=False)
    assert not arm.exists()  # the first attempt claimed it and SIGKILLed its worker after one sample
    assert any(r.startswith("train/.train-000001.tar.tmp-") for r in res.removed), res.removed
    files = _files(tmp_path / "killed")
    assert sorted(files) == sorted(reference)
    assert files == reference


def test_retries_used_up_fail_clearly_then_resume(cluster, kill_dir, recipe, reference, tmp_path):
    out = tmp_path / "noretry"
    arm = kill_dir / "test-000000.kill"
    arm.touch()
    with pytest.raises(RuntimeError, match=r"test/test-000000.tar failed after 0 retries.*--resume"):
        generate(recipe, out, executor=RayExecutor(max_retries=0, task_hook=KillOnce(kill_dir)), progress=False)
    assert not arm.exists()
    assert not (out / "manifest.json").exists()
    res = generate(recipe, out, resume=True, executor=RayExecutor(), progress=False)
    assert res.generated_shards >= 1, res
    files = _files(out)
    assert sorted(files) == sorted(reference), res.removed
    assert files == reference


def test_ray_ranges_and_local_ranges_merge_to_the_full_run(cluster, recipe, reference, tmp_path, capsys):
    out = tmp_path / "mixed"
    assert main(["generate", str(SMOKE), "--out", str(out), "--executor", "ray", "--shards", "0:3",
                 "--max-retries", "1", "--workers", "1", "--quiet"]) == 0
    assert main(["generate", str(SMOKE), "--out", str(out), "--shards", "3:", "--quiet"]) == 0
    assert main(["manifest", "merge", str(out)]) == 0
    assert "4 shards" in capsys.readouterr().out
    assert _files(out) == reference
    assert load_manifest(out)["totals"]["samples"] == 8
