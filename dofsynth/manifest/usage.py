"""Asset-usage accounting of shards and data sets: which assets under which licence the samples
used, and the asset files found bad when loaded (a shard's `usage`, the manifest's `licences`
and `skipped_assets`)."""
from __future__ import annotations


class Usage:
    """What the samples of a shard (or a data set) used: per licence, how many samples use an
    asset under it and which assets (each with its count of samples), and the asset files
    found bad when loaded. `to_dict()` is what ShardInfo.usage holds and, over all shards, the
    manifest's `licences` (and its `skipped_assets`, with the library's); `merge` adds another's."""

    def __init__(self, d: dict | None = None):
        d = d or {}
        self.licences = {lic: {"samples": int(b["samples"]), "assets": dict(b["assets"])}
                         for lic, b in d.get("licences", {}).items()}
        self.bad = dict(d.get("bad_assets", {}))

    def add(self, scene, library, bad: dict[str, str], rel) -> None:
        by_licence: dict[str, set[str]] = {}
        for ref in scene.assets.values():
            by_licence.setdefault(library[ref.id].licence, set()).add(ref.id)
        for lic, ids in by_licence.items():
            block = self.licences.setdefault(lic, {"samples": 0, "assets": {}})
            block["samples"] += 1
            for i in ids:
                block["assets"][i] = block["assets"].get(i, 0) + 1
        self.bad.update({rel(p): rel(why) for p, why in bad.items()})

    def merge(self, other: "Usage") -> "Usage":
        for lic, b in other.licences.items():
            mine = self.licences.setdefault(lic, {"samples": 0, "assets": {}})
            mine["samples"] += b["samples"]
            for i, n in b["assets"].items():
                mine["assets"][i] = mine["assets"].get(i, 0) + n
        self.bad.update(other.bad)
        return self

    def to_dict(self) -> dict:
        return {"licences": {lic: {"samples": b["samples"], "assets": dict(sorted(b["assets"].items()))}
                             for lic, b in sorted(self.licences.items())},
                "bad_assets": dict(sorted(self.bad.items()))}
