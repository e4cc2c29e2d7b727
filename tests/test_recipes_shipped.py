"""Every recipe and training config shipped in recipes/ loads and validates; the real-photo
recipe's pinned asset manifest matches ../shared/assets."""
from pathlib import Path

import pytest

from dofsynth.assets import build_library
from dofsynth.recipe import load_recipe
from dofsynth.train import config as train_config

ROOT = Path(__file__).resolve().parents[1]
RECIPES = sorted(ROOT.glob("recipes/*.toml"))
TRAIN = [p for p in RECIPES if p.name.startswith("train-")]
GENERATE = [p for p in RECIPES if p not in TRAIN]


def test_recipes_are_shipped():
    names = {p.name for p in RECIPES}
    assert {"demo.toml", "deeplens-18k.toml", "smoke.toml"} <= names
    assert TRAIN, "at least one training config"


@pytest.mark.parametrize("path", GENERATE, ids=lambda p: p.name)
def test_generation_recipe_loads(path):
    recipe = load_recipe(path)
    assert recipe.samples.train + recipe.samples.test > 0
    assert recipe.sha256 and recipe.text == path.read_text()


def test_deeplens_recipe_is_the_paper_setup():
    r = load_recipe(ROOT / "recipes" / "deeplens-18k.toml")
    assert (r.samples.train, r.samples.test) == (18000, 500)
    assert max(r.frame) == 1024
    assert max(r.focus.max_coc) == 32.0


@pytest.mark.parametrize("path", TRAIN, ids=lambda p: p.name)
def test_training_config_loads(path):
    cfg = train_config.load(path)
    assert cfg.loss.alpha == 1.5


def test_shared_assets_recipe_pins_the_real_photos(shared_assets):
    recipe = load_recipe(ROOT / "recipes" / "shared-assets.toml")
    lib = build_library(recipe)
    assert len(lib.backgrounds) == 5 and len(lib.foregrounds) == 6
    assert not lib.skipped
    tr = {a.id for a in lib.assets_for("foreground", "train")}
    te = {a.id for a in lib.assets_for("foreground", "test")}
    assert tr and te and not tr & te


PAIRS = train_config.DATA_RECIPES  # which training config goes with which data recipe


def test_every_training_config_has_its_data_recipe():
    assert set(PAIRS) == {p.name for p in TRAIN}


@pytest.mark.parametrize("config", sorted(PAIRS))
def test_a_training_config_fits_its_data(config):
    """Its crops fit the images, and the largest blur is at most a quarter of the low-res crop
    (the lens-blur network sees the whole disc and what surrounds it)."""
    cfg = train_config.load(ROOT / "recipes" / config)
    recipe = load_recipe(ROOT / "recipes" / PAIRS[config])
    s = 2 ** cfg.data.levels
    assert cfg.data.crop <= min(recipe.frame)
    assert PAIRS[config] in (ROOT / "recipes" / config).read_text()  # its header names the recipe
    if cfg.train.task == "depth":
        return  # no blur to fit
    assert recipe.focus.max_coc[1] / s <= cfg.data.crop / s / 4, (recipe.focus.max_coc, cfg.data.crop, s)
    if cfg.model.coc_ref:
        assert cfg.model.coc_ref == recipe.focus.max_coc[1]
