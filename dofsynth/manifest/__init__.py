"""`OUT/manifest.json`: the index of a finished data set, written last and atomically.

It holds everything needed to check and to rebuild the data set: the recipe (its full text and
sha256), the dofsynth version, and per split every shard with its first sample index, sample
count, sha256 and size; what its samples hold (`format`: the renderer that made them and each
member they hold, with its type, dtype, range and meaning, the conventions:
dofsynth.record.format_description) and the versions of the libraries that make the bytes
(`libraries`). It holds no time stamp, host name or duration, so the same recipe and library
versions give a byte-identical manifest on any machine, whatever the worker count.

The package's other modules: `names` (the files a run writes into OUT), `progress` (the
progress file of a run), `usage` (asset usage per licence), `parts` (partial manifests of
`--shards A:B` runs and their merge).

`summary()` is the small, recipe-text-free version that `--save-summary` copies to
`data_manifest/datasets/NAME.json` for the record of data sets made.
"""
from __future__ import annotations

import hashlib
import os
from pathlib import Path

from dofsynth import __version__
from dofsynth.files import atomic_write_bytes, canonical_json, read_json
from dofsynth.manifest.names import MANIFEST_NAME
from dofsynth.manifest.usage import Usage
from dofsynth.recipe import SHIPPED_PREFIX, recipe_from_text
from dofsynth.record import format_description
from dofsynth.shipped import shipped_dir
from dofsynth.shards import ShardInfo

MANIFEST_SCHEMA_VERSION = 3  # 2: `format` and `libraries`; 3: `format` names the set's renderer and only its members
READABLE_SCHEMAS = (1, 2, 3)


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


def recipe_format(recipe) -> dict:
    """The `format` block of a recipe's data set: its renderer and the members it holds."""
    return format_description(recipe.render.method, recipe.render.members)


def build_manifest(recipe, shards: dict[str, list[ShardInfo]], *, limits: dict[str, int | None] | None = None,
                   extra: dict | None = None) -> dict:
    """The manifest dict for finished `shards` (per split, any order: sorted here by index).

    `limits` is the `--limit` each split was made with (None: the recipe's full count); `extra`
    adds top-level keys such as the asset library's skipped files (must be deterministic: no
    times, no host names). Raises `ManifestError` if a split's shards leave a gap.
    """
    return assemble_manifest(recipe_block(recipe), {s: int(recipe.samples.count(s)) for s in shards}, shards,
                             recipe_format(recipe), limits=limits, extra=extra)


def assemble_manifest(recipe: dict, recipe_samples: dict[str, int], shards: dict[str, list[ShardInfo]],
                      format: dict, *, limits: dict[str, int | None] | None = None, extra: dict | None = None) -> dict:
    """`build_manifest` from a recipe block (`recipe_block`), the recipe's per-split sample
    counts and its `recipe_format` instead of a Recipe: what `merge_parts` has."""
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
        "format": format,
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
    return {split: [ShardInfo.from_dict({**s, "split": split}) for s in block["shards"]]
            for split, block in manifest["splits"].items()}


def recipe_from_manifest(manifest: dict, out_dir: str | os.PathLike):
    """The recipe embedded in the manifest, parsed from its stored text as the generator parsed
    it. Relative asset folders resolve against the recorded recipe's folder when it still
    exists, else against the data set folder."""
    rec = manifest.get("recipe")
    if not isinstance(rec, dict) or not isinstance(rec.get("text"), str):
        raise ValueError(f"{Path(out_dir) / MANIFEST_NAME}: holds no recipe text")
    path = rec.get("path")
    if path and path.startswith(SHIPPED_PREFIX):  # a shipped recipe, by name: this install's copy's folder
        base = shipped_dir("recipes")
    else:
        base = Path(path).parent if path and Path(path).parent.is_dir() else Path(out_dir)
    return recipe_from_text(rec["text"], path or f"{Path(out_dir) / MANIFEST_NAME} (recipe)", base)


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


