"""Recipes: the TOML file that fixes everything a data set is made from.

`load_recipe(path)` reads and validates a recipe into frozen dataclasses. Every problem (a wrong
type, an unknown key, a value out of range) raises `RecipeError` naming the file, the dotted
key and what was expected. Relative asset paths are resolved against the recipe's folder; the
value "builtin" selects the built-in assets. `Recipe.sha256` hashes the file bytes, so a data
set records exactly what made it; `recipe_from_text` rebuilds a recipe from that text.
See docs/recipes.md for every key.
"""
from __future__ import annotations

import hashlib
import os
import tomllib
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

BUILTIN = "builtin"
_REQUIRED = object()


class RecipeError(ValueError):
    """A recipe that cannot be used; the message names the file and the dotted key."""


Range = tuple[float, float]


@dataclass(frozen=True)
class Samples:
    train: int
    test: int

    def count(self, split: str) -> int:
        return {"train": self.train, "test": self.test}[split]


@dataclass(frozen=True)
class AssetSources:
    backgrounds: str          # "builtin" or an absolute folder path
    foregrounds: str          # "builtin" or an absolute folder path
    manifests: tuple[str, ...]  # absolute paths of pinning manifests (may be empty)
    on_bad_asset: str         # "skip" | "stop"
    test_share: float         # fraction of assets (per kind) in the test split
    verify: str               # "decode" (decode every file at scan) | "header" (lazy)


@dataclass(frozen=True)
class BackgroundRules:
    flat_share: float         # probability of a flat background (disparity 0 everywhere)
    b0: Range                 # ramp: disparity at the near edge (left / bottom)
    b1: Range                 # ramp: disparity at the far edge (right / top), b1 < b0
    vertical_share: float     # among ramps, probability of "vertical" (else "horizontal")
    crop: Range               # crop side as a fraction of the largest crop of the frame aspect


@dataclass(frozen=True)
class ForegroundRules:
    f0: Range                 # front plane disparity
    f1: Range                 # middle plane disparity
    min_gap: float            # f0 >= f1 + gap and f1 >= (max background disparity) + gap
    scale: Range              # object long side as a fraction of the frame's short side
    min_in_frame: float       # least share of each object's (bbox) area inside the frame
    flip_share: float         # probability of a horizontal flip (each object, background)


@dataclass(frozen=True)
class FocusRules:
    targets_per_scene: int
    plane_share: float        # probability a target focuses exactly on one of the planes
    max_coc: Range            # max circle-of-confusion radius, px at the output size


@dataclass(frozen=True)
class ApertureRules:
    kind: str                 # "disk" | "polygon"
    blades: int               # polygon only
    rotation: Range           # polygon only, degrees, sampled per scene


@dataclass(frozen=True)
class HighlightRules:
    enabled: bool
    threshold: float
    gain: float
    power: float


@dataclass(frozen=True)
class RenderRules:
    linear_light: bool
    aperture: ApertureRules
    highlight: HighlightRules


@dataclass(frozen=True)
class Recipe:
    name: str
    seed: int
    size: int                 # long side of the output, px
    aspect: float             # width / height
    shard_size: int
    samples: Samples
    assets: AssetSources
    background: BackgroundRules
    foreground: ForegroundRules
    focus: FocusRules
    render: RenderRules
    path: str = field(default="", compare=False)
    base_dir: str = field(default="", compare=False)
    text: str = field(default="", repr=False)
    sha256: str = ""

    @property
    def frame(self) -> tuple[int, int]:
        """(H, W) of every output image: the long side is `size`, W / H is `aspect`."""
        return frame_size(self.size, self.aspect)

    @property
    def height(self) -> int:
        return self.frame[0]

    @property
    def width(self) -> int:
        return self.frame[1]

    def to_dict(self) -> dict[str, Any]:
        """The resolved settings, JSON-ready (lists for tuples), plus path and sha256."""
        d = asdict(self)
        d.pop("text")
        return _jsonable(d)


def frame_size(size: int, aspect: float) -> tuple[int, int]:
    if aspect >= 1.0:
        return max(1, round(size / aspect)), size
    return size, max(1, round(size * aspect))


def _jsonable(x):
    if isinstance(x, dict):
        return {k: _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    return x


# --------------------------------------------------------------------------------- validation
class _Table:
    """One TOML table being read: typed getters, then `finish()` refuses unknown keys."""

    def __init__(self, data: Any, prefix: str, file: str):
        self.file, self.prefix = file, prefix
        if not isinstance(data, dict):
            raise self._error_at(prefix or "<top>", "a table", data)
        self.data, self.used = data, set()

    def _dotted(self, key: str) -> str:
        return f"{self.prefix}.{key}" if self.prefix else key

    def _error_at(self, dotted: str, expected: str, got: Any) -> RecipeError:
        return RecipeError(f"{self.file}: {dotted}: expected {expected}, got {got!r}")

    def error(self, key: str, expected: str, got: Any = None) -> RecipeError:
        got = self.data.get(key) if got is None else got
        return self._error_at(self._dotted(key), expected, got)

    def _raw(self, key: str, default: Any) -> Any:
        self.used.add(key)
        if key not in self.data:
            if default is _REQUIRED:
                raise RecipeError(f"{self.file}: {self._dotted(key)}: missing (required key)")
            return default
        return self.data[key]

    def int(self, key: str, default: Any = _REQUIRED, lo: int | None = None, hi: int | None = None) -> int:
        v = self._raw(key, default)
        want = f"an integer{_bounds(lo, hi)}"
        if isinstance(v, bool) or not isinstance(v, int):
            raise self.error(key, want, v)
        if (lo is not None and v < lo) or (hi is not None and v > hi):
            raise self.error(key, want, v)
        return v

    def float(self, key: str, default: Any = _REQUIRED, lo: float | None = None, hi: float | None = None,
              lo_open: bool = False) -> float:
        v = self._raw(key, default)
        want = f"a number{_bounds(lo, hi, lo_open)}"
        if isinstance(v, bool) or not isinstance(v, (int, float)) or v != v:
            raise self.error(key, want, v)
        v = float(v)
        if lo is not None and (v < lo or (lo_open and v == lo)):
            raise self.error(key, want, v)
        if hi is not None and v > hi:
            raise self.error(key, want, v)
        return v

    def bool(self, key: str, default: Any = _REQUIRED) -> bool:
        v = self._raw(key, default)
        if not isinstance(v, bool):
            raise self.error(key, "true or false", v)
        return v

    def str(self, key: str, default: Any = _REQUIRED, choices: tuple[str, ...] | None = None) -> str:
        v = self._raw(key, default)
        if not isinstance(v, str) or (choices and v not in choices) or (not choices and not v):
            want = "one of " + ", ".join(repr(c) for c in choices) if choices else "a non-empty string"
            raise self.error(key, want, v)
        return v

    def range(self, key: str, default: Any = _REQUIRED, lo: float | None = None, hi: float | None = None,
              lo_open: bool = False) -> Range:
        v = self._raw(key, default)
        want = f"[low, high] with low <= high{_bounds(lo, hi, lo_open, 'both')}"
        if isinstance(v, (int, float)) and not isinstance(v, bool):
            v = [v, v]
        if (not isinstance(v, (list, tuple)) or len(v) != 2
                or any(isinstance(x, bool) or not isinstance(x, (int, float)) or x != x for x in v)):
            raise self.error(key, want, v)
        a, b = float(v[0]), float(v[1])
        bad_lo = lo is not None and (a < lo or (lo_open and a == lo))
        if a > b or bad_lo or (hi is not None and b > hi):
            raise self.error(key, want, list(v))
        return (a, b)

    def table(self, key: str) -> "_Table":
        v = self._raw(key, {})
        if not isinstance(v, dict):
            raise self.error(key, "a table", v)
        return _Table(v, self._dotted(key), self.file)

    def finish(self) -> None:
        unknown = sorted(set(self.data) - self.used)
        if unknown:
            known = ", ".join(sorted(self.used))
            raise RecipeError(f"{self.file}: {self._dotted(unknown[0])}: unknown key (known here: {known})")


def _bounds(lo, hi, lo_open=False, what="") -> str:
    pre = f" ({what}" if what else " ("
    if lo is not None and hi is not None:
        return f"{pre} in {'(' if lo_open else '['}{lo}, {hi}])"
    if lo is not None:
        return f"{pre} {'>' if lo_open else '>='} {lo})"
    if hi is not None:
        return f"{pre} <= {hi})"
    return ""


# every table and its keys; unknown keys are reported before anything else (a typo would
# otherwise surface as a "missing key" elsewhere)
_KEYS: dict[str, tuple[str, ...]] = {
    "": ("name", "seed", "size", "aspect", "shard_size", "samples", "assets", "scene", "focus", "render"),
    "samples": ("train", "test"),
    "assets": ("backgrounds", "foregrounds", "manifest", "on_bad_asset", "test_share", "verify"),
    "scene": ("background", "foreground"),
    "scene.background": ("flat_share", "b0", "b1", "vertical_share", "crop"),
    "scene.foreground": ("f0", "f1", "min_gap", "scale", "min_in_frame", "flip_share"),
    "focus": ("targets_per_scene", "plane_share", "max_coc"),
    "render": ("linear_light", "aperture", "highlight"),
    "render.aperture": ("kind", "blades", "rotation"),
    "render.highlight": ("enabled", "threshold", "gain", "power"),
}


def _check_keys(data: dict, prefix: str, file: str) -> None:
    known = _KEYS[prefix]
    for key in sorted(data):
        dotted = f"{prefix}.{key}" if prefix else key
        if key not in known:
            raise RecipeError(f"{file}: {dotted}: unknown key (known here: {', '.join(known)})")
        if dotted in _KEYS and isinstance(data[key], dict):
            _check_keys(data[key], dotted, file)


def _asset_source(t: _Table, key: str, base_dir: Path) -> str:
    v = t.str(key)
    if v == BUILTIN:
        return BUILTIN
    return str((base_dir / os.path.expanduser(v)).resolve())


def recipe_from_text(text: str, path_for_messages: str | os.PathLike, base_dir: str | os.PathLike) -> Recipe:
    """Parse and validate recipe TOML text. `path_for_messages` names the file in errors and is
    kept as `Recipe.path`; relative asset paths are resolved against `base_dir`."""
    file = str(path_for_messages)
    base = Path(base_dir).resolve()
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise RecipeError(f"{file}: not valid TOML ({exc})") from exc
    _check_keys(data, "", file)
    top = _Table(data, "", file)
    name = top.str("name")
    seed = top.int("seed", lo=0, hi=2**63 - 1)
    size = top.int("size", lo=16, hi=16384)
    aspect = top.float("aspect", 1.0, lo=0.25, hi=4.0)
    shard_size = top.int("shard_size", 256, lo=1)

    st = top.table("samples")
    samples = Samples(train=st.int("train", lo=0), test=st.int("test", lo=0))
    st.finish()
    if samples.train + samples.test == 0:
        raise RecipeError(f"{file}: samples: expected at least one sample in train or test, got 0")

    at = top.table("assets")
    man = at._raw("manifest", [])
    man_list = [man] if isinstance(man, str) else man
    if not isinstance(man_list, list) or not all(isinstance(m, str) and m for m in man_list):
        raise at.error("manifest", "a path or a list of paths to pinning manifests", man)
    assets = AssetSources(
        backgrounds=_asset_source(at, "backgrounds", base),
        foregrounds=_asset_source(at, "foregrounds", base),
        manifests=tuple(str((base / m).resolve()) for m in man_list),
        on_bad_asset=at.str("on_bad_asset", "skip", ("skip", "stop")),
        test_share=at.float("test_share", 0.1, lo=0.0, hi=0.9),
        verify=at.str("verify", "decode", ("decode", "header")),
    )
    at.finish()

    sc = top.table("scene")
    bt = sc.table("background")
    background = BackgroundRules(
        flat_share=bt.float("flat_share", 0.3, lo=0.0, hi=1.0),
        b0=bt.range("b0", [0.1, 0.4], lo=0.0, hi=1.0),
        b1=bt.range("b1", [0.0, 0.1], lo=0.0, hi=1.0),
        vertical_share=bt.float("vertical_share", 0.5, lo=0.0, hi=1.0),
        crop=bt.range("crop", [0.6, 1.0], lo=0.05, hi=1.0, lo_open=False),
    )
    if background.flat_share < 1.0 and not background.b1[0] < background.b0[0]:
        raise bt.error("b1", f"a range whose low end is below scene.background.b0's low end "
                       f"{background.b0[0]} (a ramp runs from b0 down to b1 < b0)", list(background.b1))
    bt.finish()

    ft = sc.table("foreground")
    foreground = ForegroundRules(
        f0=ft.range("f0", [0.75, 1.0], lo=0.0, hi=1.0),
        f1=ft.range("f1", [0.45, 0.75], lo=0.0, hi=1.0),
        min_gap=ft.float("min_gap", 0.05, lo=0.0, hi=0.5, lo_open=True),
        scale=ft.range("scale", [0.35, 0.8], lo=0.01, hi=1.0),
        min_in_frame=ft.float("min_in_frame", 0.6, lo=0.05, hi=1.0),
        flip_share=ft.float("flip_share", 0.5, lo=0.0, hi=1.0),
    )
    gap = foreground.min_gap
    b_max = background.b0[1] if background.flat_share < 1.0 else 0.0
    if foreground.f1[1] < b_max + gap:
        raise ft.error("f1", f"a high end >= {b_max + gap:g} (scene.background.b0 high end "
                       f"{b_max:g} + min_gap {gap:g}) so the middle plane can be in front", list(foreground.f1))
    if foreground.f0[1] < foreground.f1[1] + gap:
        raise ft.error("f0", f"a high end >= {foreground.f1[1] + gap:g} (scene.foreground.f1 high end "
                       f"+ min_gap) so the front plane can be in front", list(foreground.f0))
    ft.finish()
    sc.finish()

    fo = top.table("focus")
    focus = FocusRules(
        targets_per_scene=fo.int("targets_per_scene", 1, lo=1, hi=64),
        plane_share=fo.float("plane_share", 0.5, lo=0.0, hi=1.0),
        max_coc=fo.range("max_coc", lo=0.0, hi=512.0),
    )
    fo.finish()

    rt = top.table("render")
    apt = rt.table("aperture")
    aperture = ApertureRules(
        kind=apt.str("kind", "disk", ("disk", "polygon")),
        blades=apt.int("blades", 6, lo=3, hi=16),
        rotation=apt.range("rotation", [0.0, 0.0], lo=-360.0, hi=360.0),
    )
    apt.finish()
    ht = rt.table("highlight")
    highlight = HighlightRules(
        enabled=ht.bool("enabled", True),
        threshold=ht.float("threshold", 0.9, lo=0.0, hi=0.999),
        gain=ht.float("gain", 4.0, lo=0.0, hi=1000.0),
        power=ht.float("power", 2.0, lo=0.0, hi=16.0, lo_open=True),
    )
    ht.finish()
    render = RenderRules(linear_light=rt.bool("linear_light", True), aperture=aperture, highlight=highlight)
    rt.finish()
    top.finish()

    return Recipe(
        name=name, seed=seed, size=size, aspect=aspect, shard_size=shard_size, samples=samples,
        assets=assets, background=background, foreground=foreground, focus=focus, render=render,
        path=file, base_dir=str(base), text=text,
        sha256=hashlib.sha256(text.encode("utf-8")).hexdigest(),
    )


def load_recipe(path: str | os.PathLike) -> Recipe:
    """Read and validate a recipe file (see docs/recipes.md). `Recipe.sha256` is of its bytes."""
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"{p}: no such recipe file")
    raw = p.read_bytes()
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise RecipeError(f"{p}: not UTF-8 text ({exc})") from exc
    return recipe_from_text(text, str(p), p.resolve().parent)
