"""`dofsynth docs [NAME]`: the user documentation that ships with dofsynth, in the terminal."""
from __future__ import annotations


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "docs", help="list or print the shipped documentation (FORMAT, recipes, training, ...)",
        description="Without NAME (or with `list`), list the documents; with it, print one (e.g. "
                    "`dofsynth docs FORMAT`).")
    p.add_argument("name", metavar="NAME", nargs="?", default=None, help="a document name, e.g. FORMAT; or list")
    p.set_defaults(func=run)


def run(args) -> int:
    from dofsynth.shipped import find_shipped, shipped

    if args.name in (None, "list"):
        for name, path in shipped("docs").items():
            title = next((ln.lstrip("# ").strip() for ln in path.read_text(encoding="utf-8").splitlines()
                          if ln.startswith("#")), "")
            print(f"{name:<10}  {title}")
        return 0
    print(find_shipped("docs", args.name).read_text(encoding="utf-8"), end="")
    return 0
