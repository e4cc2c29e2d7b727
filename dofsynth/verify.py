"""Check a finished data set folder against its manifest and its own records.

`verify_dataset(out)` checks, and reports each problem with the place it was found:
- the manifest: readable, every listed shard present with the recorded size, sha256 and sample
  count; no unlisted shard files; no truncated or unreadable tar;
- every record: all members present and decodable, the JSON schema (required keys and types),
  value ranges (finite, disparities in [0, 1], images of the recorded size), and that the
  disparity map agrees with the record (opaque front/middle pixels carry that plane's
  disparity within 1e-6, bare background pixels the flat value or the recomputed ramp);
- that no asset appears in both splits (by asset id and by content sha256);
- with `deep=True`, that a sample of records re-rendered from their JSON alone gives the
  same member bytes.
"""
from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dofsynth import dataset as ds

DEPTH_TOL = 1e-6
RAMP_TOL = 1e-5
OPAQUE = 0.99   # cover >= OPAQUE: the plane hides everything behind it
CLEAR = 0.01    # cover <= CLEAR: the plane is absent there
ROLES = ("background", "front", "middle")


@dataclass(frozen=True)
class Problem:
    where: str      # a shard path, "shard path: key" or "manifest.json"
    message: str

    def __str__(self) -> str:
        return f"{self.where}: {self.message}"


@dataclass
class Report:
    out_dir: Path
    problems: list[Problem] = field(default_factory=list)
    notes: list[Problem] = field(default_factory=list)   # worth knowing, not failures
    shards: int = 0
    samples: int = 0
    deep_checked: int = 0
    splits: dict[str, int] = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return not self.problems

    def add(self, where, message) -> None:
        self.problems.append(Problem(str(where), message))

    def summary(self) -> str:
        per = ", ".join(f"{k} {v}" for k, v in self.splits.items())
        deep = f", {self.deep_checked} re-rendered" if self.deep_checked else ""
        state = "OK" if self.ok else f"FAILED with {len(self.problems)} problem(s)"
        return (f"verify {self.out_dir}: {self.shards} shards, {self.samples} samples ({per}){deep}: "
                f"{state}")

    def lines(self) -> list[str]:
        return [f"NOTE {p}" for p in self.notes] + [f"FAIL {p}" for p in self.problems] + [self.summary()]


# ---------------------------------------------------------------- schema
_NUM = (int, float)


def _is_num(v) -> bool:
    return isinstance(v, _NUM) and not isinstance(v, bool) and math.isfinite(v)


def _is_int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _unit(v) -> bool:
    return _is_num(v) and 0.0 <= v <= 1.0


def check_record_schema(rec) -> list[str]:
    """Problems with a record's keys, types and value ranges (docs/FORMAT.md, schema 1)."""
    if not isinstance(rec, dict):
        return ["record is not a JSON object"]
    errs: list[str] = []

    def want(obj, name, pred, what, prefix=""):
        if not isinstance(obj, dict) or name not in obj:
            errs.append(f"missing key {prefix}{name}")
            return False
        if not pred(obj[name]):
            errs.append(f"{prefix}{name} must be {what}, got {obj[name]!r}")
            return False
        return True

    want(rec, "schema_version", lambda v: v == 1, "1")
    want(rec, "key", lambda v: isinstance(v, str) and "." not in v, "a string without dots")
    want(rec, "split", lambda v: isinstance(v, str), "a string")
    want(rec, "index", lambda v: _is_int(v) and v >= 0, "an integer >= 0")
    want(rec, "seed", lambda v: isinstance(v, list) and v and all(_is_int(x) and x >= 0 for x in v),
         "a list of integers >= 0")
    want(rec, "size", lambda v: isinstance(v, list) and len(v) == 2 and all(_is_int(x) and x > 0 for x in v),
         "[H, W] positive integers")
    if want(rec, "assets", lambda v: isinstance(v, dict), "an object"):
        for role in ROLES:
            p = f"assets.{role}."
            if want(rec["assets"], role, lambda v: isinstance(v, dict), "an object", "assets."):
                a = rec["assets"][role]
                want(a, "id", lambda v: isinstance(v, str) and v, "a non-empty string", p)
                want(a, "sha256", lambda v: isinstance(v, str) and len(v) == 64, "a hex sha256", p)
                want(a, "path", lambda v: isinstance(v, str), "a string", p)
    if want(rec, "background", lambda v: isinstance(v, dict), "an object"):
        b, p = rec["background"], "background."
        want(b, "mode", lambda v: v in ("flat", "ramp"), "'flat' or 'ramp'", p)
        want(b, "b0", _unit, "a number in [0, 1]", p)
        want(b, "b1", _unit, "a number in [0, 1]", p)
        want(b, "direction", lambda v: v in ("horizontal", "vertical", None), "'horizontal', 'vertical' or null", p)
        want(b, "crop", lambda v: isinstance(v, list) and len(v) == 4 and all(_is_num(x) for x in v),
             "[x, y, w, h]", p)
        want(b, "flip", lambda v: isinstance(v, bool), "a boolean", p)
        if b.get("mode") == "ramp" and b.get("direction") is None:
            errs.append("background.direction must be set for a ramp")
    for role in ("front", "middle"):
        if want(rec, role, lambda v: isinstance(v, dict), "an object"):
            o, p = rec[role], f"{role}."
            want(o, "disparity", _unit, "a number in [0, 1]", p)
            want(o, "scale", lambda v: _is_num(v) and v > 0, "a number > 0", p)
            want(o, "x", _is_num, "a number", p)
            want(o, "y", _is_num, "a number", p)
            want(o, "flip", lambda v: isinstance(v, bool), "a boolean", p)
    if want(rec, "targets", lambda v: isinstance(v, list) and len(v) > 0, "a non-empty list"):
        for i, t in enumerate(rec["targets"]):
            p = f"targets[{i}]."
            if not isinstance(t, dict):
                errs.append(f"targets[{i}] must be an object")
                continue
            want(t, "focus", _unit, "a number in [0, 1]", p)
            want(t, "max_coc", lambda v: _is_num(v) and v >= 0, "a number >= 0", p)
    if want(rec, "aperture", lambda v: isinstance(v, dict), "an object"):
        ap = rec["aperture"]
        if want(ap, "kind", lambda v: v in ("disk", "polygon"), "'disk' or 'polygon'", "aperture."):
            if ap["kind"] == "polygon":
                want(ap, "blades", lambda v: _is_int(v) and v >= 3, "an integer >= 3", "aperture.")
                want(ap, "rotation", _is_num, "a number", "aperture.")
    want(rec, "options", lambda v: isinstance(v, dict), "an object")
    want(rec, "renderer", lambda v: isinstance(v, str), "a string")
    want(rec, "dofsynth_version", lambda v: isinstance(v, str), "a string")
    return errs


# ---------------------------------------------------------------- pixels
def expected_background(bg: dict, shape: tuple[int, int]) -> np.ndarray:
    """The background plane's disparity map recomputed from the record's `background` block
    with the generator's own `compose.background_disparity` (flat: b0 everywhere; horizontal
    ramp: b0 at the left column to b1 at the right; vertical: b0 at the bottom row to b1 at
    the top)."""
    from dofsynth.compose import background_disparity

    h, w = shape
    return background_disparity(bg["mode"], float(bg["b0"]), float(bg["b1"]), bg.get("direction"), h, w)


def _cover_bounds() -> tuple[float, float]:
    """(clear, opaque): a stored cover <= clear certainly lies below the compositor's coverage
    threshold and one >= opaque certainly above (8-bit quantisation is 1/510 either way).
    Without a known threshold: <= 0.01 is absent, >= 0.99 hides what lies behind."""
    try:
        from dofsynth.compose import COVER_THRESHOLD
    except ImportError:
        return CLEAR, OPAQUE
    return float(COVER_THRESHOLD) - 0.01, float(COVER_THRESHOLD) + 0.01


def check_pixels(sample: dict) -> list[str]:
    """Problems with a decoded sample's arrays against its (schema-valid) record."""
    rec, errs = sample["record"], []
    h, w = rec["size"]
    arrays = [("aif.png", sample["aif"]), ("depth.exr", sample["depth"]), ("cover.png", sample["cover"])]
    arrays += [(f"dof.{i}.png", d) for i, d in enumerate(sample["dof"])]
    for name, arr in arrays:
        if arr.shape[:2] != (h, w):
            errs.append(f"{name} is {arr.shape[1]}x{arr.shape[0]}, the record says {w}x{h}")
    if len(sample["dof"]) != len(rec["targets"]):
        errs.append(f"{len(sample['dof'])} DoF images for {len(rec['targets'])} targets")
    if errs:
        return errs
    depth = sample["depth"]
    if not np.all(np.isfinite(depth)):
        return [f"depth.exr has {int(np.sum(~np.isfinite(depth)))} NaN/inf pixels"]
    if depth.min() < 0 or depth.max() > 1:
        errs.append(f"depth.exr values outside [0, 1]: [{depth.min():.6g}, {depth.max():.6g}]")
    front, middle = sample["cover"][:, :, 0], sample["cover"][:, :, 1]
    f0, f1 = float(rec["front"]["disparity"]), float(rec["middle"]["disparity"])
    clear, opaque = _cover_bounds()
    regions = [
        ("front", front >= opaque, np.float32(f0), DEPTH_TOL),
        ("middle", (front <= clear) & (middle >= opaque), np.float32(f1), DEPTH_TOL),
    ]
    bare = (front <= clear) & (middle <= clear)
    bg = expected_background(rec["background"], (h, w))
    regions.append((f"{rec['background']['mode']} background", bare, bg, RAMP_TOL))
    for label, mask, want, tol in regions:
        if not mask.any():
            continue
        want_px = want[mask] if np.ndim(want) else np.full(int(mask.sum()), want, np.float32)
        err = np.abs(depth[mask].astype(np.float64) - want_px.astype(np.float64))
        bad = err > tol
        if bad.any():
            ys, xs = np.nonzero(mask)
            j = int(np.argmax(err))
            errs.append(f"depth disagrees with the record on {int(bad.sum())} {label} pixels "
                        f"(worst at x={xs[j]}, y={ys[j]}: {depth[ys[j], xs[j]]:.6g}, expected "
                        f"{float(want_px[j]):.6g})")
    return errs


# ---------------------------------------------------------------- files
def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def _check_shard_file(out_dir: Path, sh: ds.ShardInfo, report: Report) -> bool:
    """Size and hash; False if the file is missing (nothing more to read)."""
    path = out_dir / sh.path
    if not path.is_file():
        report.add(sh.path, "missing shard (listed in the manifest)")
        return False
    size = path.stat().st_size
    if sh.bytes is not None and size != int(sh.bytes):
        report.add(sh.path, f"size {size} bytes, the manifest says {sh.bytes} (truncated or rewritten?)")
    if sh.sha256 is None:
        report.add(sh.path, "the manifest records no sha256")
    elif _sha256(path) != sh.sha256:
        report.add(sh.path, "sha256 differs from the manifest (corrupted or rewritten)")
    return True


def _unlisted_shards(out_dir: Path, listed: set[str], report: Report) -> None:
    for path in sorted(out_dir.rglob("*.tar")):
        rel = path.relative_to(out_dir).as_posix()
        if rel not in listed:
            report.add(rel, "shard not listed in the manifest (left over from another run?)")


def _run_state(out_dir: Path, report: Report) -> None:
    """A live generator lock is a failure (the folder is changing under us); leftovers of a
    killed run (stale lock, progress file, temporary shards) are notes."""
    import fcntl
    import os

    lock = out_dir / ".lock"
    if lock.is_file():
        fd = os.open(lock, os.O_RDONLY)
        try:
            fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.read(fd, 64).decode(errors="replace").strip() or "unknown"
            report.add(".lock", f"a dofsynth run (pid {holder}) is writing into this folder; "
                                "verify again when it has finished")
        else:
            report.notes.append(Problem(".lock", "stale lock file of a finished or killed run"))
        finally:
            os.close(fd)
    if (out_dir / ".progress.jsonl").is_file():
        report.notes.append(Problem(".progress.jsonl", "progress file of an unfinished run "
                                    "(`dofsynth generate --resume` finishes it)"))
    for p in sorted(out_dir.rglob("*.tmp*")):
        if p.is_file():
            report.notes.append(Problem(p.relative_to(out_dir).as_posix(), "temporary file left by a killed run"))


# ---------------------------------------------------------------- driver
def verify_dataset(out_dir: str | Path, deep: bool = False, deep_n: int = 8, seed: int = 0,
                   recipe_path: str | Path | None = None, progress=None) -> Report:
    """Check everything described in the module docstring; never raises for data problems
    (they go into the returned report), only for a missing folder.

    `deep`: re-render `deep_n` records chosen with `seed`. The recipe is the manifest's own
    text; `recipe_path` gives a recipe file instead (it must have the manifest's sha256), for
    asset folders given relative to a recipe that was moved. `progress(k)` is called as samples
    are checked."""
    out_dir = Path(out_dir)
    if not out_dir.is_dir():
        raise FileNotFoundError(f"{out_dir}: no such data set folder")
    report = Report(out_dir)
    _run_state(out_dir, report)
    try:
        manifest = ds.load(out_dir)
        splits = ds.manifest_splits(manifest)
        shards = {s: ds.manifest_shards(manifest, s) for s in splits}
    except (FileNotFoundError, KeyError, TypeError, ValueError) as exc:
        report.add(ds.MANIFEST, f"unreadable manifest: {exc}")
        return report

    listed = {sh.path for s in splits for sh in shards[s]}
    _unlisted_shards(out_dir, listed, report)
    assets: dict[str, dict[tuple[str, str], str]] = {}   # split -> (kind, value) -> first place
    raw_by_key: dict[str, tuple[str, dict]] = {}         # the members of the --deep picks only
    deep_keys = _deep_picks(shards, deep_n, seed) if deep else set()
    for split in splits:
        assets[split] = {}
        report.splits[split] = 0
        expect_next = 0
        for sh in shards[split]:
            report.shards += 1
            if sh.first_index != expect_next:
                report.add(sh.path, f"first index {sh.first_index}, expected {expect_next} (gap or overlap)")
            expect_next = sh.first_index + sh.samples
            if not _check_shard_file(out_dir, sh, report):
                continue
            expected_keys = sh.keys()
            seen, broken = [], False
            try:
                for key, members in ds.iter_shard(out_dir / sh.path):
                    seen.append(key)
                    where = f"{sh.path}: {key}"
                    _check_sample(key, members, split, where, report, assets[split])
                    if key in deep_keys:
                        raw_by_key[key] = (sh.path, members)
                    if progress:
                        progress(1)
            except ds.READ_ERRORS as exc:
                broken = True
                report.add(sh.path, f"truncated or unreadable after {len(seen)} samples: {exc}")
            report.samples += len(seen)
            report.splits[split] += len(seen)
            if seen != expected_keys and not broken:
                report.add(sh.path, f"holds {len(seen)} samples {_span(seen)}, the manifest says "
                                    f"{sh.samples} {_span(expected_keys)}")
    _check_totals(manifest, shards, report)
    _check_leaks(assets, report)
    if deep and raw_by_key:
        _deep_check(out_dir, manifest, raw_by_key, report, recipe_path)
    return report


def _span(keys: list[str]) -> str:
    return f"({keys[0]}..{keys[-1]})" if keys else "(none)"


def _check_totals(manifest: dict, shards: dict[str, list], report: Report) -> None:
    """The manifest's per-split and overall totals agree with its own shard list."""
    for split, infos in shards.items():
        listed = manifest["splits"][split].get("samples")
        n = sum(sh.samples for sh in infos)
        if listed != n:
            report.add(ds.MANIFEST, f"split {split!r} lists {listed} samples, its shards {n}")
    totals = manifest.get("totals", {})
    for name, n in (("samples", sum(sh.samples for i in shards.values() for sh in i)),
                    ("shards", sum(len(i) for i in shards.values())),
                    ("bytes", sum(sh.bytes for i in shards.values() for sh in i))):
        if name in totals and totals[name] != n:
            report.add(ds.MANIFEST, f"totals.{name} is {totals[name]}, its shards add up to {n}")


def _check_sample(key, members, split, where, report, assets) -> None:
    try:
        sample = ds.decode_sample(members, key)
    except Exception as exc:  # any decoder failure is a data problem
        report.add(where, f"cannot decode: {exc}")
        return
    rec = sample["record"]
    errs = check_record_schema(rec)
    if not errs:
        if rec["key"] != key:
            errs.append(f"record key {rec['key']!r} differs from the tar key")
        if rec["split"] != split:
            errs.append(f"record split {rec['split']!r} in split {split!r}")
        if f"{split}-{rec['index']:07d}" != key:
            errs.append(f"record index {rec['index']} does not match the key")
        try:
            errs += check_pixels(sample)
        except Exception as exc:  # a record the checks cannot even evaluate is a problem too
            errs.append(f"pixel checks failed: {type(exc).__name__}: {exc}")
    for e in errs:
        report.add(where, e)
    if isinstance(rec, dict) and isinstance(rec.get("assets"), dict):
        for role, a in rec["assets"].items():
            if isinstance(a, dict):
                for kind in ("id", "sha256"):
                    if isinstance(a.get(kind), str):
                        assets.setdefault((kind, a[kind]), f"{where} ({role})")


def _check_leaks(assets: dict[str, dict], report: Report) -> None:
    splits = list(assets)
    for i, a in enumerate(splits):
        for b in splits[i + 1:]:
            for (kind, value) in sorted(set(assets[a]) & set(assets[b])):
                report.add(assets[b][(kind, value)],
                           f"asset {kind} {value[:16]} is in both splits: {b!r} here and {a!r} "
                           f"at {assets[a][(kind, value)]}")


def _deep_picks(shards: dict[str, list], n: int, seed: int) -> set[str]:
    """`n` keys of the whole data set (all splits) chosen with `seed`, from the manifest."""
    keys = sorted(k for infos in shards.values() for sh in infos for k in sh.keys())
    if not keys:
        return set()
    rng = np.random.default_rng(np.random.SeedSequence(seed))
    return {keys[i] for i in rng.choice(len(keys), size=min(n, len(keys)), replace=False).tolist()}


def _deep_check(out_dir, manifest, raw_by_key, report, recipe_path=None) -> None:
    """Re-render the picked records (`raw_by_key`) from their JSON and compare member bytes."""
    import json

    try:
        from dofsynth import assets as assets_mod
        from dofsynth import record, scene
    except ImportError as exc:
        report.add(ds.MANIFEST, f"--deep needs the generator modules: {exc}")
        return
    try:
        if recipe_path is not None:
            from dofsynth.config import load_recipe

            recipe = load_recipe(recipe_path)
            if recipe.sha256 != manifest["recipe"].get("sha256"):
                report.add(str(recipe_path), "--recipe: not the recipe this data set was made from "
                                             "(its sha256 differs from the manifest's)")
                return
        else:
            recipe = ds.recipe_from_manifest(manifest, out_dir)
        library = assets_mod.build_library(recipe)
    except Exception as exc:
        report.add(ds.MANIFEST, f"--deep: cannot rebuild the recipe and asset library: {exc}")
        return
    for key in sorted(raw_by_key):
        shard, members = raw_by_key[key]
        where = f"{shard}: {key}"
        try:
            rec = json.loads(members["json"].decode("utf-8"))
            fresh = record.render_sample(scene.Scene.from_dict(rec), library, recipe)
        except Exception as exc:
            report.add(where, f"--deep: re-rendering failed: {type(exc).__name__}: {exc}")
            continue
        report.deep_checked += 1
        fresh = {k.lstrip("."): v for k, v in fresh.items()}
        for suffix in sorted(set(members) | set(fresh)):
            if suffix not in fresh:
                report.add(where, f"--deep: re-render has no member {suffix}")
            elif suffix not in members:
                report.add(where, f"--deep: re-render adds member {suffix}")
            elif fresh[suffix] != members[suffix]:
                report.add(where, f"--deep: member {suffix} differs from a re-render of its JSON")
