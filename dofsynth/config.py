"""The one typed TOML reader of dofsynth: recipes and training configs are frozen dataclasses
whose fields carry their own default, bounds and choices (`key(...)`), and `read(cls, data,
file)` turns a parsed TOML table into one.

Every problem raises `ConfigError` naming the file, the dotted key and what was expected:
a wrong type, a value out of range, a missing required key, an unknown key or table (unknown
keys are reported first: a typo would otherwise surface as a "missing key" elsewhere). Field
types: bool, int, float, str, `Range` (`[low, high]` floats, a single number meaning
`[x, x]`), `IntRange`, `tuple[int, ...]`, `tuple[float, ...]`, `tuple[str, ...]` (a string or a
list of them) and
nested dataclasses (TOML tables). A field with `toml=False` is not read (set by the loader).
"""
from __future__ import annotations

import dataclasses
import tomllib
import typing
from dataclasses import MISSING, dataclass
from pathlib import Path
from typing import Any

Range = tuple[float, float]
IntRange = tuple[int, int]
_META = "dofsynth"


class ConfigError(ValueError):
    """A config file that cannot be used; the message names the file and the dotted key."""


@dataclass(frozen=True)
class Spec:
    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    choices: tuple[str, ...] | None = None
    toml: str | bool | None = None   # the TOML key if not the field's name; False: not read
    empty: bool = False              # a string that may be "" (its default is: "" means "none")


def key(default: Any = MISSING, *, lo=None, hi=None, lo_open: bool = False, choices=None, toml=None):
    """A dataclass field read from TOML: its default (none: required), the bounds of a number
    (of both ends of a range, of every element of a tuple), the choices of a string, and the
    TOML name when it differs from the field's (`toml=False`: never read)."""
    spec = Spec(lo, hi, lo_open, tuple(choices) if choices is not None else None, toml, default == "")
    return dataclasses.field(default=default, metadata={_META: spec})


def table(cls):
    """A nested TOML table read into dataclass `cls` (every key optional unless its field is)."""
    return dataclasses.field(default_factory=cls, metadata={_META: Spec()})


def error(file: str, dotted: str, expected: str, got: Any) -> ConfigError:
    return ConfigError(f"{file}: {dotted}: expected {expected}, got {got!r}")


def _bounds(s: Spec, what: str = "") -> str:
    """The bounds of a spec as words: " in [0, 10]", " (each > 0)", "" (none)."""
    if s.lo is not None and s.hi is not None:
        text = f"in {'(' if s.lo_open else '['}{s.lo}, {s.hi}]"
    elif s.lo is not None:
        text = f"{'>' if s.lo_open else '>='} {s.lo}"
    elif s.hi is not None:
        text = f"<= {s.hi}"
    else:
        return ""
    return f" ({what} {text})" if what else f" {text}"


def _in_bounds(v: float, s: Spec) -> bool:
    if s.lo is not None and (v < s.lo or (s.lo_open and v == s.lo)):
        return False
    return s.hi is None or v <= s.hi


def _is_int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _is_num(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and v == v


def _value(tp, v, s: Spec, dotted: str, file: str):
    """One TOML value checked against its field type and spec."""
    if tp is bool:
        if not isinstance(v, bool):
            raise error(file, dotted, "true or false", v)
        return v
    if tp is int:
        want = f"an integer{_bounds(s)}"
        if not _is_int(v) or not _in_bounds(v, s):
            raise error(file, dotted, want, v)
        return v
    if tp is float:
        want = f"a number{_bounds(s)}"
        if not _is_num(v) or not _in_bounds(float(v), s):
            raise error(file, dotted, want, float(v) if _is_num(v) else v)
        return float(v)
    if tp is str:
        if not isinstance(v, str) or (s.choices and v not in s.choices) or (not s.choices and not v and not s.empty):
            want = "one of " + ", ".join(repr(c) for c in s.choices) if s.choices else "a non-empty string"
            raise error(file, dotted, want, v)
        return v
    if tp in (Range, IntRange):
        ok = _is_int if tp == IntRange else _is_num
        want = f"[low, high] with low <= high{_bounds(s, 'both')}"
        if ok(v):
            v = [v, v]
        if not isinstance(v, (list, tuple)) or len(v) != 2 or not all(ok(x) for x in v):
            raise error(file, dotted, want, v)
        a, b = (int(x) if tp == IntRange else float(x) for x in v)
        if a > b or not _in_bounds(a, s) or not _in_bounds(b, s):
            raise error(file, dotted, want, list(v))
        return (a, b)
    if tp in (tuple[int, ...], tuple[float, ...]):
        ok, kind = (_is_int, "integers") if tp == tuple[int, ...] else (_is_num, "numbers")
        want = f"a non-empty list of {kind}{_bounds(s, 'each')}"
        if not isinstance(v, (list, tuple)) or not v or not all(ok(x) and _in_bounds(x, s) for x in v):
            raise error(file, dotted, want, v)
        return tuple(v) if tp == tuple[int, ...] else tuple(float(x) for x in v)
    if tp == tuple[str, ...]:
        items = [v] if isinstance(v, str) else v
        if not isinstance(items, list) or not all(isinstance(x, str) and x for x in items):
            raise error(file, dotted, "a string or a list of non-empty strings", v)
        return tuple(items)
    raise TypeError(f"{dotted}: config fields of type {tp} are not supported")


def _fields(cls):
    """(field, spec, TOML name, type) of every field of `cls` read from TOML."""
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        s = f.metadata.get(_META)
        if s is None or s.toml is False:
            continue
        yield f, s, s.toml or f.name, hints[f.name]


def _join(prefix: str, name: str) -> str:
    return f"{prefix}.{name}" if prefix else name


def _check_unknown(cls, data: dict, prefix: str, file: str) -> None:
    known = {name: tp for _, _, name, tp in _fields(cls)}
    for name in sorted(data):
        dotted = _join(prefix, name)
        if name not in known:
            what = "table" if isinstance(data[name], dict) else "key"
            raise ConfigError(f"{file}: {dotted}: unknown {what} (known here: {', '.join(known)})")
        if dataclasses.is_dataclass(known[name]) and isinstance(data[name], dict):
            _check_unknown(known[name], data[name], dotted, file)


def _read(cls, data: Any, prefix: str, file: str):
    if not isinstance(data, dict):
        raise error(file, prefix or "<top>", "a table", data)
    kw = {}
    for f, s, name, tp in _fields(cls):
        dotted = _join(prefix, name)
        if dataclasses.is_dataclass(tp):
            kw[f.name] = _read(tp, data.get(name, {}), dotted, file)
        elif name in data:
            kw[f.name] = _value(tp, data[name], s, dotted, file)
        elif f.default is MISSING and f.default_factory is MISSING:
            raise ConfigError(f"{file}: {dotted}: missing (required key)")
    return cls(**kw)


def read(cls, data: dict, file: str, prefix: str = ""):
    """Dataclass `cls` from a parsed TOML table (see the module docstring)."""
    if isinstance(data, dict):
        _check_unknown(cls, data, prefix, file)
    return _read(cls, data, prefix, file)


def parse_toml(text: str, file: str) -> dict:
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{file}: not valid TOML ({exc})") from exc


def read_text(path: str | Path, what: str) -> str:
    """The UTF-8 text of a config file; FileNotFoundError names a missing one."""
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"{p}: no such {what}")
    try:
        return p.read_bytes().decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{p}: not UTF-8 text ({exc})") from exc


def describe(cls, prefix: str = "") -> list[tuple[str, Any]]:
    """(dotted TOML key, default or MISSING) of every key `read(cls, ...)` accepts."""
    out = []
    for f, _, name, tp in _fields(cls):
        dotted = _join(prefix, name)
        if dataclasses.is_dataclass(tp):
            out += describe(tp, dotted)
        else:
            out.append((dotted, f.default))
    return out


def to_plain(obj) -> Any:
    """A config dataclass as TOML-ready nested dicts (tuples as lists), the read fields only."""
    if dataclasses.is_dataclass(obj):
        return {name: to_plain(getattr(obj, f.name)) for f, _, name, _ in _fields(type(obj))}
    if isinstance(obj, tuple):
        return [to_plain(v) for v in obj]
    return obj
