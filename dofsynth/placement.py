"""Where an object goes: its scale, position and flip in the frame (`ObjectParams`), drawn so
that its matte's cut sides lie on the frame's edges, at least `min_in_frame` of its box is in
the frame and no asset is magnified past `assets.max_upscale`; and how much of each object is
seen (`visible_shares`, on uint8 alpha thumbnails in integer arithmetic: the same on every
machine). Used by dofsynth.scene, which draws everything else."""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from dofsynth.assets import Asset
from dofsynth.assets.fit import scale_range
from dofsynth.recipe import Recipe
from dofsynth.rng import draw_uniform

_PLACE_TRIES = 64


@dataclass(frozen=True)
class ObjectParams:
    disparity: float
    scale: float                    # output px per source px
    x: int                          # top-left of the placed extent, output px (may be < 0)
    y: int
    flip: bool                      # horizontal flip of the extent before placing
    anchored: tuple[str, ...] = ()  # frame edges the object is cut at (its matte's cut sides, flipped)
    visible: float = 1.0            # share of its alpha seen in the frame, behind what is in front
    rejected: tuple[str, ...] = ()  # assets drawn for this object first, which no placement could fit


def placed_size(scale: float, extent_w: int, extent_h: int) -> tuple[int, int]:
    """(w, h) in output px of an extent resized by `scale` (the renderer uses exactly this)."""
    return max(1, round(extent_w * scale)), max(1, round(extent_h * scale))


def in_frame_share(x: int, y: int, w: int, h: int, frame_w: int, frame_h: int) -> float:
    vis_w = max(0, min(x + w, frame_w) - max(x, 0))
    vis_h = max(0, min(y + h, frame_h) - max(y, 0))
    return vis_w * vis_h / float(w * h)


_SWAP = {"left": "right", "right": "left", "top": "top", "bottom": "bottom"}
VISIBLE_SIDE = 128  # occlusion is estimated on the frame reduced to this long side (alpha thumbnails)
_OBJECT_TRIES = 8   # assets drawn per object before giving up (an error naming them)


def _axis(size: int, frame: int, m: float, low_cut: bool, high_cut: bool) -> tuple[int, int]:
    """Range of an object's top-left coordinate along one axis: at least m of it inside, its
    cut sides on or beyond the frame's edges."""
    lo, hi = -int((1 - m) * size), frame - int(np.ceil(m * size))
    if low_cut:
        hi = min(hi, 0)
    if high_cut:
        lo = max(lo, frame - size)
    return lo, hi


def _place(rng: np.random.Generator, asset: Asset, disparity: float, recipe: Recipe) -> ObjectParams | None:
    """Draw flip, scale and position of one object; None when no placement can keep its cut
    sides on the frame's edges at the recipe's scales."""
    H, W = recipe.frame
    rules = recipe.scene.foreground
    flip = bool(rng.random() < rules.flip_share)
    anchored = tuple(sorted(_SWAP[c] if flip else c for c in asset.cut))
    lo, hi = scale_range(asset, recipe, anchored)
    if lo > hi:
        return None
    scale = draw_uniform(rng, lo, hi)
    _, _, ew, eh = asset.extent
    w, h = placed_size(scale, ew, eh)
    m = rules.min_in_frame
    (x_lo, x_hi), (y_lo, y_hi) = (_axis(w, W, m, "left" in anchored, "right" in anchored),
                                  _axis(h, H, m, "top" in anchored, "bottom" in anchored))
    if x_lo > x_hi or y_lo > y_hi:
        return None
    for _ in range(_PLACE_TRIES):
        x, y = int(rng.integers(x_lo, x_hi + 1)), int(rng.integers(y_lo, y_hi + 1))
        if in_frame_share(x, y, w, h, W, H) >= m:
            return ObjectParams(disparity=float(disparity), scale=float(scale), x=x, y=y, flip=flip, anchored=anchored)
    return None


def draw_object(rng, pool: list[Asset], disparity: float, recipe: Recipe, exclude=()):
    """(asset, params) of an object: assets drawn from `pool` (not `exclude`) until one can be
    placed; those that could not are listed in `params.rejected`."""
    rejected: list[str] = []
    for attempt in range(_OBJECT_TRIES):
        candidates = [a for a in pool if a.id not in exclude and a.id not in rejected] or pool
        asset = candidates[int(rng.integers(len(candidates)))]
        params = _place(rng, asset, disparity, recipe)
        if params is not None:
            return asset, replace(params, rejected=tuple(rejected))
        rejected.append(asset.id)
    raise ValueError(f"no foreground of the split could be placed with its cut sides on the frame's edges after "
                     f"{_OBJECT_TRIES} draws ({', '.join(rejected)}); widen scene.foreground.scale or raise "
                     "assets.max_upscale")


def _alpha_on_frame(asset: Asset, p: ObjectParams, frame: tuple[int, int]) -> tuple[np.ndarray, int]:
    """(uint8 alpha on the frame reduced to VISIBLE_SIDE, the object's whole alpha mass at that
    scale), from the asset's thumbnail (its bbox when it has none): integer arithmetic only."""
    H, W = frame
    q = VISIBLE_SIDE / max(H, W)
    FH, FW = max(1, round(H * q)), max(1, round(W * q))
    _, _, ew, eh = asset.extent
    w, h = placed_size(p.scale, ew, eh)
    tw, th = max(1, round(w * q)), max(1, round(h * q))
    thumb = asset.thumb if asset.thumb is not None else np.full((1, 1), 255, np.uint8)
    if p.flip:
        thumb = thumb[:, ::-1]
    small = thumb[(np.arange(th) * thumb.shape[0]) // th][:, (np.arange(tw) * thumb.shape[1]) // tw]
    out = np.zeros((FH, FW), np.uint8)
    x0, y0 = round(p.x * q), round(p.y * q)
    cx0, cy0, cx1, cy1 = max(x0, 0), max(y0, 0), min(x0 + tw, FW), min(y0 + th, FH)
    if cx1 > cx0 and cy1 > cy0:
        out[cy0:cy1, cx0:cx1] = small[cy0 - y0:cy1 - y0, cx0 - x0:cx1 - x0]
    return out, int(small.astype(np.int64).sum())


def visible_shares(middle: tuple[Asset, ObjectParams], front: tuple[Asset, ObjectParams],
                   frame: tuple[int, int]) -> tuple[float, float]:
    """(middle, front): the share of each object's alpha seen in the frame, the middle one
    behind the front one (on the frame reduced to VISIBLE_SIDE px)."""
    am, mass_m = _alpha_on_frame(*middle, frame)
    af, mass_f = _alpha_on_frame(*front, frame)
    seen_m = int((am.astype(np.int64) * (255 - af.astype(np.int64))).sum())
    return seen_m / max(255 * mass_m, 1), int(af.astype(np.int64).sum()) / max(mass_f, 1)
