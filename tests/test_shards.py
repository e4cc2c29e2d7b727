"""Tar shards: byte-determinism, fixed headers, atomic completion, webdataset compatibility."""
import hashlib
import tarfile

import pytest

from dofsynth.files import remove_temp_files, sha256_file, temp_path
from dofsynth.shards import (ShardError, ShardWriter, member_sort_key, read_shard, shard_name,
                             write_shard)


def _samples(n=3, salt=b""):
    out = []
    for i in range(n):
        key = f"train-{i:07d}"
        members = {"json": b'{"i":%d}\n' % i, "dof.10.png": b"ten" + salt, "dof.2.png": b"two",
                   "aif.png": bytes(range(256)) * (i + 1), "depth.exr": b"\x00" * 700, "cover.png": b"c"}
        out.append((key, members))
    return out


def test_same_samples_give_identical_bytes(tmp_path):
    a = write_shard(tmp_path / "a" / "train-000000.tar", _samples())
    # members handed over in another dict order: same file
    shuffled = [(k, dict(reversed(list(m.items())))) for k, m in _samples()]
    b = write_shard(tmp_path / "b" / "train-000000.tar", shuffled)
    assert a == b
    assert (tmp_path / "a" / "train-000000.tar").read_bytes() == (tmp_path / "b" / "train-000000.tar").read_bytes()
    count, sha, nbytes = a
    data = (tmp_path / "a" / "train-000000.tar").read_bytes()
    assert count == 3 and nbytes == len(data) and sha == hashlib.sha256(data).hexdigest()
    assert sha256_file(tmp_path / "a" / "train-000000.tar") == (sha, nbytes)
    c = write_shard(tmp_path / "c.tar", _samples(salt=b"!"))
    assert c[1] != sha


def test_headers_are_fixed_and_order_is_natural(tmp_path):
    path = tmp_path / "s.tar"
    write_shard(path, _samples(2))
    with tarfile.open(path) as tar:
        infos = tar.getmembers()
    assert all((i.mtime, i.uid, i.gid, i.uname, i.gname, i.mode) == (0, 0, 0, "", "", 0o444) for i in infos)
    assert all(i.isfile() for i in infos)
    names = [i.name for i in infos]
    assert names[:6] == ["train-0000000." + s for s in
                         ("aif.png", "cover.png", "depth.exr", "dof.2.png", "dof.10.png", "json")]
    assert sorted(["dof.10.png", "dof.2.png", "aif.png", "json"], key=member_sort_key) == \
        ["aif.png", "dof.2.png", "dof.10.png", "json"]


def test_round_trip_and_keys(tmp_path):
    path = tmp_path / "s.tar"
    samples = _samples(3)
    write_shard(path, samples)
    assert list(read_shard(path)) == samples
    assert [k for k, _ in read_shard(path)] == [k for k, _ in samples]


def test_webdataset_reads_our_shards(tmp_path):
    wds = pytest.importorskip("webdataset")
    path = tmp_path / "train-000000.tar"
    samples = _samples(3)
    write_shard(path, samples)
    got = list(wds.WebDataset(str(path), shardshuffle=False))
    assert [g["__key__"] for g in got] == [k for k, _ in samples]
    for g, (_, m) in zip(got, samples):
        assert {k: v for k, v in g.items() if not k.startswith("__")} == m


def test_failed_write_leaves_no_file(tmp_path):
    final = tmp_path / "train" / "train-000001.tar"
    with pytest.raises(RuntimeError):
        with ShardWriter(final) as w:
            w.write("train-0000000", {"json": b"{}"})
            assert temp_path(final).is_file() and not final.exists()
            raise RuntimeError("killed")
    assert not final.exists() and not temp_path(final).exists()


def test_bad_input_is_refused(tmp_path):
    with ShardWriter(tmp_path / "x.tar") as w:
        with pytest.raises(ValueError, match="no dots"):
            w.write("train.0001", {"json": b"{}"})
        with pytest.raises(ValueError, match="must be bytes"):
            w.write("train-0000001", {"json": "text"})
        w.write("train-0000002", {"json": b"{}"})
        with pytest.raises(ValueError, match="twice"):
            w.write("train-0000002", {"json": b"{}"})


def test_truncated_shard_is_reported(tmp_path):
    path = tmp_path / "s.tar"
    write_shard(path, _samples(3))
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 3])
    with pytest.raises(ShardError, match="s.tar"):
        list(read_shard(path))


def test_stale_temp_files_are_removed(tmp_path):
    (tmp_path / ".train-000000.tar.tmp-123").write_bytes(b"half")
    (tmp_path / ".manifest.json.tmp-99").write_bytes(b"half")
    (tmp_path / "train-000001.tar").write_bytes(b"keep")
    removed = remove_temp_files(tmp_path)
    assert sorted(p.name for p in removed) == [".manifest.json.tmp-99", ".train-000000.tar.tmp-123"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["train-000001.tar"]
    assert shard_name("test", 12) == "test-000012.tar"
