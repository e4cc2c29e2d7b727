"""`dofsynth render`: a real photo with a synthetic depth ramp, file errors, --help, the model hook."""
import sys
import types
from pathlib import Path

import numpy as np
import pytest

from dofsynth.cli import main
from dofsynth.color import srgb_to_linear
from dofsynth.io import encode_png, read_exr, read_image, write_exr, write_png



@pytest.fixture
def photo(shared_assets) -> Path:
    return shared_assets / "bg" / "kodak_kodim08.png"


def sharpness(img, cols):
    g = img[:, cols].mean(axis=2)
    return float(np.abs(np.diff(g, axis=0)).mean() + np.abs(np.diff(g, axis=1)).mean())


def photo_size(photo):
    img = read_image(photo)
    return img.shape[0], img.shape[1]


def test_renders_a_real_photo_with_a_ramp(tmp_path, photo):
    h, w = photo_size(photo)
    ramp = np.tile(np.linspace(1.0, 0.0, w, dtype=np.float32), (h, 1))  # near left, far right
    write_exr(tmp_path / "d.exr", ramp)
    out = tmp_path / "o" / "dof.png"
    rc = main(["render", str(photo), "--depth", str(tmp_path / "d.exr"), "--focus", "1.0", "--max-coc", "8",
               "--out", str(out)])
    assert rc == 0 and out.is_file()
    src, res = read_image(photo), read_image(out)
    assert res.shape == (h, w, 3)
    right = slice(w - 120, w - 8)
    # In focus at the left end (unchanged to 8-bit rounding where the CoC is 0.02 px), the blur
    # growing from there, strongly blurred at the right.
    diff = np.abs(res - src)
    assert diff[:, :2].max() <= 1.0 / 255
    bands = [diff[:, a:b].mean() for a, b in ((0, 8), (8, 20), (20, 40), (40, 80))]
    assert all(x < y for x, y in zip(bands, bands[1:])) and bands[0] < 0.5 / 255
    assert sharpness(res, right) < 0.5 * sharpness(src, right)
    lin = lambda x: srgb_to_linear(x[:, right]).mean()  # noqa: E731  blur in linear light keeps it
    assert abs(lin(res) - lin(src)) < 0.01


def test_png_depth_focus_at_polygon_highlight_exr(tmp_path, capsys, photo):
    h, w = photo_size(photo)
    d16 = np.tile(np.linspace(0, 65535, h).astype(np.uint16)[:, None], (1, w))
    (tmp_path / "d.png").write_bytes(encode_png(d16))
    out = tmp_path / "dof.exr"
    y = h // 2
    rc = main(["render", str(photo), "--depth", str(tmp_path / "d.png"), "--focus-at", f"10,{y}",
               "--max-coc", "6", "--aperture", "polygon:6:15", "--highlight", "--out", str(out)])
    assert rc == 0
    expect = np.uint16(np.linspace(0, 65535, h)[y]) / 65535  # median of a window on a vertical ramp
    assert f"focus {expect:.4f}" in capsys.readouterr().out
    rgb = read_exr(out, channels=None)
    assert rgb.shape == (h, w, 3) and rgb.dtype == np.float32 and rgb.max() > 1.0  # boosted


def run_err(argv, capsys):
    rc = main(["render"] + argv)
    return rc, capsys.readouterr().err


def test_errors_name_the_file(tmp_path, capsys, photo):
    h, w = photo_size(photo)
    write_exr(tmp_path / "small.exr", np.zeros((h // 2, w), np.float32))
    write_exr(tmp_path / "bad.exr", np.full((h, w), 2.0, np.float32))
    write_png(tmp_path / "grey.png", np.zeros((h, w), np.float32))
    (tmp_path / "junk.png").write_bytes(b"not an image")
    base = ["--focus", "0.5", "--max-coc", "4", "--out", str(tmp_path / "o.png")]
    cases = [
        ([str(tmp_path / "nope.png"), "--depth", str(tmp_path / "grey.png")], "nope.png"),
        ([str(photo), "--depth", str(tmp_path / "missing.exr")], "missing.exr"),
        ([str(photo), "--depth", str(tmp_path / "small.exr")], "small.exr"),
        ([str(photo), "--depth", str(tmp_path / "bad.exr")], "bad.exr"),
        ([str(tmp_path / "junk.png"), "--depth", str(tmp_path / "grey.png")], "junk.png"),
    ]
    for argv, name in cases:
        rc, err = run_err(argv + base, capsys)
        assert rc == 2 and name in err, (name, err)
    rc, err = run_err([str(photo), "--depth", str(tmp_path / "grey.png"), "--focus", "0.5", "--max-coc",
                       "4", "--out", str(tmp_path / "o.jpg")], capsys)
    assert rc == 2 and "--out" in err
    rc, err = run_err([str(photo), "--depth", str(tmp_path / "grey.png"), "--focus", "0.5",
                       "--out", str(tmp_path / "o.png")], capsys)
    assert rc == 2 and "--max-coc" in err
    rc, err = run_err([str(photo), "--depth", str(tmp_path / "grey.png"), "--focus-at", "9999,0",
                       "--max-coc", "4", "--out", str(tmp_path / "o.png")], capsys)
    assert rc == 2 and "--focus-at" in err
    rc, err = run_err([str(photo), "--depth", str(tmp_path / "grey.png"), "--focus", "0.5", "--max-coc",
                       "4", "--aperture", "star", "--out", str(tmp_path / "o.png")], capsys)
    assert rc == 2 and "--aperture" in err
    assert not (tmp_path / "o.png").exists()


def test_faults_a_user_makes_end_in_one_line_and_leave_no_file(tmp_path, capsys):
    """A huge --max-coc (bounded by the image size, not a MemoryError), --out naming a folder,
    a colour EXR given as depth: refused naming the argument, nothing written."""
    img = np.random.default_rng(0).random((40, 60, 3)).astype(np.float32)
    write_png(tmp_path / "p.png", img)
    write_exr(tmp_path / "d.exr", np.full((40, 60), 0.5, np.float32))
    write_exr(tmp_path / "rgb.exr", img)
    write_png(tmp_path / "colour.png", img)
    (tmp_path / "folder").mkdir()
    base = [str(tmp_path / "p.png"), "--focus", "0.2"]
    rc, err = run_err(base + ["--depth", str(tmp_path / "d.exr"), "--max-coc", "100000", "--out",
                              str(tmp_path / "o.png")], capsys)
    assert rc == 2 and "max_coc 100000 px is more than 2 x the image's long side (60 px)" in err, err
    rc, err = run_err(base + ["--depth", str(tmp_path / "d.exr"), "--max-coc", "4", "--out", str(tmp_path / "o.txt")],
                      capsys)
    assert rc == 2 and "must be a folder or a file ending in .png or .exr" in err, err
    for depth in ("rgb.exr", "colour.png"):
        rc, err = run_err(base + ["--depth", str(tmp_path / depth), "--max-coc", "4", "--out",
                                  str(tmp_path / "o.png")], capsys)
        assert rc == 2 and depth in err and "not a depth map" in err, err
    assert len(err.strip().splitlines()) == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["colour.png", "d.exr", "folder", "p.png", "rgb.exr"]
    assert not list((tmp_path / "folder").iterdir())


def test_out_may_be_a_folder(tmp_path):
    write_png(tmp_path / "p.png", np.full((20, 30, 3), 0.5, np.float32))
    write_exr(tmp_path / "d.exr", np.full((20, 30), 0.5, np.float32))
    (tmp_path / "folder").mkdir()
    args = ["render", str(tmp_path / "p.png"), "--depth", str(tmp_path / "d.exr"), "--focus", "0.5", "--max-coc", "2"]
    assert main(args + ["--out", str(tmp_path / "folder")]) == 0
    assert main(args + ["--out", str(tmp_path / "new") + "/"]) == 0
    assert read_image(tmp_path / "folder" / "p.dof.png").shape == (20, 30, 3)
    assert (tmp_path / "new" / "p.dof.png").read_bytes() == (tmp_path / "folder" / "p.dof.png").read_bytes()


def test_help(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["render", "--help"])
    assert exc.value.code == 0
    text = capsys.readouterr().out
    for word in ("--depth", "--focus-at", "--max-coc", "--aperture", "--highlight", "--model", "disparity"):
        assert word in text


def test_model_hook(tmp_path, monkeypatch, photo):
    h, w = photo_size(photo)
    write_exr(tmp_path / "d.exr", np.full((h, w), 0.5, np.float32))
    seen = {}

    def render_photo(run_dir, image_linear, disparity, focus, aperture):
        seen.update(run_dir=run_dir, shape=image_linear.shape, dshape=disparity.shape, focus=focus, ap=aperture)
        return np.full(image_linear.shape, 0.25, np.float32)

    fake = types.ModuleType("dofsynth.train.infer")
    fake.render_photo = render_photo
    fake.run_task = lambda run_dir: "render"
    monkeypatch.setitem(sys.modules, "dofsynth.train.infer", fake)
    out = tmp_path / "net.exr"
    run = tmp_path / "r1"
    run.mkdir()
    rc = main(["render", str(photo), "--depth", str(tmp_path / "d.exr"), "--focus", "0.3", "--model", str(run),
               "--aperture-scale", "0.7", "--out", str(out)])
    assert rc == 0
    assert seen == {"run_dir": str(run), "shape": (h, w, 3), "dshape": (h, w), "focus": 0.3, "ap": 0.7}
    np.testing.assert_allclose(read_exr(out, channels=None), 0.25)
    rc = main(["render", str(photo), "--depth", str(tmp_path / "d.exr"), "--focus", "0.3", "--model", str(run),
               "--aperture-scale", "1.5", "--out", str(out)])
    assert rc == 2
    assert main(["render", str(photo), "--depth", str(tmp_path / "d.exr"), "--focus", "0.3", "--model", str(run),
                 "--model", str(run), "--out", str(out)]) == 2   # two DoF runs: one of each task at most


def test_render_subaperture_with_cat_eye_on_the_command_line(tmp_path):
    from dofsynth.cli import main

    img = np.zeros((48, 64, 3), np.float32) + 0.05
    img[4:6, 4:6] = 1.0
    write_png(tmp_path / "p.png", img)
    write_exr(tmp_path / "d.exr", np.zeros((48, 64), np.float32))
    args = ["render", str(tmp_path / "p.png"), "--depth", str(tmp_path / "d.exr"), "--focus", "1", "--max-coc", "6"]
    assert main(args + ["--method", "subaperture", "--cells", "4", "--cat-eye", "0.6", "--out", str(tmp_path / "a.exr")]) == 0
    assert main(args + ["--method", "subaperture", "--cells", "4", "--out", str(tmp_path / "b.exr")]) == 0
    a, b = read_exr(tmp_path / "a.exr"), read_exr(tmp_path / "b.exr")
    assert a.shape == (48, 64, 3) and not np.allclose(a, b, atol=1e-4)   # the corner disc is clipped
    assert main(args + ["--cat-eye", "0.6", "--out", str(tmp_path / "c.exr")]) == 2   # layered: refused by name


def test_a_depth_map_of_another_size_is_resampled_and_a_collapsed_one_is_warned_about(tmp_path, capsys):
    import cv2

    h, w = 48, 64
    g = np.random.default_rng(3)
    write_png(tmp_path / "p.png", g.random((h, w, 3)).astype(np.float32))
    ramp = np.tile(np.linspace(0.0, 1.0, w // 2, dtype=np.float32), (h // 2, 1))
    write_exr(tmp_path / "half.exr", ramp)
    full = cv2.resize(ramp, (w, h), interpolation=cv2.INTER_LINEAR)
    write_exr(tmp_path / "full.exr", full)
    common = ["--focus", "0.2", "--max-coc", "3", "--out"]
    assert main(["render", str(tmp_path / "p.png"), "--depth", str(tmp_path / "half.exr"), *common,
                 str(tmp_path / "a.exr")]) == 0
    err = capsys.readouterr().err
    assert "32x24, IMAGE is 64x48: depth resampled (bilinear)" in err
    assert main(["render", str(tmp_path / "p.png"), "--depth", str(tmp_path / "full.exr"), *common,
                 str(tmp_path / "b.exr")]) == 0
    assert np.array_equal(read_exr(tmp_path / "a.exr"), read_exr(tmp_path / "b.exr"))
    # metric depth with a near pixel at almost 0 m: every other pixel normalises below 0.05
    metric = np.full((h, w), 5.0, np.float32) + g.random((h, w)).astype(np.float32)
    metric[0, 0] = 1e-3
    write_exr(tmp_path / "metric.exr", metric)
    capsys.readouterr()
    assert main(["render", str(tmp_path / "p.png"), "--depth", str(tmp_path / "metric.exr"), "--depth-kind", "depth",
                 *common, str(tmp_path / "c.png")]) == 0
    err = capsys.readouterr().err
    assert "warning" in err and "metric.exr" in err and "below 0.05" in err
    capsys.readouterr()
    sane = metric.copy()
    sane[0, 0] = 2.0
    write_exr(tmp_path / "sane.exr", sane)
    assert main(["render", str(tmp_path / "p.png"), "--depth", str(tmp_path / "sane.exr"), "--depth-kind", "depth",
                 *common, str(tmp_path / "d.png")]) == 0
    assert "warning" not in capsys.readouterr().err
