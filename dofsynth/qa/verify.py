"""Check a finished data set folder against its manifest and its own records.

`verify_dataset(out)` checks, and reports each problem with the place it was found:
- the manifest: readable, every listed shard present with the recorded size, sha256 and sample
  count; no unlisted shard files; no truncated or unreadable tar;
- every record: all members present and decodable, the JSON schema (required keys and types),
  value ranges (finite, disparities in [0, 1], images of the recorded size), and that the
  disparity map agrees with the record (opaque front/middle pixels carry that plane's
  disparity within 1e-6, bare background pixels the flat value or the recomputed ramp);
- that no asset appears in both splits (by asset id and by content sha256);
- a review's marks (OUT/qa-marks.json): a note of how many samples were rejected and kept,
  and a problem for each mark that no longer fits the set (dofsynth.qa.marks);
- with `deep=True`, that a sample of records re-rendered from their JSON alone gives the
  same member bytes.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dofsynth.assets import build_library
from dofsynth.files import is_temp_name, sha256_file
from dofsynth.generate.locks import LOCK_NAME, lock_state
from dofsynth.manifest import recipe_from_manifest
from dofsynth.manifest.names import MANIFEST_NAME, PROGRESS_NAME
from dofsynth.progress import note
from dofsynth.qa import dataset as ds
from dofsynth.qa.marks import MARKS_NAME, marks_summary, set_marks, stale
from dofsynth.qa.schema import check_pixels, check_record_schema
from dofsynth.recipe import load_recipe
from dofsynth.sample import render_sample
from dofsynth.scene import Scene
from dofsynth.shards import ShardInfo, read_shard


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


# ---------------------------------------------------------------- files
def _check_shard_file(out_dir: Path, sh: ShardInfo, report: Report) -> bool:
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
    elif sha256_file(path)[0] != sh.sha256:
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
    state, holder = lock_state(out_dir / LOCK_NAME)
    if state == "held":
        report.add(LOCK_NAME, f"a dofsynth run (pid {holder or 'unknown'}) is writing into this folder; "
                              "verify again when it has finished")
    elif state == "stale":
        report.notes.append(Problem(LOCK_NAME, "stale lock file of a finished or killed run"))
    if (out_dir / PROGRESS_NAME).is_file():
        report.notes.append(Problem(PROGRESS_NAME, "progress file of an unfinished run "
                                    "(`dofsynth generate --resume` finishes it)"))
    for p in sorted(out_dir.rglob(".*")):
        if p.is_file() and is_temp_name(p.name):
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
        report.add(MANIFEST_NAME, f"unreadable manifest: {exc}")
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
            seen, broken, problems_before = [], False, len(report.problems)
            try:
                for key, members in read_shard(out_dir / sh.path):
                    seen.append(key)
                    where = f"{sh.path}: {key}"
                    _check_sample(key, members, split, where, report, assets[split])
                    if key in deep_keys:
                        raw_by_key[key] = (sh.path, members)
                    if progress:
                        progress(1)
            except ds.READ_ERRORS as exc:
                broken = True
                report.add(sh.path, f"unreadable after {len(seen)} samples: {exc}")
            report.samples += len(seen)
            report.splits[split] += len(seen)
            note(f"  {sh.path}: {len(seen)} samples checked, {len(report.problems) - problems_before} problems")
            if seen != expected_keys and not broken:
                report.add(sh.path, f"holds {len(seen)} samples {_span(seen)}, the manifest says "
                                    f"{sh.samples} {_span(expected_keys)}")
    _check_totals(manifest, shards, report)
    _check_leaks(assets, report)
    _check_marks(out_dir, manifest, report)
    if deep and raw_by_key:
        _deep_check(out_dir, manifest, raw_by_key, report, recipe_path)
    return report


def _span(keys: list[str]) -> str:
    return f"({keys[0]}..{keys[-1]})" if keys else "(none)"


def _check_totals(manifest: dict, shards: dict[str, list], report: Report) -> None:
    """The manifest's per-split and overall totals agree with its own shard list."""
    for split, infos in shards.items():
        block = manifest["splits"][split]
        listed = block.get("samples")
        n = sum(sh.samples for sh in infos)
        if listed != n:
            report.add(MANIFEST_NAME, f"split {split!r} lists {listed} samples, its shards {n}")
        made = block.get("recipe_samples")
        want = made if block.get("limit") is None or made is None else min(made, block["limit"])
        if want is not None and n != want:
            report.add(MANIFEST_NAME, f"split {split!r} holds {n} samples in its shards, but its recipe makes {made}"
                                      f" (limit {block.get('limit')}): {want} expected; shards are missing from "
                                      "the manifest or the data set")
    totals = manifest.get("totals", {})
    for name, n in (("samples", sum(sh.samples for i in shards.values() for sh in i)),
                    ("shards", sum(len(i) for i in shards.values())),
                    ("bytes", sum(sh.bytes for i in shards.values() for sh in i))):
        if name in totals and totals[name] != n:
            report.add(MANIFEST_NAME, f"totals.{name} is {totals[name]}, its shards add up to {n}")


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
                shown = value if kind == "id" else value[:16] + "..."
                report.add(assets[b][(kind, value)],
                           f"asset {kind} {shown} is in both splits: {b!r} here and {a!r} "
                           f"at {assets[a][(kind, value)]}")


def _check_marks(out_dir: Path, manifest: dict, report: Report) -> None:
    """A review's marks (OUT/qa-marks.json): reported as a note; marks that no longer fit the
    set (a sample gone, a shard made again since the review) are problems."""
    if not (out_dir / MARKS_NAME).is_file():
        return
    try:
        marks = set_marks(out_dir)
    except ValueError as exc:
        report.add(MARKS_NAME, str(exc))
        return
    for why in stale(marks, manifest):
        report.add(MARKS_NAME, f"stale review mark: {why}")
    bad = sorted(k for k, m in marks.items() if m["mark"] == "reject")
    if marks:
        report.notes.append(Problem(MARKS_NAME, f"review: {marks_summary(marks)}"
                                    + (f"; rejected: {', '.join(bad[:10])}{' ...' if len(bad) > 10 else ''}"
                                       if bad else "") + " (training leaves rejected samples out)"))


def _deep_picks(shards: dict[str, list], n: int, seed: int) -> set[str]:
    """`n` keys of the whole data set (all splits) chosen with `seed`, from the manifest."""
    keys = sorted(k for infos in shards.values() for sh in infos for k in sh.keys())
    if not keys:
        return set()
    rng = np.random.default_rng(np.random.SeedSequence(seed))
    return {keys[i] for i in rng.choice(len(keys), size=min(n, len(keys)), replace=False).tolist()}


def _deep_check(out_dir, manifest, raw_by_key, report, recipe_path=None) -> None:
    """Re-render the picked records (`raw_by_key`) from their JSON and compare member bytes."""
    try:
        if recipe_path is not None:
            recipe = load_recipe(recipe_path)
            if recipe.sha256 != manifest["recipe"].get("sha256"):
                report.add(str(recipe_path), "--recipe: not the recipe this data set was made from "
                                             "(its sha256 differs from the manifest's)")
                return
        else:
            recipe = recipe_from_manifest(manifest, out_dir)
        library = build_library(recipe)
    except Exception as exc:
        report.add(MANIFEST_NAME, f"--deep: cannot rebuild the recipe and asset library: {exc}")
        return
    for key in sorted(raw_by_key):
        shard, members = raw_by_key[key]
        where = f"{shard}: {key}"
        try:
            rec = json.loads(members["json"].decode("utf-8"))
            fresh = render_sample(Scene.from_dict(rec), library)
        except Exception as exc:
            report.add(where, f"--deep: re-rendering failed: {type(exc).__name__}: {exc}")
            continue
        report.deep_checked += 1
        for suffix in sorted(set(members) | set(fresh)):
            if suffix not in fresh:
                report.add(where, f"--deep: re-render has no member {suffix}")
            elif suffix not in members:
                report.add(where, f"--deep: re-render adds member {suffix}")
            elif fresh[suffix] != members[suffix]:
                report.add(where, f"--deep: member {suffix} differs from a re-render of its JSON")
