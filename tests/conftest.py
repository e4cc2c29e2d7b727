"""Shared fixtures: tiny synthetic asset folders, recipe writers, the smoke recipe and its library.

Real photos live in ../shared/assets beside the project (the `shared_assets` fixture); they are never copied into the project.
Fixtures that write files do so under pytest's tmp_path.
"""
from __future__ import annotations

import math
import os
from pathlib import Path

import cv2
import numpy as np
import pytest

# `dofsynth generate --workers 1` tunes malloc for the process it runs in (generate.worker.setup_process):
# not for the test processes, which call the CLI in-process and live on (nor their workers).
os.environ.setdefault("DOFSYNTH_WORKER_MALLOC", "default")
# estimated foregrounds are cached in a folder of this test session, never in the user's cache
# (set before any test, so that the processes the tests start inherit it too)
if "DOFSYNTH_TEST_CACHE" not in os.environ:
    import atexit
    import shutil
    import tempfile

    os.environ["DOFSYNTH_TEST_CACHE"] = tempfile.mkdtemp(prefix="dofsynth-test-cache-")
    atexit.register(shutil.rmtree, os.environ["DOFSYNTH_TEST_CACHE"], True)  # by the process that made it
os.environ["DOFSYNTH_CACHE"] = os.environ["DOFSYNTH_TEST_CACHE"]
# and so are Hugging Face datasets' prepared copies: it keys them on a file's path, size and
# modification time, which a data set rebuilt at the same pytest path can share with an old one
os.environ["HF_DATASETS_CACHE"] = os.path.join(os.environ["DOFSYNTH_TEST_CACHE"], "hf-datasets")

ROOT = Path(__file__).resolve().parents[1]
SHARED_ASSETS = Path(__file__).resolve().parents[2] / "shared" / "assets"

RECIPE_TEMPLATE = """\
name = "test"
seed = 11
size = {size}
aspect = 1.0
shard_size = 2
samples = {{ train = 6, test = 2 }}

[assets]
backgrounds = "{backgrounds}"
foregrounds = "{foregrounds}"
on_bad_asset = "{on_bad_asset}"
test_share = 0.25
verify = "{verify}"
{manifest}
[scene.background]
flat_share = 0.3
b0 = [0.15, 0.4]
b1 = [0.0, 0.1]
vertical_share = 0.5
crop = [0.6, 1.0]

[scene.foreground]
f0 = [0.8, 1.0]
f1 = [0.5, 0.75]
min_gap = 0.05
scale = [0.4, 0.8]
min_in_frame = 0.6
flip_share = 0.5

[focus]
targets_per_scene = 2
plane_share = 0.5
max_coc = [2.0, 4.0]
"""


def write_png(path: Path, img: np.ndarray) -> Path:
    """Write uint8/uint16 (H, W), (H, W, 3) RGB or (H, W, 4) RGBA as PNG (cv2 wants BGR)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    if img.ndim == 3 and img.shape[2] == 3:
        img = img[:, :, ::-1]
    elif img.ndim == 3 and img.shape[2] == 4:
        img = img[:, :, [2, 1, 0, 3]]
    assert cv2.imwrite(str(path), np.ascontiguousarray(img)), path
    return path


def blob_alpha(h: int, w: int, seed: int) -> np.ndarray:
    """A soft elliptic matte with a hole, uint8."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w]
    cy, cx = h * rng.uniform(0.4, 0.6), w * rng.uniform(0.4, 0.6)
    r = np.hypot((yy - cy) / (0.35 * h), (xx - cx) / (0.35 * w))
    a = np.clip((1.0 - r) * 6.0, 0.0, 1.0) * np.clip((r - 0.25) * 10.0, 0.0, 1.0)
    return (a * 255 + 0.5).astype(np.uint8)


def noise_rgb(h: int, w: int, seed: int, dtype=np.uint8) -> np.ndarray:
    rng = np.random.default_rng(seed)
    hi = 255 if dtype == np.uint8 else 65535
    return rng.integers(0, hi + 1, (h, w, 3)).astype(dtype)


@pytest.fixture(scope="session")
def shared_assets() -> Path:
    """The real photos and mattes beside the project (../shared/assets). Tests that need them
    skip with a one-line reason where they are absent, but fail in CI (CI set), where they
    must be."""
    if not (SHARED_ASSETS / "SOURCES.md").is_file():
        why = f"real test photos not found at {SHARED_ASSETS} (../shared/assets beside the project)"
        if os.environ.get("CI"):
            pytest.fail(f"{why}; CI must run the tests that use them")
        pytest.skip(why)
    return SHARED_ASSETS


@pytest.fixture
def tiny_bg_dir(tmp_path) -> Path:
    """Five small backgrounds: 8-bit RGB PNG, 16-bit PNG, grey PNG, JPEG, one in a subfolder."""
    d = tmp_path / "bg"
    write_png(d / "a.png", noise_rgb(80, 96, 1))
    write_png(d / "b16.png", noise_rgb(72, 100, 2, np.uint16))
    write_png(d / "grey.png", noise_rgb(90, 90, 3)[:, :, 0])
    cv2.imwrite(str(d / "c.jpg"), noise_rgb(96, 128, 4))
    write_png(d / "sub" / "d.png", noise_rgb(100, 80, 5))
    return d


@pytest.fixture
def tiny_fg_pairs(tmp_path) -> Path:
    """fg/ + alpha/ layout, four pairs paired by stem (JPEG/PNG photos, PNG mattes)."""
    d = tmp_path / "fgpairs"
    for i in range(4):
        h, w = 80 + 8 * i, 96
        rgb = noise_rgb(h, w, 10 + i)
        if i % 2:
            (d / "fg").mkdir(parents=True, exist_ok=True)
            assert cv2.imwrite(str(d / "fg" / f"o{i}.jpg"), rgb)
        else:
            write_png(d / "fg" / f"o{i}.png", rgb)
        write_png(d / "alpha" / f"o{i}.png", blob_alpha(h, w, 20 + i))
    return d


@pytest.fixture
def tiny_cutouts(tmp_path) -> Path:
    """A folder of four RGBA cutouts (8-bit and 16-bit PNG)."""
    d = tmp_path / "cutouts"
    for i in range(4):
        h, w = 88, 72 + 8 * i
        rgba = np.dstack([noise_rgb(h, w, 30 + i), blob_alpha(h, w, 40 + i)])
        if i == 3:
            rgba = rgba.astype(np.uint16) * 257
        write_png(d / f"cut{i}.png", rgba)
    return d


@pytest.fixture
def write_recipe(tmp_path):
    """write_recipe(backgrounds=..., foregrounds=..., on_bad_asset=..., verify=..., manifest=None,
    size=64, name="recipe.toml", replace={old: new}) -> Path of a recipe in tmp_path."""
    def make(backgrounds="builtin", foregrounds="builtin", on_bad_asset="skip", verify="decode",
             manifest=None, size=64, name="recipe.toml", replace=None) -> Path:
        text = RECIPE_TEMPLATE.format(
            size=size, backgrounds=backgrounds, foregrounds=foregrounds, on_bad_asset=on_bad_asset,
            verify=verify, manifest=f'manifest = "{manifest}"\n' if manifest else "")
        for old, new in (replace or {}).items():
            assert old in text, old
            text = text.replace(old, new)
        p = tmp_path / name
        p.write_text(text, encoding="utf-8")
        return p
    return make


@pytest.fixture(params=["numpy", "compiled"])
def passes(request):
    """Run a test with the numpy per-pixel passes, then with the compiled kernels
    (dofsynth.jit: both must give the same values); this process's setting is restored after."""
    from dofsynth import jit

    was = jit.enabled()
    if request.param == "compiled":
        assert jit.enable(), "numba is missing or DOFSYNTH_JIT=0: the compiled passes cannot be tested"
    else:
        jit.disable()
    yield request.param
    jit.enable() if was else jit.disable()


@pytest.fixture(scope="session")
def smoke_recipe():
    from dofsynth.recipe import load_recipe

    return load_recipe(ROOT / "recipes" / "smoke.toml")


@pytest.fixture(scope="session")
def smoke_library(smoke_recipe):
    from dofsynth.assets import build_library

    return build_library(smoke_recipe)


@pytest.fixture(scope="session")
def demo_recipe():
    from dofsynth.recipe import load_recipe

    return load_recipe(ROOT / "recipes" / "demo.toml")


@pytest.fixture(scope="session")
def smoke_set(tmp_path_factory, smoke_recipe) -> Path:
    """The real smoke data set (recipes/smoke.toml: 64 px, 6 train + 2 test, 2 per shard),
    generated once per test process. Treat it as read-only: copy it before damaging it."""
    from dofsynth.generate import generate

    out = tmp_path_factory.mktemp("smoke") / "set"
    generate(smoke_recipe, out, progress=False)
    return out


def _brute_coverage(aperture, radius, sub=64):
    """Independent reference kernel: point-in-shape tests on sub x sub points per pixel
    (area of the aperture of `radius` px inside each pixel, unnormalized)."""
    s = 0 if radius < 0.5 else math.ceil(radius - 0.5)   # the pixels the shape touches
    n = 2 * s + 1
    t = (np.arange(n * sub) + 0.5) / sub - s - 0.5
    yy, xx = np.meshgrid(t, t, indexing="ij")
    inside = aperture.contains(xx / radius, yy / radius).astype(np.float64)
    return inside.reshape(n, sub, n, sub).sum(axis=(1, 3)) / sub**2


def _brute_tent(aperture, radius, sub=96):
    """Independent reference of the tent-weighted kernel: point-in-shape tests on a fine grid,
    each point's area shared among the kernel pixels by the bilinear tent (unnormalized)."""
    s = math.ceil(radius)
    t = (np.arange(2 * s * sub) + 0.5) / sub - s          # points over [-s, s]
    yy, xx = np.meshgrid(t, t, indexing="ij")
    inside = aperture.contains(xx / radius, yy / radius).astype(np.float64) / sub**2
    offs = np.arange(-s, s + 1)[:, None]
    tent = np.maximum(0.0, 1.0 - np.abs(offs - t[None, :]))   # (2s+1, points)
    return tent @ inside @ tent.T


@pytest.fixture(scope="session")
def brute_coverage():
    return _brute_coverage


@pytest.fixture(scope="session")
def brute_tent():
    return _brute_tent


@pytest.fixture
def one_torch_thread():
    """Tiny tensors: one intra-op thread is faster and does not fight other test workers."""
    import torch

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def torchrun_failure(proc) -> str:
    """The message for a failed `torch.distributed.run`: the ranks' own lines first (a rank's
    abort message comes before the launcher's long summary, which alone would fill the tail),
    then the tail of stderr."""
    own = [line for line in proc.stderr.splitlines() if not line.startswith(("E1", "W1", "I1", " ", "Traceback"))]
    return "\n".join(own[-40:]) + "\n---\n" + proc.stderr[-1500:]
