"""`dofsynth generate RECIPE --out OUT`: render a recipe's data set into WebDataset shards."""
from __future__ import annotations

import argparse
from pathlib import Path

from dofsynth.commands import int_at_least

DESCRIPTION = """\
Render the data set a recipe describes into OUT: WebDataset tar shards OUT/train/*.tar and
OUT/test/*.tar (each sample: aif.png, depth.exr, cover.png, dof.N.png, json; see `dofsynth docs FORMAT`)
and OUT/manifest.json, written last. Sample i of a recipe is the same bytes whatever --workers,
--executor, the machine, or an interruption and --resume. OUT must be new or empty unless
--resume is given; a second run into the same OUT while one is running is refused (OUT/.lock).
"""

EPILOG = """\
examples:
  dofsynth generate demo --out out/demo --workers 2                          # a shipped recipe by name
  dofsynth generate my-recipe.toml --out out/mine
  dofsynth recipes copy deeplens-18k .        # an editable copy; put your assets beside it
  dofsynth generate deeplens-18k.toml --out /data/dl18k --limit 100   # a quick look
  dofsynth generate deeplens-18k.toml --out /data/dl18k --resume      # then the rest
  dofsynth generate demo --out out/demo --save-summary data_manifest/datasets/demo.json
  dofsynth generate deeplens-18k.toml --out /shared/dl18k --executor ray --address auto
  dofsynth generate deeplens-18k.toml --out /shared/dl18k --shards 0:20 --resume   # one job of an array
  dofsynth manifest merge /shared/dl18k                                                   # then join the parts

--limit N keeps the first N samples of each split (indices 0..N-1, identical to the same samples
of a full run; only the last shard may be shorter). --resume keeps every shard already written
and verified (sha256), makes the missing ones, removes leftovers of a killed run, and finishes
splits an earlier run began; the result equals an uninterrupted run with the same options.
--shards A:B makes shards A..B-1 of the run's plan (train's shards, then test's; --plan prints
it) and writes OUT/manifest.part-A-B.json; disjoint ranges may run at once into one OUT.
See `dofsynth docs generate` ("Running a large job"); shipped recipes: `dofsynth recipes list`.
"""


_positive_int = int_at_least(1)
_count = int_at_least(0)


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "generate", help="render a recipe's data set into WebDataset shards and a manifest",
        description=DESCRIPTION, epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("recipe", metavar="RECIPE", help="a recipe TOML file, or a shipped recipe by name (demo, deeplens-18k, ...: `dofsynth recipes list`)")
    p.add_argument("--out", metavar="OUT", help="data set folder to create (new or empty, or with --resume); required "
                   "unless --plan")
    p.add_argument("--workers", type=_positive_int, default=None, metavar="N",
                   help="local: worker processes, each rendering whole shards (default 1; about one per core); "
                        "ray: at most N shard tasks at once (default: as many as the cluster's CPUs run)")
    p.add_argument("--executor", choices=("local", "ray"), default="local",
                   help="local: this machine (default); ray: one Ray task per shard on a Ray cluster "
                        "(needs: pip install 'dofsynth[ray]')")
    p.add_argument("--address", default=None, metavar="ADDR",
                   help="with --executor ray: the cluster to join ('auto' for the one `ray start --head` made on "
                        "this node, or HOST:PORT); default: start a local Ray instance for this run")
    p.add_argument("--max-retries", type=_count, default=3, metavar="N",
                   help="with --executor ray: retries of a shard task whose worker died (default 3)")
    p.add_argument("--shards", default=None, metavar="A:B",
                   help="make only shards A..B-1 of the plan (half-open; train's shards, then test's; 'A:' to the "
                        "end) and write OUT/manifest.part-A-B.json; join the parts with `dofsynth manifest merge`")
    p.add_argument("--plan", action="store_true",
                   help="print the shard plan (global shard numbers per split, for --shards) and exit")
    p.add_argument("--split", choices=("train", "test", "all"), default="all",
                   help="which split to make (default all)")
    p.add_argument("--limit", type=_count, default=None, metavar="N",
                   help="make at most the first N samples of each split (for a quick look or a test)")
    p.add_argument("--resume", action="store_true",
                   help="finish or extend the data set already in OUT (same recipe): keep verified shards, make the rest")
    p.add_argument("--save-summary", type=Path, default=None, metavar="PATH",
                   help="also write a short summary of the finished data set to PATH "
                        "(e.g. data_manifest/datasets/NAME.json)")
    p.set_defaults(func=run, resume_hint=resume_hint)


def resume_hint(args) -> str | None:
    """What to run to finish the data set after this run stopped (kept shards stay); None for
    a run that writes nothing (--plan, or no --out)."""
    import shlex

    if args.plan or not args.out:
        return None
    cmd = ["dofsynth", "generate", args.recipe, "--out", str(args.out)]
    for flag, value in (("--split", None if args.split == "all" else args.split), ("--limit", args.limit),
                        ("--shards", args.shards), ("--workers", args.workers),
                        ("--executor", None if args.executor == "local" else args.executor),
                        ("--address", args.address)):
        if value is not None:
            cmd += [flag, str(value)]
    return "resume with: " + shlex.join(cmd + ["--resume"]) + " (finished shards are kept)"


def print_plan(recipe, splits, limit) -> None:
    """The plan's global shard numbers per split, counted (its size costs no memory)."""
    from dofsynth.generate.plan import shard_count, split_size

    counts = {s: shard_count(recipe, s, limit) for s in splits}
    total = sum(counts.values())
    print(f"{recipe.path}: {total} shards of up to {recipe.shard_size} samples"
          + (f" (limit {limit} per split)" if limit is not None else ""))
    g = 0
    for s in splits:
        print(f"  {s:5s} --shards {g}:{g + counts[s]}  ({split_size(recipe, s, limit)} samples)")
        g += counts[s]
    print(f"  total {total}")


def run(args) -> int:
    from dofsynth.generate import generate, make_executor, parse_shard_range
    from dofsynth.generate.worker import setup_process
    from dofsynth.manifest import save_summary
    from dofsynth.recipe import load_recipe
    from dofsynth.rng import SPLITS

    if args.save_summary is not None and args.save_summary.suffix != ".json":
        raise ValueError(f"--save-summary {args.save_summary}: the summary file must end in .json")
    shard_range = parse_shard_range(args.shards) if args.shards is not None else None
    if shard_range is not None and args.save_summary is not None:
        raise ValueError("--save-summary needs the whole data set: pass it to `dofsynth manifest merge`, not to a "
                         "--shards run")
    if args.executor != "ray" and (args.address is not None or args.max_retries != 3):
        raise ValueError("--address and --max-retries are for --executor ray")
    recipe = load_recipe(args.recipe)
    splits = SPLITS if args.split == "all" else (args.split,)
    if args.plan:
        print_plan(recipe, splits, args.limit)
        return 0
    if not args.out:
        raise ValueError("--out OUT is required (the data set folder)")
    executor = make_executor(args.executor, workers=args.workers, address=args.address, max_retries=args.max_retries)
    if args.executor != "ray" and args.workers == 1:
        setup_process()  # the shards render in this process, whose one job this is (as in a worker)
    result = generate(recipe, args.out, splits=splits, limit=args.limit, resume=args.resume,
                      progress=not args.quiet, executor=executor, shard_range=shard_range)
    if args.save_summary is not None:
        path = save_summary(result.manifest, args.save_summary)
        if not args.quiet:
            print(f"  summary  {path}")
    return 0
