"""Data sets that every consumer loads: Hugging Face `datasets` (the plain webdataset builder
and the dataset card), plain `webdataset`, the shipped JSON Schema; manifests that do not
depend on where dofsynth is installed."""
from __future__ import annotations

import json
from pathlib import Path

import jsonschema
import numpy as np
import pytest

from dofsynth.generate import generate
from dofsynth.manifest import load_manifest, recipe_from_manifest
from dofsynth.qa import dataset as ds
from dofsynth.recipe import load_recipe, recipe_from_text
from dofsynth.record import MEMBERS, exr_handler, record_schema
from dofsynth.shards import read_shard

datasets = pytest.importorskip("datasets", reason="the test extra installs Hugging Face datasets")
yaml = pytest.importorskip("yaml")
ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def all_members_set(tmp_path_factory) -> Path:
    """The smoke recipe with every optional member."""
    text = (ROOT / "recipes" / "smoke.toml").read_text().replace(
        "[render]\nlinear_light = true\n", '[render]\nlinear_light = true\nmembers = ["coc", "layers", "dual_pixel"]\n')
    folder = tmp_path_factory.mktemp("allm")
    out = folder / "set"
    generate(recipe_from_text(text, folder / "all.toml", folder), out, progress=False)
    return out


def _hf_loads(out: Path):
    a = datasets.load_dataset("webdataset", data_dir=str(out))
    b = datasets.load_dataset(str(out))   # reads the dataset card: its configs and features
    return a, b


@pytest.mark.parametrize("which", ["smoke", "all members"])
def test_hugging_face_datasets_loads_every_member_both_ways(smoke_set, all_members_set, which):
    out = smoke_set if which == "smoke" else all_members_set
    a, b = _hf_loads(out)
    manifest = load_manifest(out)
    card = yaml.safe_load((out / "README.md").read_text().split("---")[1])
    declared = datasets.Features._from_yaml_list(card["dataset_info"]["features"])
    for split, block in manifest["splits"].items():
        assert a[split].num_rows == b[split].num_rows == block["samples"]
        assert a[split].features == b[split].features == declared
        first = read_shard(out / block["shards"][0]["path"])
        key, members = next(first)
        assert set(a[split].column_names) == set(members) | {"__key__", "__url__"}
        row = b[split][0]
        assert row["__key__"].endswith(key)
        assert row["json"] == json.loads(members["json"])
        for name, value in row.items():
            if name.endswith(".png"):
                assert value.size == tuple(row["json"]["size"][::-1])
            elif name.endswith(".exr"):
                assert value == members[name]   # bytes to datasets; exr_handler decodes them
    if which == "all members":
        held = {m["name"] for m in manifest["format"]["members"]}
        assert held == {m.name for m in MEMBERS.values()}


def test_plain_webdataset_decodes_every_member(all_members_set):
    wds = pytest.importorskip("webdataset")
    shards = sorted(str(p) for p in (all_members_set / "train").glob("*.tar"))
    n = 0
    for s in wds.WebDataset(shards, shardshuffle=False).decode("rgb", exr_handler):
        rec = s["json"]
        h, w = rec["size"]
        targets = len(rec["targets"])
        assert s["depth.exr"].shape == (h, w) and s["aif.png"].shape == (h, w, 3)
        for i in range(targets):
            assert s[f"coc.{i}.exr"].shape == (h, w) and s[f"dp.{i}.left.png"].shape == (h, w, 3)
        for k in range(3):
            assert s[f"layer.{k}.exr"].shape == (h, w, 5)
        n += 1
    assert n == load_manifest(all_members_set)["splits"]["train"]["samples"]


def test_every_record_of_the_demo_set_is_valid_against_the_shipped_schema(tmp_path):
    out = tmp_path / "demo"
    generate(load_recipe("demo"), out, workers=2, progress=False)
    schema = record_schema()
    jsonschema.Draft202012Validator.check_schema(schema)
    assert json.loads((out / "record.schema.json").read_text()) == schema   # beside the card
    validator = jsonschema.Draft202012Validator(schema)
    n = 0
    for split in ("train", "test"):
        for sample in ds.iter_samples(out, split, decode=False):
            rec = json.loads(sample["members"]["json"])
            assert not list(validator.iter_errors(rec)), (sample["key"], list(validator.iter_errors(rec))[:3])
            n += 1
    assert n == 64


def test_a_shipped_recipe_is_recorded_by_name_not_by_its_install_folder(tmp_path, monkeypatch):
    """Two installs (two folders holding the same shipped recipes) write the same manifest."""
    import shutil

    import dofsynth.shipped as shipped

    manifests = []
    for install in ("site-a", "site-b"):
        package = tmp_path / install / "dofsynth"
        (package / "recipes").mkdir(parents=True)
        shutil.copy(ROOT / "recipes" / "smoke.toml", package / "recipes" / "smoke.toml")
        monkeypatch.setattr(shipped, "_PACKAGE", package)
        recipe = load_recipe("smoke")
        assert recipe.path == "shipped:smoke"
        out = tmp_path / install / "out"
        generate(recipe, out, progress=False)
        manifests.append((out / "manifest.json").read_bytes())
        assert str(tmp_path) not in manifests[-1].decode()
        again = recipe_from_manifest(load_manifest(out), out)
        assert again.sha256 == recipe.sha256 and again.base_dir == str((package / "recipes").resolve())
    assert manifests[0] == manifests[1]


def test_the_card_and_schema_come_with_a_merged_set(tmp_path, smoke_recipe):
    from dofsynth.generate.merge import merge

    out = tmp_path / "ranges"
    for rng in ((0, 2), (2, 4)):
        generate(smoke_recipe, out, progress=False, shard_range=rng, resume=True)
    merge(sorted(out.glob("manifest.part-*.json")), out / "manifest.json")
    single = tmp_path / "single"
    generate(smoke_recipe, single, progress=False)
    for name in ("README.md", "record.schema.json", "manifest.json"):
        assert (out / name).read_bytes() == (single / name).read_bytes(), name
    assert np.array_equal(*(ds.read_samples(o, "test", ["test-0000000"])[0]["aif"] for o in (out, single)))
