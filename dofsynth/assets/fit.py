"""What an asset can be at a recipe's frame size: the largest background crop of the frame's
aspect and the scales a cutout may be placed at, both bounded by `assets.max_upscale`, so that
the library can refuse (by name) assets too small for the recipe before any scene is drawn."""
from __future__ import annotations

from dofsynth.assets.decode import Asset


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
