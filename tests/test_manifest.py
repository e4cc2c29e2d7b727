"""manifest.json: deterministic bytes, atomic write, load errors, summary, progress file."""
import json
from types import SimpleNamespace

import pytest

from dofsynth.files import canonical_json
from dofsynth.manifest import (ManifestError, build_manifest, load_manifest, manifest_shard_infos, save_summary, summary,
                               write_manifest)
from dofsynth.manifest.progress import append_progress, read_progress, start_progress
from dofsynth.shards import ShardInfo


def _recipe():
    return SimpleNamespace(text="name = 'x'\n", sha256="ab" * 32, path="recipes/x.toml", name="x",
                           samples=SimpleNamespace(count=lambda s: {"train": 5, "test": 2}[s]),
                           render=SimpleNamespace(method="layered", members=()))


def _infos():
    return {"train": [ShardInfo("train", 1, "train-000001.tar", 2, 2, "22" * 32, 300),
                      ShardInfo("train", 0, "train-000000.tar", 0, 2, "11" * 32, 200)],
            "test": [ShardInfo("test", 0, "test-000000.tar", 0, 1, "33" * 32, 100)]}


def test_manifest_content_and_bytes_do_not_depend_on_order(tmp_path):
    m1 = build_manifest(_recipe(), _infos(), limits={"train": 4, "test": None})
    rev = {k: list(reversed(v)) for k, v in reversed(list(_infos().items()))}
    m2 = build_manifest(_recipe(), rev, limits={"test": None, "train": 4})
    assert canonical_json(m1) == canonical_json(m2)
    assert m1["totals"] == {"samples": 5, "shards": 3, "bytes": 600}
    tr = m1["splits"]["train"]
    assert [s["name"] for s in tr["shards"]] == ["train-000000.tar", "train-000001.tar"]
    assert tr["shards"][1]["path"] == "train/train-000001.tar"
    assert (tr["samples"], tr["recipe_samples"], tr["limit"]) == (4, 5, 4)
    assert m1["recipe"] == {"text": "name = 'x'\n", "sha256": "ab" * 32, "path": "recipes/x.toml", "name": "x"}
    path = write_manifest(tmp_path, m1)
    assert path.name == "manifest.json" and sorted(p.name for p in tmp_path.iterdir()) == ["manifest.json"]
    loaded = load_manifest(tmp_path)
    assert loaded == json.loads(json.dumps(m1))
    assert manifest_shard_infos(loaded)["train"] == sorted(_infos()["train"], key=lambda s: s.index)


def test_gap_in_shards_is_refused():
    infos = _infos()
    infos["train"] = infos["train"][:1]  # shard 1 only: samples 0-1 missing
    with pytest.raises(ManifestError, match="starts at sample 2"):
        build_manifest(_recipe(), infos)


def test_load_errors_name_the_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="manifest.json"):
        load_manifest(tmp_path)
    (tmp_path / "manifest.json").write_text("{not json")
    with pytest.raises(ManifestError, match="not valid JSON"):
        load_manifest(tmp_path)
    m = build_manifest(_recipe(), _infos())
    m["schema_version"] = 99
    (tmp_path / "manifest.json").write_bytes(canonical_json(m))
    with pytest.raises(ManifestError, match="schema_version 99"):
        load_manifest(tmp_path / "manifest.json")


def test_summary_is_small_and_saved(tmp_path):
    m = build_manifest(_recipe(), _infos(), extra={"skipped_assets": ["bad.png"]})
    s = summary(m)
    assert "text" not in s["recipe"] and s["recipe"]["sha256"] == "ab" * 32
    assert s["splits"]["train"]["shards"] == 2 and s["skipped_assets"] == ["bad.png"]
    other = build_manifest(_recipe(), {**_infos(), "test": [ShardInfo("test", 0, "test-000000.tar", 0, 1, "44" * 32, 100)]})
    assert summary(other)["splits"]["test"]["shards_sha256"] != s["splits"]["test"]["shards_sha256"]
    path = save_summary(m, tmp_path / "data_manifest" / "datasets" / "x.json")
    assert json.loads(path.read_text()) == s
    with pytest.raises(ValueError, match="must end in .json"):
        save_summary(m, tmp_path / "x.txt")


def test_progress_survives_a_torn_last_line(tmp_path):
    start_progress(tmp_path, {"recipe_sha256": "ab" * 32})
    for info in _infos()["train"]:
        append_progress(tmp_path, info)
    with open(tmp_path / ".progress.jsonl", "ab") as fh:
        fh.write(b'{"shard": {"split": "tr')  # killed mid-append
    header, infos = read_progress(tmp_path)
    assert header == {"recipe_sha256": "ab" * 32}
    assert infos == _infos()["train"]
    assert read_progress(tmp_path / "nothing") == (None, [])


# ---- partial manifests ---------------------------------------------------------------------
from dofsynth.manifest.names import part_name  # noqa: E402
from dofsynth.manifest.parts import build_part, load_part, merge_parts, write_part  # noqa: E402

_PLAN = {"splits": ["train", "test"], "limits": {"train": None, "test": None}, "shards": 4,
         "split_shards": {"train": 3, "test": 1}}


def _all_infos():
    return [ShardInfo("train", 0, "train-000000.tar", 0, 2, "11" * 32, 200),
            ShardInfo("train", 1, "train-000001.tar", 2, 2, "22" * 32, 300),
            ShardInfo("train", 2, "train-000002.tar", 4, 1, "55" * 32, 150),
            ShardInfo("test", 0, "test-000000.tar", 0, 2, "33" * 32, 100)]


def _write_parts(folder, ranges, recipe=None, plan=None):
    infos = _all_infos()
    return [write_part(folder, build_part(recipe or _recipe(), (a, b), plan or _PLAN, infos[a:b],
                                          extra={"skipped_assets": []})) for a, b in ranges]


def test_merged_parts_equal_the_single_run_manifest(tmp_path):
    whole = build_manifest(_recipe(), {"train": _all_infos()[:3], "test": _all_infos()[3:]},
                           limits={"train": None, "test": None}, extra={"skipped_assets": []})
    paths = _write_parts(tmp_path, [(2, 4), (0, 1), (1, 2)])
    assert [p.name for p in paths][0] == part_name(2, 4) == "manifest.part-000002-000004.json"
    assert canonical_json(merge_parts(paths), indent=1) == canonical_json(whole, indent=1)
    assert load_part(paths[0])["range"] == [2, 4]


def test_merge_names_overlaps_gaps_and_mixed_parts(tmp_path):
    a, b, c = (tmp_path / n for n in "abc")
    p01, p04 = _write_parts(a, [(0, 1), (0, 4)])
    p24, = _write_parts(b, [(2, 4)])
    with pytest.raises(ManifestError, match=rf"overlap: .*{p01.name}.*{p04.name}.* shards 0:1 are in both"):
        merge_parts([p04, p01])
    with pytest.raises(ManifestError, match=rf"gap: shards 1:2 of the plan's 4 are in no part \(between {p01}"):
        merge_parts([p24, p01])
    with pytest.raises(ManifestError, match=r"gap: shards 0:2 .*before"):
        merge_parts([p24])
    other = _recipe()
    other.sha256 = "cd" * 32
    q24, = _write_parts(c, [(2, 4)], recipe=other)
    with pytest.raises(ManifestError, match=rf"mixed recipes: {p01}.*sha256 abab.*{q24}.*sha256 cdcd"):
        merge_parts([p01, q24])
    r24, = _write_parts(tmp_path / "d", [(2, 4)], plan={**_PLAN, "limits": {"train": 5, "test": None}})
    with pytest.raises(ManifestError, match=r"mixed parts: .*plan"):
        merge_parts([p01, r24])
    with pytest.raises(ManifestError, match="no partial manifests"):
        merge_parts([])
    (tmp_path / "bad.json").write_text('{"splits": {}}')
    with pytest.raises(ManifestError, match="bad.json: not a dofsynth partial manifest"):
        merge_parts([tmp_path / "bad.json"])
