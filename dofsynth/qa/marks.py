"""Review marks: what a reviewer decided about samples on the QA page, and where it goes.

The page (dofsynth.qa.html) lets a reviewer mark a sample "reject" or "keep" with a note and
download the marks as `qa-marks.json`:

    {"format": "dofsynth-qa-marks/1", "dataset": "<OUT as the page saw it>", "recipe_sha256": "...",
     "marks": [{"key": "train-0000003", "split": "train", "shard": "train/train-000001.tar",
                "shard_sha256": "...", "mark": "reject", "note": "halo at the hair"}, ...]}

`apply_marks(file, OUT)` (`dofsynth qa apply`) checks each mark against the set (the sample
exists, its shard still has the sha256 the reviewer saw: a shard made again since is a stale
review, refused by name) and records them in `OUT/qa-marks.json` beside the manifest, merged
with earlier ones (a later mark of a key replaces the earlier one). `verify` reports them, the
trainer's loader leaves rejected samples out (`[data] exclude = "rejected"`), and `stats` /
`sheet --marked` show them.
"""
from __future__ import annotations

from pathlib import Path

from dofsynth.files import atomic_write_bytes, canonical_json, read_json
from dofsynth.qa import dataset as ds

MARKS_NAME = "qa-marks.json"
FORMAT = "dofsynth-qa-marks/1"
KINDS = ("reject", "keep")
FIELDS = ("key", "split", "shard", "shard_sha256", "mark", "note")


class MarksError(ValueError):
    """A marks file that cannot be used; the message names it and the mark."""


def read_marks(path: str | Path) -> dict:
    """A marks file ({"format", "marks": [...], ...}), its marks checked for form."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such marks file")
    doc = read_json(path, MarksError)
    if not isinstance(doc, dict) or doc.get("format") != FORMAT or not isinstance(doc.get("marks"), list):
        raise MarksError(f"{path}: not a dofsynth marks file (format {FORMAT!r}, a list of marks)")
    for i, m in enumerate(doc["marks"]):
        if not isinstance(m, dict) or any(not isinstance(m.get(f), str) for f in FIELDS):
            raise MarksError(f"{path}: marks[{i}] needs the strings {', '.join(FIELDS)}, got {m!r}"[:300])
        if m["mark"] not in KINDS:
            raise MarksError(f"{path}: marks[{i}] ({m['key']}): mark must be one of {', '.join(KINDS)}, got "
                             f"{m['mark']!r}")
    return doc


def set_marks(out: str | Path) -> dict[str, dict]:
    """{key: mark} recorded for data set OUT ({} when none)."""
    path = Path(out) / MARKS_NAME
    return {m["key"]: m for m in read_marks(path)["marks"]} if path.is_file() else {}


def stale(marks: dict[str, dict], manifest: dict) -> list[str]:
    """Why each mark no longer fits the set: its sample is gone, or its shard was made again."""
    shards = {sh.path: sh for s in ds.manifest_splits(manifest) for sh in ds.manifest_shards(manifest, s)}
    out = []
    for key, m in sorted(marks.items()):
        sh = shards.get(m["shard"])
        if sh is None or key not in sh.keys():
            out.append(f"{key}: not in {m['shard']} of this data set")
        elif sh.sha256 != m["shard_sha256"]:
            out.append(f"{key}: {m['shard']} was made again since the review (sha256 {m['shard_sha256'][:12]}... "
                       f"then, {str(sh.sha256)[:12]}... now)")
    return out


def apply_marks(marks_path: str | Path, out: str | Path) -> tuple[Path, dict[str, int]]:
    """Record the marks of a downloaded file in OUT/qa-marks.json (merged with earlier ones);
    returns (that file, {"reject": n, "keep": n} of the file applied). MarksError names a
    mark that does not fit the set; nothing is written then."""
    out = Path(out)
    manifest = ds.load(out)
    doc = read_marks(marks_path)
    new = {m["key"]: {f: m[f] for f in FIELDS} for m in doc["marks"]}
    bad = stale(new, manifest)
    if bad:
        raise MarksError(f"{marks_path}: {len(bad)} mark(s) do not fit {out}: {bad[0]}"
                         + (f" (and {len(bad) - 1} more)" if len(bad) > 1 else ""))
    merged = {**set_marks(out), **new}
    record = {"format": FORMAT, "dataset": str(out), "recipe_sha256": manifest["recipe"]["sha256"],
              "marks": [merged[k] for k in sorted(merged)]}
    path = out / MARKS_NAME
    atomic_write_bytes(path, canonical_json(record, indent=1))
    return path, {k: sum(m["mark"] == k for m in new.values()) for k in KINDS}


def rejected(out: str | Path) -> set[str]:
    """The keys of data set OUT that a review rejected."""
    return {k for k, m in set_marks(out).items() if m["mark"] == "reject"}


def marks_summary(marks: dict[str, dict]) -> str:
    """"2 rejected, 1 kept" (or "" when there are none)."""
    if not marks:
        return ""
    n = {k: sum(m["mark"] == k for m in marks.values()) for k in KINDS}
    return f"{n['reject']} rejected, {n['keep']} kept"

