"""`dofsynth stats OUT`: histograms and counts of a data set, as a chart and as JSON."""
from __future__ import annotations

from dofsynth.progress import say


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "stats",
        help="chart (and JSON) of a data set's parameter, CoC, coverage and asset statistics",
        description=(
            "Per split: histograms of the target focus, the plane disparities f0 and f1, the ramp "
            "ends b0 and b1, the CoC radius |max_coc * (disparity - focus)| over all pixels of all "
            "targets, and the foreground coverages (share of pixels with alpha > 0.5); counts of "
            "background modes, ramp directions and asset usage. Writes a PNG of bar charts and, "
            "with --json, the same numbers (bin edges and counts)."
        ),
    )
    p.add_argument("out", help="the data set folder (holds manifest.json)")
    p.add_argument("--out", dest="path", default=None, metavar="PNG",
                   help="where to write the chart (default: OUT/stats.png)")
    p.add_argument("--json", default=None, metavar="FILE", help="also write the numbers as JSON")
    p.add_argument("--split", action="append", default=None,
                   help="only this split (repeatable; default: every split)")
    p.add_argument("--marked", action="store_true",
                   help="also list every sample a review marked (OUT/qa-marks.json): key, mark, note")
    p.set_defaults(func=run)


def run(args) -> int:
    from pathlib import Path

    from dofsynth.files import check_writable
    from dofsynth.progress import bar as progress_bar
    from dofsynth.qa.dataset import sample_count
    from dofsynth.qa.marks import marks_summary, set_marks
    from dofsynth.qa.stats import write_stats

    check_writable(args.path or Path(args.out) / "stats.png", "stats chart")
    if args.json:
        check_writable(args.json, "stats JSON")
    with progress_bar(sample_count(args.out, args.split), "stats", leave=False) as bar:
        png, js, stats = write_stats(args.out, path=args.path, json_path=args.json, splits=args.split,
                                     progress=bar.update)
    for split, st in stats["splits"].items():
        h = st["histograms"]
        say(f"{split}: {st['samples']} samples, {h['focus']['total']} targets, "
            f"{h['coc']['total']} target pixels; backgrounds {st['counts']['background_mode']}")
    marks = set_marks(args.out)
    if marks:
        say(f"review marks: {marks_summary(marks)} (OUT/qa-marks.json; training leaves rejected samples out)")
    if args.marked:
        for key, m in sorted(marks.items()):
            say(f"  {key}  {m['mark']:<6}  {m['note']}")
    say(png)
    if js:
        say(js)
    return 0
