"""`dofsynth verify`: passes on a fresh smoke data set, fails naming the place on each kind of damage."""
from __future__ import annotations

import hashlib
import io
import json
import os
import shutil
import tarfile
from pathlib import Path

import numpy as np
import pytest

from dofsynth.qa import dataset as ds
from dofsynth.cli import main
from dofsynth.record import encode_record
from dofsynth.qa.verify import check_record_schema, verify_dataset

ROOT = Path(__file__).resolve().parents[1]


# ---------------------------------------------------------------- damage helpers
def rewrite_record(out: Path, split: str, key: str, edit) -> str:
    """Rewrite the shard holding `key` with `edit(record_dict)` applied to its JSON, keeping
    every other member and the member order, and fix the manifest's sha256 and size so that
    only a semantic check can notice. Returns the shard name."""
    manifest = json.loads((out / "manifest.json").read_text())
    index = int(key.rsplit("-", 1)[1])
    sh = next(s for s in ds.manifest_shards(manifest, split)
              if s.first_index <= index < s.first_index + s.samples)
    path = out / sh.path
    with tarfile.open(path) as tar:
        members = [(info, tar.extractfile(info).read() if info.isfile() else None) for info in tar]
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w", format=tarfile.USTAR_FORMAT) as tar:
        for info, data in members:
            if info.name == f"{key}.json":
                rec = json.loads(data)
                edit(rec)
                data = encode_record(rec)
                info.size = len(data)
            tar.addfile(info, io.BytesIO(data) if data is not None else None)
    path.write_bytes(buf.getvalue())
    _fix_manifest(out, manifest, sh.path, path.read_bytes())
    return sh.path


def _fix_manifest(out, manifest, name, data):
    base = name.rsplit("/", 1)[-1]

    def walk(o):
        if isinstance(o, dict):
            vals = [v for v in o.values() if isinstance(v, str)]
            if any(v == name or v == base for v in vals) and "sha256" in o:
                o["sha256"] = hashlib.sha256(data).hexdigest()
                for k in ("bytes", "size", "size_bytes"):
                    if k in o:
                        o[k] = len(data)
            for v in o.values():
                walk(v)
        elif isinstance(o, list):
            for v in o:
                walk(v)

    walk(manifest)
    (out / "manifest.json").write_text(json.dumps(manifest, indent=2, sort_keys=True))


# ---------------------------------------------------------------- fixtures
@pytest.fixture
def copy(smoke_set, tmp_path) -> Path:
    dst = tmp_path / "set"
    shutil.copytree(smoke_set, dst)
    return dst


def _shard(out: Path, split: str, i: int = 0) -> str:
    return ds.manifest_shards(ds.load(out), split)[i].path


def _run(out: Path, capsys, *extra) -> tuple[int, str]:
    rc = main(["verify", str(out), *extra])
    return rc, capsys.readouterr().out


# ---------------------------------------------------------------- tests
def _records(out: Path) -> list[tuple[str, dict, np.ndarray]]:
    """(split, record, cover) of every sample."""
    m = ds.load(out)
    return [(split, smp["record"], smp["cover"]) for split in ds.manifest_splits(m)
            for smp in ds.iter_samples(out, split)]


def test_fresh_dataset_passes(smoke_set, capsys):
    report = verify_dataset(smoke_set)
    assert report.ok, report.lines()
    m = ds.load(smoke_set)
    n = {s: sum(sh.samples for sh in ds.manifest_shards(m, s)) for s in ds.manifest_splits(m)}
    assert report.splits == n == {"train": 6, "test": 2}
    assert report.samples == 8 and report.shards == 4
    rc, out = _run(smoke_set, capsys)
    assert rc == 0 and out.splitlines()[-1].endswith("OK") and "FAIL" not in out


def test_deep_rerender_matches(smoke_set, capsys):
    rc, out = _run(smoke_set, capsys, "--deep", "--deep-n", "3")
    assert rc == 0, out
    assert "3 re-rendered" in out.splitlines()[-1]


def test_flipped_byte_is_caught(copy, capsys):
    name = _shard(copy, "train", 1)
    path = copy / name
    data = bytearray(path.read_bytes())
    data[len(data) // 3] ^= 0x01
    path.write_bytes(bytes(data))
    rc, out = _run(copy, capsys)
    assert rc == 1
    fails = [l for l in out.splitlines() if l.startswith("FAIL")]
    assert f"FAIL {name}: sha256 differs from the manifest (corrupted or rewritten)" in fails, out
    assert all(name in l for l in fails), out      # nothing else is blamed
    assert "FAILED" in out.splitlines()[-1]


def test_truncated_shard_is_caught(copy, capsys):
    name = _shard(copy, "test", 0)
    path = copy / name
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    rc, out = _run(copy, capsys)
    assert rc == 1
    fails = [l for l in out.splitlines() if l.startswith("FAIL")]
    assert any(name in l and "size" in l for l in fails), out
    assert any(name in l and "unreadable after" in l and "truncated" in l for l in fails), out
    assert all(name in l for l in fails), out


def test_missing_and_unlisted_shards_are_caught(copy, capsys):
    gone = _shard(copy, "train", 2)
    (copy / gone).rename(copy / "train" / "train-999999.tar")
    rc, out = _run(copy, capsys)
    assert rc == 1
    fails = [l for l in out.splitlines() if l.startswith("FAIL")]
    assert f"FAIL {gone}: missing shard (listed in the manifest)" in fails, out
    assert any(l.startswith("FAIL train/train-999999.tar:") and "not listed" in l for l in fails), out
    assert len(fails) == 2, out


def test_shard_with_wrong_sample_count_is_caught(copy):
    # the manifest claims one sample more than the shard holds (hash and size still right)
    m = json.loads((copy / "manifest.json").read_text())
    m["splits"]["test"]["shards"][0]["samples"] += 1
    m["splits"]["test"]["samples"] += 1
    m["totals"]["samples"] += 1
    (copy / "manifest.json").write_text(json.dumps(m))
    report = verify_dataset(copy)
    name = _shard(copy, "test", 0)
    assert [p.where for p in report.problems] == [name, "manifest.json"], report.lines()
    assert "holds 2 samples" in report.problems[0].message and "says 3" in report.problems[0].message
    assert "its recipe makes 2" in report.problems[1].message


def test_a_manifest_edited_to_drop_a_shard_is_caught(copy):
    """Every count made consistent with one shard less: the recipe's own count still tells."""
    m = json.loads((copy / "manifest.json").read_text())
    gone = m["splits"]["train"]["shards"].pop()
    for block in (m["splits"]["train"], m["totals"]):
        block["samples"] -= gone["samples"]
        block["bytes"] -= gone["bytes"]
    m["totals"]["shards"] -= 1
    (copy / "manifest.json").write_text(json.dumps(m))
    (copy / gone["path"]).unlink()
    report = verify_dataset(copy)
    assert [p.where for p in report.problems] == ["manifest.json"], report.lines()
    assert "holds 4 samples in its shards, but its recipe makes 6" in report.problems[0].message


def test_json_disagreeing_with_disparity_is_caught(copy, capsys):
    # a sample with certainly-opaque front pixels; move its recorded front plane back a bit
    split, rec, _ = next(r for r in _records(copy) if (r[2][:, :, 0] >= 0.6).sum() > 20)
    key = rec["key"]

    def edit(r):
        r["front"]["disparity"] = r["front"]["disparity"] - 0.05
    name = rewrite_record(copy, split, key, edit)
    report = verify_dataset(copy)
    assert [p.where for p in report.problems] == [f"{name}: {key}"], report.lines()
    assert "depth disagrees with the record" in report.problems[0].message
    assert "front pixels" in report.problems[0].message
    rc, out = _run(copy, capsys)
    assert rc == 1 and f"FAIL {name}: {key}: depth disagrees" in out


def test_ramp_with_wrong_direction_is_caught(copy):
    split, rec, cover = next(r for r in _records(copy) if r[1]["background"]["mode"] == "ramp"
                             and ((r[2] <= 0.4).all(axis=2)).sum() > 100)
    key = rec["key"]

    def edit(r):
        bg = r["background"]
        bg["direction"] = "vertical" if bg["direction"] == "horizontal" else "horizontal"
    name = rewrite_record(copy, split, key, edit)
    report = verify_dataset(copy)
    assert report.problems and all(p.where == f"{name}: {key}" for p in report.problems), report.lines()
    assert any("ramp background pixels" in p.message for p in report.problems)


def test_deep_catches_a_target_that_was_not_rendered(copy, capsys):
    # a changed focus leaves every cheap check happy; only re-rendering can notice
    split, rec, _ = _records(copy)[0]
    key = rec["key"]

    def edit(r):
        r["targets"][0]["focus"] = 1.0 - r["targets"][0]["focus"]
    name = rewrite_record(copy, split, key, edit)
    assert verify_dataset(copy).ok
    report = verify_dataset(copy, deep=True, deep_n=100)
    assert report.deep_checked == 8
    assert [str(p) for p in report.problems] == [
        f"{name}: {key}: --deep: member dof.0.png differs from a re-render of its JSON"]


def test_asset_leaked_across_splits_is_caught(copy):
    recs = _records(copy)
    train0 = next(r for s, r, _ in recs if s == "train")
    test1 = [r for s, r, _ in recs if s == "test"][-1]
    leaked = train0["assets"]["front"]
    assert leaked["id"] != test1["assets"]["front"]["id"]

    def edit(r):
        r["assets"]["front"] = dict(leaked)
    name = rewrite_record(copy, "test", test1["key"], edit)
    report = verify_dataset(copy)
    msgs = [str(p) for p in report.problems]
    assert len(msgs) == 2, msgs             # once by id, once by sha256
    train_shard = _shard(copy, "train", 0)
    for m in msgs:   # both places are named, whichever split the line is filed under
        assert f"{name}: {test1['key']}" in m and f"{train_shard}: {train0['key']}" in m, m
        assert "in both splits" in m
    assert {"id", "sha256"} == {m.split("asset ")[1].split()[0] for m in msgs}


def test_schema_errors_are_named(smoke_set):
    rec = next(ds.iter_samples(smoke_set, "train"))["record"]
    assert check_record_schema(rec) == []
    bad = json.loads(json.dumps(rec))
    del bad["targets"][1]["max_coc"]
    bad["front"]["disparity"] = 1.5
    bad["size"] = [64]
    bad["background"]["mode"] = "sky"
    errs = check_record_schema(bad)
    assert "targets[1]: 'max_coc' is a required property" in errs
    assert "front.disparity: 1.5 is greater than the maximum of 1" in errs
    assert "size: [64] is too short" in errs
    assert any(e.startswith("background.mode: 'sky' is not one of") for e in errs)
    older = json.loads(json.dumps(rec))   # a record of an older schema: one line that says so
    older["schema_version"] = 5
    for k in ("background", "front", "middle"):
        del older["assets"][k]["matte"]
    assert check_record_schema(older) == ["schema_version 5: made by an older dofsynth; this one checks schema 6 "
                                          "(docs/FORMAT.md says what changed; such records still read and re-render)"]
    typed = json.loads(json.dumps(rec))   # schema 4: one JSON type per field, whatever the sample
    typed["front"]["anchored"] = ["bottom"]
    typed["excluded"] = None
    errs = check_record_schema(typed)
    assert "front.anchored: ['bottom'] is not of type 'string'" in errs and "excluded: None is not of type 'string'" in errs
    bad2 = json.loads(json.dumps(rec))
    bad2["middle"]["disparity"] = float("nan")
    assert any(e.startswith("middle.disparity") for e in check_record_schema(bad2))


def test_schema_problem_in_a_shard_is_reported(copy):
    split, rec, _ = _records(copy)[1]
    name = rewrite_record(copy, split, rec["key"], lambda r: r.pop("aperture"))
    report = verify_dataset(copy)
    assert [str(p) for p in report.problems] == [f"{name}: {rec['key']}: record: 'aperture' is a required property"]


def test_missing_manifest_and_folder(tmp_path, capsys):
    (tmp_path / "empty").mkdir()
    rc, out = _run(tmp_path / "empty", capsys)
    assert rc == 1 and "FAIL manifest.json: unreadable manifest" in out
    assert main(["verify", str(tmp_path / "nowhere")]) == 2
    assert "no such data set folder" in capsys.readouterr().err


def test_run_in_progress_fails_and_leftovers_are_noted(copy, capsys):
    from dofsynth.generate.locks import OutputLock

    with OutputLock(copy):
        report = verify_dataset(copy)
        assert [p.where for p in report.problems] == [".lock"]
        assert f"pid {os.getpid()}" in report.problems[0].message
    (copy / "train" / ".train-000009.tar.tmp-123").write_bytes(b"half a shard")
    rc, out = _run(copy, capsys)
    assert rc == 0, out                                   # leftovers are notes, not failures
    assert "NOTE train/.train-000009.tar.tmp-123: temporary file left by a killed run" in out


def test_deep_with_recipe_file(smoke_set, tmp_path, capsys):
    rc, out = _run(smoke_set, capsys, "--deep", "--deep-n", "1", "--recipe", str(ROOT / "recipes" / "smoke.toml"))
    assert rc == 0 and "1 re-rendered" in out, out
    other = tmp_path / "other.toml"
    other.write_text((ROOT / "recipes" / "smoke.toml").read_text().replace("seed = 7", "seed = 8"))
    rc, out = _run(smoke_set, capsys, "--deep", "--recipe", str(other))
    assert rc == 1 and f"FAIL {other}: --recipe: not the recipe this data set was made from" in out


def test_same_content_under_another_id_is_a_leak(copy):
    recs = _records(copy)
    train0 = next(r for s, r, _ in recs if s == "train")
    test0 = next(r for s, r, _ in recs if s == "test")
    sha = train0["assets"]["background"]["sha256"]

    def edit(r):   # a renamed copy of a training background
        r["assets"]["background"]["sha256"] = sha
    name = rewrite_record(copy, "test", test0["key"], edit)
    report = verify_dataset(copy)
    assert len(report.problems) == 1, report.lines()
    msg = str(report.problems[0])
    assert f"asset sha256 {sha[:16]}... is in both splits" in msg and f"{name}: {test0['key']}" in msg


def test_manifest_totals_are_checked(copy):
    m = json.loads((copy / "manifest.json").read_text())
    m["splits"]["train"]["samples"] = 5
    m["totals"]["bytes"] += 1
    (copy / "manifest.json").write_text(json.dumps(m))
    assert [str(p) for p in verify_dataset(copy).problems] == [
        "manifest.json: split 'train' lists 5 samples, its shards 6",
        f"manifest.json: totals.bytes is {m['totals']['bytes']}, its shards add up to {m['totals']['bytes'] - 1}"]
