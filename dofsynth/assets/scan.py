"""Scanning asset folders: every image file (recursively, sorted), checked and turned into an
`Asset`, with its licence from a SOURCES.md table.

Foregrounds come in two layouts: a folder of RGBA cutouts, or a folder holding `fg/` and
`alpha/` (names set by `assets.fg_dir` / `assets.alpha_dir`) paired by relative path without
suffix (`fg/a/x.jpg` + `alpha/a/x.png`). A bad
file is skipped with a warning naming it (`on_bad = "skip"`, listed in `Scan.skipped`) or
stops the scan with `AssetError` naming it ("stop"). With `verify = "header"` only headers
(and the small mattes) are decoded here; the loaders decode and check the rest.
"""
from __future__ import annotations

import os
import re
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dofsynth.progress import track
from dofsynth.assets.decode import (Asset, AssetError, alpha_bbox, alpha_of, area_thumb, check_size, cut_sides,
                                    background_alpha, decode_asset, image_header, unit_alpha)
from dofsynth.assets.similar import perceptual_hash
from dofsynth.files import sha256_bytes
from dofsynth.io import IMAGE_SUFFIXES


def walk_images(root: Path) -> tuple[list[Path], list[tuple[str, str]]]:
    """(image files under `root`, recursively, sorted by relative path; the symbolic links
    among them and their folders as (path relative to root, target)). Hidden names are
    skipped. Symbolic links are followed, to files and to folders (matting sets are often
    assembled from links), and listed, so a library says what it reached through them; a
    folder link that leads back into a folder already walked is not followed twice."""
    files, links, seen = [], [], {os.path.realpath(root)}
    for dirpath, dirnames, filenames in os.walk(root, followlinks=True):
        here = Path(dirpath)
        keep = []
        for d in sorted(dirnames):
            full = here / d
            if d.startswith("."):
                continue
            real = os.path.realpath(full)
            if full.is_symlink():
                links.append((full.relative_to(root).as_posix(), real))
            if real in seen:
                continue
            seen.add(real)
            keep.append(d)
        dirnames[:] = keep
        for f in filenames:
            full = here / f
            if f.startswith(".") or full.suffix.lower() not in IMAGE_SUFFIXES or not full.is_file():
                continue
            files.append(full)
            if full.is_symlink():
                links.append((full.relative_to(root).as_posix(), os.path.realpath(full)))
    return sorted(files, key=lambda p: p.relative_to(root).as_posix()), sorted(links)


def image_files(root: Path) -> list[Path]:
    """The image files of `walk_images`."""
    return walk_images(root)[0]


def rel_id(root: Path, p: Path) -> str:
    return p.relative_to(root).with_suffix("").as_posix()


def is_paired_layout(root: Path, fg_dir: str = "fg", alpha_dir: str = "alpha") -> bool:
    return (root / fg_dir).is_dir() and (root / alpha_dir).is_dir()


def read_sources_licences(folder: Path) -> dict[str, str]:
    """Licences from a SOURCES.md markdown table in `folder` or its parent: {absolute path: licence}.

    The table needs a column `file` (the path relative to SOURCES.md's folder, backticks allowed)
    and a column `licence` (or `license`)."""
    out: dict[str, str] = {}
    for where in (folder, folder.parent):
        src = where / "SOURCES.md"
        if not src.is_file():
            continue
        header: list[str] | None = None
        for line in src.read_text(encoding="utf-8", errors="replace").splitlines():
            if not line.strip().startswith("|"):
                header = None
                continue
            cells = [c.strip() for c in line.strip().strip("|").split("|")]
            if header is None:
                header = [c.lower() for c in cells]
                continue
            if all(re.fullmatch(r":?-+:?", c) for c in cells if c):
                continue
            col = {n: i for i, n in enumerate(header)}
            lic = col.get("licence", col.get("license"))
            if "file" not in col or lic is None or len(cells) <= max(col["file"], lic):
                continue
            rel = cells[col["file"]].strip("`")
            out.setdefault(str((where / rel).resolve()), cells[lic])
    return out


@dataclass
class Scan:
    """What a scan found: the assets, the skipped files (path, reason), the sha256 of every
    file it read (absolute path -> hex) and the symbolic links it followed (path, target)."""

    assets: list[Asset] = field(default_factory=list)
    skipped: list[tuple[str, str]] = field(default_factory=list)
    hashes: dict[str, str] = field(default_factory=dict)
    links: list[tuple[str, str]] = field(default_factory=list)


class Scanner:
    """Scans with a recipe's [assets] rules (`on_bad_asset`, `verify`, the paired layout's
    folder names, what to do with transparent backgrounds) into `out`."""

    def __init__(self, rules, licences: dict[str, str], out: Scan):
        self.rules, self.licences, self.out = rules, licences, out
        self.on_bad, self.decode = rules.on_bad_asset, rules.verify == "decode"

    def bad(self, path: str, reason: str) -> None:
        text = reason if reason.startswith(path) else f"{path}: {reason}"
        if self.on_bad == "stop":
            raise AssetError(text)
        self.out.skipped.append((path, reason))
        print(f"dofsynth: warning: skipping asset {text}", file=sys.stderr)

    def read(self, p: Path) -> bytes:
        try:
            data = p.read_bytes()
        except OSError as exc:
            raise AssetError(f"{p}: cannot read ({exc.strerror or exc})") from exc
        self.out.hashes[str(p)] = sha256_bytes(data)
        return data

    def probe(self, p: Path, data: bytes, check: bool = True,
              decode: bool | None = None) -> tuple[tuple[int, int], np.ndarray | None, int]:
        """(w, h), decoded image or None (header mode), channels."""
        if self.decode if decode is None else decode:
            img = decode_asset(data, str(p))
            h, w, c = img.shape
        else:
            img = None
            w, h, c = image_header(str(p))
        if check:
            check_size(str(p), w, h)
        return (w, h), img, c

    def _add(self, asset_id: str, kind: str, p: Path, size, **extra) -> None:
        self.out.assets.append(Asset(id=asset_id, kind=kind, path=str(p), sha256=self.out.hashes[str(p)], size=size,
                                     licence=self.licences.get(str(p), "unknown"), **extra))

    def background(self, root: Path, p: Path) -> None:
        try:
            data = self.read(p)
            size, img, _ = self.probe(p, data)
            if img is not None:
                background_alpha(img, str(p), self.rules.transparent_background)  # refuses if it must
            phash = perceptual_hash(data, str(p))
        except AssetError as exc:
            return self.bad(str(p), str(exc))
        self._add("bg/" + rel_id(root, p), "background", p, size, phash=phash)

    def cutout(self, root: Path, p: Path) -> None:
        try:
            data = self.read(p)
            size, img, c = self.probe(p, data)
            matte = {}
            if img is not None:
                matte = _matte(alpha_of(img, str(p), True), str(p))
            elif c not in (2, 4):
                raise AssetError(f"{p}: foreground without alpha ({c} channels; need RGBA or grey+alpha)")
            phash = perceptual_hash(data, str(p))
        except AssetError as exc:
            return self.bad(str(p), str(exc))
        self._add("fg/" + rel_id(root, p), "foreground", p, size, phash=phash, **matte)

    def pair(self, fg: Path, p: Path, a: Path) -> None:
        try:
            data = self.read(p)
            size, _, _ = self.probe(p, data)
            phash = perceptual_hash(data, str(p))
            # mattes are small single-channel files: always decoded, so the bbox and an empty
            # matte are known at scan time even with verify = "header"
            asize, aimg, _ = self.probe(a, self.read(a), check=False, decode=True)
            if asize != size:
                raise AssetError(f"{a}: alpha is {asize[0]}x{asize[1]} but its foreground {p} is "
                                 f"{size[0]}x{size[1]}")
            matte = _matte(alpha_of(aimg, str(a), False), str(a))
        except AssetError as exc:
            return self.bad(str(p), str(exc))
        self._add("fg/" + rel_id(fg, p), "foreground", p, size, alpha_path=str(a),
                  alpha_sha256=self.out.hashes[str(a)], phash=phash, **matte)

    def unique(self, assets: list[Asset]) -> list[Asset]:
        """`assets` without the later ones of a repeated id (files that differ only in suffix)."""
        seen: dict[str, Asset] = {}
        out = []
        for a in assets:
            if a.id in seen:
                self.bad(a.path, f"same id {a.id!r} as {seen[a.id].path} (two files differ only in suffix)")
                continue
            seen[a.id] = a
            out.append(a)
        return out


def _matte(alpha: np.ndarray, path: str) -> dict:
    """What a scan records of a matte: its bbox (refusing an empty one), cut sides, thumbnail."""
    alpha = unit_alpha(alpha)
    bbox = alpha_bbox(alpha, path)
    return {"bbox": bbox, "cut": cut_sides(alpha), "thumb": area_thumb(alpha, bbox)}


def _progress(files: list[Path], what: str):
    return track(files, f"scan {what}", "file", enabled=len(files) >= 500)


def _images(root: Path, sc: Scanner) -> list[Path]:
    """The image files under `root`; the links followed to them go into the scan."""
    files, links = walk_images(root)
    sc.out.links += [(str(root / rel), target) for rel, target in links]
    return files


def scan_backgrounds(root: Path, sc: Scanner) -> list[Asset]:
    n = len(sc.out.assets)
    for p in _progress(_images(root, sc), "backgrounds"):
        sc.background(root, p)
    return sc.unique(sc.out.assets[n:])


def scan_foregrounds(root: Path, sc: Scanner) -> list[Asset]:
    n = len(sc.out.assets)
    fg, al = root / sc.rules.fg_dir, root / sc.rules.alpha_dir
    if is_paired_layout(root, sc.rules.fg_dir, sc.rules.alpha_dir):
        alphas: dict[str, list[Path]] = {}
        for a in _images(al, sc):
            alphas.setdefault(rel_id(al, a), []).append(a)
        for p in _progress(_images(fg, sc), "foregrounds"):
            found = alphas.pop(rel_id(fg, p), [])
            if len(found) != 1:
                why = "no matte" if not found else "several mattes: " + ", ".join(map(str, found))
                sc.bad(str(p), f"foreground without alpha ({why} under {al} for this stem)")
                continue
            sc.pair(fg, p, found[0])
        for stem, left in sorted(alphas.items()):
            for a in left:
                sc.bad(str(a), f"alpha without a foreground (no {fg / stem}.* )")
    else:
        for p in _progress(_images(root, sc), "foregrounds"):
            sc.cutout(root, p)
    return sc.unique(sc.out.assets[n:])
