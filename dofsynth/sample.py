"""One sample rendered: `render_sample(scene, library)` -> its tar members `{suffix: bytes}`.

Everything comes from the scene (its targets, aperture and options), so a sample can be
re-rendered from its JSON record alone (`verify --deep`, focus sweeps):
- `dof.N.png`: `unboost(render_planes(boost(planes), focus_N, max_coc_N, aperture))`: with
  `options.highlight` set, each plane's colour is highlight-boosted (dofsynth.highlight) before
  the blur and the result mapped back by the exact inverse; else the plain render.
- `aif.png`: the same with no blur, `unboost(composite(boost(planes)))`, so a target equals it
  wherever nothing that reaches a pixel is blurred;
- `depth.exr`, `cover.png`: the disparity map and the two coverages (dofsynth.record);
- with the recipe's `render.members`: `coc.N.exr` (target N's signed CoC map),
  `layer.K.exr` (each plane before blur and boost) and `dp.N.left.png` / `dp.N.right.png`
  (the left and right halves of the aperture: a dual-pixel pair; `dof.N.png` is then their
  area-weighted sum, a two-cell sub-aperture render).
With `options.linear_light = false` (the naive baseline, no highlight handling) the planes are
sRGB-encoded before the blur and the result is stored as it is.
"""
from __future__ import annotations

from dataclasses import asdict, replace

import numpy as np

from dofsynth.assets import AssetLibrary
from dofsynth.color import linear_to_srgb
from dofsynth.compose import scene_layers
from dofsynth.highlight import boost, unboost
from dofsynth.record import (encode_alphas, encode_coc, encode_depth, encode_layer, encode_png8, encode_record,
                             encode_srgb_png_planar,
                             encode_srgb_png_rows, sample_record)
from dofsynth.render import render_planes
from dofsynth.render.subaperture import halves
from dofsynth.scene import Scene, Target


def render_sample(scene: Scene, library: AssetLibrary) -> dict[str, bytes]:
    """Render one scene to its tar members {suffix: bytes} (see the module docstring)."""
    layers = scene_layers(scene, library)
    planes = list(layers.planes)
    extra = scene.options.members
    optional = {}
    if "layers" in extra:  # before the highlight boost, which works on the planes in place
        for k, p in enumerate(planes):
            optional[f"layer.{k}.exr"] = encode_layer(p.rgb, p.alpha, p.disparity)
    hl = asdict(scene.options.highlight) if scene.options.highlight is not None else None
    if hl is not None:  # the planes are this call's own fresh arrays: boost in place
        for i, p in enumerate(planes):
            rgb = p.rgb
            if i > 0:  # a cutout's colour is 0 outside its alpha box
                y0, y1, x0, x1 = p.box
                if y1 <= y0 or x1 <= x0:
                    continue
                rgb = rgb[y0:y1, x0:x1]
            boost(rgb, **hl, out=rgb)
    def aif_rows(r0: int, r1: int) -> np.ndarray:  # the composite of the (boosted) planes, mapped back
        rows = layers.aif_rows(r0, r1)
        return rows if hl is None else unboost(rows, **hl, out=rows)

    # Encode the un-blurred members first and drop their arrays (peak memory at large sizes).
    members: dict[str, bytes] = {
        "aif.png": encode_srgb_png_rows(aif_rows, *layers.disparity.shape),
        "depth.exr": encode_depth(layers.disparity),
        "cover.png": encode_alphas(planes[2].alpha, planes[1].alpha),
    }
    if "coc" in extra:
        for n, t in enumerate(scene.targets):
            optional[f"coc.{n}.exr"] = encode_coc(layers.disparity, t.focus, t.max_coc)
    members.update(optional)
    del layers, aif_rows, optional
    linear_light = scene.options.linear_light
    if not linear_light:  # the naive baseline: blur sRGB-encoded values, store them as they are
        planes = [replace(p, rgb=linear_to_srgb(p.rgb)) for p in planes]
    for n, t in enumerate(scene.targets):
        if linear_light and "dual_pixel" in extra:  # the two half-aperture views; the target is their sum
            (left, wl), (right, wr) = halves(scene.aperture)
            views = [_render_target(planes, t, scene, left), _render_target(planes, t, scene, right)]
            img = views[0] * np.float32(wl) + views[1] * np.float32(wr)
            for side, view in zip(("left", "right"), views):
                if hl is not None:
                    unboost(view, **hl, out=view, axis=0)
                members[f"dp.{n}.{side}.png"] = encode_srgb_png_planar(view)
            del views
            if hl is not None:
                unboost(img, **hl, out=img, axis=0)
            members[f"dof.{n}.png"] = encode_srgb_png_planar(img)
        elif linear_light:  # planar (3, H, W): encoded in row blocks, no interleaved frame copy
            img = _render_target(planes, t, scene)
            if hl is not None:
                unboost(img, **hl, out=img, axis=0)
            members[f"dof.{n}.png"] = encode_srgb_png_planar(img)
        else:
            img = render_planes(planes, float(t.focus), float(t.max_coc), scene.aperture, **scene.options.render_kw())
            members[f"dof.{n}.png"] = encode_png8(np.clip(img, 0.0, 1.0))
        del img
    members["json"] = encode_record(sample_record(scene))
    return members


def _render_target(planes, t: Target, scene: Scene, aperture=None):
    """Target t, planar (3, H, W) linear, through `aperture` (default the scene's; a half of it
    for a dual-pixel view); with longitudinal chromatic aberration each channel is the render
    at its own CoC scale (max_coc * chromatic[ch]), three renders instead of one."""
    scales, aperture = scene.options.chromatic, aperture or scene.aperture
    kw = scene.options.render_kw()
    img = render_planes(planes, float(t.focus), float(t.max_coc) * scales[1], aperture, planar=True, **kw)
    for ch in (0, 2):
        if scales[ch] != scales[1]:
            img[ch] = render_planes(planes, float(t.focus), float(t.max_coc) * scales[ch], aperture, planar=True,
                                    **kw)[ch]
    return img


def focus_sweep(scene: Scene, library: AssetLibrary, focuses, max_coc: float | None = None) -> dict[str, bytes]:
    """The members of `scene` re-rendered with one target per focus value (at `max_coc`, by
    default its first target's): `dof.N.png` is focus N. For QA pages (dofsynth.qa)."""
    coc = float(scene.targets[0].max_coc if max_coc is None else max_coc)
    return render_sample(replace(scene, targets=tuple(Target(float(f), coc) for f in focuses)), library)
