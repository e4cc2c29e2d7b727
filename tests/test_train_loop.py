"""Training end to end on CPU: the CLI, resume, checkpoints, render_photo on a real photo, eval,
and two steps on the real generator's smoke data set."""
from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from dofsynth.cli import main
from dofsynth.color import srgb_to_linear
from dofsynth.train import checkpoint
from dofsynth.train.config import from_dict, load, replace, to_toml
from dofsynth.train.infer import inference_sizes, render_photo, render_with, upsampling_steps
from dofsynth.train.models import DeepLensNet
from test_train_data import make_dataset, tiny_config
from conftest import torchrun_failure

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
    assert [int(r["step"]) for r in rows] == [0, 1, 2, 3, 4]          # step 0: the start, validated
    assert rows[0]["val_psnr"] and not rows[0]["loss"]
    assert rows[2]["val_loss"] and rows[4]["val_psnr"] and not rows[1]["val_loss"]   # eval every 2 steps
    assert all(np.isfinite(float(r["loss"])) for r in rows[1:])
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
        assert torch.equal(a["ema"][k], b["ema"][k]), k          # the moving average resumes too
    assert [r["loss"] for r in _rows(run)] == [r["loss"] for r in _rows(run4)]
    assert main(args) == 0          # finished: nothing to do
    assert "already trained" in capsys.readouterr().out
    other = cfg_path.with_name("other.toml")
    other.write_text(to_toml(tiny_config(loss={"beta": 2.0})))
    assert main(["train", str(other), "--data", str(data), "--run", str(run)]) == 2   # refused, named


def test_validation_keeps_the_best_averaged_weights_and_a_run_is_used_from_them(setup):
    _, _, _, run = setup
    rows = [r for r in _rows(run) if r["val_psnr"]]
    best = checkpoint.load(run / checkpoint.BEST)
    top = max(rows, key=lambda r: float(r["val_psnr"]))          # the first of equals
    assert best["step"] == int(top["step"]) and math.isclose(best["val"]["val_psnr"], float(top["val_psnr"]), rel_tol=1e-5)
    last = checkpoint.load(run / "ckpt.pt")
    assert last["best_score"] == pytest.approx(float(top["val_psnr"]), rel=1e-5)
    assert any(not torch.equal(last["ema"][k], last["model"][k]) for k in last["model"])  # an average, not a copy
    if best["step"] == last["step"]:
        assert all(torch.equal(best["model"][k], last["ema"][k]) for k in best["model"])
    model, _ = checkpoint.load_model(run)                        # a run folder: its best.pt
    assert checkpoint.weights_path(run) == run / checkpoint.BEST
    assert all(torch.equal(v, best["model"][k]) for k, v in model.state_dict().items())


def test_the_moving_average_by_hand():
    """d = min(decay, (1 + t) / (10 + t)): after step 0, 0.1 of the old average is kept; late,
    the decay itself."""
    model = torch.nn.Linear(1, 1, bias=False)
    with torch.no_grad():
        model.weight.fill_(1.0)
    ema = checkpoint.Ema(model, 0.5)
    with torch.no_grad():
        model.weight.fill_(3.0)
    ema.update(model, 0)                                          # 0.1 * 1 + 0.9 * 3
    assert ema.module.weight.item() == pytest.approx(2.8)
    ema.update(model, 1000)                                       # d = 0.5: 0.5 * 2.8 + 0.5 * 3
    assert ema.module.weight.item() == pytest.approx(2.9)
    assert not ema.module.weight.requires_grad


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


@pytest.fixture(scope="module")
def learned(tmp_path_factory):
    """A tiny run trained for 200 steps on fine-grained textures (which a blur visibly
    changes), long enough to learn where to blur."""
    root = tmp_path_factory.mktemp("learned")
    data = make_dataset(root / "data", n_train=16, n_test=0, size=48, grain=1)
    cfg = tiny_config(model={"kp_width": 16}, data={"crop": 48}, augment={"enabled": False}, loss={"l1": 1.0},
                      train={"max_steps": 200, "eval_interval": 0, "log_interval": 50, "checkpoint_interval": 200,
                             "warmup_steps": 10})
    (root / "c.toml").write_text(to_toml(cfg))
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        assert main(["train", str(root / "c.toml"), "--data", str(data), "--run", str(root / "run")]) == 0
    finally:
        torch.set_num_threads(n)
    return root / "run"


def test_render_model_on_a_real_photo_is_sharp_in_focus_and_blurred_elsewhere(learned, shared_assets, tmp_path):
    """`dofsynth render --model` on a Kodak photo, the left half in focus, the right half far:
    the right half loses more of its detail than the left; with the disparity zeroed (all far)
    the left half blurs too, so the output depends on the depth it is given."""
    from dofsynth.io import read_image, write_exr

    srgb = cv2.imread(str(shared_assets / "bg" / "kodak_kodim01.png"))[:, :, ::-1].astype(np.float32) / 255
    photo = tmp_path / "photo.png"
    cv2.imwrite(str(photo), (cv2.resize(srgb, (192, 128), interpolation=cv2.INTER_AREA)[:, :, ::-1] * 255).round().astype(np.uint8))
    depth = np.zeros((128, 192), np.float32)
    depth[:, :96] = 0.8
    outs = {}
    for name, d in (("split", depth), ("zero", np.zeros_like(depth))):
        write_exr(tmp_path / f"{name}.exr", d)
        out = tmp_path / f"{name}.png"
        assert main(["render", str(photo), "--depth", str(tmp_path / f"{name}.exr"), "--focus", "0.8",
                     "--model", str(learned), "--out", str(out)]) == 0
        outs[name] = read_image(out)[:, :, :3]

    def detail(img):  # mean horizontal gradient in the left and right halves, away from the seam
        g = np.abs(np.diff(img, axis=1)).mean(axis=2)
        return g[:, 8:88].mean(), g[:, 104:184].mean()

    src_l, src_r = detail(read_image(photo)[:, :, :3])
    left, right = detail(outs["split"])
    zero_l, _ = detail(outs["zero"])
    assert left / src_l > right / src_r + 0.1      # in focus keeps more of its detail
    assert zero_l < left * 0.9                      # ... and loses it when the depth says "far"
    assert np.abs(outs["split"] - outs["zero"]).mean() > 0.003


def test_upsampling_steps_reach_the_training_low_resolution():
    assert upsampling_steps(1024, 256) == 2 and upsampling_steps(1000, 256) == 2
    assert upsampling_steps(1025, 256) == 3 and upsampling_steps(200, 256) == 0
    assert inference_sizes((512, 520), 256) == [(252, 256), (504, 512), (512, 520)]
    assert inference_sizes((256, 128), 256) == [(256, 128)]


@pytest.mark.parametrize("norm", ["batch", "none"])
def test_inference_folds_and_bands_without_changing_the_result(norm, monkeypatch):
    """`dofsynth render --model` runs a copy of the model made for inference (batch
    normalisation folded into the convolutions, channels-last) with the full-resolution steps in
    bands of rows; the photo comes out as the model itself makes it, within float rounding."""
    from dofsynth.train import infer

    cfg = tiny_config(model={"coc_ref": 8.0, "norm": norm}, infer={"low_res_side": 32})
    torch.manual_seed(0)
    model = DeepLensNet(cfg.model).eval()
    for m in model.modules():
        if isinstance(m, torch.nn.BatchNorm2d):  # statistics far from the identity
            m.running_mean.uniform_(-0.3, 0.3), m.running_var.uniform_(0.3, 2.0), m.weight.data.uniform_(0.5, 1.5)
    rng = np.random.default_rng(1)
    image = rng.random((150, 136, 3), dtype=np.float32)
    disparity = np.tile(np.linspace(0, 1, 136, dtype=np.float32), (150, 1))
    monkeypatch.setattr(infer, "BAND_ROWS", None)
    plain = render_with(model, cfg, image, disparity, 0.4)
    fast = infer.for_inference(model)
    assert not any(isinstance(m, torch.nn.BatchNorm2d) for m in fast.modules())
    assert any(isinstance(m, infer.EdgeConv) for m in fast.modules())  # replicate padding without copies
    assert any(isinstance(m, torch.nn.BatchNorm2d) for m in model.modules()) == (norm == "batch")  # untouched
    monkeypatch.setattr(infer, "BAND_ROWS", 16)   # 150 rows: bands of 16 and a last one of 6
    assert np.abs(render_with(fast, cfg, image, disparity, 0.4) - plain).max() < 1e-5


@pytest.mark.parametrize("d", [1, 2, 4])
def test_edge_conv_is_the_replicate_padded_convolution(d):
    """`edge_conv`: the zero-padded convolution with its border rows and columns redone equals
    the replicate-padded one (nn.Conv2d with padding_mode="replicate"), also for inputs too
    small for the border strips, channels-last or not."""
    from dofsynth.train.infer import edge_conv

    torch.manual_seed(d)
    conv = torch.nn.Conv2d(5, 7, 3, padding=d, dilation=d, padding_mode="replicate")
    for shape in ((2, 5, 37, 29), (1, 5, 2 * d, 9), (1, 5, 3, 2 * d + 1)):
        x = torch.randn(*shape)
        for layout in (torch.contiguous_format, torch.channels_last):
            got = edge_conv(x.contiguous(memory_format=layout), conv.weight, conv.bias, d)
            assert torch.allclose(got, conv(x), atol=1e-5), (shape, layout)


def test_untouched_reach_spreads_as_the_max_pool_iteration():
    """The reach test's spreading runs through cv2.dilate on the CPU: the same masks as the
    iterated 3 x 3 max-pool (minus one per step) it replaces, on random reaches."""
    import math

    import torch.nn.functional as F

    from dofsynth.train.models import untouched

    g = torch.Generator().manual_seed(4)
    u = torch.rand(2, 1, 61, 47, generator=g)
    few = torch.where(u > 0.995, u - 0.9, torch.zeros_like(u))  # a few blurred pixels in a sharp frame
    far = torch.zeros(1, 1, 200, 150)
    far[0, 0, 20, 20], far[0, 0, 150, 100], far[0, 0, 100, 30] = 0.5, 0.3, 0.02  # reach 21 px: cells of 2
    for signed, coc_px in ((few, 8.0), (few, 40.0), (few, 100.0), (far, 40.0)):
        h, w = signed.shape[-2:]
        c = signed.abs() * coc_px
        reach = torch.where(c >= 0.5, c + 1.0, torch.zeros_like(c))
        longest = float(reach.max())
        f = 2 ** max(0, math.ceil(math.log2(longest / 16))) if longest > 16 else 1
        if f > 1:
            cell = F.max_pool2d(reach, f, stride=f, ceil_mode=True)
            reach = torch.where(cell > 0, cell / f + 1.0, 0.0)
        for _ in range(math.ceil(float(reach.max()))):
            reach = torch.maximum(reach, F.max_pool2d(reach, 3, stride=1, padding=1) - 1.0)
        free = reach <= 0
        if f > 1:
            free = free.repeat_interleave(f, dim=-2).repeat_interleave(f, dim=-1)[..., :h, :w]
        got = untouched(signed, coc_px)
        assert torch.equal(got, free) and 0 < got.float().mean() < 1, coc_px


def test_the_edge_weight_spreads_as_the_max_pool_iteration_on_both_cpu_paths(monkeypatch):
    """The hybrid's edge weight spreads each edge's reach by cv2.dilate on small planes and by
    two raster passes on wide ones (reach.CHAMFER_WORK): both the iterated 3 x 3 max-pool
    (minus one per step), to the last bit, on random depth edges of random sizes."""
    import math

    import torch.nn.functional as F

    from dofsynth.train import reach as reach_mod

    g = torch.Generator().manual_seed(7)
    cases = [torch.rand(1, 1, 40, 90, generator=g), torch.rand(2, 1, 75, 33, generator=g)]
    blocky = torch.zeros(1, 1, 120, 160)
    blocky[..., 30:80, 40:100], blocky[..., 90:, 5:20] = 0.6, -0.35  # a near block, a far corner
    partial = 0
    for signed in [torch.where(c > 0.995, c, torch.zeros_like(c)) for c in cases] + [blocky]:
        for coc_px in (5.0, 37.0):
            c = signed * coc_px
            hi, lo = F.max_pool2d(c, 3, 1, 1), -F.max_pool2d(-c, 3, 1, 1)
            spread = torch.where(hi - lo >= 1.0, torch.maximum(hi.abs(), lo.abs()) + 1.0, torch.zeros_like(c))
            longest = spread.amax(dim=(-2, -1), keepdim=True)
            for _ in range(math.ceil(float(spread.max()))):
                spread = torch.maximum(spread, F.max_pool2d(spread, 3, stride=1, padding=1) - 1.0)
            want = torch.clamp(spread / torch.clamp(longest / 2, min=1.0), 0.0, 1.0)
            for work in (0, 10**12):  # every plane by the raster passes, then none
                monkeypatch.setattr(reach_mod, "CHAMFER_WORK", work)
                got = reach_mod.edge_weight(signed, coc_px)
                assert torch.equal(got, want), (tuple(signed.shape), coc_px, work)
            partial += 0 < float(want.mean()) < 1 and len(torch.unique(want)) > 4
    assert partial >= 4  # weights between 0 and 1, not a frame of ones or zeros


def test_untouched_pixels_are_those_no_blur_reaches():
    """A hand-computed case: one pixel of CoC 2.3 px (signed 0.23 at 10 px per unit) in a
    sharp frame reaches 3 px around it (support radius 3); a pixel of 0.4 px reaches nothing."""
    from dofsynth.train.models import untouched

    signed = torch.zeros(1, 1, 15, 15)
    signed[0, 0, 7, 7] = 0.23
    signed[0, 0, 1, 1] = 0.04   # 0.4 px: sharp
    free = untouched(signed, 10.0)[0, 0]
    yy, xx = torch.meshgrid(torch.arange(15), torch.arange(15), indexing="ij")
    near = torch.maximum((yy - 7).abs(), (xx - 7).abs()) <= 3
    assert torch.equal(free, ~near)


def test_the_output_is_the_input_where_no_blur_reaches():
    """[model] identity: however the network is initialised, wherever no pixel's blur reaches
    (here: all but a blurred square and its reach), the rendered photo is the input exactly."""
    cfg = tiny_config(model={"coc_ref": 8.0}, infer={"low_res_side": 32})
    torch.manual_seed(3)
    model = DeepLensNet(cfg.model).eval()
    rng = np.random.default_rng(2)
    image = rng.random((96, 96, 3), dtype=np.float32)
    disparity = np.full((96, 96), 0.5, np.float32)
    disparity[40:50, 40:50] = 0.9   # out of focus: CoC 0.4 x 8 px x 96 / (32 x 2**levels) = 4.8 px
    out = render_with(model, cfg, image, disparity, focus=0.5)
    far = np.ones((96, 96), bool)
    far[40 - 8:50 + 8, 40 - 8:50 + 8] = False   # 4.8 px of CoC reach 5.8 px at most
    assert np.abs(out[far] - image[far]).max() < 1e-6   # (the sRGB round trip of the network's input)
    assert np.abs(out[~far] - image[~far]).max() > 1e-3   # the network does act where there is blur
    paper = render_with(DeepLensNet(replace(cfg, "model", identity=False).model).eval(), cfg, image, disparity, focus=0.5)
    assert np.abs(paper[far] - image[far]).max() > 1e-3   # the paper's network alone does not keep it


class _FixedBlur(torch.nn.Module):
    """A lens-blur stand-in with a trained network's habit: a blur of a fixed size in low-res
    pixels (a Gaussian of sigma 3), whatever the photo's size."""

    def forward(self, image, signed):
        x = torch.arange(-12, 13, dtype=torch.float32)
        g = torch.exp(-x**2 / 18)
        g = (g[:, None] * g[None, :] / g.sum() ** 2).expand(3, 1, 25, 25)
        return torch.nn.functional.conv2d(torch.nn.functional.pad(image, (12,) * 4, mode="replicate"), g, groups=3)


def test_the_same_scene_at_two_sizes_gets_the_same_blur_as_a_fraction_of_the_picture():
    """A bright square at the centre, blurred by the networks at 512 px and 520 px (which
    power-of-two halvings would have put at 256 and 130 px): its spread over the picture side
    must agree."""
    cfg = tiny_config(data={"color": "linear"}, infer={"low_res_side": 256}, model={"coc_ref": 8.0})
    model = DeepLensNet(cfg.model).eval()
    model.lens = _FixedBlur()
    with torch.no_grad():  # M_L = 1: every upsampling step passes the upsampled blur through
        model.up.fuse[-1].weight.zero_()
        model.up.fuse[-1].bias.fill_(30.0)
    spreads = []
    for side in (512, 520):
        image = np.zeros((side, side, 3), np.float32)
        c = side // 2
        image[c - 2:c + 2, c - 2:c + 2] = 1.0
        out = render_with(model, cfg, image, np.zeros((side, side), np.float32), focus=1.0)[:, :, 0]
        yy, xx = np.mgrid[0:side, 0:side] - (side - 1) / 2
        spreads.append(np.sqrt((out * (yy**2 + xx**2)).sum() / out.sum()) / side)
    assert spreads[0] > 6 * 1.2 / 512  # blurred: sigma about 6 px at 512 px, not the 2.3 px square
    assert spreads[1] == pytest.approx(spreads[0], rel=0.02)


def test_eval_prints_and_writes_the_table(setup, capsys):
    _, data, _, run = setup
    assert main(["eval", str(run), "--data", str(data)]) == 0
    out = capsys.readouterr().out
    assert "network" in out and "classical" in out and "all-in-focus" in out
    table = json.loads((run / "eval.json").read_text())["table"]
    assert [r["method"] for r in table] == ["network", "classical", "all-in-focus"]
    assert all(r["n"] == 4 and 0 < r["psnr"] < 100 and -1 <= r["ssim"] <= 1 for r in table)  # 2 samples x 2 targets
    assert (run / "eval.csv").read_text().startswith("method,psnr,ssim,psnr_edge,ssim_edge,psnr_out,ssim_out,"
                                                     "psnr_same,ssim_same,n")
    assert "same dB" in out and "edge SSIM" in out
    assert main(["eval", str(run.parent / "nope"), "--data", str(data)]) == 2


def test_eval_metrics_split_the_frame_into_the_edge_band_the_rest_and_where_target_is_input():
    """PSNR per region over its own pixels (an error of 0.01 in the band: 40 dB; 0.001 elsewhere:
    60 dB), SSIM the mean of the map there; an empty region is None."""
    from dofsynth.train.evaluate import _metrics

    g = np.random.default_rng(0)
    target = g.uniform(0.1, 0.9, (64, 64, 3))
    band = np.zeros((64, 64), bool)
    band[:, 20:30] = True
    same = np.zeros((64, 64), bool)
    same[:, 40:] = True
    pred = target + np.where(band[:, :, None], 0.01, 0.001)
    m = _metrics(pred, target, band, same)
    assert m["psnr_edge"] == pytest.approx(40.0) and m["psnr_out"] == pytest.approx(60.0)
    assert m["psnr_same"] == pytest.approx(60.0) and 40.0 < m["psnr"] < 60.0
    assert m["ssim_edge"] < m["ssim_out"] <= 1.0 and m["ssim_same"] > m["ssim_edge"]
    none = _metrics(pred, target, band, np.zeros((64, 64), bool))
    assert none["psnr_same"] is None and none["ssim_same"] is None


def _classical(result):
    return [(r["key"], r["target"], r["psnr"]) for r in result["items"] if r["method"] == "classical"]


def test_eval_gives_every_run_and_method_the_depth_asked_for(setup, tmp_path):
    """--depth fixes the disparity: two runs trained with different corruption get the same
    classical inputs under gt / a kind / a setting file, and different ones under "run"."""
    _, data, _, run = setup
    state = checkpoint.load(run / "ckpt.pt")
    model, cfg = checkpoint.load_model(run)
    clean_cfg = from_dict({**cfg.to_dict(), "augment": {"enabled": False}})
    other = tmp_path / "clean-run"
    checkpoint.save(other / "ckpt.pt", model, torch.optim.AdamW(model.parameters()), state["step"], 0, 0, clean_cfg)
    kw = {"write": False, "device": "cpu"}
    from dofsynth.train.evaluate import evaluate_run
    for depth in ("gt", "morph"):
        assert _classical(evaluate_run(run, data, depth=depth, **kw)) == _classical(evaluate_run(other, data, depth=depth, **kw))
    assert _classical(evaluate_run(run, data, depth="gt", **kw)) != _classical(evaluate_run(run, data, depth="morph", **kw))
    assert _classical(evaluate_run(other, data, depth="run", **kw)) == _classical(evaluate_run(run, data, depth="gt", **kw))
    setting = tmp_path / "setting.toml"
    setting.write_text("[augment]\nmorph_prob = 1.0\nmorph_kernel = [3, 15]\n")
    assert _classical(evaluate_run(run, data, depth=str(setting), **kw)) == _classical(evaluate_run(run, data, depth="morph", **kw))
    result = evaluate_run(run, data, depth="gt", **kw)
    assert all(r["psnr_edge"] is not None and r["psnr_edge"] < 100 for r in result["table"])
    assert main(["eval", str(run), "--data", str(data), "--depth", "fog"]) == 2   # refused before any work


def _depth_run(folder: Path):
    """An untrained small depth network saved as a depth run in `folder`; returns the network."""
    from dofsynth.train.depth import DepthNet

    torch.manual_seed(0)
    cfg = from_dict({"train": {"task": "depth"}, "data": {"crop": 32},
                     "depth": {"backbone": "resnet18", "width": 8, "decoder_width": 16}})
    net = DepthNet(cfg.depth).eval()
    checkpoint.save(folder / "ckpt.pt", net, torch.optim.AdamW(net.parameters()), 1, 0, 0, cfg)
    return net


def test_eval_can_give_everyone_what_a_depth_network_predicts(setup, tmp_path):
    """--depth predicted:RUN: the map the depth run predicts from each all-in-focus image, fitted
    to the clean disparity's scale by the 5-knot spline, goes to every method, and its MAE
    against the clean map is reported; a missing or DoF run is refused."""
    from dofsynth.codecs import decode_depth
    from dofsynth.io import decode_image
    from dofsynth.train.segments import find_segments, raw_samples
    from dofsynth.train.depth import depth_errors, predict_disparity
    from dofsynth.train.evaluate import evaluate_run

    _, data, _, run = setup
    depth_run = tmp_path / "depth-run"
    net = _depth_run(depth_run)
    kw = {"write": False, "device": "cpu"}
    got = evaluate_run(run, data, depth=f"predicted:{depth_run}", **kw)
    want = []  # each target's: its sample's fitted prediction against the clean map
    for raw in raw_samples(find_segments(data, "test"), "test"):
        clean = decode_depth(raw["depth.exr"], "depth")
        pred = predict_disparity(net, decode_image(raw["aif.png"], "aif")[:, :, :3], 32)
        want += [depth_errors(pred, clean)["mae_spline"]] * len(json.loads(raw["json"])["targets"])
    assert got["depth_mae"] == pytest.approx(float(np.mean(want)), rel=1e-3) and got["depth_mae"] > 0.01
    gt = evaluate_run(run, data, depth="gt", **kw)
    assert gt["depth_mae"] == 0.0 and _classical(got) != _classical(gt)
    assert _classical(evaluate_run(run, data, depth=f"predicted:{depth_run}", **kw)) == _classical(got)
    with pytest.raises(ValueError, match="not of the depth network"):
        evaluate_run(run, data, depth=f"predicted:{run}", **kw)
    assert main(["eval", str(run), "--data", str(data), "--depth", f"predicted:{tmp_path / 'none'}"]) == 2


def test_a_run_trains_on_a_depth_networks_estimates(setup, tmp_path, monkeypatch):
    """[augment] predicted_prob: that share of the items (its own stream) takes the depth run's
    fitted estimate as its disparity, made once per run into RUN/depth-estimates.npz (every
    train sample, within 1/65535 of the estimate) and reused on resume; the rest are corrupted
    as before. A missing run key or estimates file is refused."""
    from dofsynth.codecs import decode_depth
    from dofsynth.train import estimates
    from dofsynth.train.data import make_loader, resolve
    from dofsynth.train.segments import find_segments, raw_samples

    _, data, _, _ = setup
    depth_run = tmp_path / "depth"
    _depth_run(depth_run)
    predict = estimates.depth_predictor(f"predicted:{depth_run}", "cpu")
    want = {}
    for raw in raw_samples(find_segments(data, "train"), "train"):
        want[raw["__key__"]] = predict(raw, decode_depth(raw["depth.exr"], "depth"))
    assert len(want) == 8

    # through `dofsynth train`, the run key relative to the config's folder; stopped after step 1
    cfg_path = tmp_path / "configs" / "est.toml"
    cfg_path.parent.mkdir()
    cfg_path.write_text(to_toml(tiny_config(augment={"predicted_prob": 1.0, "predicted_run": "../depth"},
                                            train={"max_steps": 2})))
    run = tmp_path / "run"
    args = ["train", str(cfg_path), "--data", str(data), "--run", str(run), "--device", "cpu"]
    assert main(args + ["--steps", "1"]) == 0
    cfg = resolve(load(run / "config.toml"), data)
    assert Path(cfg.augment.predicted_run).resolve() == depth_run.resolve()
    with np.load(run / estimates.ESTIMATES) as held:
        assert set(held.files) == set(want) | {"__shards__"}
        for key, est in want.items():
            assert np.abs(held[key] / 65535.0 - est).max() <= 0.5 / 65535 + 1e-7
    # every item takes its sample's estimate (crop 32 = the whole image)
    ds, _ = make_loader(data, "train", cfg, train=False, seed=0, part="all", estimates=run / estimates.ESTIMATES)
    items = list(ds)
    assert len(items) == 8 and all(json.loads(it["corruption"]) == {"given": True} for it in items)
    for it in items:
        assert np.abs(it["disparity"][0].numpy() - want[it["key"]]).max() <= 1e-5
    # half: some items take it, the others are corrupted from the clean map as before
    half = replace(cfg, "augment", predicted_prob=0.5)
    ds, _ = make_loader(data, "train", half, train=False, seed=0, estimates=run / estimates.ESTIMATES)
    given = [json.loads(it["corruption"]) == {"given": True} for it in ds]
    assert 0 < sum(given) < len(given)
    # resumed: the estimates are not made again
    monkeypatch.setattr(estimates, "depth_predictor", lambda *a: pytest.fail("estimates made again"))
    assert main(args) == 0 and checkpoint.load(run / "ckpt.pt")["step"] == 2
    monkeypatch.undo()  # estimates of other shards (a data set made again) are made again
    np.savez(run / estimates.ESTIMATES, __shards__=np.array("train-000000.tar 0123 0 8"))
    estimates.write_estimates(cfg, data, run)
    with np.load(run / estimates.ESTIMATES) as held:
        assert set(held.files) == set(want) | {"__shards__"}
    with pytest.raises(ValueError, match="estimates file"):
        make_loader(data, "train", cfg, train=True, seed=0)
    with pytest.raises(ValueError, match="predicted_run"):
        tiny_config(augment={"predicted_prob": 0.5})


def test_the_classical_baseline_renders_with_the_targets_highlight_boost():
    """In focus it returns the image exactly, highlights included; out of focus a small bright
    light spreads brighter with the record's highlight boost than without."""
    from dofsynth.train.evaluate import classical_render

    image = np.full((48, 48, 3), 0.3, np.float32)
    image[22:26, 22:26] = 1.0
    flat = np.full((48, 48), 0.5, np.float32)
    plain = {"aperture": {"kind": "disk"}, "options": {"linear_light": True}}
    boosted = {"aperture": {"kind": "disk"},
               "options": {"linear_light": True, "highlight": {"threshold": 0.9, "gain": 4.0, "power": 2.0}}}
    assert np.allclose(classical_render(image, flat, 0.5, 6.0, boosted), image, atol=2e-6)
    blurred = classical_render(image, flat, 0.0, 6.0, boosted)
    dim = classical_render(image, flat, 0.0, 6.0, plain)
    assert blurred[24, 24, 0] > dim[24, 24, 0] + 0.1


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
    from dofsynth.io import decode_image
    from dofsynth.codecs import decode_depth
    from dofsynth.train.segments import find_segments, raw_samples

    data = smoke_set
    # the corruption's model of the layers agrees with the generator's depth maps
    raw = next(raw_samples(find_segments(data, "train"), "train"))
    record, depth, cover = json.loads(raw["json"]), decode_depth(raw["depth.exr"]), decode_image(raw["cover.png"])
    layers = layers_from_record(record, cover)
    free = (cover[:, :, 0] == 0) & (cover[:, :, 1] == 0)
    assert np.abs(depth - layers.background)[free].max() < 1e-5
    assert np.all(depth[layers.planes[1][0]] == np.float32(record["front"]["disparity"]))
    assert json.loads(raw["json"])["size"] == [64, 64]
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
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=900, env=env)
    assert proc.returncode == 0, torchrun_failure(proc)
    assert json.loads((run / "env.json").read_text())["world_size"] == 2
    assert checkpoint.load(run / "ckpt.pt")["step"] == 2
    assert [r["step"] for r in _rows(run)] == ["0", "1", "2"]     # one writer (step 0: the start, validated)


def test_untouched_on_coarse_cells_is_conservative():
    """With long blurs the reach is spread on cells of f x f px: never a pixel that a blur
    reaches is called untouched (checked against the pixel-exact chessboard spread)."""
    from dofsynth.train import models

    rng = np.random.default_rng(5)
    signed = torch.zeros(1, 1, 200, 170)
    for _ in range(6):
        y, x = int(rng.integers(200)), int(rng.integers(170))
        signed[0, 0, y, x] = float(rng.uniform(0.3, 1.0))
    fast = models.untouched(signed, 60.0)        # reach up to 61 px: cells of 4 px
    c = signed.abs() * 60.0
    reach = torch.where(c >= 0.5, c + 1.0, torch.zeros_like(c))
    for _ in range(62):
        reach = torch.maximum(reach, torch.nn.functional.max_pool2d(reach, 3, stride=1, padding=1) - 1.0)
    exact = reach <= 0
    assert not (fast & ~exact).any()                # nothing reached is called free
    assert fast.sum() > 0.5 * exact.sum()           # and not much more is given up


def test_the_untrained_hybrid_is_the_classical_renderer(setup):
    """[model] kind = "hybrid": its correction starts at zero, so before training its output is
    the classical render from the depth it is given, bit for bit (and the image itself where no
    blur reaches, with [model] identity)."""
    from dofsynth.train.classical import classical_render
    from dofsynth.train.data import full_res_signed, training_item
    from dofsynth.train.segments import find_segments, raw_samples
    from dofsynth.train.models import HybridNet, untouched

    _, data, _, _ = setup
    cfg = tiny_config(model={"kind": "hybrid", "coc_ref": 4.0})
    raw = next(raw_samples(find_segments(data, "train"), "train"))
    item = training_item(raw, cfg, np.random.default_rng(3))
    rec = json.loads(raw["json"])
    image = item["image"].permute(1, 2, 0).numpy()
    expect = classical_render(image, item["disparity"][0].numpy(), item["focus"], item["max_coc"], rec)
    assert np.array_equal(item["classical"].permute(1, 2, 0).numpy(), expect.astype(np.float32))
    one = {k: (v[None] if torch.is_tensor(v) else [v]) for k, v in item.items()}
    for identity in (False, True):
        model = HybridNet(replace(cfg, "model", identity=identity).model).eval()
        with torch.no_grad():
            low, high = model(one["image"], one["signed_lo"], cfg.data.levels, **full_res_signed(one, cfg))
        kw = full_res_signed(one, cfg)
        want = torch.where(untouched(kw["signed_hi"], 4.0), one["image"], one["classical"]) if identity else one["classical"]
        assert torch.equal(high, want) and low.shape == one["target_lo"].shape
    with pytest.raises(ValueError, match="classical"):
        model(one["image"], one["signed_lo"], cfg.data.levels)


def test_the_teacher_is_the_classical_render_of_the_given_depth_and_adds_to_the_loss(setup, tmp_path):
    """[loss] teacher: each item carries the classical render of its (corrupted) disparity,
    area-downsampled as target_lo is, and the loss of the same first batch with the same weights
    grows by teacher * J(L, it) > 0. Only the paper's networks take it."""
    from dofsynth.train.classical import classical_render
    from dofsynth.train.data import area_downsample, training_item
    from dofsynth.train.segments import find_segments, raw_samples

    _, data, cfg_path, run4 = setup
    cfg = replace(load(cfg_path), "loss", teacher=0.5)
    raw = next(raw_samples(find_segments(data, "train"), "train"))
    item = training_item(raw, replace(cfg, "model", coc_ref=4.0), np.random.default_rng(3))
    image = item["image"].permute(1, 2, 0).numpy()
    full = classical_render(image, item["disparity"][0].numpy(), item["focus"], item["max_coc"], json.loads(raw["json"]))
    assert np.allclose(item["teacher_lo"].permute(1, 2, 0).numpy(), area_downsample(full, 2), atol=1e-6)
    assert item["teacher_lo"].shape == item["target_lo"].shape
    path = tmp_path / "teacher.toml"
    path.write_text(to_toml(replace(cfg, "train", max_steps=1, checkpoint_interval=1)))
    assert main(["train", str(path), "--data", str(data), "--run", str(tmp_path / "run"), "--device", "cpu"]) == 0
    assert float(_rows(tmp_path / "run")[1]["loss"]) > float(_rows(run4)[1]["loss"])
    with pytest.raises(ValueError, match="loss.teacher"):
        from_dict({"model": {"kind": "hybrid"}, "loss": {"teacher": 0.5}})


def test_the_near_regions_grow_and_shrink_by_a_disc_of_the_radius():
    """classical.near_shifted: a plate of near disparity grown and shrunk by r px, by Euclidean
    distance (a disc), the far side untouched."""
    from dofsynth.train.classical import near_shifted

    d = np.full((40, 40), 0.2, np.float32)
    d[15:25, 15:25] = 0.8
    grown, shrunk = near_shifted(d, 3)
    yy, xx = np.mgrid[0:40, 0:40]
    dist = np.hypot(np.clip(np.maximum(15 - yy, yy - 24), 0, None), np.clip(np.maximum(15 - xx, xx - 24), 0, None))
    assert np.array_equal(grown == 0.8, dist <= 3.0)  # (the disc of radius 3 px on the pixel grid)
    assert np.array_equal(shrunk == 0.8, (yy >= 18) & (yy <= 21) & (xx >= 18) & (xx <= 21))
    assert set(np.unique(grown)) | set(np.unique(shrunk)) == {np.float32(0.2), np.float32(0.8)}


def test_a_hybrid_given_shifted_renders_starts_as_the_classical_render_and_can_pick_one(setup):
    """[model] near_shift: the hybrid's input holds the classical renders from the given depth and
    from it with its near regions grown and shrunk (the same renders as classical_render's);
    untrained, its output is the first bit for bit; a head that mixes one of the others in
    with weight 1 outputs that render."""
    from dofsynth.train.classical import classical_render, near_shifted
    from dofsynth.train.data import full_res_signed, training_item
    from dofsynth.train.segments import find_segments, raw_samples
    from dofsynth.train.models import HybridNet

    _, data, _, _ = setup
    cfg = tiny_config(model={"kind": "hybrid", "coc_ref": 4.0, "identity": False, "near_shift": 2})
    raw = next(raw_samples(find_segments(data, "train"), "train"))
    item = training_item(raw, cfg, np.random.default_rng(3))
    rec, image, disparity = json.loads(raw["json"]), item["image"].permute(1, 2, 0).numpy(), item["disparity"][0].numpy()
    stack = item["classical"].permute(1, 2, 0).numpy()
    assert stack.shape[2] == 9
    for k, d in enumerate([disparity, *near_shifted(disparity, 2)]):
        assert np.array_equal(stack[:, :, 3 * k : 3 * k + 3], classical_render(image, d, item["focus"], item["max_coc"], rec))
    assert not np.array_equal(stack[:, :, 3:6], stack[:, :, 6:9])  # the grown and the shrunk near regions differ
    one = {k: (v[None] if torch.is_tensor(v) else [v]) for k, v in item.items()}
    model = HybridNet(cfg.model).eval()
    with torch.no_grad():
        assert torch.equal(model(one["image"], one["signed_lo"], cfg.data.levels, **full_res_signed(one, cfg))[1],
                           one["classical"][:, :3])
        for k in (1, 2):  # the head mixes render k in with weight 1, the rest 0
            torch.nn.init.zeros_(model.head.bias), torch.nn.init.constant_(model.head.bias[2 + k], 1.0)
            _, high = model(one["image"], one["signed_lo"], cfg.data.levels, **full_res_signed(one, cfg))
            torch.testing.assert_close(high, one["classical"][:, 3 * k : 3 * k + 3], atol=1e-6, rtol=0)
        with pytest.raises(ValueError, match=r"classical must be \(B, 9"):
            model(one["image"], one["signed_lo"], cfg.data.levels, classical=one["classical"][:, :3])
    with pytest.raises(ValueError, match="model.near_shift"):
        tiny_config(model={"near_shift": 2})  # the paper's networks have no classical input


def test_render_with_scales_the_near_shift_with_the_photo(monkeypatch):
    """At inference the hybrid's grown and shrunk renders shift the near regions by near_shift
    px scaled as the CoC is (the photo's long side over the training image's), at least 1 px;
    its CoC likewise."""
    import dofsynth.train.infer as infer
    from dofsynth.train.models import HybridNet

    cfg = tiny_config(model={"kind": "hybrid", "coc_ref": 8.0, "near_shift": 3}, infer={"low_res_side": 16})
    model = HybridNet(cfg.model).eval()
    seen = []
    real = infer.classical_stack
    monkeypatch.setattr(infer, "classical_stack",
                        lambda *a: seen.append((a[3], a[6])) or real(*a))  # (max_coc, near_shift)
    train_side = 16 * 2 ** cfg.data.levels
    for side in (train_side, 2 * train_side, train_side // 4):
        image = np.full((side, side, 3), 0.5, np.float32)
        infer.render_with(model, cfg, image, np.full((side, side), 0.3, np.float32), 0.6)
    # a photo under low_res_side (16 px) is rendered enlarged to it: half the training side
    assert cfg.data.levels == 1 and seen == [(8.0, 3), (16.0, 6), (4.0, 2)]
    infer.render_with(model, cfg, np.full((train_side, train_side, 3), 0.5, np.float32),
                      np.full((train_side, train_side), 0.3, np.float32), 0.6, aperture=0.5)
    assert seen[-1] == (4.0, 3)  # a smaller aperture blurs less; the edges' displacement stays


def _edge_scene() -> np.ndarray:
    """A signed disparity with a plate 2.4 px of CoC in front, a step of 1.2 px behind and one of
    0.2 px (no edge) at coc_px 4, plus noise far below 1 px."""
    g = np.random.default_rng(4)
    signed = np.zeros((40, 50), np.float32) + 0.1
    signed[10:22, 8:30] = 0.6                      # a plate 2.4 px of CoC in front (coc_px 4)
    signed[30:, 35:] = -0.2                        # a step of 1.2 px behind
    signed[:5, 40:] = 0.1 + 0.2 / 4                # a step of 0.2 px: no edge
    signed += g.uniform(-0.01, 0.01, signed.shape).astype(np.float32)  # noise far below 1 px
    return signed


def _band_by_scan(c: np.ndarray, margin: float = 0.0) -> np.ndarray:
    """Brute force: the pixels within (larger |CoC| + 1 px + margin) chessboard distance of a
    pixel whose 3 x 3 neighbourhood's CoCs differ by 1 px or more."""
    want = np.zeros(c.shape, bool)
    H, W = c.shape
    for y in range(H):
        for x in range(W):
            win = c[max(y - 1, 0) : y + 2, max(x - 1, 0) : x + 2]
            if win.max() - win.min() >= 1.0:
                r = int(np.floor(np.abs(win).max() + 1.0 + margin))
                want[max(y - r, 0) : y + r + 1, max(x - r, 0) : x + r + 1] = True
    return want


def test_the_edge_weight_covers_every_pixel_an_edges_blur_reaches_and_fades():
    """`edge_weight` > 0: the pixels within (larger |CoC| + 1 px) chessboard distance of a pair
    of neighbours whose CoCs differ by 1 px or more, against a brute-force scan; the weight
    fades from 1 near the edges to 0 where the band ends without a step."""
    from dofsynth.train.models import edge_weight

    signed = _edge_scene()
    weight = edge_weight(torch.from_numpy(signed)[None, None], 4.0)[0, 0].numpy()
    got = weight > 0
    c = signed * 4.0
    want = _band_by_scan(c)
    assert np.array_equal(got, want)
    assert want.any() and not want.all() and not want[:3, 44:].any()
    # the gate's weight: 1 on the edges of the longest reach, no step anywhere (no seam)
    ramp = max(np.floor(np.abs(c).max() + 1.0), 2.0) / 2  # (the plate's reach / 2)
    assert weight.min() == 0.0 and weight.max() == 1.0 and weight[10, 8:30].min() == 1.0
    assert max(np.abs(np.diff(weight, axis=0)).max(), np.abs(np.diff(weight, axis=1)).max()) <= 1.0 / ramp + 1e-6


def test_the_edge_weight_reaches_its_margin_further():
    """`edge_weight(..., margin)`: every edge reaches `margin` px further (the brute-force band
    of the grown reach), still fading without a step; margin 0 is the plain band."""
    from dofsynth.train.models import edge_weight

    signed = _edge_scene()
    c = signed * 4.0
    plain = edge_weight(torch.from_numpy(signed)[None, None], 4.0)[0, 0].numpy()
    wide = edge_weight(torch.from_numpy(signed)[None, None], 4.0, 3.5)[0, 0].numpy()
    assert np.array_equal(wide > 0, _band_by_scan(c, 3.5))
    assert (wide > 0).sum() > (plain > 0).sum() and np.all(wide[plain > 0] > 0)
    assert np.array_equal(edge_weight(torch.from_numpy(signed)[None, None], 4.0, 0.0)[0, 0].numpy(), plain)
    ramp = max(np.floor(np.abs(c).max() + 1.0 + 3.5), 2.0) / 2
    assert wide.max() == 1.0 and max(np.abs(np.diff(wide, axis=0)).max(), np.abs(np.diff(wide, axis=1)).max()) <= 1.0 / ramp + 1e-6


def test_the_hybrids_gate_margin_is_px_at_the_data_size_scaled_with_the_coc(monkeypatch):
    """[model] gate_margin: px at the data's size (where coc_px = coc_ref), so a render at twice
    the CoC scale widens the gate by twice as many px; only with gate = "edges"."""
    from dofsynth.train import models
    from dofsynth.train.config import ModelConfig

    seen = []
    real = models.edge_weight
    monkeypatch.setattr(models, "edge_weight", lambda s, c, m=0.0: seen.append((c, m)) or real(s, c, m))
    model = models.HybridNet(ModelConfig(kind="hybrid", kp_width=4, kp_depth=1, gate="edges", gate_margin=3,
                                         coc_ref=4.0)).eval()
    image, signed = torch.rand(1, 3, 16, 16), torch.zeros(1, 1, 16, 16)
    with torch.no_grad():
        for coc_px in (4.0, 8.0):
            model(image, signed, sizes=[(16, 16)], signed_hi=signed, coc_px=coc_px, classical=image)
    assert seen == [(4.0, 3.0), (8.0, 6.0)]
    with pytest.raises(ValueError, match="coc_ref"):  # not silently the plain gate
        models.HybridNet(ModelConfig(kind="hybrid", gate="edges", gate_margin=3))
    with pytest.raises(ValueError, match="model.gate_margin"):
        tiny_config(model={"kind": "hybrid", "gate_margin": 2})  # no gate to widen


def test_a_gated_hybrid_corrects_only_near_the_given_depths_edges(setup):
    """[model] gate = "edges": whatever the correction learned, the output is the classical
    render wherever no edge of the given depth is within the blur's reach (`edge_weight` 0)."""
    from dofsynth.train.data import full_res_signed, training_item
    from dofsynth.train.segments import find_segments, raw_samples
    from dofsynth.train.models import HybridNet, edge_weight

    _, data, _, _ = setup
    cfg = tiny_config(model={"kind": "hybrid", "coc_ref": 4.0, "identity": False, "gate": "edges"})
    raw = next(raw_samples(find_segments(data, "train"), "train"))
    one = {k: (v[None] if torch.is_tensor(v) else [v]) for k, v in training_item(raw, cfg, np.random.default_rng(3)).items()}
    model = HybridNet(cfg.model).eval()
    torch.nn.init.normal_(model.head.weight, std=0.5), torch.nn.init.constant_(model.head.bias, 0.25)  # "trained"
    kw = full_res_signed(one, cfg)
    with torch.no_grad():
        _, high = model(one["image"], one["signed_lo"], cfg.data.levels, **kw)
    band = (edge_weight(kw["signed_hi"], 4.0) > 0).expand_as(high)
    assert band.any() and not band.all()
    assert torch.equal(high[~band], one["classical"][~band])
    assert not torch.equal(high[band], one["classical"][band])
    with pytest.raises(ValueError, match="gate"):
        model(one["image"], one["signed_lo"], cfg.data.levels, classical=one["classical"])
    with pytest.raises(ValueError, match="model.gate"):
        tiny_config(model={"gate": "edges"})  # the paper's networks have no correction to gate


@pytest.mark.parametrize("near_shift", [0, 2])
def test_a_hybrid_run_trains_resumes_bit_identically_and_renders_a_photo(setup, tmp_path, shared_assets, near_shift):
    _, data, _, _ = setup
    cfg_path = tmp_path / "hybrid.toml"
    cfg_path.write_text(to_toml(tiny_config(model={"kind": "hybrid", "near_shift": near_shift})))
    runs = {}
    for name, stops in (("4", [None]), ("2+2", ["2", None])):
        runs[name] = tmp_path / name
        for stop in stops:
            args = ["train", str(cfg_path), "--data", str(data), "--run", str(runs[name]), "--device", "cpu"]
            assert main(args + (["--steps", stop] if stop else [])) == 0
    a, b = checkpoint.load(runs["4"] / "ckpt.pt"), checkpoint.load(runs["2+2"] / "ckpt.pt")
    assert a["step"] == b["step"] == 4
    assert all(torch.equal(a["model"][k], b["model"][k]) and torch.equal(a["ema"][k], b["ema"][k]) for k in a["model"])
    assert any(a["model"][k].abs().sum() > 0 for k in a["model"] if k.startswith("head."))  # it learned a correction
    photo = tmp_path / "photo.png"
    srgb = cv2.imread(str(shared_assets / "bg" / "kodak_kodim01.png"))
    cv2.imwrite(str(photo), cv2.resize(srgb, (96, 64), interpolation=cv2.INTER_AREA))
    depth = tmp_path / "depth.png"
    cv2.imwrite(str(depth), np.tile(np.linspace(0, 255, 96).astype(np.uint8), (64, 1)))
    out = tmp_path / "hybrid.png"
    assert main(["render", str(photo), "--depth", str(depth), "--focus", "0.5", "--model", str(runs["4"]),
                 "--out", str(out)]) == 0
    img = cv2.imread(str(out))
    assert img.shape == (64, 96, 3) and not np.array_equal(img, cv2.imread(str(photo)))


def test_the_hybrids_classical_input_is_the_same_render_in_either_colour_space():
    """classical_input for [data] color = "linear" is the sRGB input's render in linear light
    (decoded once, no encode and decode of the result), equal to decoding the "srgb" one."""
    import json

    from dofsynth.color import srgb_to_linear
    from dofsynth.train.classical import classical_input

    g = np.random.default_rng(np.random.SeedSequence(40))
    d = np.tile(np.linspace(0.2, 0.9, 40, dtype=np.float32), (32, 1))
    item = {"image": g.integers(0, 256, (32, 40, 3), dtype=np.uint8), "key": "k", "disparity": d, "focus": 0.5,
            "max_coc": 6.0, "look": json.dumps({"aperture": {"kind": "disk"}, "options": {
                "linear_light": True, "highlight": {"threshold": 0.9, "gain": 4.0, "power": 2.0}}})}
    srgb, linear = classical_input(item, "srgb"), classical_input(item, "linear")
    assert linear.dtype == np.float32 and linear.shape == (32, 40, 3)
    np.testing.assert_allclose(linear, srgb_to_linear(srgb), atol=2e-6)
    assert np.abs(linear - srgb).max() > 0.05  # a different colour space, not the same numbers
