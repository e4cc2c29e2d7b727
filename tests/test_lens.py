"""The thin-lens description of a target (dofsynth.optics.lens) and its recipe table."""
from __future__ import annotations

import math
import re
from pathlib import Path

import pytest

from dofsynth.config import ConfigError
from dofsynth.optics.lens import ThinLens

ROOT = Path(__file__).resolve().parents[1]


def test_the_mapping_against_a_hand_computed_case():
    """50 mm at f/2 focused at 2 m, disparity 1 at 1 m, 0 at infinity, 1024 px of a 36 mm
    sensor: A = 25 mm, the CoC diameter of a point at 1 m is 25 * 50 / 1950 * 1000 / 1000 mm
    = 0.6410 mm = 18.23 px, so radius 9.12 px at |d - focus| = 0.5: max_coc = 18.23 px."""
    lens = ThinLens(50.0, 2.0, 36.0, near_m=1.0)
    focus, max_coc = lens.target(2.0, 1024)
    assert focus == pytest.approx(0.5)
    assert max_coc == pytest.approx(2 * 0.5 * (25 * 50 / 1950) * 1024 / 36, rel=1e-12)
    assert max_coc == pytest.approx(18.2336, abs=1e-4)
    assert lens.distance(0.25) == pytest.approx(4.0) and lens.distance(0.0) == math.inf
    assert lens.disparity(lens.distance(0.7)) == pytest.approx(0.7)
    finite = ThinLens(85.0, 1.4, 24.0, near_m=0.5, far_m=10.0)
    assert finite.disparity(10.0) == pytest.approx(0.0) and finite.disparity(0.5) == pytest.approx(1.0)
    with pytest.raises(ValueError, match="far_m"):
        ThinLens(50.0, 2.0, near_m=2.0, far_m=1.0)


def _recipe(extra: str, max_coc: str = "[1.0, 8.0]"):
    from dofsynth.recipe import recipe_from_text

    text = re.sub(r"(?m)^max_coc = .*$", f"max_coc = {max_coc}", (ROOT / "recipes" / "smoke.toml").read_text())
    return recipe_from_text(text + "\n[focus.lens]\n" + extra, "lens.toml", ROOT / "recipes")


def test_lens_targets_are_recorded_and_their_max_coc_follows_the_lens():
    from dofsynth.assets import build_library
    from dofsynth.scene import Scene, sample_scene

    recipe = _recipe("enabled = true\nfocal_length_mm = [35.0, 50.0]\nf_number = [2.0, 4.0]\nnear_m = 2.0\n")
    scene = sample_scene(recipe, build_library(recipe), "train", 0)
    for t in scene.to_dict()["targets"]:
        lens = t["lens"]
        assert 35 <= lens["focal_length_mm"] <= 50 and 2 <= lens["f_number"] <= 4 and lens["far_m"] == 0.0  # infinity
        lens_obj = ThinLens(lens["focal_length_mm"], lens["f_number"], lens["sensor_width_mm"], lens["near_m"])
        distance = lens["focus_distance_m"] or math.inf   # 0 = infinity, as in the recipe
        assert lens_obj.disparity(distance) == pytest.approx(t["focus"])
        assert lens_obj.max_coc(distance, recipe.frame[1]) == pytest.approx(t["max_coc"])
    assert Scene.from_dict(scene.to_dict()) == scene
    plain = sample_scene(_recipe("enabled = false\n"), build_library(recipe), "train", 0)
    assert all("lens" not in t for t in plain.to_dict()["targets"])


def test_a_lens_that_blurs_past_max_coc_is_refused_by_name():
    with pytest.raises(ConfigError, match="focus.max_coc"):
        _recipe("enabled = true\nfocal_length_mm = [200.0, 400.0]\nf_number = [1.4, 2.0]\nnear_m = 1.0\n", "[1.0, 4.0]")
