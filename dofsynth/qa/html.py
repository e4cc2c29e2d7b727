"""The QA page of a data set: `write_html(out_dir, html_dir)` writes the contact sheet's rows
as a static page whose images open at full resolution, with a focus sweep (one scene
re-rendered from its JSON at several focus values) for a few samples."""
from __future__ import annotations

import html
from pathlib import Path

import numpy as np

from dofsynth.assets import build_library
from dofsynth.files import atomic_write_bytes
from dofsynth.io import encode_png
from dofsynth.qa import dataset as ds
from dofsynth.qa.draw import colorize_disparity, coverage_overlay
from dofsynth.qa.sheets import asset_names, choose_keys, sheet_layout, sweep_images, tile_labels
from dofsynth.scene import Scene


_CSS = """body{background:#181818;color:#eee;font:14px sans-serif;margin:16px}
table{border-collapse:collapse}td,th{padding:4px 6px;vertical-align:top;text-align:left}
th{position:sticky;top:0;background:#181818}img{display:block;height:%dpx}
.cap td{padding-top:14px;color:#fff;font-weight:bold}.lbl{color:#aaa;font-size:12px}
.sweep{display:flex;gap:6px}.sweep figure{margin:0}a{color:#8cf}"""


def write_html(out_dir, html_dir, split: str = "test", n: int = 24, seed: int = 0, sweep: int = 3,
               sweep_steps: int = 7, thumb: int = 192) -> Path:
    """A static page `html_dir/index.html` with the rows of `write_sheet` (same samples for the
    same seed); each image links to its full-size PNG in `html_dir/img/`. The first `sweep`
    samples also get a focus sweep at `sweep_steps` focus values from 0 to 1. Returns the page."""
    out_dir, html_dir = Path(out_dir), Path(html_dir)
    manifest = ds.load(out_dir)
    keys = choose_keys(manifest, split, n, seed)
    raw = ds.read_members_many(out_dir, split, keys)
    samples = [ds.decode_sample(raw[k], k) for k in keys]
    img_dir = html_dir / "img"
    img_dir.mkdir(parents=True, exist_ok=True)
    n_targets = max(len(s["dof"]) for s in samples)
    lay = sheet_layout(1, n_targets, samples[0]["depth"].shape, thumb)
    head = "".join(f"<th>{html.escape(c)}</th>" for c in lay.columns)
    rows = []
    for s in samples:
        key = s["key"]
        members = raw[key]
        files = [f"{key}.aif.png", f"{key}.disparity.png", f"{key}.coverage.png"] + [
            f"{key}.dof.{i}.png" for i in range(len(s["dof"]))]
        atomic_write_bytes(img_dir / files[0], members["aif.png"])
        atomic_write_bytes(img_dir / files[1], encode_png(colorize_disparity(s["depth"])))
        atomic_write_bytes(img_dir / files[2], encode_png(coverage_overlay(s["aif"], s["cover"])))
        atomic_write_bytes(img_dir / f"{key}.depth.exr", members["depth.exr"])
        atomic_write_bytes(img_dir / f"{key}.json", members["json"])
        for i in range(len(s["dof"])):
            atomic_write_bytes(img_dir / files[3 + i], members[f"dof.{i}.png"])
        labels = tile_labels(s)
        cells = "".join(
            f'<td><a href="img/{f}"><img src="img/{f}" alt="{html.escape(f)}"></a>'
            f'<div class="lbl">{html.escape(l)}</div></td>' for f, l in zip(files, labels))
        if len(s["dof"]) < n_targets:
            cells += "<td></td>" * (n_targets - len(s["dof"]))
        rows.append(f'<tr class="cap"><td colspan="{len(lay.columns)}">{html.escape(key)} '
                    f'&nbsp; {html.escape(asset_names(s["record"]))} &nbsp; '
                    f'<a href="img/{key}.json">json</a> <a href="img/{key}.depth.exr">depth.exr</a></td></tr>'
                    f"<tr>{cells}</tr>")
    sweeps = _sweep_section(out_dir, manifest, samples[:max(0, sweep)], img_dir, sweep_steps)
    title = f"dofsynth {manifest['recipe'].get('name', '')}: {split}, seed {seed}"
    page = (f"<!doctype html><html><head><meta charset='utf-8'><title>{html.escape(title)}</title>"
            f"<style>{_CSS % thumb}</style></head><body><h1>{html.escape(title)}</h1>"
            f"<p>{len(samples)} of {len(ds.split_keys(manifest, split))} samples from "
            f"{html.escape(str(out_dir))}. Click an image for full resolution. Disparity: "
            f"TURBO colour map, 0 (far, blue) to 1 (near, red).</p>"
            f"<table><tr>{head}</tr>{''.join(rows)}</table>{sweeps}</body></html>\n")
    path = html_dir / "index.html"
    atomic_write_bytes(path, page.encode("utf-8"))
    return path


def _sweep_section(out_dir, manifest, samples, img_dir, steps) -> str:
    if not samples or steps < 1:
        return ""
    try:
        recipe = ds.recipe_from_manifest(manifest, out_dir)
        library = build_library(recipe)
    except Exception as exc:  # the page is still useful without the sweep
        return f"<h2>Focus sweep</h2><p>not available: {html.escape(f'{type(exc).__name__}: {exc}')}</p>"
    focuses = np.linspace(0.0, 1.0, steps)
    parts = ["<h2>Focus sweep</h2><p>Each scene re-rendered from its JSON at focus 0 (far) to 1 "
             "(near) with its first target's max CoC.</p>"]
    for s in samples:
        key = s["key"]
        frames = sweep_images(Scene.from_dict(s["record"]), library, focuses)
        figs = []
        for i, (f, img) in enumerate(zip(focuses, frames)):
            name = f"{key}.sweep.{i}.png"
            atomic_write_bytes(img_dir / name, encode_png(img))
            figs.append(f'<figure><a href="img/{name}"><img src="img/{name}" alt="{name}"></a>'
                        f'<figcaption class="lbl">focus {f:.2f}</figcaption></figure>')
        parts.append(f"<h3>{html.escape(key)}</h3><div class='sweep'>{''.join(figs)}</div>")
    return "".join(parts)
