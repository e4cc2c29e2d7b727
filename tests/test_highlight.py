"""The highlight boost (dofsynth.render.highlight): its formula, its exact inverse, hues kept, in-focus
pixels returned as they were, and point highlights turned into visible discs."""
from __future__ import annotations

import numpy as np
import pytest

from dofsynth.color import linear_to_srgb8, srgb_to_linear
from dofsynth.render.highlight import KNOTS, boost, srgb_decode_exact, unboost
from dofsynth.optics import Polygon, kernel
from dofsynth.render import Plane, render_planes


def rng(seed):
    return np.random.default_rng(np.random.SeedSequence(seed))


def formula(x, threshold=0.9, gain=4.0, power=2.0):
    """B(x) = x (1 + gain s^power), s from the linear max, in float64 (no knots)."""
    t = srgb_to_linear(np.float32(threshold)).astype(np.float64)
    m = x.astype(np.float64).max(axis=-1, keepdims=True)
    s = np.clip((m - t) / (1 - t), 0, 1)
    return x * (1 + gain * s**power)


def test_the_boost_is_the_formula_within_its_knots_and_leaves_dark_pixels_alone(passes):
    x = rng(1).random((120, 90, 3), dtype=np.float32) ** 0.5
    x[0, 0], x[0, 1], x[0, 2] = 1.0, (2.0, 1.0, 0.5), 0.0
    b = boost(x, 0.9, 4.0, 2.0)
    # linear interpolation of s^2 on KNOTS segments: within gain / (8 KNOTS^2) of the formula
    np.testing.assert_allclose(b, formula(x), rtol=0, atol=4.0 * 5 / (8 * KNOTS**2) + 1e-6)
    np.testing.assert_allclose(b[0, 0], 5.0) and np.testing.assert_allclose(b[0, 1], (10.0, 5.0, 2.5))
    dark = x.max(axis=2) <= srgb_decode_exact(0.9)
    assert dark.mean() > 0.2 and np.array_equal(b[dark], x[dark])  # bit for bit
    ratio = b / np.where(x > 0, x, 1)  # one factor per pixel: hues kept
    assert np.ptp(ratio[x.min(axis=2) > 1e-3], axis=1).max() < 1e-6


def test_unboost_is_the_exact_inverse_in_any_layout(passes):
    x = rng(2).random((64, 70, 3), dtype=np.float32)
    x[:20] = 0.75 + 0.25 * x[:20]
    x[30, 30] = (3.0, 0.2, 0.1)  # beyond white (an HDR asset)
    for params in ((0.9, 4.0, 2.0), (0.5, 20.0, 0.7), (0.99, 1.0, 6.0)):
        t = srgb_decode_exact(params[0])
        knots = (t + (1 - t) * np.arange(KNOTS + 1) / KNOTS).astype(np.float32)  # maxima on and by the knots
        x[40:44, :65, 0] = np.resize(knots, 260).reshape(4, 65)
        x[44:48, :65, 0] = np.resize(np.nextafter(knots, np.float32(2)), 260).reshape(4, 65)
        x[40:48, :65, 1:] = 0.5 * x[40:48, :65, :1]
        back = unboost(boost(x, *params), *params)
        np.testing.assert_allclose(back, x, rtol=3e-7, atol=1e-9)
        assert np.array_equal(linear_to_srgb8(back), linear_to_srgb8(x))
    planar = np.ascontiguousarray(x.transpose(2, 0, 1))
    np.testing.assert_array_equal(boost(planar, axis=0).transpose(1, 2, 0), boost(x))
    inplace = x.copy()
    view = inplace[5:40, 3:50]  # a non-contiguous view: writes go through, nothing outside it
    assert boost(view, out=view) is view
    np.testing.assert_array_equal(inplace[5:40, 3:50], boost(x[5:40, 3:50]))
    np.testing.assert_array_equal(inplace[:5], x[:5])
    canvas = planar.copy()  # a planar canvas's frame (rows apart by the canvas's width), in place
    frame = canvas[:, 5:40, 3:50]
    assert boost(frame, axis=0, out=frame) is frame
    np.testing.assert_array_equal(frame, boost(planar[:, 5:40, 3:50], axis=0))
    assert unboost(frame, axis=0, out=frame) is frame
    np.testing.assert_allclose(canvas, planar, rtol=3e-7, atol=1e-9)
    np.testing.assert_array_equal(canvas[:, :5], planar[:, :5])
    strided = x.copy()[::2, ::3]  # rows not a whole number of columns apart: index tuples
    odd = x.copy()
    odd[10, 10] = (0.95, np.nan, 0.1)  # a NaN makes the max NaN: the pixel is left alone, any layout
    for a, kw in ((odd, {}), (np.ascontiguousarray(odd.transpose(2, 0, 1)), {"axis": 0})):
        b = boost(a, **kw)
        got = b[10, 10] if a is odd else b[:, 10, 10]
        np.testing.assert_array_equal(got, odd[10, 10])
    np.testing.assert_array_equal(boost(strided, out=strided), boost(x[::2, ::3]))
    np.testing.assert_allclose(boost(np.float32([1.0, 0.5, 0.2])), [5.0, 2.5, 1.0], rtol=1e-6)
    with pytest.raises(ValueError, match="threshold"):
        boost(x, threshold=1.0)


def test_an_in_focus_plane_of_near_white_texture_comes_back_as_it_was():
    """In focus (CoC 0), a cutout of near-white texture over a blurred background: inside it
    the target is the all-in-focus image bit for bit, because both are unboost(boosted
    composite); the boost shows only where the blur reaches."""
    g = rng(3)
    h, w = 80, 96
    bg = Plane(g.random((h, w, 3), dtype=np.float32) * 0.3, np.ones((h, w), np.float32), 0.1)
    white = srgb_to_linear(0.85 + 0.15 * g.random((h, w, 3), dtype=np.float32))
    a = np.zeros((h, w), np.float32)
    a[20:60, 25:75] = 1.0
    fg = Plane(white, a, 0.8)
    hl = {"threshold": 0.9, "gain": 4.0, "power": 2.0}
    planes = [Plane(boost(p.rgb, **hl), p.alpha, p.disparity) for p in (bg, fg)]
    target = unboost(render_planes(planes, 0.8, 12.0), **hl)
    still = unboost(render_planes(planes, 0.8, 0.0), **hl)
    inside = (slice(20, 60), slice(25, 75))
    np.testing.assert_array_equal(target[inside], still[inside])
    np.testing.assert_allclose(still[inside], white[inside], rtol=3e-7)  # and that is the texture itself


def test_a_point_highlight_becomes_a_visible_disc_of_the_aperture():
    """A single white pixel on a dark background, defocused through a hexagon: a disc of the
    kernel's shape, 1 + gain times brighter than without the boost (below T it is not mapped
    back), over the same dark background."""
    h = w = 41
    img = np.full((h, w, 3), 0.01, np.float32)
    img[20, 20] = 1.0
    ap = Polygon(6, 15.0)
    hl = {"threshold": 0.9, "gain": 4.0, "power": 2.0}
    boosted = unboost(render_planes([Plane(boost(img, **hl), np.ones((h, w), np.float32), 0.5)], 0.0, 8.0, ap), **hl)
    plain = render_planes([Plane(img, np.ones((h, w), np.float32), 0.5)], 0.0, 8.0, ap)
    k = kernel(ap, 4.0)
    s = k.shape[0] // 2
    disc = np.zeros((h, w), bool)
    disc[20 - s:21 + s, 20 - s:21 + s] = k > 0.5 * k.max()
    assert disc.sum() > 30
    lift = (boosted - 0.01)[disc].mean() / (plain - 0.01)[disc].mean()
    assert abs(lift - 5.0) < 0.05, lift
    assert linear_to_srgb8(boosted[disc]).min() > 2 * linear_to_srgb8(np.float32(0.01))  # plainly visible
    ring = np.zeros((h, w), bool)
    ring[20 - s - 3:23 + s, 20 - s - 3:23 + s] = True
    np.testing.assert_allclose(boosted[~ring], 0.01, atol=1e-6)  # nothing spills beyond the disc
