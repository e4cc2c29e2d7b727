"""Scene placement rules that keep real mattes artifact-free: cut objects sit on the frame's
edges, nothing is magnified past assets.max_upscale, both objects stay visible, focus targets
are apart. Checked on constructed mattes with a known answer and on the real photos."""
from dataclasses import replace

import numpy as np
import pytest

from dofsynth.assets import AssetLibrary, build_library
from dofsynth.assets.decode import cut_sides
from dofsynth.compose import scene_layers
from dofsynth.config import ConfigError
from dofsynth.recipe import load_recipe
from dofsynth.assets.placement import placed_size
from dofsynth.scene import Scene, sample_scene

from conftest import noise_rgb, write_png


def _pairs(root, mattes: dict[str, np.ndarray]):
    """A fg/ + alpha/ folder with a noise photo per matte (uint8)."""
    for name, a in mattes.items():
        write_png(root / "fg" / f"{name}.png", noise_rgb(*a.shape, seed=len(name)))
        write_png(root / "alpha" / f"{name}.png", a)
    return root


def _matte(h, w, box, soft=3):
    """A uint8 matte opaque inside box = (y0, y1, x0, x1), soft for `soft` px around it."""
    yy, xx = np.mgrid[0:h, 0:w]
    y0, y1, x0, x1 = box
    d = np.maximum.reduce([y0 - yy, yy - (y1 - 1), x0 - xx, xx - (x1 - 1), np.zeros_like(yy)])
    return np.clip(255 - d * (255 // soft), 0, 255).astype(np.uint8)


@pytest.fixture
def cut_recipe(write_recipe, tmp_path):
    """Three mattes: cut at the bottom (a bust), cut at the left, and a whole object."""
    _pairs(tmp_path / "fg", {
        "bust": _matte(96, 64, (20, 96, 12, 52)),   # opaque down to the photo's bottom edge
        "side": _matte(64, 96, (16, 48, 0, 70)),    # opaque from the photo's left edge
        "whole": _matte(80, 80, (10, 70, 10, 70)),
    })
    path = write_recipe(foregrounds="fg", size=96, replace={"samples = { train = 6, test = 2 }": "samples = { train = 6, test = 0 }",
                                                            "test_share = 0.25": "test_share = 0.0"})
    recipe = load_recipe(path)
    return recipe, build_library(recipe)


def test_cut_sides_are_found_where_the_matte_is_opaque_at_the_border():
    assert cut_sides(_matte(96, 64, (20, 96, 12, 52)) / 255) == ("bottom",)
    assert cut_sides(_matte(64, 96, (16, 48, 0, 70)) / 255) == ("left",)
    assert cut_sides(_matte(80, 80, (0, 80, 0, 80)) / 255) == ("top", "bottom", "left", "right")
    assert cut_sides(_matte(80, 80, (10, 70, 10, 70)) / 255) == ()
    a = np.zeros((80, 80))
    a[-1, 40:42] = 1.0  # two stray pixels on the border: not a cut
    a[30:50, 30:50] = 1.0
    assert cut_sides(a) == ()


def test_a_matte_whose_soft_part_runs_off_its_photo_is_cut_there():
    """Hair strands that end on the photo's bottom row and a faint veil (alpha 0.13) along its
    top edge continue past the photo: cut there like an opaque matte; matting noise of a few
    codes along a border is not a cut."""
    a = np.zeros((80, 80))
    a[20:50, 20:60] = 1.0
    for x in (24, 31, 37, 44, 52):  # thin strands of hair from the body down to the bottom row
        a[50:, x] = np.linspace(0.6, 0.08, 30)
    assert cut_sides(a) == ("bottom",)
    veil = np.zeros((80, 80))
    veil[30:60, 20:60] = 1.0
    veil[:30, 10:70] = 0.13
    assert cut_sides(veil) == ("top",)
    noisy = np.zeros((80, 80))
    noisy[30:50, 30:50] = 1.0
    noisy[0], noisy[:, -1] = 2 / 255, 3 / 255  # below the tolerance: no cut
    assert cut_sides(noisy) == ()


def test_real_mattes_cut_at_the_chest_or_legs_are_found(shared_assets, write_recipe):
    recipe = load_recipe(write_recipe(backgrounds=shared_assets / "bg", foregrounds=shared_assets, size=96))
    lib = build_library(recipe)
    cuts = {a.id: a.cut for a in lib.foregrounds}
    assert cuts["fg/rembg_girl-1"] == cuts["fg/rembg_girl-3"] == cuts["fg/pymatting_lemur"] == ("bottom",)
    assert cuts["fg/rembg_car-2"] == ()


def test_a_matte_cut_at_its_bottom_always_lands_on_the_frame_bottom(cut_recipe):
    recipe, lib = cut_recipe
    H, W = recipe.frame
    seen = {"bust": 0, "side-left": 0, "side-right": 0}
    for i in range(300):
        s = sample_scene(recipe, lib, "train", i)
        for role in ("front", "middle"):
            p, name = getattr(s, role), s.assets[role].id
            _, _, ew, eh = lib[name].extent
            w, h = placed_size(p.scale, ew, eh)
            if name == "fg/bust":
                seen["bust"] += 1
                assert p.anchored == ("bottom",) and p.y + h >= H
            elif name == "fg/side":  # cut at its left: on the frame's left edge, or the right one when flipped
                seen["side-right" if p.flip else "side-left"] += 1
                assert p.anchored == (("right",) if p.flip else ("left",))
                assert (p.x + w >= W) if p.flip else (p.x <= 0)
            else:
                assert p.anchored == ()
    assert min(seen.values()) > 20
    # and in the pixels: the bust's alpha reaches the frame's last row, opaque there
    for i in range(300):
        s = sample_scene(recipe, lib, "train", i)
        if s.assets["front"].id == "fg/bust":
            layers = scene_layers(s, lib)
            assert layers.planes[2].alpha[-1].max() == pytest.approx(1.0)
            break


def test_an_asset_no_placement_can_fit_is_skipped_by_name_or_redrawn_and_recorded(cut_recipe, write_recipe, tmp_path):
    recipe, lib = cut_recipe
    # a band cut at both sides must span the frame's width: wider than scene.foreground.scale allows
    _pairs(tmp_path / "fg", {"band": _matte(64, 140, (10, 50, 0, 140))})
    again = build_library(recipe)
    assert "fg/band" not in {a.id for a in again.foregrounds}
    (path, why), = [s for s in again.skipped if "band" in s[0]]
    assert "cut sides (left, right) must span the frame" in why
    stop = load_recipe(write_recipe(foregrounds="fg", size=96, name="stop.toml", on_bad_asset="stop"))
    with pytest.raises(Exception, match="band.*too small for 96x96"):
        build_library(stop)
    # a library that holds it anyway (e.g. from an older scan): it is drawn, rejected and recorded
    band = replace(lib["fg/bust"], id="fg/band", cut=("left", "right"))
    forced = AssetLibrary(lib.backgrounds, [*lib.foregrounds, band], {**lib.splits, "fg/band": "train"}, rules=lib.rules)
    rejected = 0
    for i in range(200):
        s = sample_scene(recipe, forced, "train", i)
        assert "fg/band" not in (s.assets["front"].id, s.assets["middle"].id)
        rejected += "fg/band" in (*s.front.rejected, *s.middle.rejected)
        assert s.to_dict()["front"]["rejected"] == "\n".join(s.front.rejected)
        assert Scene.from_dict(s.to_dict()).front.rejected == s.front.rejected
    assert rejected > 20


def test_nothing_is_magnified_past_max_upscale(demo_recipe, write_recipe, capsys):
    recipe, lib = demo_recipe, build_library(demo_recipe)
    H, W = recipe.frame
    limit = recipe.assets.max_upscale
    for i in range(200):
        s = sample_scene(recipe, lib, "train", i)
        assert s.front.scale <= limit and s.middle.scale <= limit
        assert W / s.background.crop[2] <= limit * 1.01  # crop width -> frame width (rounded crop)
    # at the default (1.0), the built-in photos too small for 512 px are skipped, each named
    skip = load_recipe(write_recipe(size=512, on_bad_asset="skip"))
    names = {p for p, _ in build_library(skip).skipped}
    assert "builtin:bg/chelsea" in names and "builtin:bg/retina" not in names
    assert "magnified 1.71x (assets.max_upscale = 1)" in dict(build_library(skip).skipped)["builtin:bg/chelsea"]
    stop = load_recipe(write_recipe(size=512, on_bad_asset="stop", name="stop.toml"))
    with pytest.raises(Exception, match="builtin:bg/chelsea: too small for 512x512 samples"):
        build_library(stop)


def _full_res_visible(s, lib) -> tuple[float, float]:
    """(middle, front) share of each object's whole placed alpha seen, from the rendered planes."""
    layers = scene_layers(s, lib)
    af, am = layers.planes[2].alpha.astype(np.float64), layers.planes[1].alpha.astype(np.float64)
    out = []
    for role, seen in (("middle", (am * (1 - af)).sum()), ("front", af.sum())):
        p = getattr(s, role)
        rgb, alpha = lib.load_foreground(lib[s.assets[role].id])
        x, y, ew, eh = lib[s.assets[role].id].extent
        w, h = placed_size(p.scale, ew, eh)
        out.append(seen / (alpha[y:y + eh, x:x + ew].sum() * w * h / (ew * eh)))
    return tuple(out)


def test_both_objects_stay_visible_and_the_record_says_how_much(demo_recipe):
    recipe, lib = demo_recipe, build_library(demo_recipe)
    least = recipe.scene.foreground.min_visible
    shares = []
    for i in range(300):
        s = sample_scene(recipe, lib, "train", i)
        assert s.middle.visible >= least and s.front.visible >= least
        shares.append(s.middle.visible)
    assert min(shares) < 0.6 < max(shares)  # occlusion happens, and is limited, not avoided
    for i in range(0, 60, 6):  # the 128 px estimate agrees with the full-resolution planes
        s = sample_scene(recipe, lib, "train", i)
        mid, front = _full_res_visible(s, lib)
        assert abs(mid - s.middle.visible) < 0.06 and abs(front - s.front.visible) < 0.06


def test_focus_targets_are_apart_and_an_impossible_separation_is_refused(demo_recipe, write_recipe):
    recipe, lib = demo_recipe, build_library(demo_recipe)
    for i in range(300):
        a, b = (t.focus for t in sample_scene(recipe, lib, "train", i).targets)
        assert abs(a - b) >= recipe.focus.min_separation
    many = load_recipe(write_recipe(replace={"targets_per_scene = 2": "targets_per_scene = 10\nmin_separation = 0.05"}))
    lib = build_library(many)
    for i in range(40):
        f = np.sort([t.focus for t in sample_scene(many, lib, "train", i).targets])
        assert len(f) == 10 and np.diff(f).min() >= 0.05 - 1e-12 and 0 <= f[0] and f[-1] <= 1
    with pytest.raises(ConfigError, match="focus.min_separation.*at most 0.0455 for 12 targets"):
        load_recipe(write_recipe(name="bad.toml", replace={"targets_per_scene = 2": "targets_per_scene = 12\nmin_separation = 0.05"}))
