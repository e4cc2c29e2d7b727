"""The asset library: background photos and foreground cutouts, scanned, checked and split.

`build_library(recipe)` scans the recipe's asset folders (dofsynth.assets.scan) or takes the
built-in assets, checks the pins (dofsynth.assets.pins), splits the assets into train and test
(dofsynth.assets.splits) and returns an `AssetLibrary` whose loaders give linear-light float32
pixels. With `verify = "header"` the loaders decode, re-check and raise `AssetError` naming
the file, so a bad file never becomes a silent wrong sample; every load checks the file's sha256.
"""
from __future__ import annotations

import os
from collections import OrderedDict
from dataclasses import replace
from pathlib import Path

import numpy as np

from dofsynth.assets import builtin as B
from dofsynth.assets.decode import (KINDS, Asset, AssetError, alpha_bbox, alpha_of, check_size, colour_linear,
                                    decode_asset, flatten, is_exr, unit_alpha)
from dofsynth.assets.placement import too_small
from dofsynth.assets.foreground import estimate, estimator_id
from dofsynth.assets.pins import check_pins
from dofsynth.assets.scan import Scan, Scanner, read_sources_licences, scan_backgrounds, scan_foregrounds
from dofsynth.assets.similar import near_duplicate_groups
from dofsynth.assets.splits import assign_splits
from dofsynth.color import srgb8_to_linear
from dofsynth.files import canonical_json, sha256_bytes
from dofsynth.image import area_halve, premultiply
from dofsynth.recipe import BUILTIN, AssetSources, Recipe
from dofsynth.rng import SPLITS

CACHE_BYTES = 256 * 2**20  # decoded pixels kept per process (a 24 MP photo alone is 288 MB)
CACHE_ENV = "DOFSYNTH_ASSET_CACHE_MIB"  # another bound, MiB, for the processes that get it (0: none)


def cache_bytes() -> int:
    """The pixel cache bound of this process: $DOFSYNTH_ASSET_CACHE_MIB MiB, else CACHE_BYTES."""
    mib = os.environ.get(CACHE_ENV, "").strip()
    try:
        return int(float(mib) * 2**20) if mib else CACHE_BYTES
    except ValueError:
        raise ValueError(f"{CACHE_ENV}={mib!r}: expected a number of MiB") from None


def _nbytes(value) -> int:
    return sum(a.nbytes for a in value) if isinstance(value, tuple) else value.nbytes


class AssetLibrary:
    """Sorted background and foreground assets, their split, and loaders (linear float32).

    `rules`: the recipe's [assets] table (foreground estimation, flattening of transparent
    backgrounds). Decoded (and estimated, and pre-scaled) pixels are kept in a per-process LRU
    cache keyed by the files' sha256 and what was made of them, of at most `cache_bytes` bytes
    (default: `cache_bytes()`, read by each process; an entry larger than that is not kept),
    so a worker's memory stays flat however many photos there are."""

    def __init__(self, backgrounds: list[Asset], foregrounds: list[Asset], splits: dict[str, str],
                 skipped: list[tuple[str, str]] | None = None, rules: AssetSources | None = None,
                 cache_bytes: int | None = None, groups: list[list[str]] | None = None,
                 links: list[tuple[str, str]] | None = None):
        self.backgrounds = sorted(backgrounds, key=lambda a: a.id)
        self.foregrounds = sorted(foregrounds, key=lambda a: a.id)
        self.splits = dict(splits)
        self.skipped = list(skipped or [])
        self.groups = list(groups or [])  # near-duplicate assets that share a split (perceptual hash)
        self.links = list(links or [])    # symbolic links the scan followed: (path, target)
        self.rules = rules or AssetSources(backgrounds=BUILTIN, foregrounds=BUILTIN)
        self._by_id = {a.id: a for a in (*self.backgrounds, *self.foregrounds)}
        self._cache: OrderedDict[str, object] = OrderedDict()
        self._bad: dict[str, str] = {}  # asset id -> why its file failed to load
        self._cache_bytes = cache_bytes

    def __getstate__(self) -> dict:
        """Pickled (to spawn workers, Ray tasks) without the decoded-pixel cache, but with the
        built-in assets it lists as drawn so far (uint8, 26 MB for all of them), which the
        receiving process then adopts instead of drawing them again."""
        keys = [a.path.split(":", 1)[1] for a in (*self.backgrounds, *self.foregrounds) if a.path.startswith("builtin:")]
        return {**self.__dict__, "_cache": OrderedDict(), "_bad": {}, "_builtin_pixels": B.generated(keys)}

    def __setstate__(self, state: dict) -> None:
        B.adopt(state.pop("_builtin_pixels", {}))
        self.__dict__.update(state)

    def listing(self) -> dict[str, str]:
        """{asset id: sha256} of every asset (a matte's after its photo's, joined by "+"), by id:
        what a data set was made from, recorded in its manifest."""
        return {a.id: a.sha256 + (f"+{a.alpha_sha256}" if a.alpha_sha256 else "")
                for a in sorted((*self.backgrounds, *self.foregrounds), key=lambda a: a.id)}

    def fingerprint(self) -> str:
        """sha256 of `listing()` and the split of each asset: another photo, a changed or removed
        one gives another fingerprint (a resume with it is refused)."""
        return sha256_bytes(canonical_json([self.listing(), dict(sorted(self.splits.items()))]))

    def failure(self, asset: Asset) -> str | None:
        """Why `asset`'s files fail to load, or None when they load."""
        try:
            (self.load_background if asset.kind == "background" else self.load_foreground)(asset)
        except AssetError as exc:
            return str(exc)
        return None

    def colour(self, asset: Asset) -> str:
        """Where the loaders' colour of `asset` comes from, as its sample records say: "file",
        or "estimated:<estimator>-<version>" (a photo + matte pair with estimate_foreground)."""
        if asset.alpha_path and self.rules.estimate_foreground:
            return f"estimated:{estimator_id(self.rules.estimate_space)}"
        return "file"

    def matte(self, asset: Asset) -> str:
        """How the loaders' alpha of `asset` relates to its file, as its sample records say:
        "file", or "opaque_from:<v>" (a photo's matte, values >= v loaded as 1)."""
        if asset.kind == "background" or asset.path.startswith("builtin:") or self.rules.opaque_from >= 1.0:
            return "file"
        return f"opaque_from:{self.rules.opaque_from:g}"

    def __getitem__(self, asset_id: str) -> Asset:
        try:
            return self._by_id[asset_id]
        except KeyError:
            raise AssetError(f"{asset_id}: no such asset in this library") from None

    def assets_for(self, kind: str, split: str) -> list[Asset]:
        if kind not in KINDS or split not in SPLITS:
            raise ValueError(f"kind must be one of {KINDS} and split one of {SPLITS}, got {kind!r}, {split!r}")
        pool = self.backgrounds if kind == "background" else self.foregrounds
        return [a for a in pool if self.splits[a.id] == split]

    def _cached(self, asset: Asset, what: str, make):
        """`make()`'s read-only arrays for `asset`, kept in the LRU pixel cache under the asset's
        file hashes and `what` (e.g. "premul@1"); a file that fails is remembered as bad."""
        key = f"{asset.sha256}+{asset.alpha_sha256 or ''}:{what}"
        if key in self._cache:
            self._cache.move_to_end(key)
            return self._cache[key]
        if asset.id in self._bad:  # a bad file stays bad: not decoded again by this process
            raise AssetError(self._bad[asset.id], asset.id)
        try:
            value = make()
        except AssetError as exc:
            self._bad[asset.id] = str(exc)
            raise AssetError(str(exc), asset.id) from exc
        for a in value if isinstance(value, tuple) else (value,):
            a.setflags(write=False)
        bound = cache_bytes() if self._cache_bytes is None else self._cache_bytes
        if _nbytes(value) > bound:
            return value
        self._cache[key] = value
        while sum(map(_nbytes, self._cache.values())) > bound:
            self._cache.popitem(last=False)
        return value

    def _read(self, path: str, sha: str | None) -> bytes:
        try:
            data = Path(path).read_bytes()
        except OSError as exc:
            raise AssetError(f"{path}: cannot read ({exc.strerror or exc})") from exc
        if sha is not None and sha256_bytes(data) != sha:
            raise AssetError(f"{path}: changed since the asset library was built (sha256 differs)")
        return data

    def load_background(self, asset: Asset) -> np.ndarray:
        """Linear-light RGB (H, W, 3) float32 >= 0 (negative values of a float file clipped),
        read-only."""
        def make():
            if asset.path.startswith("builtin:"):
                img = srgb8_to_linear(B.background_pixels(asset.path.split("/", 1)[1]))
            else:
                raw = decode_asset(self._read(asset.path, asset.sha256), asset.path, codes=True)
                check_size(asset.path, raw.shape[1], raw.shape[0])
                img = flatten(colour_linear(raw, asset.path), raw, asset.path, self.rules.transparent_background)
            img = np.ascontiguousarray(img, dtype=np.float32)
            return np.maximum(img, 0.0, out=img if img.flags.writeable else None)
        return self._cached(asset, "linear", make)

    def load_foreground(self, asset: Asset) -> tuple[np.ndarray, np.ndarray]:
        """(linear-light RGB (H, W, 3) float32 straight colour, alpha (H, W) float32), read-only:
        for a photo + matte pair with `estimate_foreground`, the colour estimated inside the
        extent (`dofsynth.assets.foreground`)."""
        return self._cached(asset, "linear", lambda: self._foreground(asset, whole=True))

    def premultiplied(self, asset: Asset, level: int = 0) -> np.ndarray:
        """(h, w, 4) float32 >= 0 of a foreground's extent: linear colour x alpha, and alpha,
        read-only; at `level` k > 0 area-halved k times (`dofsynth.image.area_halve`), what an
        object placed at a small scale is resampled from. Cached by the files' sha256 and the
        level, so a worker keeps what it places, not whole photos."""
        if level > 0:
            return self._cached(asset, f"premul@{level}", lambda: area_halve(self.premultiplied(asset, level - 1)))

        def make():
            rgb, alpha = self._foreground(asset, whole=False)
            p = premultiply(rgb, alpha, (0, 0, alpha.shape[1], alpha.shape[0]))
            return np.maximum(p, 0.0, out=p)  # >= 0 once here: resampling keeps it so
        return self._cached(asset, "premul@0", make)

    def _foreground(self, asset: Asset, whole: bool) -> tuple[np.ndarray, np.ndarray]:
        """The foreground's (straight linear colour, alpha), decoded and checked, not cached:
        the whole photo, or (`whole=False`) only its extent."""
        x, y, w, h = asset.extent
        if asset.path.startswith("builtin:"):
            rgb8, a8 = B.foreground_pixels(asset.path.split("/", 1)[1])
            if not whole:
                rgb8, a8 = rgb8[y:y + h, x:x + w], a8[y:y + h, x:x + w]
            return srgb8_to_linear(rgb8), a8.astype(np.float32) / 255
        raw = decode_asset(self._read(asset.path, asset.sha256), asset.path, codes=True)
        check_size(asset.path, raw.shape[1], raw.shape[0])
        if asset.alpha_path:
            araw = decode_asset(self._read(asset.alpha_path, asset.alpha_sha256), asset.alpha_path, codes=True)
            if araw.shape[:2] != raw.shape[:2]:
                raise AssetError(f"{asset.alpha_path}: alpha is {araw.shape[1]}x{araw.shape[0]} but "
                                 f"its foreground {asset.path} is {raw.shape[1]}x{raw.shape[0]}")
            alpha, name = alpha_of(araw, asset.alpha_path, False), asset.alpha_path
        else:
            alpha, name = alpha_of(raw, asset.path, True), asset.path
        if (raw.shape[1], raw.shape[0]) != asset.size:
            raise AssetError(f"{asset.path}: is {raw.shape[1]}x{raw.shape[0]}, scanned as {asset.size}")
        alpha = unit_alpha(alpha)
        alpha_bbox(alpha, name)
        alpha = np.clip(alpha, 0.0, 1.0).astype(np.float32)
        alpha[alpha >= np.float32(self.rules.opaque_from)] = 1.0  # matting networks stop short of 255 (`matte`)
        if not whole:
            raw, alpha = raw[y:y + h, x:x + w], np.ascontiguousarray(alpha[y:y + h, x:x + w])
        rgb = colour_linear(raw, asset.path)
        if is_exr(asset.path) and not asset.alpha_path:
            # EXR colour is premultiplied by convention: store straight colour
            rgb = np.where(alpha[..., None] > 0, rgb / np.maximum(alpha[..., None], 1e-6), 0.0)
        if asset.alpha_path and self.rules.estimate_foreground:  # the photo's backdrop out of soft edges
            if whole:  # estimated over the extent, as for the extent alone
                rgb = np.array(rgb, dtype=np.float32)
                rgb[y:y + h, x:x + w] = estimate(np.ascontiguousarray(rgb[y:y + h, x:x + w]),
                                                 np.ascontiguousarray(alpha[y:y + h, x:x + w]),
                                                 asset.sha256, asset.alpha_sha256, self.rules.estimate_space)
            else:
                rgb = estimate(rgb, alpha, asset.sha256, asset.alpha_sha256, self.rules.estimate_space)
        return np.ascontiguousarray(rgb, dtype=np.float32), np.ascontiguousarray(alpha, dtype=np.float32)


def _too_small(sc: Scanner, asset: Asset, recipe: Recipe) -> bool:
    """Refuse (skip or stop, naming it) an asset too small for the recipe's frame size."""
    why = too_small(asset, recipe)
    if why is not None:
        sc.bad(asset.path, why)
    return why is not None


def build_library(recipe: Recipe) -> AssetLibrary:
    """Scan (or generate) the recipe's assets, check them, pin them and split them."""
    src = recipe.assets
    scan = Scan()
    lic: dict[str, str] = {}
    for folder in (src.backgrounds, src.foregrounds):
        if folder != BUILTIN:
            if not Path(folder).is_dir():
                raise FileNotFoundError(f"{recipe.path}: asset folder {folder} does not exist")
            lic.update(read_sources_licences(Path(folder)))
    sc = Scanner(src, lic, scan)
    bgs = list(B.builtin_assets("background")) if src.backgrounds == BUILTIN else scan_backgrounds(Path(src.backgrounds), sc)
    fgs = list(B.builtin_assets("foreground")) if src.foregrounds == BUILTIN else scan_foregrounds(Path(src.foregrounds), sc)
    bgs, fgs = ([a for a in kind if not _too_small(sc, a, recipe)] for kind in (bgs, fgs))
    if src.manifests:
        pinned = check_pins(src.manifests, scan, [*bgs, *fgs])
        relic = lambda a: a if a.licence != "unknown" or a.path not in pinned else replace(a, licence=pinned[a.path])
        bgs, fgs = [relic(a) for a in bgs], [relic(a) for a in fgs]
    need = {s: 1 if recipe.samples.count(s) > 0 else 0 for s in SPLITS}
    groups = [g for kind in (bgs, fgs) for g in near_duplicate_groups({a.id: a.phash for a in kind if a.phash is not None})]
    splits = {**assign_splits(bgs, recipe.seed, src.test_share, need, groups),
              **assign_splits(fgs, recipe.seed, src.test_share, {s: 2 * n for s, n in need.items()}, groups)}
    lib = AssetLibrary(bgs, fgs, splits, scan.skipped, rules=src, groups=groups, links=scan.links)
    for split in SPLITS:
        if need[split]:
            nb, nf = len(lib.assets_for("background", split)), len(lib.assets_for("foreground", split))
            if nb < 1 or nf < 2:
                raise AssetError(f"{recipe.path}: the {split} split has {nb} usable backgrounds and {nf} "
                                 f"foregrounds; a scene needs 1 background and 2 distinct foregrounds "
                                 f"(backgrounds: {src.backgrounds}, foregrounds: {src.foregrounds})")
    return lib
