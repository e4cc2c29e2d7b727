"""Round trips of every file format dofsynth reads and writes, and its read errors."""
from pathlib import Path

import numpy as np
import pytest

from dofsynth import io as dio
from dofsynth.color import srgb_to_linear


def _rng(seed=0):
    return np.random.default_rng(seed)


@pytest.mark.parametrize("channels", [1, 3, 4])
@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_png_round_trip_is_exact(tmp_path, channels, dtype):
    hi = np.iinfo(dtype).max
    img = _rng().integers(0, hi + 1, size=(7, 9, channels), dtype=dtype)
    path = tmp_path / "x.png"
    dio.write_png(path, img)
    back = dio.read_image(path)
    assert back.shape == (7, 9, channels) and back.dtype == np.float32
    np.testing.assert_array_equal(np.round(back * hi).astype(dtype), img)  # RGB(A) order kept


def test_png_float_input_is_quantised_srgb():
    img = _rng(1).random((5, 6, 3), dtype=np.float32)
    back = dio.decode_image(dio.encode_png(img))
    assert np.abs(back - img).max() <= 0.5 / 255 + 1e-7


@pytest.mark.parametrize("shape", [(16, 24), (16, 24, 3), (16, 24, 4)])
def test_exr_round_trip_is_bit_exact(tmp_path, shape):
    x = _rng(2).random(shape, dtype=np.float32) * 3.0  # beyond 1: linear light may exceed white
    path = tmp_path / "x.exr"
    dio.write_exr(path, x)
    back = dio.read_exr(path, channels="Y" if len(shape) == 2 else None)
    np.testing.assert_array_equal(back.reshape(shape), x)


def test_exr_of_a_non_contiguous_view_is_written_right():
    x = _rng(3).random((8, 10, 3), dtype=np.float32)
    view = x[:, :, 1]  # non-contiguous: OpenEXR would scramble it if passed as is
    np.testing.assert_array_equal(dio.decode_exr(dio.encode_exr(view), channels="Y"), view)


def test_read_depth_from_exr_and_16_bit_png(tmp_path):
    d = np.linspace(0, 1, 12 * 5, dtype=np.float32).reshape(12, 5)
    dio.write_exr(tmp_path / "d.exr", d)
    np.testing.assert_array_equal(dio.read_depth(tmp_path / "d.exr"), d)
    dio.write_png(tmp_path / "d.png", np.round(d * 65535).astype(np.uint16))
    assert np.abs(dio.read_depth(tmp_path / "d.png") - d).max() <= 0.5 / 65535 + 1e-7


def test_load_linear_rgba_grey_rgb_rgba(tmp_path):
    grey = _rng(4).integers(0, 256, (6, 4, 1), dtype=np.uint8)
    dio.write_png(tmp_path / "g.png", grey)
    rgb, alpha = dio.load_linear_rgba(tmp_path / "g.png")
    assert rgb.shape == (6, 4, 3) and alpha is None
    np.testing.assert_allclose(rgb[:, :, 2], srgb_to_linear(grey[:, :, 0] / 255.0), atol=1e-6)
    rgba = _rng(5).integers(0, 256, (6, 4, 4), dtype=np.uint8)
    dio.write_png(tmp_path / "c.png", rgba)
    rgb, alpha = dio.load_linear_rgba(tmp_path / "c.png")
    np.testing.assert_allclose(alpha, rgba[:, :, 3] / 255.0, atol=1e-7)   # alpha is not decoded
    np.testing.assert_allclose(rgb, srgb_to_linear(rgba[:, :, :3] / 255.0), atol=1e-6)


def test_truncated_and_missing_files_are_named(tmp_path):
    path = tmp_path / "cut.png"
    data = dio.encode_png(np.zeros((32, 32, 3), np.uint8) + 77)
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(dio.ImageReadError, match="cut.png"):
        dio.read_image(path)
    bad = tmp_path / "bad.exr"
    bad.write_bytes(b"not an exr")
    with pytest.raises(dio.ImageReadError, match="bad.exr"):
        dio.read_exr(bad)
    with pytest.raises(FileNotFoundError, match="gone.png"):
        dio.read_image(tmp_path / "gone.png")
    with pytest.raises(dio.ImageReadError, match="channel 'disparity' or 'Z'"):
        dio.decode_exr(dio.encode_exr(np.zeros((2, 2, 3), np.float32)), "rgb.exr", channels=("disparity", "Z"))


def test_atomic_write_leaves_no_temporary(tmp_path):
    dio.atomic_write_bytes(tmp_path / "sub" / "f.bin", b"abc")
    assert [p.name for p in (tmp_path / "sub").iterdir()] == ["f.bin"]
    assert (tmp_path / "sub" / "f.bin").read_bytes() == b"abc"


def test_real_photo_and_matte_decode(shared_assets: Path):
    rgb, alpha = dio.load_linear_rgba(shared_assets / "fg" / "rembg_girl-1.jpg")
    matte = dio.read_image(shared_assets / "alpha" / "rembg_girl-1.png")
    assert rgb.shape == (399, 600, 3) and alpha is None
    assert matte.shape == (399, 600, 1) and 0.0 <= matte.min() and matte.max() <= 1.0


def test_both_png_encoders_write_the_same_member_bytes(shared_assets, monkeypatch):
    """The PNG members (images, cover) come out byte for byte the same from imagecodecs and from
    OpenCV, the fallback, on real photos and mattes: shards do not depend on which is installed."""
    from dofsynth.codecs import encode_alphas, encode_srgb_png_planar

    photos = sorted(p for p in shared_assets.rglob("*") if p.suffix.lower() in (".jpg", ".png"))[:6]
    assert len(photos) >= 4
    for path in photos:
        img = dio.read_image(path)
        rgb = img[:, :, :3] if img.shape[2] >= 3 else np.repeat(img[:, :, :1], 3, axis=2)
        linear = np.ascontiguousarray(srgb_to_linear(rgb).transpose(2, 0, 1))
        alpha = img[:, :, -1] if img.shape[2] in (2, 4) else img[:, :, 0]
        got = {}
        for backend in ("cv2", "imagecodecs"):
            monkeypatch.setenv("DOFSYNTH_PNG", backend)
            assert dio.png_backend() == backend
            got[backend] = (encode_srgb_png_planar(linear), encode_alphas(alpha, alpha[::-1].copy()))
        assert got["cv2"] == got["imagecodecs"], path.name
        back = dio.decode_image(got["cv2"][0], raw=True)
        assert back.shape == img.shape[:2] + (3,)
    monkeypatch.delenv("DOFSYNTH_PNG")
    monkeypatch.setitem(__import__("sys").modules, "imagecodecs", None)  # not installed: OpenCV
    assert dio.png_backend() == "cv2"
    assert (encode_srgb_png_planar(linear), encode_alphas(alpha, alpha[::-1].copy())) == got["imagecodecs"]
    monkeypatch.setenv("DOFSYNTH_PNG", "zlib")
    with pytest.raises(ValueError, match="DOFSYNTH_PNG"):
        dio.png_backend()
