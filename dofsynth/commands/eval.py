"""`dofsynth eval RUN --data OUT`: PSNR/SSIM of a trained run next to the classical renderer."""
from __future__ import annotations

from dofsynth.commands import int_at_least
from dofsynth.progress import say


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "eval",
        help="score a trained run on the test split (DoF: against the classical renderer; depth: MAE)",
        description=(
            "Run the trained networks of RUN on every target of the test split of OUT and report "
            "PSNR and SSIM (sRGB, against the rendered targets; over the frame and in three regions: "
            "the band within max CoC of a depth edge, the rest of the frame, and where no blur reaches "
            "by the clean depth, so the target is the input) next to the classical renderer given the "
            "same disparity as a single "
            "image with the options that made the targets, and the all-in-focus input. --depth "
            "chooses that disparity, the same for every method and every run, so runs trained "
            "differently are scored on the same inputs. A run of the depth network ([train] task = "
            "\"depth\") is scored by the mean absolute error of its normalized disparity, raw and after "
            "the DeepLens paper's 5-knot linear-spline fit, beside the best constant map. The table is "
            "printed and written to RUN/eval.csv and RUN/eval.json."
        ),
    )
    p.add_argument("run_dir", metavar="RUN", help="run folder written by `dofsynth train`")
    p.add_argument("--data", required=True, help="data set folder with a test split")
    p.add_argument("--split", default="test", help="which split to score (default: test)")
    p.add_argument("--limit", type=int_at_least(1), default=None, help="score only the first N samples")
    p.add_argument("--no-classical", action="store_true", help="skip the classical renderer")
    p.add_argument("--depth", default="run", metavar="WHICH",
                   help="the disparity everyone is given: gt (clean), run (the run's own training "
                        "corruption), realistic (the errors of monocular estimates together: disparity MAE "
                        "about 0.14), morph, edge_blur, noise, quantize, shift, swap, fill, warp or remap "
                        "(that kind alone, always, with the default [augment] ranges), predicted:DEPTH_RUN "
                        "(what the depth network of that run predicts from the all-in-focus image, fitted "
                        "to the clean disparity's scale by the 5-knot spline), or a TOML file whose "
                        "[augment] table is the setting (a training config, or a shipped one by name: "
                        "train-learn); default: run. The given disparity's MAE is printed with the table")
    p.add_argument("--device", default=None, choices=["cpu", "cuda"], help="default: cuda when available")
    p.set_defaults(func=run)


def run(args) -> int:
    from pathlib import Path

    from dofsynth.train.evaluate import depth_corruption, evaluate_run, format_table
    from dofsynth.train.config import AugmentConfig

    if not Path(args.run_dir).is_dir():
        raise FileNotFoundError(f"RUN {args.run_dir}: no such run folder")
    depth_corruption(args.depth, AugmentConfig())  # a bad --depth stops here, before any work
    result = evaluate_run(args.run_dir, args.data, split=args.split, limit=args.limit,
                          classical=not args.no_classical, depth=args.depth, device=args.device)
    print(format_table(result))
    say(f"written: {Path(args.run_dir) / 'eval.csv'}, {Path(args.run_dir) / 'eval.json'}")
    return 0
