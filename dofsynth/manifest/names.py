"""The names of what a run writes into its data set folder OUT, besides the shards: one owner
for each (dofsynth.generate.folder tidies a folder by them, verify reads them)."""
from __future__ import annotations

import re

MANIFEST_NAME = "manifest.json"      # the finished data set's index (dofsynth.manifest)
PROGRESS_NAME = ".progress.jsonl"    # a run in progress (dofsynth.manifest.progress)
PART_RE = re.compile(r"^manifest\.part-(\d+)-(\d+)\.json$")
PROGRESS_PART_RE = re.compile(r"^\.progress\.part-(\d+)-(\d+)\.jsonl$")


def part_name(first: int, stop: int) -> str:
    """The partial manifest of shards first..stop-1 of the plan: "manifest.part-AAAAAA-BBBBBB.json"."""
    return f"manifest.part-{first:06d}-{stop:06d}.json"


def progress_part_name(first: int, stop: int) -> str:
    return f".progress.part-{first:06d}-{stop:06d}.jsonl"
