"""Foreground colour estimation (dofsynth.assets.foreground): the photo's backdrop must not
reach the new scene through hair and fur; the estimate is cached and the same bytes every time."""
import os
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from dofsynth.assets import build_library
from dofsynth.assets.foreground import cache_dir, estimate, estimator_id
from dofsynth.color import srgb8_to_linear
from dofsynth.io import decode_image
from dofsynth.recipe import load_recipe
from dofsynth.scene import sample_scene

ROOT = Path(__file__).resolve().parents[1]


def _read(path: Path) -> np.ndarray:
    return decode_image(path.read_bytes(), str(path), raw=True)


@pytest.fixture(scope="module")
def fur(shared_assets):
    """The lemur's real fur matte in [0, 1] and a known, smooth object colour (linear)."""
    a = _read(shared_assets / "alpha" / "pymatting_lemur.png")
    a = (a[..., 0] if a.ndim == 3 else a).astype(np.float32) / 255
    h, w = a.shape
    yy, xx = np.mgrid[0:h, 0:w] / max(h, w)
    colour = np.stack([0.2 + 0.3 * xx, 0.5 - 0.2 * yy, 0.3 + 0.1 * xx * yy], -1).astype(np.float32)
    return a, colour


def _leak(alpha, estimated, truth):
    """Per soft pixel, the largest channel error of the estimate once composited (alpha * |F' - F|):
    what differs from the true object over ANY new background."""
    soft = (alpha > 0) & (alpha < 1)
    return (alpha[..., None] * np.abs(estimated - truth)).max(-1)[soft]


def test_a_saturated_backdrop_leaves_no_trace_through_real_fur(fur):
    alpha, colour = fur
    assert ((alpha > 0) & (alpha < 1)).mean() > 0.1  # a real fur matte: much of it is soft
    backdrop = np.zeros_like(colour)
    backdrop[..., 0] = backdrop[..., 2] = 1.0  # saturated magenta
    photo = alpha[..., None] * colour + (1 - alpha[..., None]) * backdrop
    as_is = _leak(alpha, photo, colour)
    est = _leak(alpha, estimate(photo, alpha, "a" * 64, "magenta" + "0" * 57), colour)
    assert as_is.max() > 0.15  # the photo itself carries the backdrop in (0.18 in linear light)
    # what is left is the 8-bit sRGB quantisation of the cached estimate (half a code: <= 0.0045)
    assert est.max() < 0.005 and est.mean() < 0.0025


def test_a_real_photo_backdrop_is_mostly_removed_from_fur(fur, shared_assets):
    """A textured backdrop (a Kodak photo, blurred as a matting photo's backdrop usually is) is
    harder: the estimate must remove at least 2/3 of what the photo carries in on average."""
    alpha, colour = fur
    h, w = alpha.shape
    kodak = srgb8_to_linear(_read(shared_assets / "bg" / "kodak_kodim22.png")[:h, :w, :3])
    backdrop = cv2.GaussianBlur(kodak, (0, 0), 4)
    photo = alpha[..., None] * colour + (1 - alpha[..., None]) * backdrop
    as_is = _leak(alpha, photo, colour)
    est = _leak(alpha, estimate(photo, alpha, "b" * 64, "kodak" + "0" * 59), colour)
    assert est.mean() < as_is.mean() / 3
    assert np.percentile(est, 99) < 0.05 < np.percentile(as_is, 99)


def test_opaque_and_clear_pixels_keep_the_photo_and_no_soft_edge_is_a_no_op():
    rng = np.random.default_rng(0)
    photo = rng.random((40, 50, 3), dtype=np.float32)
    alpha = np.zeros((40, 50), np.float32)
    alpha[10:30, 10:40] = 1.0
    assert estimate(photo, alpha, "c" * 64, "d" * 64) is photo  # a hard matte: nothing to estimate
    alpha[10:30, 8:10] = 0.5
    out = estimate(photo, alpha, "c" * 64, "e" * 64)
    keep = (alpha == 0) | (alpha == 1)
    assert np.array_equal(out[keep], photo[keep]) and not np.array_equal(out[~keep], photo[~keep])


def test_the_cache_gives_the_same_bytes_and_a_broken_entry_is_made_again(tmp_path, monkeypatch):
    monkeypatch.setenv("DOFSYNTH_CACHE", str(tmp_path / "cache"))
    rng = np.random.default_rng(1)
    photo = rng.random((32, 48, 3), dtype=np.float32)
    yy, xx = np.mgrid[0:32, 0:48]
    alpha = np.clip((20 - np.hypot(yy - 16, xx - 24)) / 6, 0, 1).astype(np.float32)
    first = estimate(photo, alpha, "f" * 64, "0" * 64)
    files = list((tmp_path / "cache" / "foreground").iterdir())
    assert len(files) == 1 and files[0].name.startswith(estimator_id()) and cache_dir() == tmp_path / "cache"
    assert np.array_equal(estimate(photo, alpha, "f" * 64, "0" * 64), first)  # from the cache
    n = int(((alpha > 0) & (alpha < 1)).sum())
    assert files[0].name.endswith(f"-{n}.npy") and np.load(files[0]).shape == (n, 3)  # the soft pixels' codes
    files[0].write_bytes(b"\x93NUMPY broken")
    assert np.array_equal(estimate(photo, alpha, "f" * 64, "0" * 64), first)  # made again
    assert np.load(files[0]).shape == (n, 3)
    # another process, its own empty cache, the same bytes
    code = ("import numpy as np, sys; from dofsynth.assets.foreground import estimate; "
            "rng = np.random.default_rng(1); p = rng.random((32, 48, 3), dtype=np.float32); "
            "yy, xx = np.mgrid[0:32, 0:48]; a = np.clip((20 - np.hypot(yy - 16, xx - 24)) / 6, 0, 1).astype(np.float32); "
            "sys.stdout.buffer.write(estimate(p, a, 'f' * 64, '0' * 64).tobytes())")
    env = {**os.environ, "DOFSYNTH_CACHE": str(tmp_path / "other")}
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, check=True).stdout
    assert out == first.tobytes()


def test_an_unwritable_cache_warns_and_gives_the_same_result(tmp_path, monkeypatch, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    monkeypatch.setenv("DOFSYNTH_CACHE", str(blocker))
    photo = np.full((16, 16, 3), 0.5, np.float32)
    alpha = np.full((16, 16), 0.5, np.float32)
    out = estimate(photo, alpha, "1" * 64, "2" * 64)
    assert "cannot cache estimated foregrounds" in capsys.readouterr().err
    monkeypatch.setenv("DOFSYNTH_CACHE", str(tmp_path / "ok"))
    assert np.array_equal(out, estimate(photo, alpha, "1" * 64, "2" * 64))


def test_the_library_estimates_pairs_by_default_and_records_it(write_recipe, shared_assets):
    on = load_recipe(write_recipe(backgrounds=shared_assets / "bg", foregrounds=shared_assets, size=96))
    off = load_recipe(write_recipe(backgrounds=shared_assets / "bg", foregrounds=shared_assets, size=96,
                                   name="off.toml", replace={'verify = "decode"': 'verify = "decode"\nestimate_foreground = false'}))
    lib_on, lib_off = build_library(on), build_library(off)
    lemur = lib_on["fg/pymatting_lemur"]
    rgb_on, alpha = lib_on.load_foreground(lemur)
    rgb_off, _ = lib_off.load_foreground(lib_off["fg/pymatting_lemur"])
    soft, hard = (alpha > 0) & (alpha < 1), alpha == 1
    assert np.array_equal(rgb_on[hard], rgb_off[hard]) and np.abs(rgb_on[soft] - rgb_off[soft]).max() > 0.05
    s_on, s_off = sample_scene(on, lib_on, "train", 0), sample_scene(off, lib_off, "train", 0)
    assert s_on.assets["front"].colour == f"estimated:{estimator_id('srgb')}" and s_off.assets["front"].colour == "file"
    assert s_on.assets["front"].colour.endswith("-srgb")  # the default space, named in the record
    assert s_on.assets["background"].colour == "file"


@pytest.mark.parametrize("made_in", ["srgb", "linear"])
def test_each_estimation_space_undoes_a_composite_made_in_it(fur, made_in):
    """A photo composited over a saturated backdrop in 8-bit sRGB codes (as Composition-1k is
    made, and as mattes drawn on photos fit them) is undone best by estimating in sRGB codes;
    one composited in linear light, by estimating in linear light. Each space leaves at most
    a third of the other's leak of the backdrop, measured over the real fur matte."""
    from dofsynth.color import linear_to_srgb8

    alpha, colour = fur
    backdrop = np.zeros_like(colour)
    backdrop[..., 0], backdrop[..., 2] = 1.0, 0.6  # pink
    if made_in == "srgb":
        codes = alpha[..., None] * linear_to_srgb8(colour) + (1 - alpha[..., None]) * linear_to_srgb8(backdrop)
        photo = srgb8_to_linear(np.floor(codes + 0.5).astype(np.uint8))
    else:
        photo = alpha[..., None] * colour + (1 - alpha[..., None]) * backdrop
    leak = {space: _leak(alpha, estimate(photo, alpha, "9" * 64, made_in + space + "0" * (58 - len(made_in + space)),
                                         space), colour).mean() for space in ("srgb", "linear")}
    other = "linear" if made_in == "srgb" else "srgb"
    assert leak[made_in] < leak[other] / 3, leak
