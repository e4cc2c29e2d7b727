"""Scene sampling: every random choice of one sample, as pure data (no pixels).

`sample_scene(recipe, library, split, index)` draws from the sample's own generator
(dofsynth.rng: `default_rng(SeedSequence([recipe.seed, SPLIT_ID[split], index]))`), so sample
k is the same whether drawn alone or in a loop, on any machine. The `Scene` it returns is
everything a renderer needs besides the asset pixels; `Scene.to_dict()` is the JSON sample
record's scene part (docs/FORMAT.md) and `Scene.from_dict` reads it back exactly.

Depth rules (normalized disparity, 1 = nearest): the background is flat (0 everywhere) or a
ramp from b0 at the near edge to b1 < b0 at the far edge ("horizontal": b0 at the left edge;
"vertical": b0 at the bottom edge). The middle plane has constant disparity
f1 >= b_max + min_gap (b_max = b0 for a ramp, 0 when flat), so it is in front of the
background everywhere; the front plane f0 >= f1 + min_gap.

Placement: an object's placed part is its asset's `extent` (the alpha's bounding box); it is
resized by `scale` (output px per source px) to `placed_size(...)` and its top-left corner is
put at integer (x, y) of the output frame (may be negative), keeping at least `min_in_frame`
of its area inside the frame.
"""
from __future__ import annotations

import os
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from dofsynth.assets import Asset, AssetLibrary
from dofsynth.optics.aperture import APERTURES, Aperture, aperture_from_dict
from dofsynth.recipe import Recipe
from dofsynth.rng import draw_uniform, sample_key, sample_rng, sample_seed

_PLACE_TRIES = 64


@dataclass(frozen=True)
class AssetRef:
    id: str
    path: str      # relative to the recipe's folder (portable), or "builtin:..."
    sha256: str


@dataclass(frozen=True)
class BackgroundParams:
    mode: str                       # "flat" | "ramp"
    b0: float
    b1: float
    direction: str | None           # "horizontal" | "vertical" | None (flat)
    crop: tuple[int, int, int, int]  # (x, y, w, h) in source pixels, before the flip
    flip: bool                      # horizontal flip after cropping


@dataclass(frozen=True)
class ObjectParams:
    disparity: float
    scale: float                    # output px per source px
    x: int                          # top-left of the placed extent, output px (may be < 0)
    y: int
    flip: bool                      # horizontal flip of the extent before placing


@dataclass(frozen=True)
class Target:
    focus: float                    # focus disparity in [0, 1]
    max_coc: float                  # px at the output size


@dataclass(frozen=True)
class Highlight:
    threshold: float
    gain: float
    power: float


@dataclass(frozen=True)
class Options:
    highlight: Highlight | None
    linear_light: bool


@dataclass(frozen=True)
class Scene:
    key: str
    split: str
    index: int
    seed: tuple[int, int, int]      # the SeedSequence entropy
    size: tuple[int, int]           # (H, W)
    assets: dict[str, AssetRef]     # "background", "front", "middle"
    background: BackgroundParams
    front: ObjectParams
    middle: ObjectParams
    targets: tuple[Target, ...]
    aperture: Aperture              # a kind of dofsynth.optics.aperture (its own to_dict in the record)
    options: Options

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict with the record fields of docs/FORMAT.md (lists for tuples)."""
        return {
            "key": self.key, "split": self.split, "index": self.index, "seed": list(self.seed),
            "size": list(self.size),
            "assets": {k: asdict(self.assets[k]) for k in ("background", "front", "middle")},
            "background": {**asdict(self.background), "crop": list(self.background.crop)},
            "front": asdict(self.front), "middle": asdict(self.middle),
            "targets": [asdict(t) for t in self.targets],
            "aperture": self.aperture.to_dict(),
            "options": {"highlight": asdict(self.options.highlight) if self.options.highlight else None,
                        "linear_light": self.options.linear_light},
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "Scene":
        """Inverse of `to_dict`; extra record keys (schema_version, renderer, ...) are ignored."""
        hl = d["options"].get("highlight")
        return cls(
            key=d["key"], split=d["split"], index=int(d["index"]), seed=tuple(int(s) for s in d["seed"]),
            size=(int(d["size"][0]), int(d["size"][1])),
            assets={k: AssetRef(**d["assets"][k]) for k in ("background", "front", "middle")},
            background=BackgroundParams(**{**d["background"], "crop": tuple(int(v) for v in d["background"]["crop"])}),
            front=ObjectParams(**d["front"]), middle=ObjectParams(**d["middle"]),
            targets=tuple(Target(**t) for t in d["targets"]),
            aperture=aperture_from_dict(d["aperture"]),
            options=Options(highlight=Highlight(**hl) if hl else None,
                            linear_light=bool(d["options"].get("linear_light", True))),
        )


def placed_size(scale: float, extent_w: int, extent_h: int) -> tuple[int, int]:
    """(w, h) in output px of an extent resized by `scale` (the renderer uses exactly this)."""
    return max(1, round(extent_w * scale)), max(1, round(extent_h * scale))


def in_frame_share(x: int, y: int, w: int, h: int, frame_w: int, frame_h: int) -> float:
    vis_w = max(0, min(x + w, frame_w) - max(x, 0))
    vis_h = max(0, min(y + h, frame_h) - max(y, 0))
    return vis_w * vis_h / float(w * h)


def background_disparity(mode: str, b0: float, b1: float, direction: str | None, h: int, w: int) -> np.ndarray:
    """(H, W) float32 disparity of the background. "flat": b0 everywhere (0 in sampled scenes);
    "ramp" + "horizontal": b0 at the left pixel column, linear to b1 at the right column;
    "ramp" + "vertical": b0 at the bottom pixel row, linear to b1 at the top row. (A ramp of
    h = 1 or w = 1 is its row or column: what a broadcast plane holds.)"""
    if mode == "flat":
        return np.full((h, w), b0, dtype=np.float32)
    if mode != "ramp":
        raise ValueError(f"background mode must be 'flat' or 'ramp', got {mode!r}")
    if direction == "horizontal":
        t = np.linspace(0.0, 1.0, w) if w > 1 else np.zeros(1)
        row = b0 + (b1 - b0) * t
        return np.ascontiguousarray(np.broadcast_to(row[None, :], (h, w)), dtype=np.float32)
    if direction == "vertical":
        t = np.linspace(1.0, 0.0, h) if h > 1 else np.zeros(1)  # 1 at the top row, 0 at the bottom
        col = b0 + (b1 - b0) * t
        return np.ascontiguousarray(np.broadcast_to(col[:, None], (h, w)), dtype=np.float32)
    raise ValueError(f"ramp direction must be 'horizontal' or 'vertical', got {direction!r}")


def _ref(asset: Asset, recipe: Recipe) -> AssetRef:
    path = asset.path
    if not path.startswith("builtin:") and recipe.base_dir:
        path = os.path.relpath(path, recipe.base_dir).replace(os.sep, "/")
    return AssetRef(id=asset.id, path=path, sha256=asset.sha256)


def _place(rng: np.random.Generator, asset: Asset, disparity: float, recipe: Recipe) -> ObjectParams:
    H, W = recipe.frame
    rules = recipe.scene.foreground
    _, _, ew, eh = asset.extent
    long_px = float(rng.uniform(*rules.scale)) * min(H, W)
    scale = long_px / max(ew, eh)
    w, h = placed_size(scale, ew, eh)
    m = rules.min_in_frame
    x_lo, x_hi = -int((1 - m) * w), W - int(np.ceil(m * w))
    y_lo, y_hi = -int((1 - m) * h), H - int(np.ceil(m * h))
    for _ in range(_PLACE_TRIES):
        x = int(rng.integers(min(x_lo, x_hi), max(x_lo, x_hi) + 1))
        y = int(rng.integers(min(y_lo, y_hi), max(y_lo, y_hi) + 1))
        if in_frame_share(x, y, w, h, W, H) >= m:
            break
    else:  # fall back to the nearest position fully inside (or centred if larger than the frame)
        x = (W - w) // 2 if w >= W else min(max(x, 0), W - w)
        y = (H - h) // 2 if h >= H else min(max(y, 0), H - h)
    flip = bool(rng.random() < rules.flip_share)
    return ObjectParams(disparity=float(disparity), scale=float(scale), x=x, y=y, flip=flip)


def sample_scene(recipe: Recipe, library: AssetLibrary, split: str, index: int) -> Scene:
    """Draw every random choice of sample `index` of `split` (pure data, deterministic)."""
    seed = sample_seed(recipe.seed, split, index)
    rng = sample_rng(seed)
    H, W = recipe.frame
    bgs, fgs = library.assets_for("background", split), library.assets_for("foreground", split)
    if not bgs or len(fgs) < 2:
        raise ValueError(f"the {split} split needs 1 background and 2 foregrounds, has {len(bgs)} and {len(fgs)}")

    # 1. background asset, crop and flip
    bg = bgs[int(rng.integers(len(bgs)))]
    sw, sh = bg.size
    if sw * H > sh * W:   # source wider than the frame aspect
        cw_max, ch_max = sh * W / H, float(sh)
    else:
        cw_max, ch_max = float(sw), sw * H / W
    br, fr = recipe.scene.background, recipe.scene.foreground
    c = float(rng.uniform(*br.crop))
    cw, ch = max(1, min(sw, round(cw_max * c))), max(1, min(sh, round(ch_max * c)))
    cx, cy = int(rng.integers(0, sw - cw + 1)), int(rng.integers(0, sh - ch + 1))
    bflip = bool(rng.random() < fr.flip_share)

    # 2. background depth
    if rng.random() < br.flat_share:
        mode, b0, b1, direction = "flat", 0.0, 0.0, None
    else:
        mode = "ramp"
        b0 = draw_uniform(rng, *br.b0)
        b1 = draw_uniform(rng, br.b1[0], min(br.b1[1], b0))
        if b1 >= b0:  # only when the ranges touch; keep a strict ramp
            b1 = max(0.0, b0 - 1e-3)
        direction = "vertical" if rng.random() < br.vertical_share else "horizontal"
    background = BackgroundParams(mode=mode, b0=float(b0), b1=float(b1), direction=direction,
                                  crop=(cx, cy, cw, ch), flip=bflip)

    # 3. foreground planes: middle in front of the background, front in front of the middle
    f1 = draw_uniform(rng, max(fr.f1[0], b0 + fr.min_gap), fr.f1[1])
    f0 = draw_uniform(rng, max(fr.f0[0], f1 + fr.min_gap), fr.f0[1])

    # 4. foreground assets (distinct) and placement
    i = int(rng.integers(len(fgs)))
    j = int(rng.integers(len(fgs) - 1))
    j = j + 1 if j >= i else j
    front_asset, middle_asset = fgs[i], fgs[j]
    middle = _place(rng, middle_asset, f1, recipe)
    front = _place(rng, front_asset, f0, recipe)

    # 5. focus targets
    fo = recipe.focus
    targets = []
    for _ in range(fo.targets_per_scene):
        if rng.random() < fo.plane_share:
            plane = int(rng.integers(3))  # 0 background (a point of the ramp), 1 middle, 2 front
            focus = draw_uniform(rng, b1, b0) if plane == 0 else (f1 if plane == 1 else f0)
        else:
            focus = float(rng.uniform(0.0, 1.0))
        targets.append(Target(focus=float(focus), max_coc=draw_uniform(rng, *fo.max_coc)))

    # 6. aperture and options
    ar = recipe.render.aperture
    aperture = APERTURES[ar.kind].from_rules(ar, rng)
    hr = recipe.render.highlight
    linear = recipe.render.linear_light  # highlights are light: the naive (sRGB) baseline has none
    options = Options(highlight=Highlight(hr.threshold, hr.gain, hr.power) if hr.enabled and linear else None,
                      linear_light=linear)

    return Scene(
        key=sample_key(split, index), split=split, index=int(index), seed=seed, size=(H, W),
        assets={"background": _ref(bg, recipe), "front": _ref(front_asset, recipe),
                "middle": _ref(middle_asset, recipe)},
        background=background, front=front, middle=middle, targets=tuple(targets),
        aperture=aperture, options=options,
    )
