"""`OUT/manifest.json`: the index of a finished data set, written last and atomically.

It holds everything needed to check and to rebuild the data set: the recipe (its full text and
sha256), the dofsynth version, and per split every shard with its first sample index, sample
count, sha256 and size. It holds no time stamp, host name or duration, so the same recipe gives
a byte-identical manifest on any machine, whatever the worker count.

While a run is in progress, `OUT/.progress.jsonl` records the plan (first line) and each shard
as it is finished (one JSON line each); `--resume` reads it, and it is deleted once the manifest
is written.

`summary()` is the small, recipe-text-free version that `--save-summary` copies to
`data_manifest/datasets/NAME.json` for the record of data sets made.
"""
from __future__ import annotations

import json
import os
from pathlib import Path

from dofsynth import __version__
from dofsynth.io import atomic_write_bytes
from dofsynth.shards import ShardInfo

MANIFEST_NAME = "manifest.json"
PROGRESS_NAME = ".progress.jsonl"
MANIFEST_SCHEMA_VERSION = 1


class ManifestError(ValueError):
    """A manifest or progress file that is missing, unreadable or inconsistent; names the file."""


def canonical_json(obj, indent: int | None = None) -> bytes:
    """Byte-deterministic JSON: sorted keys, Python's shortest round-trip float repr, no NaN,
    UTF-8, trailing newline."""
    text = json.dumps(obj, sort_keys=True, indent=indent, ensure_ascii=False, allow_nan=False,
                      separators=(",", ": ") if indent is not None else (",", ":"))
    return (text + "\n").encode("utf-8")


def recipe_block(recipe) -> dict:
    """The recipe as the manifest stores it: full text, sha256, path (as given), name."""
    path = getattr(recipe, "path", None)
    name = getattr(recipe, "name", None) or (Path(str(path)).stem if path else "recipe")
    return {"text": recipe.text, "sha256": recipe.sha256,
            "path": str(path) if path is not None else None, "name": str(name)}


def build_manifest(recipe, shards: dict[str, list[ShardInfo]], *, limits: dict[str, int | None] | None = None,
                   extra: dict | None = None) -> dict:
    """The manifest dict for finished `shards` (per split, any order: sorted here by index).

    `limits` is the `--limit` each split was made with (None: the recipe's full count); `extra`
    adds top-level keys such as the asset library's skipped files (must be deterministic: no
    times, no host names). Raises `ManifestError` if a split's shards leave a gap.
    """
    limits = limits or {}
    splits = {}
    for split in sorted(shards):
        infos = sorted(shards[split], key=lambda s: s.index)
        expect = 0
        for s in infos:
            if s.first_index != expect:
                raise ManifestError(f"split {split!r}: shard {s.name} starts at sample {s.first_index}, expected {expect}")
            expect += s.samples
        splits[split] = {
            "samples": sum(s.samples for s in infos),
            "recipe_samples": int(recipe.samples.count(split)),
            "limit": limits.get(split),
            "bytes": sum(s.bytes for s in infos),
            "shards": [
                {"name": s.name, "path": s.path, "index": s.index, "first_index": s.first_index,
                 "samples": s.samples, "sha256": s.sha256, "bytes": s.bytes}
                for s in infos
            ],
        }
    manifest = {
        "schema_version": MANIFEST_SCHEMA_VERSION,
        "dofsynth_version": __version__,
        "recipe": recipe_block(recipe),
        "splits": splits,
        "totals": {
            "samples": sum(v["samples"] for v in splits.values()),
            "shards": sum(len(v["shards"]) for v in splits.values()),
            "bytes": sum(v["bytes"] for v in splits.values()),
        },
    }
    if extra:
        manifest.update(extra)
    return manifest


def write_manifest(out: str | os.PathLike, manifest: dict) -> Path:
    """Write `OUT/manifest.json` atomically (temp name, fsync, rename)."""
    path = Path(out) / MANIFEST_NAME
    atomic_write_bytes(path, canonical_json(manifest, indent=1))
    return path


def load_manifest(out_or_path: str | os.PathLike) -> dict:
    """Read a manifest, given the data set folder or the manifest file itself."""
    p = Path(out_or_path)
    path = p / MANIFEST_NAME if p.is_dir() else p
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no manifest (an unfinished or foreign data set folder?)")
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ManifestError(f"{path}: not valid JSON ({exc})") from exc
    if not isinstance(data, dict) or "splits" not in data or "recipe" not in data:
        raise ManifestError(f"{path}: not a dofsynth manifest (no 'splits' or 'recipe')")
    if data.get("schema_version") != MANIFEST_SCHEMA_VERSION:
        raise ManifestError(f"{path}: schema_version {data.get('schema_version')!r} is not "
                            f"{MANIFEST_SCHEMA_VERSION}; this dofsynth {__version__} cannot read it")
    return data


def manifest_shard_infos(manifest: dict) -> dict[str, list[ShardInfo]]:
    """The shards a manifest lists, as ShardInfo per split."""
    out = {}
    for split, block in manifest["splits"].items():
        out[split] = [ShardInfo(split=split, index=int(s["index"]), name=s["name"],
                                first_index=int(s["first_index"]), samples=int(s["samples"]),
                                sha256=s["sha256"], bytes=int(s["bytes"])) for s in block["shards"]]
    return out


def summary(manifest: dict) -> dict:
    """A short record of a data set for `data_manifest/datasets/`: recipe name/path/sha256 (not
    its text), version, per split limit, samples/shards/bytes and one sha256 over the shard
    hashes (so two data sets compare with one string), and totals."""
    import hashlib

    splits = {}
    for split, block in sorted(manifest["splits"].items()):
        h = hashlib.sha256()
        for s in block["shards"]:
            h.update(f"{s['path']} {s['sha256']}\n".encode())
        splits[split] = {"samples": block["samples"], "limit": block.get("limit"),
                         "shards": len(block["shards"]), "bytes": block["bytes"],
                         "shards_sha256": h.hexdigest()}
    rec = manifest["recipe"]
    out = {
        "schema_version": manifest["schema_version"],
        "dofsynth_version": manifest["dofsynth_version"],
        "recipe": {"name": rec["name"], "path": rec["path"], "sha256": rec["sha256"]},
        "splits": splits,
        "totals": manifest["totals"],
    }
    if "skipped_assets" in manifest:
        out["skipped_assets"] = manifest["skipped_assets"]
    return out


def save_summary(manifest: dict, path: str | os.PathLike) -> Path:
    """Write `summary(manifest)` to `path` (e.g. data_manifest/datasets/NAME.json) atomically."""
    path = Path(path)
    if path.suffix != ".json":
        raise ValueError(f"--save-summary {path}: the summary file must end in .json")
    atomic_write_bytes(path, canonical_json(summary(manifest), indent=1))
    return path


# ---- progress file -------------------------------------------------------------------------

def start_progress(out: str | os.PathLike, header: dict) -> Path:
    """Create `OUT/.progress.jsonl` with its header line (the run's plan), atomically."""
    path = Path(out) / PROGRESS_NAME
    atomic_write_bytes(path, canonical_json({"header": header}))
    return path


def append_progress(out: str | os.PathLike, info: ShardInfo) -> None:
    """Record one finished shard (a single short append, fsync'ed)."""
    with open(Path(out) / PROGRESS_NAME, "ab") as fh:
        fh.write(canonical_json({"shard": info.to_dict()}))
        fh.flush()
        os.fsync(fh.fileno())


def read_progress(out: str | os.PathLike) -> tuple[dict | None, list[ShardInfo]]:
    """(header or None, finished shards) from `OUT/.progress.jsonl`; a torn last line (a run
    killed mid-append) is ignored."""
    path = Path(out) / PROGRESS_NAME
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


def remove_progress(out: str | os.PathLike) -> None:
    (Path(out) / PROGRESS_NAME).unlink(missing_ok=True)
