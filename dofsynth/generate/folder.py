"""The output folder `OUT` of a run: what may already be in it, what `--resume` keeps, and the
temp files a killed run leaves.

- Without `resume`, an OUT holding anything is refused (never silently mixed); a `--shards`
  run accepts only the work of other ranges of the same recipe and plan.
- With `resume`, shards already there are kept when their size and sha256 are what the
  progress file or old manifest recorded; the rest, a shard never recorded included, are
  made; a resumed data set is byte-identical to an uninterrupted one.
- Leftover temp files of a killed run (or of a killed Ray task) are removed, only while the
  run holds OUT's lock.
"""
from __future__ import annotations

from pathlib import Path

from dofsynth import __version__
from dofsynth.files import final_name, is_temp_name, sha256_file
from dofsynth.generate.locks import LOCK_NAME
from dofsynth.generate.plan import ShardTask
from dofsynth.manifest import load_manifest, manifest_shard_infos
from dofsynth.manifest.names import MANIFEST_NAME, PART_RE, PROGRESS_NAME, PROGRESS_PART_RE
from dofsynth.manifest.parts import load_part
from dofsynth.manifest.progress import read_progress
from dofsynth.rng import SPLITS
from dofsynth.shards import ShardInfo


class OutputNotEmptyError(ValueError):
    """The output folder already holds files and `resume` was not asked for."""


class ResumeError(ValueError):
    """The output folder cannot be resumed with this recipe."""


def entries(out: Path) -> list[str]:
    """The names in OUT but the lock files, sorted ([] for a folder that does not exist)."""
    return sorted(p.name for p in out.iterdir() if not p.name.startswith(LOCK_NAME)) if out.is_dir() else []


def check_same_assets(out: Path, where: str, before: dict | None, now: dict) -> None:
    """Refuse to resume with another asset library than the one `where` was begun with, naming
    what changed (a folder of an older dofsynth that recorded none is not checked)."""
    if not before or before.get("sha256") == now["sha256"]:
        return
    old, new = before.get("files", {}), now["files"]
    added = sorted(set(new) - set(old))
    gone = sorted(set(old) - set(new))
    changed = sorted(k for k in set(old) & set(new) if old[k] != new[k])

    def some(ids):
        return f"{len(ids)} ({', '.join(ids[:3])}{', ...' if len(ids) > 3 else ''})" if ids else "0"

    what = f"{some(added)} added, {some(gone)} removed, {some(changed)} changed"
    if not (added or gone or changed):
        what = "the same files in other splits"
    raise ResumeError(f"{out}: {where} was made from another asset library: {what}; resume with the asset folders "
                      "it was begun with, or choose a new --out folder (samples would mix two libraries)")


def previous_state(out: Path, recipe, assets: dict) -> tuple[dict[str, int | None], dict[str, ShardInfo]]:
    """For --resume: the per-split limits of the earlier run and the shards it recorded;
    refuses another recipe, dofsynth version or asset library (`assets`: this run's
    {"sha256", "files"} of dofsynth.assets.AssetLibrary)."""
    header, progressed = read_progress(out)
    manifest = load_manifest(out) if (out / MANIFEST_NAME).is_file() else None
    if header is None and manifest is None:
        leftovers = [n for n in entries(out) if not n.startswith(".")]
        if any(PART_RE.match(n) for n in leftovers):
            raise ResumeError(f"{out}: holds partial manifests of --shards runs ({', '.join(leftovers[:3])}...); "
                              f"finish those ranges with --shards A:B --resume and join them with "
                              f"`dofsynth manifest merge {out}`, or choose a new --out folder")
        if leftovers:
            raise ResumeError(f"{out}: holds {', '.join(leftovers[:5])} but no {PROGRESS_NAME} or {MANIFEST_NAME}: "
                              "not a dofsynth data set; choose a new --out folder")
        return {}, {}
    prev_sha = (header or {}).get("recipe_sha256") or manifest["recipe"]["sha256"]
    if prev_sha != recipe.sha256:
        raise ResumeError(f"{out}: was made from a recipe with sha256 {prev_sha[:12]}..., not {recipe.path} "
                          f"({recipe.sha256[:12]}...); resume with the same recipe or choose a new --out folder")
    prev_version = (header or {}).get("dofsynth_version") or manifest["dofsynth_version"]
    if prev_version != __version__:
        raise ResumeError(f"{out}: was made by dofsynth {prev_version}, this is {__version__} (samples would "
                          "differ); choose a new --out folder")
    if header is not None:
        check_same_assets(out, "it", header.get("assets"), assets)
    if manifest is not None:
        check_same_assets(out, "it", manifest.get("assets"), assets)
    limits: dict[str, int | None] = {}
    known: dict[str, ShardInfo] = {}
    if manifest is not None:
        limits.update({s: b.get("limit") for s, b in manifest["splits"].items()})
        for infos in manifest_shard_infos(manifest).values():
            known.update({i.path: i for i in infos})
    if header is not None:
        limits.update(header.get("limits", {}))
        known.update({i.path: i for i in progressed})
    return limits, known


def verify_existing(out: Path, task: ShardTask, known: dict[str, ShardInfo]) -> ShardInfo | None:
    """The ShardInfo of an already-written shard whose content is proven: the plan's shard,
    with the size and sha256 its run recorded. Any other shard at that name is deleted at once
    and remade: one that differs from its record, and one never recorded (its run was killed
    between the rename and the progress line, so nothing ever hashed its bytes: a damaged
    one would otherwise be kept on its sample keys and its bad hash go into the manifest)."""
    final = out / task.path
    if not final.is_file():
        return None
    rec = known.get(task.path)
    ok = rec is not None and (rec.first_index, rec.samples) == (task.first_index, task.samples)
    if ok:
        sha, nbytes = sha256_file(final)
        ok = (rec.sha256, rec.bytes) == (sha, nbytes)
    if not ok:
        final.unlink()
        return None
    return ShardInfo(task.split, task.index, task.name, task.first_index, task.samples, sha, nbytes, usage=rec.usage)


def remove_shard_temps(out: Path, paths: set[str] | None = None) -> list[str]:
    """Delete leftover shard temp files ("<split>/.<name>.tmp-<pid>") of the shards `paths`
    ("train/train-000001.tar", ...), or of every shard if None (only with OUT's exclusive lock).
    A killed run, or a task killed mid-shard and retried by Ray, leaves them."""
    removed = []
    for s in SPLITS:
        folder = out / s
        if not folder.is_dir():
            continue
        for p in sorted(folder.iterdir()):
            if not (p.is_file() and is_temp_name(p.name)):
                continue
            if paths is None or f"{s}/{final_name(p.name)}" in paths:
                p.unlink(missing_ok=True)
                removed.append(f"{s}/{p.name}")
    return removed


def check_shared_folder(out: Path, recipe, header: dict, tasks: list[ShardTask], resume: bool) -> None:
    """What a --shards run accepts in OUT: other ranges of the same recipe and plan (their
    shards, partial manifests, progress and lock files), and, with `resume`, its own earlier
    work. Refuses the rest, naming it."""
    first, stop = header["range"]
    same = ("recipe_sha256", "dofsynth_version", "limits", "shards")
    for name in entries(out):
        p = out / name
        if name in SPLITS and p.is_dir() or name.startswith(LOCK_NAME) or is_temp_name(name):
            continue  # temp files: another range's part or progress file being written
        m = PART_RE.match(name) or PROGRESS_PART_RE.match(name)
        if m:
            a, b = int(m[1]), int(m[2])
            if PART_RE.match(name):
                part = load_part(p)
                other = {"recipe_sha256": part["recipe"]["sha256"], "dofsynth_version": part["dofsynth_version"],
                         "limits": part["plan"]["limits"], "shards": part["plan"]["shards"],
                         "assets": part["extra"].get("assets")}
            else:
                other = read_progress(out, name)[0]
                if other is None:
                    continue
            if other.get("recipe_sha256") != header["recipe_sha256"]:
                raise OutputNotEmptyError(f"{out}: holds {name}, made from another recipe (sha256 "
                                          f"{str(other.get('recipe_sha256'))[:12]}..., not {recipe.path}); one folder "
                                          "holds one data set: choose another --out")
            if any(other.get(k) != header[k] for k in same):
                raise OutputNotEmptyError(f"{out}: holds {name}, of another plan (dofsynth version, --split or --limit "
                                          "differ); every --shards run into one OUT needs the same recipe and options")
            check_same_assets(out, name, other.get("assets"), header["assets"])
            if (a, b) == (first, stop):
                if not resume:
                    raise OutputNotEmptyError(f"{out}: shards {a}:{b} were made or begun here before ({name}); pass "
                                              "--resume to verify and finish them")
            elif a < stop and first < b:
                raise OutputNotEmptyError(f"{out}: --shards {first}:{stop} overlaps {name} (shards {a}:{b}); the "
                                          "ranges of one data set must be disjoint")
            continue
        if name == MANIFEST_NAME:
            raise OutputNotEmptyError(f"{out}: holds a finished data set ({MANIFEST_NAME}); choose a new --out folder")
        if name == PROGRESS_NAME:
            raise OutputNotEmptyError(f"{out}: a whole run (without --shards) began here ({PROGRESS_NAME}); finish it "
                                      "with --resume and no --shards, or choose a new --out folder")
        raise OutputNotEmptyError(f"{out}: holds {name}, which is not part of a dofsynth data set made with "
                                  "--shards; choose a new --out folder")
    if not resume:
        for t in tasks:
            if (out / t.path).exists():
                raise OutputNotEmptyError(f"{out}: {t.path} (in --shards {first}:{stop}) exists already; pass "
                                          "--resume to verify and keep it")
