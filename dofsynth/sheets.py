"""Contact sheets of a finished data set: one row per sample, readable at a glance.

A row shows the all-in-focus image, the disparity map in a colour map with a 0..1 scale bar,
the two foreground coverages as an overlay on the image (front tinted red, middle tinted green,
each outlined), and every DoF target; a caption strip above the row names the sample key and
its assets, and a label strip under each tile gives its numbers (focus and max CoC for a
target). A header row names the columns. Samples are chosen with `--seed`, deterministically.

`write_html` writes the same rows as a static page whose images open at full resolution, and a
focus sweep (one scene re-rendered from its JSON at several focus values) for a few samples.

Drawing is plain numpy + OpenCV (`cv2.putText` with measured text sizes); images are RGB uint8.
"""
from __future__ import annotations

import html
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from dofsynth import dataset as ds
from dofsynth.io import atomic_write_bytes, encode_png

FONT = cv2.FONT_HERSHEY_SIMPLEX
BG = (24, 24, 24)            # sheet background (RGB)
FG = (235, 235, 235)         # text
DIM = (150, 150, 150)        # secondary text, ticks
COLORMAP = cv2.COLORMAP_TURBO
FRONT_TINT = (255, 40, 40)   # red
MIDDLE_TINT = (40, 255, 40)  # green


# ---------------------------------------------------------------- text and small drawing helpers
def text_size(text: str, scale: float = 0.45, thickness: int = 1) -> tuple[int, int, int]:
    """(width, ascent, descent) in pixels of `text` drawn with `put_text`."""
    (w, h), base = cv2.getTextSize(text, FONT, scale, thickness)
    return w, h, base


def fit_text(text: str, width: int, scale: float = 0.45) -> str:
    """`text`, shortened with '...' until it fits `width` pixels."""
    if text_size(text, scale)[0] <= width:
        return text
    while text and text_size(text + "...", scale)[0] > width:
        text = text[:-1]
    return text + "..." if text else ""


def put_text(img: np.ndarray, text: str, x: int, y_top: int, color=FG, scale: float = 0.45,
             thickness: int = 1, max_width: int | None = None) -> int:
    """Draw `text` with its top-left corner at (x, y_top); returns the drawn width. Text is
    shortened to `max_width` pixels when given, so labels never run into their neighbours."""
    if max_width is not None:
        text = fit_text(text, max_width, scale)
    w, h, _ = text_size(text, scale, thickness)
    cv2.putText(img, text, (int(x), int(y_top + h)), FONT, scale, color, thickness, cv2.LINE_AA)
    return w


def to_u8(img: np.ndarray) -> np.ndarray:
    """float [0, 1] -> uint8 (H, W, 3) (grey replicated)."""
    img = np.asarray(img)
    if img.dtype != np.uint8:
        img = np.floor(np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8)
    if img.ndim == 2:
        img = img[:, :, None]
    if img.shape[2] == 1:
        img = np.repeat(img, 3, axis=2)
    return np.ascontiguousarray(img[:, :, :3])


def resize(img: np.ndarray, w: int, h: int, nearest: bool = False) -> np.ndarray:
    if img.shape[1] == w and img.shape[0] == h:
        return img
    if nearest:
        interp = cv2.INTER_NEAREST
    else:
        interp = cv2.INTER_AREA if w < img.shape[1] else cv2.INTER_LINEAR
    out = cv2.resize(img, (int(w), int(h)), interpolation=interp)
    return out if out.ndim == img.ndim else out[:, :, None]


def colorize_disparity(disparity: np.ndarray) -> np.ndarray:
    """Disparity in [0, 1] (H, W) -> RGB uint8 through the colour map (0 = far, 1 = near)."""
    q = np.floor(np.clip(np.nan_to_num(disparity, nan=0.0), 0, 1) * 255 + 0.5).astype(np.uint8)
    return np.ascontiguousarray(cv2.applyColorMap(q, COLORMAP)[:, :, ::-1])


def colormap_lut() -> np.ndarray:
    """(256, 3) RGB uint8: the colour of each quantised disparity level."""
    return colorize_disparity(np.arange(256, dtype=np.float32)[None, :] / 255.0)[0]


def coverage_overlay(aif: np.ndarray, cover: np.ndarray, outline: int = 1) -> np.ndarray:
    """The image dimmed, the front coverage tinted red and the middle one green (each by its
    alpha), with an outline at alpha 0.5. `aif` (H, W, 3) uint8 or float, `cover` (H, W, 2)."""
    base = to_u8(aif).astype(np.float32) * 0.55
    front = np.clip(cover[:, :, 0], 0, 1)[:, :, None]
    middle = np.clip(cover[:, :, 1], 0, 1)[:, :, None]
    out = base * (1 - 0.5 * middle) + 0.5 * middle * np.float32(MIDDLE_TINT)
    out = out * (1 - 0.5 * front) + 0.5 * front * np.float32(FRONT_TINT)
    out = np.clip(out + 0.5, 0, 255).astype(np.uint8)
    for a, colour in ((cover[:, :, 1], MIDDLE_TINT), (cover[:, :, 0], FRONT_TINT)):
        mask = (a >= 0.5).astype(np.uint8)
        contours, _ = cv2.findContours(mask, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        cv2.drawContours(out, contours, -1, colour, outline, cv2.LINE_8)
    return out


def scale_bar(height: int, width: int = 12) -> np.ndarray:
    """(height, width, 3): the colour map from 1 (top) to 0 (bottom)."""
    ramp = np.linspace(1.0, 0.0, height, dtype=np.float32)[:, None]
    return colorize_disparity(np.repeat(ramp, width, axis=1))


# ---------------------------------------------------------------- layout
@dataclass(frozen=True)
class SheetLayout:
    """Where everything is on a contact sheet (pixels); rows are numbered from 0."""

    n_rows: int
    n_targets: int
    thumb_w: int
    thumb_h: int
    bar_w: int = 12           # the disparity scale bar
    bar_gap: int = 4
    tick_w: int = 30          # room for the tick labels right of the bar
    pad: int = 10             # between columns and around the sheet
    header_h: int = 46        # a title line, then the column names
    caption_h: int = 22       # sample key and assets, above each row
    label_h: int = 20         # under each tile
    row_gap: int = 10

    @property
    def columns(self) -> list[str]:
        return ["all-in-focus", "disparity (0 far, 1 near)", "coverage"] + [
            f"DoF target {i}" for i in range(self.n_targets)]

    @property
    def column_widths(self) -> list[int]:
        disp = self.thumb_w + self.bar_gap + self.bar_w + self.tick_w
        return [self.thumb_w, disp, self.thumb_w] + [self.thumb_w] * self.n_targets

    @property
    def column_x(self) -> list[int]:
        xs, x = [], self.pad
        for w in self.column_widths:
            xs.append(x)
            x += w + self.pad
        return xs

    @property
    def width(self) -> int:
        return self.pad + sum(w + self.pad for w in self.column_widths)

    @property
    def row_h(self) -> int:
        return self.caption_h + self.thumb_h + self.label_h + self.row_gap

    @property
    def height(self) -> int:
        return self.header_h + self.n_rows * self.row_h

    def row_y(self, row: int) -> int:
        """Top of row `row` (its caption strip)."""
        return self.header_h + row * self.row_h

    def tile(self, row: int, col: int) -> tuple[int, int, int, int]:
        """(x, y, w, h) of the image tile of column `col` in row `row` (the disparity tile
        without its scale bar)."""
        return self.column_x[col], self.row_y(row) + self.caption_h, self.thumb_w, self.thumb_h

    def bar(self, row: int) -> tuple[int, int, int, int]:
        x, y, w, h = self.tile(row, 1)
        return x + w + self.bar_gap, y, self.bar_w, h

    def label(self, row: int, col: int) -> tuple[int, int, int, int]:
        """(x, y, w, h) of the label strip under a tile."""
        x, y, _, h = self.tile(row, col)
        return x, y + h, self.column_widths[col], self.label_h

    def caption(self, row: int) -> tuple[int, int, int, int]:
        return self.pad, self.row_y(row), self.width - 2 * self.pad, self.caption_h


def sheet_layout(n_rows: int, n_targets: int, size_hw: tuple[int, int], thumb: int = 192) -> SheetLayout:
    """The layout for `n_rows` samples of size (H, W) with `n_targets` DoF targets each:
    tiles are `thumb` pixels high and keep the aspect ratio."""
    h, w = size_hw
    thumb_w = max(8, int(round(thumb * w / h)))
    return SheetLayout(n_rows=n_rows, n_targets=n_targets, thumb_w=thumb_w, thumb_h=int(thumb))


# ---------------------------------------------------------------- labels
def asset_names(record: dict) -> str:
    a = record.get("assets", {})
    parts = [f"{role}: {a[role].get('id', '?')}" for role in ("background", "front", "middle")
             if isinstance(a.get(role), dict)]
    return "   ".join(parts)


def _fmt(v, digits=2) -> str:
    try:
        return f"{float(v):.{digits}f}"
    except (TypeError, ValueError):
        return "?"


def tile_labels(sample: dict) -> list[str]:
    rec = sample["record"]
    bg = rec.get("background", {})
    bg_text = "flat bg" if bg.get("mode") == "flat" else (
        f"ramp {str(bg.get('direction', '?'))[:1]} {_fmt(bg.get('b0'))}->{_fmt(bg.get('b1'))}")
    h, w = sample["depth"].shape
    cover = sample["cover"]
    labels = [
        f"{w}x{h}",
        f"f0 {_fmt(rec['front']['disparity'])}  f1 {_fmt(rec['middle']['disparity'])}  {bg_text}",
        f"red front {100 * np.mean(cover[:, :, 0] > 0.5):.0f}%  green middle {100 * np.mean(cover[:, :, 1] > 0.5):.0f}%",
    ]
    labels += [f"focus {_fmt(t['focus'])}  max CoC {_fmt(t['max_coc'], 1)}px" for t in rec["targets"]]
    return labels


# ---------------------------------------------------------------- the sheet
def render_sheet(samples: list[dict], thumb: int = 192, title: str | None = None) -> np.ndarray:
    """The contact sheet (RGB uint8) of decoded samples (`record.decode_sample` dicts)."""
    if not samples:
        raise ValueError("render_sheet: no samples to show")
    n_targets = max(len(s["dof"]) for s in samples)
    lay = sheet_layout(len(samples), n_targets, samples[0]["depth"].shape, thumb)
    sheet = np.empty((lay.height, lay.width, 3), np.uint8)
    sheet[:] = BG
    if title:
        put_text(sheet, title, lay.pad, 6, DIM, 0.4, max_width=lay.width - 2 * lay.pad)
    for col, name in enumerate(lay.columns):
        put_text(sheet, name, lay.column_x[col], 24, FG, 0.5, max_width=lay.column_widths[col])
    for row, s in enumerate(samples):
        _draw_row(sheet, lay, row, s)
    return sheet


def _paste(sheet, img, box):
    x, y, w, h = box
    sheet[y:y + h, x:x + w] = img


def _draw_row(sheet: np.ndarray, lay: SheetLayout, row: int, s: dict) -> None:
    tw, th = lay.thumb_w, lay.thumb_h
    rec = s["record"]
    x, y, w, h = lay.caption(row)
    caption = f"{s['key']}    {asset_names(rec)}"
    put_text(sheet, caption, x, y + (h - text_size(caption)[1]) // 2 - 1, FG, max_width=w)

    aif = to_u8(s["aif"])
    _paste(sheet, resize(aif, tw, th), lay.tile(row, 0))
    # disparity: nearest-neighbour resize so every tile pixel is an exact colour-map entry
    _paste(sheet, colorize_disparity(resize(s["depth"], tw, th, nearest=True)), lay.tile(row, 1))
    bx, by, bw, bh = lay.bar(row)
    _paste(sheet, scale_bar(bh, bw), (bx, by, bw, bh))
    for v in (0.0, 0.5, 1.0):
        ty = int(round(by + (1 - v) * (bh - 1)))
        cv2.line(sheet, (bx + bw, ty), (bx + bw + 3, ty), DIM, 1)
        label = f"{v:g}"
        lw, lh, _ = text_size(label, 0.35)
        put_text(sheet, label, bx + bw + 5, min(max(ty - lh // 2, by), by + bh - lh), DIM, 0.35)
    cover = resize(s["cover"].astype(np.float32), tw, th)
    _paste(sheet, coverage_overlay(resize(aif, tw, th), cover), lay.tile(row, 2))
    for i, dof in enumerate(s["dof"]):
        _paste(sheet, resize(to_u8(dof), tw, th), lay.tile(row, 3 + i))
    for col, text in enumerate(tile_labels(s)):
        x, y, w, h = lay.label(row, col)
        put_text(sheet, text, x, y + 4, DIM, 0.4, max_width=w)


def choose_keys(manifest: dict, split: str, n: int, seed: int) -> list[str]:
    """`n` sample keys of `split` chosen with `seed` (same seed, same keys), in index order."""
    keys = ds.split_keys(manifest, split)
    if not keys:
        raise ValueError(f"split {split!r} has no samples")
    if n < 1:
        raise ValueError(f"--n must be >= 1, got {n}")
    rng = np.random.default_rng(np.random.SeedSequence(seed))
    pick = rng.choice(len(keys), size=min(n, len(keys)), replace=False)
    return [keys[i] for i in sorted(pick.tolist())]


def write_sheet(out_dir, split: str = "test", n: int = 24, seed: int = 0, path=None,
                thumb: int = 192) -> Path:
    """Write the contact sheet of `n` samples of `split` (chosen with `seed`) as a PNG; the
    default path is `OUT/sheet-<split>.png`. Returns the path written."""
    out_dir = Path(out_dir)
    manifest = ds.load(out_dir)
    keys = choose_keys(manifest, split, n, seed)
    samples = ds.read_samples(out_dir, split, keys)
    title = f"{manifest['recipe'].get('name', '')}  {split}  seed {seed}  {len(keys)} of {len(ds.split_keys(manifest, split))}"
    sheet = render_sheet(samples, thumb=thumb, title=title)
    path = Path(path) if path is not None else out_dir / f"sheet-{split}.png"
    atomic_write_bytes(path, encode_png(sheet))
    return path


# ---------------------------------------------------------------- HTML
def focus_sweep(record: dict, library, recipe, focuses) -> list[np.ndarray]:
    """The scene of `record` re-rendered (from its JSON, as `verify --deep` does) at each focus
    value with its first target's max CoC; RGB uint8 images."""
    from dofsynth import record as record_mod
    from dofsynth.io import decode_image
    from dofsynth.scene import Scene

    rec = dict(record)
    max_coc = float(rec["targets"][0]["max_coc"])
    rec["targets"] = [{"focus": float(f), "max_coc": max_coc} for f in focuses]
    members = record_mod.render_sample(Scene.from_dict(rec), library, recipe)
    return [to_u8(decode_image(members[f"dof.{i}.png"])) for i in range(len(focuses))]


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
        from dofsynth.assets import build_library

        recipe = ds.recipe_from_manifest(manifest, out_dir)
        library = build_library(recipe)
    except Exception as exc:  # the page is still useful without the sweep
        return f"<h2>Focus sweep</h2><p>not available: {html.escape(f'{type(exc).__name__}: {exc}')}</p>"
    focuses = np.linspace(0.0, 1.0, steps)
    parts = ["<h2>Focus sweep</h2><p>Each scene re-rendered from its JSON at focus 0 (far) to 1 "
             "(near) with its first target's max CoC.</p>"]
    for s in samples:
        key = s["key"]
        frames = focus_sweep(s["record"], library, recipe, focuses)
        figs = []
        for i, (f, img) in enumerate(zip(focuses, frames)):
            name = f"{key}.sweep.{i}.png"
            atomic_write_bytes(img_dir / name, encode_png(img))
            figs.append(f'<figure><a href="img/{name}"><img src="img/{name}" alt="{name}"></a>'
                        f'<figcaption class="lbl">focus {f:.2f}</figcaption></figure>')
        parts.append(f"<h3>{html.escape(key)}</h3><div class='sweep'>{''.join(figs)}</div>")
    return "".join(parts)
