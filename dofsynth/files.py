"""Files written safely, and their checksums: the one temp-name scheme of dofsynth, atomic
writes (temp name, fsync, rename), sha256 of bytes and files, and canonical JSON.

A file under its final name is always whole: it is written as `.<name>.tmp-<pid>` beside its
final path and renamed (`os.replace`, atomic on one file system) only once complete and
fsync'ed; a failed write removes its temp file. Leftovers of a killed process match
`is_temp_name` and are removed by `remove_temp_files` (only while holding the folder's lock).
"""
from __future__ import annotations

import csv
import hashlib
import io
import json
import os
from pathlib import Path

TEMP_MARK = ".tmp-"


def temp_path(final: str | os.PathLike) -> Path:
    """The temporary name `final` is written under before its rename: `.<name>.tmp-<pid>`."""
    final = Path(final)
    return final.with_name(f".{final.name}{TEMP_MARK}{os.getpid()}")


def is_temp_name(name: str) -> bool:
    """Whether a file name is a temporary of `temp_path`."""
    return name.startswith(".") and TEMP_MARK in name


def final_name(temp_name: str) -> str:
    """The final file name of a temporary name (`.x.tar.tmp-12` -> `x.tar`)."""
    return temp_name[1:].split(TEMP_MARK)[0]


class AtomicFile:
    """A binary file written under `temp_path(path)`; `commit()` fsyncs and renames it to
    `path`, `abort()` (or leaving a `with` block by an exception) removes it.

        with AtomicFile(path) as fh:
            fh.write(b"...")
    """

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.tmp = temp_path(self.path)
        self.file = open(self.tmp, "wb")

    def write(self, data) -> int:
        return self.file.write(data)

    def commit(self) -> Path:
        try:
            self.file.flush()
            os.fsync(self.file.fileno())
            self.file.close()
            os.replace(self.tmp, self.path)
        except BaseException:
            self.abort()
            raise
        return self.path

    def abort(self) -> None:
        try:
            self.file.close()
        finally:
            self.tmp.unlink(missing_ok=True)

    def __enter__(self):
        return self.file

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.commit()
        else:
            self.abort()


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Write bytes to `path` through its temp name, fsync and rename: never a half file."""
    with AtomicFile(path) as fh:
        fh.write(data)
    return Path(path)


def check_writable(path: str | os.PathLike, what: str) -> Path:
    """Refuse, before any work, a file that cannot be written: its folder (or the nearest
    existing parent, which would hold it) must be writable. ValueError names it and `what`."""
    path = Path(path)
    folder = path.parent
    while not folder.exists() and folder != folder.parent:
        folder = folder.parent
    if not os.access(folder, os.W_OK | os.X_OK) or (path.exists() and not os.access(path, os.W_OK)):
        raise ValueError(f"{path}: cannot write the {what} there ({folder} is read-only); give another path "
                         "for it")
    return path


def remove_temp_files(folder: str | os.PathLike) -> list[Path]:
    """Delete leftover temporary files directly in `folder`; returns what was removed. Call
    only while holding the folder's lock (a live writer's temp file looks the same)."""
    folder = Path(folder)
    removed = []
    if folder.is_dir():
        for p in sorted(folder.iterdir()):
            if p.is_file() and is_temp_name(p.name):
                p.unlink(missing_ok=True)
                removed.append(p)
    return removed


def sha256_bytes(data: bytes) -> str:
    """sha256 hex digest of bytes."""
    return hashlib.sha256(data).hexdigest()


def sha256_file(path: str | os.PathLike, chunk: int = 1 << 20) -> tuple[str, int]:
    """(sha256 hex, size in bytes) of a file, read in 1 MiB blocks."""
    h, n = hashlib.sha256(), 0
    with open(path, "rb") as fh:
        while block := fh.read(chunk):
            h.update(block)
            n += len(block)
    return h.hexdigest(), n


def canonical_json(obj, indent: int | None = None) -> bytes:
    """Byte-deterministic JSON: sorted keys, Python's shortest round-trip float repr, no NaN,
    UTF-8, trailing newline; compact separators unless `indent` is given."""
    text = json.dumps(obj, sort_keys=True, indent=indent, ensure_ascii=False, allow_nan=False,
                      separators=(",", ": ") if indent is not None else (",", ":"))
    return (text + "\n").encode("utf-8")


def csv_text(fields: list[str], rows: list[dict]) -> str:
    """CSV text with a header row (as csv.DictWriter writes it)."""
    buf = io.StringIO(newline="")
    w = csv.DictWriter(buf, fieldnames=fields)
    w.writeheader()
    w.writerows(rows)
    return buf.getvalue()


def read_json(path: str | os.PathLike, error=ValueError):
    """Parse a JSON file; `error(message)` (naming the file) for text that is not JSON."""
    path = Path(path)
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise error(f"{path}: not valid JSON ({exc})") from exc
