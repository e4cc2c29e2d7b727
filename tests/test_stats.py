"""`dofsynth stats`: the numbers against an independent recount, the chart on its pixels."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from dofsynth.qa import dataset as ds
from dofsynth.qa import stats
from dofsynth.cli import main
from dofsynth.io import read_image
from dofsynth.qa.draw import BG

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def computed(smoke_set, tmp_path_factory):
    d = tmp_path_factory.mktemp("out")
    png, js, st = stats.write_stats(smoke_set, path=d / "stats.png", json_path=d / "stats.json")
    return png, js, st


@pytest.fixture(scope="module")
def decoded(smoke_set):
    m = ds.load(smoke_set)
    return {s: list(ds.iter_samples(smoke_set, s)) for s in ds.manifest_splits(m)}


def test_counts_equal_the_number_of_samples(computed, decoded):
    _, _, st = computed
    assert set(st["splits"]) == {"train", "test"}
    for split, samples in decoded.items():
        s = st["splits"][split]
        n = len(samples)
        h = s["histograms"]
        assert s["samples"] == n == {"train": 6, "test": 2}[split]
        assert s["size"] == [64, 64]
        for name in ("f0", "f1", "cover_front", "cover_middle"):
            assert h[name]["total"] == sum(h[name]["counts"]) == n
        n_targets = sum(len(x["record"]["targets"]) for x in samples)
        assert h["focus"]["total"] == n_targets == 2 * n
        assert h["coc"]["total"] == sum(h["coc"]["counts"]) == n_targets * 64 * 64
        modes = s["counts"]["background_mode"]
        assert sum(modes.values()) == n
        assert h["b0"]["total"] == h["b1"]["total"] == modes.get("ramp", 0) == sum(s["counts"]["ramp_direction"].values())
        for role, table in s["counts"]["assets"].items():
            assert sum(table.values()) == n, role
        for hist in h.values():
            assert len(hist["edges"]) == len(hist["counts"]) + 1
            assert np.all(np.diff(hist["edges"]) > 0)


def test_histograms_match_an_independent_recount(computed, decoded):
    _, _, st = computed
    for split, samples in decoded.items():
        h = st["splits"][split]["histograms"]
        recs = [x["record"] for x in samples]
        edges = np.linspace(0, 1, stats.UNIT_BINS + 1)
        for name, values in (("f0", [r["front"]["disparity"] for r in recs]),
                             ("f1", [r["middle"]["disparity"] for r in recs]),
                             ("focus", [t["focus"] for r in recs for t in r["targets"]]),
                             ("b0", [r["background"]["b0"] for r in recs if r["background"]["mode"] == "ramp"]),
                             ("cover_middle", [np.mean(x["cover"][:, :, 1] > 0.5) for x in samples])):
            assert h[name]["counts"] == np.histogram(values, edges)[0].tolist(), name
        # CoC over pixels, from the depth map and each target
        radii = np.concatenate([np.abs(np.float32(t["max_coc"]) * (x["depth"] - np.float32(t["focus"]))).ravel()
                                for x in samples for t in x["record"]["targets"]])
        e = np.asarray(h["coc"]["edges"])
        assert e[0] == 0 and e[-1] >= radii.max() and e[-2] <= radii.max()
        assert h["coc"]["counts"] == np.histogram(radii, e)[0].tolist()
        # the range ends near the largest max CoC (radii are at most max_coc)
        max_coc = max(t["max_coc"] for r in recs for t in r["targets"])
        assert e[-1] <= max_coc + 1


def test_json_file_holds_the_same_numbers(computed):
    _, js, st = computed
    assert json.loads(js.read_text()) == json.loads(json.dumps(st))


def test_chart_layout_and_pixels(computed):
    png, _, st = computed
    img = np.round(read_image(png) * 255).astype(np.uint8)
    w, h, rows = stats.chart_layout(2)
    assert img.shape == (h, w, 3) and rows == 3
    bg = np.uint8(BG)
    for si, split in enumerate(st["splits"]):
        for pi, name in enumerate(stats.PANELS):
            x0, y0 = stats.panel_origin(si, pi)
            panel = img[y0:y0 + stats.PANEL_H, x0:x0 + stats.PANEL_W].astype(int)
            title = img[y0 + 6:y0 + 24, x0 + 6:x0 + stats.PANEL_W - 6]
            assert np.any(title != bg, axis=-1).sum() > 40, (split, name)     # a title is written
            colour = stats.BAR if name in st["splits"][split]["histograms"] else stats.BAR_CAT
            bars = np.all(np.abs(panel - np.array(colour)) <= 1, axis=-1)
            assert bars.sum() > 20, (split, name)
        # bar heights follow the counts: the tallest f0 bar reaches the top of the plot area
        pi = stats.PANELS.index("f0")
        x, y, pw, ph = stats.plot_area(*stats.panel_origin(si, pi))
        hist = st["splits"][split]["histograms"]["f0"]
        area = np.all(np.abs(img[y:y + ph, x:x + pw].astype(int) - np.array(stats.BAR)) <= 1, axis=-1)
        cols = area.sum(axis=0)
        nb = len(hist["counts"])
        top = stats._nice_max(max(hist["counts"]))
        for i, c in enumerate(hist["counts"]):
            col = cols[int((i + 0.5) * pw / nb)]
            assert abs(col - round(ph * c / top)) <= 1, (split, i, col, c)


def test_cli_and_errors(smoke_set, tmp_path, capsys):
    out_png, out_json = tmp_path / "s.png", tmp_path / "s.json"
    assert main(["stats", str(smoke_set), "--out", str(out_png), "--json", str(out_json), "--split", "test"]) == 0
    text = capsys.readouterr().out
    assert "test: 2 samples, 4 targets, 16384 target pixels" in text and str(out_png) in text
    st = json.loads(out_json.read_text())
    assert list(st["splits"]) == ["test"]
    w, h, _ = stats.chart_layout(1)
    assert read_image(out_png).shape == (h, w, 3)
    assert main(["stats", str(smoke_set), "--split", "valid"]) == 2
    assert "split 'valid'" in capsys.readouterr().err
    assert main(["stats", str(tmp_path / "nowhere")]) == 2
