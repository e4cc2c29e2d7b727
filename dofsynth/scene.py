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
resized by `scale` (output px per source px, at most `assets.max_upscale`) to
`dofsynth.assets.placement.placed_size(...)` and its top-left corner is put at integer (x, y) of the
output frame (may be negative), keeping at least `min_in_frame` of its area inside the frame.
A matte cut by its photo's border (a portrait cut at the chest: `Asset.cut`) is placed with
each cut side on or beyond the matching frame edge (`ObjectParams.anchored`, after the flip);
an asset no placement can do that for is redrawn and listed in `rejected`. Each object keeps
at least `min_visible` of its alpha in view, the middle one behind the front one (`visible`,
estimated on 128 px thumbnails). Focus targets of a scene lie at least
`focus.min_separation` apart in disparity.
"""
from __future__ import annotations

import math
import os
from dataclasses import asdict, dataclass, replace
from typing import Any


from dofsynth.assets import Asset, AssetLibrary
from dofsynth.assets.placement import ObjectParams, draw_crop, draw_object, visible_shares
from dofsynth.optics.aperture import APERTURES, Aperture, aperture_from_dict
from dofsynth.optics.kernel import support_radius
from dofsynth.recipe import Recipe, recipe_lens, recipe_look
from dofsynth.render.look import Look
from dofsynth.rng import draw_uniform, sample_key, sample_rng, sample_seed

@dataclass(frozen=True)
class AssetRef:
    id: str
    path: str      # relative to the recipe's folder (portable), or "builtin:..."
    sha256: str
    colour: str = "file"  # "file": the file's colour as it is; "estimated:<estimator>" (dofsynth.assets.foreground)
    matte: str = "file"   # "file": its alpha as it is; "opaque_from:<v>": values >= v loaded as 1 (assets.opaque_from)


@dataclass(frozen=True)
class BackgroundParams:
    mode: str                       # "flat" | "ramp"
    b0: float
    b1: float
    direction: str | None           # "horizontal" | "vertical" | None (flat; "none" in the record)
    crop: tuple[int, int, int, int]  # (x, y, w, h) in source pixels, before the flip
    flip: bool                      # horizontal flip after cropping
    margin: int = 0                 # px the planes extend past each frame edge for the blur (`frame_margin`)
    real: tuple[int, int, int, int] = (0, 0, 0, 0)  # (top, bottom, left, right): px of that margin from the photo


@dataclass(frozen=True)
class Target:
    focus: float                    # focus disparity in [0, 1]
    max_coc: float                  # px at the output size
    lens: dict | None = None        # the thin lens behind it, if the recipe has one (ThinLens.to_dict)

    def to_dict(self) -> dict:
        d = {"focus": self.focus, "max_coc": self.max_coc}
        return d if self.lens is None else {**d, "lens": dict(self.lens)}


@dataclass(frozen=True)
class Options:
    look: Look = Look()             # how the targets are rendered (dofsynth.render.look)
    members: tuple[str, ...] = ()   # optional members written (recipe render.members, dofsynth.members)


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
    excluded: tuple[str, ...] = ()  # assets left out of this sample's draw: found bad when it loaded them

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict with the record fields of docs/FORMAT.md (lists for tuples)."""
        return {
            "key": self.key, "split": self.split, "index": self.index, "seed": list(self.seed),
            "size": list(self.size),
            "assets": {k: asdict(self.assets[k]) for k in ("background", "front", "middle")},
            "background": {**asdict(self.background), "crop": list(self.background.crop),
                           "real": list(self.background.real), "direction": self.background.direction or "none"},
            "front": _object_dict(self.front), "middle": _object_dict(self.middle),
            "targets": [t.to_dict() for t in self.targets],
            "aperture": self.aperture.to_dict(),
            "options": {**self.options.look.to_dict(), "members": list(self.options.members)},
            "excluded": "\n".join(self.excluded),
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "Scene":
        """Inverse of `to_dict`; extra record keys (schema_version, renderer, ...) are ignored."""
        return cls(
            key=d["key"], split=d["split"], index=int(d["index"]), seed=tuple(int(s) for s in d["seed"]),
            size=(int(d["size"][0]), int(d["size"][1])),
            assets={k: AssetRef(**d["assets"][k]) for k in ("background", "front", "middle")},
            background=BackgroundParams(**{**d["background"], "crop": tuple(int(v) for v in d["background"]["crop"]),
                                           "real": tuple(int(v) for v in d["background"].get("real", (0, 0, 0, 0))),
                                           "direction": _direction(d["background"].get("direction"))}),
            front=_object(d["front"]), middle=_object(d["middle"]),
            targets=tuple(Target(**t) for t in d["targets"]),
            aperture=aperture_from_dict(d["aperture"]),
            options=Options(look=Look.from_dict(d["options"]), members=tuple(d["options"].get("members", ()))),
            excluded=_split(d.get("excluded", ()), "\n"),
        )


# Lists of names are stored as one string (schema 4): a field's JSON type must not depend on the
# sample, and an empty list has none (Hugging Face datasets infers `null` from the first samples
# and then cannot read a later non-empty one). Sides are joined by ",", asset ids by newlines.
def _direction(value) -> str | None:
    """A ramp's direction; None for a flat background ("none" in schema >= 4, null before)."""
    return None if value in (None, "none") else value


def _split(value, sep: str) -> tuple[str, ...]:
    """Names of a record field: a joined string (schema >= 4) or a list (older records)."""
    return tuple(x for x in value.split(sep) if x) if isinstance(value, str) else tuple(value)


def _object_dict(o: ObjectParams) -> dict[str, Any]:
    d = asdict(o)
    return {**d, "anchored": ",".join(o.anchored), "rejected": "\n".join(o.rejected)}


def _object(d: dict[str, Any]) -> ObjectParams:
    return ObjectParams(**{**d, "anchored": _split(d.get("anchored", ()), ","),
                           "rejected": _split(d.get("rejected", ()), "\n")})


def _ref(asset: Asset, recipe: Recipe, library: AssetLibrary) -> AssetRef:
    path = asset.path
    if not path.startswith("builtin:") and recipe.base_dir:
        path = os.path.relpath(path, recipe.base_dir).replace(os.sep, "/")
    return AssetRef(id=asset.id, path=path, sha256=asset.sha256, colour=library.colour(asset), matte=library.matte(asset))


_VISIBLE_TRIES = 32  # object draws for both to stay visible (a new middle object every 8)
_FOCUS_TRIES = 32


def _draw_focus(rng, plane_share: float, ramp: tuple[float, float], f1: float, f0: float,
                taken: list[float], sep: float) -> float:
    """A target's focus, at least `sep` from every focus in `taken`: exactly on a plane (a point
    of the background ramp) or uniform in [0, 1]; after _FOCUS_TRIES draws too close, uniform
    over what [0, 1] has left (never empty: recipe checks (targets - 1) * sep <= 0.5)."""
    for _ in range(_FOCUS_TRIES):
        if rng.random() < plane_share:
            plane = int(rng.integers(3))  # 0 background (a point of the ramp), 1 middle, 2 front
            focus = draw_uniform(rng, *ramp) if plane == 0 else (f1 if plane == 1 else f0)
        else:
            focus = float(rng.uniform(0.0, 1.0))
        if all(abs(focus - t) >= sep for t in taken):
            return float(focus)
    free, start = [], 0.0  # [0, 1] less (t - sep, t + sep) of every taken focus
    for t in sorted(taken):
        if t - sep > start:
            free.append((start, t - sep))
        start = max(start, t + sep)
    if start < 1.0:
        free.append((start, 1.0))
    u = float(rng.uniform(0.0, sum(b - a for a, b in free)))
    for a, b in free:
        if u <= b - a:
            return min(a + u, b)
        u -= b - a
    return free[-1][1] if free else 1.0


def frame_margin(background: BackgroundParams, planes: tuple[float, ...], targets, look: Look,
                 size: tuple[int, int]) -> int:
    """Px past each frame edge that the blur of any target reaches: the support radius of the
    largest CoC |max_coc * scale * (d - focus)| over the targets, the chromatic scales and the
    planes' disparities (a ramp extrapolated over that margin too). The planes are composed
    that far beyond the frame, so border pixels blur what lies beyond, not copies of the edge."""
    H, W = size
    lo, hi = min(background.b0, background.b1), max(background.b0, background.b1)
    scale = max(look.chromatic)

    def reach(lo: float, hi: float) -> int:
        d = (lo, hi) + tuple(planes)
        return max((support_radius(t.max_coc * scale * max(abs(v - t.focus) for v in d)) for t in targets), default=0)

    m = reach(lo, hi)
    if background.mode == "ramp" and m:  # the ramp goes on past the frame: its CoC grows there
        step = (hi - lo) * m / max((W if background.direction == "horizontal" else H) - 1, 1)
        m = reach(max(lo - step, 0.0), min(hi + step, 1.0)) + 1
    return int(m)


def real_margin(crop, photo_size: tuple[int, int], size: tuple[int, int], margin: int,
                flip: bool) -> tuple[int, int, int, int]:
    """(top, bottom, left, right): how many px of a `margin` around the frame the photo holds
    beyond the crop (x, y, w, h) at the crop's scale (the rest is its edge replicated); left
    and right as seen in the frame (after the flip)."""
    x, y, cw, ch = crop
    pw, ph = photo_size
    H, W = size
    sx, sy = cw / W, ch / H  # source px per output px
    side = lambda free, s: int(min(margin, math.floor(free / s + 1e-9)))  # noqa: E731
    top, bottom, left, right = side(y, sy), side(ph - y - ch, sy), side(x, sx), side(pw - x - cw, sx)
    return (top, bottom, right, left) if flip else (top, bottom, left, right)


def sample_scene(recipe: Recipe, library: AssetLibrary, split: str, index: int, exclude=()) -> Scene:
    """Draw every random choice of sample `index` of `split` (pure data, deterministic).
    `exclude`: asset ids this sample must not use (bad files found when loading its earlier
    draw); the draw starts again from the sample's own seed without them."""
    seed = sample_seed(recipe.seed, split, index)
    rng = sample_rng(seed)
    H, W = recipe.frame
    exclude = tuple(sorted(set(exclude)))
    bgs, fgs = ([a for a in library.assets_for(kind, split) if a.id not in exclude] for kind in ("background", "foreground"))
    if not bgs or len(fgs) < 2:
        left = f" once the bad assets {', '.join(exclude)} are left out" if exclude else ""
        raise ValueError(f"the {split} split needs 1 background and 2 foregrounds, has {len(bgs)} and {len(fgs)}{left}")

    # 1. background asset, crop and flip
    bg = bgs[int(rng.integers(len(bgs)))]
    (cx, cy, cw, ch), bflip = draw_crop(rng, bg, recipe)
    br, fr = recipe.scene.background, recipe.scene.foreground

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

    # 4. foreground assets (distinct) and placement: cut sides on the frame's edges, each object
    #    at least min_visible seen (front draws redrawn, a new middle object every 8 of them)
    best = None
    for attempt in range(_VISIBLE_TRIES):
        if attempt % 8 == 0:
            middle_asset, middle = draw_object(rng, fgs, f1, recipe)
        front_asset, front = draw_object(rng, fgs, f0, recipe, exclude={middle_asset.id})
        seen = visible_shares((middle_asset, middle), (front_asset, front), (H, W))
        if best is None or min(seen) > min(best[-1]):
            best = (middle_asset, middle, front_asset, front, seen)
        if min(seen) >= fr.min_visible:
            break
    middle_asset, middle, front_asset, front, (seen_m, seen_f) = best
    if min(seen_m, seen_f) < fr.min_visible:
        raise ValueError(f"{sample_key(split, index)}: no placement in {_VISIBLE_TRIES} draws shows both objects "
                         f"at least scene.foreground.min_visible = {fr.min_visible:g} (best: middle {seen_m:.2f}, "
                         f"front {seen_f:.2f}); lower it, or min_in_frame, or the scale range")
    middle, front = replace(middle, visible=round(seen_m, 4)), replace(front, visible=round(seen_f, 4))

    # 5. focus targets, at least min_separation apart in disparity
    fo = recipe.focus
    targets: list[Target] = []
    for _ in range(fo.targets_per_scene):
        focus = _draw_focus(rng, fo.plane_share, (b1, b0), f1, f0, [t.focus for t in targets], fo.min_separation)
        if fo.lens.enabled:  # a thin lens: its focal length and f-number drawn, max_coc follows
            lens = recipe_lens(recipe, draw_uniform(rng, *fo.lens.focal_length_mm), draw_uniform(rng, *fo.lens.f_number))
            distance = lens.distance(focus)
            targets.append(Target(focus=focus, max_coc=lens.max_coc(distance, W), lens=lens.to_dict(distance)))
        else:
            targets.append(Target(focus=focus, max_coc=draw_uniform(rng, *fo.max_coc)))

    # 6. aperture and options
    ar = recipe.render.aperture
    aperture = APERTURES[ar.kind].from_rules(ar, rng)
    options = Options(look=recipe_look(recipe), members=tuple(recipe.render.members))

    # 7. how far past the frame the blur reaches, and how much of that the photo holds (no draw)
    margin = frame_margin(background, (f1, f0), targets, options.look, (H, W))
    background = replace(background, margin=margin,
                         real=real_margin(background.crop, bg.size, (H, W), margin, background.flip))

    return Scene(
        key=sample_key(split, index), split=split, index=int(index), seed=seed, size=(H, W),
        assets={"background": _ref(bg, recipe, library), "front": _ref(front_asset, recipe, library),
                "middle": _ref(middle_asset, recipe, library)},
        background=background, front=front, middle=middle, targets=tuple(targets),
        aperture=aperture, options=options, excluded=exclude,
    )
