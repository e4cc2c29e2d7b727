"""`dofsynth verify`: passes on a fresh data set, fails naming the place on each kind of damage."""
from __future__ import annotations

import hashlib
import io
import json
import shutil
import tarfile
from pathlib import Path

import numpy as np
import pytest

from dofsynth import dataset as ds
from dofsynth.cli import main
from dofsynth.io import encode_exr, encode_png
from dofsynth.verify import check_record_schema, verify_dataset

# ---------------------------------------------------------------- a hand-made data set (FORMAT.md)
H, W = 48, 64


def _fake_sha(name: str) -> str:
    return hashlib.sha256(name.encode()).hexdigest()


def _record(split, index, rng, assets):
    mode = ["flat", "ramp"][index % 2]
    direction = None if mode == "flat" else ["horizontal", "vertical"][(index // 2) % 2]
    b0, b1 = (0.0, 0.0) if mode == "flat" else sorted(rng.uniform(0, 0.3, 2).round(4).tolist())
    f1 = round(float(rng.uniform(0.35, 0.6)), 4)
    f0 = round(float(rng.uniform(0.65, 1.0)), 4)
    return {
        "schema_version": 1, "key": f"{split}-{index:07d}", "split": split, "index": index,
        "seed": [7, 0 if split == "train" else 1, index], "size": [H, W],
        "assets": {role: {"id": a, "path": f"assets/{a}.png", "sha256": _fake_sha(a)}
                   for role, a in zip(("background", "front", "middle"), assets)},
        "background": {"mode": mode, "b0": b0, "b1": b1, "direction": direction,
                       "crop": [0, 0, W, H], "flip": False},
        "front": {"disparity": f0, "scale": 0.5, "x": 10 + index, "y": 8, "flip": False},
        "middle": {"disparity": f1, "scale": 0.6, "x": 30, "y": 14, "flip": True},
        "targets": [{"focus": f0, "max_coc": 6.0}, {"focus": round(float(rng.uniform(0, 1)), 4), "max_coc": 4.0}],
        "aperture": {"kind": "disk"}, "options": {"highlight": None},
        "renderer": "layered-v1", "dofsynth_version": "0.1.0",
    }


def _pixels(rec, rng):
    y, x = np.mgrid[0:H, 0:W].astype(np.float32)
    fr, md = rec["front"], rec["middle"]
    front = np.clip(9.5 - np.hypot(x - fr["x"] - 8, y - fr["y"] - 10), 0, 1)      # a soft-edged disc
    middle = ((abs(x - md["x"] - 12) < 11) & (abs(y - md["y"] - 12) < 14)).astype(np.float32)
    bg = rec["background"]
    if bg["mode"] == "flat":
        depth = np.full((H, W), bg["b0"], np.float32)
    elif bg["direction"] == "horizontal":
        depth = np.broadcast_to(bg["b0"] + (bg["b1"] - bg["b0"]) * np.linspace(0, 1, W)[None], (H, W))
    else:
        depth = np.broadcast_to(bg["b0"] + (bg["b1"] - bg["b0"]) * np.linspace(1, 0, H)[:, None], (H, W))
    depth = np.where(middle > 0.5, np.float32(md["disparity"]), depth)
    depth = np.where(front > 0.5, np.float32(fr["disparity"]), depth).astype(np.float32)
    aif = np.clip(rng.uniform(0, 1, (H, W, 3)) * 0.3 + 0.4 * front[..., None] * [1, 0.2, 0.1]
                  + 0.4 * middle[..., None] * [0.1, 0.8, 0.2], 0, 1)
    cover = np.stack([front, middle, np.zeros_like(front)], axis=2)
    dofs = [np.clip(aif * (0.8 + 0.1 * i), 0, 1) for i in range(len(rec["targets"]))]
    return aif, depth, cover, dofs


def _members(rec, rng) -> dict[str, bytes]:
    aif, depth, cover, dofs = _pixels(rec, rng)
    m = {"json": json.dumps(rec, sort_keys=True).encode(), "aif.png": encode_png(aif),
         "depth.exr": encode_exr(depth), "cover.png": encode_png(cover)}
    m.update({f"dof.{i}.png": encode_png(d) for i, d in enumerate(dofs)})
    return m


def write_fixture_dataset(out: Path, n_train=6, n_test=2, shard_size=2) -> Path:
    """A data set folder written by hand after docs/FORMAT.md (independent of the generator)."""
    import webdataset as wds

    rng = np.random.default_rng(1234)
    out.mkdir(parents=True, exist_ok=True)
    pools = {"train": (["bg-a", "bg-b"], ["fg-a", "fg-b", "fg-c"], ["mid-a", "mid-b"]),
             "test": (["bg-t"], ["fg-t"], ["mid-t"])}
    splits = {}
    for split, n in (("train", n_train), ("test", n_test)):
        (out / split).mkdir(exist_ok=True)
        shards = []
        for first in range(0, n, shard_size):
            name = f"{split}/{split}-{first // shard_size:06d}.tar"
            with wds.TarWriter(str(out / name), mtime=0) as tw:
                for i in range(first, min(n, first + shard_size)):
                    pick = [p[i % len(p)] for p in pools[split]]
                    sample = {"__key__": f"{split}-{i:07d}"}
                    sample.update(_members(_record(split, i, rng, pick), rng))
                    tw.write(sample)
            data = (out / name).read_bytes()
            shards.append({"name": name.split("/")[1], "path": name, "index": first // shard_size,
                           "first_index": first, "samples": min(n, first + shard_size) - first,
                           "sha256": hashlib.sha256(data).hexdigest(), "bytes": len(data)})
        splits[split] = {"samples": n, "planned_samples": n, "bytes": sum(x["bytes"] for x in shards),
                         "shards": shards}
    text = "# fixture\n"
    manifest = {"schema_version": 1, "dofsynth_version": "0.1.0",
                "recipe": {"text": text, "sha256": hashlib.sha256(text.encode()).hexdigest(),
                           "path": "fixture.toml", "name": "fixture"},
                "splits": splits, "totals": {"samples": n_train + n_test}}
    (out / "manifest.json").write_text(json.dumps(manifest, indent=2, sort_keys=True))
    return out


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
                data = json.dumps(rec, sort_keys=True).encode()
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
@pytest.fixture(scope="module")
def fresh(tmp_path_factory) -> Path:
    return write_fixture_dataset(tmp_path_factory.mktemp("verify") / "set")


@pytest.fixture
def copy(fresh, tmp_path) -> Path:
    dst = tmp_path / "set"
    shutil.copytree(fresh, dst)
    return dst


def _shard(out: Path, split: str, i: int = 0) -> str:
    return ds.manifest_shards(ds.load(out), split)[i].path


def _run(out: Path, capsys, *extra) -> tuple[int, str]:
    rc = main(["verify", str(out), *extra])
    return rc, capsys.readouterr().out


# ---------------------------------------------------------------- tests
def test_fresh_dataset_passes(fresh, capsys):
    report = verify_dataset(fresh)
    assert report.ok, report.lines()
    m = ds.load(fresh)
    n = {s: sum(sh.samples for sh in ds.manifest_shards(m, s)) for s in ds.manifest_splits(m)}
    assert report.splits == n and report.samples == sum(n.values()) > 0
    rc, out = _run(fresh, capsys)
    assert rc == 0 and "OK" in out.splitlines()[-1] and "FAIL" not in out


def test_flipped_byte_is_caught(copy, capsys):
    name = _shard(copy, "train", 1)
    path = copy / name
    data = bytearray(path.read_bytes())
    data[700] ^= 0x01     # inside the first member's data, past the 512-byte header
    path.write_bytes(bytes(data))
    rc, out = _run(copy, capsys)
    assert rc == 1
    fails = [l for l in out.splitlines() if l.startswith("FAIL")]
    assert any(name in l and "sha256" in l for l in fails), out
    assert all(name in l for l in fails), out      # nothing else is blamed


def test_truncated_shard_is_caught(copy, capsys):
    name = _shard(copy, "test", 0)
    path = copy / name
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    rc, out = _run(copy, capsys)
    assert rc == 1
    assert any(name in l and "size" in l for l in out.splitlines()), out
    assert any(name in l and "truncated" in l for l in out.splitlines()), out


def test_missing_and_unlisted_shards_are_caught(copy, capsys):
    gone = _shard(copy, "train", 2)
    (copy / gone).rename(copy / "train" / "train-999999.tar")
    rc, out = _run(copy, capsys)
    assert rc == 1
    assert any(gone in l and "missing" in l for l in out.splitlines()), out
    assert any("train/train-999999.tar" in l and "not listed" in l for l in out.splitlines()), out


def test_json_disagreeing_with_disparity_is_caught(copy, capsys):
    key = "train-0000003"

    def edit(rec):
        rec["front"]["disparity"] = round(rec["front"]["disparity"] - 0.05, 4)
    name = rewrite_record(copy, "train", key, edit)
    report = verify_dataset(copy)
    # the hashes were fixed: only the pixel check can see it, and it names shard and key
    assert [p.where for p in report.problems] == [f"{name}: {key}"], report.lines()
    assert "opaque front" in report.problems[0].message
    rc, out = _run(copy, capsys)
    assert rc == 1 and f"{name}: {key}" in out


def test_ramp_with_wrong_direction_is_caught(copy):
    # sample 1 is a horizontal ramp (see _record): flipping its direction must be noticed
    def edit(rec):
        assert rec["background"]["mode"] == "ramp"
        rec["background"]["direction"] = "vertical" if rec["background"]["direction"] == "horizontal" else "horizontal"
    name = rewrite_record(copy, "train", "train-0000001", edit)
    report = verify_dataset(copy)
    assert not report.ok
    assert all(p.where == f"{name}: train-0000001" and "background" in p.message for p in report.problems)


def test_asset_leaked_across_splits_is_caught(copy, capsys):
    train_rec = next(ds.iter_samples(copy, "train"))["record"]
    leaked = train_rec["assets"]["front"]

    def edit(rec):
        rec["assets"]["front"] = dict(leaked)
    name = rewrite_record(copy, "test", "test-0000001", edit)
    report = verify_dataset(copy)
    msgs = [str(p) for p in report.problems]
    assert len(msgs) == 2, msgs             # once by id, once by sha256
    for m in msgs:   # both places are named, whichever split the line is filed under
        assert f"{name}: test-0000001" in m and "train/train-000000.tar: train-0000000" in m, m
        assert "in both splits" in m
    assert {"id", "sha256"} == {m.split("asset ")[1].split()[0] for m in msgs}


def test_schema_errors_are_named():
    rec = _record("train", 0, np.random.default_rng(0), ["a", "b", "c"])
    assert check_record_schema(rec) == []
    bad = json.loads(json.dumps(rec))
    del bad["targets"][1]["max_coc"]
    bad["front"]["disparity"] = 1.5
    bad["size"] = [H]
    errs = check_record_schema(bad)
    assert "missing key targets[1].max_coc" in errs
    assert any(e.startswith("front.disparity must be a number in [0, 1]") for e in errs)
    assert any(e.startswith("size must be") for e in errs)
    bad2 = json.loads(json.dumps(rec))
    bad2["front"]["disparity"] = float("nan")
    assert any(e.startswith("front.disparity") for e in check_record_schema(bad2))


def test_missing_manifest_and_folder(tmp_path, capsys):
    (tmp_path / "empty").mkdir()
    rc, out = _run(tmp_path / "empty", capsys)
    assert rc == 1 and "manifest.json" in out
    assert main(["verify", str(tmp_path / "nowhere")]) == 2
