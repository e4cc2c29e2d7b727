"""`dofsynth sheet OUT`: a contact sheet (PNG) and optionally a static HTML page of a data set."""
from __future__ import annotations

from pathlib import Path

from dofsynth.commands import int_at_least
from dofsynth.progress import say


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "sheet",
        help="draw a contact sheet of a data set (PNG, optionally an HTML page)",
        description=(
            "Draw one row per sample: the all-in-focus image, the disparity map in a colour map "
            "with a 0..1 scale bar, the front (red) and middle (green) coverages over the image, "
            "and every DoF target labelled with its focus and max CoC; each row is captioned with "
            "the sample key and its assets. Samples are picked deterministically with --seed. "
            "With --html, also write a QA page (one folder that works from file://, no server): "
            "thumbnails that open the full image, a key to flip between the all-in-focus image and "
            "each target, zoom at 100 % and 400 %, a focus slider over a focus sweep (scenes "
            "re-rendered from their JSON), filters by split, background, focus, CoC, asset and mark, "
            "each sample's record, and review marks (reject / keep, a note) downloaded as qa-marks.json "
            "for `dofsynth qa apply`. `dofsynth docs qa` describes it."
        ),
    )
    p.add_argument("out", help="the data set folder (holds manifest.json)")
    p.add_argument("--split", default="test",
                   help="which split to show, or all: --n samples of every split, a PNG sheet each "
                        "(OUT/sheet-SPLIT.png) and one page (default: test)")
    p.add_argument("--n", type=int_at_least(1), default=24, help="how many samples, one row each (default: 24)")
    p.add_argument("--seed", type=int, default=0, help="picks the samples; the same seed shows the same ones (default: 0)")
    p.add_argument("--png", dest="path", default=None, metavar="PNG",
                   help="where to write the sheet (default: OUT/sheet-SPLIT.png)")
    p.add_argument("--thumb", type=int, default=192, help="tile height in pixels (default: 192)")
    p.add_argument("--marked", action="store_true",
                   help="draw the samples a review marked (OUT/qa-marks.json, `dofsynth qa apply`), each captioned "
                        "with its mark and note, instead of --n picked with --seed")
    p.add_argument("--html", default=None, metavar="DIR",
                   help="also write the QA page DIR/index.html and its images DIR/img/")
    p.add_argument("--sweep", type=int, default=3, help="how many samples get a focus sweep in --html (default: 3)")
    p.add_argument("--sweep-steps", type=int, default=7, help="focus values per sweep, from 0 to 1 (default: 7)")
    p.set_defaults(func=run)


def run(args) -> int:
    from dofsynth.files import check_writable
    from dofsynth.progress import bar, note
    from dofsynth.qa.dataset import load, manifest_splits
    from dofsynth.qa.html import write_html
    from dofsynth.qa.sheets import sheet_path, write_sheet

    if not 16 <= args.thumb <= 2048:
        raise ValueError(f"--thumb must be between 16 and 2048 pixels, got {args.thumb}")
    manifest = load(args.out)
    splits = manifest_splits(manifest) if args.split == "all" else [args.split]
    if len(splits) > 1 and args.path:
        raise ValueError("--png names one file: give it with one --split, not all")
    for split in splits:  # every output checked before the work (a read-only set: --png elsewhere)
        check_writable(sheet_path(args.out, split, args.path), "contact sheet")
    if args.html:
        check_writable(Path(args.html) / "index.html", "QA page")
    total = sum(min(args.n, manifest["splits"][s]["samples"]) for s in splits if s in manifest["splits"])
    with bar(total, "sheet", leave=False) as progress:
        for split in splits:
            path = write_sheet(args.out, split=split, n=args.n, seed=args.seed, path=args.path, thumb=args.thumb,
                               progress=progress.update, marked=args.marked)
            note(f"  {split}: {path}")
            say(path)
    if args.html:
        with bar(total, "page", leave=False) as progress:
            page = write_html(args.out, args.html, split=args.split, n=args.n, seed=args.seed, sweep=args.sweep,
                              sweep_steps=args.sweep_steps, thumb=args.thumb, progress=progress.update)
        say(page)
    return 0
