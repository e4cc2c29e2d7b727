"""`dofsynth render IMAGE --depth DEPTH --focus F --max-coc R --out OUT`: shallow depth of field
for one photo and its depth map (the photo is one opaque plane of varying disparity); the depth
map may come from a trained depth network instead (`--model DEPTH_RUN`)."""
from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np

from dofsynth.commands import float_at_least, int_at_least, output_file
from dofsynth.progress import say

DESCRIPTION = """\
Render synthetic shallow depth of field for a single photo and its disparity map, in linear
light. The photo is treated as ONE opaque plane whose disparity varies per pixel: each pixel is
spread over a disc (or polygon) of radius |max_coc * (disparity - focus)| pixels, normalized.
There is no hidden background behind foreground objects, so at depth edges a blurred background
bleeds over a sharp foreground edge and a blurred foreground has nothing behind it to reveal
(see `dofsynth docs rendering` for the known limits; layered scenes avoid them).

DEPTH is normalized disparity (1 = nearest, 0 = infinity): a float32 EXR (channel disparity, Z
or its only channel) or an 8/16-bit grey PNG/TIFF scaled to [0, 1], or a .npy array. A map of
another size with the photo's aspect ratio is resampled to it (a note says so). A depth map
from any monocular depth network run elsewhere works too: --depth-kind disparity (relative
inverse depth, any scale: MiDaS, DPT, Depth Anything) or depth (any unit: ZoeDepth, Metric3D,
Depth Pro, Marigold) normalises it as the DeepLens paper does (inverted for depth, then
min-max to [0, 1]); a map whose range a few outliers set (a metric depth of 0) gets a warning.
`dofsynth docs rendering` has the table of common models.

--model RUN (repeatable) renders with trained networks: a run of the DoF networks replaces the
classical renderer; a run of the depth network (`[train] task = "depth"`) predicts DEPTH from
the photo when --depth is not given, so one photo is enough.

OUT is an sRGB 8-bit PNG, or a linear float32 RGB EXR when it ends in .exr; or a folder (existing,
or ending in /), which receives IMAGE_STEM.dof.png. Written atomically.
"""

EPILOG = """\
examples:
  dofsynth render photo.jpg --depth photo_depth.png --focus-at 320,240 --max-coc 12 --out dof.png
  dofsynth render photo.png --depth d.exr --focus 0.8 --max-coc 20 --aperture polygon:6:15 --highlight --out dof.exr
  dofsynth render photo.png --depth d.png --focus 0.8 --model runs/r1 --aperture-scale 1.0 --out net.png
  dofsynth render photo.jpg --depth midas.png --depth-kind disparity --focus-at 320,240 --max-coc 12 --out dof.png
  dofsynth render photo.jpg --model runs/depth --model runs/r1 --focus-at 320,240 --out dof.png
"""


def _focus_at(text: str) -> tuple[int, int]:
    try:
        x, y = (int(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected X,Y pixel coordinates, got {text!r}") from None
    return x, y


_nonneg = float_at_least(0.0)


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "render", help="shallow depth of field for one photo and its depth map",
        description=DESCRIPTION, epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("image", metavar="IMAGE", help="the photo (PNG, JPEG, TIFF, WebP: sRGB; EXR: linear)")
    p.add_argument("--depth", metavar="DEPTH",
                   help="disparity map in [0, 1], 1 = nearest (EXR, grey PNG or .npy); without it, a depth "
                        "run among --model predicts it")
    p.add_argument("--depth-kind", default="normalized", metavar="KIND",
                   help="what DEPTH holds: normalized (disparity in [0, 1], the default), disparity (any "
                        "scale) or depth (any unit); the last two are normalised to [0, 1], depth inverted")
    focus = p.add_mutually_exclusive_group(required=True)
    focus.add_argument("--focus", type=_nonneg, metavar="F", help="in-focus disparity in [0, 1]")
    focus.add_argument("--focus-at", type=_focus_at, metavar="X,Y",
                       help="focus on the disparity at pixel column X, row Y (median of a 5x5 window)")
    p.add_argument("--max-coc", type=_nonneg, metavar="R",
                   help="CoC radius in pixels at |disparity - focus| = 1 (required unless --model)")
    p.add_argument("--out", required=True, metavar="OUT",
                   help="output image: .png (sRGB 8-bit) or .exr (linear), or a folder for IMAGE_STEM.dof.png")
    p.add_argument("--aperture", default="disk", metavar="SHAPE",
                   help="disk (default), polygon:N or polygon:N:ROTATION_DEGREES (circumradius = CoC)")
    p.add_argument("--highlight", action="store_true",
                   help="boost near-white pixels to brighter-than-white before blurring, so highlights "
                        "become bright bokeh discs, and map the result back (dofsynth.render.highlight; not with --model)")
    p.add_argument("--method", default=None, metavar="METHOD",
                   help="how the blur is rendered (dofsynth.render.METHODS): layered (fast, the default), "
                        "adaptive (layered, with sub-aperture parts where a blurred edge of a layered scene lies "
                        "over a blurred plane; a single photo has no such edge, so it renders as layered), "
                        "subaperture (--cells N: N x N aperture cells, up to about N^2 times the cost; it shows what "
                        "blurred edges of layered scenes reveal, so a single photo gains little) or exact "
                        "(aperture sampling; slow, for small images); `dofsynth docs rendering` lists them")
    p.add_argument("--cells", type=int_at_least(1), default=None, metavar="N",
                   help="with a method that reads cells (subaperture): an N x N grid of aperture cells, 1..16 "
                        "(default 3)")
    p.add_argument("--cat-eye", type=_nonneg, default=0.0, metavar="S",
                   help="optical vignetting strength in [0, 1]: bokeh become cat's eyes toward the corners "
                        "(with a method that reads it: subaperture or exact; default 0)")
    p.add_argument("--model", metavar="RUN", action="append", default=[],
                   help="a training run folder: the DoF networks (render with them instead) or the depth "
                        "network (predict DEPTH); give it twice for both")
    p.add_argument("--aperture-scale", type=_nonneg, default=1.0, metavar="S",
                   help="with --model: blur strength as a fraction r*/r_max of the largest the network "
                        "learned, in (0, 1] (default 1.0)")
    p.set_defaults(func=run)


def focus_at(disparity: np.ndarray, x: int, y: int, window: int = 5) -> float:
    """Median disparity of the window x window pixels around column x, row y (clipped to the map)."""
    h, w = disparity.shape
    if not (0 <= x < w and 0 <= y < h):
        raise ValueError(f"--focus-at {x},{y} lies outside the {w}x{h} image")
    r = window // 2
    return float(np.median(disparity[max(y - r, 0) : y + r + 1, max(x - r, 0) : x + r + 1]))


def _read_inputs(args, depth_run):
    from dofsynth.io import load_linear_rgba, normalize_disparity, read_depth

    for name, path in (("IMAGE", args.image), ("--depth", args.depth)):
        if path is not None and not Path(path).is_file():
            raise FileNotFoundError(f"{name} {path}: no such file")
    rgb, _ = load_linear_rgba(args.image)
    if args.depth is None:
        from dofsynth.train.infer import predict_depth

        return rgb, predict_depth(depth_run, rgb)
    disparity, known = normalize_disparity(read_depth(args.depth), args.depth_kind)
    disparity = _fit_depth(disparity, rgb.shape[:2], args)
    if args.depth_kind != "normalized" and known.any():
        _warn_if_collapsed(disparity[_fit_mask(known, rgb.shape[:2])], args)
    if not np.all(np.isfinite(disparity)) or disparity.min() < 0 or disparity.max() > 1:
        raise ValueError(f"--depth {args.depth}: disparity must be finite and in [0, 1], "
                         f"got [{np.nanmin(disparity)}, {np.nanmax(disparity)}] (another network's raw "
                         "output: --depth-kind disparity or depth)")
    if not np.all(np.isfinite(rgb)) or rgb.min() < 0:
        raise ValueError(f"IMAGE {args.image}: colour must be finite and >= 0")
    return rgb, disparity


COLLAPSE = 0.98  # share of a normalised map's pixels within 0.05 of one end that says it collapsed


def _fit_depth(disparity: np.ndarray, shape: tuple[int, int], args) -> np.ndarray:
    """A depth map of another size than the photo, resampled to it (saying so); one of another
    aspect ratio is refused (it is not this photo's map)."""
    import cv2

    (h, w), (dh, dw) = shape, disparity.shape
    if (dh, dw) == (h, w):
        return disparity
    if abs(dw / dh - w / h) > 0.01 * (w / h):
        raise ValueError(f"--depth {args.depth} is {dw}x{dh} but IMAGE {args.image} is {w}x{h}: another aspect "
                         "ratio, so not this photo's depth map")
    interp = cv2.INTER_AREA if dw > w else cv2.INTER_LINEAR
    print(f"dofsynth render: note: --depth {args.depth} is {dw}x{dh}, IMAGE is {w}x{h}: depth resampled "
          f"({'area' if dw > w else 'bilinear'})", file=sys.stderr)
    return cv2.resize(np.ascontiguousarray(disparity, np.float32), (w, h), interpolation=interp)


def _fit_mask(mask: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    import cv2

    if mask.shape == shape:
        return mask
    return cv2.resize(mask.astype(np.uint8), (shape[1], shape[0]), interpolation=cv2.INTER_NEAREST) > 0


def _warn_if_collapsed(disp: np.ndarray, args) -> None:
    """A warning when min-max normalisation squeezed almost every pixel to one end: a few
    extreme values (a metric depth of 0 near the camera, a far outlier) dominate the range, and
    the render would be nearly uniform."""
    low, high = float(np.mean(disp < 0.05)), float(np.mean(disp > 0.95))
    if max(low, high) >= COLLAPSE:
        end = "below 0.05" if low >= high else "above 0.95"
        print(f"dofsynth render: warning: --depth {args.depth} (--depth-kind {args.depth_kind}) normalises to "
              f"{max(low, high):.1%} of its pixels {end}: a few extreme values set its range, so the blur will be "
              "nearly uniform; clip the map's outliers (a depth of 0, a far sky value) or check --depth-kind",
              file=sys.stderr)


def _runs(models: list[str]) -> dict[str, str]:
    """{task: run folder} of the --model runs: at most one of each task."""
    if not models:
        return {}
    from dofsynth.train.infer import run_task

    runs: dict[str, str] = {}
    for run_dir in models:
        if not Path(run_dir).exists():
            raise FileNotFoundError(f"--model {run_dir}: no such run folder")
        task = run_task(run_dir)
        if task in runs:
            raise ValueError(f"--model {runs[task]} and {run_dir} are both {task} runs; give one of each at most")
        runs[task] = run_dir
    return runs


def _write(path: Path, rgb: np.ndarray) -> None:
    from dofsynth.color import linear_to_srgb
    from dofsynth.io import write_exr, write_png

    if path.suffix.lower() == ".exr":
        write_exr(path, rgb)
    else:
        write_png(path, linear_to_srgb(rgb))


def _look(args):
    """The Look of the command's options; a ValueError names an option the method ignores."""
    from dofsynth.render import DEFAULT_METHOD, method_entry, readers
    from dofsynth.render.look import Highlight, Look

    method = args.method or DEFAULT_METHOD
    reads = method_entry(method).options
    for flag, name, given in (("--cells", "cells", args.cells is not None), ("--cat-eye", "cat_eye", bool(args.cat_eye))):
        if given and name not in reads:
            raise ValueError(f"{flag} applies to --method {readers(name)}, not --method {method}")
    cells = (3 if args.cells is None else args.cells) if "cells" in reads else 1
    return Look(method=method, cells=cells, cat_eye=args.cat_eye,
                highlight=Highlight() if args.highlight else None)


def run(args) -> int:
    import scipy.fft

    from dofsynth.generate.worker import keep_large_blocks
    from dofsynth.optics.aperture import parse_aperture
    from dofsynth.render.look import render_photo

    keep_large_blocks()  # this process renders one photo: keep its large blocks for reuse (0.4-1.7 s of page faults at 2048 px)

    out = output_file(args.out, args.image, ".dof.png", (".png", ".exr"))
    aperture = parse_aperture(args.aperture)
    look = _look(args)
    from dofsynth.io import DEPTH_MAP_KINDS

    if args.depth_kind not in DEPTH_MAP_KINDS:
        raise ValueError(f"--depth-kind must be one of {', '.join(DEPTH_MAP_KINDS)}, got {args.depth_kind!r}")
    runs = _runs(args.model)
    if "render" in runs and not 0.0 < args.aperture_scale <= 1.0:
        raise ValueError(f"--aperture-scale must lie in (0, 1], got {args.aperture_scale}")
    if "render" not in runs and args.max_coc is None:
        raise ValueError("--max-coc is required (unless a --model run of the DoF networks renders)")
    if args.depth is None and "depth" not in runs:
        raise ValueError("give --depth DEPTH, or a --model run of the depth network to predict it from the photo")
    rgb, disparity = _read_inputs(args, runs.get("depth"))
    focus = focus_at(disparity, *args.focus_at) if args.focus_at else args.focus
    if not 0.0 <= focus <= 1.0:
        raise ValueError(f"--focus must be a disparity in [0, 1], got {focus}")
    if "render" in runs:  # a trained network renders instead (dofsynth.train.infer)
        from dofsynth.train.infer import render_photo as network_render

        result = network_render(run_dir=runs["render"], image_linear=rgb, disparity=disparity,
                                focus=focus, aperture=args.aperture_scale)
    else:
        with scipy.fft.set_workers(os.cpu_count() or 1):
            result = render_photo(rgb, disparity, focus, args.max_coc, aperture, look)
    _write(out, np.asarray(result, dtype=np.float32))
    how = (f"network {runs['render']}, aperture scale {args.aperture_scale}" if "render" in runs
           else f"max CoC {args.max_coc} px, aperture {args.aperture}")
    if args.depth is None:
        how += f", depth predicted by {runs['depth']}"
    say(f"wrote {out} (focus {focus:.4f}, {how})")
    return 0
