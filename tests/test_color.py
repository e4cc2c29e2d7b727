"""Colour conversions: the table-driven sRGB encode/decode against the analytic formula (with the
numpy passes and the compiled kernels, dofsynth.jit), and the highlight boost's fast paths (in
place, on views) against its plain formula."""
import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dofsynth.color import (SRGB8_THRESHOLDS, SRGB8_TO_LINEAR, linear_to_srgb, linear_to_srgb8,
                            srgb8_to_linear, srgb_to_linear)
from dofsynth.image import to_uint8


def srgb_encode64(x):
    x = np.clip(np.asarray(x, np.float64), 0.0, 1.0)
    return np.where(x <= 0.0031308, x * 12.92, 1.055 * x ** (1 / 2.4) - 0.055)


def analytic_codes(x):
    """Round-half-up 8-bit codes of the float64 sRGB formula (NaN taken as 0)."""
    x = np.nan_to_num(np.asarray(x, np.float32).astype(np.float64), nan=0.0, posinf=1.0, neginf=0.0)
    return np.floor(srgb_encode64(x) * 255.0 + 0.5).astype(np.uint8)


def test_encode_table_equals_the_analytic_formula(passes):
    g = np.random.default_rng(np.random.SeedSequence(11))
    x = np.concatenate([g.random(400_000, dtype=np.float32),                  # all of [0, 1)
                        g.random(100_000, dtype=np.float32) * 0.01,           # the linear toe
                        np.float32([0, 1, 1e-30, 0.0031308, 0.5, -1, 2, np.inf, -np.inf, np.nan])])
    np.testing.assert_array_equal(linear_to_srgb8(x), analytic_codes(x))
    img = x[: 3 * 40_000].reshape(200, 200, 3)
    np.testing.assert_array_equal(linear_to_srgb8(img[:, ::-1]), analytic_codes(img[:, ::-1]))  # views too
    # The old float32 path differs only by float32 rounding right at a few thresholds.
    old = to_uint8(linear_to_srgb(x[:400_000]))
    diff = np.abs(old.astype(int) - linear_to_srgb8(x[:400_000]).astype(int))
    assert diff.max() <= 1 and np.count_nonzero(diff) < 20


def test_encode_thresholds_are_exact_and_codes_monotone(passes):
    t = SRGB8_THRESHOLDS
    assert t.dtype == np.float32 and np.all(np.diff(t) > 0)
    below = np.nextafter(t, np.float32(-1))
    np.testing.assert_array_equal(linear_to_srgb8(t), np.arange(1, 256))      # code k+1 starts at T_k
    np.testing.assert_array_equal(linear_to_srgb8(below), np.arange(0, 255))   # and not one float earlier
    assert np.all(srgb_encode64(t) * 255 + 0.5 >= np.arange(1, 256))
    assert np.all(srgb_encode64(below) * 255 + 0.5 < np.arange(1, 256))
    dense = np.linspace(-0.1, 1.1, 2_000_001, dtype=np.float32)
    assert np.all(np.diff(linear_to_srgb8(dense).astype(int)) >= 0)
    # the first and last float32 of every group sharing their top 16 bits (the table's bins):
    # every sign, exponent, NaN and infinity
    top = np.arange(1 << 16, dtype=np.uint32) << 16
    edges = np.concatenate([top, top | 0xFFFF]).view(np.float32)
    np.testing.assert_array_equal(linear_to_srgb8(edges), analytic_codes(edges))


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.lists(st.floats(width=32, allow_nan=True, allow_infinity=True), min_size=1, max_size=50))
def test_encode_matches_the_formula_for_any_float32(passes, values):
    x = np.array(values, np.float32)
    np.testing.assert_array_equal(linear_to_srgb8(x), analytic_codes(x))


def test_decode_table_is_the_formula_and_inverts_the_encode():
    codes = np.arange(256, dtype=np.uint8)
    s = codes / 255.0
    exact = np.where(s <= 0.04045, s / 12.92, ((s + 0.055) / 1.055) ** 2.4)
    np.testing.assert_allclose(SRGB8_TO_LINEAR, exact, rtol=1e-7, atol=0)  # float32 rounding only
    np.testing.assert_allclose(srgb8_to_linear(codes), srgb_to_linear(s), rtol=2e-6, atol=1e-9)
    assert np.all(np.diff(SRGB8_TO_LINEAR) > 0)
    np.testing.assert_array_equal(linear_to_srgb8(srgb8_to_linear(codes)), codes)  # 8 bit round trip
    img = np.random.default_rng(3).integers(0, 256, (5, 7, 3), dtype=np.uint8)
    assert srgb8_to_linear(img).dtype == np.float32 and srgb8_to_linear(img).shape == (5, 7, 3)
