"""`dofsynth recipes list|copy|show`: the shipped recipes and training configs, by name."""
from __future__ import annotations

import argparse
from pathlib import Path

from dofsynth.progress import say

EPILOG = """\
examples:
  dofsynth recipes list
  dofsynth recipes copy demo my-recipes/        # then edit my-recipes/demo.toml
  dofsynth generate demo --out out/demo         # a shipped recipe by name
  dofsynth train train-demo --data out/demo --run runs/demo
"""


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "recipes", help="list, show or copy the shipped recipes and training configs",
        description="The recipes (data sets) and training configs that ship with dofsynth. Every "
                    "command that takes a recipe or training config takes one of these names too.",
        epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="action", metavar="ACTION", required=True)
    sub.add_parser("list", help="the shipped names, each with its first comment line")
    show = sub.add_parser("show", help="print one shipped file")
    show.add_argument("name", metavar="NAME")
    copy = sub.add_parser("copy", help="copy one shipped file into a folder, to edit it")
    copy.add_argument("name", metavar="NAME")
    copy.add_argument("dir", metavar="DIR", type=Path, help="folder to copy into (made if missing)")
    copy.add_argument("--force", action="store_true", help="replace a file of that name in DIR")
    p.set_defaults(func=run)


def _summary(path: Path) -> str:
    for line in path.read_text(encoding="utf-8").splitlines():
        if line.startswith("#"):
            return line.lstrip("# ").strip()
    return ""


def run(args) -> int:
    from dofsynth.files import atomic_write_bytes
    from dofsynth.shipped import find_shipped, shipped

    if args.action == "list":
        files = shipped("recipes")
        width = max(map(len, files))
        for name, path in files.items():
            kind = "training" if name.startswith("train-") else "data    "
            print(f"{name:<{width}}  {kind}  {_summary(path)}")
        return 0
    src = find_shipped("recipes", args.name)
    if args.action == "show":
        print(src.read_text(encoding="utf-8"), end="")
        return 0
    dst = args.dir / src.name
    if dst.exists() and not args.force:
        raise FileExistsError(f"{dst}: exists (use --force to replace it)")
    atomic_write_bytes(dst, src.read_bytes())
    say(f"copied {src.name} to {dst} (its relative asset paths now mean relative to {args.dir})")
    return 0
