"""The recipes, training configs and docs that ship with dofsynth, found by name.

In a wheel they are package data (dofsynth/recipes/*.toml, dofsynth/docs/*.md, copied there at
build time by setup.py); in a source checkout they are the repository's recipes/ and docs/.
`recipe_path("demo")` is recipes/demo.toml; a path to an existing file is returned as it is, so
every command takes either. A shipped recipe's relative asset paths mean, as for any recipe,
"relative to the recipe file"; `dofsynth recipes copy NAME DIR` makes an editable copy.
"""
from __future__ import annotations

from pathlib import Path

_PACKAGE = Path(__file__).resolve().parent
KINDS = {"recipes": ".toml", "docs": ".md"}


def shipped_dir(kind: str) -> Path:
    """The folder of a kind of shipped file ("recipes" or "docs")."""
    if kind not in KINDS:
        raise ValueError(f"kind must be one of {tuple(KINDS)}, got {kind!r}")
    for folder in (_PACKAGE / kind, _PACKAGE.parent / kind):  # the wheel's, then a checkout's
        if folder.is_dir() and any(folder.glob("*" + KINDS[kind])):
            return folder
    raise FileNotFoundError(f"no shipped {kind} found (looked in {_PACKAGE / kind} and {_PACKAGE.parent / kind})")


def shipped(kind: str) -> dict[str, Path]:
    """{name: path} of the shipped files of a kind, names without their suffix, sorted."""
    return {p.stem: p for p in sorted(shipped_dir(kind).glob("*" + KINDS[kind]))}


def find_shipped(kind: str, name: str) -> Path:
    """A shipped file by name (with or without its suffix); FileNotFoundError lists the names."""
    stem = name[: -len(KINDS[kind])] if name.endswith(KINDS[kind]) else name
    files = shipped(kind)
    if stem not in files:
        raise FileNotFoundError(f"{name}: no such file and no shipped {kind[:-1]} of that name "
                                f"(shipped: {', '.join(files)}; see `dofsynth {kind} list`)")
    return files[stem]


def recipe_path(name_or_path: str | Path) -> Path:
    """An existing file as given, else the shipped recipe or training config of that name."""
    p = Path(name_or_path)
    if p.is_file() or p.parent != Path("."):
        return p  # a path (a missing one is reported by whoever reads it)
    return find_shipped("recipes", str(name_or_path))
