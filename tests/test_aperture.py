"""Aperture kernels: area, symmetry, continuity in the radius, identity at zero radius, the
pixel-tent integral against a brute-force reference."""
import json
import math

import numpy as np
import pytest

from pathlib import Path

from dofsynth.config import ConfigError
from dofsynth.optics import APERTURES, Disk, Polygon, aperture_from_dict, coverage, kernel, parse_aperture, support_radius
from dofsynth.optics.aperture import Aperture
from dofsynth.recipe import ApertureRules

ROOT = Path(__file__).resolve().parents[1]


def embed(k, n):
    out = np.zeros((n, n))
    s = (n - k.shape[0]) // 2
    out[s : s + k.shape[0], s : s + k.shape[1]] = k
    return out


@pytest.mark.parametrize("r", [0.7, 1.5, 2.3, 5.0, 9.6])
def test_disk_area_and_brute_force(r, brute_coverage):
    cov = coverage(Disk(), r)
    assert cov.sum() == pytest.approx(math.pi * r * r, rel=5e-4)
    assert np.abs(cov - brute_coverage(Disk(), r)).max() < 8e-3  # 64x64 point sampling error


@pytest.mark.parametrize("blades,rotation", [(3, 0.0), (5, 17.0), (6, 0.0), (8, 11.0)])
def test_polygon_area_and_brute_force(blades, rotation, brute_coverage):
    ap, r = Polygon(blades, rotation), 6.3
    cov = coverage(ap, r)
    assert cov.sum() == pytest.approx(0.5 * blades * r * r * math.sin(2 * math.pi / blades), rel=2e-4)
    assert cov.sum() == pytest.approx(ap.area(r), rel=2e-4)
    assert np.abs(cov - brute_coverage(ap, r)).max() < 8e-3


@pytest.mark.parametrize("ap", [Disk(), Polygon(5, 17.0), Polygon(6), Polygon(3, 90.0)])
def test_coverage_is_the_midpoint_rule_summed_directly(ap):
    """coverage() sums the clipped chords with cumulative sums over the pixel edges; the same
    midpoint rule written out per (row, sub-column) gives the same areas."""
    from dofsynth.optics.kernel import X_SUBSAMPLES

    for r in [0.5, 0.7, 1.49, 2.3, 5.5, 12.25, 31.9, 64.0, 129.3]:
        s = math.ceil(r - 0.5)   # coverage's array: the pixels the shape touches
        n = 2 * s + 1
        xmin, xmax = ap.x_extent(r)
        cells = np.clip(np.arange(n * X_SUBSAMPLES + 1) / X_SUBSAMPLES - s - 0.5, xmin, xmax)
        lo, hi = ap.chord(0.5 * (cells[1:] + cells[:-1]), r)
        edges = np.arange(n) - s - 0.5
        seg = np.maximum(np.minimum(hi[None, :], edges[:, None] + 1.0) - np.maximum(lo[None, :], edges[:, None]), 0.0)
        want = (seg * np.diff(cells)).reshape(n, n, X_SUBSAMPLES).sum(axis=2)
        np.testing.assert_allclose(coverage(ap, r), want, rtol=0, atol=1e-11 * max(r, 1.0) ** 2)


def test_polygon_symmetry():
    r = 7.2
    # N-fold: turning the polygon by 360/N degrees gives the same shape.
    for n in (5, 6, 7):
        a, b = kernel(Polygon(n, 10.0), r), kernel(Polygon(n, 10.0 + 360.0 / n), r)
        np.testing.assert_allclose(a, b, atol=1e-6)
    # Where the grid allows it, the kernel itself has the symmetry.
    for n, rot in ((4, 45.0), (4, 0.0), (8, 22.5)):
        k = kernel(Polygon(n, rot), r)
        np.testing.assert_allclose(np.rot90(k), k, atol=1e-4)  # x midpoint rule
    k6 = kernel(Polygon(6, 0.0), r)
    np.testing.assert_allclose(k6[::-1, ::-1], k6, atol=1e-6)
    # The inertia of a regular polygon is isotropic (any N >= 3).
    k5 = kernel(Polygon(5, 13.0), 12.0).astype(np.float64)
    s = k5.shape[0] // 2
    y, x = np.mgrid[-s : s + 1, -s : s + 1]
    assert (k5 * x * x).sum() == pytest.approx((k5 * y * y).sum(), rel=5e-3)
    assert abs((k5 * x * y).sum()) < 5e-3 * (k5 * x * x).sum()
    # A triangle is not centrally symmetric, so the sign of the radius matters.
    k3 = kernel(Polygon(3), 5.0)
    assert np.abs(k3 - k3[::-1, ::-1]).max() > 0.01


@pytest.mark.parametrize("ap", [Disk(), Polygon(3), Polygon(5, 30.0)])
def test_negative_radius_is_point_reflection(ap):
    for r in (0.8, 3.3, 6.0):
        np.testing.assert_array_equal(kernel(ap, -r), kernel(ap, r)[::-1, ::-1])


@pytest.mark.parametrize("ap", [Disk(), Polygon(6, 5.0)])
def test_normalized_identity_at_zero_and_growing_from_it(ap):
    np.testing.assert_array_equal(kernel(ap, 0.0), np.ones((1, 1), np.float32))
    centre = [embed(kernel(ap, r), 3)[1, 1] for r in (1e-4, 0.1, 0.2, 0.3, 0.45)]
    assert centre[0] > 0.9999 and all(a > b for a, b in zip(centre, centre[1:]))  # blur starts at once
    for r in (0.2, -0.3, 0.6, 2.0, 3.0, 10.4):
        k = kernel(ap, r)
        assert k.dtype == np.float32 and k.sum() == pytest.approx(1.0, abs=1e-5)
        assert k.shape == (2 * support_radius(r) + 1,) * 2


@pytest.mark.parametrize("ap,r", [(Disk(), 0.3), (Disk(), 1.7), (Disk(), 4.2), (Polygon(5, 17.0), 3.6)])
def test_kernel_is_the_shape_integrated_against_the_pixel_tent(ap, r, brute_tent):
    from dofsynth.optics.kernel import tent_weights

    w = tent_weights(ap, r)
    assert w.sum() == pytest.approx(ap.area(r), rel=5e-4)
    np.testing.assert_allclose(w, brute_tent(ap, r), atol=3e-3 * max(r, 1.0))


@pytest.mark.parametrize("ap,r", [(Disk(), 0.4), (Disk(), 3.3), (Polygon(5, 17.0), -4.6)])
def test_kernel_moments_are_the_aperture_coordinate_under_the_pixel_tent(ap, r):
    """kernel_moments: each pixel carries the mean aperture point p = (x, y) / |r| of the light
    landing there, tent-weighted like the kernel: against point samples of the shape, each
    point's p shared among pixels by the tent. They sum to the centroid (0 for these shapes,
    the cell's for a part of a disc)."""
    from dofsynth.optics.kernel import kernel_moments
    from dofsynth.render.subaperture import Cell

    for shape in (ap, Cell(ap, 0.0, 1.0, -1.0, -0.2)):
        s, a = math.ceil(abs(r)), abs(r)
        sub = 96 if a > 2 else 480   # points per pixel: enough across a small shape
        t = (np.arange(2 * s * sub) + 0.5) / sub - s
        yy, xx = np.meshgrid(t, t, indexing="ij")
        inside = shape.contains(xx / a, yy / a).astype(np.float64)
        offs = np.arange(-s, s + 1)[:, None]
        tent = np.maximum(0.0, 1.0 - np.abs(offs - t[None, :]))
        total = (tent @ inside @ tent.T).sum()
        want_x, want_y = tent @ (inside * xx / a) @ tent.T / total, tent @ (inside * yy / a) @ tent.T / total
        if r < 0:  # the kernel's point reflection: the same aperture points on mirrored pixels
            want_x, want_y = want_x[::-1, ::-1], want_y[::-1, ::-1]
        mx, my = kernel_moments(shape, r)
        assert mx.shape == kernel(shape, r).shape and mx.dtype == np.float32
        np.testing.assert_allclose(mx, want_x, atol=2e-3)
        np.testing.assert_allclose(my, want_y, atol=2e-3)
        cx, cy = (float(np.sum(inside * v / a) / inside.sum()) for v in (xx, yy))
        assert float(mx.sum()) == pytest.approx(cx, abs=2e-3) and float(my.sum()) == pytest.approx(cy, abs=2e-3)
    np.testing.assert_array_equal(kernel_moments(ap, 0.0)[0].shape, (1, 1))


@pytest.mark.parametrize("ap", [Disk(), Polygon(5, 12.0)])
def test_kernel_continuous_in_radius(ap):
    """No jump at integer or half-integer radii: tiny radius steps make tiny kernel changes."""
    for lo, hi in ((0.45, 0.55), (1.45, 1.55), (2.9, 3.1), (3.45, 3.55)):
        rs = np.linspace(lo, hi, 101)
        n = 2 * support_radius(hi) + 1
        ks = [embed(kernel(ap, float(r)), n) for r in rs]
        steps = [np.abs(b - a).max() for a, b in zip(ks, ks[1:])]
        # Each step is 1/1000 of a pixel; the largest kernel change must be of that order.
        assert max(steps) < 5e-3, (lo, hi, max(steps))


def test_the_registry_is_what_recipes_records_and_the_command_line_accept(tmp_path):
    """A kind is one class: a square registered here is taken by the recipe key, drawn into a
    scene's record and read back, parsed from the command line and rendered."""
    from dataclasses import dataclass
    from typing import ClassVar

    from dofsynth.assets import build_library
    from dofsynth.optics.aperture import register
    from dofsynth.recipe import recipe_from_text
    from dofsynth.scene import Scene, sample_scene

    @register
    @dataclass(frozen=True)
    class Square(Aperture):
        kind: ClassVar[str] = "toy_square"

        def chord(self, x, r):
            inside = np.abs(x) <= r
            return np.where(inside, -r, 0.0), np.where(inside, r, 0.0)

        def x_extent(self, r):
            return -r, r

        def area(self, radius):
            return 4.0 * float(radius) ** 2

        def contains(self, x, y):
            return (np.abs(x) <= 1.0) & (np.abs(y) <= 1.0)

    try:
        text = (ROOT / "recipes" / "smoke.toml").read_text().replace('kind = "disk"', 'kind = "toy_square"')
        recipe = recipe_from_text(text, tmp_path / "sq.toml", tmp_path)
        scene = sample_scene(recipe, build_library(recipe), "train", 0)
        assert scene.aperture == Square() and Scene.from_dict(scene.to_dict()).aperture == Square()
        assert parse_aperture("toy_square") == aperture_from_dict({"kind": "toy_square"}) == Square()
        k = kernel(Square(), 3.0)
        assert abs(k.sum() - 1.0) < 1e-5 and k[k.shape[0] // 2, 0] > 0  # a square fills its corners' rows
        bad = text.replace('kind = "toy_square"', 'kind = "nope"')
        with pytest.raises(ConfigError, match="render.aperture.kind"):
            recipe_from_text(bad, tmp_path / "bad.toml", tmp_path)
    finally:
        del APERTURES["toy_square"]
    for kind, cls in APERTURES.items():
        assert parse_aperture(kind if kind == "disk" else f"{kind}:6") == aperture_from_dict({"kind": kind})
        assert cls.from_rules(ApertureRules(kind=kind, rotation=(10.0, 10.0)), None).kind == kind


def test_dict_round_trip_and_parsing():
    for ap in (Disk(), Polygon(6), Polygon(7, 12.5)):
        d = json.loads(json.dumps(ap.to_dict()))
        assert aperture_from_dict(d) == ap
    assert Disk().to_dict() == {"kind": "disk"}
    assert Polygon(6).to_dict() == {"kind": "polygon", "blades": 6, "rotation": 0.0}
    assert parse_aperture("disk") == Disk()
    assert parse_aperture("polygon:5:30") == Polygon(5, 30.0)
    for bad in ({"kind": "star"}, "disk", {}):
        with pytest.raises(ValueError, match="aperture"):
            aperture_from_dict(bad)
    for bad in ("hexagon", "polygon:2", "polygon:x"):
        with pytest.raises(ValueError, match="aperture"):
            parse_aperture(bad)
    with pytest.raises(ValueError, match="blades"):
        Polygon(2)
    with pytest.raises(ValueError, match="signed_radius"):
        kernel(Disk(), float("nan"))
