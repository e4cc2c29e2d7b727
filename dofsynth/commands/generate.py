"""`dofsynth generate RECIPE --out OUT`: render a recipe's data set into WebDataset shards."""
from __future__ import annotations

import argparse
from pathlib import Path

DESCRIPTION = """\
Render the data set a recipe describes into OUT: WebDataset tar shards OUT/train/*.tar and
OUT/test/*.tar (each sample: aif.png, depth.exr, cover.png, dof.N.png, json; see docs/FORMAT.md)
and OUT/manifest.json, written last. Sample i of a recipe is the same bytes whatever --workers,
the machine, or an interruption and --resume. OUT must be new or empty unless --resume is given;
a second run into the same OUT while one is running is refused (OUT/.lock).
"""

EPILOG = """\
examples:
  dofsynth generate recipes/demo.toml --out out/demo --workers 2
  dofsynth generate recipes/deeplens-18k.toml --out /data/dl18k --limit 100   # a quick look
  dofsynth generate recipes/deeplens-18k.toml --out /data/dl18k --resume      # then the rest
  dofsynth generate recipes/demo.toml --out out/demo --save-summary data_manifest/datasets/demo.json

--limit N keeps the first N samples of each split (indices 0..N-1, identical to the same samples
of a full run; only the last shard may be shorter). --resume keeps every shard already written
and verified (sha256), makes the missing ones, removes leftovers of a killed run, and finishes
splits an earlier run began; the result equals an uninterrupted run with the same options.
See docs/generate.md.
"""


def _positive_int(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
    if v < 1:
        raise argparse.ArgumentTypeError(f"expected an integer >= 1, got {v}")
    return v


def _count(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
    if v < 0:
        raise argparse.ArgumentTypeError(f"expected an integer >= 0, got {v}")
    return v


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "generate", help="render a recipe's data set into WebDataset shards and a manifest",
        description=DESCRIPTION, epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("recipe", metavar="RECIPE", help="the recipe TOML file (e.g. recipes/demo.toml)")
    p.add_argument("--out", required=True, metavar="OUT", help="data set folder to create (new or empty, or with --resume)")
    p.add_argument("--workers", type=_positive_int, default=1, metavar="N",
                   help="worker processes, each rendering whole shards (default 1; about one per core)")
    p.add_argument("--split", choices=("train", "test", "all"), default="all",
                   help="which split to make (default all)")
    p.add_argument("--limit", type=_count, default=None, metavar="N",
                   help="make at most the first N samples of each split (for a quick look or a test)")
    p.add_argument("--resume", action="store_true",
                   help="finish or extend the data set already in OUT (same recipe): keep verified shards, make the rest")
    p.add_argument("--save-summary", type=Path, default=None, metavar="PATH",
                   help="also write a short summary of the finished data set to PATH "
                        "(e.g. data_manifest/datasets/NAME.json)")
    p.add_argument("--quiet", action="store_true", help="no progress bar and no closing summary")
    p.set_defaults(func=run)


def run(args) -> int:
    from dofsynth.config import load_recipe
    from dofsynth.generate import SPLITS, generate
    from dofsynth.manifest import save_summary

    if args.save_summary is not None and args.save_summary.suffix != ".json":
        raise ValueError(f"--save-summary {args.save_summary}: the summary file must end in .json")
    recipe = load_recipe(args.recipe)
    splits = SPLITS if args.split == "all" else (args.split,)
    result = generate(recipe, args.out, workers=args.workers, splits=splits, limit=args.limit,
                      resume=args.resume, progress=not args.quiet)
    if args.save_summary is not None:
        path = save_summary(result.manifest, args.save_summary)
        if not args.quiet:
            print(f"  summary  {path}")
    return 0
