"""Rendering layered scenes with shallow depth of field: `render_planes(planes, focus, max_coc,
aperture, method=...)`, and `render_look` / `render_photo` (dofsynth.render.look), the one way
a target or a photo is rendered with a recipe's options (highlight boost, method, chromatic
aberration, colour space).

planes (dofsynth.render.planes.Plane) are listed back to front; each method of `METHODS`
(the one registry of methods: recipes, records, `dofsynth render` and the docs ask it)
turns validated planes into linear RGB:
- "layered" (dofsynth.render.layered): each plane blurred on its own with its aperture kernel
  (premultiplied), composited back to front; fast, what `generate` uses;
- "subaperture" (dofsynth.render.subaperture): the aperture cut into n x n cells, the layered
  method per cell with the part of the kernel in it, the cells added; shows what a blurred
  edge reveals behind it, at about the cell count times the layered cost;
- "adaptive" (dofsynth.render.adaptive): the layered method, and the sub-aperture one only in
  the tiles where the layered one errs (a blurred cutout's edge over a blurred plane that
  varies); the default of the 18K and shared-assets recipes;
- "exact" (dofsynth.render.exact): the aperture sampled, every plane warped and composited per
  aperture point, averaged; handles partial occlusion at depth edges, slow.
A method is one `Method` entry: its function (validated planes, focus, max_coc, aperture,
RenderOptions) -> planar (3, H, W) float32, the renderer id its records carry, the
RenderOptions it reads (any other option set away from its default is refused by name) and
whether it reads only inside the planes' boxes. A new method is one `METHODS[name] = Method(...)`.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Callable

import cv2
import numpy as np

from dofsynth.optics.aperture import Aperture, Disk
from dofsynth.render.adaptive import render_adaptive
from dofsynth.render.exact import render_exact
from dofsynth.render.layered import LEVEL_RATIO, render_layered
from dofsynth.render.planes import Plane, validate_planes
from dofsynth.render.subaperture import render_subaperture

__all__ = ["DEFAULT_METHOD", "METHODS", "LEVEL_RATIO", "Method", "Plane", "RenderOptions", "method_entry", "readers",
           "render_planes"]


@dataclass(frozen=True)
class RenderOptions:
    """level_step: largest CoC gap (px) between the levels of a varying-disparity plane;
    level_ratio: their relative spacing (layered). samples: aperture points, None = enough for
    <= 0.5 px steps (exact)."""

    level_step: float = 0.5
    level_ratio: float = LEVEL_RATIO
    samples: int | None = None
    cells: int = 1
    cat_eye: float = 0.0
    margin: int = 0  # px the planes go on past the frame on each side: cat-eye is measured on the
    #                  frame, and the layered, adaptive and (without cat-eye, the margin past every
    #                  kernel's reach) sub-aperture methods compute only it (the rest of the result is 0)

    def __post_init__(self):
        if not (math.isfinite(self.level_step) and self.level_step > 0):
            raise ValueError(f"level_step must be a positive number of pixels, got {self.level_step}")
        if not (math.isfinite(self.level_ratio) and 0.0 <= self.level_ratio < 1.0):
            raise ValueError(f"level_ratio must be in [0, 1), got {self.level_ratio}")
        s = self.samples
        if s is not None and (isinstance(s, bool) or not isinstance(s, (int, np.integer)) or s < 1):
            raise ValueError(f"samples must be a positive integer or None, got {s}")
        c = self.cells
        if isinstance(c, bool) or not isinstance(c, (int, np.integer)) or not 1 <= c <= 16:
            raise ValueError(f"cells must be an integer in 1..16 (an n x n grid), got {c}")
        if not (math.isfinite(self.cat_eye) and 0.0 <= self.cat_eye <= 1.0):
            raise ValueError(f"cat_eye must be a strength in [0, 1], got {self.cat_eye}")
        if isinstance(self.margin, bool) or not isinstance(self.margin, (int, np.integer)) or self.margin < 0:
            raise ValueError(f"margin must be a non-negative integer of pixels, got {self.margin}")


_OPTION_DEFAULTS = {f.name: f.default for f in dataclasses.fields(RenderOptions)}


@dataclass(frozen=True)
class Method:
    """One render method: `render(planes, focus, max_coc, aperture, RenderOptions)` -> planar
    (3, H, W) float32 linear; `renderer_id`, what records and manifests name (bumped when its
    output bytes change in meaning); `options`, the RenderOptions fields it reads (the recipe
    keys render.cells / render.cat_eye and `dofsynth render --cells / --cat-eye` among them);
    `uses_boxes`, whether it reads colour and alpha only inside each plane's box; `summary`,
    a line for --help and the docs."""

    render: Callable
    renderer_id: str
    options: tuple[str, ...] = ()
    uses_boxes: bool = True
    summary: str = ""


METHODS: dict[str, Method] = {
    "layered": Method(render_layered, "layered-v9", ("level_step", "level_ratio", "margin"),
                      summary="each plane blurred on its own and composited back to front (fast)"),
    "subaperture": Method(render_subaperture, "subaperture-v12", ("level_step", "level_ratio", "cells", "cat_eye", "margin"),
                          summary="the aperture cut into cells x cells parts, layered per part: shows what "
                                  "a blurred edge reveals behind it, about cells^2 x the cost"),
    "adaptive": Method(render_adaptive, "adaptive-v8", ("level_step", "level_ratio", "margin"),
                       summary="the layered render, with 2 x 2 sub-aperture cells only in the tiles where it errs: "
                               "a blurred cutout's edge over a blurred plane that varies"),
    "exact": Method(render_exact, "exact-v4", ("samples", "cat_eye", "margin"), uses_boxes=False,
                    summary="every aperture point warped and composited, averaged (slow, a reference)"),
}


DEFAULT_METHOD = "layered"  # what recipes, records without method keys and `dofsynth render` use


def method_entry(name: str) -> Method:
    """The METHODS entry `name`; a ValueError lists the known ones."""
    if name not in METHODS:
        raise ValueError(f"method must be one of {', '.join(METHODS)}, got {name!r}")
    return METHODS[name]


def readers(option: str) -> str:
    """The methods that read RenderOptions field `option`, as "a or b" (for messages)."""
    return " or ".join(n for n, m in METHODS.items() if option in m.options) or "none"


def render_planes(planes, focus: float, max_coc: float, aperture: Aperture = Disk(), *, method: str = DEFAULT_METHOD,
                  level_step: float = 0.5, level_ratio: float = LEVEL_RATIO, samples: int | None = None,
                  cells: int = 1, cat_eye: float = 0.0, margin: int = 0, planar: bool = False,
                  values_checked: bool = False) -> np.ndarray:
    """Render a layered scene with shallow depth of field; linear RGB (H, W, 3) float32.

    planes: Plane, back to front (disparity in [0, 1], 1 = nearest). focus: the in-focus
    disparity. max_coc: CoC radius in pixels at |disparity - focus| = 1. aperture: a kind of
    dofsynth.optics.aperture. method: a key of METHODS; level_step, level_ratio, samples,
    cells (subaperture: an n x n grid) and cat_eye (subaperture, exact: optical vignetting,
    the aperture clipped by a unit circle offset by cat_eye x the position over the frame's
    half-diagonal; `margin`: px of the planes past that frame on each side) are its RenderOptions. The result is the premultiplied composite over black (opaque if the
    backmost plane is). planar=True returns the same values as (3, H, W) (the renderer's own
    layout: no interleaving copy, which at 4096 px is a fresh 192 MiB frame and ~0.17 s).
    values_checked=True: the caller has run `validate_planes` on these planes' values (a sample
    renders each target from the same planes), so only their shapes, boxes and the scalars are.
    """
    planes = list(planes)
    m = method_entry(method)
    validate_planes(planes, focus, max_coc, use_boxes=m.uses_boxes, values=not values_checked)
    if not isinstance(aperture, Aperture):
        raise ValueError(f"aperture must be an aperture kind (Disk(), Polygon(...)), got {aperture!r}")
    options = RenderOptions(level_step=level_step, level_ratio=level_ratio, samples=samples, cells=cells,
                            cat_eye=float(cat_eye), margin=margin)
    unread = [f for f in _OPTION_DEFAULTS if f not in m.options and getattr(options, f) != _OPTION_DEFAULTS[f]]
    if unread:
        raise ValueError("; ".join(f"{f} applies to method {readers(f)}, not {method!r}" for f in unread))
    acc = m.render(planes, focus, max_coc, aperture, options)
    if planar:
        return acc
    return cv2.merge([acc[0], acc[1], acc[2]])  # (H, W, 3) float32
