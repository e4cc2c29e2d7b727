import json

import numpy as np
import pytest

from dofsynth.assets import build_library
from dofsynth.recipe import load_recipe
from dofsynth.rng import SPLIT_ID
from dofsynth.assets.placement import in_frame_share, placed_size
from dofsynth.scene import Scene, sample_scene


@pytest.fixture(scope="module")
def demo(demo_recipe):
    return demo_recipe, build_library(demo_recipe)


@pytest.fixture(scope="module")
def many(demo):
    recipe, lib = demo
    return [sample_scene(recipe, lib, "train", i) for i in range(400)]


def test_same_index_same_scene_alone_or_in_a_loop(demo):
    recipe, lib = demo
    loop = [sample_scene(recipe, lib, "test", i) for i in range(12)]
    fresh = build_library(recipe)
    alone = sample_scene(recipe, fresh, "test", 7)
    assert alone == loop[7] and alone.to_dict() == loop[7].to_dict()
    assert sample_scene(recipe, lib, "train", 7) != alone
    assert alone.key == "test-0000007" and alone.seed == (recipe.seed, SPLIT_ID["test"], 7)


def test_dict_round_trip_is_exact_through_json(many):
    for s in many[:50]:
        d = s.to_dict()
        back = Scene.from_dict(json.loads(json.dumps(d, sort_keys=True)))
        assert back == s and back.to_dict() == d
    rec = {**many[0].to_dict(), "schema_version": 2, "renderer": "layered-v3", "dofsynth_version": "0.1.0"}
    assert Scene.from_dict(rec) == many[0]
    # a schema-1 record (no colour, anchored, visible, rejected) reads with their defaults
    old = json.loads(json.dumps(many[0].to_dict()))
    for role in ("front", "middle"):
        for k in ("anchored", "visible", "rejected"):
            del old[role][k]
    for ref in old["assets"].values():
        del ref["colour"]
    back = Scene.from_dict(old)
    assert back.front.anchored == () and back.front.visible == 1.0 and back.assets["front"].colour == "file"
    # a schema-3 record (lists of names, a flat background's direction null) reads the same
    for s in many:
        v3 = json.loads(json.dumps(s.to_dict()))
        for role in ("front", "middle"):
            v3[role]["anchored"] = list(s.to_dict()[role]["anchored"].split(",")) if v3[role]["anchored"] else []
            v3[role]["rejected"] = list(getattr(s, role).rejected)
        v3["excluded"] = list(s.excluded)
        if v3["background"]["direction"] == "none":
            v3["background"]["direction"] = None
        assert Scene.from_dict(v3) == s


def test_record_fields_match_the_format(many):
    d = many[0].to_dict()
    assert set(d) == {"key", "split", "index", "seed", "size", "assets", "background", "front", "middle",
                      "targets", "aperture", "options", "excluded"}
    assert d["excluded"] == "" and isinstance(d["front"]["anchored"], str) and isinstance(d["front"]["rejected"], str)
    assert set(d["assets"]) == {"background", "front", "middle"}
    assert set(d["assets"]["front"]) == {"id", "path", "sha256", "colour", "matte"}
    assert d["assets"]["front"]["colour"] == d["assets"]["front"]["matte"] == "file"  # built-in cutouts: their own colour and alpha
    assert set(d["background"]) == {"mode", "b0", "b1", "direction", "crop", "flip", "margin", "real"}
    assert d["background"]["margin"] > 0 and len(d["background"]["real"]) == 4
    assert set(d["front"]) == {"disparity", "scale", "x", "y", "flip", "anchored", "visible", "rejected"}
    assert d["aperture"]["kind"] == "polygon" and d["aperture"]["blades"] == 6
    assert d["options"]["highlight"] == {"threshold": 0.9, "gain": 4.0, "power": 2.0}


def test_depth_rules_hold_over_many_scenes(demo, many):
    recipe, _ = demo
    br, fr, fo = recipe.scene.background, recipe.scene.foreground, recipe.focus
    gap = fr.min_gap
    modes = {"flat": 0, "horizontal": 0, "vertical": 0}
    for s in many:
        bg = s.background
        if bg.mode == "flat":
            assert bg.b0 == bg.b1 == 0.0 and bg.direction is None
            modes["flat"] += 1
        else:
            assert br.b0[0] <= bg.b0 <= br.b0[1] and br.b1[0] <= bg.b1 <= br.b1[1] and bg.b1 < bg.b0
            modes[bg.direction] += 1
        f0, f1 = s.front.disparity, s.middle.disparity
        assert fr.f1[0] <= f1 <= fr.f1[1] and fr.f0[0] <= f0 <= fr.f0[1]
        assert f1 >= max(bg.b0, bg.b1) + gap - 1e-12 and f0 >= f1 + gap - 1e-12
        assert f0 > f1 > max(bg.b0, bg.b1)
        assert len(s.targets) == fo.targets_per_scene
        for t in s.targets:
            assert 0.0 <= t.focus <= 1.0 and fo.max_coc[0] <= t.max_coc <= fo.max_coc[1]
        assert s.assets["front"].id != s.assets["middle"].id
        rot = s.aperture.rotation
        assert recipe.render.aperture.rotation[0] <= rot <= recipe.render.aperture.rotation[1]
    n = len(many)
    assert 0.2 * n < modes["flat"] < 0.4 * n          # flat_share 0.3
    assert modes["horizontal"] > 0.25 * n and modes["vertical"] > 0.25 * n
    # plane_share 0.5: some targets sit exactly on a plane, some anywhere
    on_plane = sum(t.focus in (s.front.disparity, s.middle.disparity) for s in many for t in s.targets)
    assert 0.15 < on_plane / (2 * n) < 0.5


def test_placement_keeps_objects_in_frame_at_the_recipe_scale(demo, many):
    recipe, lib = demo
    H, W = recipe.frame
    lo, hi = recipe.scene.foreground.scale
    for s in many:
        for role, p in (("front", s.front), ("middle", s.middle)):
            _, _, ew, eh = lib[s.assets[role].id].extent
            w, h = placed_size(p.scale, ew, eh)
            assert lo * min(H, W) - 1 <= max(w, h) <= hi * min(H, W) + 1
            assert in_frame_share(p.x, p.y, w, h, W, H) >= recipe.scene.foreground.min_in_frame
        x, y, cw, ch = s.background.crop
        bw, bh = lib[s.assets["background"].id].size
        assert 0 <= x and x + cw <= bw and 0 <= y and y + ch <= bh
        assert cw / ch == pytest.approx(W / H, rel=0.02)
    flips = np.mean([s.front.flip for s in many])
    assert 0.35 < flips < 0.65


def test_each_split_uses_only_its_own_assets(demo):
    recipe, lib = demo
    for split in ("train", "test"):
        for i in range(60):
            s = sample_scene(recipe, lib, split, i)
            assert all(lib.splits[ref.id] == split for ref in s.assets.values())


def test_asset_paths_are_recorded_relative_to_the_recipe(write_recipe, tiny_bg_dir, tiny_cutouts):
    recipe = load_recipe(write_recipe(backgrounds="bg", foregrounds="cutouts"))
    s = sample_scene(recipe, build_library(recipe), "train", 0)
    assert s.assets["background"].path.startswith("bg/") and s.assets["front"].path.startswith("cutouts/")


def test_bad_arguments(demo):
    recipe, lib = demo
    with pytest.raises(ValueError, match="split"):
        sample_scene(recipe, lib, "val", 0)
    with pytest.raises(ValueError, match="index"):
        sample_scene(recipe, lib, "train", -1)
