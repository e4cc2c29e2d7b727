"""The CoC levels of a varying-disparity plane (the layered renderer's normalized scatter): one
grid fixed in CoC radius (px), shared by every plane of every sample, and each pixel's linear
weights between its two neighbouring levels (docs/rendering.md)."""
from __future__ import annotations

import numpy as np

_GRIDS: dict[tuple[float, float], np.ndarray] = {}  # (level_step, level_ratio) -> its levels >= 0 so far


def _positive_levels(level_step: float, level_ratio: float, reach: float) -> np.ndarray:
    """The grid's levels >= 0 (px), from 0 to the first one >= reach: g_0 = 0 and
    g_{k+1} = g_k + max(level_step, level_ratio * g_k); computed once per spacing and extended
    as larger radii come (the same float values every time)."""
    key = (float(level_step), float(level_ratio))
    grid = _GRIDS.get(key)
    if grid is None or grid[-1] < reach:
        levels = [0.0] if grid is None else grid.tolist()
        while levels[-1] < reach:
            c = levels[-1]
            levels.append(c + max(level_step, level_ratio * c))
        grid = _GRIDS[key] = np.array(levels)
    return grid


def level_grid(cmin: float, cmax: float, level_step: float, level_ratio: float = 0.0) -> np.ndarray:
    """CoC levels (pixels) covering [c_min, c_max], taken from one grid that every plane of every
    sample shares (so each level's kernels are computed once per process and cached): 0 and
    +-g_k, g_{k+1} = g_k + max(level_step, level_ratio * g_k), from the last level <= c_min to
    the first >= c_max. With level_ratio 0 the step is fixed; above 0 it grows with the radius,
    where neighbouring kernels differ relatively less. A constant map (c_min = c_max) is the one
    level c_min itself."""
    if cmax <= cmin:
        return np.array([float(cmin)])
    pos = _positive_levels(level_step, level_ratio, max(abs(cmin), abs(cmax)))
    grid = np.concatenate([-pos[:0:-1], pos])
    lo = int(np.searchsorted(grid, cmin, side="right")) - 1  # the last level <= c_min
    hi = int(np.searchsorted(grid, cmax, side="left"))  # the first level >= c_max
    return grid[lo : hi + 1]


_CHUNK = 1 << 16  # pixels per block of `level_weights`


def level_weights(cmap: np.ndarray, level_step: float, level_ratio: float = 0.0):
    """CoC levels (pixels, `level_grid`) covering [c_min, c_max], and for each pixel its lower
    level index k0 and the weight f of level k0+1 (1 - f goes to level k0), linear in the
    pixel's CoC between the two levels.

    The levels lie on a grid fixed in CoC, so the result is continuous in focus, max_coc and
    the map (a level enters or leaves with weight 0) except where a map becomes constant: that
    is a single level, the constant-plane result, which a map varying by a hair differs from by
    the interpolation between its two grid levels (docs/rendering.md bounds it).
    """
    cmin, cmax = float(cmap.min()), float(cmap.max())
    levels = level_grid(cmin, cmax, level_step, level_ratio)
    if levels.size == 1:
        return levels, np.zeros(cmap.shape, np.int32), np.zeros(cmap.shape, np.float32)
    k0, f = np.empty(cmap.shape, np.int32), np.empty(cmap.shape, np.float32)
    lower, gaps = levels[:-1], np.diff(levels)
    flat_map, flat_k0, flat_f = cmap.reshape(-1), k0.reshape(-1), f.reshape(-1)
    for a in range(0, flat_map.size, _CHUNK):  # in blocks: the float64 temporaries stay in cache
        c = flat_map[a : a + _CHUNK].astype(np.float64)
        k = np.searchsorted(levels, c, side="right")
        k -= 1
        np.clip(k, 0, levels.size - 2, out=k)
        # f = (c - levels[k]) / (levels[k + 1] - levels[k]), in place, one gather per table
        c -= lower.take(k)
        c /= gaps.take(k)
        np.clip(c, 0.0, 1.0, out=c)
        flat_k0[a : a + c.size] = k
        flat_f[a : a + c.size] = c
    return levels, k0, f


def level_weight(k0: np.ndarray, f: np.ndarray, k: int) -> np.ndarray:
    """Level k's linear weight of pixels with lower level index k0 and fraction f (float32):
    1 - f where k0 = k, f where k0 = k - 1, else 0."""
    w = np.zeros(k0.shape, np.float32)
    np.subtract(np.float32(1.0), f, out=w, where=k0 == k)
    np.copyto(w, f, where=k0 == k - 1)
    return w
