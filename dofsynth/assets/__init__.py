"""Assets: the background photos and foreground cutouts scenes are made from.

decode (one asset's pixels and checks), builtin (the built-in assets), scan (folders), pins
(pinning manifests), splits (train/test), library (`build_library(recipe)` -> `AssetLibrary`)."""
from dofsynth.assets.decode import Asset, AssetError
from dofsynth.assets.library import AssetLibrary, build_library

__all__ = ["Asset", "AssetError", "AssetLibrary", "build_library"]
