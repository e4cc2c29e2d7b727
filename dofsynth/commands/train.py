"""`dofsynth train CONFIG --data OUT --run RUN`: train (or continue training) the DeepLens networks."""
from __future__ import annotations

from dofsynth.commands import int_at_least


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "train",
        help="train the DeepLens networks (lens blur + upsampling, or depth prediction) on a data set",
        description=(
            "Train the DeepLens networks on the train split of a dofsynth data set (its last "
            "[data] val_share held out for periodic validation; the test split is left for "
            "`dofsynth eval`). RUN receives config.toml (the resolved config), log.csv, ckpt.pt "
            "(model, optimizer, step, config, RNG states) and eval results. Running the same "
            "command again continues from the checkpoint. For several GPUs: torchrun "
            "--nproc_per_node N -m dofsynth -- train ... --device cuda. Which config goes with "
            "which data recipe, and every key: `dofsynth docs training`. A config with [train] task = "
            "\"depth\" (train-depth-tiny, train-depth) trains the depth-prediction network instead, on "
            "the data set's disparity and coverage and on the [depth] rgbd and mattes folders."
        ),
    )
    p.add_argument("config", help="training config: a TOML file or a shipped name (train-tiny, train-demo, "
                                   "train-learn, train-deeplens, train-depth-tiny, train-depth; `dofsynth recipes list`)")
    p.add_argument("--data", required=True, help="data set folder written by `dofsynth generate`")
    p.add_argument("--run", required=True, help="run folder for checkpoints, logs and config")
    p.add_argument("--device", default="auto", choices=["auto", "cpu", "cuda"],
                   help="where to train (default: auto = cuda when available)")
    p.add_argument("--steps", type=int_at_least(0), default=None, help="stop after step N this time (the LR schedule still runs to train.max_steps; "
                        "run again without --steps to continue)")
    p.set_defaults(func=run, resume_hint=lambda args: "the last checkpoint is kept; run the same command again "
                                                    "to continue from it")


def run(args) -> int:
    from pathlib import Path

    from dofsynth.train.config import load
    from dofsynth.train.loop import train

    if not Path(args.data).is_dir():
        raise FileNotFoundError(f"--data {args.data}: no such data set folder")
    train(load(args.config), args.data, args.run, device=args.device, stop_at=args.steps)
    return 0
