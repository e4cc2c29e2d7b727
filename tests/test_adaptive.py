"""The adaptive method (dofsynth.render.adaptive): the layered render, with sub-aperture cells
only in the tiles where the layered method errs."""
import cv2
import numpy as np
import pytest

from dofsynth.optics import Disk, Polygon
from dofsynth.render import RenderOptions, render_planes
from dofsynth.render.adaptive import TILE, error_scores, need_map, rectangles
from dofsynth.render.planes import Plane
from dofsynth.render.subaperture import cells, cut_planes, render_cells

N = 160


def _scene(n=N, seed=3):
    """A background of random 8 px blocks (disparity 0.1) behind a soft disc (0.6) and a
    hard-edged bar cut by the frame's bottom edge (0.9)."""
    g = np.random.default_rng(seed)
    bg = cv2.resize(g.random((n // 8, n // 8, 3)).astype(np.float32), (n, n), interpolation=cv2.INTER_NEAREST)
    yy, xx = np.mgrid[0:n, 0:n]
    disc = np.clip(n * 0.25 - np.hypot(yy - n * 0.45, xx - n * 0.4), 0, 1).astype(np.float32)
    bar = np.zeros((n, n), np.float32)
    bar[n // 2 :, n // 2 : n // 2 + n // 5] = 1.0
    colour = lambda c: np.zeros((n, n, 3), np.float32) + np.float32(c)  # noqa: E731
    return [Plane(bg, np.ones((n, n), np.float32), 0.1), Plane(colour([0.9, 0.3, 0.1]), disc, 0.6),
            Plane(colour([0.1, 0.7, 0.9]), bar, 0.9)]


def _psnr(a, b):
    return 10 * np.log10(1.0 / float(np.mean((a - b) ** 2)))


@pytest.mark.parametrize("focus", [0.35, 1.0])
def test_adaptive_is_as_close_to_the_exact_mode_as_the_subaperture_method(focus):
    """Where blurred edges overlap a blurred textured background the layered method misses by
    40-43 dB; the adaptive render reaches the 2 x 2 sub-aperture render's accuracy (55-61 dB
    measured) and stays above 50 dB."""
    planes = _scene()
    exact = render_planes(planes, focus, 12.0, Disk(), method="exact")
    layered = _psnr(render_planes(planes, focus, 12.0, Disk()), exact)
    adaptive = _psnr(render_planes(planes, focus, 12.0, Disk(), method="adaptive"), exact)
    cells = _psnr(render_planes(planes, focus, 12.0, Disk(), method="subaperture", cells=2), exact)
    assert layered < 45.0 and adaptive > 50.0 and adaptive > cells - 1.0, (layered, adaptive, cells)


def test_adaptive_keeps_the_layered_bytes_where_the_layered_method_is_exact():
    """Where no blurred cutout edge lies over a blurred plane with another CoC, the layered
    method is exact and the adaptive render is it, byte for byte: the background in focus, the
    cutouts in focus, one plane, a flat background."""
    planes = _scene()
    flat = Plane(np.full((N, N, 3), 0.4, np.float32), np.ones((N, N), np.float32), 0.1)
    cases = [([planes[0], planes[2]], 0.1), ([planes[0], planes[1]], 0.6), (planes[:1], 0.7), ([flat, planes[2]], 0.3)]
    for scene, focus in cases:
        assert not need_map(scene, focus, 12.0, (0, N, 0, N)).any()
        assert np.array_equal(render_planes(scene, focus, 12.0, Disk(), method="adaptive"),
                              render_planes(scene, focus, 12.0, Disk()))


@pytest.mark.parametrize("aperture", [Disk(), Polygon(6, 15.0)])
def test_adaptive_is_the_sub_aperture_render_in_its_tiles_and_layered_elsewhere(aperture):
    """The contract, pixel by pixel: each pixel is the layered render's, byte for byte, or the
    2 x 2 sub-aperture render's of the whole frame, to float32 rounding; every tile `need_map`
    marks is the latter. The planes cut to a rectangle and its margin give the whole frame's
    pixels there: nothing the cut leaves out reaches them. (The whole frame's render is that of
    the planes going on past the frame, as the renderers extend them, so that its edge pixels
    too take central differences in the composite.)"""
    planes = _scene()
    for focus in (0.35, 1.0):
        out = render_planes(planes, focus, 12.0, aperture, method="adaptive", planar=True)
        layered = render_planes(planes, focus, 12.0, aperture, planar=True)
        need = need_map(planes, focus, 12.0, (0, N, 0, N))
        assert 0 < need.mean() < 1
        per_pixel = np.kron(need, np.ones((TILE, TILE), bool))[:N, :N]
        p = 15  # past every kernel's reach
        past = cut_planes(planes, -p, N + p, -p, N + p)
        whole = render_cells(past, focus, 12.0, cells(aperture, 2), RenderOptions(), inner=p - 1)[:, p:-p, p:-p]
        err = np.abs(out - whole).max(axis=0)
        same = (out == layered).all(axis=0)
        assert np.all(same | (err < 2e-5)), (focus, err[~same].max())
        assert np.all(err[per_pixel] < 2e-5) and not same.all()


def test_a_blurred_edge_over_a_flat_or_sharp_background_scores_nothing():
    """`error_scores` bounds the covariance of a cutout's alpha and what lies behind it: zero
    where what lies behind is flat or in focus, or the cutout is in focus; above zero along a
    blurred edge over a blurred textured background, and only near that edge."""
    planes = _scene()
    kept = (0, N, 0, N)
    textured = error_scores(planes, 1.0, 12.0, kept)
    assert textured.max() > 0.003
    far = np.zeros_like(textured, bool)
    far[0, -1] = True  # the top right corner tile: 40+ px from both cutouts, whose CoC is at most 10.8 px
    assert textured[far].max() == 0.0
    flat = Plane(np.full((N, N, 3), 0.4, np.float32), np.ones((N, N), np.float32), 0.1)
    assert error_scores([flat, planes[2]], 1.0, 12.0, kept).max() < 1e-6
    assert error_scores([planes[0], planes[2]], 0.1, 12.0, kept).max() == 0.0  # the background in focus
    assert error_scores([planes[0], planes[2]], 0.9, 12.0, kept).max() == 0.0  # the cutout in focus


def test_a_cutouts_colour_outside_its_box_is_never_read():
    """A cutout's `box` promises alpha 0 outside it; its colour there is not read: NaN there
    (in the disc, which lies behind the bar) gives the same render, byte for byte."""
    from dataclasses import replace

    from dofsynth.render.planes import alpha_box

    planes = _scene()
    disc = planes[1]
    y0, y1, x0, x1 = box = alpha_box(disc.alpha)
    nan = np.full((N, N, 3), np.nan, np.float32)
    nan[y0:y1, x0:x1] = np.asarray(disc.rgb)[y0:y1, x0:x1]
    boxed = [planes[0], replace(disc, box=box), planes[2]]
    want = render_planes(boxed, 1.0, 12.0, Disk(), method="adaptive")
    got = render_planes([planes[0], replace(disc, rgb=nan, box=box), planes[2]], 1.0, 12.0, Disk(), method="adaptive")
    assert np.isfinite(got).all() and np.array_equal(got, want)
    assert need_map(boxed, 1.0, 12.0, (0, N, 0, N)).any()


def test_need_map_marks_the_highest_bounds_until_what_is_left_fits_the_budget(monkeypatch):
    """`need_map`: tiles whose bound is below MIN_SCORE stay layered; of the others the highest
    bounds get cells, as few as leave the layered tiles' bounds within ERROR_BUDGET a tile."""
    import dofsynth.render.adaptive as A

    planes, kept = _scene(), (0, N, 0, N)
    scores = error_scores(planes, 1.0, 12.0, kept)
    n, above = scores.size, scores >= A.MIN_SCORE
    assert above.sum() >= 4
    for budget in (0.0, float(np.sort(scores[above])[: above.sum() // 2].sum()) / n):
        monkeypatch.setattr(A, "ERROR_BUDGET", budget)
        need = need_map(planes, 1.0, 12.0, kept)
        left = scores[~need]
        assert not (need & ~above).any() and need.any()
        assert left.sum() <= budget * n * (1 + 1e-9) or not (above & ~need).any()
        assert scores[need].min() >= scores[above & ~need].max(initial=0.0)   # the highest first
        assert left.sum() + scores[need].min() > budget * n                   # no fewer would do
        if budget == 0.0:
            assert np.array_equal(need, above)
        else:
            assert 0 < need.sum() < above.sum()


def test_rectangles_cover_every_marked_tile_and_merge_when_it_pays():
    marked = np.zeros((8, 10), bool)
    marked[1, 1:3] = marked[2, 1:4] = True   # two runs one above the other: one rectangle
    marked[6, 8] = True                       # a lone tile far away: its own
    rects = rectangles(marked, pad=1.0)
    covered = np.zeros_like(marked)
    for y0, y1, x0, x1 in rects:
        covered[y0:y1, x0:x1] = True
    assert np.all(covered[marked])
    assert sorted(rects) == [(1, 3, 1, 4), (6, 7, 8, 9)]
    assert rectangles(np.zeros((3, 3), bool), pad=1.0) == []
    assert rectangles(marked, pad=1.0) == rects  # deterministic


def _greedy_merges(marked, pad, fixed):
    """The rule `rectangles` states, recomputed from scratch at every step: of all pairs of
    the current rectangles (in their order: survivors first, the merged one last) merge the
    first one whose union saves the most, while any saves something."""
    def cost(b):
        return (b[1] - b[0] + 2 * pad) * (b[3] - b[2] + 2 * pad) + fixed

    rects = []
    for r in range(marked.shape[0]):
        c = 0
        while c < marked.shape[1]:
            if marked[r, c]:
                e = c
                while e < marked.shape[1] and marked[r, e]:
                    e += 1
                rects.append((r, r + 1, c, e))
                c = e
            c += 1
    while len(rects) > 1:
        best, pair = None, None
        for i, a in enumerate(rects):
            for j, b in enumerate(rects):
                if i != j:
                    u = (min(a[0], b[0]), max(a[1], b[1]), min(a[2], b[2]), max(a[3], b[3]))
                    s = cost(a) + cost(b) - cost(u)
                    if best is None or s > best:
                        best, pair = s, (i, j, u)
        if best < 0:
            break
        i, j, u = pair
        rects = [r for k, r in enumerate(rects) if k not in (i, j)] + [u]
    return sorted(rects)


def test_rectangles_follow_the_greedy_rule_on_random_maps():
    """`rectangles` keeps its pair savings up to date instead of recomputing them: the same
    rectangles as recomputing every pair at every step, on random maps and margins."""
    g = np.random.default_rng(5)
    for _ in range(60):
        marked = g.random((9, 12)) < g.uniform(0.05, 0.4)
        pad = float(g.choice([0.3, 0.7, 1.0]))
        assert rectangles(marked, pad) == _greedy_merges(marked, pad, 4.0)


def test_batched_cells_equal_cell_by_cell(monkeypatch):
    """Constant-disparity planes whose cell kernels take the FFT are blurred for all cells in
    one batch; above BATCH_MAX they go cell by cell: the same render to float32 rounding (max
    CoC 24: the bar's CoC of 13 px takes the FFT, the others' cells go direct either way)."""
    import dofsynth.render.cellblur as sub

    planes = _scene(96)
    want = render_planes(planes, 0.35, 24.0, Disk(), method="subaperture", cells=2)
    monkeypatch.setattr(sub, "BATCH_MAX", 0)
    got = render_planes(planes, 0.35, 24.0, Disk(), method="subaperture", cells=2)
    np.testing.assert_allclose(got, want, atol=2e-6)
    assert not np.array_equal(got, want)  # the other path did run


def test_adaptive_renders_only_the_kept_frame_with_a_margin():
    """With `margin` (planes past the kept frame) the adaptive render, like the layered one,
    computes the kept part only; there it is the render of the same planes without a margin
    read on the kept part (the margin holds the same content)."""
    planes = _scene()
    m = 16
    kept = render_planes(planes, 1.0, 12.0, Disk(), method="adaptive", margin=m, planar=True)
    assert not kept[:, :m].any() and not kept[:, -m:].any()
    assert np.isfinite(kept).all() and kept[:, m:-m, m:-m].min() > 0.0


@pytest.mark.parametrize("ramp", [False, True])
def test_subaperture_with_a_margin_computes_the_frame_only_and_the_same_pixels(ramp):
    """With `margin` past every kernel's reach, the sub-aperture method computes the frame (and
    its cells' blurs only there), which equals the render of the same planes without a margin
    on it to float32 rounding; the margin stays 0. A flat background, and one whose disparity
    varies along y (farthest in the middle, where both renders anchor their CoC levels)."""
    planes = _scene()
    if ramp:
        d = np.broadcast_to((0.05 + 0.25 * np.abs(np.linspace(-1.0, 1.0, N, dtype=np.float32)))[:, None], (N, N))
        planes[0] = Plane(planes[0].rgb, planes[0].alpha, d)
    m = 16
    kept = render_planes(planes, 0.35, 12.0, Disk(), method="subaperture", cells=2, margin=m, planar=True)
    full = render_planes(planes, 0.35, 12.0, Disk(), method="subaperture", cells=2, planar=True)
    assert not kept[:, :m].any() and not kept[:, -m:].any() and not kept[:, :, :m].any() and not kept[:, :, -m:].any()
    np.testing.assert_allclose(kept[:, m:-m, m:-m], full[:, m:-m, m:-m], atol=2e-6)
