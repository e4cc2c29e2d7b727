"""`dofsynth demo`: the main job on built-in assets, as `make demo` runs it."""
from __future__ import annotations

import argparse
import os
from pathlib import Path

DEFAULT_RECIPE = Path(__file__).resolve().parents[2] / "recipes" / "demo.toml"
SWEEP_FOCUS = (0.0, 0.25, 0.5, 0.75, 1.0)


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "demo", help="render the demo data set from built-in assets, its contact sheet and a focus sweep",
        description=(
            "The main job on built-in assets, no download needed: renders a focus sweep of one "
            "layered scene to OUT/demo.png, generates the demo recipe's data set into OUT/demo "
            "(resuming if it is already there) and writes its contact sheet to OUT/demo-sheet.png."),
        formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default="out", type=Path, metavar="DIR", help="output folder (default: out)")
    p.add_argument("--recipe", default=DEFAULT_RECIPE, type=Path, metavar="RECIPE",
                   help="recipe to run (default: recipes/demo.toml)")
    p.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1), metavar="N",
                   help="worker processes (default: up to 2)")
    p.set_defaults(func=run)


def focus_sweep_image(recipe, library, focuses=SWEEP_FOCUS):
    """One test scene of `recipe` rendered at each focus, side by side with a label strip (uint8 RGB)."""
    import cv2
    import numpy as np

    from dofsynth.scene import sample_scene
    from dofsynth.sheets import focus_sweep, put_text

    scene = sample_scene(recipe, library, "test", 0)
    tiles = focus_sweep(scene.to_dict(), library, recipe, focuses)
    h = 256
    tiles = [cv2.resize(t, (round(t.shape[1] * h / t.shape[0]), h), interpolation=cv2.INTER_AREA) for t in tiles]
    strip = np.full((22, sum(t.shape[1] for t in tiles), 3), 24, np.uint8)
    x = 0
    for f, t in zip(focuses, tiles):
        put_text(strip, f"focus {f:.2f}", x + 4, 4)
        x += t.shape[1]
    return np.concatenate([strip, np.concatenate(tiles, axis=1)], axis=0)


def run(args) -> int:
    from dofsynth.config import load_recipe
    from dofsynth.assets import build_library
    from dofsynth.generate import generate
    from dofsynth.io import write_png
    from dofsynth.sheets import write_sheet

    out = Path(args.out)
    recipe = load_recipe(args.recipe)
    sweep_path = out / "demo.png"
    write_png(sweep_path, focus_sweep_image(recipe, build_library(recipe)))
    print(f"focus sweep: {sweep_path}")
    data = out / recipe.name
    generate(recipe, data, workers=args.workers, resume=True)
    sheet = write_sheet(data, split="test", n=8, seed=0, path=out / f"{recipe.name}-sheet.png")
    print(f"data set:      {data}/manifest.json")
    print(f"contact sheet: {sheet}")
    return 0
