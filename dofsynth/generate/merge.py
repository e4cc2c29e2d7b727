"""Joining the partial manifests of `generate --shards A:B` runs into OUT/manifest.json
(`dofsynth manifest merge`): the same bytes a single run of the recipe writes."""
from __future__ import annotations

from pathlib import Path

from dofsynth.files import atomic_write_bytes, canonical_json, is_temp_name
from dofsynth.generate.folder import remove_shard_temps
from dofsynth.generate.locks import LOCK_NAME, OutputLock
from dofsynth.manifest.card import write_card
from dofsynth.manifest.names import MANIFEST_NAME, PROGRESS_PART_RE
from dofsynth.manifest.parts import merge_parts


def merge(parts: list[Path], out: Path, keep_parts: bool = False) -> tuple[dict, list[str]]:
    """Merge `parts` into the manifest file `out`; check the shards against the folder of
    `out`; returns (manifest, removed files)."""
    if out.suffix != ".json":
        raise ValueError(f"--out {out}: the manifest file must end in .json")
    folder = out.parent
    removed: list[str] = []
    with OutputLock(folder):
        manifest = merge_parts(parts)
        for split in manifest["splits"].values():
            for s in split["shards"]:
                f = folder / s["path"]
                if not f.is_file():
                    raise FileNotFoundError(f"{f}: shard listed by the parts is missing from {folder}")
                if f.stat().st_size != s["bytes"]:
                    raise ValueError(f"{f}: {f.stat().st_size} bytes, the parts say {s['bytes']} (rerun its "
                                     "range with --resume)")
        data = canonical_json(manifest, indent=1)
        if out.name == MANIFEST_NAME:  # the data set's own manifest: its card first, as a single run does
            write_card(folder, manifest)
        atomic_write_bytes(out, data)
        if not keep_parts:
            for p in parts:
                Path(p).unlink(missing_ok=True)
                removed.append(Path(p).name)
        if out.name == MANIFEST_NAME:  # the data set's own manifest: tidy OUT like a single run's folder
            for p in sorted(folder.iterdir()):
                stale = (p.name.startswith(f"{LOCK_NAME}.part-") or PROGRESS_PART_RE.match(p.name)
                         or (is_temp_name(p.name) and p.is_file()))
                if stale:
                    p.unlink(missing_ok=True)
                    removed.append(p.name)
            removed += remove_shard_temps(folder)
    return manifest, removed
