"""Recipes: the TOML file that fixes everything a data set is made from.

`load_recipe(path)` reads and validates a recipe into frozen dataclasses that mirror its
tables (`recipe.scene.background.flat_share` is `[scene.background] flat_share`); every key's
default and range lives on its field below, read by the one typed reader (dofsynth.config),
so a problem names the file, the dotted key and what was expected. Relative asset paths are
resolved against the recipe's folder; the value "builtin" selects the built-in assets.
`Recipe.sha256` hashes the file bytes, so a data set records exactly what made it;
`recipe_from_text` rebuilds a recipe from that text. The key table is in docs/recipes.md.
"""
from __future__ import annotations

import dataclasses
import math
import os
from pathlib import Path

from dofsynth.config import ConfigError, Range, error, key, parse_toml, read, read_text, table
from dofsynth.files import sha256_bytes
from dofsynth.shipped import recipe_path
from dofsynth.optics.aperture import APERTURES
from dofsynth.optics.coc import MAX_COC_PER_SIDE
from dofsynth.optics.lens import ThinLens
from dofsynth.record import member_options, unknown_options
from dofsynth.render import DEFAULT_METHOD, METHODS, readers
from dofsynth.render.look import METHOD_FIELDS, Highlight, Look

BUILTIN = "builtin"
dataclass_kw = dataclasses.dataclass(frozen=True, kw_only=True)


MAX_SAMPLES = 10_000_000   # per split: sample keys have 7 digits ("train-0000042")
MAX_SHARDS = 1_000_000     # per split: shard names have 6 digits ("train-000042.tar")


@dataclass_kw
class Samples:
    train: int = key(lo=0, hi=MAX_SAMPLES)
    test: int = key(lo=0, hi=MAX_SAMPLES)

    def count(self, split: str) -> int:
        return {"train": self.train, "test": self.test}[split]


@dataclass_kw
class AssetSources:
    backgrounds: str = key()            # "builtin" or a folder (absolute once loaded)
    foregrounds: str = key()            # "builtin" or a folder: RGBA cutouts, or fg/ + alpha/
    manifests: tuple[str, ...] = key((), toml="manifest")  # pinning manifests (absolute once loaded)
    on_bad_asset: str = key("skip", choices=("skip", "stop"))
    test_share: float = key(0.1, lo=0.0, hi=0.9)    # fraction of assets (per kind) in the test split
    verify: str = key("decode", choices=("decode", "header"))  # decode every file at scan, or lazily
    fg_dir: str = key("fg")                          # the paired layout: photos in foregrounds/<fg_dir> ...
    alpha_dir: str = key("alpha")                    # ... their mattes in foregrounds/<alpha_dir>
    estimate_foreground: bool = key(True)            # paired layout: estimate the colour where 0 < alpha < 1
    estimate_space: str = key("srgb", choices=("srgb", "linear"))  # ... solving I = a F + (1 - a) B in sRGB codes or linear light
    opaque_from: float = key(0.98, lo=0.5, hi=1.0)   # a photo's matte at least this opaque counts as opaque (1)
    max_upscale: float = key(1.0, lo=1.0, hi=64.0)   # most magnification of a background crop or a cutout
    transparent_background: str = key("bad", choices=("bad", "black", "grey", "white"))  # or flatten onto


@dataclass_kw
class BackgroundRules:
    flat_share: float = key(0.3, lo=0.0, hi=1.0)     # probability of a flat background (disparity 0)
    b0: Range = key((0.1, 0.4), lo=0.0, hi=1.0)      # ramp: disparity at the near edge (left / bottom)
    b1: Range = key((0.0, 0.1), lo=0.0, hi=1.0)      # ramp: disparity at the far edge, b1 < b0
    vertical_share: float = key(0.5, lo=0.0, hi=1.0)  # among ramps, probability of "vertical"
    crop: Range = key((0.6, 1.0), lo=0.05, hi=1.0)   # crop side / largest crop of the frame aspect


@dataclass_kw
class ForegroundRules:
    f0: Range = key((0.75, 1.0), lo=0.0, hi=1.0)     # front plane disparity
    f1: Range = key((0.45, 0.75), lo=0.0, hi=1.0)    # middle plane disparity
    min_gap: float = key(0.05, lo=0.0, hi=0.5, lo_open=True)  # f0 >= f1 + gap, f1 >= b_max + gap
    scale: Range = key((0.35, 0.8), lo=0.01, hi=1.0)  # object long side / frame short side
    min_in_frame: float = key(0.6, lo=0.05, hi=1.0)  # least share of each object's bbox in the frame
    min_visible: float = key(0.3, lo=0.0, hi=1.0)    # least share of each object's alpha seen (frame, occlusion)
    flip_share: float = key(0.5, lo=0.0, hi=1.0)     # probability of a horizontal flip (each object, background)


@dataclass_kw
class SceneRules:
    background: BackgroundRules = table(BackgroundRules)
    foreground: ForegroundRules = table(ForegroundRules)


@dataclass_kw
class LensRules:
    enabled: bool = key(False)                       # max_coc from a thin lens per target (dofsynth.optics.lens)
    focal_length_mm: Range = key((35.0, 85.0), lo=1.0, hi=2000.0)  # drawn per target
    f_number: Range = key((1.4, 4.0), lo=0.5, hi=64.0)             # drawn per target
    sensor_width_mm: float = key(36.0, lo=1.0, hi=100.0)
    near_m: float = key(1.0, lo=0.01, hi=1e6)        # distance of disparity 1
    far_m: float = key(0.0, lo=0.0, hi=1e9)          # distance of disparity 0; 0 = infinity


@dataclass_kw
class FocusRules:
    targets_per_scene: int = key(1, lo=1, hi=64)
    plane_share: float = key(0.5, lo=0.0, hi=1.0)    # probability a target focuses exactly on a plane
    min_separation: float = key(0.05, lo=0.0, hi=0.5)  # least disparity between the focus of two targets
    max_coc: Range = key(lo=0.0, hi=512.0)           # max circle-of-confusion radius, px at the output size
    lens: LensRules = table(LensRules)


@dataclass_kw
class ApertureRules:
    kind: str = key("disk")                          # a kind of the aperture registry (APERTURES)
    blades: int = key(6, lo=3, hi=16)                # polygon only
    rotation: Range = key((0.0, 0.0), lo=-360.0, hi=360.0)  # polygon only, degrees, drawn per scene


@dataclass_kw
class HighlightRules:
    enabled: bool = key(True)
    threshold: float = key(Highlight.threshold, lo=0.0, hi=0.999)   # defaults: render.look.Highlight's
    gain: float = key(Highlight.gain, lo=0.0, hi=1000.0)
    power: float = key(Highlight.power, lo=0.0, hi=16.0, lo_open=True)


@dataclass_kw
class RenderRules:
    linear_light: bool = key(True)
    members: tuple[str, ...] = key(())   # optional members per sample: options of dofsynth.record.MEMBERS
    chromatic: tuple[float, ...] = key((1.0, 1.0, 1.0), lo=0.25, hi=4.0)  # CoC scale of R, G, B (longitudinal CA)
    method: str = key(DEFAULT_METHOD)     # a key of dofsynth.render.METHODS
    cells: int = key(3, lo=1, hi=16)     # methods reading cells (subaperture): an n x n grid of aperture cells
    cat_eye: float = key(0.0, lo=0.0, hi=1.0)  # methods reading cat_eye (subaperture, exact): vignetting strength
    aperture: ApertureRules = table(ApertureRules)
    highlight: HighlightRules = table(HighlightRules)


@dataclass_kw
class Recipe:
    name: str = key()
    seed: int = key(lo=0, hi=2**63 - 1)
    size: int = key(lo=16, hi=16384)                  # long side of the output, px
    aspect: float = key(1.0, lo=0.25, hi=4.0)         # width / height
    shard_size: int = key(256, lo=1)
    samples: Samples = table(Samples)
    assets: AssetSources = table(AssetSources)
    scene: SceneRules = table(SceneRules)
    focus: FocusRules = table(FocusRules)
    render: RenderRules = table(RenderRules)
    path: str = dataclasses.field(default="", compare=False)      # the file, as given
    base_dir: str = dataclasses.field(default="", compare=False)  # relative asset paths resolve here
    text: str = dataclasses.field(default="", repr=False)
    sha256: str = ""

    @property
    def frame(self) -> tuple[int, int]:
        """(H, W) of every output image: the long side is `size`, W / H is `aspect`."""
        return frame_size(self.size, self.aspect)


def frame_size(size: int, aspect: float) -> tuple[int, int]:
    if aspect >= 1.0:
        return max(1, round(size / aspect)), size
    return size, max(1, round(size * aspect))


def recipe_look(r: Recipe) -> Look:
    """How the recipe's targets are rendered (its [render] table): the method with the options
    it reads, highlight boost (linear light only), chromatic scales, colour space."""
    rr, hl = r.render, r.render.highlight
    return Look(method=rr.method, cells=rr.cells if "cells" in METHODS[rr.method].options else 1,
                cat_eye=rr.cat_eye, chromatic=tuple(rr.chromatic),
                highlight=Highlight(hl.threshold, hl.gain, hl.power) if hl.enabled and rr.linear_light else None,
                linear_light=rr.linear_light)


def _check_render(r: Recipe, given: dict, file: str) -> None:
    """[render]: a known method and members, and no option that the renderer would not apply
    (`given` is the [render] table as written, to tell a default from a choice)."""
    rr = r.render
    if rr.aperture.kind not in APERTURES:
        raise error(file, "render.aperture.kind", f"one of {list(APERTURES)}", rr.aperture.kind)
    if rr.method not in METHODS:
        raise error(file, "render.method", f"one of {list(METHODS)}", rr.method)
    for f in METHOD_FIELDS:  # a method option given, away from its neutral value, that the method ignores
        if f in given and f not in METHODS[rr.method].options and not (f == "cat_eye" and given[f] == 0):
            raise error(file, f"render.{f}", f"no {f} with method {rr.method} (it applies to method {readers(f)}); "
                        "remove it or choose that method", given[f])
    if len(rr.chromatic) != 3:
        raise error(file, "render.chromatic", "three CoC scales (R, G, B)", list(rr.chromatic))
    if max(rr.chromatic) * r.focus.max_coc[1] > MAX_COC_PER_SIDE * r.size:
        raise error(file, "render.chromatic", f"scales that keep max_coc * scale <= {MAX_COC_PER_SIDE * r.size}",
                    list(rr.chromatic))
    known = member_options()
    if unknown_options(rr.members) or len(set(rr.members)) < len(rr.members):
        raise error(file, "render.members", f"distinct names among {list(known)}", list(rr.members))
    if not rr.linear_light:  # the naive baseline blurs sRGB codes: nothing that is light applies
        hl = given.get("highlight", {})
        naive = [("render.highlight", "enabled = false (the boost is of light)", hl)
                 if hl and hl.get("enabled", True) else None,
                 ("render.chromatic", "[1, 1, 1] (chromatic aberration is of light)", list(rr.chromatic))
                 if tuple(rr.chromatic) != (1.0, 1.0, 1.0) else None,
                 ("render.members", "no dual_pixel (its views are linear-light renders)", list(rr.members))
                 if "dual_pixel" in rr.members else None]
        for dotted, expected, got in filter(None, naive):
            raise error(file, dotted, f"{expected} with render.linear_light = false", got)
    try:
        recipe_look(r)
    except ValueError as exc:
        raise ConfigError(f"{file}: render: {exc}") from None


def _check(r: Recipe, file: str, given_render: dict) -> None:
    """The rules between keys: at least one sample, a renderer that applies every option, a
    ramp that falls, planes in front."""
    if r.samples.train + r.samples.test == 0:
        raise ConfigError(f"{file}: samples: expected at least one sample in train or test, got 0")
    for split in ("train", "test"):
        n = r.samples.count(split)
        if -(-n // r.shard_size) > MAX_SHARDS:
            raise error(file, f"samples.{split}", f"at most shard_size x {MAX_SHARDS} = {r.shard_size * MAX_SHARDS} "
                        f"samples (shard names have 6 digits; raise shard_size)", n)
    _check_render(r, given_render, file)
    fo = r.focus
    if fo.lens.enabled:
        _check_lens(r, file)
    if (fo.targets_per_scene - 1) * fo.min_separation > 0.5:
        raise error(file, "focus.min_separation", f"at most {0.5 / max(fo.targets_per_scene - 1, 1):.3g} for "
                    f"{fo.targets_per_scene} targets per scene (they must fit into half the disparity range)",
                    fo.min_separation)
    if r.focus.max_coc[1] > MAX_COC_PER_SIDE * r.size:
        raise error(file, "focus.max_coc", f"a high end <= {MAX_COC_PER_SIDE * r.size} ({MAX_COC_PER_SIDE} x size)",
                    list(r.focus.max_coc))
    bg, fg = r.scene.background, r.scene.foreground
    if bg.flat_share < 1.0 and not bg.b1[0] < bg.b0[0]:
        raise error(file, "scene.background.b1", f"a range whose low end is below scene.background.b0's low "
                    f"end {bg.b0[0]} (a ramp runs from b0 down to b1 < b0)", list(bg.b1))
    gap = fg.min_gap
    b_max = bg.b0[1] if bg.flat_share < 1.0 else 0.0
    if fg.f1[1] < b_max + gap:
        raise error(file, "scene.foreground.f1", f"a high end >= {b_max + gap:g} (scene.background.b0 high end "
                    f"{b_max:g} + min_gap {gap:g}) so the middle plane can be in front", list(fg.f1))
    if fg.f0[1] < fg.f1[1] + gap:
        raise error(file, "scene.foreground.f0", f"a high end >= {fg.f1[1] + gap:g} (scene.foreground.f1 high "
                    "end + min_gap) so the front plane can be in front", list(fg.f0))


def recipe_lens(r: Recipe, focal_length_mm: float, f_number: float):
    """The ThinLens of a recipe's [focus.lens] with a drawn focal length and f-number."""
    lr = r.focus.lens
    return ThinLens(focal_length_mm, f_number, lr.sensor_width_mm, lr.near_m, lr.far_m or math.inf)


def _check_lens(r: Recipe, file: str) -> None:
    """The lens's largest blur (longest focal length, widest aperture, focus at `near`) must stay
    within focus.max_coc's high end, which the trainer takes as r_max."""
    lr = r.focus.lens
    if lr.far_m and lr.far_m <= lr.near_m:
        raise error(file, "focus.lens.far_m", f"0 (infinity) or more than near_m {lr.near_m}", lr.far_m)
    try:
        worst = recipe_lens(r, lr.focal_length_mm[1], lr.f_number[0]).max_coc(lr.near_m, r.frame[1])
    except ValueError as exc:
        raise error(file, "focus.lens", "a lens that can focus on the scene", str(exc)) from None
    if worst > r.focus.max_coc[1]:
        raise error(file, "focus.max_coc", f"a high end >= {worst:.4g} px, the largest blur [focus.lens] gives "
                    f"(focal length {lr.focal_length_mm[1]:g} mm at f/{lr.f_number[0]:g} focused at {lr.near_m:g} m)",
                    list(r.focus.max_coc))


def _resolve(folder: str, base: Path) -> str:
    return BUILTIN if folder == BUILTIN else str((base / os.path.expanduser(folder)).resolve())


def recipe_from_text(text: str, path_for_messages: str | os.PathLike, base_dir: str | os.PathLike) -> Recipe:
    """Parse and validate recipe TOML text. `path_for_messages` names the file in errors and is
    kept as `Recipe.path`; relative asset paths are resolved against `base_dir`."""
    file = str(path_for_messages)
    base = Path(base_dir).resolve()
    data = parse_toml(text, file)
    r = read(Recipe, data, file)
    _check(r, file, data.get("render", {}))
    a = r.assets
    assets = dataclasses.replace(a, backgrounds=_resolve(a.backgrounds, base), foregrounds=_resolve(a.foregrounds, base),
                                 manifests=tuple(str((base / m).resolve()) for m in a.manifests))
    return dataclasses.replace(r, assets=assets, path=file, base_dir=str(base), text=text,
                               sha256=sha256_bytes(text.encode("utf-8")))


SHIPPED_PREFIX = "shipped:"  # Recipe.path of a recipe loaded by name: "shipped:demo", the same in every install


def load_recipe(path: str | os.PathLike) -> Recipe:
    """Read and validate a recipe file, or the shipped recipe of that name ("demo"; see
    dofsynth.shipped and docs/recipes.md). `Recipe.sha256` is of its bytes. A recipe loaded
    by name keeps the path "shipped:NAME" (what manifests record: never an install's folder)."""
    p = recipe_path(path)
    recipe = recipe_from_text(read_text(p, "recipe file"), str(p), p.resolve().parent)
    return dataclasses.replace(recipe, path=SHIPPED_PREFIX + p.stem) if p != Path(path) else recipe
