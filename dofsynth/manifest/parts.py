"""Partial manifests of `generate --shards A:B` runs (`OUT/manifest.part-A-B.json`) and their
merge into the manifest a single run writes (`dofsynth manifest merge`)."""
from __future__ import annotations

import json
import os
from pathlib import Path

from dofsynth import __version__
from dofsynth.files import atomic_write_bytes, canonical_json, read_json
from dofsynth.manifest import MANIFEST_SCHEMA_VERSION, ManifestError, assemble_manifest, recipe_block, recipe_format
from dofsynth.manifest.names import part_name
from dofsynth.shards import ShardInfo


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
        "format": recipe_format(recipe),
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
    need = ("schema_version", "dofsynth_version", "recipe", "recipe_samples", "format", "plan", "range", "shards",
            "extra")
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
                          ("format", "sample format (renderer, members)"),
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
    covered, last, last_range = 0, None, None  # shards 0..covered-1 are in parts seen so far; `last` reaches furthest
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
    return assemble_manifest(first["recipe"], first["recipe_samples"], shards, first["format"],
                             limits=plan["limits"], extra=first["extra"])
