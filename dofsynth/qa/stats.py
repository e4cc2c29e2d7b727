"""Statistics of a finished data set, per split: the numbers (JSON) and a chart (PNG).

Per split:
- histograms over samples of the front and middle plane disparities `f0`, `f1`, of `b0`, `b1`
  (ramp backgrounds only: a flat background is at disparity 0 and records no ramp), of the
  foreground coverage (share of the frame with alpha > 0.5, front and middle), and over DoF
  targets of the focus;
- a histogram over pixels of the CoC radius `|max_coc * (disparity - focus)|` (px), for every
  pixel of every target, from the depth EXR and the target's focus and max CoC;
- counts of background mode, ramp direction, and asset usage (samples using each asset id,
  per role).

Every histogram is `{"edges": [...], "counts": [...], "total": n}` with `len(edges) ==
len(counts) + 1`, bins `[e_i, e_i+1)` and the last one closed. The chart is a grid of bar-chart
panels drawn with OpenCV (no matplotlib), one block of panels per split.
"""
from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np

from dofsynth.files import atomic_write_bytes, canonical_json
from dofsynth.io import decode_image, encode_png
from dofsynth.optics.coc import coc_radius
from dofsynth.codecs import decode_depth
from dofsynth.progress import note
from dofsynth.qa import dataset as ds
from dofsynth.qa.draw import BG, DIM, FG, put_text, text_size

UNIT_BINS = 20                 # bins over [0, 1] for disparities, focus and coverage
COC_BINS = 24
COC_STEP = 1.0 / 16            # resolution (px) at which CoC radii are counted before binning
UNIT_HISTS = ("focus", "f0", "f1", "b0", "b1", "cover_front", "cover_middle")
TITLES = {
    "focus": "focus (per target)", "f0": "f0 front disparity", "f1": "f1 middle disparity",
    "b0": "b0 (ramps)", "b1": "b1 (ramps)", "coc": "CoC radius px (per pixel)",
    "cover_front": "front coverage (alpha>0.5)", "cover_middle": "middle coverage (alpha>0.5)",
    "background_mode": "background mode", "ramp_direction": "ramp direction",
    "assets": "asset usage (top)",
}


def _unit_hist(values) -> dict:
    edges = np.linspace(0.0, 1.0, UNIT_BINS + 1)
    counts, _ = np.histogram(np.clip(np.asarray(values, np.float64), 0, 1), bins=edges)
    return {"edges": [round(float(e), 6) for e in edges], "counts": counts.tolist(), "total": int(counts.sum())}


class _CocCounter:
    """Counts |CoC| radii at COC_STEP resolution; rebinned to COC_BINS equal bins at the end."""

    def __init__(self):
        self.fine = np.zeros(0, np.int64)

    def add(self, radii: np.ndarray) -> None:
        idx = np.floor(np.abs(radii.astype(np.float64)) / COC_STEP).astype(np.int64).ravel()
        c = np.bincount(idx)
        if c.size > self.fine.size:
            self.fine = np.concatenate([self.fine, np.zeros(c.size - self.fine.size, np.int64)])
        self.fine[: c.size] += c

    def histogram(self) -> dict:
        n_fine = max(1, self.fine.size)
        width = max(1, math.ceil(n_fine / COC_BINS))          # fine steps per bin
        n_bins = math.ceil(n_fine / width)
        padded = np.zeros(n_bins * width, np.int64)
        padded[: self.fine.size] = self.fine
        counts = padded.reshape(n_bins, width).sum(axis=1)
        edges = np.arange(n_bins + 1) * width * COC_STEP
        return {"edges": [float(e) for e in edges], "counts": counts.tolist(), "total": int(counts.sum())}


def split_stats(out_dir, split: str, progress=None) -> dict:
    """The statistics of one split (see the module docstring). Decodes only each sample's
    JSON, depth and cover members."""
    out_dir = Path(out_dir)
    vals = {k: [] for k in UNIT_HISTS}
    coc = _CocCounter()
    modes: dict[str, int] = {}
    directions: dict[str, int] = {}
    assets: dict[str, dict[str, int]] = {"background": {}, "front": {}, "middle": {}}
    n = 0
    size = None
    for item in ds.iter_samples(out_dir, split, decode=False):
        key, m = item["key"], item["members"]
        rec = json.loads(m["json"].decode("utf-8"))
        depth = decode_depth(m["depth.exr"], f"{key}.depth.exr")
        cover = decode_image(m["cover.png"], f"{key}.cover.png")
        n += 1
        size = size or list(depth.shape)
        vals["f0"].append(rec["front"]["disparity"])
        vals["f1"].append(rec["middle"]["disparity"])
        bg = rec["background"]
        modes[bg["mode"]] = modes.get(bg["mode"], 0) + 1
        if bg["mode"] == "ramp":
            vals["b0"].append(bg["b0"])
            vals["b1"].append(bg["b1"])
            d = str(bg.get("direction"))
            directions[d] = directions.get(d, 0) + 1
        vals["cover_front"].append(float(np.mean(cover[:, :, 0] > 0.5)))
        vals["cover_middle"].append(float(np.mean(cover[:, :, 1] > 0.5)))
        for t in rec["targets"]:
            vals["focus"].append(t["focus"])
            coc.add(coc_radius(depth, t["focus"], t["max_coc"]))
        for role, table in assets.items():
            a = rec.get("assets", {}).get(role)
            if isinstance(a, dict):
                table[a["id"]] = table.get(a["id"], 0) + 1
        if progress:
            progress(1)
    hists = {k: _unit_hist(v) for k, v in vals.items()}
    hists["coc"] = coc.histogram()
    note(f"  {split}: {n} samples read")
    return {
        "samples": n,
        "size": size,
        "histograms": hists,
        "counts": {
            "background_mode": dict(sorted(modes.items())),
            "ramp_direction": dict(sorted(directions.items())),
            "assets": {role: dict(sorted(t.items(), key=lambda kv: (-kv[1], kv[0]))) for role, t in assets.items()},
        },
    }


def compute_stats(out_dir, splits=None, progress=None) -> dict:
    """{"dataset": path, "recipe": name, "splits": {split: split_stats(...)}} for every split
    (or the ones given)."""
    out_dir = Path(out_dir)
    manifest = ds.load(out_dir)
    names = list(splits) if splits else ds.manifest_splits(manifest)
    for s in names:
        ds.manifest_shards(manifest, s)  # refuses an unknown split, naming it
    return {"dataset": str(out_dir), "recipe": manifest["recipe"].get("name"),
            "splits": {s: split_stats(out_dir, s, progress) for s in names}}


# ---------------------------------------------------------------- drawing
PANEL_W, PANEL_H = 340, 230
COLS = 4
SPLIT_TITLE_H = 34
BAR = (90, 170, 250)
BAR_CAT = (250, 170, 90)
PANELS = ("focus", "f0", "f1", "b0", "b1", "coc", "cover_front", "cover_middle",
          "background_mode", "ramp_direction", "assets")


def _nice_max(v: int) -> int:
    if v <= 0:
        return 1
    mag = 10 ** int(math.floor(math.log10(v)))
    for m in (1, 2, 2.5, 5, 10):
        if v <= m * mag:
            return int(math.ceil(m * mag))
    return int(v)


def _fmt_count(v: int) -> str:
    for div, suf in ((1e9, "G"), (1e6, "M"), (1e3, "k")):
        if v >= div:
            return f"{v / div:.3g}{suf}"
    return str(int(v)) if float(v).is_integer() else f"{v:g}"


def _fmt_edge(e: float) -> str:
    return f"{e:.2f}".rstrip("0").rstrip(".") if e != int(e) else str(int(e))


def plot_area(x0: int, y0: int) -> tuple[int, int, int, int]:
    """(x, y, w, h) of the bar area inside the panel whose top-left corner is (x0, y0)."""
    return x0 + 48, y0 + 30, PANEL_W - 48 - 14, PANEL_H - 30 - 34


def draw_histogram(img, x0, y0, title, hist) -> None:
    """A bar chart of one histogram in the panel at (x0, y0): title, bars, y ticks (0, half,
    max) and x ticks at the edges (thinned to fit)."""
    put_text(img, f"{title}  (n={_fmt_count(hist['total'])})", x0 + 8, y0 + 8, FG, 0.45, max_width=PANEL_W - 16)
    x, y, w, h = plot_area(x0, y0)
    counts, edges = np.asarray(hist["counts"]), np.asarray(hist["edges"], np.float64)
    top = _nice_max(int(counts.max()) if counts.size else 0)
    _axes(img, x, y, w, h, top)
    nb = max(1, counts.size)
    for i, c in enumerate(counts):
        bx0, bx1 = x + int(round(i * w / nb)), x + int(round((i + 1) * w / nb)) - 1
        bh = int(round(h * c / top))
        if bh > 0:
            cv2.rectangle(img, (bx0 + 1, y + h - bh), (max(bx0 + 1, bx1), y + h - 1), BAR, -1)
    # x ticks: as many edge labels as fit without touching
    label_w = max(text_size(_fmt_edge(e), 0.35)[0] for e in edges) + 8
    step = max(1, math.ceil(label_w / max(1, w / nb)))
    for i in range(0, len(edges), step):
        tx = x + int(round(i * w / nb))
        cv2.line(img, (tx, y + h), (tx, y + h + 3), DIM, 1)
        lab = _fmt_edge(edges[i])
        lw = text_size(lab, 0.35)[0]
        put_text(img, lab, min(max(tx - lw // 2, x0 + 2), x0 + PANEL_W - lw - 2), y + h + 6, DIM, 0.35)


def draw_counts(img, x0, y0, title, table: dict[str, int], max_items: int = 8) -> None:
    """A horizontal bar chart of named counts (largest first, at most `max_items`)."""
    items = sorted(table.items(), key=lambda kv: (-kv[1], kv[0]))
    shown = items[:max_items]
    more = f", {len(items) - len(shown)} more" if len(items) > len(shown) else ""
    put_text(img, f"{title}  ({len(items)} kinds{more})", x0 + 8, y0 + 8, FG, 0.45, max_width=PANEL_W - 16)
    if not shown:
        put_text(img, "none", x0 + 16, y0 + 40, DIM, 0.4)
        return
    label_w = min(130, max(text_size(k, 0.35)[0] for k, _ in shown) + 6)
    x, y = x0 + 8 + label_w, y0 + 30
    w, h = PANEL_W - 8 - label_w - 50, PANEL_H - 30 - 12
    row = h / len(shown)
    top = max(v for _, v in shown)
    for i, (name, v) in enumerate(shown):
        ry = y + int(round(i * row))
        bh = max(2, min(22, int(row * 0.7)))
        put_text(img, name, x0 + 8, ry + (bh - text_size(name, 0.35)[1]) // 2, DIM, 0.35, max_width=label_w - 6)
        bw = int(round(w * v / top))
        if bw > 0:
            cv2.rectangle(img, (x, ry), (x + bw - 1, ry + bh - 1), BAR_CAT, -1)
        put_text(img, _fmt_count(v), x + bw + 4, ry + (bh - text_size("0", 0.35)[1]) // 2, FG, 0.35)


def _axes(img, x, y, w, h, top) -> None:
    cv2.line(img, (x - 1, y), (x - 1, y + h), DIM, 1)
    cv2.line(img, (x - 1, y + h), (x + w, y + h), DIM, 1)
    for frac in (0.0, 0.5, 1.0):
        ty = y + h - int(round(frac * h))
        cv2.line(img, (x - 4, ty), (x - 1, ty), DIM, 1)
        lab = _fmt_count(top * frac) if frac != 0.5 or top >= 2 else ""
        lw, lh, _ = text_size(lab, 0.35)
        put_text(img, lab, x - 6 - lw, ty - lh // 2, DIM, 0.35)


def _asset_table(counts: dict) -> dict[str, int]:
    short = {"background": "bg", "front": "fr", "middle": "mid"}
    return {f"{short[r]}:{k}": v for r, t in counts["assets"].items() for k, v in t.items()}


def chart_layout(n_splits: int) -> tuple[int, int, int]:
    """(width, height, rows of panels per split) of the stats chart."""
    rows = math.ceil(len(PANELS) / COLS)
    return COLS * PANEL_W, n_splits * (SPLIT_TITLE_H + rows * PANEL_H), rows


def panel_origin(split_i: int, panel_i: int) -> tuple[int, int]:
    """Top-left corner of panel `panel_i` (index into PANELS) of the `split_i`-th split."""
    _, _, rows = chart_layout(1)
    block = SPLIT_TITLE_H + rows * PANEL_H
    return (panel_i % COLS) * PANEL_W, split_i * block + SPLIT_TITLE_H + (panel_i // COLS) * PANEL_H


def render_stats(stats: dict) -> np.ndarray:
    """The chart (RGB uint8) of `compute_stats` output."""
    splits = list(stats["splits"])
    width, height, _ = chart_layout(len(splits))
    img = np.empty((height, width, 3), np.uint8)
    img[:] = BG
    for si, split in enumerate(splits):
        st = stats["splits"][split]
        _, py = panel_origin(si, 0)
        size = "x".join(str(v) for v in reversed(st["size"])) if st["size"] else "-"
        put_text(img, f"{stats.get('recipe') or ''}  split {split}: {st['samples']} samples, {size} px",
                 10, py - SPLIT_TITLE_H + 8, FG, 0.6, max_width=width - 20)
        for pi, name in enumerate(PANELS):
            x0, y0 = panel_origin(si, pi)
            cv2.rectangle(img, (x0 + 2, y0 + 2), (x0 + PANEL_W - 3, y0 + PANEL_H - 3), (48, 48, 48), 1)
            if name in st["histograms"]:
                draw_histogram(img, x0, y0, TITLES[name], st["histograms"][name])
            elif name == "assets":
                draw_counts(img, x0, y0, TITLES[name], _asset_table(st["counts"]))
            else:
                draw_counts(img, x0, y0, TITLES[name], st["counts"][name])
    return img


def write_stats(out_dir, path=None, json_path=None, splits=None, progress=None) -> tuple[Path, Path | None, dict]:
    """Compute the statistics, write the chart PNG (default `OUT/stats.png`) and, if asked,
    the JSON. Returns (png path, json path or None, stats)."""
    out_dir = Path(out_dir)
    stats = compute_stats(out_dir, splits, progress)
    png = Path(path) if path is not None else out_dir / "stats.png"
    atomic_write_bytes(png, encode_png(render_stats(stats)))
    jp = None
    if json_path is not None:
        jp = Path(json_path)
        atomic_write_bytes(jp, canonical_json(stats, indent=1))
    return png, jp, stats
