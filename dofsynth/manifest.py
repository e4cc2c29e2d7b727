"""`OUT/manifest.json`: the index of a finished data set, written last and atomically.

It holds everything needed to check and to rebuild the data set: the recipe (its full text and
sha256), the dofsynth version, and per split every shard with its first sample index, sample
count, sha256 and size; what a sample holds (`format`: each member's type, dtype, range and
meaning, the conventions: dofsynth.record.format_description) and the versions of the libraries
that make the bytes (`libraries`). It holds no time stamp, host name or duration, so the same
recipe and library versions give a byte-identical manifest on any machine, whatever the worker
count.

While a run is in progress, `OUT/.progress.jsonl` records the plan (first line) and each shard
as it is finished (one JSON line each); `--resume` reads it, and it is deleted once the manifest
is written.

`summary()` is the small, recipe-text-free version that `--save-summary` copies to
`data_manifest/datasets/NAME.json` for the record of data sets made.
"""
from __future__ import annotations

import hashlib
import json
import os
import re
from pathlib import Path

from dofsynth import __version__
from dofsynth.files import atomic_write_bytes, canonical_json, read_json
from dofsynth.record import format_description
from dofsynth.shards import ShardInfo

MANIFEST_NAME = "manifest.json"
PROGRESS_NAME = ".progress.jsonl"
MANIFEST_SCHEMA_VERSION = 2  # 2: `format` and `libraries`
READABLE_SCHEMAS = (1, 2)


def library_versions() -> dict:
    """The versions of what makes a sample's bytes (the determinism caveat depends on them)."""
    import platform

    import cv2
    import numpy
    import OpenEXR
    import scipy

    out = {"python": platform.python_version(), "numpy": numpy.__version__, "opencv": cv2.__version__,
           "OpenEXR": getattr(OpenEXR, "__version__", "?"), "scipy": scipy.__version__}
    try:
        from importlib.metadata import version
        out["pymatting"] = version("pymatting")
    except Exception:  # not installed: photo + matte pairs cannot be generated either
        out["pymatting"] = None
    return out


class ManifestError(ValueError):
    """A manifest or progress file that is missing, unreadable or inconsistent; names the file."""


def recipe_block(recipe) -> dict:
    """The recipe as the manifest stores it: full text, sha256, path (as given), name."""
    return {"text": recipe.text, "sha256": recipe.sha256, "path": str(recipe.path), "name": recipe.name}


class Usage:
    """What the samples of a shard (or a data set) used: per licence, how many samples use an
    asset under it and which assets (each with its count of samples), and the asset files
    found bad when loaded. `to_dict()` is what ShardInfo.usage holds and, over all shards, the
    manifest's `licences` (and its `skipped_assets`, with the library's); `merge` adds another's."""

    def __init__(self, d: dict | None = None):
        d = d or {}
        self.licences = {lic: {"samples": int(b["samples"]), "assets": dict(b["assets"])}
                         for lic, b in d.get("licences", {}).items()}
        self.bad = dict(d.get("bad_assets", {}))

    def add(self, scene, library, bad: dict[str, str], rel) -> None:
        by_licence: dict[str, set[str]] = {}
        for ref in scene.assets.values():
            by_licence.setdefault(library[ref.id].licence, set()).add(ref.id)
        for lic, ids in by_licence.items():
            block = self.licences.setdefault(lic, {"samples": 0, "assets": {}})
            block["samples"] += 1
            for i in ids:
                block["assets"][i] = block["assets"].get(i, 0) + 1
        self.bad.update({rel(p): rel(why) for p, why in bad.items()})

    def merge(self, other: "Usage") -> "Usage":
        for lic, b in other.licences.items():
            mine = self.licences.setdefault(lic, {"samples": 0, "assets": {}})
            mine["samples"] += b["samples"]
            for i, n in b["assets"].items():
                mine["assets"][i] = mine["assets"].get(i, 0) + n
        self.bad.update(other.bad)
        return self

    def to_dict(self) -> dict:
        return {"licences": {lic: {"samples": b["samples"], "assets": dict(sorted(b["assets"].items()))}
                             for lic, b in sorted(self.licences.items())},
                "bad_assets": dict(sorted(self.bad.items()))}


def build_manifest(recipe, shards: dict[str, list[ShardInfo]], *, limits: dict[str, int | None] | None = None,
                   extra: dict | None = None) -> dict:
    """The manifest dict for finished `shards` (per split, any order: sorted here by index).

    `limits` is the `--limit` each split was made with (None: the recipe's full count); `extra`
    adds top-level keys such as the asset library's skipped files (must be deterministic: no
    times, no host names). Raises `ManifestError` if a split's shards leave a gap.
    """
    return assemble_manifest(recipe_block(recipe), {s: int(recipe.samples.count(s)) for s in shards}, shards,
                             limits=limits, extra=extra)


def assemble_manifest(recipe: dict, recipe_samples: dict[str, int], shards: dict[str, list[ShardInfo]], *,
                      limits: dict[str, int | None] | None = None, extra: dict | None = None) -> dict:
    """`build_manifest` from a recipe block (`recipe_block`) and the recipe's per-split sample
    counts instead of a Recipe: what `merge_parts` has."""
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
            "recipe_samples": int(recipe_samples[split]),
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
        "format": format_description(),
        "libraries": library_versions(),
        "recipe": dict(recipe),
        "splits": splits,
        "totals": {
            "samples": sum(v["samples"] for v in splits.values()),
            "shards": sum(len(v["shards"]) for v in splits.values()),
            "bytes": sum(v["bytes"] for v in splits.values()),
        },
    }
    if extra:
        manifest.update(extra)
    used = [i.usage for infos in shards.values() for i in infos if i.usage is not None]
    if used:
        total = Usage()
        for u in used:
            total.merge(Usage(u))
        manifest["licences"] = total.to_dict()["licences"]
        manifest["skipped_assets"] = with_bad_assets(manifest.get("skipped_assets", []), total.bad)
    return manifest


def with_bad_assets(skipped: list, bad: dict[str, str]) -> list[list[str]]:
    """The skipped files of a library ([path, reason]) and those found bad on loading, by path."""
    rows = {str(p): str(why) for p, why in skipped}
    rows.update({p: why for p, why in bad.items() if p not in rows})
    return [[p, rows[p]] for p in sorted(rows)]


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
    data = read_json(path, ManifestError)
    if not isinstance(data, dict) or "splits" not in data or "recipe" not in data:
        raise ManifestError(f"{path}: not a dofsynth manifest (no 'splits' or 'recipe')")
    if data.get("schema_version") not in READABLE_SCHEMAS:
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
    if "licences" in manifest:  # samples per licence (the assets are in the manifest)
        out["licences"] = {lic: b["samples"] for lic, b in manifest["licences"].items()}
    return out


def save_summary(manifest: dict, path: str | os.PathLike) -> Path:
    """Write `summary(manifest)` to `path` (e.g. data_manifest/datasets/NAME.json) atomically."""
    path = Path(path)
    if path.suffix != ".json":
        raise ValueError(f"--save-summary {path}: the summary file must end in .json")
    atomic_write_bytes(path, canonical_json(summary(manifest), indent=1))
    return path


# ---- progress file -------------------------------------------------------------------------

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


# ---- partial manifests (`generate --shards A:B`) and their merge ---------------------------

PART_RE = re.compile(r"^manifest\.part-(\d+)-(\d+)\.json$")
PROGRESS_PART_RE = re.compile(r"^\.progress\.part-(\d+)-(\d+)\.jsonl$")


def part_name(first: int, stop: int) -> str:
    """The partial manifest of shards first..stop-1 of the plan: "manifest.part-AAAAAA-BBBBBB.json"."""
    return f"manifest.part-{first:06d}-{stop:06d}.json"


def progress_part_name(first: int, stop: int) -> str:
    return f".progress.part-{first:06d}-{stop:06d}.jsonl"


def build_part(recipe, shard_range: tuple[int, int], plan: dict, shards: list[ShardInfo],
               extra: dict | None = None) -> dict:
    """The partial manifest of a `--shards A:B` run.

    `plan` describes the whole run the range belongs to: {"splits": [...], "limits": {split:
    limit}, "split_shards": {split: shard count}, "shards": total}; global shard g is shard g of
    the first split, then of the next, in `splits` order. `shards` are this range's ShardInfos.
    Holds everything `merge_parts` needs to write the manifest a single run writes."""
    order = {s: i for i, s in enumerate(plan["splits"])}
    return {
        "schema_version": MANIFEST_SCHEMA_VERSION,
        "dofsynth_version": __version__,
        "recipe": recipe_block(recipe),
        "recipe_samples": {s: int(recipe.samples.count(s)) for s in plan["splits"]},
        "plan": plan,
        "range": [int(shard_range[0]), int(shard_range[1])],
        "shards": [i.to_dict() for i in sorted(shards, key=lambda i: (order[i.split], i.index))],
        "extra": dict(extra or {}),
    }


def write_part(out: str | os.PathLike, part: dict) -> Path:
    path = Path(out) / part_name(*part["range"])
    atomic_write_bytes(path, canonical_json(part, indent=1))
    return path


def load_part(path: str | os.PathLike) -> dict:
    """Read a partial manifest; `ManifestError`/`FileNotFoundError` name the file."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such partial manifest")
    data = read_json(path, ManifestError)
    need = ("schema_version", "dofsynth_version", "recipe", "recipe_samples", "plan", "range", "shards", "extra")
    if not isinstance(data, dict) or any(k not in data for k in need):
        raise ManifestError(f"{path}: not a dofsynth partial manifest (written by generate --shards A:B)")
    if data["schema_version"] != MANIFEST_SCHEMA_VERSION:
        raise ManifestError(f"{path}: schema_version {data['schema_version']!r} is not {MANIFEST_SCHEMA_VERSION}")
    return data


def plan_index(plan: dict) -> list[tuple[str, int]]:
    """(split, shard index) of every global shard index of a plan."""
    return [(s, k) for s in plan["splits"] for k in range(int(plan["split_shards"][s]))]


def merge_parts(paths) -> dict:
    """The manifest of the whole data set from the partial manifests at `paths` (any order).

    Refuses, naming the offending files: parts of different recipes, dofsynth versions or plans
    (`--split`/`--limit`), parts whose ranges overlap, shards of the plan in no part (gaps), and
    a part whose shards are not its range. The result is byte-identical (`canonical_json`) to
    the manifest a single run of the same recipe and options writes."""
    paths = [Path(p) for p in paths]
    if not paths:
        raise ManifestError("no partial manifests to merge (expected manifest.part-A-B.json files)")
    parts = [(p, load_part(p)) for p in paths]
    p0, first = parts[0]
    for p, part in parts[1:]:
        r0, r1 = first["recipe"], part["recipe"]
        if r0["sha256"] != r1["sha256"]:
            raise ManifestError(f"mixed recipes: {p0} was made from {r0['path']} (sha256 {r0['sha256'][:12]}...), "
                                f"{p} from {r1['path']} (sha256 {r1['sha256'][:12]}...)")
        for key, what in (("recipe", "recipe name or path"), ("dofsynth_version", "dofsynth version"),
                          ("plan", "plan (--split / --limit)"), ("recipe_samples", "recipe sample counts"),
                          ("extra", "skipped or used assets")):
            if first[key] != part[key]:
                raise ManifestError(f"mixed parts: {p0} and {p} differ in their {what}: "
                                    f"{json.dumps(first[key])[:120]} vs {json.dumps(part[key])[:120]}")
    plan = first["plan"]
    index = plan_index(plan)
    total = len(index)
    if total != int(plan["shards"]):
        raise ManifestError(f"{p0}: its plan lists {plan['shards']} shards but its splits hold {total}")
    parts.sort(key=lambda pp: (pp[1]["range"][0], pp[1]["range"][1], str(pp[0])))
    covered, last = 0, None  # shards 0..covered-1 are in parts seen so far; `last` reaches furthest
    for p, part in parts:
        a, b = part["range"]
        if not 0 <= a < b <= total:
            raise ManifestError(f"{p}: range {a}:{b} is not inside the plan's {total} shards")
        if a < covered:
            raise ManifestError(f"overlap: {last} holds shards {last_range[0]}:{last_range[1]} and {p} holds {a}:{b}; "
                                f"shards {a}:{min(b, covered)} are in both")
        if a > covered:
            where = f"between {last} and {p}" if last is not None else f"before {p}"
            raise ManifestError(f"gap: shards {covered}:{a} of the plan's {total} are in no part ({where})")
        want = [f"{s}/{k}" for s, k in index[a:b]]
        got = [f"{d['split']}/{d['index']}" for d in part["shards"]]
        if got != want:
            raise ManifestError(f"{p}: lists shards {got[:3]}... but its range {a}:{b} holds {want[:3]}...")
        covered, last, last_range = b, p, (a, b)
    if covered < total:
        raise ManifestError(f"gap: shards {covered}:{total} of the plan's {total} are in no part (after {last})")
    shards: dict[str, list[ShardInfo]] = {s: [] for s in plan["splits"]}
    for _, part in parts:
        for d in part["shards"]:
            shards[d["split"]].append(ShardInfo.from_dict(d))
    return assemble_manifest(first["recipe"], first["recipe_samples"], shards, limits=plan["limits"],
                             extra=first["extra"])
