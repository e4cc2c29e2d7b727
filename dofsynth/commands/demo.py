"""`dofsynth demo`: the main job on built-in assets, as `make demo` runs it."""
from __future__ import annotations

import argparse
import os
from pathlib import Path

from dofsynth.progress import say



def register(subparsers) -> None:
    p = subparsers.add_parser(
        "demo", help="render the demo data set from built-in assets, its contact sheet and a focus sweep",
        description=(
            "The main job on built-in assets, no download needed: renders a focus sweep of one "
            "layered scene to OUT/demo.png, generates the demo recipe's data set into OUT/demo "
            "(resuming if it is already there) and writes its contact sheet to OUT/demo-sheet.png."),
        formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default="out", type=Path, metavar="DIR", help="output folder (default: out)")
    p.add_argument("--recipe", default="demo", metavar="RECIPE",
                   help="recipe file or shipped name (`dofsynth recipes list`; default: demo)")
    p.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1), metavar="N",
                   help="worker processes (default: up to 2)")
    p.set_defaults(func=run)


def run(args) -> int:
    from dofsynth.assets import build_library
    from dofsynth.generate import generate
    from dofsynth.io import write_png
    from dofsynth.qa.sheets import focus_sweep_strip, write_sheet
    from dofsynth.recipe import load_recipe

    out = Path(args.out)
    recipe = load_recipe(args.recipe)
    sweep_path = out / "demo.png"
    write_png(sweep_path, focus_sweep_strip(recipe, build_library(recipe)))
    say(f"focus sweep: {sweep_path}")
    data = out / recipe.name
    generate(recipe, data, workers=args.workers, resume=True)
    sheet = write_sheet(data, split="test", n=8, seed=0, path=out / f"{recipe.name}-sheet.png")
    say(f"data set:      {data}/manifest.json")
    say(f"contact sheet: {sheet}")
    return 0
