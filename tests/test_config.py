import hashlib
import json
from pathlib import Path

import pytest

from dofsynth.config import ConfigError, to_plain
from dofsynth.recipe import BUILTIN, frame_size, load_recipe, recipe_from_text

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("name,frame,total", [("smoke", (64, 64), 8), ("demo", (512, 512), 64),
                                              ("deeplens-18k", (1024, 1024), 18500)])
def test_shipped_recipes_load(name, frame, total):
    p = ROOT / "recipes" / f"{name}.toml"
    r = load_recipe(p)
    assert r.name == name and r.frame == frame
    assert r.samples.train + r.samples.test == total
    assert r.sha256 == hashlib.sha256(p.read_bytes()).hexdigest()
    assert r.text == p.read_text(encoding="utf-8")
    plain = json.loads(json.dumps(to_plain(r)))  # the read tables, JSON-ready
    assert plain["name"] == name and "text" not in plain and "sha256" not in plain


def test_demo_and_deeplens_settings():
    demo = load_recipe(ROOT / "recipes" / "demo.toml")
    assert (demo.samples.train, demo.samples.test, demo.shard_size) == (56, 8, 16)
    assert demo.focus.targets_per_scene == 2 and demo.focus.max_coc == (8.0, 16.0)
    assert demo.assets.backgrounds == BUILTIN and demo.assets.foregrounds == BUILTIN
    deep = load_recipe(ROOT / "recipes" / "deeplens-18k.toml")
    assert (deep.samples.train, deep.samples.test, deep.size) == (18000, 500, 1024)
    assert deep.focus.max_coc == (32.0, 32.0)
    assert deep.assets.backgrounds == str((ROOT / "recipes" / "assets" / "bg").resolve())
    assert deep.assets.verify == "header"


def test_recipe_from_text_rebuilds_the_same_recipe():
    p = ROOT / "recipes" / "demo.toml"
    a = load_recipe(p)
    b = recipe_from_text(a.text, "manifest.json#recipe", p.parent)
    assert a == b and a.assets == b.assets
    assert b.path == "manifest.json#recipe"


def test_relative_paths_resolve_against_the_recipe_folder(write_recipe, tmp_path):
    p = write_recipe(backgrounds="bgs", foregrounds="../elsewhere/fg", manifest="pins/x.json")
    r = load_recipe(p)
    assert r.assets.backgrounds == str((tmp_path / "bgs").resolve())
    assert r.assets.foregrounds == str((tmp_path.parent / "elsewhere" / "fg").resolve())
    assert r.assets.manifests == (str((tmp_path / "pins" / "x.json").resolve()),)


@pytest.mark.parametrize("size,aspect,frame", [(96, 1.0, (96, 96)), (96, 1.5, (64, 96)), (96, 0.5, (96, 48))])
def test_frame_from_size_and_aspect(size, aspect, frame):
    assert frame_size(size, aspect) == frame


def _error(write_recipe, **replace) -> str:
    p = write_recipe(replace=replace)
    with pytest.raises(ConfigError) as exc:
        load_recipe(p)
    msg = str(exc.value)
    assert str(p) in msg, msg
    return msg


def test_wrong_type_names_file_and_key(write_recipe):
    msg = _error(write_recipe, **{"seed = 11": 'seed = "eleven"'})
    assert "seed" in msg and "integer" in msg
    msg = _error(write_recipe, **{"flat_share = 0.3": "flat_share = true"})
    assert "scene.background.flat_share" in msg and "number" in msg
    msg = _error(write_recipe, **{"size = 64": "size = 64.0"})
    assert "size" in msg


def test_unknown_key_names_file_and_dotted_key(write_recipe):
    msg = _error(write_recipe, **{"flat_share = 0.3": "flat_share = 0.3\nramp_share = 0.7"})
    assert "scene.background.ramp_share" in msg and "unknown key" in msg
    msg = _error(write_recipe, **{"[focus]": "[focuss]"})
    assert "focuss" in msg and "unknown table" in msg


def test_out_of_range_names_file_and_key(write_recipe):
    msg = _error(write_recipe, **{"test_share = 0.25": "test_share = 1.5"})
    assert "assets.test_share" in msg and "[0.0, 0.9]" in msg
    msg = _error(write_recipe, **{"max_coc = [2.0, 4.0]": "max_coc = [4.0, 2.0]"})
    assert "focus.max_coc" in msg and "low <= high" in msg
    msg = _error(write_recipe, **{'on_bad_asset = "skip"': 'on_bad_asset = "ignore"'})
    assert "assets.on_bad_asset" in msg and "'skip'" in msg
    msg = _error(write_recipe, **{"min_gap = 0.05": "min_gap = 0.0"})
    assert "scene.foreground.min_gap" in msg


def test_impossible_depth_rules_are_refused(write_recipe):
    msg = _error(write_recipe, **{"f1 = [0.5, 0.75]": "f1 = [0.3, 0.4]"})  # b0 up to 0.4 + gap
    assert "scene.foreground.f1" in msg
    msg = _error(write_recipe, **{"f0 = [0.8, 1.0]": "f0 = [0.7, 0.78]"})
    assert "scene.foreground.f0" in msg
    msg = _error(write_recipe, **{"b1 = [0.0, 0.1]": "b1 = [0.2, 0.3]"})
    assert "scene.background.b1" in msg


def test_missing_required_and_bad_toml(write_recipe, tmp_path):
    msg = _error(write_recipe, **{"seed = 11\n": ""})
    assert "seed" in msg and "missing" in msg
    bad = tmp_path / "bad.toml"
    bad.write_text("name = [", encoding="utf-8")
    with pytest.raises(ConfigError, match="bad.toml.*not valid TOML"):
        load_recipe(bad)
    with pytest.raises(FileNotFoundError, match="nope.toml"):
        load_recipe(tmp_path / "nope.toml")


def test_recipe_is_frozen(smoke_recipe):
    with pytest.raises(Exception):
        smoke_recipe.seed = 3  # type: ignore[misc]


def _doc_table(path: Path) -> dict[str, str]:
    """{key: default cell} of the `| key | type / range | default | meaning |` table of a doc."""
    rows, inside = {}, False
    for line in path.read_text(encoding="utf-8").splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if cells[:3] == ["key", "type / range", "default"]:
            inside = True
        elif inside and line.startswith("|") and not set(cells[0]) <= set("-: "):
            rows[cells[0].strip("`")] = cells[2]
        elif inside and not line.startswith("|"):
            break
    return rows


def test_the_docs_key_table_is_the_recipe_fields():
    """docs/recipes.md lists every key the reader accepts, with the default on its field."""
    import tomllib
    from dataclasses import MISSING

    from dofsynth.config import describe
    from dofsynth.recipe import Recipe

    table = _doc_table(ROOT / "docs" / "recipes.md")
    fields = dict(describe(Recipe))
    assert list(table) == list(fields)
    for k, default in fields.items():
        cell = table[k]
        if default is MISSING:
            assert cell == "*required*", k
        else:
            doc = tomllib.loads(f"v = {cell}")["v"]
            assert doc == (list(default) if isinstance(default, tuple) else default), (k, cell, default)


def test_a_training_config_with_any_string_round_trips_through_its_toml():
    """A path may hold a quote, a backslash or a newline: the written config.toml stays valid."""
    import dataclasses
    import tomllib

    from dofsynth.train.config import from_dict, load, to_toml

    cfg = load("train-tiny")
    odd = dataclasses.replace(cfg, depth=dataclasses.replace(cfg.depth, mattes='we"ird\\folder\nname', rgbd="tab\there"))
    assert from_dict(tomllib.loads(to_toml(odd)), "config.toml") == odd
