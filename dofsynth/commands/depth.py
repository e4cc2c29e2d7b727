"""`dofsynth depth IMAGE --model RUN --out D.exr`: predict a photo's disparity with a trained depth network."""
from __future__ import annotations

import argparse
from pathlib import Path

from dofsynth.commands import output_file
from dofsynth.progress import say

DESCRIPTION = """\
Predict the normalized disparity (1 = nearest, 0 = farthest in the photo; min-max normalized, as
the DeepLens paper does) of one photo with a depth network trained by `dofsynth train` with a
depth config ([train] task = "depth", e.g. train-depth-tiny). The network runs at its training
scale (short side [data] crop) and the map is resized to the photo's size.

OUT: a float32 EXR (channel `disparity`, what `dofsynth render --depth` reads) or a 16-bit grey
PNG (0..65535 = 0..1), or a folder (existing, or ending in /) for IMAGE_STEM.depth.exr; written
atomically. `dofsynth render IMAGE --model RUN` without --depth does this step itself.
"""

EPILOG = """\
examples:
  dofsynth depth photo.jpg --model runs/depth --out photo_depth.exr
  dofsynth depth photo.jpg --model runs/depth --out photo_depth.png
"""


def register(subparsers) -> None:
    p = subparsers.add_parser("depth", help="predict a photo's disparity map with a trained depth network",
                              description=DESCRIPTION, epilog=EPILOG,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("image", metavar="IMAGE", help="the photo (PNG, JPEG, TIFF, WebP: sRGB; EXR: linear)")
    p.add_argument("--model", required=True, metavar="RUN", help="run folder of a depth network (dofsynth train)")
    p.add_argument("--out", required=True, metavar="OUT", help="output disparity map: .exr (float32) or .png (16-bit), or a folder")
    p.add_argument("--device", default=None, choices=["cpu", "cuda"], help="default: cuda when available")
    p.set_defaults(func=run)


def run(args) -> int:
    import numpy as np

    from dofsynth.files import atomic_write_bytes
    from dofsynth.io import encode_exr, encode_png, load_linear_rgba
    from dofsynth.train.infer import predict_depth

    out = output_file(args.out, args.image, ".depth.exr", (".exr", ".png"))
    if not Path(args.image).is_file():
        raise FileNotFoundError(f"IMAGE {args.image}: no such file")
    if not Path(args.model).exists():
        raise FileNotFoundError(f"--model {args.model}: no such run folder")
    rgb, _ = load_linear_rgba(args.image)
    d = predict_depth(args.model, rgb, device=args.device)
    if out.suffix.lower() == ".exr":
        data = encode_exr(d, "disparity", {"dofsynth:quantity": "normalized disparity (min-max per image)",
                                          "dofsynth:convention": "1 = nearest, 0 = farthest; not a distance",
                                          "dofsynth:model": str(args.model)})
    else:
        data = encode_png(np.round(np.clip(d, 0.0, 1.0) * 65535.0).astype(np.uint16))
    atomic_write_bytes(out, data)
    say(f"wrote {out} ({d.shape[1]}x{d.shape[0]}, disparity {d.min():.3f}..{d.max():.3f})")
    return 0
