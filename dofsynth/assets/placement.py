"""Placement rules, in one place: what an asset can be at a recipe's frame size and where an
object goes.

- `largest_crop`, `scale_range`, `too_small`: the largest background crop of the frame's aspect
  and the scales a cutout may be placed at, both bounded by `assets.max_upscale`, so that the
  library can refuse (by name) assets too small for the recipe before any scene is drawn;
- `draw_object`: an object's scale, position and flip in the frame (`ObjectParams`), drawn so
  that its matte's cut sides lie on the frame's edges, at least `min_in_frame` of its box is in
  the frame and no asset is magnified past `assets.max_upscale`;
- `visible_shares`: how much of each object is seen (on uint8 alpha thumbnails in integer
  arithmetic: the same on every machine).
dofsynth.scene draws everything else; dofsynth.compose places the pixels with `placed_size`."""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from dofsynth.assets.decode import Asset
from dofsynth.recipe import Recipe
from dofsynth.rng import draw_uniform

_PLACE_TRIES = 64


def largest_crop(size: tuple[int, int], frame: tuple[int, int]) -> tuple[float, float]:
    """(w, h) in source px of the largest crop of a (w, h) photo with the frame's aspect."""
    sw, sh = size
    H, W = frame
    if sw * H > sh * W:  # source wider than the frame aspect
        return sh * W / H, float(sh)
    return float(sw), sw * H / W


def background_upscale(asset: Asset, frame: tuple[int, int]) -> float:
    """How much the largest crop of a background is magnified to fill the frame."""
    return frame[1] / largest_crop(asset.size, frame)[0]


def scale_range(asset: Asset, recipe, anchored=()) -> tuple[float, float]:
    """The scales (output px per source px) an object may be placed at: its long side at
    `scene.foreground.scale` of the frame's short side, no more magnified than
    `assets.max_upscale`, and wide (tall) enough to span the frame when cut on both sides."""
    H, W = recipe.frame
    _, _, ew, eh = asset.extent
    lo, hi = (f * min(H, W) / max(ew, eh) for f in recipe.scene.foreground.scale)
    hi = min(hi, recipe.assets.max_upscale)
    if {"left", "right"} <= set(anchored):
        lo = max(lo, W / ew)
    if {"top", "bottom"} <= set(anchored):
        lo = max(lo, H / eh)
    return lo, hi


def too_small(asset: Asset, recipe) -> str | None:
    """Why `asset` cannot be used at the recipe's frame size, or None."""
    H, W = recipe.frame
    limit = recipe.assets.max_upscale
    if asset.kind == "background":
        up = background_upscale(asset, (H, W))
        if up > limit:
            return (f"too small for {W}x{H} samples: {asset.size[0]}x{asset.size[1]}, its largest crop would be "
                    f"magnified {up:.2f}x (assets.max_upscale = {limit:g})")
        return None
    lo, hi = scale_range(asset, recipe, asset.cut)
    if lo > hi:
        _, _, ew, eh = asset.extent
        why = (f"its cut sides ({', '.join(asset.cut)}) must span the frame" if lo > recipe.scene.foreground.scale[1]
               * min(H, W) / max(ew, eh) else f"it would be magnified {lo:.2f}x")
        return (f"too small for {W}x{H} samples: a {ew}x{eh} cutout, {why} (assets.max_upscale = {limit:g}, "
                f"scene.foreground.scale = {list(recipe.scene.foreground.scale)})")
    return None



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


def draw_crop(rng: np.random.Generator, asset: Asset, recipe: Recipe) -> tuple[tuple[int, int, int, int], bool]:
    """((x, y, w, h) in source px, flip) of a background: a crop of the frame's aspect,
    `scene.background.crop` of the largest one and at least so large that it is magnified no
    more than `assets.max_upscale`, at a uniform position; flipped with `flip_share`."""
    H, W = recipe.frame
    sw, sh = asset.size
    cw_max, ch_max = largest_crop(asset.size, (H, W))
    lo, hi = recipe.scene.background.crop
    need = W / (recipe.assets.max_upscale * cw_max)  # the least crop magnified no more than max_upscale
    c = float(rng.uniform(max(lo, need), max(hi, need)))
    cw, ch = max(1, min(sw, round(cw_max * c))), max(1, min(sh, round(ch_max * c)))
    cx, cy = int(rng.integers(0, sw - cw + 1)), int(rng.integers(0, sh - ch + 1))
    return (cx, cy, cw, ch), bool(rng.random() < recipe.scene.foreground.flip_share)


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
