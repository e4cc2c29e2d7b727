import json
import shutil

import cv2
import numpy as np
import pytest
from scipy import ndimage

from dofsynth.assets import builtin as B
from dofsynth.assets import Asset, AssetError, AssetLibrary, build_library
from dofsynth.assets.builtin import builtin_assets
from dofsynth.assets.pins import pin_folder
from dofsynth.assets.scan import read_sources_licences
from dofsynth.assets.splits import assign_splits
from dofsynth.cli import main as cli_main
from dofsynth.recipe import load_recipe
from dofsynth.io import read_image

from conftest import blob_alpha, noise_rgb, write_png


# ------------------------------------------------------------------------------ built-in assets
def _in_a_fresh_process(code: str) -> str:
    import subprocess
    import sys

    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()


def test_builtin_assets_are_many_sorted_and_deterministic():
    bgs, fgs = builtin_assets("background"), builtin_assets("foreground")
    assert len(bgs) >= 12 and len(fgs) >= 12
    assert [a.id for a in bgs] == sorted(a.id for a in bgs)
    assert all(a.id.startswith("builtin:bg/") and a.path == a.id for a in bgs)
    assert all(a.id.startswith("builtin:fg/") and a.kind == "foreground" for a in fgs)
    assert len({a.sha256 for a in (*bgs, *fgs)}) == len(bgs) + len(fgs)
    # drawn from scratch in another process: the same pixels, the same hashes
    fresh = _in_a_fresh_process("from dofsynth.assets.builtin import builtin_assets as b\n"
                                "print(' '.join(a.sha256 for k in ('background', 'foreground') for a in b(k)))")
    assert fresh.split() == [a.sha256 for a in (*bgs, *fgs)]


def test_a_pickled_library_loads_the_same_pixels_in_another_process(tmp_path):
    """Spawn workers and Ray tasks get the parent's library pickled (with the built-in pixels
    drawn so far, not its decoded-asset cache): they load the same linear pixels."""
    import hashlib
    import pickle

    lib = AssetLibrary(list(builtin_assets("background")), list(builtin_assets("foreground")), {})
    lib.load_background(lib["builtin:bg/noise"])  # fills the decoded cache, which must not travel
    (tmp_path / "lib.pkl").write_bytes(pickle.dumps(lib))
    ids = ("builtin:bg/noise", "builtin:bg/astronaut")
    got = _in_a_fresh_process(
        "import hashlib, pickle, sys\n"
        f"lib = pickle.loads(open({str(tmp_path / 'lib.pkl')!r}, 'rb').read())\n"
        f"print(' '.join(hashlib.sha256(lib.load_background(lib[i]).tobytes()).hexdigest() for i in {ids!r}))\n"
        "rgb, a = lib.load_foreground(lib['builtin:fg/hair-00'])\n"
        "print(hashlib.sha256(rgb.tobytes() + a.tobytes()).hexdigest())")
    want = [hashlib.sha256(lib.load_background(lib[i]).tobytes()).hexdigest() for i in ids]
    rgb, a = lib.load_foreground(lib["builtin:fg/hair-00"])
    assert got.split() == want + [hashlib.sha256(rgb.tobytes() + a.tobytes()).hexdigest()]


def _mattes() -> dict[str, np.ndarray]:
    return {n: B.foreground_pixels(n)[1].astype(np.float32) / 255 for n in B.FOREGROUND_NAMES}


def test_builtin_mattes_have_soft_edges_everywhere():
    for name, a in _mattes().items():
        fractional = (a > 0.02) & (a < 0.98)
        assert fractional.sum() > 200, name
        assert a.max() == 1.0 and a.min() == 0.0, name


def test_builtin_mattes_have_holes_thin_structures_and_semi_transparency():
    holes, thin, veils = [], [], []
    for name, a in _mattes().items():
        solid = a > 0.5
        if (ndimage.binary_fill_holes(solid) & ~solid).sum() > 100:
            holes.append(name)
        gone = (a > 0.1) & ~ndimage.binary_opening(a > 0.1, structure=np.ones((5, 5)))
        if gone.sum() > 500:  # structures thinner than 5 px: strands, branches, bars
            thin.append(name)
        mid = ndimage.binary_erosion((a > 0.25) & (a < 0.75), structure=np.ones((9, 9)))
        if mid.sum() > 500:   # a semi-transparent region, not just an edge
            veils.append(name)
    assert len(holes) >= 3, holes
    assert len(thin) >= 3, thin
    assert len(veils) >= 2, veils


def test_builtin_library_loads_linear_float32(smoke_library):
    bg = smoke_library.backgrounds[0]
    img = smoke_library.load_background(bg)
    assert img.dtype == np.float32 and img.shape == (bg.size[1], bg.size[0], 3)
    assert 0.0 <= img.min() and img.max() <= 1.0
    fg = smoke_library.foregrounds[0]
    rgb, alpha = smoke_library.load_foreground(fg)
    assert rgb.shape[:2] == alpha.shape == (fg.size[1], fg.size[0]) and alpha.dtype == np.float32
    x, y, w, h = fg.extent
    assert alpha[y:y + h, x:x + w].sum() == pytest.approx(alpha.sum())


# ------------------------------------------------------------------------------ real assets
def test_paired_layout_with_shared_assets(write_recipe, shared_assets):
    r = load_recipe(write_recipe(backgrounds=shared_assets / "bg", foregrounds=shared_assets))
    lib = build_library(r)
    assert [a.id for a in lib.backgrounds] == [f"bg/{p.stem}" for p in sorted((shared_assets / "bg").iterdir())]
    assert len(lib.foregrounds) == 6 and not lib.skipped
    car = lib["fg/rembg_car-2"]
    assert car.alpha_path.endswith("alpha/rembg_car-2.png") and car.size == (1000, 667)
    assert car.licence == "MIT (repo LICENSE.txt)"
    assert lib["bg/kodak_kodim01"].licence == "no repo licence file"
    rgb, alpha = lib.load_foreground(car)
    assert rgb.shape == (667, 1000, 3) and alpha.shape == (667, 1000)
    assert ((alpha > 0.05) & (alpha < 0.95)).any() and alpha.max() > 0.97
    x, y, w, h = car.extent
    assert (alpha[:, :x] == 0).all() and (alpha[y + h:, :] == 0).all()


def test_a_real_mattes_near_opaque_interior_loads_opaque(write_recipe, shared_assets):
    """rembg stops at codes 253-254 inside solid objects, which would let 0.4-0.8 % of the new
    background through a face (visibly where the highlight boost brightens it): a matte at
    least `assets.opaque_from` opaque loads as 1; softer values (hair, edges) stay as they are;
    opaque_from = 1 keeps the matte as it is."""
    codes = _read_codes(shared_assets / "alpha" / "rembg_girl-3.png")
    inside = codes >= 250
    assert ((codes == 253) | (codes == 254)).sum() > 0.5 * inside.sum()  # the matting network's interior
    soft = (codes > 0) & (codes < 250)
    for opaque_from, want in ((0.98, np.where(inside, 1.0, codes / 255.0)), (1.0, codes / 255.0)):
        r = load_recipe(write_recipe(backgrounds=shared_assets / "bg", foregrounds=shared_assets,
                                     replace={'verify = "decode"': f'verify = "decode"\nopaque_from = {opaque_from}'}))
        lib = build_library(r)
        _, alpha = lib.load_foreground(lib["fg/rembg_girl-3"])
        np.testing.assert_allclose(alpha, want, atol=1e-6)
        assert lib.matte(lib["fg/rembg_girl-3"]) == ("file" if opaque_from == 1.0 else "opaque_from:0.98")  # as records say
        assert lib.matte(lib["bg/kodak_kodim01"]) == "file"
        assert soft.any() and np.array_equal(alpha[soft], (codes[soft] / np.float32(255)).astype(np.float32))


def _read_codes(path):
    """A matte file's 8-bit codes (its first channel)."""
    import cv2

    a = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    return a[..., 0] if a.ndim == 3 else a


def test_rgba_cutout_folder_made_from_shared_assets(write_recipe, shared_assets, tmp_path):
    cut = tmp_path / "cutouts"
    for name in ("rembg_girl-1", "pymatting_lemur"):
        fg = next((shared_assets / "fg").glob(name + ".*"))
        rgb = (read_image(fg)[:, :, :3] * 255 + 0.5).astype(np.uint8)
        a = (read_image(shared_assets / "alpha" / f"{name}.png")[:, :, 0] * 255 + 0.5).astype(np.uint8)
        write_png(cut / f"{name}.png", np.dstack([rgb, a]))
    for i in range(2):
        write_png(cut / "more" / f"x{i}.png", np.dstack([noise_rgb(70, 80, i), blob_alpha(70, 80, i)]))
    lib = build_library(load_recipe(write_recipe(backgrounds=shared_assets / "bg", foregrounds=cut)))
    assert [a.id for a in lib.foregrounds] == ["fg/more/x0", "fg/more/x1", "fg/pymatting_lemur", "fg/rembg_girl-1"]
    girl = lib["fg/rembg_girl-1"]
    _, alpha = lib.load_foreground(girl)
    ref = read_image(shared_assets / "alpha" / "rembg_girl-1.png")[:, :, 0]
    ref = np.where(ref >= np.float32(0.98), np.float32(1.0), ref)  # assets.opaque_from
    assert np.array_equal(alpha, ref) and girl.alpha_path is None


def test_formats_8_16_bit_grey_jpeg_and_cutouts(write_recipe, tiny_bg_dir, tiny_cutouts):
    lib = build_library(load_recipe(write_recipe(backgrounds=tiny_bg_dir, foregrounds=tiny_cutouts)))
    assert [a.id for a in lib.backgrounds] == ["bg/a", "bg/b16", "bg/c", "bg/grey", "bg/sub/d"]
    for a in lib.backgrounds:
        img = lib.load_background(a)
        assert img.shape == (a.size[1], a.size[0], 3) and img.dtype == np.float32
    grey = lib.load_background(lib["bg/grey"])
    assert np.array_equal(grey[..., 0], grey[..., 2])
    rgb16, a16 = lib.load_foreground(lib["fg/cut3"])
    assert a16.dtype == np.float32 and len(np.unique(a16)) > 10


# ------------------------------------------------------------------------------ bad assets
def _bad_cases(tmp_path, tiny_fg_pairs, tiny_bg_dir):
    """Each bad file, its folder role and a word its reason must contain."""
    good = (tiny_bg_dir / "a.png").read_bytes()
    (tiny_bg_dir / "truncated.png").write_bytes(good[: len(good) // 2])
    write_png(tiny_bg_dir / "tiny.png", noise_rgb(40, 200, 9))
    write_png(tiny_fg_pairs / "fg" / "wrongsize.png", noise_rgb(80, 96, 3))
    write_png(tiny_fg_pairs / "alpha" / "wrongsize.png", blob_alpha(60, 96, 3))
    write_png(tiny_fg_pairs / "fg" / "empty.png", noise_rgb(80, 96, 4))
    write_png(tiny_fg_pairs / "alpha" / "empty.png", np.zeros((80, 96), np.uint8))
    write_png(tiny_fg_pairs / "fg" / "nomatte.png", noise_rgb(80, 96, 5))
    write_png(tiny_bg_dir / "holes.png", np.dstack([noise_rgb(80, 96, 6), blob_alpha(80, 96, 6)]))
    return {
        tiny_bg_dir / "truncated.png": "not a readable image",
        tiny_bg_dir / "tiny.png": "tiny image",
        tiny_fg_pairs / "fg" / "wrongsize.png": "alpha is 96x60",
        tiny_fg_pairs / "fg" / "empty.png": "empty alpha",
        tiny_fg_pairs / "fg" / "nomatte.png": "without alpha",
        tiny_bg_dir / "holes.png": "a background with transparent pixels",
    }


def test_bad_assets_are_skipped_with_their_names(write_recipe, tmp_path, tiny_fg_pairs, tiny_bg_dir, capsys):
    cases = _bad_cases(tmp_path, tiny_fg_pairs, tiny_bg_dir)
    lib = build_library(load_recipe(write_recipe(backgrounds=tiny_bg_dir, foregrounds=tiny_fg_pairs)))
    skipped = dict(lib.skipped)
    err = capsys.readouterr().err
    for path, why in cases.items():
        assert str(path) in skipped, (path, skipped)
        assert why in skipped[str(path)]
        assert f"skipping asset {path}" in err
    assert {a.id for a in lib.foregrounds} == {"fg/o0", "fg/o1", "fg/o2", "fg/o3"}
    assert len(lib.backgrounds) == 5


@pytest.mark.parametrize("which", range(6))
def test_bad_assets_stop_with_their_names(which, write_recipe, tmp_path, tiny_fg_pairs, tiny_bg_dir):
    cases = list(_bad_cases(tmp_path, tiny_fg_pairs, tiny_bg_dir).items())
    for i, (path, _) in enumerate(cases):  # keep only one bad file
        if i != which:
            path.unlink()
    path, why = cases[which]
    with pytest.raises(AssetError) as exc:
        build_library(load_recipe(write_recipe(backgrounds=tiny_bg_dir, foregrounds=tiny_fg_pairs,
                                               on_bad_asset="stop")))
    assert str(path) in str(exc.value) and why in str(exc.value)


@pytest.mark.parametrize("onto, level", [("black", 0.0), ("grey", 0.21404114), ("white", 1.0)])
def test_a_transparent_background_is_flattened_as_the_recipe_says(onto, level, write_recipe, tiny_bg_dir, tmp_path):
    rgb, a = noise_rgb(80, 96, 6), blob_alpha(80, 96, 6)
    write_png(tiny_bg_dir / "holes.png", np.dstack([rgb, a]))
    write_png(tiny_bg_dir / "opaque.png", np.dstack([rgb, np.full_like(a, 255)]))  # alpha 1 everywhere: fine
    for verify in ("decode", "header"):
        recipe = load_recipe(write_recipe(backgrounds=tiny_bg_dir, on_bad_asset="stop", verify=verify,
                                          replace={'test_share = 0.25': f'test_share = 0.25\ntransparent_background = "{onto}"'}))
        lib = build_library(recipe)
        flat = lib.load_background(lib["bg/holes"])
        clear, solid = a == 0, a == 255
        assert np.allclose(flat[clear], level, atol=1e-6)
        assert np.array_equal(flat[solid], lib.load_background(lib["bg/opaque"])[solid])
        half = (a > 100) & (a < 150)
        assert half.any() and not np.allclose(flat[half], level)


def test_header_mode_refuses_a_transparent_background_when_it_is_loaded(write_recipe, tiny_bg_dir):
    write_png(tiny_bg_dir / "holes.png", np.dstack([noise_rgb(80, 96, 6), blob_alpha(80, 96, 6)]))
    lib = build_library(load_recipe(write_recipe(backgrounds=tiny_bg_dir, verify="header")))
    with pytest.raises(AssetError, match=r"holes\.png: a background with transparent pixels .*assets.transparent_background"):
        lib.load_background(lib["bg/holes"])


@pytest.mark.parametrize("fg_dir, alpha_dir", [("FG", "GT"), ("original", "mask"), ("blurred_image", "mask")])
def test_the_paired_layout_takes_its_folder_names_from_the_recipe(fg_dir, alpha_dir, write_recipe, tiny_fg_pairs):
    (tiny_fg_pairs / "fg").rename(tiny_fg_pairs / fg_dir)
    (tiny_fg_pairs / "alpha").rename(tiny_fg_pairs / alpha_dir)
    names = f'test_share = 0.25\nfg_dir = "{fg_dir}"\nalpha_dir = "{alpha_dir}"'
    lib = build_library(load_recipe(write_recipe(foregrounds=tiny_fg_pairs, on_bad_asset="stop",
                                                 replace={"test_share = 0.25": names})))
    assert [a.id for a in lib.foregrounds] == ["fg/o0", "fg/o1", "fg/o2", "fg/o3"]
    assert all(f"/{alpha_dir}/" in a.alpha_path for a in lib.foregrounds)
    # with the default names the folder is not a paired layout: its files are taken as RGBA cutouts
    with pytest.raises(AssetError, match="foreground without alpha"):
        build_library(load_recipe(write_recipe(foregrounds=tiny_fg_pairs, on_bad_asset="stop", name="plain.toml")))


def test_rgb_file_in_a_cutout_folder_is_a_foreground_without_alpha(write_recipe, tiny_cutouts, tiny_bg_dir):
    write_png(tiny_cutouts / "rgb.png", noise_rgb(80, 80, 1))
    with pytest.raises(AssetError, match=r"rgb\.png: foreground without alpha"):
        build_library(load_recipe(write_recipe(backgrounds=tiny_bg_dir, foregrounds=tiny_cutouts,
                                               on_bad_asset="stop")))


def test_header_mode_still_finds_unreadable_files_and_the_loader_names_the_rest(write_recipe, tiny_bg_dir, tiny_cutouts):
    """verify = "header" reads headers and a reduced grey decode (the perceptual hash), so an
    unreadable file is skipped at scan time too; what only a full decode shows is left to the
    loaders, which name the file."""
    good = (tiny_bg_dir / "a.png").read_bytes()
    (tiny_bg_dir / "zz_truncated.png").write_bytes(good[: int(len(good) * 0.6)])
    write_png(tiny_bg_dir / "holes.png", np.dstack([noise_rgb(80, 96, 6), blob_alpha(80, 96, 6)]))
    lib = build_library(load_recipe(write_recipe(backgrounds=tiny_bg_dir, foregrounds=tiny_cutouts,
                                                 verify="header", on_bad_asset="skip")))
    assert "not a readable image" in dict(lib.skipped)[str(tiny_bg_dir / "zz_truncated.png")]
    with pytest.raises(AssetError, match=r"holes\.png: a background with transparent pixels") as exc:
        lib.load_background(lib["bg/holes"])
    assert exc.value.asset_id == "bg/holes"
    # a file changed after the scan is refused by the loader too
    a = lib["bg/a"]
    write_png(tiny_bg_dir / "a.png", noise_rgb(80, 96, 99))
    with pytest.raises(AssetError, match=r"a\.png: changed since"):
        lib.load_background(a)


# ------------------------------------------------------------------------------ splits
def test_splits_are_disjoint_deterministic_and_per_asset(smoke_recipe, smoke_library):
    lib = smoke_library
    for kind in ("background", "foreground"):
        train, test = lib.assets_for(kind, "train"), lib.assets_for(kind, "test")
        assert train and test and not {a.id for a in train} & {a.id for a in test}
        assert len(train) + len(test) == len(lib.backgrounds if kind == "background" else lib.foregrounds)
    again = build_library(smoke_recipe)
    assert all(again.splits[a.id] == lib.splits[a.id] for a in (*lib.backgrounds, *lib.foregrounds))


def test_split_is_stable_when_assets_are_added_and_duplicates_stay_together():
    assets = [Asset(id=f"bg/{i:03d}", kind="background", path=f"/x/{i}", sha256=f"{i:064x}", size=(99, 99))
              for i in range(200)]
    s1 = assign_splits(assets[:150], 5, 0.2, {"train": 1, "test": 1})
    s2 = assign_splits(assets, 5, 0.2, {"train": 1, "test": 1})
    assert all(s1[k] == s2[k] for k in s1)
    assert 15 < sum(v == "test" for v in s2.values()) < 65
    assert assign_splits(assets, 6, 0.2, {}) != s2   # the seed matters
    dup = [*assets[:50], Asset(id="bg/zzz", kind="background", path="/y", sha256=assets[7].sha256, size=(99, 99))]
    s3 = assign_splits(dup, 5, 0.2, {})
    assert s3["bg/zzz"] == s3[assets[7].id]


def test_tiny_sets_still_fill_both_splits():
    assets = [Asset(id=f"fg/{i}", kind="foreground", path=f"/x/{i}", sha256=f"{i:064x}", size=(99, 99))
              for i in range(5)]
    s = assign_splits(assets, 1, 0.0, {"train": 2, "test": 2})
    assert sorted(s.values()).count("test") == 2


# ------------------------------------------------------------------------------ manifests
def test_scan_command_writes_a_manifest(tmp_path, tiny_bg_dir, capsys):
    out = tmp_path / "pins" / "bg.json"
    assert cli_main(["assets", "scan", str(tiny_bg_dir), "--manifest", str(out), "--licence", "CC0"]) == 0
    doc = json.loads(out.read_text())
    assert doc["schema_version"] == 1 and doc["root"] == "../bg"
    files = {f["path"]: f for f in doc["files"]}
    assert sorted(files) == ["a.png", "b16.png", "c.jpg", "grey.png", "sub/d.png"]
    a = files["a.png"]
    assert (a["width"], a["height"], a["channels"], a["kind"], a["licence"]) == (96, 80, 3, "background", "CC0")
    assert a["bytes"] == (tiny_bg_dir / "a.png").stat().st_size
    assert "pinned 5 files" in capsys.readouterr().out
    assert cli_main(["assets", "scan", str(tmp_path / "nowhere"), "--manifest", str(out)]) == 2


def test_scan_reads_licences_from_sources_md(shared_assets, tmp_path):
    doc = pin_folder(shared_assets, tmp_path, progress=False)
    files = {f["path"]: f for f in doc["files"]}
    assert files["alpha/rembg_car-2.png"]["kind"] == "alpha"
    assert files["fg/rembg_car-2.jpg"]["kind"] == "foreground"
    assert files["bg/kodak_kodim08.png"]["kind"] == "background"
    assert files["fg/pymatting_lemur.png"]["licence"] == "MIT (repo LICENSE.md)"
    lic = read_sources_licences(shared_assets / "bg")
    assert lic[str(shared_assets / "bg" / "kodak_kodim13.png")] == "no repo licence file"


def test_manifest_pin_refuses_changed_missing_and_new_files(write_recipe, tmp_path, tiny_bg_dir, tiny_cutouts):
    root = tmp_path / "assets"
    shutil.move(str(tiny_bg_dir), root / "bg")
    shutil.move(str(tiny_cutouts), root / "fg")
    man = tmp_path / "pins" / "assets.json"
    assert cli_main(["assets", "scan", str(root), "--manifest", str(man), "-q"]) == 0
    recipe = load_recipe(write_recipe(backgrounds="assets/bg", foregrounds="assets/fg", manifest="pins/assets.json"))
    lib = build_library(recipe)
    assert len(lib.backgrounds) == 5 and len(lib.foregrounds) == 4

    write_png(root / "bg" / "a.png", noise_rgb(80, 96, 123))          # changed
    with pytest.raises(AssetError, match=r"bg/a\.png: changed since pinned"):
        build_library(recipe)
    (root / "bg" / "a.png").unlink()                                  # missing
    with pytest.raises(AssetError, match=r"bg/a\.png: missing"):
        build_library(recipe)
    assert cli_main(["assets", "scan", str(root), "--manifest", str(man), "-q"]) == 0
    build_library(recipe)
    write_png(root / "fg" / "new.png", np.dstack([noise_rgb(80, 80, 1), blob_alpha(80, 80, 1)]))
    with pytest.raises(AssetError, match=r"fg/new\.png: not in the pinning manifest"):
        build_library(recipe)


def test_missing_asset_folder_names_it(write_recipe, tmp_path):
    with pytest.raises(FileNotFoundError, match="nothere"):
        build_library(load_recipe(write_recipe(backgrounds="nothere")))


def test_tiff_webp_and_exr_assets(write_recipe, tmp_path, tiny_cutouts):
    import OpenEXR

    d = tmp_path / "mixed"
    d.mkdir()
    img = noise_rgb(70, 90, 7)
    assert cv2.imwrite(str(d / "t.tif"), img[:, :, ::-1])
    assert cv2.imwrite(str(d / "w.webp"), img[:, :, ::-1], [cv2.IMWRITE_WEBP_QUALITY, 101])
    lin = np.random.default_rng(1).random((66, 80, 3)).astype(np.float32)
    chans = {c: np.ascontiguousarray(lin[:, :, i]) for i, c in enumerate("RGB")}
    OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}, chans).write(str(d / "e.exr"))
    for verify in ("decode", "header"):
        lib = build_library(load_recipe(write_recipe(backgrounds=d, foregrounds=tiny_cutouts, verify=verify)))
        assert [a.id for a in lib.backgrounds] == ["bg/e", "bg/t", "bg/w"]
        assert lib["bg/e"].size == (80, 66)
        assert np.array_equal(lib.load_background(lib["bg/e"]), lin)   # EXR is linear already
        t, w = lib.load_background(lib["bg/t"]), lib.load_background(lib["bg/w"])
        assert np.array_equal(t, w)                                     # lossless WebP == TIFF


def test_header_mode_still_decodes_mattes(write_recipe, tiny_bg_dir, tiny_fg_pairs):
    write_png(tiny_fg_pairs / "fg" / "empty.png", noise_rgb(80, 96, 4))
    write_png(tiny_fg_pairs / "alpha" / "empty.png", np.zeros((80, 96), np.uint8))
    lib = build_library(load_recipe(write_recipe(backgrounds=tiny_bg_dir, foregrounds=tiny_fg_pairs,
                                                 verify="header")))
    assert "empty alpha" in dict(lib.skipped)[str(tiny_fg_pairs / "fg" / "empty.png")]
    assert all(a.bbox is not None and a.bbox[2] < a.size[0] for a in lib.foregrounds)


def test_8bit_loads_use_the_exact_table_and_the_cache_is_bounded(write_recipe, shared_assets):
    from dofsynth.assets import AssetLibrary
    from dofsynth.color import srgb_to_linear
    from dofsynth.io import decode_image

    lib = build_library(load_recipe(write_recipe(backgrounds=shared_assets / "bg", foregrounds=shared_assets)))
    bg = lib["bg/kodak_kodim01"]
    img = lib.load_background(bg)
    want = srgb_to_linear(decode_image((shared_assets / "bg" / "kodak_kodim01.png").read_bytes())[..., :3])
    assert img.dtype == np.float32 and not img.flags.writeable
    np.testing.assert_allclose(img, want, rtol=2e-6, atol=1e-9)  # table vs float32 formula: rounding only
    car = lib["fg/rembg_car-2"]
    rgb, alpha = lib.load_foreground(car)
    a8 = cv2.imread(str(shared_assets / "alpha" / "rembg_car-2.png"), cv2.IMREAD_UNCHANGED)
    a = (a8 if a8.ndim == 2 else a8[..., -1]).astype(np.float32) / 255.0
    np.testing.assert_array_equal(alpha, np.where(a >= np.float32(0.98), np.float32(1.0), a))  # assets.opaque_from
    assert lib.load_background(bg) is img  # cached
    small = AssetLibrary(lib.backgrounds, lib.foregrounds, {a.id: lib.splits[a.id] for a in (*lib.backgrounds, *lib.foregrounds)},
                         cache_bytes=img.nbytes - 1)
    first = small.load_background(bg)
    assert small.load_background(bg) is not first and np.array_equal(small.load_background(bg), first)  # too big to keep
    two = AssetLibrary(lib.backgrounds, lib.foregrounds, {a.id: lib.splits[a.id] for a in (*lib.backgrounds, *lib.foregrounds)},
                       cache_bytes=int(img.nbytes * 1.5))
    a, b = two.load_background(bg), two.load_background(lib["bg/kodak_kodim08"])
    assert two.load_background(lib["bg/kodak_kodim08"]) is b and two.load_background(bg) is not a  # evicted by bytes
