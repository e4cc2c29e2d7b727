"""One sample rendered: `render_sample(scene, library)` -> its tar members `{suffix: bytes}`.

Everything comes from the scene (its targets, aperture and options), so a sample can be
re-rendered from its JSON record alone (`verify --deep`, focus sweeps). The members are the
rows of the member table (dofsynth.record.MEMBERS) that the scene's `options.members` asks
for, each made by its writer from a `SampleRender`:
- `dof.N.png`: `restore(render_look(prepare_planes(planes), focus_N, max_coc_N, aperture))`
  (dofsynth.render.look): with a highlight boost, each plane's colour is boosted before the
  blur and the result mapped back by the exact inverse;
- `aif.png`: the same with no blur, `restore(composite(prepare_planes(planes)))`, so a target
  equals it wherever nothing that reaches a pixel is blurred;
- `depth.exr`, `cover.png`: the disparity map and the two coverages;
- with the recipe's `render.members`: `coc.N.exr`, `layer.K.exr` (each plane before blur and
  boost), `dp.N.left.png` / `dp.N.right.png` (the left and right halves of the aperture: a
  dual-pixel pair, rendered and mapped back like the target, then scaled so that their
  area-weighted sum is the target in linear light; `dof.N.png` is the same with or without them).
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from dofsynth.assets import AssetLibrary
from dofsynth.compose import scene_layers
from dofsynth.record import held_members, unknown_options
from dofsynth.render import method_entry
from dofsynth.render.look import prepare_planes, render_look, restore, views_adding_up
from dofsynth.render.planes import validate_planes
from dofsynth.render.subaperture import halves
from dofsynth.scene import Scene, Target


class SampleRender:
    """One scene being rendered: what the member writers read. `planes` (back to front) are
    the composed planes, prepared for the blur in place on first use of `target` / `view` /
    `aif_rows` (before that, as placed: what `before_blur` members see); `disparity` (H, W)
    float32; `target(n)` and `view(n, side)` planar (3, H, W) renders, restored."""

    def __init__(self, scene: Scene, library: AssetLibrary):
        self.scene, self.look = scene, scene.options.look
        self._layers = scene_layers(scene, library)
        self.planes = list(self._layers.planes)
        self.disparity = self._layers.disparity
        self._blur_planes = None
        self._targets: dict[int, np.ndarray] = {}  # target n, restored (kept for its dual-pixel views)
        self._views = None  # (n, (left, right)) of the last dual-pixel target, adding up to it

    def _prepared(self) -> list:
        """The planes the renderer takes (`SceneLayers.blur_planes`: `margin` px past the frame),
        their values checked once for all targets (`validate_planes`), then prepared in place;
        `planes` are views of their frame part, so they are prepared too."""
        if self._blur_planes is None:
            planes = list(self._layers.blur_planes)
            t = self.scene.targets[0] if self.scene.targets else Target(0.0, 0.0)
            validate_planes(planes, t.focus, t.max_coc, use_boxes=method_entry(self.look.method).uses_boxes)
            self._blur_planes = prepare_planes(planes, self.look)
        return self._blur_planes

    def aif_rows(self, r0: int, r1: int) -> np.ndarray:
        """Rows r0:r1 of the all-in-focus composite of the prepared planes, restored (linear)."""
        if self.look.linear_light:
            self._prepared()  # boosted in place: the composite of the boosted planes, mapped back
            return restore(self._layers.aif_rows(r0, r1), self.look, axis=-1)
        return self._layers.aif_rows(r0, r1)  # the naive baseline stores the linear composite

    def _render(self, n: int, aperture=None) -> np.ndarray:
        """Target n's render on the canvas, cut to the frame (3, H, W)."""
        t = self.scene.targets[n]
        m = self._layers.margin
        img = render_look(self._prepared(), t.focus, t.max_coc, aperture or self.scene.aperture, self.look, m,
                          values_checked=True)
        if not m:
            return img
        h, w = self.scene.size
        return img[:, m:m + h, m:m + w]  # a view: the encoders read it row block by row block

    def target(self, n: int) -> np.ndarray:
        """Target n (3, H, W), restored: the same whether dual-pixel views are asked for or not."""
        if n not in self._targets:
            self._targets = {n: restore(self._render(n), self.look)}  # one at a time: memory
        return self._targets[n]

    def view(self, n: int, side: str) -> np.ndarray:
        """Target n through the left or right half of the aperture (3, H, W): the two half
        renders, each mapped back like the target, then made to add up to it exactly
        (`views_adding_up`: wl * left + wr * right = target in linear light)."""
        if self._views is None or self._views[0] != n:
            (left, wl), (right, wr) = halves(self.scene.aperture)
            raw = [restore(self._render(n, half), self.look) for half in (left, right)]
            self._views = (n, views_adding_up(self.target(n), *raw, wl, wr))
        return self._views[1][("left", "right").index(side)]


def render_sample(scene: Scene, library: AssetLibrary) -> dict[str, bytes]:
    """Render one scene to its tar members {suffix: bytes} (see the module docstring)."""
    unknown = unknown_options(scene.options.members)
    if unknown:
        raise ValueError(f"{scene.key}: members {unknown} are not in the member table (dofsynth.record.MEMBERS)")
    s = SampleRender(scene, library)
    held = held_members(scene.options.members)
    n_targets = len(scene.targets)
    out: dict[str, bytes] = {}
    # before-blur members first; then the sample's own and per-plane ones; then target by target
    # (a target's renders are dropped before the next one: peak memory at large sizes)
    order = sorted(held, key=lambda m: (not m.before_blur, m.per == "target"))
    for m in order:
        if m.per != "target":
            for i, name in enumerate(m.names(n_targets)):
                out[name] = m.write(s, i if m.per == "plane" else None)
    per_target = [m for m in order if m.per == "target"]
    for n in range(n_targets):
        for m in per_target:
            out[m.names(n_targets)[n]] = m.write(s, n)
    return out


def focus_sweep(scene: Scene, library: AssetLibrary, focuses, max_coc: float | None = None) -> dict[str, bytes]:
    """The members of `scene` re-rendered with one target per focus value (at `max_coc`, by
    default its first target's): `dof.N.png` is focus N. For QA pages (dofsynth.qa). The planes
    keep the sample's margin past the frame (so its own focus gives its target exactly); a focus
    whose blur reaches further repeats their edges beyond it."""
    coc = float(scene.targets[0].max_coc if max_coc is None else max_coc)
    return render_sample(replace(scene, targets=tuple(Target(float(f), coc) for f in focuses)), library)
