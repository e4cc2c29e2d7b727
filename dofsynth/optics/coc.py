"""The circle of confusion: the one place its formula is written."""
from __future__ import annotations

import numpy as np

# No lens blurs a point over more than the picture: max_coc (px) is at most this many times the
# image's long side (px). Recipes and render_planes refuse more (its kernel would not fit in memory).
MAX_COC_PER_SIDE = 2


def coc_radius(disparity, focus: float, max_coc: float):
    """Signed circle-of-confusion radius in pixels, `c = max_coc * (disparity - focus)`:
    positive in front of the focal plane, 0 on it; `max_coc` is the radius at |disparity -
    focus| = 1, in pixels at the resolution being rendered.

    A scalar disparity gives a Python float (float64 arithmetic); an array (numpy or torch)
    gives an array of its own dtype (float32 maps stay float32: the renderer's precision)."""
    if np.ndim(disparity) == 0:
        return float(max_coc) * (float(disparity) - float(focus))
    if isinstance(disparity, np.ndarray):  # keep its dtype whatever the scalars' types
        t = disparity.dtype.type
        return t(max_coc) * (disparity - t(focus))
    return max_coc * (disparity - focus)
