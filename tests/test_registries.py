"""The method registry (dofsynth.render.METHODS) and the member table (dofsynth.record.MEMBERS)
own their concepts: a toy method or member registered here, from this file alone, is reached
through the public recipe keys; manifests and records agree on the renderer and the members;
and every option the renderer would not apply is refused by name."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from dofsynth.cli import main
from dofsynth.config import ConfigError
from dofsynth.generate import generate
from dofsynth.manifest import load_manifest
from dofsynth.optics import Disk
from dofsynth.qa import dataset as ds
from dofsynth.qa.verify import verify_dataset
from dofsynth.recipe import recipe_from_text
from dofsynth.record import MEMBERS, Member, decode_sample, register_member
from dofsynth.render import METHODS, Method, Plane, render_planes
from dofsynth.render.layered import render_layered
from dofsynth.render.look import Highlight, Look, render_photo
from dofsynth.shards import read_shard, write_shard

ROOT = Path(__file__).resolve().parents[1]
SMOKE = (ROOT / "recipes" / "smoke.toml").read_text()


def _recipe(tmp_path, render: str = "", name: str = "r", samples: str = "{ train = 2, test = 1 }"):
    text = SMOKE.replace("samples = { train = 6, test = 2 }", f"samples = {samples}")
    text = text.replace('name = "smoke"', f'name = "{name}"').replace("[render]\nlinear_light = true\n",
                                                                        "[render]\nlinear_light = true\n" + render)
    path = tmp_path / f"{name}.toml"
    path.write_text(text)
    return recipe_from_text(text, path, tmp_path)


def _records(out: Path) -> list[dict]:
    m = load_manifest(out)
    recs = []
    for split in m["splits"]:
        for sh in ds.manifest_shards(m, split):
            recs += [json.loads(members["json"]) for _, members in read_shard(out / sh.path)]
    return recs


@pytest.fixture
def toy_method():
    """A method of its own: the layered render, then every channel halved."""
    def render(planes, focus, max_coc, aperture, options):
        return render_layered(planes, focus, max_coc, aperture, options) * np.float32(0.5)

    METHODS["toy"] = Method(render, "toy-v1", ("level_step", "level_ratio"), summary="layered, halved")
    yield "toy"
    del METHODS["toy"]


@pytest.fixture
def toy_member():
    """A member of its own: each target's mean colour as 3 float32 numbers."""
    m = register_member(Member("mean.N.bin", "raw", "float32", "RGB", "linear", "target N's mean colour",
                               option="toy_mean", write=lambda s, n: s.target(n).mean(axis=(1, 2)).astype("<f4").tobytes(),
                               read=lambda data, name: np.frombuffer(data, "<f4")))
    yield m
    del MEMBERS[m.name]


def test_a_method_registered_here_renders_a_set_through_the_recipe_key(tmp_path, toy_method):
    recipe = _recipe(tmp_path, 'method = "toy"\n')
    out = tmp_path / "toy"
    generate(recipe, out, workers=1)
    manifest = load_manifest(out)
    assert manifest["format"]["renderer"] == "toy-v1"
    recs = _records(out)
    assert recs and all(r["renderer"] == "toy-v1" and r["options"]["method"] == "toy" for r in recs)
    assert verify_dataset(out).ok
    # the same scenes rendered by the layered method are twice as bright (in linear light)
    base = tmp_path / "base"
    generate(_recipe(tmp_path, "", name="base"), base, workers=1)
    key = recs[0]["key"]
    split = recs[0]["split"]
    toy_img = ds.read_samples(out, split, [key])[0]["dof"][0]
    base_img = ds.read_samples(base, split, [key])[0]["dof"][0]
    assert toy_img.mean() < base_img.mean() * 0.8


def test_a_member_registered_here_is_written_read_and_verified(tmp_path, toy_member):
    recipe = _recipe(tmp_path, 'members = ["toy_mean"]\n')
    out = tmp_path / "mean"
    generate(recipe, out, workers=1)
    manifest = load_manifest(out)
    assert "mean.N.bin" in [m["name"] for m in manifest["format"]["members"]]
    assert verify_dataset(out).ok
    sample = ds.read_samples(out, "train", ["train-0000000"])[0]
    n = len(sample["record"]["targets"])
    for i in range(n):
        mean = sample["optional"][f"mean.{i}.bin"]
        assert mean.shape == (3,) and np.all(mean > 0)
    # an unknown option is refused by name
    with pytest.raises(ConfigError, match="render.members"):
        _recipe(tmp_path, 'members = ["toy_mean", "nope"]\n')


@pytest.mark.parametrize("method,render", [("layered", ""), ("subaperture", 'method = "subaperture"\ncells = 2\n'),
                                           ("exact", 'method = "exact"\n')])
def test_manifest_format_agrees_with_the_records(tmp_path, method, render):
    members = 'members = ["coc"]\n' if method == "exact" else ""
    out = tmp_path / method
    generate(_recipe(tmp_path, render + members, name=method, samples="{ train = 1, test = 1 }"), out, workers=1)
    manifest = load_manifest(out)
    recs = _records(out)
    assert {r["renderer"] for r in recs} == {manifest["format"]["renderer"]} == {METHODS[method].renderer_id}
    held = {m["name"] for m in manifest["format"]["members"]}
    for r in recs:
        listed = {m.name for m in MEMBERS.values() if m.option is None or m.option in r["options"]["members"]}
        assert listed == held
    assert ("coc.N.exr" in held) == (method == "exact")


def _rewrite_shard(path: Path, drop: str | None = None, cut: str | None = None) -> None:
    samples = []
    for key, members in read_shard(path):
        members = dict(members)
        if drop and drop in members:
            del members[drop]
        if cut and cut in members:
            members[cut] = members[cut][: len(members[cut]) // 2]
        samples.append((key, members))
    write_shard(path, samples)


@pytest.mark.parametrize("damage", ["drop", "cut"])
def test_verify_fails_a_set_with_a_missing_or_truncated_optional_member(tmp_path, damage):
    out = tmp_path / "opt"
    generate(_recipe(tmp_path, 'members = ["coc", "layers"]\n', name="opt", samples="{ train = 2, test = 0 }"),
             out, workers=1)
    assert verify_dataset(out).ok
    shard = next((out / "train").glob("*.tar"))
    _rewrite_shard(shard, **{damage: "layer.1.exr"})
    problems = [str(p) for p in verify_dataset(out).problems]
    assert any("layer.1.exr" in p for p in problems), problems
    # decode_sample names the member too
    key, members = next(iter(read_shard(shard)))
    with pytest.raises(ValueError, match="layer.1.exr"):
        decode_sample(members, key)


@pytest.mark.parametrize("render,key", [
    ("cells = 4\n", "render.cells"),                                   # layered reads no cells
    ('method = "exact"\ncells = 2\n', "render.cells"),
    ("cat_eye = 0.5\n", "render.cat_eye"),
    ('method = "nope"\n', "render.method"),
])
def test_recipes_refuse_options_the_renderer_would_not_apply(tmp_path, render, key):
    with pytest.raises(ConfigError, match=key):
        _recipe(tmp_path, render)
    assert _recipe(tmp_path, 'method = "subaperture"\ncells = 4\ncat_eye = 0.5\n').render.cells == 4


def _naive(tmp_path, extra: str, highlight: bool = True):
    text = SMOKE.replace("[render]\nlinear_light = true\n", "[render]\nlinear_light = false\n" + extra)
    if not highlight:
        text = text.replace("[render.highlight]\nenabled = true", "[render.highlight]\nenabled = false")
    path = tmp_path / "naive.toml"
    path.write_text(text)
    return recipe_from_text(text, path, tmp_path)


def test_the_naive_baseline_refuses_light_options_by_name(tmp_path):
    with pytest.raises(ConfigError, match="render.highlight"):
        _naive(tmp_path, "")
    assert _naive(tmp_path, "", highlight=False).render.linear_light is False
    with pytest.raises(ConfigError, match="render.chromatic"):
        _naive(tmp_path, "chromatic = [1.0, 1.0, 1.2]\n", highlight=False)
    with pytest.raises(ConfigError, match="render.members"):
        _naive(tmp_path, 'members = ["dual_pixel"]\n', highlight=False)


def test_render_planes_and_looks_refuse_options_by_name():
    plane = Plane(np.full((8, 8, 3), 0.5, np.float32), np.ones((8, 8), np.float32), 0.5)
    with pytest.raises(ValueError, match="cells applies to method subaperture"):
        render_planes([plane], 0.5, 2.0, cells=3)
    with pytest.raises(ValueError, match="cat_eye applies to method subaperture or exact"):
        render_planes([plane], 0.5, 2.0, cat_eye=0.5)
    with pytest.raises(ValueError, match="samples applies to method exact"):
        render_planes([plane], 0.5, 2.0, method="subaperture", samples=16)
    with pytest.raises(ValueError, match="method must be one of"):
        render_planes([plane], 0.5, 2.0, method="nope")
    with pytest.raises(ValueError, match="cells"):
        Look(method="exact", cells=2)
    with pytest.raises(ValueError, match="highlight"):
        Look(linear_light=False, highlight=Highlight())
    with pytest.raises(ValueError, match="chromatic"):
        Look(linear_light=False, chromatic=(1.0, 1.0, 1.5))


def test_a_look_round_trips_through_its_record_form():
    for look in (Look(), Look(method="subaperture", cells=3, cat_eye=0.25, chromatic=(0.9, 1.0, 1.1),
                              highlight=Highlight(0.8, 2.0, 3.0)), Look(method="exact", linear_light=False)):
        assert Look.from_dict(json.loads(json.dumps(look.to_dict()))) == look
    assert Look().to_dict() == {"highlight": None, "linear_light": True}  # layered records carry no method keys


def test_render_photo_applies_the_whole_look():
    """The photo render is the boost -> method -> inverse chain: a flat photo stays itself under
    any blur (highlight boost included: the inverse is exact), and chromatic scales blur each
    channel by its own amount."""
    rng = np.random.default_rng(0)
    flat = np.full((24, 24, 3), 0.95, np.float32)
    d = np.full((24, 24), 0.9, np.float32)
    out = render_photo(flat, d, 0.1, 6.0, Disk(), Look(highlight=Highlight()))
    assert np.abs(out - flat).max() < 1e-4
    img = rng.random((32, 32, 3)).astype(np.float32)
    d = np.full((32, 32), 1.0, np.float32)
    plain = render_photo(img, d, 0.0, 3.0, Disk(), Look())
    chroma = render_photo(img, d, 0.0, 3.0, Disk(), Look(chromatic=(0.5, 1.0, 2.0)))
    assert np.array_equal(chroma[..., 1], plain[..., 1])
    assert chroma[..., 0].std() > plain[..., 0].std() > chroma[..., 2].std()  # less blur keeps more contrast


def test_dofsynth_render_refuses_options_its_method_ignores(tmp_path, capsys):
    from dofsynth.io import write_exr, write_png
    img, depth = tmp_path / "p.png", tmp_path / "d.exr"
    write_png(img, np.full((16, 16, 3), 0.5, np.float32))
    write_exr(depth, np.full((16, 16), 0.5, np.float32))
    common = ["render", str(img), "--depth", str(depth), "--focus", "0.5", "--max-coc", "2", "--out",
              str(tmp_path / "o.png")]
    assert main(common + ["--cells", "4"]) == 2
    assert "--cells applies to --method subaperture, not --method layered" in capsys.readouterr().err
    assert main(common + ["--method", "nope"]) == 2
    assert "method must be one of layered, subaperture, adaptive, exact" in capsys.readouterr().err
    assert main(common + ["--method", "subaperture", "--cells", "2"]) == 0


def test_the_docs_method_table_is_the_registry():
    text = (ROOT / "docs" / "rendering.md").read_text()
    for name, m in METHODS.items():
        row = f"| `{name}` | {m.renderer_id} | {', '.join(m.options)} | {m.summary} |"
        assert row in text, row


def test_dual_pixel_views_add_up_to_the_target_which_they_leave_unchanged(tmp_path):
    """With the highlight boost on (the smoke recipe's): wl * L + wr * R = target within 1/255
    (in sRGB codes, after each view is rounded to 8 bits), and the targets are the bytes of
    the same recipe without the member."""
    from dofsynth.color import linear_to_srgb, srgb_to_linear
    from dofsynth.optics import aperture_from_dict
    from dofsynth.render.subaperture import halves

    dp, plain = tmp_path / "dp", tmp_path / "plain"
    generate(_recipe(tmp_path, 'members = ["dual_pixel"]\n', name="dp", samples="{ train = 3, test = 1 }"), dp,
             workers=1)
    generate(_recipe(tmp_path, "", name="plain", samples="{ train = 3, test = 1 }"), plain, workers=1)
    worst, n = 0, 0
    for split in ("train", "test"):
        for a, b in zip(ds.iter_samples(dp, split, decode=False), ds.iter_samples(plain, split, decode=False)):
            ma, mb = a["members"], b["members"]
            rec = json.loads(ma["json"])
            assert rec["options"]["highlight"] is not None
            (_, wl), (_, wr) = halves(aperture_from_dict(rec["aperture"]))
            s = decode_sample(ma, a["key"])
            for i, target in enumerate(s["dof"]):
                assert ma[f"dof.{i}.png"] == mb[f"dof.{i}.png"]
                left, right = (s["optional"][f"dp.{i}.{side}.png"] for side in ("left", "right"))
                total = linear_to_srgb(wl * srgb_to_linear(left) + wr * srgb_to_linear(right))
                worst = max(worst, float(np.abs(np.round(total * 255) - np.round(target * 255)).max()))
                assert not np.array_equal(left, right)      # the views differ: they carry parallax
                n += 1
    assert n == 8 and worst <= 1.0, worst
