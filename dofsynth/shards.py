"""Deterministic WebDataset tar shards (docs/FORMAT.md), written complete or not at all.

A shard is a plain (uncompressed, POSIX ustar) tar of samples; sample `KEY` with members
`{"aif.png": b"...", ...}` becomes the tar members `KEY.aif.png`, ... . Every tar header is
fixed (mtime 0, uid/gid 0, uname/gname "", mode 0o444, regular file) and the members of a
sample are written in a fixed order (`member_sort_key`), so the same samples give the same
bytes on any machine, any day.

We write with `tarfile` directly rather than `webdataset.TarWriter`: the latter can be made
just as deterministic (mtime=0, user="", group="") but importing `webdataset` imports torch
(about 2 s and 300 MB per spawned worker), and torch stays out of the generation path. The
tests read our shards back with `webdataset.WebDataset`.

A shard is written under its temp name (dofsynth.files: `OUT/<split>/.<name>.tmp-<pid>`) and
renamed to `OUT/<split>/<name>` only when complete and fsync'ed: a file under a final name is
always a whole shard. Every read of a shard goes through `iter_members`, which checks each
member's length and the end-of-archive marker and names the file in a `ShardError`.
"""
from __future__ import annotations

import hashlib
import io
import os
import re
import tarfile
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Iterable, Iterator

from dofsynth.files import AtomicFile
from dofsynth.rng import sample_key

TAR_MODE = 0o444
_KEY_RE = re.compile(r"^[A-Za-z0-9_-]+$")


class ShardError(ValueError):
    """A shard that is unreadable or not what it should be; the message names the file."""


@dataclass(frozen=True)
class ShardInfo:
    """One finished shard: where it is, which samples it holds, and its checksum."""

    split: str
    index: int          # shard number within the split
    name: str           # file name, e.g. "train-000003.tar"
    first_index: int    # sample index of its first sample
    samples: int        # number of samples (consecutive indices)
    sha256: str
    bytes: int
    usage: dict | None = field(default=None, compare=False)  # what its samples used: dofsynth.generate.worker.Usage

    @property
    def path(self) -> str:
        """Path relative to the data set folder, e.g. "train/train-000003.tar"."""
        return f"{self.split}/{self.name}"

    def keys(self) -> list[str]:
        return [sample_key(self.split, i) for i in range(self.first_index, self.first_index + self.samples)]

    def to_dict(self) -> dict:
        d = asdict(self)
        d["path"] = self.path
        if self.usage is None:
            del d["usage"]
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "ShardInfo":
        return cls(split=str(d["split"]), index=int(d["index"]), name=str(d["name"]),
                   first_index=int(d["first_index"]), samples=int(d["samples"]),
                   sha256=None if d["sha256"] is None else str(d["sha256"]), bytes=int(d["bytes"]),
                   usage=d.get("usage"))


def shard_name(split: str, shard_index: int) -> str:
    """"<split>-<shard_index:06d>.tar"."""
    return f"{split}-{shard_index:06d}.tar"


def member_sort_key(suffix: str) -> tuple:
    """Natural order of member suffixes: dot-separated parts, numeric parts compared as numbers
    ("aif.png" < "cover.png" < "depth.exr" < "dof.2.png" < "dof.10.png" < "json")."""
    return tuple((0, int(p), "") if p.isdigit() else (1, 0, p) for p in suffix.split("."))


def _tarinfo(name: str, size: int) -> tarfile.TarInfo:
    ti = tarfile.TarInfo(name)
    ti.size = size
    ti.mtime = 0
    ti.mode = TAR_MODE
    ti.uid = ti.gid = 0
    ti.uname = ti.gname = ""
    ti.type = tarfile.REGTYPE
    return ti


class _HashingFile(io.RawIOBase):
    """A write-only file object that forwards to `fh` and hashes/counts what passes."""

    def __init__(self, fh):
        self.fh = fh
        self.sha = hashlib.sha256()
        self.nbytes = 0

    def writable(self) -> bool:
        return True

    def write(self, b) -> int:
        self.sha.update(b)
        self.nbytes += len(b)
        return self.fh.write(b)


class ShardWriter:
    """Write samples into one tar shard under a temporary name; `close()` renames it.

        with ShardWriter(path) as w:
            w.write("train-0000000", {"aif.png": b"...", "json": b"..."})
        w.samples, w.sha256, w.bytes

    Leaving the block by an exception deletes the temporary file and leaves `path` untouched.
    """

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        self._file = AtomicFile(self.path)
        self.tmp = self._file.tmp
        self._hf = _HashingFile(self._file.file)
        self._tar = tarfile.open(fileobj=self._hf, mode="w|", format=tarfile.USTAR_FORMAT)
        self.samples = 0
        self.sha256: str | None = None
        self.bytes: int | None = None
        self._keys: set[str] = set()

    def write(self, key: str, members: dict[str, bytes]) -> None:
        if not _KEY_RE.match(key):
            raise ValueError(f"sample key {key!r}: keys hold letters, digits, '-' and '_' only (no dots)")
        if key in self._keys:
            raise ValueError(f"sample key {key!r} written twice into {self.path}")
        if not members:
            raise ValueError(f"sample {key!r} has no members")
        self._keys.add(key)
        for suffix in sorted(members, key=member_sort_key):
            data = members[suffix]
            if not isinstance(data, (bytes, bytearray, memoryview)):
                raise ValueError(f"{key}.{suffix}: member must be bytes, got {type(data).__name__}")
            if not suffix or suffix.startswith(".") or "/" in suffix:
                raise ValueError(f"{key}.{suffix}: bad member suffix {suffix!r}")
            data = bytes(data)
            self._tar.addfile(_tarinfo(f"{key}.{suffix}", len(data)), io.BytesIO(data))
        self.samples += 1

    def close(self) -> tuple[int, str, int]:
        """Finish the tar, fsync, rename to the final name; returns (samples, sha256, bytes)."""
        if self.sha256 is not None:
            return self.samples, self.sha256, self.bytes
        self._tar.close()
        self._file.commit()
        self.sha256, self.bytes = self._hf.sha.hexdigest(), self._hf.nbytes
        return self.samples, self.sha256, self.bytes

    def abort(self) -> None:
        """Drop the half-written temp file."""
        try:
            self._tar.close()  # so its stream does not write again at garbage collection
        except (OSError, tarfile.TarError, ValueError):
            pass
        self._file.abort()

    def __enter__(self) -> "ShardWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


def write_shard(path: str | os.PathLike, samples: Iterable[tuple[str, dict[str, bytes]]]) -> tuple[int, str, int]:
    """Write (key, members) pairs, in the order given, as one shard at `path`.
    Returns (sample count, sha256 hex, bytes)."""
    with ShardWriter(path) as w:
        for key, members in samples:
            w.write(key, members)
    return w.samples, w.sha256, w.bytes


def _check_end(path: Path, offset: int) -> None:
    """A whole tar ends with two zero blocks after its last member; `tarfile` accepts a file cut
    at a member boundary as a shorter archive, so check for them."""
    with open(path, "rb") as fh:
        fh.seek(offset)
        end = fh.read(2 * tarfile.BLOCKSIZE)
    if len(end) < 2 * tarfile.BLOCKSIZE or end.count(0) != len(end):
        raise ShardError(f"{path}: truncated tar (no end-of-archive marker after the last member)")


def _key_member(name: str) -> tuple[str, str]:
    """(sample key, member suffix) of a tar member name: "dir/KEY.aif.png" -> ("KEY", "aif.png")."""
    key, _, member = name.rsplit("/", 1)[-1].partition(".")
    return key, member


class _HashingReader(io.RawIOBase):
    """A file read front to back, hashed as it goes (a tar stream's source)."""

    def __init__(self, fh):
        self._fh, self.hash = fh, hashlib.sha256()

    def readable(self) -> bool:
        return True

    def readinto(self, b) -> int:
        n = self._fh.readinto(b)
        self.hash.update(memoryview(b)[:n])
        return n

    def drain(self) -> str:
        """Read (and hash) what is left; the hex digest of the whole file."""
        while self.read(1 << 20):
            pass
        return self.hash.hexdigest()


def _entries(path: Path, sha256: str | None = None) -> Iterator[tuple[str, str, tarfile.TarInfo, tarfile.TarFile]]:
    """(key, suffix, header, open tar) of every regular member of a shard in file order, then
    the end-of-archive check: the one place a shard is opened for reading. With `sha256`, the
    file is read as a stream, every byte hashed, and a file whose hash differs fails at its
    end. `ShardError` names a bad file."""
    try:
        with open(path, "rb") as raw:
            src = _HashingReader(raw) if sha256 else raw
            with tarfile.open(fileobj=src, mode="r|" if sha256 else "r:") as tar:
                for info in tar:
                    if info.isfile():
                        yield (*_key_member(info.name), info, tar)
                end = tar.offset
            if sha256 and src.drain() != sha256:
                raise ShardError(f"{path}: sha256 differs from the manifest's (the shard is damaged or was "
                                 "rewritten); verify the data set (dofsynth verify) or make it again")
    except (tarfile.TarError, EOFError, OSError) as exc:
        raise ShardError(f"{path}: unreadable tar ({exc})") from exc
    _check_end(path, end)


def iter_members(path: str | os.PathLike, keys=None, data: bool = True, suffix: str | None = None,
                 sha256: str | None = None) -> Iterator[tuple[str, str, bytes | None]]:
    """(key, suffix, bytes) of every regular member of a shard in file order; with `keys`,
    only the members of those samples, with `suffix` only those members (e.g. "json": the
    others' data is skipped, not read); with `data=False`, None instead of the bytes (headers
    only); with `sha256`, the whole file is read and checked against it (at its end).
    `ShardError` names a bad file."""
    path = Path(path)
    for key, member, info, tar in _entries(path, sha256):
        if (keys is not None and key not in keys) or (suffix is not None and member != suffix):
            continue
        blob = None
        if data:
            try:
                blob = tar.extractfile(info).read()
            except (tarfile.TarError, EOFError, OSError) as exc:
                raise ShardError(f"{path}: unreadable tar ({exc})") from exc
            if len(blob) != info.size:
                raise ShardError(f"{path}: member {info.name} is truncated")
        yield key, member, blob


def read_shard(path: str | os.PathLike, keys=None, sha256: str | None = None) -> Iterator[tuple[str, dict[str, bytes]]]:
    """Yield (key, {suffix: bytes}) per sample in file order (only `keys`, if given); with
    `sha256`, the whole file is hashed as it is read and a mismatch raises ShardError at its end."""
    current, members = None, {}
    for key, suffix, blob in iter_members(path, keys, sha256=sha256):
        if current is not None and key != current:
            yield current, members
            members = {}
        current = key
        members[suffix] = blob
    if current is not None:
        yield current, members


def member_index(path: str | os.PathLike, sha256: str | None = None) -> dict[str, dict[str, tuple[int, int]]]:
    """{key: {suffix: (byte offset of the data, size)}} of a shard, from its headers only: for
    random access to samples (`read_members`); with `sha256`, the whole file is read and
    checked against it. `ShardError` names a bad file."""
    index: dict[str, dict[str, tuple[int, int]]] = {}
    for key, member, info, _ in _entries(Path(path), sha256):
        index.setdefault(key, {})[member] = (info.offset_data, info.size)
    return index


def read_members(path: str | os.PathLike, members: dict[str, tuple[int, int]]) -> dict[str, bytes]:
    """{suffix: bytes} of one sample's entry of `member_index(path)`."""
    out = {}
    with open(path, "rb") as fh:
        for suffix, (offset, size) in members.items():
            fh.seek(offset)
            out[suffix] = fh.read(size)
            if len(out[suffix]) != size:
                raise ShardError(f"{path}: member {suffix} at byte {offset} is truncated")
    return out
