"""Near-duplicate assets: a perceptual hash per photo (OpenCV's img_hash pHash) and the groups
of photos whose hashes are close, so that a resized, recompressed or brightened copy of a photo
lands in the same split as the original (dofsynth.assets.splits).

The hash is made from the file's bytes the same way whatever `assets.verify` says (a grey
decode, halved in the JPEG decoder for speed, area-reduced to 32x32, then pHash's 64-bit DCT
sign pattern), so grouping, and the split, never depend on how thoroughly files were checked.
On the shared Kodak photos a half-size JPEG copy, a quarter-size copy and a 20 % brighter copy
are 0-1 bits from the original, a 5 % crop 12-14, different photos 23 bits or more apart.
"""
from __future__ import annotations

import cv2
import numpy as np

from dofsynth.assets.decode import AssetError, decode_asset, is_exr
from dofsynth.color import linear_to_srgb8

HASH_SIDE = 32        # the grey image is area-reduced to this square before hashing
MAX_DISTANCE = 10     # photos at most this many of 64 bits apart are near-duplicates
_JPEG = (".jpg", ".jpeg", ".jpe", ".jfif")


def hash_grey(grey: np.ndarray) -> int:
    """The 64-bit perceptual hash of an 8-bit grey image (any size)."""
    small = cv2.resize(np.ascontiguousarray(grey), (HASH_SIDE, HASH_SIDE), interpolation=cv2.INTER_AREA)
    return int.from_bytes(cv2.img_hash.pHash(small).tobytes(), "big")


def perceptual_hash(data: bytes, path: str) -> int:
    """The perceptual hash of an image file's bytes; AssetError names a file that cannot be decoded."""
    if is_exr(path):  # linear light: to sRGB codes like any other photo
        img = decode_asset(data, path)
        grey = linear_to_srgb8(np.clip(img[..., :3].mean(axis=2) if img.shape[2] >= 3 else img[..., 0], 0, 1))
        return hash_grey(grey)
    flag = cv2.IMREAD_REDUCED_GRAYSCALE_2 if path.lower().endswith(_JPEG) else cv2.IMREAD_GRAYSCALE
    grey = cv2.imdecode(np.frombuffer(data, np.uint8), flag)
    if grey is None:
        raise AssetError(f"{path}: not a readable image (cannot decode it)")
    return hash_grey(grey)


def near_duplicate_groups(hashes: dict[str, int], max_distance: int = MAX_DISTANCE) -> list[list[str]]:
    """Groups (sorted lists of 2 or more ids, sorted by their first id) of the ids whose hashes
    are linked by chains of pairs at most `max_distance` bits apart (all pairs, in blocks)."""
    ids = sorted(hashes)
    if len(ids) < 2:
        return []
    h = np.array([hashes[i] for i in ids], dtype=np.uint64)
    parent = list(range(len(ids)))

    def root(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    block = 512
    for s in range(0, len(ids), block):
        d = np.bitwise_count(h[s:s + block, None] ^ h[None, :])  # (block, n) bits apart
        rows, cols = np.nonzero(d <= max_distance)
        for r, c in zip(rows + s, cols):
            if c > r:
                a, b = root(int(r)), root(int(c))
                if a != b:
                    parent[max(a, b)] = min(a, b)
    groups: dict[int, list[str]] = {}
    for i, name in enumerate(ids):
        groups.setdefault(root(i), []).append(name)
    return sorted((g for g in groups.values() if len(g) > 1), key=lambda g: g[0])
