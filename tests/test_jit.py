"""The compiled per-pixel passes (dofsynth.jit) give the numpy references' bytes: the highlight
boost and its inverse on adversarial values in every layout, a cutout's un-premultiplying, whole
samples with them off and on; and the switch's own contract. (The sRGB encode is tested both
ways in tests/test_color.py.)"""
from __future__ import annotations

import numpy as np
import pytest

from dofsynth import jit
from dofsynth.render.highlight import _tables, boost, unboost


def both(fn):
    """fn() with the numpy passes, then with the compiled kernels (this process's setting
    restored after)."""
    was = jit.enabled()
    try:
        jit.disable()
        ref = fn()
        assert jit.enable()
        return ref, fn()
    finally:
        jit.enable() if was else jit.disable()


def bits(a):
    return np.asarray(a, np.float32).view(np.uint32)  # NaN == NaN, -0 != +0


def adversarial(params, seed=0):
    """(H, W, 3) float32 maxima on, just by and between everything the passes test: the float32
    threshold lo and T, every knot of m (the boost) and of h = m g(m) (its inverse), 1, h's end,
    beyond it; zeros, negatives, infinities and NaNs; the other channels at random below."""
    tb = _tables(*params)
    lo = np.float32(tb.t * (1 - 1e-6))
    marks = np.concatenate([[lo, tb.t, 1.0, tb.h[-1], 2 * tb.h[-1], 0.0], tb.m, tb.h]).astype(np.float32)
    near = np.concatenate([marks, np.nextafter(marks, np.float32(-np.inf)), np.nextafter(marks, np.float32(np.inf))])
    g = np.random.default_rng(seed)
    spread = g.uniform(tb.t * 0.99, tb.h[-1] * 1.01, 20_000).astype(np.float32)
    mx = np.concatenate([near, spread, np.float32([np.inf, -np.inf, np.nan, -1.0, 1e-30])])
    n = mx.size - mx.size % 64
    x = g.random((n, 3), dtype=np.float32) * mx[:n, None]
    x[np.arange(n), g.integers(0, 3, n)] = mx[:n]  # each pixel's max in a random channel
    x[:50, 1] = np.nan  # a NaN beside a bright value
    return x.reshape(64, -1, 3)


@pytest.mark.parametrize("params", [(0.9, 4.0, 2.0), (0.5, 20.0, 0.7), (0.99, 1.0, 6.0), (0.0, 3.0, 1.0)])
def test_compiled_boost_and_inverse_are_the_numpy_bytes_in_every_layout(params):
    x = adversarial(params)
    boosted = boost(x, *params)
    layouts = {
        "interleaved": (x, {}),
        "planar": (np.ascontiguousarray(x.transpose(2, 0, 1)), {"axis": 0}),
        "frame of a canvas": (np.pad(x.transpose(2, 0, 1), ((0, 0), (3, 3), (5, 5)))[:, 3:-3, 5:-5], {"axis": 0}),
        "strided": (x[::2, ::3], {}),
        "pixels": (x.reshape(-1, 3), {}),
        "one pixel": (x[0, 0], {}),
        "boosted, interleaved": (boosted, {}),
        "boosted, planar": (np.ascontiguousarray(boosted.transpose(2, 0, 1)), {"axis": 0}),
    }
    for name, (a, kw) in layouts.items():
        for fn in (boost, unboost):
            ref, got = both(lambda: fn(a, *params, **kw))
            assert np.array_equal(bits(ref), bits(got)), (name, fn.__name__)

            def in_place():  # out= a view: written where it lies, nothing else touched
                canvas = np.pad(a, [(1, 1)] * a.ndim, constant_values=7.0)
                view = canvas[(slice(1, -1),) * a.ndim]
                assert fn(view, *params, out=view, **kw) is view
                return canvas
            ref, got = both(in_place)
            assert np.array_equal(bits(ref), bits(got)), (name, fn.__name__, "in place")


def test_compiled_unpremultiply_is_the_numpy_bytes():
    from dofsynth.assets.placement import ObjectParams
    from dofsynth.compose import place_premultiplied

    g = np.random.default_rng(3)
    premul = g.random((40, 50, 4), dtype=np.float32) * 2  # alpha up to 2 (a resampled extent's overshoot)
    a = premul[..., 3].reshape(-1)
    near = np.float32([0, 1e-6, 1, 1e-30, np.nan, np.inf])
    a[: 3 * near.size] = np.concatenate([near, np.nextafter(near, np.float32(-1)), np.nextafter(near, np.float32(2))])
    for x, y, flip in ((5, 7, False), (-9, -4, True), (30, 20, False)):  # inside, cut by the frame, partly outside
        params = ObjectParams(disparity=0.8, scale=1.0, x=x, y=y, flip=flip)
        ref, got = both(lambda: place_premultiplied(premul, (50, 40), params, 60, 70))
        for r, o in zip(ref, got):
            assert np.array_equal(bits(r), bits(o)), (x, y)


def test_samples_are_the_same_bytes_with_the_compiled_passes(smoke_recipe, smoke_library, demo_recipe):
    from dofsynth.assets import build_library
    from dofsynth.generate import render_one

    # the demo recipe: highlight boost, ramps, the default method
    for recipe, library in ((smoke_recipe, smoke_library), (demo_recipe, build_library(demo_recipe))):
        for i in range(3):
            ref, got = both(lambda: render_one(recipe, library, "train", i))
            assert ref == got, (recipe.name, i)


def test_a_numba_that_cannot_compile_leaves_the_numpy_passes_with_a_warning(monkeypatch, capsys):
    import numba

    from dofsynth.color import _SRGB8, linear_to_srgb8

    was = jit.enabled()
    try:
        jit.disable()
        monkeypatch.setattr(_SRGB8, "_compiled", None)

        def broken(*a, **k):
            raise RuntimeError("no LLVM target here")
        monkeypatch.setattr(numba, "njit", broken)
        assert jit.enable() is False and not jit.enabled()
        assert "compiled per-pixel passes unavailable (RuntimeError: no LLVM target here)" in capsys.readouterr().err
        assert linear_to_srgb8(np.float32([0.5]))[0] == 188  # the numpy pass still runs
    finally:
        monkeypatch.undo()
        jit.enable() if was else jit.disable()


def test_the_switch(monkeypatch):
    was = jit.enabled()
    try:
        monkeypatch.setenv(jit.ENV, "0")
        assert jit.enable() is False and not jit.enabled()
        monkeypatch.setenv(jit.ENV, "yes")
        with pytest.raises(ValueError, match="DOFSYNTH_JIT='yes'"):
            jit.enable()
        monkeypatch.setenv(jit.ENV, "1")
        jit._STATE["on"] = None  # a fresh process: DOFSYNTH_JIT=1 turns them on without enable()
        assert jit.enabled()
        monkeypatch.delenv(jit.ENV)
        jit._STATE["on"] = None  # a fresh process by default: off until enable()
        assert not jit.enabled() and jit.enable() and jit.enabled()
    finally:
        jit.enable() if was else jit.disable()
