"""Training end to end on CPU: the CLI, resume, checkpoints, render_photo on a real photo, eval,
and two steps on the real generator's smoke data set."""
from __future__ import annotations

import csv
import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from dofsynth.cli import main
from dofsynth.color import srgb_to_linear
from dofsynth.train import checkpoint
from dofsynth.train.config import from_dict, load, to_toml
from dofsynth.train.infer import render_photo, upsampling_steps
from dofsynth.train.models import DeepLensNet
from test_train_data import make_dataset, tiny_config

ROOT = Path(__file__).resolve().parents[1]


pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    """A tiny data set, a tiny config file and one finished 4-step run."""
    root = tmp_path_factory.mktemp("train")
    data = make_dataset(root / "data", n_train=8, n_test=2, size=32)
    cfg_path = root / "tiny.toml"
    cfg_path.write_text(to_toml(tiny_config()))
    run = root / "run4"
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        assert main(["train", str(cfg_path), "--data", str(data), "--run", str(run), "--device", "cpu"]) == 0
    finally:
        torch.set_num_threads(n)
    return root, data, cfg_path, run


def _rows(run: Path) -> list[dict]:
    with open(run / "log.csv") as fh:
        return list(csv.DictReader(fh))


def test_a_run_folder_holds_config_log_and_checkpoint(setup):
    _, data, cfg_path, run = setup
    stored = load(run / "config.toml")
    assert stored.model.coc_ref == 4.0 and stored.infer.low_res_side == 16   # resolved from the data
    assert stored.data == load(cfg_path).data
    state = checkpoint.load(run / "ckpt.pt")
    assert state["step"] == 4 and set(state) >= {"model", "optimizer", "step", "config", "rng"}
    assert from_dict(state["config"]) == stored
    rows = _rows(run)
    assert [int(r["step"]) for r in rows] == [1, 2, 3, 4]
    assert rows[1]["val_loss"] and rows[3]["val_psnr"] and not rows[0]["val_loss"]   # eval every 2 steps
    assert all(np.isfinite(float(r["loss"])) for r in rows)
    assert json.loads((run / "env.json").read_text())["device"] == "cpu"


def test_stopping_and_resuming_equals_an_uninterrupted_run(setup, capsys):
    root, data, cfg_path, run4 = setup
    run = root / "run2+2"
    args = ["train", str(cfg_path), "--data", str(data), "--run", str(run)]
    assert main(args + ["--steps", "2"]) == 0
    assert checkpoint.load(run / "ckpt.pt")["step"] == 2
    with open(run / "log.csv", "a") as fh:          # a row logged after the last checkpoint
        fh.write("3,0,0.1,9.9,9.9,9.9,,,1,1\n")
    assert main(args) == 0          # the same command continues to train.max_steps
    assert "resuming" in capsys.readouterr().out
    a, b = checkpoint.load(run4 / "ckpt.pt"), checkpoint.load(run / "ckpt.pt")
    assert b["step"] == 4
    for k in a["model"]:
        assert torch.equal(a["model"][k], b["model"][k]), k
    assert [r["loss"] for r in _rows(run)] == [r["loss"] for r in _rows(run4)]
    assert main(args) == 0          # finished: nothing to do
    assert "already trained" in capsys.readouterr().out
    other = cfg_path.with_name("other.toml")
    other.write_text(to_toml(tiny_config(loss={"beta": 2.0})))
    assert main(["train", str(other), "--data", str(data), "--run", str(run)]) == 2   # refused, named


def test_checkpoint_reload_gives_the_same_outputs(tmp_path):
    torch.manual_seed(1)
    cfg = tiny_config(model={"coc_ref": 4.0}, infer={"low_res_side": 16})
    model = DeepLensNet(cfg.model)
    opt = torch.optim.AdamW(model.parameters())
    checkpoint.save(tmp_path / "ckpt.pt", model, opt, 7, 0, 3, cfg)
    again, cfg2 = checkpoint.load_model(tmp_path)
    x, s = torch.rand(1, 3, 40, 24), torch.rand(1, 1, 20, 12) - 0.5
    with torch.no_grad():
        assert all(torch.equal(p, q) for p, q in zip(model.eval()(x, s, 1), again(x, s, 1)))
    assert cfg2 == cfg
    with pytest.raises(FileNotFoundError):
        checkpoint.load_model(tmp_path / "nothing")


def test_render_photo_on_a_real_photo(setup, shared_assets):
    _, _, _, run = setup
    srgb = cv2.imread(str(shared_assets / "bg" / "kodak_kodim01.png"))[:, :, ::-1].astype(np.float32) / 255
    photo = srgb_to_linear(cv2.resize(srgb, (150, 100), interpolation=cv2.INTER_AREA))
    disparity = np.tile(np.linspace(0.1, 0.9, 150, dtype=np.float32), (100, 1))
    disparity[30:70, 50:100] = 0.7
    out = render_photo(run, photo, disparity, focus=0.7, aperture=1.0)
    assert out.shape == (100, 150, 3) and out.dtype == np.float32
    assert np.isfinite(out).all() and out.min() >= 0
    half = render_photo(run, photo, disparity, focus=0.7, aperture=0.5)
    assert half.shape == out.shape and not np.array_equal(half, out)
    small = render_photo(run, photo[:10, :12], disparity[:10, :12], focus=0.5)   # below the low-res side
    assert small.shape == (10, 12, 3)
    with pytest.raises(ValueError, match="aperture"):
        render_photo(run, photo, disparity, focus=0.7, aperture=0.0)
    with pytest.raises(ValueError, match="disparity"):
        render_photo(run, photo, disparity[:50], focus=0.7)
    with pytest.raises(FileNotFoundError):
        render_photo(run / "missing", photo, disparity, focus=0.7)


def test_upsampling_steps_reach_the_training_low_resolution():
    assert upsampling_steps(1024, 256) == 2 and upsampling_steps(1000, 256) == 2
    assert upsampling_steps(1025, 256) == 3 and upsampling_steps(200, 256) == 0


def test_eval_prints_and_writes_the_table(setup, capsys):
    _, data, _, run = setup
    assert main(["eval", str(run), "--data", str(data)]) == 0
    out = capsys.readouterr().out
    assert "network" in out and "classical" in out and "all-in-focus" in out
    table = json.loads((run / "eval.json").read_text())["table"]
    assert [r["method"] for r in table] == ["network", "classical", "all-in-focus"]
    assert all(r["n"] == 4 and 0 < r["psnr"] < 100 and -1 <= r["ssim"] <= 1 for r in table)  # 2 samples x 2 targets
    assert (run / "eval.csv").read_text().startswith("method,psnr,ssim,n")
    assert main(["eval", str(run.parent / "nope"), "--data", str(data)]) == 2


def test_config_round_trip_and_refusals(tmp_path):
    cfg = tiny_config()
    assert from_dict(__import__("tomllib").loads(to_toml(cfg))) == cfg
    with pytest.raises(ValueError, match="unknown key"):
        from_dict({"train": {"max_step": 3}})
    with pytest.raises(ValueError, match="unknown table"):
        from_dict({"trian": {}})
    with pytest.raises(ValueError, match="crop"):
        from_dict({"data": {"crop": 30, "levels": 2}})
    with pytest.raises(FileNotFoundError, match="nothing.toml"):
        load(tmp_path / "nothing.toml")
    for name in ("train-tiny.toml", "train-deeplens.toml"):
        load(ROOT / "recipes" / name)


def test_two_steps_on_the_generators_smoke_data(tmp_path, smoke_set):
    from dofsynth.train.augment import layers_from_record
    from dofsynth.io import decode_exr, decode_image
    from dofsynth.train.data import find_shards, peek_records, raw_samples

    data = smoke_set
    # the corruption's model of the layers agrees with the generator's depth maps
    raw = next(raw_samples(find_shards(data, "train")))
    record, depth, cover = json.loads(raw["json"]), decode_exr(raw["depth.exr"]), decode_image(raw["cover.png"])
    layers = layers_from_record(record, cover)
    free = (cover[:, :, 0] == 0) & (cover[:, :, 1] == 0)
    assert np.abs(depth - layers.background)[free].max() < 1e-5
    assert np.all(depth[layers.planes[1][0]] == np.float32(record["front"]["disparity"]))
    assert peek_records(find_shards(data, "train")[0])[0]["size"] == [64, 64]
    run = tmp_path / "run"
    assert main(["train", str(ROOT / "recipes" / "train-tiny.toml"), "--data", str(data), "--run", str(run),
                 "--steps", "2"]) == 0
    assert checkpoint.load(run / "ckpt.pt")["step"] == 2
    out = render_photo(run, np.full((64, 64, 3), 0.5, np.float32), np.full((64, 64), 0.5, np.float32), 0.5)
    assert out.shape == (64, 64, 3) and np.isfinite(out).all()


def test_two_processes_under_torchrun_train_together_and_rank0_writes(setup, tmp_path):
    """DistributedDataParallel on the CPU (gloo): the same code path as multi-GPU training."""
    import os
    import subprocess
    import sys

    _, data, cfg_path, _ = setup
    run = tmp_path / "ddp"
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2",
           "-m", "dofsynth", "--", "train", str(cfg_path), "--data", str(data), "--run", str(run),
           "--device", "cpu", "--steps", "2"]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=240, env=env)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert json.loads((run / "env.json").read_text())["world_size"] == 2
    assert checkpoint.load(run / "ckpt.pt")["step"] == 2
    assert [r["step"] for r in _rows(run)] == ["1", "2"]          # one writer
