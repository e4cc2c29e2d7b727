"""Pinning manifests of asset folders: written by `dofsynth assets scan` (`pin_folder`), read
when a recipe names one under `[assets] manifest` (`read_pins`, `check_pins`), so a changed,
missing or unlisted file stops the build instead of silently changing the data set.

A pinning manifest is JSON: `schema_version`, `root` (relative to the manifest's folder),
`files` (per file: path relative to root, sha256, bytes, width, height, channels, kind and
licence) and `skipped` (unreadable files with the reason).
"""
from __future__ import annotations

import os
import sys
from pathlib import Path

from dofsynth.progress import track
from dofsynth.assets.decode import Asset, AssetError, decode_asset, image_header
from dofsynth.assets.scan import Scan, image_files, is_paired_layout, read_sources_licences
from dofsynth.files import atomic_write_bytes, canonical_json, read_json, sha256_bytes, sha256_file

PINS_SCHEMA = 1


def _kind_of(rel: str, paired_root: bool, forced: str | None, channels: int, fg_dir: str, alpha_dir: str) -> str:
    parts = rel.split("/")
    if alpha_dir in parts[:-1]:
        return "alpha"
    if forced:
        return forced
    if paired_root and parts[0] == fg_dir:
        return "foreground"
    if paired_root and parts[0] in ("bg", "background", "backgrounds"):
        return "background"
    return "foreground" if channels in (2, 4) else "background"


def pin_folder(root: Path, out_dir: Path, kind: str | None = None, licence: str | None = None,
               progress: bool = True, decode: bool = True, fg_dir: str = "fg", alpha_dir: str = "alpha") -> dict:
    """The pinning manifest of every image under `root` (sorted); `root` is written relative
    to `out_dir`, the folder the manifest goes into. Every file is decoded (`decode=False`:
    headers only), so a truncated or unreadable one is listed under `skipped`, never pinned.
    `fg_dir` / `alpha_dir`: the paired layout's folder names (assets.fg_dir, assets.alpha_dir)."""
    root = root.resolve()
    if not root.is_dir():
        raise FileNotFoundError(f"{root}: no such asset folder")
    lic = read_sources_licences(root)
    for sub in sorted(p for p in root.iterdir() if p.is_dir()):
        for k, v in read_sources_licences(sub).items():
            lic.setdefault(k, v)
    paired = is_paired_layout(root, fg_dir, alpha_dir) or (root / fg_dir).is_dir()
    files, skipped = [], []
    for p in track(image_files(root), f"scan {root.name}", "file", enabled=progress):
        rel = p.relative_to(root).as_posix()
        data = p.read_bytes()
        try:
            w, h, c = image_header(str(p))
            if decode:
                img = decode_asset(data, str(p))
                if img.shape[:2] != (h, w):
                    raise AssetError(f"{p}: decodes to {img.shape[1]}x{img.shape[0]}, its header says {w}x{h}")
        except AssetError as exc:
            skipped.append({"path": rel, "reason": str(exc)})
            print(f"dofsynth assets scan: warning: skipping {exc}", file=sys.stderr)
            continue
        files.append({
            "path": rel, "sha256": sha256_bytes(data), "bytes": len(data), "width": w, "height": h,
            "channels": c, "kind": _kind_of(rel, paired, kind, c, fg_dir, alpha_dir),
            "licence": lic.get(str(p), licence or "unknown"),
        })
    return {"schema_version": PINS_SCHEMA,
            "root": Path(os.path.relpath(root, out_dir.resolve())).as_posix(),
            "files": files, "skipped": skipped}


def write_pins(path: str | os.PathLike, pins: dict) -> Path:
    """Write a pinning manifest atomically (sorted keys, one-space indent)."""
    return atomic_write_bytes(path, canonical_json(pins, indent=1))


def read_pins(path: str | Path) -> tuple[Path, dict[str, dict]]:
    """(root, {absolute path: entry}) of a pinning manifest written by `dofsynth assets scan`."""
    path = Path(path)
    if not path.is_file():
        raise AssetError(f"{path}: no such asset manifest")
    try:
        doc = read_json(path)
        if doc.get("schema_version") != PINS_SCHEMA:
            raise ValueError(f"schema_version {doc.get('schema_version')!r}, expected {PINS_SCHEMA}")
        root = (path.parent / doc["root"]).resolve()
        entries = {str((root / e["path"]).resolve()): e for e in doc["files"]}
    except (ValueError, KeyError, TypeError, AttributeError) as exc:
        raise AssetError(f"{path}: not a dofsynth asset manifest ({exc})") from exc
    return root, entries


def check_pins(manifests: tuple[str, ...], scan: Scan, used: list[Asset]) -> dict[str, str]:
    """Refuse files that changed, went missing or are not listed; return {path: licence}."""
    problems: list[str] = []
    licences: dict[str, str] = {}
    used_files = {f for a in used for f in (a.path, a.alpha_path) if f}
    for m in manifests:
        root, entries = read_pins(m)
        for p, e in sorted(entries.items()):
            licences[p] = e.get("licence", "unknown")
            fp = Path(p)
            if not fp.is_file():
                problems.append(f"{p}: missing (pinned by {m})")
                continue
            sha = scan.hashes.get(p) or sha256_file(fp)[0]
            if sha != e.get("sha256") or fp.stat().st_size != e.get("bytes", fp.stat().st_size):
                problems.append(f"{p}: changed since pinned by {m} (sha256 {sha[:12]}..., pinned "
                                f"{str(e.get('sha256'))[:12]}...)")
        for f in sorted(used_files):
            if Path(f).is_relative_to(root) and f not in entries:
                problems.append(f"{f}: not in the pinning manifest {m}")
    if problems:
        raise AssetError("asset files do not match their pinned manifest:\n  " + "\n  ".join(problems))
    return licences
