"""Review marks without a browser: `dofsynth qa apply` records what fits the set and refuses, by
name, what does not; verify reports marks and fails stale ones; marks merge by key."""
from __future__ import annotations

import json
import shutil

import pytest

from dofsynth.cli import main
from dofsynth.qa import dataset as ds
from dofsynth.qa.marks import FORMAT, MARKS_NAME, rejected, set_marks
from dofsynth.qa.verify import verify_dataset


@pytest.fixture
def reviewed(smoke_set, tmp_path):
    out = tmp_path / "set"
    shutil.copytree(smoke_set, out)
    return out


def _marks(out, *picks, path=None):
    """A marks file as the page writes it: picks are (key, mark, note)."""
    manifest = ds.load(out)
    shard_of = {k: sh for s in ds.manifest_splits(manifest) for sh in ds.manifest_shards(manifest, s) for k in sh.keys()}
    doc = {"format": FORMAT, "dataset": str(out), "recipe_sha256": manifest["recipe"]["sha256"],
           "marks": [{"key": k, "split": k.split("-")[0], "shard": shard_of[k].path, "shard_sha256": shard_of[k].sha256,
                      "mark": m, "note": n} for k, m, n in picks]}
    path = path or out.parent / "qa-marks.json"
    path.write_text(json.dumps(doc))
    return path


def test_marks_apply_merge_and_are_reported(reviewed, capsys):
    first = _marks(reviewed, ("train-0000001", "reject", "floating cut"), ("test-0000000", "keep", ""))
    assert main(["qa", "apply", str(first), str(reviewed)]) == 0
    assert "recorded 1 rejected and 1 kept" in capsys.readouterr().out
    assert rejected(reviewed) == {"train-0000001"}
    again = _marks(reviewed, ("train-0000001", "keep", "fine after all"), ("train-0000004", "reject", "halo"))
    assert main(["qa", "apply", str(again), str(reviewed)]) == 0
    marks = set_marks(reviewed)
    assert {k: m["mark"] for k, m in marks.items()} == {"train-0000001": "keep", "test-0000000": "keep",
                                                       "train-0000004": "reject"}
    report = verify_dataset(reviewed)
    assert report.ok and any("1 rejected, 2 kept" in str(n) and "train-0000004" in str(n) for n in report.notes)
    assert main(["stats", str(reviewed), "--marked", "--out", str(reviewed.parent / "s.png")]) == 0
    out = capsys.readouterr().out
    assert "review marks: 1 rejected, 2 kept" in out and "train-0000004  reject  halo" in out


def test_marks_that_do_not_fit_the_set_are_refused_by_name(reviewed, capsys):
    path = _marks(reviewed, ("train-0000002", "reject", ""))
    doc = json.loads(path.read_text())
    doc["marks"][0]["shard_sha256"] = "0" * 64               # the shard was made again since the review
    path.write_text(json.dumps(doc))
    assert main(["qa", "apply", str(path), str(reviewed)]) == 2
    err = capsys.readouterr().err
    assert "train-0000002" in err and "made again since the review" in err and not (reviewed / MARKS_NAME).exists()
    doc["marks"][0].update(shard_sha256=_sha(reviewed, "train-0000002"), mark="maybe")
    path.write_text(json.dumps(doc))
    assert main(["qa", "apply", str(path), str(reviewed)]) == 2
    assert "mark must be one of reject, keep" in capsys.readouterr().err
    path.write_text("{}")
    assert main(["qa", "apply", str(path), str(reviewed)]) == 2
    assert "not a dofsynth marks file" in capsys.readouterr().err


def test_verify_fails_a_mark_whose_shard_changed(reviewed):
    assert main(["qa", "apply", str(_marks(reviewed, ("test-0000001", "reject", "x"))), str(reviewed), "-q"]) == 0
    record = json.loads((reviewed / MARKS_NAME).read_text())
    record["marks"][0]["shard_sha256"] = "f" * 64
    (reviewed / MARKS_NAME).write_text(json.dumps(record))
    report = verify_dataset(reviewed)
    assert not report.ok and any("stale review mark: test-0000001" in str(p) for p in report.problems)


def _sha(out, key):
    manifest = ds.load(out)
    return next(sh.sha256 for s in ds.manifest_splits(manifest) for sh in ds.manifest_shards(manifest, s)
                if key in sh.keys())


def test_the_trainers_loader_leaves_rejected_samples_out(reviewed):
    """An epoch of the training loader over a reviewed set: every sample but the rejected one
    (with [data] exclude = "none": all of them)."""
    import dataclasses

    from dofsynth.train.config import load, replace
    from dofsynth.train.data import make_loader, resolve

    assert main(["qa", "apply", str(_marks(reviewed, ("train-0000002", "reject", "bad"))), str(reviewed), "-q"]) == 0
    cfg = resolve(load("train-tiny"), reviewed)
    cfg = replace(cfg, "data", val_share=0.0, batch_size=1, num_workers=0, crop=32)

    def keys(c):
        ds_, loader = make_loader(reviewed, "train", c, train=False, seed=0)
        return sorted(k for batch in loader for k in batch["key"])

    assert keys(cfg) == [f"train-{i:07d}" for i in range(6) if i != 2]
    assert keys(replace(cfg, "data", exclude="none")) == [f"train-{i:07d}" for i in range(6)]
    assert dataclasses.asdict(cfg.data)["exclude"] == "rejected"
