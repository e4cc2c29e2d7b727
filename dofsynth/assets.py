"""The asset library: background photos and foreground cutouts, scanned, checked and split.

`build_library(recipe)` scans the recipe's asset folders (recursively, sorted) or takes the
built-in assets, checks every file, splits the assets into train and test, and returns an
`AssetLibrary` whose loaders give linear-light float32 pixels.

Foregrounds come in two layouts: a folder of RGBA cutouts, or a folder holding `fg/` and
`alpha/` paired by relative path without suffix (`fg/a/x.jpg` + `alpha/a/x.png`).
A bad asset (unreadable, truncated, tiny, a cutout without alpha, an alpha of another size
than its photo, an empty alpha) is skipped with a warning naming it (`on_bad_asset = "skip"`,
listed in `library.skipped`) or stops the build with `AssetError` naming it ("stop"). With
`verify = "header"` only headers are read at scan time; the loaders then decode, re-check
and raise `AssetError` naming the file, so a bad file never becomes a silent wrong sample.
"""
from __future__ import annotations

import functools
import hashlib
import json
import re
import sys
from collections import OrderedDict
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from dofsynth import builtin_assets as B
from dofsynth.color import srgb8_to_linear, srgb_to_linear
from dofsynth.config import BUILTIN, Recipe
from dofsynth.io import IMAGE_SUFFIXES, decode_exr, decode_image

MIN_SIDE = 64
KINDS = ("background", "foreground")
SPLITS = ("train", "test")
MANIFEST_SCHEMA = 1


class AssetError(ValueError):
    """A bad or changed asset; the message names the file and the problem."""


@dataclass(frozen=True)
class Asset:
    id: str                          # "bg/REL" or "fg/REL" (REL: path under the root, no suffix); builtin:...
    kind: str                        # "background" | "foreground"
    path: str                        # absolute path, or "builtin:bg/NAME"
    sha256: str                      # of the file bytes (builtin: of the generated pixels)
    size: tuple[int, int]            # (w, h)
    licence: str = "unknown"
    alpha_path: str | None = None    # fg/ + alpha/ layout: the alpha file
    alpha_sha256: str | None = None
    bbox: tuple[int, int, int, int] | None = None  # (x, y, w, h) where alpha > 0; None = whole image

    @property
    def extent(self) -> tuple[int, int, int, int]:
        """(x, y, w, h) of the part of the image that is placed: the alpha's bbox, or all."""
        return self.bbox if self.bbox is not None else (0, 0, self.size[0], self.size[1])


# --------------------------------------------------------------------------------- decoding
def file_sha256(data: bytes) -> str:
    """sha256 hex digest of bytes."""
    return hashlib.sha256(data).hexdigest()


def _decode(data: bytes, path: str) -> np.ndarray:
    """(H, W, C) float32; sRGB-encoded [0, 1] for 8/16-bit files, stored values for EXR."""
    try:
        if path.lower().endswith(".exr"):
            return decode_exr(data, path, channels=None)
        return decode_image(data, path)
    except ValueError as exc:
        raise AssetError(str(exc)) from exc
    except Exception as exc:  # decoders raise assorted errors on malformed files
        raise AssetError(f"{path}: not a readable image ({exc})") from exc


def _decode_for_load(data: bytes, path: str) -> np.ndarray:
    """Like `_decode`, but an 8-bit file comes back as its uint8 codes (RGB(A) order), so the
    loaders linearize through the exact 256-entry table instead of a power per value."""
    if not path.lower().endswith(".exr"):
        import cv2

        buf = np.frombuffer(data, dtype=np.uint8)
        img = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED) if buf.size else None
        if img is not None and img.dtype == np.uint8:
            if img.ndim == 2:
                return img[:, :, None]
            if img.shape[2] == 3:
                return np.ascontiguousarray(img[:, :, ::-1])
            if img.shape[2] == 4:
                return np.ascontiguousarray(img[:, :, [2, 1, 0, 3]])
            return img
    return _decode(data, path)  # 16 bit, float, EXR, or an error that names the file


def _unit(a: np.ndarray) -> np.ndarray:
    """A channel as float32 in [0, 1] (uint8 codes / 255, as io.decode_image does)."""
    return a.astype(np.float32) / 255.0 if a.dtype == np.uint8 else a


def image_header(path: str) -> tuple[int, int, int]:
    """(w, h, channels) from the file header only."""
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(path)
    if inp is None:
        raise AssetError(f"{path}: not a readable image ({oiio.geterror().strip()})")
    try:
        spec = inp.spec()
        return spec.width, spec.height, spec.nchannels
    finally:
        inp.close()


def _check_size(path: str, w: int, h: int) -> None:
    if min(w, h) < MIN_SIDE:
        raise AssetError(f"{path}: tiny image ({w}x{h}); need at least {MIN_SIDE} px on each side")


def _alpha_of(img: np.ndarray, path: str, is_cutout: bool) -> np.ndarray:
    c = img.shape[2]
    if is_cutout:
        if c not in (2, 4):
            raise AssetError(f"{path}: foreground without alpha ({c} channels; need RGBA or grey+alpha, "
                             f"or put it in fg/ with its matte in alpha/)")
        return img[:, :, c - 1]
    return img[:, :, c - 1] if c in (2, 4) else img[:, :, 0]


def _check_alpha(alpha: np.ndarray, path: str) -> tuple[int, int, int, int]:
    """Refuse an empty alpha; return the bbox (x, y, w, h) of alpha > 0."""
    if not np.all(np.isfinite(alpha)):
        raise AssetError(f"{path}: alpha contains NaN or inf")
    on = alpha > 0
    if not on.any():
        raise AssetError(f"{path}: empty alpha (fully transparent)")
    rows, cols = np.flatnonzero(on.any(axis=1)), np.flatnonzero(on.any(axis=0))
    return int(cols[0]), int(rows[0]), int(cols[-1] - cols[0] + 1), int(rows[-1] - rows[0] + 1)


def _colour_linear(img: np.ndarray, path: str) -> np.ndarray:
    c = img.shape[2]
    colour = img[:, :, :1] if c in (1, 2) else img[:, :, :3]
    if colour.shape[2] == 1:
        colour = np.repeat(colour, 3, axis=2)
    if colour.dtype == np.uint8:
        return srgb8_to_linear(colour)
    if path.lower().endswith(".exr"):
        return np.clip(colour, 0.0, None).astype(np.float32)
    return srgb_to_linear(colour)


# ----------------------------------------------------------------------------------- scanning
def image_files(root: Path) -> list[Path]:
    """Image files under `root`, recursively, sorted by relative path (hidden names skipped)."""
    out = [p for p in root.rglob("*") if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES
           and not any(part.startswith(".") for part in p.relative_to(root).parts)]
    return sorted(out, key=lambda p: p.relative_to(root).as_posix())


def _rel_id(root: Path, p: Path) -> str:
    return p.relative_to(root).with_suffix("").as_posix()


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
class _Scan:
    assets: list[Asset] = field(default_factory=list)
    skipped: list[tuple[str, str]] = field(default_factory=list)
    hashes: dict[str, str] = field(default_factory=dict)  # absolute path -> sha256 of every file read


class _Scanner:
    def __init__(self, on_bad: str, verify: str, licences: dict[str, str], out: _Scan):
        self.on_bad, self.decode, self.licences, self.out = on_bad, verify == "decode", licences, out

    def bad(self, path: str, reason: str) -> None:
        if self.on_bad == "stop":
            raise AssetError(reason if reason.startswith(path) else f"{path}: {reason}")
        self.out.skipped.append((path, reason))
        print(f"dofsynth: warning: skipping asset {reason if reason.startswith(path) else path + ': ' + reason}",
              file=sys.stderr)

    def read(self, p: Path) -> bytes:
        try:
            data = p.read_bytes()
        except OSError as exc:
            raise AssetError(f"{p}: cannot read ({exc.strerror or exc})") from exc
        self.out.hashes[str(p)] = file_sha256(data)
        return data

    def probe(self, p: Path, data: bytes, check_size: bool = True,
              decode: bool | None = None) -> tuple[tuple[int, int], np.ndarray | None, int]:
        """(w, h), decoded image or None (header mode), channels."""
        if self.decode if decode is None else decode:
            img = _decode(data, str(p))
            h, w, c = img.shape
        else:
            img = None
            w, h, c = image_header(str(p))
        if check_size:
            _check_size(str(p), w, h)
        return (w, h), img, c

    def background(self, root: Path, p: Path) -> None:
        try:
            data = self.read(p)
            size, img, _ = self.probe(p, data)
        except AssetError as exc:
            return self.bad(str(p), str(exc))
        self.out.assets.append(Asset(id="bg/" + _rel_id(root, p), kind="background", path=str(p),
                                     sha256=self.out.hashes[str(p)], size=size,
                                     licence=self.licences.get(str(p), "unknown")))

    def cutout(self, root: Path, p: Path) -> None:
        try:
            data = self.read(p)
            size, img, c = self.probe(p, data)
            bbox = None
            if img is not None:
                bbox = _check_alpha(_alpha_of(img, str(p), True), str(p))
            elif c not in (2, 4):
                raise AssetError(f"{p}: foreground without alpha ({c} channels; need RGBA or grey+alpha)")
        except AssetError as exc:
            return self.bad(str(p), str(exc))
        self.out.assets.append(Asset(id="fg/" + _rel_id(root, p), kind="foreground", path=str(p),
                                     sha256=self.out.hashes[str(p)], size=size,
                                     licence=self.licences.get(str(p), "unknown"), bbox=bbox))

    def pair(self, root: Path, p: Path, a: Path) -> None:
        try:
            data = self.read(p)
            size, _, _ = self.probe(p, data)
            adata = self.read(a)
            # mattes are small single-channel files: always decoded, so the bbox and an empty
            # matte are known at scan time even with verify = "header"
            asize, aimg, _ = self.probe(a, adata, check_size=False, decode=True)
            if asize != size:
                raise AssetError(f"{a}: alpha is {asize[0]}x{asize[1]} but its foreground {p} is "
                                 f"{size[0]}x{size[1]}")
            bbox = _check_alpha(_alpha_of(aimg, str(a), False), str(a))
        except AssetError as exc:
            return self.bad(str(p), str(exc))
        self.out.assets.append(Asset(id="fg/" + _rel_id(root / "fg", p), kind="foreground", path=str(p),
                                     sha256=self.out.hashes[str(p)], size=size,
                                     licence=self.licences.get(str(p), "unknown"),
                                     alpha_path=str(a), alpha_sha256=self.out.hashes[str(a)], bbox=bbox))


def _unique(sc: _Scanner, assets: list[Asset]) -> list[Asset]:
    seen: dict[str, Asset] = {}
    out = []
    for a in assets:
        if a.id in seen:
            sc.bad(a.path, f"same id {a.id!r} as {seen[a.id].path} (two files differ only in suffix)")
            continue
        seen[a.id] = a
        out.append(a)
    return out


def is_paired_layout(root: Path) -> bool:
    return (root / "fg").is_dir() and (root / "alpha").is_dir()


def _progress(files: list[Path], what: str):
    from tqdm import tqdm

    return tqdm(files, desc=f"scan {what}", unit="file", disable=len(files) < 500, file=sys.stderr)


def scan_backgrounds(root: Path, sc: _Scanner) -> list[Asset]:
    n = len(sc.out.assets)
    for p in _progress(image_files(root), "backgrounds"):
        sc.background(root, p)
    return _unique(sc, sc.out.assets[n:])


def scan_foregrounds(root: Path, sc: _Scanner) -> list[Asset]:
    n = len(sc.out.assets)
    if is_paired_layout(root):
        alphas: dict[str, list[Path]] = {}
        for a in image_files(root / "alpha"):
            alphas.setdefault(_rel_id(root / "alpha", a), []).append(a)
        for p in _progress(image_files(root / "fg"), "foregrounds"):
            found = alphas.pop(_rel_id(root / "fg", p), [])
            if len(found) != 1:
                why = "no matte" if not found else "several mattes: " + ", ".join(map(str, found))
                sc.bad(str(p), f"foreground without alpha ({why} under {root / 'alpha'} for this stem)")
                continue
            sc.pair(root, p, found[0])
        for stem, left in sorted(alphas.items()):
            for a in left:
                sc.bad(str(a), f"alpha without a foreground (no {root / 'fg' / stem}.* )")
    else:
        for p in _progress(image_files(root), "foregrounds"):
            sc.cutout(root, p)
    return _unique(sc, sc.out.assets[n:])


# ---------------------------------------------------------------------------------- manifests
def load_manifest(path: str | Path) -> tuple[Path, dict[str, dict]]:
    """(root, {absolute path: entry}) of a pinning manifest written by `dofsynth assets scan`."""
    path = Path(path)
    if not path.is_file():
        raise AssetError(f"{path}: no such asset manifest")
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
        if doc.get("schema_version") != MANIFEST_SCHEMA:
            raise ValueError(f"schema_version {doc.get('schema_version')!r}, expected {MANIFEST_SCHEMA}")
        root = (path.parent / doc["root"]).resolve()
        entries = {str((root / e["path"]).resolve()): e for e in doc["files"]}
    except (ValueError, KeyError, TypeError) as exc:
        raise AssetError(f"{path}: not a dofsynth asset manifest ({exc})") from exc
    return root, entries


def _check_pins(manifests: tuple[str, ...], scan: _Scan, used: list[Asset]) -> dict[str, str]:
    """Refuse files that changed, went missing or are not listed; return {path: licence}."""
    problems: list[str] = []
    licences: dict[str, str] = {}
    used_files = {f for a in used for f in (a.path, a.alpha_path) if f}
    for m in manifests:
        root, entries = load_manifest(m)
        for p, e in sorted(entries.items()):
            licences[p] = e.get("licence", "unknown")
            fp = Path(p)
            if not fp.is_file():
                problems.append(f"{p}: missing (pinned by {m})")
                continue
            sha = scan.hashes.get(p) or file_sha256(fp.read_bytes())
            if sha != e.get("sha256") or fp.stat().st_size != e.get("bytes", fp.stat().st_size):
                problems.append(f"{p}: changed since pinned by {m} (sha256 {sha[:12]}..., pinned "
                                f"{str(e.get('sha256'))[:12]}...)")
        for f in sorted(used_files):
            if Path(f).is_relative_to(root) and f not in entries:
                problems.append(f"{f}: not in the pinning manifest {m}")
    if problems:
        raise AssetError("asset files do not match their pinned manifest:\n  " + "\n  ".join(problems))
    return licences


# ------------------------------------------------------------------------------------ library
def _uniform(seed: int, asset_id: str) -> float:
    d = hashlib.sha256(f"dofsynth-split:{seed}:{asset_id}".encode("utf-8")).digest()
    return int.from_bytes(d[:8], "big") / 2.0**64


def assign_splits(assets: list[Asset], seed: int, test_share: float, need: dict[str, int]) -> dict[str, str]:
    """{asset id: split}. An asset is in test when a sha256-based uniform of (seed, id) is below
    `test_share`. Byte-identical files (same sha256) share the split of the smallest id among
    them, so a duplicate never leaks across. If a split that must hold samples gets fewer than
    `need[split]` assets, the assets nearest the threshold move over (deterministic; only
    happens for tiny sets)."""
    rep: dict[str, str] = {}
    for a in sorted(assets, key=lambda a: a.id):
        rep.setdefault(a.sha256, a.id)
    u = {a.id: _uniform(seed, rep[a.sha256]) for a in assets}
    order = sorted(assets, key=lambda a: (u[a.id], rep[a.sha256], a.id))
    n_test = sum(1 for a in order if u[a.id] < test_share)
    n_test = max(n_test, min(need.get("test", 0), len(order)))
    n_test = min(n_test, max(0, len(order) - need.get("train", 0)))
    while 0 < n_test < len(order) and order[n_test].sha256 == order[n_test - 1].sha256:
        n_test += 1  # never cut a group of duplicates
    return {a.id: ("test" if i < n_test else "train") for i, a in enumerate(order)}


CACHE_BYTES = 256 * 2**20  # decoded pixels kept per process (a 24 MP photo alone is 288 MB)


def _nbytes(value) -> int:
    return sum(a.nbytes for a in value) if isinstance(value, tuple) else value.nbytes


class AssetLibrary:
    """Sorted background and foreground assets, their split, and loaders (linear float32).

    Decoded assets are kept in a per-process LRU cache of at most `cache_size` entries and
    `cache_bytes` bytes of pixels (an asset larger than that is not kept): with thousands of
    photos a hit is rare, and the bound keeps a worker's memory flat."""

    def __init__(self, backgrounds: list[Asset], foregrounds: list[Asset], splits: dict[str, str],
                 skipped: list[tuple[str, str]] | None = None, cache_size: int = 8,
                 cache_bytes: int = CACHE_BYTES):
        self.backgrounds = sorted(backgrounds, key=lambda a: a.id)
        self.foregrounds = sorted(foregrounds, key=lambda a: a.id)
        self._splits = dict(splits)
        self.skipped = list(skipped or [])
        self._by_id = {a.id: a for a in (*self.backgrounds, *self.foregrounds)}
        self._cache: OrderedDict[str, object] = OrderedDict()
        self._cache_size = cache_size
        self._cache_bytes = cache_bytes

    def __getstate__(self) -> dict:
        """Pickled (to spawn workers, Ray tasks) without the decoded-pixel cache, but with the
        built-in assets it lists as drawn so far (uint8, 26 MB for all of them), which the
        receiving process then adopts instead of drawing them again."""
        keys = [a.path.split(":", 1)[1] for a in (*self.backgrounds, *self.foregrounds) if a.path.startswith("builtin:")]
        return {**self.__dict__, "_cache": OrderedDict(), "_builtin_pixels": B.generated(keys)}

    def __setstate__(self, state: dict) -> None:
        B.adopt(state.pop("_builtin_pixels", {}))
        self.__dict__.update(state)

    def __getitem__(self, asset_id: str) -> Asset:
        try:
            return self._by_id[asset_id]
        except KeyError:
            raise AssetError(f"{asset_id}: no such asset in this library") from None

    def split_of(self, asset: Asset | str) -> str:
        return self._splits[asset if isinstance(asset, str) else asset.id]

    def assets_for(self, kind: str, split: str) -> list[Asset]:
        if kind not in KINDS or split not in SPLITS:
            raise ValueError(f"kind must be one of {KINDS} and split one of {SPLITS}, got {kind!r}, {split!r}")
        pool = self.backgrounds if kind == "background" else self.foregrounds
        return [a for a in pool if self._splits[a.id] == split]

    def _cached(self, key: str, make):
        if key in self._cache:
            self._cache.move_to_end(key)
            return self._cache[key]
        value = make()
        if _nbytes(value) > self._cache_bytes:
            return value
        self._cache[key] = value
        while len(self._cache) > self._cache_size or sum(map(_nbytes, self._cache.values())) > self._cache_bytes:
            self._cache.popitem(last=False)
        return value

    def _read(self, path: str, sha: str | None) -> bytes:
        try:
            data = Path(path).read_bytes()
        except OSError as exc:
            raise AssetError(f"{path}: cannot read ({exc.strerror or exc})") from exc
        if sha is not None and file_sha256(data) != sha:
            raise AssetError(f"{path}: changed since the asset library was built (sha256 differs)")
        return data

    def load_background(self, asset: Asset) -> np.ndarray:
        """Linear-light RGB (H, W, 3) float32, read-only."""
        def make():
            if asset.path.startswith("builtin:"):
                img = srgb8_to_linear(B.background_pixels(asset.path.split("/", 1)[1]))
            else:
                raw = _decode_for_load(self._read(asset.path, asset.sha256), asset.path)
                _check_size(asset.path, raw.shape[1], raw.shape[0])
                img = _colour_linear(raw, asset.path)
            img = np.ascontiguousarray(img, dtype=np.float32)
            img.setflags(write=False)
            return img
        return self._cached(asset.id, make)

    def load_foreground(self, asset: Asset) -> tuple[np.ndarray, np.ndarray]:
        """(linear-light RGB (H, W, 3) float32 straight colour, alpha (H, W) float32), read-only."""
        def make():
            if asset.path.startswith("builtin:"):
                rgb8, a8 = B.foreground_pixels(asset.path.split("/", 1)[1])
                rgb, alpha = srgb8_to_linear(rgb8), a8.astype(np.float32) / 255
            else:
                raw = _decode_for_load(self._read(asset.path, asset.sha256), asset.path)
                _check_size(asset.path, raw.shape[1], raw.shape[0])
                if asset.alpha_path:
                    araw = _decode_for_load(self._read(asset.alpha_path, asset.alpha_sha256), asset.alpha_path)
                    if araw.shape[:2] != raw.shape[:2]:
                        raise AssetError(f"{asset.alpha_path}: alpha is {araw.shape[1]}x{araw.shape[0]} but "
                                         f"its foreground {asset.path} is {raw.shape[1]}x{raw.shape[0]}")
                    alpha, name = _alpha_of(araw, asset.alpha_path, False), asset.alpha_path
                else:
                    alpha, name = _alpha_of(raw, asset.path, True), asset.path
                if (raw.shape[1], raw.shape[0]) != asset.size:
                    raise AssetError(f"{asset.path}: is {raw.shape[1]}x{raw.shape[0]}, scanned as {asset.size}")
                alpha = _unit(alpha)
                _check_alpha(alpha, name)
                alpha = np.clip(alpha, 0.0, 1.0).astype(np.float32)
                rgb = _colour_linear(raw, asset.path)
                if asset.path.lower().endswith(".exr") and not asset.alpha_path:
                    # EXR colour is premultiplied by convention: store straight colour
                    rgb = np.where(alpha[..., None] > 0, rgb / np.maximum(alpha[..., None], 1e-6), 0.0)
            rgb = np.ascontiguousarray(rgb, dtype=np.float32)
            alpha = np.ascontiguousarray(alpha, dtype=np.float32)
            rgb.setflags(write=False)
            alpha.setflags(write=False)
            return rgb, alpha
        return self._cached(asset.id, make)


@functools.lru_cache(maxsize=None)
def builtin_assets(kind: str) -> tuple[Asset, ...]:
    """The built-in assets of `kind`, sorted by id (generated once per process)."""
    out = []
    if kind == "background":
        for name in B.BACKGROUND_NAMES:
            px = B.background_pixels(name)
            out.append(Asset(id=f"builtin:bg/{name}", kind=kind, path=f"builtin:bg/{name}",
                             sha256=B.pixels_sha256(px), size=(px.shape[1], px.shape[0]),
                             licence=B.background_licence(name)))
    elif kind == "foreground":
        for name in B.FOREGROUND_NAMES:
            rgb, a = B.foreground_pixels(name)
            out.append(Asset(id=f"builtin:fg/{name}", kind=kind, path=f"builtin:fg/{name}",
                             sha256=B.pixels_sha256(rgb, a), size=(rgb.shape[1], rgb.shape[0]),
                             licence=B.PROCEDURAL_LICENCE, bbox=_check_alpha(a, name)))
    else:
        raise ValueError(f"kind must be one of {KINDS}, got {kind!r}")
    return tuple(out)


def build_library(recipe: Recipe) -> AssetLibrary:
    """Scan (or generate) the recipe's assets, check them, pin them and split them."""
    src = recipe.assets
    scan = _Scan()
    lic: dict[str, str] = {}
    for folder in (src.backgrounds, src.foregrounds):
        if folder != BUILTIN:
            if not Path(folder).is_dir():
                raise FileNotFoundError(f"{recipe.path}: asset folder {folder} does not exist")
            lic.update(read_sources_licences(Path(folder)))
    sc = _Scanner(src.on_bad_asset, src.verify, lic, scan)
    bgs = list(builtin_assets("background")) if src.backgrounds == BUILTIN else scan_backgrounds(Path(src.backgrounds), sc)
    fgs = list(builtin_assets("foreground")) if src.foregrounds == BUILTIN else scan_foregrounds(Path(src.foregrounds), sc)
    if src.manifests:
        pinned = _check_pins(src.manifests, scan, [*bgs, *fgs])
        relic = lambda a: a if a.licence != "unknown" or a.path not in pinned else replace(a, licence=pinned[a.path])
        bgs, fgs = [relic(a) for a in bgs], [relic(a) for a in fgs]
    need = {s: 1 if recipe.samples.count(s) > 0 else 0 for s in SPLITS}
    splits = {**assign_splits(bgs, recipe.seed, src.test_share, need),
              **assign_splits(fgs, recipe.seed, src.test_share, {s: 2 * n for s, n in need.items()})}
    lib = AssetLibrary(bgs, fgs, splits, scan.skipped)
    for split in SPLITS:
        if need[split]:
            nb, nf = len(lib.assets_for("background", split)), len(lib.assets_for("foreground", split))
            if nb < 1 or nf < 2:
                raise AssetError(f"{recipe.path}: the {split} split has {nb} usable backgrounds and {nf} "
                                 f"foregrounds; a scene needs 1 background and 2 distinct foregrounds "
                                 f"(backgrounds: {src.backgrounds}, foregrounds: {src.foregrounds})")
    return lib
