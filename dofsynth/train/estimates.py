"""A depth network's estimates as the disparity the DoF networks are given: in evaluation
(`dofsynth eval --depth predicted:RUN`) and in training ([augment] predicted_prob and
predicted_run).

A sample's estimate is what the depth run predicts from its all-in-focus image, mapped onto the
clean disparity's scale by the paper's 5-knot spline fit (`depth.spline_fit`: the scale, offset
and monotone warp a relative estimate leaves open; its boundaries, holes and smoothing stay the
network's) and clipped to [0, 1]: float32 normalized disparity (H, W). Training makes every
train-split sample's estimate once, before its first step, into RUN_DIR/depth-estimates.npz
(one uint16 member per sample key, d * 65535 rounded: within 8e-6 of the float; written
atomically, one map in memory at a time; reused on resume while the data set's train shards
are the same), so its loader reads them instead of running the depth network.
"""
from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np

from dofsynth import progress
from dofsynth.codecs import decode_depth
from dofsynth.files import AtomicFile
from dofsynth.io import decode_image
from dofsynth.train.checkpoint import load_model, weights_path
from dofsynth.train.config import Config
from dofsynth.train.depth import predict_disparity, spline_fit
from dofsynth.train.segments import excluded, find_segments, raw_samples

PREDICTED = "predicted:"  # depth = "predicted:RUN": what the depth network of RUN predicts
ESTIMATES = "depth-estimates.npz"  # in a DoF run trained on estimates: one member per train sample
_SCALE = 65535.0
_SHARDS = "__shards__"  # the member naming the shards the estimates are of


def check_depth_run(run: str, what: str) -> None:
    """Raise ValueError naming `what` unless `run` holds trained weights."""
    if not run or not weights_path(run).is_file():
        raise ValueError(f"{what}: no trained depth run at {run!r} (dofsynth train with [train] task = \"depth\")")


def depth_predictor(depth: str, device: str):
    """For depth = "predicted:RUN", a function (raw sample, its clean disparity (H, W)) -> the
    run's estimate of the sample (see the module docstring). None for any other `depth`."""
    if not depth.startswith(PREDICTED):
        return None
    run = depth[len(PREDICTED):]
    check_depth_run(run, f"depth {depth!r}")
    model, cfg = load_model(run, device)
    if cfg.train.task != "depth":
        raise ValueError(f"depth {depth!r}: {run} is a run of the DoF networks, not of the depth network")

    def predict(raw: dict, clean: np.ndarray) -> np.ndarray:
        image = decode_image(raw["aif.png"], f"{raw['__key__']}.aif.png")[:, :, :3]
        pred = predict_disparity(model, image, cfg.data.crop)
        return np.clip(spline_fit(pred, clean), 0.0, 1.0).astype(np.float32)
    return predict


def write_estimates(cfg: Config, data_dir: str | Path, run_dir: str | Path, device: str = "cpu") -> Path | None:
    """RUN_DIR/depth-estimates.npz with the estimate of every train-split sample of `data_dir`
    by the depth run [augment] predicted_run, made unless one of the same shards is there; None
    when [augment] predicted_prob is 0."""
    a = cfg.augment
    if a.predicted_prob <= 0:
        return None
    path = Path(run_dir) / ESTIMATES
    segments = find_segments(data_dir, "train", exclude=excluded(cfg, data_dir))
    # the shards' names and manifest hashes: a data set made again is estimated again
    shards = "\n".join(f"{Path(s.path).name} {s.sha256} {s.lo} {s.hi}" for s in segments)
    if path.is_file():
        with np.load(path) as held:
            if _SHARDS in held.files and str(held[_SHARDS]) == shards:
                return path
    predict = depth_predictor(PREDICTED + a.predicted_run, device)
    # an .npz as np.savez writes it, one member at a time (memory stays one map at any size of set)
    with AtomicFile(path) as fh, zipfile.ZipFile(fh, "w", allowZip64=True) as zf, \
            progress.bar(sum(s.hi - s.lo for s in segments), "depth estimates") as bar:
        _member(zf, _SHARDS, np.array(shards))
        for raw in raw_samples(segments, "train"):
            clean = decode_depth(raw["depth.exr"], f"{raw['__key__']}.depth.exr")
            _member(zf, raw["__key__"], np.round(predict(raw, clean) * _SCALE).astype(np.uint16))
            bar.update()
    return path


def _member(zf: zipfile.ZipFile, name: str, array: np.ndarray) -> None:
    with zf.open(f"{name}.npy", "w", force_zip64=True) as f:
        np.lib.format.write_array(f, array, allow_pickle=False)


class Estimates:
    """The estimates of a file `write_estimates` made, read on demand (each process opens the
    file itself: a dataset holding this goes to DataLoader workers by pickling)."""

    def __init__(self, path: str | Path):
        self.path, self._file = Path(path), None

    def __getstate__(self):
        return {"path": self.path, "_file": None}

    def __call__(self, key: str) -> np.ndarray:
        """The estimate of sample `key`, float32 (H, W)."""
        if self._file is None:
            self._file = np.load(self.path)
        if key not in self._file.files:
            raise ValueError(f"{self.path}: no depth estimate of sample {key} (delete the file to make it again)")
        return self._file[key].astype(np.float32) / np.float32(_SCALE)
