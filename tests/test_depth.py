"""The depth-prediction module: the network's structure and gradients, its loss against hand
values, the spline-fit metric, the backbone-weights file, the data sources and their mixed
batches, a tiny model that overfits, and the commands on a real photo."""
from __future__ import annotations

import csv
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from dofsynth.cli import main
from dofsynth.io import normalize_disparity, read_depth, read_image
from dofsynth.train.config import Config, from_dict, load, replace
from dofsynth.train.depth import (DepthNet, depth_errors, depth_loss, load_backbone, minmax,
                                  predict_disparity, spline_fit)
from dofsynth.train.depth_data import DepthMix, Item, fit_crop, load_item, make_depth_loader, pair_files, sources
from conftest import torchrun_failure

ROOT = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.usefixtures("one_torch_thread")


def small(**depth) -> Config:
    base = {"backbone": "resnet18", "width": 8, "decoder_width": 16, **depth}
    return from_dict({"train": {"task": "depth", "max_steps": 20, "warmup_steps": 2, "lr": 3e-3,
                                "log_interval": 5, "eval_interval": 10, "checkpoint_interval": 10},
                      "data": {"crop": 32, "batch_size": 4, "num_workers": 0}, "depth": base})


def test_the_encoder_is_torchvisions_resnet50_up_to_res4f_with_an_atrous_last_stage():
    net = DepthNet(from_dict({"train": {"task": "depth"}}).depth)
    names = net.encoder.state_dict().keys()
    # torchvision's resnet50 has 25,557,032 parameters; without layer4 (14,964,736) and fc
    # (2,049,000) that leaves 8,543,296 for conv1 .. layer3 (res4f)
    assert sum(p.numel() for p in net.encoder.parameters()) == 8_543_296
    assert {"conv1.weight", "bn1.running_mean", "layer3.5.conv3.weight", "layer2.0.downsample.0.weight"} <= set(names)
    assert not any(n.startswith("layer4") for n in names)
    assert net.encoder.layer3[1].conv2.dilation == (2, 2) and net.encoder.layer3[0].conv2.stride == (1, 1)
    with torch.no_grad():
        x1, x2, x3 = net.encoder(torch.zeros(1, 3, 64, 96))
    assert x1.shape[-2:] == (32, 48) and x2.shape[-2:] == (16, 24) and x3.shape == (1, 1024, 8, 12)  # 1/8 kept


def test_shapes_and_gradients_flow_to_every_weight_with_the_small_backbone():
    torch.manual_seed(0)
    net = DepthNet(small().depth)
    image = torch.rand(2, 3, 40, 56)   # not a multiple of 8
    depth, seg = net(image)
    assert depth.shape == seg.shape == (2, 1, 40, 56)
    assert 0 <= seg.min() and seg.max() <= 1
    batch = {"depth": torch.rand(2, 1, 40, 56), "depth_valid": torch.ones(2, 1, 40, 56),
             "seg": (torch.rand(2, 1, 40, 56) > 0.5).float(), "has_depth": torch.tensor([1.0, 1.0]),
             "has_seg": torch.tensor([1.0, 1.0])}
    loss, _, _ = depth_loss(depth, seg, batch)
    loss.backward()
    for name, p in net.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all(), name
    assert net.encoder.conv1.weight.grad.abs().sum() > 0 and net.seg_head[-1].weight.grad.abs().sum() > 0
    with pytest.raises(ValueError, match=r"\(B, 3, H, W\)"):
        net(torch.zeros(1, 1, 8, 8))


def test_mixed_batch_loss_against_hand_computed_values():
    # sample 0: depth only, 2 of 4 pixels known; sample 1: segmentation only
    depth = torch.tensor([[[[0.0, 2.0], [4.0, 9.0]]], [[[5.0, 5.0], [5.0, 5.0]]]])
    seg = torch.tensor([[[[0.9, 0.9], [0.9, 0.9]]], [[[0.5, 1.0], [0.0, 0.25]]]])
    batch = {"depth": torch.tensor([[[[1.0, 0.0], [0.0, 0.0]]], [[[0.0, 0.0], [0.0, 0.0]]]]),
             "depth_valid": torch.tensor([[[[1.0, 1.0], [0.0, 0.0]]], [[[0.0, 0.0], [0.0, 0.0]]]]),
             "seg": torch.tensor([[[[0.0, 0.0], [0.0, 0.0]]], [[[1.0, 1.0], [0.0, 0.0]]]]),
             "has_depth": torch.tensor([1.0, 0.0]), "has_seg": torch.tensor([0.0, 1.0])}
    total, j_d, j_s = depth_loss(depth, seg, batch, gamma=0.5)
    # sample 0's prediction over its known pixels (0, 2) normalises to (0, 1); gt (1, 0): |0-1|, |1-0|
    assert j_d.item() == pytest.approx(1.0)
    # sample 1: |0.5-1| + |1-1| + |0-0| + |0.25-0| = 0.75 over 4 pixels
    assert j_s.item() == pytest.approx(0.1875)
    assert total.item() == pytest.approx(1.0 + 0.5 * 0.1875)
    # what a sample is not supervised on contributes nothing
    moved = depth_loss(depth.clone().index_fill_(0, torch.tensor([1]), 7.0),
                       seg.clone().index_fill_(0, torch.tensor([0]), 0.1), batch, gamma=0.5)[0]
    assert moved.item() == pytest.approx(total.item())
    none = {**batch, "has_depth": torch.zeros(2), "has_seg": torch.zeros(2)}
    assert depth_loss(depth, seg, none)[0].item() == 0.0


def test_minmax_and_the_five_knot_spline_fit():
    x = torch.tensor([[[[2.0, 4.0], [6.0, 10.0]]]])
    assert torch.allclose(minmax(x), torch.tensor([[[[0.0, 0.25], [0.5, 1.0]]]]))
    assert minmax(torch.full((1, 1, 2, 2), 3.0)).abs().max() == 0   # flat: 0, not NaN
    gt = np.linspace(0, 1, 101).reshape(1, 101)
    inverted = 1.0 - gt
    e = depth_errors(inverted, gt)
    assert e["mae"] == pytest.approx(0.5, abs=0.01) and e["mae_spline"] < 1e-9   # an inverted map fits exactly
    warped = np.interp(gt, [0, 0.25, 0.5, 0.75, 1], [0, 0.6, 0.7, 0.9, 1.0])  # gt = a 5-knot warp of pred
    assert np.abs(spline_fit(gt, warped) - warped).max() < 1e-9
    assert np.abs(spline_fit(gt, gt ** 2) - gt ** 2).max() > 1e-3   # only a spline with these knots fits exactly
    assert e["mae_constant"] == pytest.approx(np.abs(gt - 0.5).mean())
    skewed = np.array([[0.0, 0.0, 0.0, 1.0]])   # the best constant under MAE is the median, 0: MAE 1/4
    assert depth_errors(skewed, skewed)["mae_constant"] == pytest.approx(0.25)   # (the mean, 1/4, would give 3/8)
    assert np.allclose(spline_fit(np.zeros(5), np.arange(5.0)), 2.0)   # a flat prediction: the mean


def _save_encoder(net: DepthNet, path: Path, extra: bool = True) -> dict:
    state = {k: v.clone() for k, v in net.encoder.state_dict().items()}
    if extra:  # a torchvision file also holds layer4 and fc
        state["fc.weight"] = torch.zeros(10, 4)
    torch.save(state, path)
    return state


def test_backbone_weights_file_present_absent_wrong_shapes_and_not_weights(tmp_path):
    cfg = small().depth
    torch.manual_seed(1)
    src = DepthNet(cfg)
    state = _save_encoder(src, tmp_path / "w.pth")
    torch.manual_seed(2)
    dst = DepthNet(cfg)
    assert load_backbone(dst, tmp_path / "w.pth") == len(dst.encoder.state_dict())
    assert all(torch.equal(dst.encoder.state_dict()[k], v) for k, v in state.items() if not k.startswith("fc"))
    with pytest.raises(FileNotFoundError, match="nope.pth: no such file"):
        load_backbone(dst, tmp_path / "nope.pth")
    _save_encoder(DepthNet(replace(small(), "depth", width=16).depth), tmp_path / "wide.pth")
    with pytest.raises(ValueError, match=r"wide.pth: does not fit .*shapes differ: conv1.weight \(16, 3, 7, 7\)"):
        load_backbone(dst, tmp_path / "wide.pth")
    _save_encoder(DepthNet(replace(small(), "depth", backbone="resnet50").depth), tmp_path / "r50.pth")
    with pytest.raises(ValueError, match=r"r50.pth: does not fit"):
        load_backbone(dst, tmp_path / "r50.pth")
    (tmp_path / "junk.pth").write_bytes(b"not a checkpoint")
    with pytest.raises(ValueError, match="junk.pth: not a PyTorch state_dict"):
        load_backbone(dst, tmp_path / "junk.pth")


def test_config_paths_are_relative_to_the_config_file(tmp_path):
    (tmp_path / "c.toml").write_text('[train]\ntask = "depth"\n[depth]\nweights = "w/r.pth"\nmattes = "m"\n')
    cfg = load(tmp_path / "c.toml")
    assert cfg.depth.weights == str(tmp_path.resolve() / "w" / "r.pth")
    assert cfg.depth.mattes == str(tmp_path.resolve() / "m") and cfg.depth.rgbd == ""
    assert from_dict(cfg.to_dict()) == cfg   # "" round-trips through the stored config


def _write_rgbd(root: Path, n: int = 3, size: int = 40, kind: str = "npy") -> None:
    """Photos of a bright near square on a dark far background, with metric depth (2 m / 8 m)."""
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    for i in range(n):
        img = np.full((size, size + 8, 3), 40, np.uint8)
        z = np.full((size, size + 8), 8.0, np.float32)
        y0 = 4 + 3 * i
        img[y0:y0 + 16, 10:30] = 220
        z[y0:y0 + 16, 10:30] = 2.0
        z[0, 0] = 0.0   # unknown
        cv2.imwrite(str(root / "rgb" / f"p{i}.png"), img)
        if kind == "npy":
            np.save(root / "depth" / f"p{i}.npy", z)
        else:
            cv2.imwrite(str(root / "depth" / f"p{i}.png"), (z * 1000).astype(np.uint16))


def _write_mattes(root: Path, n: int = 2, size: int = 40) -> None:
    (root / "fg").mkdir(parents=True)
    (root / "alpha").mkdir()
    for i in range(n):
        img = np.full((size, size, 3), 90, np.uint8)
        a = np.zeros((size, size), np.uint8)
        a[5:25, 8 + i:30] = 255
        cv2.imwrite(str(root / "fg" / f"m{i}.jpg"), img)
        cv2.imwrite(str(root / "alpha" / f"m{i}.png"), a)


def test_rgbd_depth_becomes_normalized_disparity_and_mattes_become_segmentation(tmp_path):
    _write_rgbd(tmp_path / "rgbd", kind="png")
    _write_mattes(tmp_path / "mattes")
    x = load_item(Item("rgbd", str(tmp_path / "rgbd/rgb/p0.png"), str(tmp_path / "rgbd/depth/p0.png")), "depth")
    assert not x["valid"][0, 0] and x["valid"].sum() == x["valid"].size - 1
    near, far = x["depth"][10, 20], x["depth"][35, 40]
    assert near == pytest.approx(1.0) and far == pytest.approx(0.0)   # 2 m nearest, 8 m farthest
    d, valid = normalize_disparity(np.array([[2.0, 8.0, 4.0, 0.0]]), "depth")
    assert np.allclose(d, [[1.0, 0.0, 1 / 3, 0.0]]) and valid.tolist() == [[True, True, True, False]]
    m = load_item(Item("matte", str(tmp_path / "mattes/fg/m0.jpg"), str(tmp_path / "mattes/alpha/m0.png")))
    assert m["depth"] is None and m["seg"][10, 10] == 1 and m["seg"][30, 10] == 0
    t = fit_crop(x, 32, np.random.default_rng(0))
    assert t["image"].shape == (3, 32, 32) and t["depth"].shape == t["seg"].shape == (1, 32, 32)
    assert t["has_depth"] == 1 and t["has_seg"] == 0
    ramp = {"image": np.zeros((20, 100, 3), np.float32), "depth": np.tile(np.linspace(0, 1, 100, dtype=np.float32), (20, 1)),
            "valid": np.ones((20, 100), bool), "seg": None}
    crop = fit_crop(ramp, 20, np.random.default_rng(1))["depth"]   # a fifth of the ramp ...
    assert crop.min() == 0 and crop.max() == pytest.approx(1)       # ... normalized again, as the prediction is


def test_colour_jitter_changes_only_the_image_and_is_off_by_default(tmp_path):
    _write_rgbd(tmp_path / "rgbd", n=1)
    x = load_item(Item("rgbd", str(tmp_path / "rgbd/rgb/p0.png"), str(tmp_path / "rgbd/depth/p0.npy")), "depth")
    plain = fit_crop(x, 32, np.random.default_rng(5))
    assert all(torch.equal(plain[k], fit_crop(x, 32, np.random.default_rng(5), 0.0)[k]) for k in plain)
    jittered = fit_crop(x, 32, np.random.default_rng(5), 1.0)
    for k in ("depth", "depth_valid", "seg"):   # the same crop and flip: only the colours change
        assert torch.equal(plain[k], jittered[k])
    assert not torch.equal(plain["image"], jittered["image"])
    assert 0 <= jittered["image"].min() and jittered["image"].max() <= 1
    assert torch.equal(fit_crop(x, 32, None, 1.0)["image"], fit_crop(x, 32, None)["image"])   # never in evaluation


def test_a_file_without_its_partner_is_named(tmp_path):
    _write_rgbd(tmp_path / "rgbd")
    (tmp_path / "rgbd/rgb/extra.png").write_bytes((tmp_path / "rgbd/rgb/p0.png").read_bytes())
    with pytest.raises(ValueError, match=r"without a partner .*extra.png"):
        pair_files(tmp_path / "rgbd", "rgb", "depth", (".npy",))
    with pytest.raises(FileNotFoundError, match="no alpha/ folder"):
        pair_files(tmp_path / "rgbd", "rgb", "alpha", (".png",))


def test_every_batch_mixes_depth_and_segmentation_samples_the_same_on_any_world(tmp_path, smoke_set):
    _write_rgbd(tmp_path / "rgbd")
    _write_mattes(tmp_path / "mattes")
    cfg = replace(small(rgbd=str(tmp_path / "rgbd"), mattes=str(tmp_path / "mattes"), seg_share=0.25), "data", batch_size=4)
    depth, seg = sources(cfg, smoke_set, "fit")
    assert {i.kind for i in depth} == {"shard", "rgbd"} and {i.kind for i in seg} == {"matte"}
    ds = DepthMix(depth, seg, cfg, train=True, seed=3)
    plan = ds.plan(0)
    assert all([i.kind == "matte" for i in b].count(True) == 1 for b in plan)   # 1 of 4 from the mattes
    assert len({i for b in plan for i in b if i.kind != "matte"}) == len(depth)  # every depth item each epoch
    one = [x["key"] for x in DepthMix(depth, seg, cfg, train=True, seed=3, rank=0, world=1)]
    two = [[x["key"] for x in DepthMix(depth, seg, cfg, train=True, seed=3, rank=r, world=2)] for r in (0, 1)]
    half = len(plan) // 2
    assert two[0] + two[1] == [k for g in [*range(0, 2 * half, 2), *range(1, 2 * half, 2)] for k in one[4 * g:4 * g + 4]]
    resumed = DepthMix(depth, seg, cfg, train=True, seed=3, rank=0, world=1)
    resumed.set_epoch(0, skip_batches=2)
    assert [x["key"] for x in resumed] == one[8:]
    b = next(iter(make_depth_loader(smoke_set, cfg, train=True, seed=3)[1]))
    assert b["has_seg"].tolist().count(1.0) >= 1 and b["has_depth"].sum() >= 1


def test_a_tiny_model_overfits_a_few_samples(tmp_path):
    _write_rgbd(tmp_path / "rgbd", n=3, size=32)
    items = [Item("rgbd", str(tmp_path / f"rgbd/rgb/p{i}.png"), str(tmp_path / f"rgbd/depth/p{i}.npy")) for i in range(3)]
    batch = [fit_crop(load_item(it, "depth"), 32, None) for it in items]
    batch = {k: torch.stack([b[k] for b in batch]) for k in batch[0]}
    torch.manual_seed(0)
    net = DepthNet(small().depth)
    opt = torch.optim.Adam(net.parameters(), lr=3e-3)

    def mae():
        net.eval()
        with torch.no_grad():
            d, _ = net(batch["image"])
        net.train()
        v = batch["depth_valid"] > 0
        return ((minmax(d, v) - batch["depth"]).abs()[v]).mean().item()

    before = mae()
    for _ in range(120):
        d, s = net(batch["image"])
        loss, _, _ = depth_loss(d, s, batch)
        opt.zero_grad()
        loss.backward()
        opt.step()
    after = mae()
    assert after * 5 <= before, (before, after)


@pytest.fixture(scope="module")
def depth_run(tmp_path_factory, smoke_set):
    run = tmp_path_factory.mktemp("depth") / "run"
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        assert main(["train", "train-depth-tiny", "--data", str(smoke_set), "--run", str(run), "--steps", "20", "-q"]) == 0
    finally:
        torch.set_num_threads(n)
    return run


def test_train_writes_a_depth_run_that_resumes_and_eval_reports_mae(depth_run, smoke_set, capsys):
    with open(depth_run / "log.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert [int(r["step"]) for r in rows] == [0, 10, 20]             # step 0: the start, validated
    assert rows[0]["val_mae"] and all(r["loss_depth"] and r["loss_seg"] and not r["loss_low"] for r in rows[1:])
    assert main(["train", "train-depth-tiny", "--data", str(smoke_set), "--run", str(depth_run), "--steps", "20"]) == 0
    assert "already trained to step 20" in capsys.readouterr().out
    assert main(["eval", str(depth_run), "--data", str(smoke_set)]) == 0
    out = capsys.readouterr().out
    assert "MAE spline" in out and "constant" in out
    with open(depth_run / "eval.csv") as fh:
        table = {r["method"]: r for r in csv.DictReader(fh)}
    assert 0 <= float(table["network"]["mae_spline"]) <= 1 and float(table["constant"]["mae"]) > 0


def test_depth_and_render_without_depth_on_a_real_photo(depth_run, shared_assets, tmp_path):
    photo = shared_assets / "fg" / "rembg_girl-1.jpg"
    h, w = read_image(photo).shape[:2]
    assert main(["depth", str(photo), "--model", str(depth_run), "--out", str(tmp_path / "d.exr")]) == 0
    assert main(["depth", str(photo), "--model", str(depth_run), "--out", str(tmp_path / "d.png")]) == 0
    d = read_depth(tmp_path / "d.exr")
    assert d.shape == (h, w) and d.dtype == np.float32 and 0 <= d.min() and d.max() <= 1 and np.ptp(d) > 0.5
    assert cv2.imread(str(tmp_path / "d.png"), cv2.IMREAD_UNCHANGED).dtype == np.uint16
    assert np.abs(read_depth(tmp_path / "d.png") - d).max() < 1e-4
    out = tmp_path / "dof.png"
    args = ["render", str(photo), "--model", str(depth_run), "--focus-at", f"{w // 2},{h // 2}", "--max-coc", "8"]
    assert main(args + ["--out", str(out)]) == 0
    same = tmp_path / "same.png"   # = the classical render given the predicted map as --depth
    assert main(["render", str(photo), "--depth", str(tmp_path / "d.exr"), "--focus-at", f"{w // 2},{h // 2}",
                 "--max-coc", "8", "--out", str(same)]) == 0
    assert out.read_bytes() == same.read_bytes()
    src = cv2.imread(str(photo)).astype(float)
    assert np.abs(cv2.imread(str(out)).astype(float) - src).mean() > 1.0   # something was blurred
    assert main(["render", str(photo), "--focus", "0.5", "--out", str(tmp_path / "x.png"), "--max-coc", "8"]) == 2


def test_render_depth_kind_normalises_a_monocular_networks_raw_map(tmp_path, shared_assets):
    photo = shared_assets / "bg" / "kodak_kodim13.png"
    h, w = read_image(photo).shape[:2]
    disparity = np.tile(np.linspace(0.0, 1.0, w, dtype=np.float32), (h, 1))
    np.save(tmp_path / "norm.npy", disparity)
    np.save(tmp_path / "rel.npy", 3.0 * disparity + 5.0)            # relative disparity, any scale/offset
    np.save(tmp_path / "z.npy", 1.0 / (0.5 * disparity + 0.25))     # metric depth, far = 4, near = 1.33
    outs = {}
    for name, kind in (("norm", "normalized"), ("rel", "disparity"), ("z", "depth")):
        outs[name] = tmp_path / f"{name}.png"
        assert main(["render", str(photo), "--depth", str(tmp_path / f"{name}.npy"), "--depth-kind", kind,
                     "--focus", "0.5", "--max-coc", "6", "--out", str(outs[name])]) == 0
    ref = cv2.imread(str(outs["norm"])).astype(int)
    for name in ("rel", "z"):
        assert np.abs(cv2.imread(str(outs[name])).astype(int) - ref).max() <= 1, name
    assert main(["render", str(photo), "--depth", str(tmp_path / "z.npy"), "--depth-kind", "inverse",
                 "--focus", "0.5", "--max-coc", "6", "--out", str(tmp_path / "bad.png")]) == 2


def test_predict_disparity_keeps_the_photo_size():
    net = DepthNet(small().depth).eval()
    d = predict_disparity(net, np.random.default_rng(0).random((37, 53, 3)).astype(np.float32), 32)
    assert d.shape == (37, 53) and d.dtype == np.float32 and 0 <= d.min() <= d.max() <= 1


def test_two_processes_under_torchrun_train_the_depth_network(smoke_set, tmp_path):
    """DistributedDataParallel on the CPU (gloo) with the depth network's mixed batches."""
    import json
    import os
    import subprocess
    import sys

    run = tmp_path / "ddp"
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2",
           "-m", "dofsynth", "--", "train", "train-depth-tiny", "--data", str(smoke_set), "--run", str(run),
           "--device", "cpu", "--steps", "2", "-q"]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=900, env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert proc.returncode == 0, torchrun_failure(proc)
    assert json.loads((run / "env.json").read_text())["world_size"] == 2
    with open(run / "log.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert [r["step"] for r in rows] == ["0", "2"] and rows[1]["loss_depth"] and rows[1]["val_mae"]   # one writer
