"""`dofsynth qa apply MARKS OUT`: record a reviewer's marks (the QA page's qa-marks.json)."""
from __future__ import annotations

import argparse
from pathlib import Path

from dofsynth.progress import say

DESCRIPTION = """\
Review loop. On the QA page (`dofsynth sheet OUT --html DIR`) a reviewer marks samples reject or
keep, with a note, and downloads the marks as qa-marks.json. `apply` checks every mark against
the data set (the sample exists and its shard still has the sha256 the reviewer saw: a shard
made again since is a stale review, refused by name) and records them in OUT/qa-marks.json
beside the manifest, merged with earlier marks (a later mark of a sample replaces the earlier
one). Then `verify` reports them, `train` leaves rejected samples out ([data] exclude =
"rejected", the default), `stats --marked` lists them and `sheet --marked` draws them.
"""


def register(subparsers) -> None:
    p = subparsers.add_parser("qa", help="review loop: record the marks made on the QA page",
                              description=DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="qa_command", metavar="ACTION")
    a = sub.add_parser("apply", help="record the marks of a downloaded qa-marks.json in OUT/qa-marks.json",
                       description=DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter,
                       epilog="example:\n  dofsynth qa apply ~/Downloads/qa-marks.json /data/dl18k")
    a.add_argument("marks", type=Path, metavar="MARKS", help="the marks file the QA page downloaded")
    a.add_argument("out", type=Path, metavar="OUT", help="the data set folder (holds manifest.json)")
    a.set_defaults(func=run)
    p.set_defaults(func=lambda args: p.print_help() or 2)


def run(args) -> int:
    from dofsynth.files import check_writable
    from dofsynth.qa.marks import MARKS_NAME, apply_marks, marks_summary, set_marks

    check_writable(args.out / MARKS_NAME, "review marks")
    path, counts = apply_marks(args.marks, args.out)
    say(f"recorded {counts['reject']} rejected and {counts['keep']} kept samples in {path} "
        f"(the set now has {marks_summary(set_marks(args.out))})")
    return 0
