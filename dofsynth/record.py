"""What a sample is (docs/FORMAT.md): the member table, the JSON record, and `decode_sample`.

`MEMBERS` is the one table of a sample's tar members: each `Member` has its name (`N` stands
for a target's index, `K` for a plane's), codec, dtype, channels, range and meaning, the
`render.members` option that asks for it (None: every sample has it), its writer and its
reader. dofsynth.sample writes what a record asks for from it, `decode_sample` and `verify`
read and check it, and the manifest's `format` and the table in docs/FORMAT.md are made from
it. A new member is one `register_member(Member(...))` (option names are what recipes accept).

The JSON record is the scene's own parameters (`scene.to_dict()`) plus the schema version,
renderer id (dofsynth.render.METHODS) and dofsynth version, encoded canonically (sorted keys,
Python's shortest round-trip float repr), so a sample is the same bytes wherever and whenever
it is rendered. The codecs and their fixed settings are in dofsynth.codecs.
"""
from __future__ import annotations

import json
import math
import re
from dataclasses import dataclass
from importlib import resources
from typing import Any, Callable

import numpy as np

from dofsynth import __version__
from dofsynth.codecs import (DEPTH_CHANNEL, SCHEMA_VERSION, decode_depth, encode_alphas, encode_coc, encode_depth,
                             encode_layer, encode_png8, encode_srgb_png_planar, encode_srgb_png_rows)
from dofsynth.files import canonical_json
from dofsynth.io import decode_exr, decode_image
from dofsynth.render import DEFAULT_METHOD, METHODS

PLANES = 3  # layered planes of a scene: K = 0 background, 1 middle, 2 front


@dataclass(frozen=True)
class Member:
    """One tar member of a sample. `write(sample, i) -> bytes` makes it from a
    `dofsynth.sample.SampleRender` (i: its N or K, None for a member of its own); `read(bytes,
    name)` decodes it (errors name it). `before_blur`: written from the planes before they are
    prepared for the blur (the highlight boost works in place)."""

    name: str
    codec: str
    dtype: str
    channels: str
    range: str
    meaning: str
    option: str | None = None
    write: Callable[[Any, int | None], bytes] | None = None
    read: Callable[[bytes, str], Any] | None = None
    before_blur: bool = False

    @property
    def per(self) -> str:
        """"target" (name holds N), "plane" (K) or "sample"."""
        parts = self.name.split(".")
        return "target" if "N" in parts else "plane" if "K" in parts else "sample"

    def names(self, targets: int) -> list[str]:
        """The member names of a sample with `targets` targets."""
        letter, count = {"target": ("N", targets), "plane": ("K", PLANES), "sample": (None, 1)}[self.per]
        if letter is None:
            return [self.name]
        return [".".join(str(i) if p == letter else p for p in self.name.split(".")) for i in range(count)]

    def matches(self, suffix: str) -> bool:
        pattern = r"\.".join(r"\d+" if p in ("N", "K") else re.escape(p) for p in self.name.split("."))
        return re.fullmatch(pattern, suffix) is not None

    def to_dict(self) -> dict:
        """The manifest's `format.members` row (and docs/FORMAT.md's)."""
        return {"name": self.name, "type": self.codec, "dtype": self.dtype, "channels": self.channels,
                "range": self.range, "meaning": self.meaning, "option": self.option}


MEMBERS: dict[str, Member] = {}


def register_member(m: Member) -> Member:
    """Add a member to the table (its name must be new); returns it."""
    if m.name in MEMBERS:
        raise ValueError(f"member {m.name!r} is already in the table")
    if m.write is None or m.read is None:
        raise ValueError(f"member {m.name!r} needs a writer and a reader")
    MEMBERS[m.name] = m
    return m


def member_of(name: str) -> Member | None:
    """The table's member a tar member name is (its suffix, "KEY." or a path in front allowed)."""
    parts = name.rsplit("/", 1)[-1].split(".")
    return next((m for i in range(len(parts)) for m in MEMBERS.values() if m.matches(".".join(parts[i:]))), None)


def member_options() -> tuple[str, ...]:
    """The names `render.members` accepts: every option of the table, in table order."""
    return tuple(dict.fromkeys(m.option for m in MEMBERS.values() if m.option))


def unknown_options(options) -> list[str]:
    """The `render.members` names in `options` that no member of the table has, sorted."""
    return sorted(set(options) - set(member_options()))


def held_members(options: tuple[str, ...] | list[str]) -> list[Member]:
    """The table's members that a sample with these `render.members` options holds."""
    return [m for m in MEMBERS.values() if m.option is None or m.option in options]


def _png(data: bytes, name: str) -> np.ndarray:
    return decode_image(data, name)[:, :, :3]


def _json(data: bytes, name: str) -> dict:
    try:
        return json.loads(data.decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise SampleDecodeError(f"{name}: not valid JSON ({exc})") from exc


def _target_png(s, n: int) -> bytes:
    img = s.target(n)  # planar (3, H, W): linear light, or the naive render's sRGB codes
    if s.look.linear_light:
        return encode_srgb_png_planar(img)
    return encode_png8(np.ascontiguousarray(np.moveaxis(img, 0, -1)))


for _m in (
    Member("aif.png", "PNG", "uint8", "RGB", "0-255", "all-in-focus image, sRGB-encoded (sRGB chunk)",
           write=lambda s, _: encode_srgb_png_rows(s.aif_rows, *s.disparity.shape), read=_png),
    Member("depth.exr", "EXR", "float32", DEPTH_CHANNEL, "0-1",
           "normalized disparity, 1 = nearest, 0 = infinity (older shards: channel Z)",
           write=lambda s, _: encode_depth(s.disparity), read=decode_depth),
    Member("cover.png", "PNG", "uint8", "RGB", "0-255",
           "coverage of each plane as placed, before blur: R = front, G = middle, B = 0 (not sRGB)",
           write=lambda s, _: encode_alphas(s.planes[2].alpha, s.planes[1].alpha),
           read=lambda d, name: np.ascontiguousarray(decode_image(d, name)[:, :, :2])),
    Member("dof.N.png", "PNG", "uint8", "RGB", "0-255",
           "DoF target N = 0, 1, ..., sRGB-encoded (sRGB chunk); focus and max_coc in targets[N]",
           write=_target_png, read=_png),
    Member("json", "JSON", "utf-8", "-", "-", "the sample record: the scene's parameters, sorted keys",
           write=lambda s, _: encode_record(sample_record(s.scene)), read=_json),
    Member("coc.N.exr", "EXR", "float32", "coc", "px",
           "optional (render.members coc): signed CoC radius of target N, max_coc * (disparity - focus)",
           option="coc", write=lambda s, n: encode_coc(s.disparity, s.scene.targets[n].focus, s.scene.targets[n].max_coc),
           read=lambda d, name: decode_exr(d, name, channels="coc")),
    Member("layer.K.exr", "EXR", "float32", "R, G, B, A, disparity", "linear",
           "optional (render.members layers): plane K = 0 background, 1 middle, 2 front before blur",
           option="layers", write=lambda s, k: encode_layer(s.planes[k].rgb, s.planes[k].alpha, s.planes[k].disparity),
           read=lambda d, name: decode_exr(d, name, channels=None), before_blur=True),
    Member("dp.N.left.png", "PNG", "uint8", "RGB", "0-255",
           "optional (render.members dual_pixel): target N through the left half of the aperture, sRGB; "
           "with the right one it adds up to dof.N.png in linear light (weights: the halves' areas)",
           option="dual_pixel", write=lambda s, n: encode_srgb_png_planar(s.view(n, "left")), read=_png),
    Member("dp.N.right.png", "PNG", "uint8", "RGB", "0-255",
           "optional (render.members dual_pixel): target N through the right half of the aperture, sRGB",
           option="dual_pixel", write=lambda s, n: encode_srgb_png_planar(s.view(n, "right")), read=_png),
):
    register_member(_m)

def members_markdown() -> str:
    """The member table as docs/FORMAT.md shows it (a test keeps the two equal)."""
    rows = ["| member | type | dtype | channels | range | option | meaning |", "|---|---|---|---|---|---|---|"]
    rows += [f"| `KEY.{m.name}` | {m.codec} | {m.dtype} | {m.channels} | {m.range} | {m.option or '-'} | {m.meaning} |"
             for m in MEMBERS.values()]
    return "\n".join(rows) + "\n"


RECORD_SCHEMA_FILE = "record.schema.json"  # the JSON Schema of the record, shipped in the package


def record_schema() -> dict:
    """The JSON Schema (draft 2020-12) of the sample record (dofsynth/record.schema.json)."""
    return json.loads(resources.files("dofsynth").joinpath(RECORD_SCHEMA_FILE).read_text(encoding="utf-8"))


CONVENTIONS = {
    "disparity": "normalized disparity in [0, 1]: 1 = nearest, 0 = infinity",
    "coc": "signed circle-of-confusion radius in px = max_coc * (disparity - focus), > 0 in front of focus",
    "max_coc": "px at the stored size (halve it with the image)",
    "colour": "PNG images are sRGB-encoded; blur and compositing happened in linear light, float32",
    "paths": "shard paths are relative to the data set folder",
}


def format_description(method: str = DEFAULT_METHOD, options: tuple[str, ...] | list[str] = ()) -> dict:
    """What the manifest says about the samples of a set made with render `method` and the
    `render.members` `options`: the members they hold, conventions, record schema, renderer."""
    return {"members": [m.to_dict() for m in held_members(options)], "conventions": CONVENTIONS,
            "record_schema_version": SCHEMA_VERSION, "record_schema": RECORD_SCHEMA_FILE,
            "renderer": METHODS[method].renderer_id}


def exr_handler(key: str, data: bytes):
    """A webdataset decoder handler for the EXR members: `wds.WebDataset(url).decode("rgb",
    exr_handler)` decodes each EXR member with its table reader (depth.exr: (H, W) float32
    disparity of any schema; coc.N.exr: (H, W) float32 px; layer.K.exr: (H, W, 5) float32 R,
    G, B, A, disparity); other EXRs as (H, W, C); None for other members (the next handler's)."""
    if not key.lower().endswith("exr"):
        return None
    name = key.rsplit("/", 1)[-1]
    m = member_of(name)
    return m.read(data, name) if m is not None and m.codec == "EXR" else decode_exr(data, name, channels=None)


class SampleDecodeError(ValueError):
    """A sample whose members cannot be decoded; the message names the member."""


def _plain(obj):
    """JSON-ready copy: numpy scalars/arrays to Python, tuples to lists; NaN/inf refused."""
    if isinstance(obj, dict):
        return {str(k): _plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_plain(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _plain(obj.tolist())
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        f = float(obj)
        if not math.isfinite(f):
            raise ValueError(f"sample record holds a non-finite number {f}")
        return f
    return obj


def encode_record(record: dict) -> bytes:
    """Canonical JSON bytes: sorted keys, compact separators, UTF-8, trailing newline."""
    return canonical_json(_plain(record))


def sample_record(scene) -> dict:
    """The JSON record of a scene: `scene.to_dict()` plus schema/renderer/version stamps."""
    rec = dict(scene.to_dict())
    rec["schema_version"] = SCHEMA_VERSION
    rec["renderer"] = scene.options.look.renderer_id
    rec["dofsynth_version"] = __version__
    return _plain(rec)


def decode_sample(members: dict[str, bytes], key: str | None = None) -> dict:
    """Decode one sample's members (bare suffix keys; a `webdataset` sample's "__key__" and
    other "_"-prefixed entries are used for the key or ignored).

    Returns {"key", "record" (dict), "aif" (H, W, 3) float32 sRGB in [0, 1], "depth" (H, W)
    float32 disparity, "cover" (H, W, 2) float32 front/middle alpha, "dof" [(H, W, 3) float32
    sRGB, ...] in target order, "optional" {name: array} of every optional member the record's
    `options.members` lists (MEMBERS' readers)}. A missing or undecodable member is a
    SampleDecodeError naming it.
    """
    key = key or members.get("__key__") or "<sample>"
    if isinstance(key, bytes):
        key = key.decode()

    def read(name: str):
        if name not in members:
            raise SampleDecodeError(f"{key}: missing member {key}.{name}")
        try:
            return member_of(name).read(members[name], f"{key}.{name}")
        except SampleDecodeError:
            raise
        except ValueError as exc:
            raise SampleDecodeError(str(exc)) from exc

    record = read("json")
    aif, cover, depth = read("aif.png"), read("cover.png"), read("depth.exr")
    dof_ids = sorted(int(s.split(".")[1]) for s in members
                     if s.startswith("dof.") and s.endswith(".png") and s.split(".")[1].isdigit())
    if dof_ids != list(range(len(dof_ids))):
        raise SampleDecodeError(f"{key}: DoF targets must be numbered 0..N-1, found {dof_ids}")
    n_targets = len(record.get("targets", dof_ids))
    if n_targets != len(dof_ids):
        raise SampleDecodeError(f"{key}: record lists {n_targets} targets but {len(dof_ids)} dof.N.png members exist")
    dof = [read(f"dof.{i}.png") for i in dof_ids]
    options = record.get("options", {}).get("members", []) if isinstance(record.get("options"), dict) else []
    unknown = unknown_options(options)
    if unknown:
        raise SampleDecodeError(f"{key}.json: lists members {unknown} that this dofsynth's member table does not "
                                f"know (it knows {list(member_options())})")
    optional = {name: read(name) for m in held_members(options) if m.option for name in m.names(n_targets)}
    images = [("aif.png", aif), ("cover.png", cover)] + [(f"dof.{i}.png", d) for i, d in enumerate(dof)]
    for name, arr in images + list(optional.items()):
        if np.ndim(arr) >= 2 and np.shape(arr)[:2] != depth.shape:
            raise SampleDecodeError(f"{key}.{name}: size {np.shape(arr)[:2]} differs from depth.exr {depth.shape}")
    return {"key": key, "record": record, "aif": aif, "depth": depth, "cover": cover, "dof": dof,
            "optional": optional}
