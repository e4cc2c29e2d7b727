"""`dofsynth manifest merge`: join the partial manifests of `generate --shards A:B` runs."""
from __future__ import annotations

import argparse
from pathlib import Path

DESCRIPTION = """\
Work on data set manifests. `merge` joins the partial manifests OUT/manifest.part-A-B.json that
`dofsynth generate --shards A:B` runs wrote into OUT/manifest.json: the same bytes a single run
of the recipe writes. It refuses parts of different recipes or plans, overlapping ranges and
gaps (shards of the plan in no part), naming the offending parts, and shards missing from the
data set folder or of the wrong size.
"""

MERGE_EPILOG = """\
examples:
  dofsynth manifest merge /shared/dl18k            # every /shared/dl18k/manifest.part-*.json
  dofsynth manifest merge a/manifest.part-000000-000010.json a/manifest.part-000010-000020.json \\
      --out a/manifest.json --keep-parts

Merging into OUT/manifest.json takes OUT's lock (refused while a --shards run is writing), then
removes the merged parts and the stale lock, progress and temp files of the ranges (unless
--keep-parts), so OUT ends up like the folder of a single run. See `dofsynth docs generate`.
"""


def register(subparsers) -> None:
    p = subparsers.add_parser("manifest", help="work on data set manifests (merge the parts of --shards runs)",
                              description=DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="manifest_command", metavar="ACTION")
    m = sub.add_parser("merge", help="join partial manifests (generate --shards A:B) into manifest.json",
                       description=DESCRIPTION, epilog=MERGE_EPILOG,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    m.add_argument("parts", nargs="+", metavar="PART",
                   help="partial manifests (manifest.part-A-B.json), or one data set folder: all its parts")
    m.add_argument("--out", type=Path, default=None, metavar="PATH",
                   help="the manifest to write (default: manifest.json in the parts' folder)")
    m.add_argument("--keep-parts", action="store_true", help="keep the partial manifests after merging")
    m.add_argument("--save-summary", type=Path, default=None, metavar="PATH",
                   help="also write a short summary of the data set to PATH (e.g. data_manifest/datasets/NAME.json)")
    m.set_defaults(func=run)
    p.set_defaults(func=lambda args: p.print_help() or 2)


def _parts(args) -> tuple[list[Path], Path]:
    from dofsynth.manifest.names import MANIFEST_NAME, PART_RE

    given = [Path(x) for x in args.parts]
    if len(given) == 1 and given[0].is_dir():
        folder = given[0]
        parts = sorted(p for p in folder.iterdir() if PART_RE.match(p.name))
        if not parts:
            raise FileNotFoundError(f"{folder}: no partial manifests (manifest.part-A-B.json) to merge")
        return parts, args.out or folder / MANIFEST_NAME
    for p in given:
        if p.is_dir():
            raise ValueError(f"{p}: a folder; give either one data set folder or partial manifest files")
        if not p.is_file():
            raise FileNotFoundError(f"{p}: no such partial manifest")
    if args.out is None:
        folders = {p.resolve().parent for p in given}
        if len(folders) != 1:
            raise ValueError("the parts lie in different folders: name the manifest to write with --out")
        return given, folders.pop() / MANIFEST_NAME
    return given, args.out


def run(args) -> int:
    from dofsynth.generate.merge import merge
    from dofsynth.manifest import save_summary

    if args.save_summary is not None and args.save_summary.suffix != ".json":
        raise ValueError(f"--save-summary {args.save_summary}: the summary file must end in .json")
    parts, out = _parts(args)
    manifest, removed = merge(parts, out, keep_parts=args.keep_parts)
    if args.save_summary is not None:
        save_summary(manifest, args.save_summary)
    if not args.quiet:
        t = manifest["totals"]
        print(f"dofsynth manifest merge: {len(parts)} parts -> {out}: {t['samples']} samples in {t['shards']} "
              f"shards, {t['bytes'] / 1e6:.1f} MB" + (f"; removed {len(removed)} files" if removed else ""))
    return 0
