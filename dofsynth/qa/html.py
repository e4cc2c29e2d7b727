"""The QA page of a data set: `write_html(out_dir, html_dir)` writes one self-contained folder
(index.html + img/) that works from file:// with no server.

The page (script and styles inline, the samples as JSON inside it, docs/qa.md):
  * a row per sample: thumbnails (JPEG, `thumb` px high) of the all-in-focus image, the
    disparity, the coverages and every target; a click opens the full-size image in a viewer;
  * the viewer: F or Space flips between the all-in-focus image and the chosen target (0..9
    choose), D and C show the disparity and the coverages, Z cycles fit / 100 % / 400 % zoom
    around the clicked point, the arrows step through the shown samples, Esc closes; a focus
    slider over the focus sweep (the scene re-rendered from its JSON at focus 0..1) for the
    first `sweep` samples;
  * filters by split, background mode, focus, max CoC and asset, and each sample's record.
The full images are the shards' own PNG bytes; only thumbnails are re-encoded.
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
from dofsynth.io import encode_png
from dofsynth.manifest import recipe_from_manifest
from dofsynth.qa import dataset as ds
from dofsynth.qa.draw import colorize_disparity, coverage_overlay
from dofsynth.qa.sheets import asset_names, choose_keys, sweep_images
from dofsynth.scene import Scene

PAGE = Path(__file__).with_name("page.html")  # the page template: {title}, {data}


def _thumb(img: np.ndarray, height: int) -> bytes:
    """JPEG bytes of an sRGB (H, W, 3) image (float in [0, 1] or uint8), `height` px high."""
    h, w = img.shape[:2]
    small = resize(np.asarray(img), max(1, round(w * height / h)), height)
    small = small if small.dtype == np.uint8 else to_uint8(small)
    ok, buf = cv2.imencode(".jpg", np.ascontiguousarray(small[:, :, 2::-1]), [cv2.IMWRITE_JPEG_QUALITY, 88])
    if not ok:
        raise ValueError(f"JPEG encoding failed for a thumbnail of shape {img.shape}")
    return buf.tobytes()


def background_mode(record: dict) -> str:
    """"flat", "ramp horizontal" or "ramp vertical": what the filter offers."""
    bg = record.get("background", {})
    return "flat" if bg.get("mode") != "ramp" else f"ramp {bg.get('direction', '')}".strip()


def _save(img_dir: Path, name: str, full: bytes | None, preview: np.ndarray, thumb: int) -> dict:
    """Write img/NAME.png (the given bytes, or `preview` encoded) and img/NAME.t.jpg."""
    atomic_write_bytes(img_dir / f"{name}.png", full if full is not None else encode_png(preview))
    atomic_write_bytes(img_dir / f"{name}.t.jpg", _thumb(preview, thumb))
    return {"src": f"img/{name}.png", "thumb": f"img/{name}.t.jpg"}


def write_html(out_dir, html_dir, split: str = "test", n: int = 24, seed: int = 0, sweep: int = 3,
               sweep_steps: int = 7, thumb: int = 192) -> Path:
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
    for sp in splits:
        keys = choose_keys(manifest, sp, n, seed)
        raw = ds.read_members_many(out_dir, sp, keys)
        for key in keys:
            s = ds.decode_sample(raw[key], key)
            rec, members = s["record"], raw[key]
            images = {"aif": _save(img_dir, f"{key}.aif", members["aif.png"], s["aif"], thumb),
                      "disparity": _save(img_dir, f"{key}.disparity", None, colorize_disparity(s["depth"]), thumb),
                      "coverage": _save(img_dir, f"{key}.coverage", None, coverage_overlay(s["aif"], s["cover"]), thumb),
                      "targets": [_save(img_dir, f"{key}.dof.{i}", members[f"dof.{i}.png"], d, thumb)
                                  for i, d in enumerate(s["dof"])]}
            atomic_write_bytes(img_dir / f"{key}.json", members["json"])
            atomic_write_bytes(img_dir / f"{key}.depth.exr", members["depth.exr"])
            if swept < sweep and sweep_steps >= 1:
                library, images["sweep"] = _sweep(out_dir, manifest, library, rec, key, img_dir, sweep_steps)
                swept += 1
            t = rec.get("targets", [])
            items.append({"key": key, "split": sp, "mode": background_mode(rec), "assets": asset_names(rec),
                          "focus": [x["focus"] for x in t], "max_coc": [x["max_coc"] for x in t],
                          "images": images, "record": rec})
    title = f"dofsynth {manifest['recipe'].get('name', '')}: {split}, seed {seed}"
    data = json.dumps({"title": title, "source": str(out_dir), "thumb": thumb, "samples": items,
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
        atomic_write_bytes(img_dir / f"{key}.sweep.{i}.png", encode_png(img))
        out.append({"focus": float(f), "src": f"img/{key}.sweep.{i}.png"})
    return library, out
