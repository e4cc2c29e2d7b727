"""Contact sheets of a finished data set: one row per sample, readable at a glance.

A row shows the all-in-focus image, the disparity map in a colour map with a 0..1 scale bar,
the two foreground coverages as an overlay on the image (front tinted red, middle tinted green,
each outlined), and every DoF target; a caption strip above the row names the sample key and
its assets, and a label strip under each tile gives its numbers (focus and max CoC for a
target). A header row names the columns. Samples are chosen with `--seed`, deterministically.

dofsynth.qa.html writes the same rows as a page. Drawing: dofsynth.qa.draw; images are RGB uint8.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from dofsynth.files import atomic_write_bytes
from dofsynth.image import resize, to_rgb8
from dofsynth.io import decode_image, encode_png
from dofsynth.qa import dataset as ds
from dofsynth.qa.draw import BG, DIM, FG, colorize_disparity, coverage_overlay, put_text, scale_bar, text_size
from dofsynth.qa.marks import set_marks
from dofsynth.sample import focus_sweep
from dofsynth.scene import Scene, sample_scene

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
    n_views: int = 0          # target 0's dual-pixel views (left, right) where the set holds them

    @property
    def columns(self) -> list[str]:
        return ["all-in-focus", "disparity (0 far, 1 near)", "coverage"] + [
            f"DoF target {i}" for i in range(self.n_targets)] + VIEW_COLUMNS[:self.n_views]

    @property
    def column_widths(self) -> list[int]:
        disp = self.thumb_w + self.bar_gap + self.bar_w + self.tick_w
        return [self.thumb_w, disp, self.thumb_w] + [self.thumb_w] * (self.n_targets + self.n_views)

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


VIEW_COLUMNS = ["target 0, left half", "target 0, right half"]
VIEW_MEMBERS = ("dp.0.left.png", "dp.0.right.png")  # their members (render.members dual_pixel)


def _has_views(sample: dict) -> bool:
    """Whether a decoded sample holds target 0's dual-pixel views."""
    return all(m in sample.get("optional", {}) for m in VIEW_MEMBERS)


def sheet_layout(n_rows: int, n_targets: int, size_hw: tuple[int, int], thumb: int = 192,
                 n_views: int = 0) -> SheetLayout:
    """The layout for `n_rows` samples of size (H, W) with `n_targets` DoF targets each (and
    `n_views` dual-pixel views of target 0): tiles are `thumb` pixels high and keep the aspect
    ratio."""
    h, w = size_hw
    thumb_w = max(8, int(round(thumb * w / h)))
    return SheetLayout(n_rows=n_rows, n_targets=n_targets, thumb_w=thumb_w, thumb_h=int(thumb), n_views=n_views)


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
    opts = rec.get("options", {})
    look = "".join(f"  {k} {opts[k]:g}" for k in ("cells", "cat_eye") if opts.get(k))
    labels += [f"focus {_fmt(t['focus'])}  max CoC {_fmt(t['max_coc'], 1)}px{look}" for t in rec["targets"]]
    if _has_views(sample):
        labels += ["left half of the aperture", "right half: the two add up to target 0"]
    return labels


# ---------------------------------------------------------------- the sheet
def render_sheet(samples: list[dict], thumb: int = 192, title: str | None = None) -> np.ndarray:
    """The contact sheet (RGB uint8) of decoded samples (`record.decode_sample` dicts)."""
    if not samples:
        raise ValueError("render_sheet: no samples to show")
    n_targets = max(len(s["dof"]) for s in samples)
    views = any(_has_views(s) for s in samples)
    lay = sheet_layout(len(samples), n_targets, samples[0]["depth"].shape, thumb, len(VIEW_MEMBERS) if views else 0)
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
    caption = f"{s['key']}    {s['label'] + '    ' if s.get('label') else ''}{asset_names(rec)}"
    put_text(sheet, caption, x, y + (h - text_size(caption)[1]) // 2 - 1, FG, max_width=w)

    aif = to_rgb8(s["aif"])
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
        _paste(sheet, resize(to_rgb8(dof), tw, th), lay.tile(row, 3 + i))
    if lay.n_views and _has_views(s):
        for i, name in enumerate(VIEW_MEMBERS):
            _paste(sheet, resize(to_rgb8(s["optional"][name]), tw, th), lay.tile(row, 3 + lay.n_targets + i))
    labels = tile_labels(s)
    if len(s["dof"]) < lay.n_targets and len(labels) > 3 + len(s["dof"]):  # views after a short row's targets
        labels = labels[:3 + len(s["dof"])] + [""] * (lay.n_targets - len(s["dof"])) + labels[3 + len(s["dof"]):]
    for col, text in enumerate(labels):
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


def sheet_path(out_dir, split: str, path=None) -> Path:
    """Where `write_sheet` writes: `path`, or OUT/sheet-<split>.png."""
    return Path(path) if path is not None else Path(out_dir) / f"sheet-{split}.png"


def write_sheet(out_dir, split: str = "test", n: int = 24, seed: int = 0, path=None,
                thumb: int = 192, progress=None, marked: bool = False) -> Path:
    """Write the contact sheet of `n` samples of `split` (chosen with `seed`) as a PNG; the
    default path is `OUT/sheet-<split>.png`; `progress(1)` is called per sample decoded.
    `marked`: the samples a review marked instead (up to `n`, by key), each captioned with its
    mark and note. Returns the path written."""
    out_dir = Path(out_dir)
    manifest = ds.load(out_dir)
    marks = set_marks(out_dir)
    if marked:
        keys = sorted(k for k, m in marks.items() if m["split"] == split)[:n]
        if not keys:
            raise ValueError(f"{out_dir}: no {split} sample has a review mark (dofsynth qa apply records them)")
    else:
        keys = choose_keys(manifest, split, n, seed)
    samples = ds.read_samples(out_dir, split, keys, progress)
    for s in samples:
        if s["key"] in marks:
            s["label"] = f"{marks[s['key']]['mark'].upper()} {marks[s['key']]['note']}".strip()
    title = f"{manifest['recipe'].get('name', '')}  {split}  seed {seed}  {len(keys)} of {len(ds.split_keys(manifest, split))}"
    sheet = render_sheet(samples, thumb=thumb, title=title)
    path = sheet_path(out_dir, split, path)
    atomic_write_bytes(path, encode_png(sheet))
    return path


def sweep_images(scene: Scene, library, focuses) -> list[np.ndarray]:
    """`scene` (e.g. a record's, `Scene.from_dict`) re-rendered at each focus value with its
    first target's max CoC (dofsynth.sample.focus_sweep); RGB uint8 images."""
    members = focus_sweep(scene, library, focuses)
    return [to_rgb8(decode_image(members[f"dof.{i}.png"])) for i in range(len(focuses))]


def focus_sweep_strip(recipe, library, focuses=(0.0, 0.25, 0.5, 0.75, 1.0), height: int = 256) -> np.ndarray:
    """Test scene 0 of `recipe` rendered at each focus, side by side under a label strip (RGB
    uint8): what `dofsynth demo` writes to OUT/demo.png."""
    scene = sample_scene(recipe, library, "test", 0)
    tiles = sweep_images(scene, library, focuses)
    tiles = [resize(t, round(t.shape[1] * height / t.shape[0]), height) for t in tiles]
    strip = np.full((22, sum(t.shape[1] for t in tiles), 3), 24, np.uint8)
    x = 0
    for f, t in zip(focuses, tiles):
        put_text(strip, f"focus {f:.2f}", x + 4, 4)
        x += t.shape[1]
    return np.concatenate([strip, np.concatenate(tiles, axis=1)], axis=0)
