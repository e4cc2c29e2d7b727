"""record: what each member holds, byte round trips, determinism, webdataset decoding."""
import io
import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from dofsynth.assets import build_library
from dofsynth.color import linear_to_srgb8, srgb_to_linear
from dofsynth.render.highlight import boost, unboost
from dofsynth.image import to_uint8
from dofsynth.compose import SceneLayers, scene_layers
from dofsynth.recipe import load_recipe
from dofsynth.io import decode_image, encode_png
from dofsynth.render.planes import Plane
from dofsynth.codecs import (SCHEMA_VERSION, encode_alphas, encode_depth, encode_png8, encode_srgb_png_planar,
                             encode_srgb_png_rows)
from dofsynth.record import SampleDecodeError, decode_sample, encode_record
from dofsynth.render import METHODS
from dofsynth.sample import render_sample
from dofsynth.render import render_planes
from dofsynth.optics import aperture_from_dict
from dofsynth.scene import Scene, sample_scene
from dofsynth.shards import write_shard

SMOKE = Path(__file__).resolve().parents[1] / "recipes" / "smoke.toml"


@pytest.fixture(scope="module")
def setup():
    recipe = load_recipe(SMOKE)
    library = build_library(recipe)
    scenes = [sample_scene(recipe, library, "train", i) for i in range(3)]
    return recipe, library, scenes, [render_sample(s, library) for s in scenes]


def test_members_and_record(setup):
    recipe, _, scenes, samples = setup
    for scene, m in zip(scenes, samples):
        n = len(scene.targets)
        assert set(m) == {"aif.png", "depth.exr", "cover.png", "json"} | {f"dof.{i}.png" for i in range(n)}
        rec = json.loads(m["json"])
        assert rec["schema_version"] == SCHEMA_VERSION == 6 and rec["renderer"] == METHODS["layered"].renderer_id and rec["dofsynth_version"] == "0.1.0"
        assert rec["key"] == scene.key and list(rec) == sorted(rec)
        assert {k: v for k, v in rec.items() if k not in ("schema_version", "renderer", "dofsynth_version")} == \
            json.loads(json.dumps(scene.to_dict()))


def _blur_planes(layers, hl) -> list:
    """The planes the targets are rendered from (`margin` px past the frame), boosted."""
    return [Plane(boost(np.array(p.rgb), **hl), p.alpha, p.disparity, p.box) for p in layers.blur_planes]


def _frame(img: np.ndarray, layers) -> np.ndarray:
    """A render of `_blur_planes` (H + 2m, W + 2m, ...) cut to the frame."""
    m = layers.margin
    return img[m:img.shape[0] - m, m:img.shape[1] - m] if m else img


def test_pixels_are_what_the_format_says(setup):
    recipe, library, scenes, samples = setup
    scene, m = scenes[0], samples[0]
    layers = scene_layers(scene, library)
    d = decode_sample(m)
    h, w = recipe.frame
    assert d["aif"].shape == (h, w, 3) and d["depth"].shape == (h, w) and d["cover"].shape == (h, w, 2)
    assert d["depth"].dtype == np.float32 and np.array_equal(d["depth"], layers.disparity)
    assert np.array_equal(to_uint8(d["cover"]), to_uint8(layers.cover))
    hl = vars(scene.options.look.highlight)
    boosted = SceneLayers([Plane(boost(p.rgb, **hl), p.alpha, p.disparity) for p in layers.planes], layers.disparity)
    assert np.array_equal(to_uint8(d["aif"]), linear_to_srgb8(unboost(boosted.aif, **hl)))
    assert layers.margin == scene.background.margin > 0   # targets: the planes past the frame, cut after
    planes = _blur_planes(layers, hl)
    ap = aperture_from_dict(scene.aperture.to_dict())
    for i, t in enumerate(scene.targets):
        want = linear_to_srgb8(unboost(_frame(render_planes(planes, t.focus, t.max_coc, ap, margin=layers.margin),
                                              layers), **hl))
        assert np.array_equal(to_uint8(d["dof"][i]), want)


def test_every_member_round_trips_to_the_same_bytes(setup):
    for m in setup[3]:
        d = decode_sample(m)
        assert encode_png8(to_uint8(d["aif"])) == m["aif.png"]
        assert encode_depth(d["depth"]) == m["depth.exr"]
        assert encode_alphas(d["cover"][..., 0], d["cover"][..., 1]) == m["cover.png"]
        for i, img in enumerate(d["dof"]):
            assert encode_png8(to_uint8(img)) == m[f"dof.{i}.png"]
        assert encode_record(d["record"]) == m["json"]


def test_deterministic_and_rerenderable_from_json(setup):
    recipe, library, scenes, samples = setup
    again = render_sample(sample_scene(recipe, library, "train", 1), library)
    assert again == samples[1]
    from_json = Scene.from_dict(json.loads(samples[2]["json"]))
    assert render_sample(from_json, library) == samples[2]


def test_where_nothing_is_blurred_every_target_is_the_all_in_focus_image(setup):
    """max_coc 0: the targets are the all-in-focus image byte for byte, highlights, hair-like
    soft edges and ramps included; the boost changes only what is blurred."""
    recipe, library, scenes, samples = setup
    for scene in scenes:
        still = render_sample(replace(scene, targets=tuple(replace(t, max_coc=0.0) for t in scene.targets)), library)
        assert all(still[f"dof.{i}.png"] == still["aif.png"] for i in range(len(scene.targets)))
        # The boost undone: where no plane is partly transparent the all-in-focus image is the
        # plain composite (to float rounding); at soft edges it is composited in boosted light.
        plain = decode_sample(render_sample(replace(scene, options=replace(scene.options, look=replace(scene.options.look, highlight=None))), library))
        d = decode_sample(samples[scenes.index(scene)])
        solid = np.all((d["cover"] == 0) | (d["cover"] == 1), axis=2)
        assert np.abs(d["aif"] - plain["aif"])[solid].max() <= 1.5 / 255


def test_webdataset_reads_every_field(setup, tmp_path):
    """FORMAT.md's recipe: `.decode(..., exr_handler)` gives arrays for every member."""
    import webdataset as wds

    from dofsynth.record import exr_handler

    recipe, _, scenes, samples = setup
    path = tmp_path / "train-000000.tar"
    write_shard(path, [(s.key, m) for s, m in zip(scenes, samples)])
    ds = wds.WebDataset(str(path), shardshuffle=False).decode("rgb8", exr_handler)
    got = list(ds)
    assert [g["__key__"] for g in got] == [s.key for s in scenes]
    for g, m in zip(got, samples):
        d = decode_sample(m)
        assert np.array_equal(g["aif.png"], to_uint8(d["aif"]))
        assert np.array_equal(g["cover.png"][:, :, :2], to_uint8(d["cover"])) and not g["cover.png"][:, :, 2].any()
        assert np.array_equal(g["depth.exr"], d["depth"])
        for i, img in enumerate(d["dof"]):
            assert np.array_equal(g[f"dof.{i}.png"], to_uint8(img))
        assert g["json"] == d["record"]
    raw = next(iter(wds.WebDataset(str(path), shardshuffle=False)))  # undecoded: decode_sample takes it as is
    assert decode_sample(raw)["key"] == scenes[0].key


def _chunks(png: bytes) -> list[bytes]:
    out, i = [], 8
    while i < len(png):
        n = int.from_bytes(png[i:i + 4], "big")
        out.append(png[i + 4:i + 8])
        i += 12 + n
    return out


def test_image_members_say_srgb_and_the_depth_member_says_what_it_is(setup):
    import OpenEXR

    m = setup[3][0]
    for name in ("aif.png", "dof.0.png", "dof.1.png"):
        assert _chunks(m[name])[:2] == [b"IHDR", b"sRGB"], name
    assert b"sRGB" not in _chunks(m["cover.png"])           # coverage, not colour
    f = OpenEXR.File(io.BytesIO(m["depth.exr"]))
    assert list(f.channels()) == ["disparity"]                # not "Z": that means distance
    header = f.header()
    assert header["dofsynth:quantity"] == "normalized disparity"
    assert "1 = nearest" in header["dofsynth:convention"] and header["dofsynth:schema_version"] == "6"


def test_shards_of_older_schemas_still_decode(setup):
    """Before schema 3 the depth member's channel was "Z"."""
    from dofsynth.io import encode_exr
    from dofsynth.codecs import decode_depth

    m = dict(setup[3][0])
    depth = decode_sample(m)["depth"]
    m["depth.exr"] = encode_exr(depth, channel="Z")
    assert np.array_equal(decode_sample(m)["depth"], depth) and np.array_equal(decode_depth(m["depth.exr"]), depth)


def test_decode_errors_name_the_member(setup):
    m = dict(setup[3][0])
    key = json.loads(m["json"])["key"]
    with pytest.raises(SampleDecodeError, match=f"{key}.depth.exr"):
        decode_sample({k: v for k, v in m.items() if k != "depth.exr"}, key)
    with pytest.raises(SampleDecodeError, match="numbered 0..N-1"):
        decode_sample({k: v for k, v in m.items() if k != "dof.0.png"}, key)
    small = encode_png(np.zeros((8, 8, 3), np.uint8))
    with pytest.raises(SampleDecodeError, match="aif.png: size"):
        decode_sample({**m, "aif.png": small}, key)
    with pytest.raises(SampleDecodeError, match="json: not valid JSON"):
        decode_sample({**m, "json": b"{"}, key)


def test_record_json_is_canonical():
    a = encode_record({"b": np.float32(0.5), "a": (1, np.int64(2)), "c": np.array([0.25])})
    assert a == b'{"a":[1,2],"b":0.5,"c":[0.25]}\n'
    with pytest.raises(ValueError, match="non-finite"):
        encode_record({"x": float("nan")})


def test_cover_from_alphas_is_the_cover_png(setup):
    g = np.random.default_rng(5)
    front, middle = g.random((2, 30, 40), dtype=np.float32)
    front[:5] = 0.0
    png = encode_alphas(front, middle)
    import cv2

    img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED)[:, :, ::-1]
    np.testing.assert_array_equal(img[..., 0], to_uint8(front))
    np.testing.assert_array_equal(img[..., 1], to_uint8(middle))
    assert not img[..., 2].any()
    with pytest.raises(ValueError, match="cover"):
        encode_alphas(front, middle[:, :3])


def test_planar_srgb_png_is_the_same_bytes():
    g = np.random.default_rng(np.random.SeedSequence(31))
    for h, w in ((150, 37), (64, 5), (1, 3)):
        x = g.random((3, h, w), dtype=np.float32) * 1.4 - 0.2  # out of [0, 1] too
        x[1, 0, 0], x[2, -1, -1] = np.nan, np.inf
        hwc = np.ascontiguousarray(x.transpose(1, 2, 0))
        png = encode_srgb_png_rows(lambda r0, r1: hwc[r0:r1], h, w)
        assert encode_srgb_png_planar(x) == png
        codes = decode_image(png, "x.png")  # float RGB in [0, 1]: the member's sRGB codes / 255
        assert np.array_equal(np.round(codes * 255).astype(np.uint8), linear_to_srgb8(hwc))  # RGB order, every row
    with pytest.raises(ValueError, match="3, H, W"):
        encode_srgb_png_planar(np.zeros((4, 4, 3), np.float32))


def test_optional_members_coc_maps_and_layers(tmp_path):
    """render.members = ["coc", "layers"]: coc.N.exr is max_coc * (depth - focus), the layers
    composited back to front give the all-in-focus image, and the record says they are there."""
    import re

    from dofsynth.assets import build_library
    from dofsynth.color import linear_to_srgb
    from dofsynth.record import exr_handler
    from dofsynth.recipe import recipe_from_text
    from dofsynth.scene import sample_scene

    root = Path(__file__).resolve().parents[1] / "recipes"
    text = re.sub(r"(?m)^\[render\]$", '[render]\nmembers = ["coc", "layers"]', (root / "smoke.toml").read_text())
    recipe = recipe_from_text(text, "smoke-members.toml", root)
    scene = sample_scene(recipe, build_library(recipe), "train", 0)
    m = render_sample(scene, build_library(recipe))
    assert {"coc.0.exr", "layer.0.exr", "layer.1.exr", "layer.2.exr"} <= set(m)
    d = decode_sample(m)
    assert d["record"]["options"]["members"] == ["coc", "layers"]
    for n, t in enumerate(d["record"]["targets"]):
        coc = exr_handler(f"{d['key']}.coc.{n}.exr", m[f"coc.{n}.exr"])
        assert np.array_equal(coc, np.float32(t["max_coc"]) * (d["depth"] - np.float32(t["focus"])))
    comp = np.zeros(d["aif"].shape, np.float32)
    for k in range(3):
        layer = exr_handler("layer.exr", m[f"layer.{k}.exr"])
        assert layer.shape == d["aif"].shape[:2] + (5,)
        a = layer[:, :, 3:4]
        comp = layer[:, :, :3] * a + (1 - a) * comp
    hard = np.all((d["cover"] == 0) | (d["cover"] == 1), axis=2)
    assert np.abs(linear_to_srgb(comp) - d["aif"])[hard].max() <= 0.5 / 255 + 1e-6
    plain = render_sample(sample_scene(load_recipe(root / "smoke.toml"), build_library(recipe), "train", 0),
                          build_library(recipe))
    assert not any(k.startswith(("coc.", "layer.")) for k in plain)


def test_longitudinal_chromatic_aberration_scales_each_channels_coc():
    """render.chromatic = [0.8, 1.0, 1.25]: the boosted target's red is the render at 0.8 x
    max_coc, green the plain one, blue at 1.25 x, before the highlight inverse maps the result
    back; the record keeps the scales."""
    import re

    from dofsynth.assets import build_library
    from dofsynth.recipe import recipe_from_text
    from dofsynth.scene import sample_scene

    root = Path(__file__).resolve().parents[1] / "recipes"
    base = (root / "smoke.toml").read_text()
    text = re.sub(r"(?m)^\[render\]$", "[render]\nchromatic = [0.8, 1.0, 1.25]", base)
    recipe = recipe_from_text(text, "smoke-lca.toml", root)
    library = build_library(recipe)
    scene = sample_scene(recipe, library, "train", 1)
    assert scene.to_dict()["options"]["chromatic"] == [0.8, 1.0, 1.25]
    d = decode_sample(render_sample(scene, library))
    layers = scene_layers(scene, library)
    hl = scene.to_dict()["options"]["highlight"]
    planes = _blur_planes(layers, hl)
    ap = aperture_from_dict(scene.aperture.to_dict())
    t = scene.targets[0]
    mixed = np.stack([_frame(render_planes(planes, t.focus, t.max_coc * s, ap, margin=layers.margin), layers)[:, :, ch]
                      for ch, s in enumerate((0.8, 1.0, 1.25))], axis=2)
    assert np.array_equal(to_uint8(d["dof"][0]), linear_to_srgb8(unboost(mixed, **hl)))
    same = _frame(render_planes(planes, t.focus, t.max_coc, ap, margin=layers.margin), layers)
    assert not np.array_equal(mixed[:, :, 0], same[:, :, 0])      # red really is defocused differently
    plain = sample_scene(recipe_from_text(base, "smoke.toml", root), library, "train", 1)
    assert "chromatic" not in plain.to_dict()["options"]


def test_dual_pixel_views_are_mirror_halves_that_sum_to_the_target():
    """A mirror-symmetric scene through a disk: the left view is the right one mirrored, and
    the area-weighted sum of the two views is the target (in linear light, exactly)."""
    from dofsynth.optics import Disk
    from dofsynth.render.subaperture import halves

    h, w = 40, 48
    yy, xx = np.mgrid[0:h, 0:w]
    bg = np.stack([np.cos(yy / 3.0) * 0.4 + 0.5, np.abs(xx - (w - 1) / 2) / w, np.full((h, w), 0.3)], axis=2)
    disc = np.clip(9 - np.hypot(yy - 20, xx - (w - 1) / 2), 0, 1).astype(np.float32)
    planes = [Plane(bg.astype(np.float32), np.ones((h, w), np.float32), 0.1),
              Plane(np.zeros((h, w, 3), np.float32) + [0.9, 0.2, 0.1], disc, 0.8)]
    (left, wl), (right, wr) = halves(Disk())
    assert wl == pytest.approx(0.5) and wr == pytest.approx(0.5)
    lv, rv = (render_planes(planes, 0.1, 10.0, a) for a in (left, right))
    assert np.allclose(lv, rv[:, ::-1], atol=1e-5)
    assert not np.allclose(lv, rv, atol=1e-3)        # the views differ: the disc's blur shifts
    full = render_planes(planes, 0.1, 10.0, Disk())
    both = wl * lv + wr * rv
    assert np.abs(both - full)[disc == 0].max() < 0.02     # the layered target, away from the occluder


def test_dual_pixel_views_that_would_pass_1_keep_the_targets_hue():
    """At a bright blurred edge one half-aperture view, scaled to add up to the target, would
    pass 1 in one channel: both views then move toward the target by one factor per pixel.
    They still add up to it and keep its hue, where clipping that channel alone turned the
    other view red (0.6 red against 0.024 green here: measured on a lion's edge over dark hair)."""
    from dofsynth.render.look import views_adding_up

    target = np.float32([0.8, 0.5, 0.3]).reshape(3, 1, 1)
    left, right = np.float32([0.9, 0.8, 0.6]).reshape(3, 1, 1), np.full((3, 1, 1), 0.02, np.float32)
    lv, rv = views_adding_up(target, left, right, 0.5, 0.5)
    np.testing.assert_allclose(0.5 * lv + 0.5 * rv, target, atol=1e-6)
    assert lv.max() <= 1.0 and rv.min() >= 0.0
    for view in (lv, rv):
        hue = view[:, 0, 0] / view[1, 0, 0]
        np.testing.assert_allclose(hue, target[:, 0, 0] / target[1, 0, 0], rtol=0.1)
    assert float(lv[0, 0, 0]) == pytest.approx(1.0) and float(rv[0, 0, 0]) < float(lv[0, 0, 0])  # parallax kept


def test_dual_pixel_members_in_a_sample():
    import re

    from dofsynth.assets import build_library
    from dofsynth.recipe import recipe_from_text
    from dofsynth.scene import sample_scene

    root = Path(__file__).resolve().parents[1] / "recipes"
    text = re.sub(r"(?m)^\[render\]$", '[render]\nmembers = ["dual_pixel"]', (root / "smoke.toml").read_text())
    recipe = recipe_from_text(text, "smoke-dp.toml", root)
    library = build_library(recipe)
    m = render_sample(sample_scene(recipe, library, "train", 0), library)
    d = decode_sample(m)
    for n in range(len(d["dof"])):
        lv = decode_image(m[f"dp.{n}.left.png"])
        rv = decode_image(m[f"dp.{n}.right.png"])
        assert lv.shape == d["dof"][n].shape
        # the 8-bit views average to the target within the rounding (and the highlight inverse)
        mean = (srgb_to_linear(lv) + srgb_to_linear(rv)) / 2      # a disk: the halves weigh 1/2 each
        assert np.abs(mean - srgb_to_linear(d["dof"][n])).mean() < 2e-3
        assert not np.array_equal(lv, rv)


def test_a_recipe_can_choose_the_subaperture_method_and_the_record_says_so(tmp_path):
    import re

    from dofsynth.assets import build_library
    from dofsynth.cli import main
    from dofsynth.recipe import recipe_from_text
    from dofsynth.scene import sample_scene

    root = Path(__file__).resolve().parents[1] / "recipes"
    text = re.sub(r"(?m)^\[render\]$", '[render]\nmethod = "subaperture"\ncells = 2\ncat_eye = 0.3', (root / "smoke.toml").read_text())
    recipe = recipe_from_text(text, "smoke-sub.toml", root)
    library = build_library(recipe)
    scene = sample_scene(recipe, library, "train", 0)
    d = decode_sample(render_sample(scene, library))
    assert d["record"]["renderer"] == "subaperture-v12"
    assert {k: d["record"]["options"][k] for k in ("method", "cells", "cat_eye")} == {"method": "subaperture", "cells": 2, "cat_eye": 0.3}
    layers = scene_layers(scene, library)
    hl = d["record"]["options"]["highlight"]
    t = scene.targets[0]
    want = _frame(render_planes(_blur_planes(layers, hl), t.focus, t.max_coc, aperture_from_dict(d["record"]["aperture"]),
                                method="subaperture", cells=2, cat_eye=0.3, margin=layers.margin), layers)
    assert np.array_equal(to_uint8(d["dof"][0]), linear_to_srgb8(unboost(want, **hl)))
    path = tmp_path / "sub.toml"
    path.write_text(text.replace('"builtin"', '"builtin"'))
    out = tmp_path / "set"
    assert main(["generate", str(path), "--out", str(out), "-q"]) == 0 and main(["verify", str(out), "--deep", "-q"]) == 0
