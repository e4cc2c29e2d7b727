"""`OUT/.progress.jsonl`: while a run is in progress it records the plan (first line) and each
shard as it is finished (one JSON line each, fsync'ed); `--resume` reads it, and it is deleted
once the manifest is written. A `--shards A:B` run keeps its own (`progress_part_name`)."""
from __future__ import annotations

import json
import os
from pathlib import Path

from dofsynth.files import atomic_write_bytes, canonical_json
from dofsynth.manifest.names import PROGRESS_NAME
from dofsynth.shards import ShardInfo


def start_progress(out: str | os.PathLike, header: dict, name: str = PROGRESS_NAME,
                   shards: list[ShardInfo] = ()) -> Path:
    """Write `OUT/.progress.jsonl` (or `OUT/<name>`) afresh, atomically: its header line (the
    run's plan) and a line per shard already made and verified (kept by a resume)."""
    path = Path(out) / name
    lines = [canonical_json({"header": header})] + [canonical_json({"shard": i.to_dict()}) for i in shards]
    atomic_write_bytes(path, b"".join(lines))
    return path


def append_progress(out: str | os.PathLike, info: ShardInfo, name: str = PROGRESS_NAME) -> None:
    """Record one finished shard (a single short append, fsync'ed)."""
    with open(Path(out) / name, "ab") as fh:
        fh.write(canonical_json({"shard": info.to_dict()}))
        fh.flush()
        os.fsync(fh.fileno())


def read_progress(out: str | os.PathLike, name: str = PROGRESS_NAME) -> tuple[dict | None, list[ShardInfo]]:
    """(header or None, finished shards) from `OUT/.progress.jsonl` (or `OUT/<name>`); a torn
    last line (a run killed mid-append) is ignored."""
    path = Path(out) / name
    if not path.is_file():
        return None, []
    header, infos = None, []
    for line in path.read_bytes().splitlines():
        try:
            obj = json.loads(line)
        except (UnicodeDecodeError, json.JSONDecodeError):
            continue
        if "header" in obj:
            header = obj["header"]
        elif "shard" in obj:
            try:
                infos.append(ShardInfo.from_dict(obj["shard"]))
            except (KeyError, TypeError, ValueError):
                continue
    return header, infos


def remove_progress(out: str | os.PathLike, name: str = PROGRESS_NAME) -> None:
    (Path(out) / name).unlink(missing_ok=True)
