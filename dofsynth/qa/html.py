"""The QA page of a data set: `write_html(out_dir, html_dir)` writes one self-contained folder
(index.html + img/) that works from file:// with no server.

The page (script and styles inline, the samples as JSON inside it, docs/qa.md):
  * a row per sample: thumbnails (JPEG, `thumb` px high) of the all-in-focus image, the
    disparity, the coverages and every target; a click opens the full-size image in a viewer
    (a WebP preview at quality 90, loaded only then: the page stays small; the lossless
    members are in the shards);
  * review marks: reject / keep and a note per sample (buttons, or X / K in the viewer), kept
    in the browser's storage and downloaded as qa-marks.json (dofsynth.qa.marks), which
    `dofsynth qa apply` records beside the manifest;
  * the viewer: F or Space flips between the all-in-focus image and the chosen target (0..9
    choose), D and C show the disparity and the coverages, Z cycles fit / 100 % / 400 % zoom
    around the clicked point, the arrows step through the shown samples, Esc closes; a focus
    slider over the focus sweep (the scene re-rendered from its JSON at focus 0..1) for the
    first `sweep` samples;
  * filters by split, background mode, focus, max CoC and asset, and each sample's record.
"""
from __future__ import annotations

import html
import json
from pathlib import Path

import cv2
import numpy as np

from dofsynth.assets import build_library
from dofsynth.files import atomic_write_bytes
from dofsynth.image import resize, to_uint8
from dofsynth.manifest import recipe_from_manifest
from dofsynth.qa import dataset as ds
from dofsynth.qa.draw import colorize_disparity, coverage_overlay
from dofsynth.qa.marks import FORMAT as MARKS_FORMAT
from dofsynth.qa.marks import set_marks
from dofsynth.qa.sheets import asset_names, choose_keys, sweep_images
from dofsynth.scene import Scene

PAGE = Path(__file__).with_name("page.html")  # the page template: {title}, {data}


# Full-size previews: WebP at quality 90 (half the bytes of JPEG at the same quality, measured
# on the demo set: 0.19 MB a sample with thumbnails, docs/qa.md); thumbnails: JPEG at 80, 4:4:4.
PREVIEW = (".webp", [cv2.IMWRITE_WEBP_QUALITY, 90])
THUMB = (".jpg", [cv2.IMWRITE_JPEG_QUALITY, 80, cv2.IMWRITE_JPEG_SAMPLING_FACTOR, cv2.IMWRITE_JPEG_SAMPLING_FACTOR_444])


def _encode(img: np.ndarray, kind: tuple, height: int | None = None) -> bytes:
    """`kind` (PREVIEW or THUMB) bytes of an sRGB (H, W, 3) image (float in [0, 1] or uint8), at
    its size or `height` px high."""
    h, w = img.shape[:2]
    img = np.asarray(img) if height is None else resize(np.asarray(img), max(1, round(w * height / h)), height)
    img = img if img.dtype == np.uint8 else to_uint8(img)
    ok, buf = cv2.imencode(kind[0], np.ascontiguousarray(img[:, :, 2::-1]), kind[1])
    if not ok:
        raise ValueError(f"{kind[0]} encoding failed for an image of shape {img.shape}")
    return buf.tobytes()


def background_mode(record: dict) -> str:
    """"flat", "ramp horizontal" or "ramp vertical": what the filter offers."""
    bg = record.get("background", {})
    return "flat" if bg.get("mode") != "ramp" else f"ramp {bg.get('direction', '')}".strip()


def _save(img_dir: Path, name: str, image: np.ndarray, thumb: int) -> dict:
    """Write img/NAME.webp (the full-size preview, opened on demand) and img/NAME.t.jpg."""
    atomic_write_bytes(img_dir / f"{name}.webp", _encode(image, PREVIEW))
    atomic_write_bytes(img_dir / f"{name}.t.jpg", _encode(image, THUMB, thumb))
    return {"src": f"img/{name}.webp", "thumb": f"img/{name}.t.jpg"}


def write_html(out_dir, html_dir, split: str = "test", n: int = 24, seed: int = 0, sweep: int = 3,
               sweep_steps: int = 7, thumb: int = 192, progress=None) -> Path:
    """Write `html_dir/index.html` and `html_dir/img/` for `n` samples of `split` ("all": `n`
    of every split), picked as `write_sheet` picks them (same seed, same samples); the first
    `sweep` samples get a focus sweep of `sweep_steps` focus values from 0 to 1. Returns the page."""
    out_dir, html_dir = Path(out_dir), Path(html_dir)
    manifest = ds.load(out_dir)
    splits = ds.manifest_splits(manifest) if split == "all" else [split]
    img_dir = html_dir / "img"
    img_dir.mkdir(parents=True, exist_ok=True)
    items, swept = [], 0
    library = None
    marks = set_marks(out_dir)
    for sp in splits:
        keys = choose_keys(manifest, sp, n, seed)
        shard_of = {k: sh for sh in ds.manifest_shards(manifest, sp) for k in sh.keys()}
        raw = ds.read_members_many(out_dir, sp, keys)
        for key in keys:
            s = ds.decode_sample(raw.pop(key), key)
            rec = s["record"]
            images = {"aif": _save(img_dir, f"{key}.aif", s["aif"], thumb),
                      "disparity": _save(img_dir, f"{key}.disparity", colorize_disparity(s["depth"]), thumb),
                      "coverage": _save(img_dir, f"{key}.coverage", coverage_overlay(s["aif"], s["cover"]), thumb),
                      "targets": [_save(img_dir, f"{key}.dof.{i}", d, thumb) for i, d in enumerate(s["dof"])]}
            if progress:
                progress(1)
            if swept < sweep and sweep_steps >= 1:
                library, images["sweep"] = _sweep(out_dir, manifest, library, rec, key, img_dir, sweep_steps)
                swept += 1
            t = rec.get("targets", [])
            m = marks.get(key, {})
            items.append({"key": key, "split": sp, "mode": background_mode(rec), "assets": asset_names(rec),
                          "focus": [x["focus"] for x in t], "max_coc": [x["max_coc"] for x in t],
                          "images": images, "record": rec, "shard": shard_of[key].path,
                          "shard_sha256": shard_of[key].sha256, "mark": m.get("mark", ""), "note": m.get("note", "")})
    title = f"dofsynth {manifest['recipe'].get('name', '')}: {split}, seed {seed}"
    data = json.dumps({"title": title, "source": str(out_dir), "thumb": thumb, "samples": items,
                       "recipe_sha256": manifest["recipe"]["sha256"], "marks_format": MARKS_FORMAT,
                       "total": {sp: len(ds.split_keys(manifest, sp)) for sp in splits}}, sort_keys=True)
    page = PAGE.read_text(encoding="utf-8").replace("{title}", html.escape(title)).replace(
        "{data}", data.replace("</", "<\\/"))
    path = html_dir / "index.html"
    atomic_write_bytes(path, page.encode("utf-8"))
    return path


def _sweep(out_dir, manifest, library, record, key, img_dir, steps):
    """(library, [{"focus", "src"}] or {"error": why}): the scene re-rendered at `steps` focus
    values with its first target's max CoC."""
    try:
        if library is None:
            library = build_library(recipe_from_manifest(manifest, out_dir))
        focuses = np.linspace(0.0, 1.0, steps)
        frames = sweep_images(Scene.from_dict(record), library, focuses)
    except Exception as exc:  # the page is still useful without the sweep
        return library, {"error": f"{type(exc).__name__}: {exc}"}
    out = []
    for i, (f, img) in enumerate(zip(focuses, frames)):
        atomic_write_bytes(img_dir / f"{key}.sweep.{i}.webp", _encode(img, PREVIEW))
        out.append({"focus": float(f), "src": f"img/{key}.sweep.{i}.webp"})
    return library, out
