"""Contact sheets and the HTML page, checked on their pixels against a real smoke data set."""
from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from dofsynth.image import resize, to_rgb8
from dofsynth.manifest import recipe_from_manifest
from dofsynth.qa import dataset as ds
from dofsynth.qa import draw, html, sheets
from dofsynth.scene import Scene
from dofsynth.cli import main
from dofsynth.io import decode_image, read_image
from dofsynth.record import decode_sample

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def sheet4(smoke_set, tmp_path_factory):
    """A 4-row sheet of the train split: (image, layout, samples)."""
    path = sheets.write_sheet(smoke_set, split="train", n=4, seed=5, path=tmp_path_factory.mktemp("s") / "s.png")
    img = np.round(read_image(path) * 255).astype(np.uint8)
    keys = sheets.choose_keys(ds.load(smoke_set), "train", 4, 5)
    samples = ds.read_samples(smoke_set, "train", keys)
    lay = sheets.sheet_layout(4, 2, (64, 64), 192)
    return img, lay, samples


def _crop(img, box):
    x, y, w, h = box
    return img[y:y + h, x:x + w]


def _ink(region) -> int:
    """Pixels that differ from the sheet background."""
    return int(np.any(region != np.uint8(draw.BG), axis=-1).sum())


def test_sheet_size_follows_the_layout(sheet4):
    img, lay, _ = sheet4
    assert lay.thumb_h == 192 and lay.thumb_w == 192      # 64x64 samples, 192 px tiles
    assert img.shape == (lay.header_h + 4 * lay.row_h, lay.width, 3) == (lay.height, lay.width, 3)
    assert lay.columns[3:] == ["DoF target 0", "DoF target 1"]


def test_tiles_show_the_sample_pixels(sheet4):
    img, lay, samples = sheet4
    for row, s in enumerate(samples):
        aif = _crop(img, lay.tile(row, 0)).astype(int)
        want = resize(to_rgb8(s["aif"]), 192, 192).astype(int)
        assert np.abs(aif - want).max() <= 1 and aif.std() > 5
        for i, dof in enumerate(s["dof"]):
            tile = _crop(img, lay.tile(row, 3 + i)).astype(int)
            assert np.abs(tile - resize(to_rgb8(dof), 192, 192).astype(int)).max() <= 1


def test_disparity_tile_follows_the_colour_map(sheet4):
    img, lay, samples = sheet4
    lut = draw.colorize_disparity(np.arange(256, dtype=np.float32)[None, :] / 255.0)[0].astype(int)
    ref = cv2.applyColorMap(np.arange(256, dtype=np.uint8)[None], cv2.COLORMAP_TURBO)[0, :, ::-1]
    np.testing.assert_array_equal(lut, ref)           # OpenCV's TURBO, in RGB order
    assert lut[255, 0] > 2 * lut[255, 2] and lut[0, 2] > lut[0, 0]   # near red, far blue-violet
    for row, s in enumerate(samples):
        tile = _crop(img, lay.tile(row, 1)).astype(int)
        # each pixel is the colour-map entry of the (nearest) disparity under it
        ys = (np.arange(192) * 64) // 192
        d = s["depth"][np.ix_(ys, ys)]
        want = lut[np.floor(np.clip(d, 0, 1) * 255 + 0.5).astype(int)]
        assert np.abs(tile - want).max() <= 1
        # the scale bar runs from the colour of 1 at the top to the colour of 0 at the bottom
        bar = _crop(img, lay.bar(row)).astype(int)
        assert np.abs(bar[0, 5] - lut[255]).max() <= 1 and np.abs(bar[-1, 5] - lut[0]).max() <= 1
        mid = bar[bar.shape[0] // 2, 5]
        assert np.abs(lut - mid).max(axis=1).min() <= 1
        # the tick labels right of the bar are drawn
        x, y, w, h = lay.bar(row)
        assert _ink(img[y:y + h, x + w + 4:x + w + lay.tick_w]) > 30


def test_coverage_tile_tints_front_red_and_middle_green(sheet4):
    img, lay, samples = sheet4
    seen_front = seen_middle = False
    for row, s in enumerate(samples):
        tile = _crop(img, lay.tile(row, 2)).astype(int)
        cov = resize(s["cover"].astype(np.float32), 192, 192)
        front = cov[:, :, 0] > 0.95
        middle = (cov[:, :, 1] > 0.95) & (cov[:, :, 0] < 0.05)
        if front.sum() > 50:
            seen_front = True
            assert np.median(tile[front][:, 0] - tile[front][:, 1]) > 40   # red over green
        if middle.sum() > 50:
            seen_middle = True
            assert np.median(tile[middle][:, 1] - tile[middle][:, 0]) > 40  # green over red
    assert seen_front and seen_middle


def test_labels_header_and_captions_have_text(sheet4):
    img, lay, samples = sheet4
    assert all(_ink(img[20:lay.header_h, x:x + w]) > 40 for x, w in zip(lay.column_x, lay.column_widths))
    for row in range(4):
        assert _ink(_crop(img, lay.caption(row))) > 100
        for col in range(len(lay.columns)):
            assert _ink(_crop(img, lay.label(row, col))) > 30
        # nothing is drawn in the gaps between tiles (labels never spill over)
        x, y, w, h = lay.tile(row, 0)
        gap_x = lay.column_x[2] + lay.column_widths[2]
        assert _ink(img[y:y + h + lay.label_h, gap_x + 1:gap_x + lay.pad - 1]) == 0
    labels = sheets.tile_labels(samples[0])
    t = samples[0]["record"]["targets"]
    assert labels[3] == f"focus {t[0]['focus']:.2f}  max CoC {t[0]['max_coc']:.1f}px"


def test_sample_choice_is_deterministic(smoke_set):
    m = ds.load(smoke_set)
    a = sheets.choose_keys(m, "train", 3, 1)
    assert a == sheets.choose_keys(m, "train", 3, 1) and a == sorted(a) and len(set(a)) == 3
    assert len({tuple(sheets.choose_keys(m, "train", 3, s)) for s in range(6)}) > 1
    assert sheets.choose_keys(m, "test", 24, 0) == ["test-0000000", "test-0000001"]
    with pytest.raises(ValueError, match="split 'valid'"):
        sheets.choose_keys(m, "valid", 3, 0)


def test_default_path_and_cli(smoke_set, tmp_path, capsys):
    own = tmp_path / "set"
    shutil.copytree(smoke_set, own)                       # the shared set stays untouched
    p = sheets.write_sheet(own)                       # the test split, into the data set folder
    assert p == own / "sheet-test.png"
    lay = sheets.sheet_layout(2, 2, (64, 64), 192)
    assert read_image(p).shape == (lay.height, lay.width, 3)
    out = tmp_path / "cli.png"
    assert main(["sheet", str(smoke_set), "--split", "train", "--n", "2", "--thumb", "96", "--png", str(out)]) == 0
    assert capsys.readouterr().out.strip() == str(out)
    lay = sheets.sheet_layout(2, 2, (64, 64), 96)
    assert read_image(out).shape == (lay.header_h + 2 * lay.row_h, lay.width, 3)
    with pytest.raises(SystemExit) as exc:                # argparse refuses it: status 2
        main(["sheet", str(smoke_set), "--n", "0"])
    assert exc.value.code == 2 and "--n" in capsys.readouterr().err
    assert main(["sheet", str(tmp_path / "nowhere")]) == 2


def page_data(page) -> dict:
    """The samples a QA page embeds (its JSON script)."""
    text = page.read_text(encoding="utf-8")
    m = re.search(r'<script type="application/json" id="dofsynth-data">(.*?)</script>', text, re.S)
    return json.loads(m.group(1))


def test_html_page_holds_thumbnails_full_size_images_and_sweeps(smoke_set, tmp_path):
    page = html.write_html(smoke_set, tmp_path / "html", split="train", n=3, seed=2, sweep=1, sweep_steps=4, thumb=48)
    data = page_data(page)
    keys = sheets.choose_keys(ds.load(smoke_set), "train", 3, 2)
    assert [s["key"] for s in data["samples"]] == keys and data["total"] == {"train": 6}
    for s in data["samples"]:
        key, im = s["key"], s["images"]
        sample = decode_sample(ds.read_members_many(smoke_set, "train", [key])[key], key)
        # the full-size images are WebP previews (quality 90) of the shard's members, close
        # to them; the thumbnails are JPEGs `thumb` px high
        for preview, member in ((im["aif"], sample["aif"]), (im["targets"][1], sample["dof"][1])):
            full = read_image(page.parent / preview["src"])
            assert preview["src"].endswith(".webp") and full.shape == member.shape
            assert np.abs(full - member).mean() < 6 / 255   # 64 px noise textures: the worst case for WebP
        for v in [im["aif"], im["disparity"], im["coverage"], *im["targets"]]:
            t = read_image(page.parent / v["thumb"])
            assert v["thumb"].endswith(".t.jpg") and t.shape[0] == 48
        assert read_image(page.parent / im["disparity"]["src"]).shape == (64, 64, 3)
        assert s["shard"].startswith("train/") and len(s["shard_sha256"]) == 64 and s["mark"] == ""
        assert s["focus"] == [t["focus"] for t in s["record"]["targets"]] and s["mode"] in html.background_mode(s["record"])
    sweep = data["samples"][0]["images"]["sweep"]
    assert [f["focus"] for f in sweep] == pytest.approx([0, 1 / 3, 2 / 3, 1]) and "sweep" not in data["samples"][1]["images"]
    frames = [read_image(page.parent / f["src"]) for f in sweep]
    assert all(f.shape == (64, 64, 3) for f in frames)
    assert max(np.abs(frames[0] - f).max() for f in frames[1:]) > 0.05   # focus changes the image
    every = page_data(html.write_html(smoke_set, tmp_path / "all", split="all", n=2, sweep=0))
    assert sorted({s["split"] for s in every["samples"]}) == ["test", "train"] and len(every["samples"]) == 4


def test_focus_sweep_at_a_target_focus_is_that_target(smoke_set):
    """Re-rendering a record at its own target's focus gives the stored DoF image exactly."""
    from dofsynth.assets import build_library

    m = ds.load(smoke_set)
    recipe = recipe_from_manifest(m, smoke_set)
    library = build_library(recipe)
    key = ds.split_keys(m, "test")[1]
    members = ds.read_members_many(smoke_set, "test", [key])[key]
    s = decode_sample(members, key)
    t0 = s["record"]["targets"][0]
    frames = sheets.sweep_images(Scene.from_dict(s["record"]), library, [t0["focus"], 0.0])
    want = np.round(decode_image(members["dof.0.png"]) * 255).astype(np.uint8)
    np.testing.assert_array_equal(frames[0], want)


def test_reader_picks_exactly_the_asked_samples(smoke_set):
    """dataset.read_members_many (used by the sheet) returns what a full shard read returns."""
    everything = {s["key"]: s["members"] for s in ds.iter_samples(smoke_set, "train", decode=False)}
    keys = ["train-0000005", "train-0000000", "train-0000003"]
    got = ds.read_members_many(smoke_set, "train", keys)
    assert list(got) == keys
    assert all(got[k] == everything[k] for k in keys)
    assert set(got[keys[0]]) == {"json", "aif.png", "depth.exr", "cover.png", "dof.0.png", "dof.1.png"}
    with pytest.raises(ValueError, match="train-0000042"):
        ds.read_members_many(smoke_set, "train", ["train-0000042"])


def test_a_set_with_dual_pixel_views_shows_them_beside_the_targets(tmp_path):
    """render.members dual_pixel and cat-eye: the sheet has two more columns, target 0 through
    the left and the right half of the aperture, and the labels name the method's options."""
    text = (ROOT / "recipes" / "smoke.toml").read_text()
    text = re.sub(r"(?m)^\[render\]$", '[render]\nmethod = "subaperture"\ncells = 2\ncat_eye = 0.5\n'
                  'members = ["dual_pixel"]', text)
    recipe = tmp_path / "dp.toml"
    recipe.write_text(text)
    out = tmp_path / "set"
    assert main(["generate", str(recipe), "--out", str(out), "-q", "--limit", "2", "--split", "train"]) == 0
    path = sheets.write_sheet(out, split="train", n=2, path=tmp_path / "s.png")
    img = np.round(read_image(path) * 255).astype(np.uint8)
    samples = ds.read_samples(out, "train", sheets.choose_keys(ds.load(out), "train", 2, 0))
    lay = sheets.sheet_layout(2, 2, (64, 64), 192, n_views=2)
    assert img.shape == (lay.height, lay.width, 3) and lay.columns[-2:] == sheets.VIEW_COLUMNS
    for row, s in enumerate(samples):
        for i, name in enumerate(sheets.VIEW_MEMBERS):
            tile = _crop(img, lay.tile(row, 5 + i)).astype(int)
            assert np.abs(tile - resize(to_rgb8(s["optional"][name]), 192, 192).astype(int)).max() <= 1
    assert "cat_eye 0.5" in sheets.tile_labels(samples[0])[3]
