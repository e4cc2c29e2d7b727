"""How a target is rendered from its planes: the `Look` a recipe's [render] table fixes and a
record's `options` store, and the one function that applies it.

`render_photo(rgb, disparity, focus, max_coc, aperture, look)` renders a photo with its depth
(one opaque plane); `prepare_planes` + `render_look` + `restore` are the same steps for a
layered scene whose planes are prepared once for all its targets (dofsynth.sample):
1. prepare: in linear light, each plane's colour highlight-boosted (dofsynth.render.highlight);
   with `linear_light = False` (the naive baseline) sRGB-encoded copies instead;
2. render: the look's method (dofsynth.render.METHODS) with its options; with longitudinal
   chromatic aberration each channel at its own CoC scale (max_coc * chromatic[ch]);
3. restore: the exact inverse of the boost (linear light), or the naive render's sRGB codes
   clipped to [0, 1].
A Look refuses, by name, every option its method or colour space would not apply.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace

import numpy as np

from dofsynth.color import linear_to_srgb, srgb_to_linear
from dofsynth.optics.aperture import Aperture
from dofsynth.render import DEFAULT_METHOD, METHODS, method_entry, readers, render_planes
from dofsynth.render.highlight import boost, unboost
from dofsynth.render.planes import Plane

NO_CHROMATIC = (1.0, 1.0, 1.0)
METHOD_FIELDS = ("cells", "cat_eye")  # the Look's fields that are options of some methods (RenderOptions)


@dataclass(frozen=True)
class Highlight:
    """The highlight boost's parameters (dofsynth.render.highlight.boost): the sRGB level above
    which light is boosted, the gain of a white pixel and the curve's power."""

    threshold: float = 0.9
    gain: float = 4.0
    power: float = 2.0


@dataclass(frozen=True)
class Look:
    """method: a key of METHODS; cells: its n x n aperture cells (methods reading "cells");
    cat_eye: optical vignetting strength in [0, 1] (methods reading "cat_eye"); chromatic: the
    CoC scale of R, G, B; highlight: the boost, or None; linear_light: blur in linear light
    (False: the naive baseline, blur of sRGB codes, no highlight, no chromatic aberration)."""

    method: str = DEFAULT_METHOD
    cells: int = 1
    cat_eye: float = 0.0
    chromatic: tuple[float, float, float] = NO_CHROMATIC
    highlight: Highlight | None = None
    linear_light: bool = True

    def __post_init__(self):
        m = method_entry(self.method)
        for f in METHOD_FIELDS:
            if getattr(self, f) != getattr(Look, f) and f not in m.options:
                raise ValueError(f"{f} = {getattr(self, f)!r} applies to method {readers(f)}, not {self.method!r}")
        if len(self.chromatic) != 3 or not all(math.isfinite(v) and v > 0 for v in self.chromatic):
            raise ValueError(f"chromatic must be three positive CoC scales (R, G, B), got {self.chromatic!r}")
        if not self.linear_light:
            given = [name for name, on in (("highlight", self.highlight is not None),
                                           ("chromatic", tuple(self.chromatic) != NO_CHROMATIC)) if on]
            if given:
                raise ValueError(f"{' and '.join(given)} need linear_light (the naive sRGB baseline applies neither)")

    def keywords(self) -> dict:
        """The render_planes keywords: the method and the options it reads that are not zero."""
        m = METHODS[self.method]
        return {"method": self.method, **{f: getattr(self, f) for f in METHOD_FIELDS
                                          if f in m.options and getattr(self, f)}}

    @property
    def renderer_id(self) -> str:
        return METHODS[self.method].renderer_id

    def to_dict(self) -> dict:
        """The record's `options` keys of this look (docs/FORMAT.md): highlight, linear_light;
        chromatic unless (1, 1, 1); the method keys (`keywords`) unless the method is the
        default (layered records stay as they were before methods existed)."""
        d = {"highlight": asdict(self.highlight) if self.highlight else None, "linear_light": self.linear_light}
        if tuple(self.chromatic) != NO_CHROMATIC:
            d["chromatic"] = list(self.chromatic)
        return d if self.method == DEFAULT_METHOD else {**d, **self.keywords()}

    @classmethod
    def from_dict(cls, d: dict) -> "Look":
        """Inverse of `to_dict` (other keys of a record's options are ignored)."""
        hl = d.get("highlight")
        return cls(method=d.get("method", DEFAULT_METHOD), cells=int(d.get("cells", 1)),
                   cat_eye=float(d.get("cat_eye", 0.0)),
                   chromatic=tuple(float(v) for v in d.get("chromatic", NO_CHROMATIC)),
                   highlight=Highlight(**hl) if hl else None, linear_light=bool(d.get("linear_light", True)))


def prepare_planes(planes: list[Plane], look: Look) -> list[Plane]:
    """The planes as the blur takes them: colour highlight-boosted IN PLACE (linear light; a
    cutout only inside its box, where its colour is not 0), or sRGB-encoded copies (naive)."""
    if not look.linear_light:
        return [replace(p, rgb=linear_to_srgb(p.rgb)) for p in planes]
    if look.highlight is not None:
        hl = asdict(look.highlight)
        for i, p in enumerate(planes):
            rgb = p.rgb
            if i > 0 and p.box is not None:
                y0, y1, x0, x1 = p.box
                if y1 <= y0 or x1 <= x0:
                    continue
                rgb = rgb[y0:y1, x0:x1]
            boost(rgb, **hl, out=rgb)
    return planes


def render_look(planes: list[Plane], focus: float, max_coc: float, aperture: Aperture, look: Look,
                margin: int = 0, values_checked: bool = False) -> np.ndarray:
    """Planar (3, H, W) float32 render of prepared planes (`prepare_planes`), not yet restored:
    with chromatic aberration channel ch is the render at max_coc * chromatic[ch]. `margin`: px
    the planes go on past the frame on each side; only the frame of the result is meant (what
    cat-eye is measured on; the layered method computes nothing else). `values_checked`: as
    `render_planes`'s (the planes' values are checked once either way)."""
    scales, kw = look.chromatic, look.keywords()
    if margin and "margin" in METHODS[look.method].options:  # (a method that does not read it renders all)
        kw["margin"] = int(margin)
    img = render_planes(planes, float(focus), float(max_coc) * scales[1], aperture, planar=True,
                        values_checked=values_checked, **kw)
    for ch in (0, 2):
        if scales[ch] != scales[1]:
            img[ch] = render_planes(planes, float(focus), float(max_coc) * scales[ch], aperture, planar=True,
                                    values_checked=True, **kw)[ch]
    return img


def restore(img: np.ndarray, look: Look, axis: int = 0) -> np.ndarray:
    """A render of prepared planes mapped back, in place: the boost's exact inverse (linear
    light; channels along `axis`), or the naive render's sRGB codes clipped to [0, 1]."""
    if not look.linear_light:
        return np.clip(img, 0.0, 1.0, out=img)
    if look.highlight is not None:
        unboost(img, **asdict(look.highlight), out=img, axis=axis)
    return img


def views_adding_up(target: np.ndarray, left: np.ndarray, right: np.ndarray, wl: float,
                    wr: float) -> tuple[np.ndarray, np.ndarray]:
    """Two views through complementary parts of the aperture (a dual-pixel pair: left, right
    with area shares wl + wr = 1), made to add up to `target` in linear light: each is scaled,
    per pixel and channel, by target / (wl * left + wr * right), so wl * L + wr * R = target
    (clipped to [0, 1]) exactly while the views keep their own parallax. Where a view would pass
    1, both move toward the target by one factor per pixel, the same for the three channels,
    until none passes 1: they still add up, and keep the target's hue (clipping channels one
    by one gave a bright edge's views red and yellow fringes). Where both are 0 each view is the
    target. All arrays planar (3, H, W) float32; the views come back new."""
    t = np.clip(target, 0.0, 1.0)
    s = left * np.float32(wl) + right * np.float32(wr)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(s > 0, t / s, 0.0).astype(np.float32)
    lv = np.where(s > 0, left * ratio, t)
    rv = np.where(s > 0, right * ratio, t)
    over = np.maximum(lv, rv)  # >= t (their weighted mean is t): only the larger can pass 1
    with np.errstate(divide="ignore", invalid="ignore"):
        room = np.where(over > 1.0, (1.0 - t) / (over - t), 1.0)
    beta = np.clip(room.min(axis=0, keepdims=True), 0.0, 1.0).astype(np.float32)
    lv = t + beta * (lv - t)
    rv = t + beta * (rv - t)
    return np.clip(lv, 0.0, 1.0).astype(np.float32), np.clip(rv, 0.0, 1.0).astype(np.float32)


def render_photo(rgb: np.ndarray, disparity: np.ndarray, focus: float, max_coc: float, aperture: Aperture,
                 look: Look = Look()) -> np.ndarray:
    """A photo with its depth rendered as `look` says: linear RGB (H, W, 3) float32 in, linear
    (H, W, 3) float32 out. rgb is linear light (>= 0); disparity (H, W) normalized, 1 = nearest.
    The photo is one opaque plane (no hidden background: dofsynth docs rendering)."""
    plane = Plane(np.array(rgb, dtype=np.float32), np.ones(disparity.shape, np.float32), disparity)
    planes = prepare_planes([plane], look)
    img = restore(render_look(planes, focus, max_coc, aperture, look), look)
    out = np.ascontiguousarray(np.moveaxis(img, 0, -1))
    return out if look.linear_light else srgb_to_linear(out)
