from dataclasses import replace

import cv2
import numpy as np
import pytest

from dofsynth.assets import build_library
from dofsynth.compose import place_premultiplied, scene_layers
from dofsynth.image import area_halve, premultiply, pyramid_level
from dofsynth.image import resize
from dofsynth.recipe import load_recipe
from dofsynth.render.planes import validate_planes
from dofsynth.assets.placement import ObjectParams, placed_size
from dofsynth.render.planes import background_disparity
from dofsynth.scene import sample_scene



def test_horizontal_ramp_runs_from_b0_left_to_b1_right():
    d = background_disparity("ramp", 0.4, 0.1, "horizontal", 5, 7)
    assert d.dtype == np.float32 and d.shape == (5, 7)
    assert np.allclose(d[:, 0], 0.4) and np.allclose(d[:, -1], 0.1)
    assert (np.diff(d, axis=1) < 0).all() and (np.diff(d, axis=0) == 0).all()


def test_vertical_ramp_runs_from_b0_bottom_to_b1_top():
    d = background_disparity("ramp", 0.4, 0.1, "vertical", 6, 3)
    assert np.allclose(d[-1], 0.4) and np.allclose(d[0], 0.1)
    assert (np.diff(d, axis=0) > 0).all()          # rows go top -> bottom: disparity grows
    assert (np.diff(d, axis=1) == 0).all()


def test_flat_background_and_bad_modes():
    assert (background_disparity("flat", 0.0, 0.0, None, 4, 4) == 0).all()
    with pytest.raises(ValueError, match="mode"):
        background_disparity("tilt", 0.4, 0.1, "horizontal", 4, 4)
    with pytest.raises(ValueError, match="direction"):
        background_disparity("ramp", 0.4, 0.1, "diagonal", 4, 4)


@pytest.fixture(scope="module")
def layers_of(smoke_recipe, smoke_library):
    return [(s, scene_layers(s, smoke_library))
            for s in (sample_scene(smoke_recipe, smoke_library, sp, i)
                      for sp, n in (("train", 6), ("test", 2)) for i in range(n))]


def test_layers_shapes_and_renderer_contract(layers_of):
    assert any(o.anchored for s, _ in layers_of for o in (s.middle, s.front))  # objects cut by their photo
    for s, L in layers_of:
        H, W = s.size
        assert [p.rgb.shape for p in L.planes] == [(H, W, 3)] * 3
        assert L.aif.shape == (H, W, 3) and L.disparity.shape == (H, W) and L.cover.shape == (H, W, 2)
        assert all(a.dtype == np.float32 for a in (L.aif, L.disparity, L.cover))
        assert (L.planes[0].alpha == 1).all()
        assert L.planes[1].disparity == s.middle.disparity and L.planes[2].disparity == s.front.disparity
        for t in s.targets:
            validate_planes(L.planes, t.focus, t.max_coc)
        assert L.planes[0].box is None
        assert L.canvas is not None
        for p in L.planes[1:] + L.canvas[1:]:  # each cutout carries the tight box of alpha > 0 (empty: (0, 0, 0, 0))
            y0, y1, x0, x1 = p.box
            on = p.alpha > 0
            assert on[y0:y1, x0:x1].sum() == on.sum()
            if on.any():
                assert on[y0].any() and on[y1 - 1].any() and on[:, x0].any() and on[:, x1 - 1].any()


def test_planes_are_in_front_of_what_they_cover(layers_of):
    for s, L in layers_of:
        bg = L.planes[0].disparity_map()
        mid, front = L.planes[1], L.planes[2]
        assert mid.alpha.any() and front.alpha.any()
        assert bg[mid.alpha > 0].max() < mid.disparity < front.disparity
        assert bg[front.alpha > 0].max() < front.disparity


def test_aif_disparity_and_cover_follow_the_planes(layers_of):
    for s, L in layers_of:
        bg, mid, front = L.planes
        ref = bg.rgb
        for p in (mid, front):
            ref = p.rgb * p.alpha[..., None] + ref * (1 - p.alpha[..., None])
        np.testing.assert_array_equal(L.aif, ref)  # "over", float32, each product rounded once
        want = np.where(front.alpha >= 0.5, front.disparity,
                        np.where(mid.alpha >= 0.5, mid.disparity, bg.disparity_map()))
        assert np.array_equal(L.disparity, want.astype(np.float32))
        assert np.array_equal(L.cover[..., 0], front.alpha) and np.array_equal(L.cover[..., 1], mid.alpha)


def test_objects_are_zero_outside_their_placed_rectangle(layers_of, smoke_library):
    for s, L in layers_of:
        for p, params, role in ((L.planes[1], s.middle, "middle"), (L.planes[2], s.front, "front")):
            _, _, ew, eh = smoke_library[s.assets[role].id].extent
            w, h = placed_size(params.scale, ew, eh)
            mask = np.zeros(s.size, bool)
            mask[max(params.y, 0):max(params.y + h, 0), max(params.x, 0):max(params.x + w, 0)] = True
            assert (p.alpha[~mask] == 0).all() and (p.rgb[~mask] == 0).all()


def place_foreground(rgb, alpha, extent, params, h, w):
    """An object placed from its whole asset by the public pieces: premultiply its extent, halve
    down to the pyramid level of its placed size, place (what scene_layers does from the cache)."""
    _, _, ew, eh = extent
    size = placed_size(params.scale, ew, eh)
    premul = premultiply(rgb, alpha, extent)
    for _ in range(pyramid_level((ew, eh), size)):
        premul = area_halve(premul)
    return place_premultiplied(premul, size, params, h, w)


def test_resampling_is_premultiplied_no_fringe_from_the_transparent_surround():
    h, w = 90, 90
    rgb = np.zeros((h, w, 3), np.float32)
    rgb[..., 1] = 1.0                       # bright green where alpha = 0
    alpha = np.zeros((h, w), np.float32)
    alpha[20:70, 25:65] = 1.0
    rgb[alpha > 0] = (1.0, 0.0, 0.0)        # red object
    for scale in (0.37, 1.7):
        params = ObjectParams(disparity=0.9, scale=scale, x=3, y=4, flip=False)
        prgb, pa = place_foreground(rgb, alpha, (20, 15, 50, 60), params, 160, 160)
        edge = (pa > 0) & (pa < 1)
        assert edge.any()
        assert np.abs(prgb[pa > 0][:, 1]).max() < 1e-5     # no green leaked in
        assert np.allclose(prgb[pa > 0][:, 0], 1.0, atol=1e-4)


def test_cutout_frames_are_writable_zeros_that_pickle():
    """compose.lazy_zeros (the cutout frames): writable float32 zeros, each its own buffer, that
    survive pickling (Ray, spawn workers). Their memory cost is measured in benchmarks/generate.py."""
    import pickle

    from dofsynth.compose import lazy_zeros

    a, b = lazy_zeros((5, 7, 3)), lazy_zeros((5, 7))
    assert a.dtype == np.float32 and a.shape == (5, 7, 3) and a.flags.writeable and not a.any()
    a[1, 2] = 3.0
    assert not b.any() and a.sum() == 9.0 and lazy_zeros((0, 4)).shape == (0, 4)
    np.testing.assert_array_equal(pickle.loads(pickle.dumps(a)), a)


def test_identity_placement_and_flip():
    rng = np.random.default_rng(0)
    rgb = rng.random((40, 50, 3)).astype(np.float32)
    alpha = np.clip(rng.random((40, 50)) * 1.5, 0, 1).astype(np.float32)
    p = ObjectParams(disparity=0.9, scale=1.0, x=5, y=6, flip=False)
    prgb, pa = place_foreground(rgb, alpha, (0, 0, 50, 40), p, 60, 70)
    assert np.allclose(pa[6:46, 5:55], alpha)
    on = alpha > 1e-3
    assert np.allclose(prgb[6:46, 5:55][on], rgb[on], atol=1e-4)
    _, fa = place_foreground(rgb, alpha, (0, 0, 50, 40), replace(p, flip=True), 60, 70)
    assert np.allclose(fa[6:46, 5:55], alpha[:, ::-1])
    # partly outside the frame: clipped, not wrapped
    _, ca = place_foreground(rgb, alpha, (0, 0, 50, 40), replace(p, x=-10, y=-20), 60, 70)
    assert np.allclose(ca[:20, :40], alpha[20:, 10:]) and (ca[20:] == 0).all()


def test_resize_uses_area_when_shrinking():
    img = np.zeros((8, 8), np.float32)
    img[::2, ::2] = 1.0
    assert np.allclose(resize(img, 4, 4), 0.25)   # area average, not point sampling


def test_compose_with_real_cutouts(write_recipe, shared_assets):
    recipe = load_recipe(write_recipe(backgrounds=shared_assets / "bg", foregrounds=shared_assets, size=96))
    lib = build_library(recipe)
    s = sample_scene(recipe, lib, "train", 1)
    L = scene_layers(s, lib)
    assert L.aif.shape == (96, 96, 3) and np.isfinite(L.aif).all() and L.aif.min() >= 0
    assert ((L.cover > 0) & (L.cover < 1)).any()       # real mattes keep fractional edges


def test_a_changed_asset_is_refused(layers_of, smoke_library):
    s, _ = layers_of[0]
    bad = replace(s, assets={**s.assets, "front": replace(s.assets["front"], sha256="0" * 64)})
    with pytest.raises(ValueError, match="front asset .* changed"):
        scene_layers(bad, smoke_library)


def test_background_plane_holds_no_frame_sized_alpha_or_disparity(layers_of):
    """Memory at large sizes: the background's alpha is a broadcast 1 and its disparity a float
    (flat) or a broadcast row/column (ramp) that equals background_disparity."""
    for s, L in layers_of:
        bg = L.planes[0]
        H, W = s.size
        assert bg.alpha.shape == (H, W) and bg.alpha.strides == (0, 0) and not bg.alpha.flags.writeable
        b = s.background
        want = background_disparity(b.mode, b.b0, b.b1, b.direction, H, W)
        if b.mode == "flat":
            assert isinstance(bg.disparity, float) and bg.disparity == want[0, 0]
        else:
            assert 0 in bg.disparity.strides and np.array_equal(bg.disparity, want)
        for p in L.planes:  # the renderer may boost colour in place: planes own their colour
            assert p.rgb.flags.writeable


def test_aif_rows_are_the_aif(layers_of):
    for s, L in layers_of[:3]:
        full = L.aif
        H = full.shape[0]
        blocks = np.concatenate([L.aif_rows(r, min(r + 7, H)) for r in range(0, H, 7)])
        np.testing.assert_array_equal(blocks, full)


def test_small_placements_resample_from_the_cached_pyramid_with_the_same_pixels(demo_recipe, monkeypatch):
    """scene_layers takes each object from the library's cached premultiplied pyramid
    (AssetLibrary.premultiplied): the same pixels as placing from the whole asset, the
    level that is still at least the placed size, and cached by file hash and level."""
    from dofsynth.image import halved_size

    assert pyramid_level((400, 300), (400, 300)) == 0 and pyramid_level((400, 300), (500, 100)) == 0
    assert pyramid_level((400, 300), (200, 150)) == 1 and pyramid_level((400, 300), (100, 74)) == 2 and pyramid_level((400, 300), (101, 74)) == 1
    assert halved_size(401, 3) == (200, 1) and halved_size(1, 1) == (1, 1)
    lib = build_library(demo_recipe)
    seen_levels = set()
    for i in range(12):
        s = sample_scene(demo_recipe, lib, "train", i)
        layers = scene_layers(s, lib)
        for plane, role in ((layers.planes[1], "middle"), (layers.planes[2], "front")):
            asset, params = lib[s.assets[role].id], getattr(s, role)
            rgb, alpha = lib.load_foreground(asset)
            want_rgb, want_a = place_foreground(rgb, alpha, asset.extent, params, *s.size)
            assert np.array_equal(plane.alpha, want_a) and np.array_equal(plane.rgb, want_rgb)
            _, _, ew, eh = asset.extent
            seen_levels.add(pyramid_level((ew, eh), placed_size(params.scale, ew, eh)))
    assert 0 in seen_levels and max(seen_levels) >= 1  # both paths were taken
    keys = [k for k in lib._cache if "premul@" in k]
    assert keys and all(k.split(":")[0].split("+")[0] in {a.sha256 for a in lib.foregrounds} for k in keys)
    # DOFSYNTH_ASSET_CACHE_MIB bounds the cache of the process that reads it: 0 keeps nothing
    monkeypatch.setenv("DOFSYNTH_ASSET_CACHE_MIB", "0")
    fresh = build_library(demo_recipe)
    scene_layers(sample_scene(demo_recipe, fresh, "train", 0), fresh)
    assert not fresh._cache
    monkeypatch.setenv("DOFSYNTH_ASSET_CACHE_MIB", "lots")
    with pytest.raises(ValueError, match="DOFSYNTH_ASSET_CACHE_MIB='lots': expected a number of MiB"):
        scene_layers(sample_scene(demo_recipe, fresh, "train", 0), fresh)


def _reference_target(scene, library, n: int) -> np.ndarray:
    """Target n of `scene` the long way: the WHOLE background photo as the plane (flipped as
    the scene says, at the crop's scale 1), the objects placed on it where the crop puts them,
    rendered and cut to the frame afterwards: linear (3, H, W)."""
    from dofsynth.compose import extend_cut_sides
    from dofsynth.image import pyramid_level
    from dofsynth.render.look import prepare_planes, render_look, restore
    from dofsynth.render.planes import Plane

    bgp, (h, w) = scene.background, scene.size
    photo = np.array(library.load_background(library[scene.assets["background"].id]), dtype=np.float32)
    x, y, cw, ch = bgp.crop
    assert (cw, ch) == (w, h)  # scale 1
    if bgp.flip:
        photo, x = np.ascontiguousarray(photo[:, ::-1]), photo.shape[1] - x - cw
    H, W = photo.shape[:2]
    planes = [Plane(photo, np.ones((H, W), np.float32), float(bgp.b0))]
    for role, params in (("middle", scene.middle), ("front", scene.front)):
        asset = library[scene.assets[role].id]
        size = placed_size(params.scale, *asset.extent[2:])
        premul = library.premultiplied(asset, pyramid_level(asset.extent[2:], size))
        rgb, a = place_premultiplied(premul, size, replace(params, x=params.x + x, y=params.y + y), H, W)
        extend_cut_sides(rgb, a, params.x + x, params.y + y, size, params.anchored)
        planes.append(Plane(rgb, a, float(params.disparity)))
    look, t = scene.options.look, scene.targets[n]
    img = restore(render_look(prepare_planes(planes, look), t.focus, t.max_coc, scene.aperture, look), look)
    return img[:, y:y + h, x:x + w]


def test_a_target_blurs_what_the_photo_holds_past_the_frame_edge(tmp_path, write_recipe):
    """A 64 px frame cropped 1:1 from a 160 px photo with bright lights all around: each
    target equals a render of the whole photo cut to the frame afterwards, within 1 sRGB code,
    border band included, wherever the photo holds the margin; replicating the frame's edge
    instead (margin 0, how targets were made before) is far off in the border band."""
    from dofsynth.codecs import encode_srgb_png_planar
    from dofsynth.io import decode_image
    from dofsynth.sample import render_sample

    rng = np.random.default_rng(3)
    photo = (rng.random((160, 160, 3)) * 0.3).astype(np.float32)
    photo[2::9, 2::9] = 1.0   # lights everywhere, also just past any crop's edge
    (tmp_path / "bg").mkdir()
    cv2.imwrite(str(tmp_path / "bg" / "lights.png"), np.round(photo * 255).astype(np.uint8))
    recipe = load_recipe(write_recipe(backgrounds=tmp_path / "bg", replace={
        "flat_share = 0.3": "flat_share = 1.0", "crop = [0.6, 1.0]": "crop = [0.4, 0.4]",
        "max_coc = [2.0, 4.0]": "max_coc = [6.0, 8.0]", "test_share = 0.25": "test_share = 0.0",
        "samples = { train = 6, test = 2 }": "samples = { train = 6, test = 0 }"}))
    library = build_library(recipe)
    checked = worst = 0
    for index in range(6):
        scene = sample_scene(recipe, library, "train", index)
        m = scene.background.margin
        assert m == max(int(np.ceil(t.max_coc * max(abs(d - t.focus) for d in (0.0, scene.middle.disparity,
                                                                                 scene.front.disparity))))
                        for t in scene.targets)
        if scene.background.real != (m, m, m, m):
            continue   # the crop lies too near the photo's edge for the comparison
        members = render_sample(scene, library)
        old = render_sample(replace(scene, background=replace(scene.background, margin=0)), library)
        for n in range(len(scene.targets)):
            got = decode_image(members[f"dof.{n}.png"], raw=True).astype(int)
            want = decode_image(encode_srgb_png_planar(_reference_target(scene, library, n)), raw=True).astype(int)
            assert np.abs(got - want).max() <= 1, (index, n)
            band = np.ones(got.shape[:2], bool)
            band[m:-m, m:-m] = False
            before = decode_image(old[f"dof.{n}.png"], raw=True).astype(int)
            worst = max(worst, int(np.abs(before - want)[band].max()))
            checked += 1
    assert checked >= 4 and worst > 40, (checked, worst)   # the edge copies were far off


def test_the_canvas_continues_the_ramp_and_cut_objects_and_repeats_only_where_the_photo_ends():
    """Past the frame: a ramp goes on linearly (clipped to [0, 1]); an object cut at its bottom
    is repeated from its cut line down to the canvas edge, other sides are not; the photo's
    own pixels fill the margin as far as `real_margin` says, its edge repeated beyond."""
    from dofsynth.compose import beyond_frame, extend_cut_sides, ramp_beyond
    from dofsynth.scene import BackgroundParams, real_margin

    bgp = BackgroundParams(mode="ramp", b0=0.4, b1=0.25, direction="horizontal", crop=(0, 0, 8, 8), flip=False)
    row = ramp_beyond(bgp, 6, 7, 3)[0]
    assert row.shape == (13,) and np.allclose(row[3:10], np.linspace(0.4, 0.25, 7), atol=1e-6)
    assert np.allclose(np.diff(row), -0.025, atol=1e-6)   # the same slope on past both edges
    steep = ramp_beyond(replace(bgp, b0=1.0, b1=0.9, direction="vertical"), 4, 4, 50)[:, 0]
    assert steep.max() == 1.0 and steep.min() >= 0.0 and steep[-1] == 1.0   # clipped; b0 at the bottom

    rgb, alpha = np.zeros((20, 20, 3), np.float32), np.zeros((20, 20), np.float32)
    alpha[5:12, 6:10] = 1.0
    alpha[11, 6:10] = 0.5   # the cut line is soft
    rgb[5:12, 6:10] = 0.7
    extend_cut_sides(rgb, alpha, 6, 5, (4, 7), ("bottom",))
    assert np.array_equal(alpha[12:, 6:10], np.full((8, 4), 0.5, np.float32)) and not alpha[:5].any()
    assert not alpha[:, :6].any() and not alpha[:, 10:].any() and np.allclose(rgb[12:, 6:10], 0.7)

    photo = np.random.default_rng(0).random((40, 60, 3)).astype(np.float32)
    crop, m = (5, 30, 10, 10), 8   # 5 px of photo left of the crop, 0 below, scale 1
    canvas = beyond_frame(photo, crop, False, 10, 10, m)
    top, bottom, left, right = real_margin(crop, (60, 40), (10, 10), m, False)
    assert (top, bottom, left, right) == (8, 0, 5, 8)
    assert np.array_equal(canvas[m - top:m + 10, m - left:m + 10 + right], photo[30 - top:40, 5 - left:15 + right])
    assert np.array_equal(canvas[m + 10:, m - left:m + 10 + right], np.broadcast_to(photo[39, :23], (m, 23, 3)))
    assert np.array_equal(canvas[:, :m - left], np.broadcast_to(canvas[:, m - left:m - left + 1], (26, 3, 3)))
    flipped = beyond_frame(photo, crop, True, 10, 10, m)
    assert np.array_equal(flipped, canvas[:, ::-1])   # scale 1: flipping the window flips the canvas
    # into the caller's canvas: everything but the frame, the same values
    given = np.full((26, 26, 3), -1.0, np.float32)
    assert beyond_frame(photo, crop, False, 10, 10, m, out=given) is given
    outside = np.ones((26, 26), bool)
    outside[m:m + 10, m:m + 10] = False
    assert (given[~outside] == -1.0).all() and np.array_equal(given[outside], canvas[outside])


def test_the_background_resampled_into_a_canvas_view_is_the_same_as_on_its_own():
    from dofsynth.compose import background_image

    photo = np.maximum(np.random.default_rng(1).random((90, 120, 3)).astype(np.float32) - 0.6, 0.0)  # many 0
    for crop, flip, (h, w) in (((10, 5, 80, 60), False, (40, 30)), ((0, 0, 50, 50), True, (70, 70)),
                               ((3, 4, 30, 20), False, (20, 30))):  # shrink, grow, same size
        alone = background_image(photo, crop, flip, h, w)
        canvas = np.zeros((h + 8, w + 8, 3), np.float32)
        view = canvas[4:4 + h, 4:4 + w]
        assert background_image(photo, crop, flip, h, w, out=view) is view
        assert np.array_equal(view, alone) and alone.min() == 0.0
        assert not canvas[:4].any() and not canvas[:, :4].any()


def test_a_sample_refuses_planes_with_non_finite_values(layers_of, smoke_library, monkeypatch):
    """The planes' values are checked once per sample, before its first target: a NaN in the
    background is still refused by name."""
    import dofsynth.sample as sample_module

    s, L = layers_of[0]
    bg = L.blur_planes[0]
    rgb = np.array(bg.rgb, copy=True)
    rgb[3, 4, 1] = np.nan
    poisoned = replace(L, canvas=[replace(bg, rgb=rgb)] + list(L.blur_planes[1:]))
    monkeypatch.setattr(sample_module, "scene_layers", lambda scene, library: poisoned)
    with pytest.raises(ValueError, match=r"planes\[0\]\.rgb contains NaN or inf"):
        sample_module.render_sample(s, smoke_library)
