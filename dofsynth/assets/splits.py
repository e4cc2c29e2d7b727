"""Splitting assets between train and test, so that no asset, byte-identical copy or near-duplicate
(dofsynth.assets.similar) is in both."""
from __future__ import annotations

import hashlib

from dofsynth.assets.decode import Asset


def _uniform(seed: int, asset_id: str) -> float:
    d = hashlib.sha256(f"dofsynth-split:{seed}:{asset_id}".encode("utf-8")).digest()
    return int.from_bytes(d[:8], "big") / 2.0**64


def assign_splits(assets: list[Asset], seed: int, test_share: float, need: dict[str, int],
                  groups: list[list[str]] = ()) -> dict[str, str]:
    """{asset id: split}. An asset is in test when a sha256-based uniform of (seed, id) is below
    `test_share`. Byte-identical files (same sha256) and the near-duplicates of each group in
    `groups` (dofsynth.assets.similar) share the split of the smallest id among them, so a copy
    never leaks across. If a split that must hold samples gets fewer than `need[split]`
    assets, the assets nearest the threshold move over (deterministic; only happens for tiny
    sets). Adding an asset moves no other, unless it joins two groups."""
    rep: dict[str, str] = {}
    for a in sorted(assets, key=lambda a: a.id):
        rep.setdefault(a.sha256, a.id)
    rep_of = {a.id: rep[a.sha256] for a in assets}
    alias: dict[str, str] = {}  # a group joins its members' sha256 groups under its smallest id

    def find(r: str) -> str:
        while r in alias:
            r = alias[r]
        return r

    for g in groups:
        roots = {find(rep_of[i]) for i in g if i in rep_of}
        for r in roots - {min(roots, default=None)}:
            alias[r] = min(roots)
    rep_of = {i: find(r) for i, r in rep_of.items()}
    u = {a.id: _uniform(seed, rep_of[a.id]) for a in assets}
    order = sorted(assets, key=lambda a: (u[a.id], rep_of[a.id], a.id))
    n_test = sum(1 for a in order if u[a.id] < test_share)
    n_test = max(n_test, min(need.get("test", 0), len(order)))
    n_test = min(n_test, max(0, len(order) - need.get("train", 0)))
    while 0 < n_test < len(order) and rep_of[order[n_test].id] == rep_of[order[n_test - 1].id]:
        n_test += 1  # never cut a group
    return {a.id: ("test" if i < n_test else "train") for i, a in enumerate(order)}
