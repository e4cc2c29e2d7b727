"""`dofsynth verify OUT`: check a data set folder against its manifest and its own records."""
from __future__ import annotations

import sys

from dofsynth.commands import int_at_least


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "verify",
        help="check a data set's shards, records and splits; non-zero exit on any problem",
        description=(
            "Check every shard's sha256, size and sample count against OUT/manifest.json (and "
            "report missing, truncated and unlisted shards), decode every record, check its JSON "
            "schema and value ranges, check that the disparity map agrees with the recorded plane "
            "disparities, and that no asset is shared between splits. Prints one line per problem "
            "(shard and key) and a summary; exit status 1 if anything is wrong."
        ),
    )
    p.add_argument("out", help="the data set folder (holds manifest.json)")
    p.add_argument("--deep", action="store_true",
                   help="also re-render a sample of records from their JSON and compare the bytes")
    p.add_argument("--deep-n", type=int_at_least(1), default=8, metavar="N",
                   help="how many records --deep re-renders (default: 8)")
    p.add_argument("--seed", type=int, default=0, help="picks the records --deep re-renders (default: 0)")
    p.add_argument("--recipe", default=None, metavar="TOML",
                   help="for --deep: use this recipe file (same sha256 as the manifest's) instead of "
                        "the manifest's copy, e.g. when its relative asset folders moved")
    p.set_defaults(func=run)


def run(args) -> int:
    from dofsynth.progress import bar as progress_bar
    from dofsynth.progress import quiet
    from dofsynth.qa.dataset import sample_count
    from dofsynth.qa.verify import verify_dataset

    with progress_bar(sample_count(args.out), "verify", leave=False) as bar:
        report = verify_dataset(args.out, deep=args.deep, deep_n=args.deep_n, seed=args.seed,
                                recipe_path=args.recipe, progress=bar.update)
    for line in report.lines():
        if not quiet() or line.startswith("FAIL"):  # -q: the problems alone (and the exit status)
            print(line)
    sys.stdout.flush()
    return 0 if report.ok else 1
