"""DeepLens networks and loss: shapes, gradient flow, the loss by hand, a tiny model overfits."""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

from dofsynth.train.config import ModelConfig, from_dict
from dofsynth.train.loss import deeplens_loss, normalized_loss, ssim
from dofsynth.train.models import (ChannelFeatures, DeepLensNet, GuidedUpsampler, KernelPredictor,
                                   LensBlurNet, size_chain)

TINY = ModelConfig(feat_channels=4, kp_width=8, kp_depth=2, up_width=8)


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def test_size_chain_halves_rounding_up():
    assert size_chain((100, 60), 2) == [(25, 15), (50, 30), (100, 60)]
    assert size_chain((33, 17), 3) == [(5, 3), (9, 5), (17, 9), (33, 17)]
    assert size_chain((8, 8), 0) == [(8, 8)]


def test_module_shapes():
    torch.manual_seed(0)
    x = torch.rand(2, 3, 20, 28)
    s = torch.rand(2, 1, 20, 28) * 2 - 1
    feats = ChannelFeatures(8, (1, 2, 4, 8))
    assert feats(x).shape == (2, 3, 32, 20, 28) and feats.out_channels == 32   # c = 32 as in the paper
    assert KernelPredictor(32, 8, 3)(x, s).shape == (2, 32, 20, 28)
    assert LensBlurNet(8, (1, 2, 4, 8), 8, 3)(x, s).shape == (2, 3, 20, 28)
    up = GuidedUpsampler(8)(x, x, s, torch.rand(2, 3, 40, 55))
    assert up.shape == (2, 3, 40, 55)


@pytest.mark.parametrize("size,steps", [((32, 32), 1), ((45, 70), 2), ((17, 9), 3)])
def test_deeplens_net_any_size(size, steps):
    torch.manual_seed(0)
    net = DeepLensNet(TINY).eval()  # inference on any size (batch norm uses its running statistics)
    low_size = size_chain(size, steps)[0]
    low, high = net(torch.rand(1, 3, *size), torch.zeros(1, 1, *low_size), steps)
    assert low.shape == (1, 3, *low_size) and high.shape == (1, 3, *size)
    with pytest.raises(ValueError, match="signed_lo"):
        net(torch.rand(1, 3, *size), torch.zeros(1, 1, low_size[0] + 1, low_size[1]), steps)
    with pytest.raises(ValueError, match="image"):
        net(torch.rand(1, 4, *size), torch.zeros(1, 1, *low_size), steps)


VARIANTS = {
    "paper": TINY,
    "official": ModelConfig(feat_channels=4, kp_width=8, kp_depth=2, up_width=8, up_depth=2, features="joint",
                            raw_feature=True, kernel="blur", norm="batch"),
    "group-norm": ModelConfig(feat_channels=4, kp_width=8, kp_depth=1, up_width=8, norm="group"),
    "blur-init": ModelConfig(feat_channels=4, kp_width=8, kp_depth=1, up_width=8, feat_init="blur"),
    "blur-init joint": ModelConfig(feat_channels=4, kp_width=8, kp_depth=1, up_width=8, feat_init="blur",
                                   features="joint"),
}


@pytest.mark.parametrize("variant", list(VARIANTS))
def test_gradients_reach_every_parameter(variant):
    torch.manual_seed(0)
    net = DeepLensNet(VARIANTS[variant])
    image = torch.rand(2, 3, 32, 32)
    signed = torch.rand(2, 1, 8, 8) - 0.5
    low, high = net(image, signed, 2)
    loss, _, _ = deeplens_loss(low, high, torch.rand_like(low), torch.rand_like(high))
    loss.backward()
    for name, p in net.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all() and p.grad.abs().sum() > 0, name


@pytest.mark.parametrize("joint", [False, True])
def test_blur_init_features_are_blurs_of_their_own_colour(joint):
    """feat_init = "blur": every feature starts as a normalised blur of its colour alone, so a flat
    image gives flat features equal to it, an impulse keeps its mass, each layer's map k blurs
    more than map k - 1, and the deepest, widest map spreads it with the cascade's std
    sqrt(2/3 x sum d^2) px (box means of 3 taps, d apart, have variance 2 d^2 / 3 per axis)."""
    feats = ChannelFeatures(4, (1, 2, 4), joint=joint, init="blur")
    flat = torch.tensor([0.2, 0.5, 0.9]).view(1, 3, 1, 1).expand(1, 3, 9, 11)
    assert torch.allclose(feats(flat), flat.unsqueeze(2).expand(1, 3, 12, 9, 11), atol=1e-6)
    x = torch.zeros(1, 3, 41, 41)
    x[0, 1, 20, 20] = 1.0  # an impulse in green only
    f = feats(x).detach()[0]
    assert f[0].abs().max() == 0 and f[2].abs().max() == 0          # red and blue untouched
    assert torch.allclose(f[1].sum(dim=(-2, -1)), torch.ones(12), atol=1e-5)
    rows = torch.arange(41.0).view(41, 1) - 20
    std = ((rows**2 * f[1]).sum(dim=(-2, -1))).sqrt()               # per feature, px
    assert torch.all(std.view(3, 4).diff(dim=1) > 0)                # within a layer: t grows
    assert std[-1] == pytest.approx(math.sqrt(2 / 3 * (1 + 4 + 16)), rel=1e-4)
    with pytest.raises(ValueError, match="init"):
        ChannelFeatures(4, (1, 2), init="gauss")
    with pytest.raises(ValueError, match="model.feat_init"):  # the hybrid has no features to start
        from_dict({"model": {"kind": "hybrid", "feat_init": "blur"}})


def _disc_blur(image: np.ndarray, radius: float) -> np.ndarray:
    """(H, W, 3) float32 image blurred by the anti-aliased disc of `radius` px (edges replicated)."""
    import cv2

    from dofsynth.optics.aperture import Disk
    from dofsynth.optics.kernel import kernel
    return image if radius == 0 else cv2.filter2D(image, -1, kernel(Disk(), radius), borderType=cv2.BORDER_REPLICATE)


def test_kernel_prior_starts_the_lens_blur_as_the_disc_blur_the_depth_asks_for(shared_assets):
    """[model] kernel_prior = "discs": the untrained lens-blur module on a photo is the disc blur of
    radius |s| coc_ref / 2**levels px wherever s is constant (PSNR over 36 dB against it, 41-45
    measured, where the photo itself is under 30), for either sign of s, between knots and with s
    beyond [-1, 1] clamped; s = 0 gives the photo itself. Gradients reach the table and the
    predictor's head (started at zero)."""
    import cv2

    cfg = from_dict({"model": {**dataclasses.asdict(TINY), "feat_channels": 8, "feat_dilations": [1, 2, 4, 8],
                               "feat_init": "blur", "kernel_prior": "discs", "coc_ref": 24.0}})
    net = DeepLensNet(cfg.model, levels=1).eval()                   # 12 px of radius per unit of s
    bgr = cv2.imread(str(shared_assets / "bg" / "kodak_kodim08.png"))
    photo = cv2.resize(bgr, (192, 128), interpolation=cv2.INTER_AREA)[:, :, ::-1].astype(np.float32) / 255
    x = torch.from_numpy(photo.transpose(2, 0, 1).copy())[None]

    def psnr(a, b, m=16):  # away from the frame's edge and from the depth step (columns 80-112)
        a, b = a[m:-m, m:-m], b[m:-m, m:-m]
        return 10 * math.log10(1 / float(np.mean((a - b) ** 2)))

    for left, right in [(0.0, -1.0), (0.5, 0.37), (-0.25, 1.6)]:
        signed = torch.full((1, 1, 128, 192), left)
        signed[..., 96:] = right
        with torch.no_grad():
            lens = net.lens(x, signed)[0].numpy().transpose(1, 2, 0)
        for value, part in [(left, np.s_[:, :80]), (right, np.s_[:, 112:])]:
            want = _disc_blur(photo, 12 * min(abs(value), 1.0))
            if value == 0:
                assert np.abs(lens[part] - photo[part])[16:-16, 16:-16].max() < 2e-3
            else:
                assert psnr(lens[part], want[part]) > 36, (value, psnr(lens[part], want[part]))
                assert psnr(photo[part], want[part]) < 30   # (the blur is not the photo)
    net.train()
    low, high = net(x[..., :64, :64], torch.rand(1, 1, 32, 32) * 2 - 1, 1)
    deeplens_loss(low, high, torch.rand_like(low), torch.rand_like(high))[0].backward()
    assert net.lens.prior.table.grad.abs().sum() > 0 and net.lens.kernel.head.weight.grad.abs().sum() > 0
    assert net.lens.kernel.head.weight.abs().max() == 0            # (started at zero)


def test_boosted_light_is_the_renders_highlight_boost_and_its_inverse(shared_assets):
    """dofsynth.train.light against dofsynth.render.highlight on a real photo with near-white
    pixels: the boost within 2e-5 (the render's 256-knot curve), the inverse undoes it, and its
    gradient is the derivative of the inverse (checked numerically, in float64)."""
    import cv2

    from dofsynth.color import linear_to_srgb, srgb_to_linear
    from dofsynth.render.highlight import boost, unboost
    from dofsynth.train.light import BoostedLight, srgb_decode, srgb_encode

    photo = cv2.imread(str(shared_assets / "bg" / "kodak_kodim08.png"))[::4, ::4, ::-1].astype(np.float32) / 255
    lin = srgb_to_linear(photo)
    assert (lin.max(axis=2) > srgb_to_linear(np.float32(0.9))).mean() > 0.005      # it has highlights
    t = torch.from_numpy(lin.transpose(2, 0, 1).copy())[None]
    light = BoostedLight(0.9, 4.0, 2.0)
    boosted = boost(lin, 0.9, 4.0, 2.0).transpose(2, 0, 1)[None]
    assert float((light.boost(t) - torch.from_numpy(boosted)).abs().max()) < 2e-5 and boosted.max() > 4.5
    assert float((light.unboost(torch.from_numpy(boosted)) - t).abs().max()) < 2e-5
    assert np.allclose(light.unboost(torch.from_numpy(boosted)).numpy(), unboost(boosted.copy(), axis=1), atol=2e-5)
    assert float((srgb_decode(torch.from_numpy(photo)) - torch.from_numpy(lin)).abs().max()) < 1e-6
    assert float((srgb_encode(torch.from_numpy(lin)) - torch.from_numpy(linear_to_srgb(lin))).abs().max()) < 1e-6
    y = (torch.rand(1, 3, 4, 5, dtype=torch.float64, generator=torch.Generator().manual_seed(0)) * 6).requires_grad_(True)
    assert torch.autograd.gradcheck(light.unboost, (y,), eps=1e-6, atol=1e-4)
    x = torch.tensor([-0.5, 0.5, 2.0], requires_grad=True)          # out of range: still a gradient
    srgb_encode(x).sum().backward()
    assert (x.grad > 0).all()


def test_boosted_light_starts_the_lens_blur_as_the_targets_blur(shared_assets):
    """[model] light = "boosted" with the disc prior: the untrained module on a photo with small
    white lights is the disc blur made as the targets are (linear light, highlights boosted, the
    boost undone, sRGB), within 32 dB (33-35 measured) at radii of 3-12 px; the module on the
    sRGB codes is under 22 dB from it (its lights come out dim and grey)."""
    import cv2

    from dofsynth.color import linear_to_srgb, srgb_to_linear
    from dofsynth.render.highlight import boost, unboost

    bgr = cv2.imread(str(shared_assets / "bg" / "kodak_kodim08.png"))
    photo = cv2.resize(bgr, (192, 128), interpolation=cv2.INTER_AREA)[:, :, ::-1].astype(np.float32) / 255
    for y, x in [(30, 40), (60, 100), (90, 150), (40, 160), (100, 50)]:
        photo[y:y + 2, x:x + 2] = 1.0
    image = torch.from_numpy(photo.transpose(2, 0, 1).copy())[None]

    def psnr(a, b, m=16):  # away from the frame's edge
        return 10 * math.log10(1 / float(np.mean((a[m:-m, m:-m] - b[m:-m, m:-m]) ** 2)))

    for light in ("boosted", "input"):
        cfg = from_dict({"model": {**dataclasses.asdict(TINY), "feat_channels": 8, "feat_init": "blur",
                                   "kernel_prior": "discs", "coc_ref": 24.0, "light": light}})
        net = DeepLensNet(cfg.model, levels=1).eval()                   # 12 px of radius per unit of s
        for s in (0.25, -0.5, 1.0):
            want = linear_to_srgb(unboost(_disc_blur(boost(srgb_to_linear(photo)), 12 * abs(s))))
            with torch.no_grad():
                low, _ = net(image, torch.full((1, 1, 128, 192), s), 0)
            got = psnr(low[0].numpy().transpose(1, 2, 0), want)
            assert (got > 32) if light == "boosted" else (got < 22), (light, s, got)


def test_kernel_prior_is_refused_where_it_cannot_be_fitted():
    for model in [{"kernel_prior": "discs"},                                   # random features
                  {"kernel_prior": "discs", "feat_init": "blur", "kernel": "blur"},
                  {"kernel_prior": "discs", "kind": "hybrid"}]:
        with pytest.raises(ValueError, match="model.kernel_prior"):
            from_dict({"model": model})
    cfg = from_dict({"model": {"kernel_prior": "discs", "feat_init": "blur"}})   # coc_ref not resolved
    with pytest.raises(ValueError, match="coc_ref"):
        DeepLensNet(cfg.model, levels=1)
    with pytest.raises(ValueError, match="levels"):                            # nor the lens blur's size
        DeepLensNet(from_dict({"model": {**cfg.to_dict()["model"], "coc_ref": 8.0}}).model)
    for bad in [{"model": {"light": "boosted", "kind": "hybrid"}}, {"model": {"light": "boosted"}, "data": {"color": "linear"}}]:
        with pytest.raises(ValueError, match="model.light"):
            from_dict(bad)
    with pytest.raises(ValueError, match="model.boost"):
        from_dict({"model": {"boost": [1.0, 4.0, 2.0]}})


def test_joint_features_with_the_raw_image_and_blur_kernels():
    """Joint RGB features deal their maps out to the colours, the raw channel comes first, and
    "blur" kernels make each output pixel a convex mix of its features."""
    torch.manual_seed(0)
    x = torch.rand(2, 3, 12, 14)
    feats = ChannelFeatures(4, (1, 2), joint=True, raw=True)
    f = feats(x)
    assert f.shape == (2, 3, 9, 12, 14) and feats.out_channels == 9
    assert torch.equal(f[:, :, 0], x)
    net = LensBlurNet(4, (1, 2), 8, 1, joint=True, raw=True, kernel="blur")
    out = net(x, torch.rand(2, 1, 12, 14) - 0.5)
    f = net.features(x)
    assert (out >= f.min(dim=2).values - 1e-5).all() and (out <= f.max(dim=2).values + 1e-5).all()
    with pytest.raises(ValueError, match="kernel"):
        LensBlurNet(4, (1,), 8, 1, kernel="sharp")


def test_guided_upsampler_blends_between_the_sharp_image_and_the_upsampled_result():
    torch.manual_seed(0)
    up = GuidedUpsampler(4)
    hi = torch.rand(1, 3, 16, 16)
    lo = torch.rand(1, 3, 8, 8)
    out = up(lo, lo, torch.zeros(1, 1, 8, 8), hi)
    up_lo = torch.nn.functional.interpolate(lo, size=(16, 16), mode="bilinear", align_corners=False)
    assert torch.all(out >= torch.minimum(hi, up_lo) - 1e-6) and torch.all(out <= torch.maximum(hi, up_lo) + 1e-6)


def test_normalized_loss_by_hand():
    x = torch.tensor([1.0, 3.0, -2.0, 0.5])
    y = torch.tensor([0.0, 1.0, -2.0, 0.5])      # errors 1, 2, 0, 0
    expect = (1 + 2**2.5) / (1 + 2**1.5)        # = 1.73880...
    assert math.isclose(normalized_loss(x, y, alpha=1.5).item(), expect, rel_tol=1e-6)
    assert math.isclose(expect, 1.738796, rel_tol=1e-5)
    assert math.isclose(normalized_loss(x, y, alpha=0.0).item(), 3 / 4, rel_tol=1e-6)  # alpha 0: plain L1 mean
    total, jl, jh = deeplens_loss(x, y, x * 0, y * 0, beta=0.5)
    assert math.isclose(total.item(), jl.item() + 0.5 * jh.item(), rel_tol=1e-6)
    with_l1, _, _ = deeplens_loss(x, y, x * 0, y * 0, beta=0.5, l1=2.0)   # + 2 * (mean|x| + 0.5 mean|y|)
    assert math.isclose(with_l1.item(), total.item() + 2.0 * (6.5 / 4 + 0.5 * 3.5 / 4), rel_tol=1e-6)
    # [loss] teacher: + 0.5 * J(L, C_lo), here C_lo = y, so the same J by hand as above
    taught, _, _ = deeplens_loss(x, y, x * 0, y * 0, beta=0.5, teacher=0.5, teacher_lo=y)
    assert math.isclose(taught.item(), total.item() + 0.5 * expect, rel_tol=1e-6)
    with pytest.raises(ValueError, match="teacher_lo"):
        deeplens_loss(x, y, x * 0, y * 0, teacher=0.5)


def test_ssim_is_the_evaluations_and_its_loss_term_is_zero_only_at_the_target():
    """[loss] ssim: the SSIM of skimage's structural_similarity (what eval reports), 1 at the
    target, so ssim * (1 - SSIM(H, T)) adds nothing there and pulls H toward T elsewhere."""
    from skimage.metrics import structural_similarity

    rng = np.random.default_rng(3)
    t = rng.random((2, 3, 23, 30)).astype(np.float32)
    h = np.clip(t + 0.08 * rng.standard_normal(t.shape).astype(np.float32), 0, 1)
    want = np.mean([structural_similarity(t[i].astype(np.float64), h[i].astype(np.float64), data_range=1.0,
                                          channel_axis=0) for i in range(2)])
    assert abs(ssim(torch.from_numpy(h), torch.from_numpy(t)).item() - want) < 1e-5
    T, H = torch.from_numpy(t), torch.from_numpy(h).requires_grad_()
    assert ssim(T, T).item() == pytest.approx(1.0, abs=1e-6)
    lo = torch.zeros(2, 3, 4, 4)
    base, _, _ = deeplens_loss(lo, T, lo, T)
    at_target, _, _ = deeplens_loss(lo, T, lo, T, ssim_weight=2.0)
    assert at_target.item() == pytest.approx(base.item(), abs=1e-6)
    total, _, jh = deeplens_loss(lo, H, lo, T, ssim_weight=2.0)
    assert total.item() == pytest.approx(jh.item() + 2.0 * (1.0 - want), abs=1e-5)
    total.backward()
    step = H.detach() - 0.05 * H.grad / H.grad.abs().max()  # a small step down the gradient
    assert ssim(step, T).item() > want
    with pytest.raises(ValueError, match="differ in shape"):
        ssim(T, T[:, :, :-1])
    with pytest.raises(ValueError, match="at least 7 x 7"):
        ssim(T[:, :, :6], T[:, :, :6])


def test_the_default_loss_pulls_every_pixel_toward_its_target_where_j_pushes_small_errors_up():
    """Errors 0.01 and 0.5, by hand: J = (0.01^2.5 + 0.5^2.5) / (0.01^1.5 + 0.5^1.5) = 0.49862,
    and dJ/dx_0 has the sign of 2.5 * 0.01 - 1.5 J < 0: J pushes the small error *up*. The
    default ("weighted") has the same value; its gradient is w_i sign(e_i) / sum w with
    w = |e|^1.5: (0.001, 0.35355) / 0.35455, toward the target at both pixels."""
    y = torch.tensor([0.2, 0.3])
    j_value = (0.01 ** 2.5 + 0.5 ** 2.5) / (0.01 ** 1.5 + 0.5 ** 1.5)
    assert math.isclose(j_value, 0.49862, rel_tol=1e-4)
    grads = {}
    for kind in ("j", "weighted"):
        x = (y + torch.tensor([0.01, 0.5])).requires_grad_(True)
        total, low, _ = deeplens_loss(x, y, y, y, beta=0.0, kind=kind)  # L = x against T_lo = y
        assert math.isclose(low.item(), j_value, rel_tol=1e-5)  # one value, two gradients
        total.backward()
        grads[kind] = x.grad
    assert grads["j"][0] < 0 < grads["j"][1]                     # the paper's J: the small error grows
    w = torch.tensor([0.01 ** 1.5, 0.5 ** 1.5])
    assert torch.allclose(grads["weighted"], w / w.sum(), rtol=1e-4)
    assert (grads["weighted"] > 0).all()                          # both errors shrink
    # its only minimum is the target: 0 there, > 0 at any other point of a line through it
    for t in (-1.0, -0.1, -1e-3, 1e-3, 0.1, 1.0):
        x = y + t * torch.tensor([0.3, -0.7])
        assert deeplens_loss(x, x, y, y, kind="weighted")[0].item() > 0
    assert deeplens_loss(y, y, y, y, kind="weighted")[0].item() == 0.0
    with pytest.raises(ValueError, match="loss kind"):
        deeplens_loss(y, y, y, y, kind="l2")


def test_zero_error_gives_zero_loss_and_finite_gradients():
    x = torch.rand(2, 3, 4, 4, requires_grad=True)
    loss = normalized_loss(x, x.detach().clone())
    assert loss.item() == 0.0
    loss.backward()
    assert torch.isfinite(x.grad).all() and x.grad.abs().sum() == 0
    with pytest.raises(ValueError, match="shape"):
        normalized_loss(torch.zeros(2), torch.zeros(3))


def test_a_tiny_model_overfits_a_small_batch():
    """Lens blur of a fixed batch: the loss falls at least five-fold (about eight-fold) in 200 CPU steps."""
    g = torch.Generator().manual_seed(0)
    torch.manual_seed(0)
    image = torch.nn.functional.interpolate(torch.rand(2, 3, 4, 4, generator=g), size=(16, 16), mode="nearest")
    disparity = torch.zeros(2, 1, 16, 16)
    disparity[:, :, 4:12, 4:12] = 1.0
    focus = 1.0
    blurred = torch.nn.functional.avg_pool2d(image, 5, stride=1, padding=2, count_include_pad=False)
    w = (disparity - focus).abs()
    target = (1 - w) * image + w * blurred                     # sharp square in focus, blurred around it
    target_lo = torch.nn.functional.avg_pool2d(target, 2)
    signed_lo = torch.nn.functional.avg_pool2d(disparity - focus, 2)
    net = DeepLensNet(TINY)
    opt = torch.optim.AdamW(net.parameters(), lr=3e-3)
    losses = []
    for _ in range(200):
        low, high = net(image, signed_lo, 1)
        loss, _, _ = deeplens_loss(low, high, target_lo, target)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert np.isfinite(losses).all()
    assert min(losses[-10:]) < losses[0] / 5, (losses[0], losses[-10:])


@pytest.mark.parametrize("depth", [1, 3])
def test_the_hybrids_correction_in_bands_of_rows_is_the_whole_frames(depth):
    """`render --model` runs the hybrid's full-resolution U-Net in bands of rows (memory); each
    band reads `unet_reach` more rows on either side, so the result is the whole frame's, for a
    height that is not a multiple of the U-Net's stride; with too small a margin it is not."""
    from dofsynth.train import models
    from dofsynth.train.models import HybridNet

    torch.manual_seed(depth)
    model = HybridNet(ModelConfig(kind="hybrid", kp_width=8, kp_depth=depth)).eval()
    torch.nn.init.normal_(model.head.weight, std=0.5)
    x = torch.rand(1, 7, 213, 40)
    with torch.no_grad():
        whole = model._correction([x], None)
        for rows in (8, 50):
            torch.testing.assert_close(model._correction([x], rows), whole, atol=1e-6, rtol=0)
        reach = models.unet_reach
        models.unet_reach = lambda d: 1
        try:
            assert (model._correction([x], 8) - whole).abs().max() > 2e-5
        finally:
            models.unet_reach = reach
    assert whole.abs().max() > 0.05


def test_the_gated_hybrid_runs_its_u_net_only_near_the_depth_edges():
    """With [model] gate = "edges" the correction is weighted 0 beyond the blur's reach of a depth
    edge, so `render --model` (rows given) runs the U-Net only on the tiles within it: the
    output is the whole frame's, from under half of its pixels; with group normalisation (not
    local) the frame goes whole."""
    from dofsynth.train.models import HybridNet, edge_weight

    torch.manual_seed(0)
    H, W = 200, 264
    image, classical = torch.rand(1, 3, H, W), torch.rand(1, 3, H, W)
    signed = torch.full((1, 1, H, W), -0.1)
    signed[..., 150:, 200:] = 0.3  # a near object in one corner: its edge reaches 7 px (coc_px 16)
    for norm in ("batch", "group"):
        model = HybridNet(ModelConfig(kind="hybrid", kp_width=8, kp_depth=1, gate="edges", norm=norm)).eval()
        torch.nn.init.normal_(model.head.weight, std=0.5)
        areas = []
        model.body.register_forward_hook(lambda m, i, o: areas.append(i[0].shape[-2] * i[0].shape[-1]))
        kw = dict(sizes=[(H, W)], signed_hi=signed, coc_px=16.0, classical=classical)
        with torch.no_grad():
            _, whole = model(image, signed, **kw)
            areas.clear()
            _, tiled = model(image, signed, rows=8, **kw)
        torch.testing.assert_close(tiled, whole, atol=1e-6, rtol=0)
        band = edge_weight(signed, 16.0) > 0
        assert band.any() and not torch.equal(whole[band.expand_as(whole)], classical[band.expand_as(whole)])
        assert sum(areas) < H * W / 2 if norm == "batch" else areas == [H * W]


@pytest.mark.parametrize("color", ["srgb", "linear"])
def test_render_model_with_an_untrained_hybrid_is_the_classical_render_of_the_photo(color, shared_assets):
    """`render --model` (infer.render_with) with a hybrid whose correction is still 0 and no
    identity rule gives the classical render of the linear photo (render.look.render_photo with
    the photo look, the CoC the run's coc_ref scaled to the photo), through the network's colour
    space and back: float rounding. (Given the photo as sRGB values instead, it is 0.16 off.)"""
    import cv2

    from dofsynth.color import srgb8_to_linear
    from dofsynth.optics.aperture import aperture_from_dict
    from dofsynth.render.look import Look, render_photo
    from dofsynth.train import infer
    from dofsynth.train.checkpoint import build_model
    from dofsynth.train.classical import PHOTO_LOOK
    from test_train_data import tiny_config

    cfg = tiny_config(data={"color": color}, model={"kind": "hybrid", "coc_ref": 3.0, "identity": False},
                      infer={"low_res_side": 16})
    model = infer.for_inference(build_model(cfg).eval())
    bgr = cv2.imread(str(shared_assets / "bg" / "kodak_kodim08.png"))
    photo = srgb8_to_linear(np.ascontiguousarray(cv2.resize(bgr, (64, 40), interpolation=cv2.INTER_AREA)[:, :, ::-1]))
    disparity = np.tile(np.linspace(0.0, 1.0, 64, dtype=np.float32), (40, 1))
    got = infer.render_with(model, cfg, photo, disparity, 0.4)
    coc_px = 3.0 * 64 / (16 * 2 ** cfg.data.levels)  # coc_ref at the photo's size (render_with's rule)
    want = render_photo(photo, disparity, 0.4, coc_px, aperture_from_dict(PHOTO_LOOK["aperture"]), Look())
    assert got.shape == want.shape == (40, 64, 3)
    assert float(np.abs(got - want).max()) < (2e-6 if color == "linear" else 1e-5)
    assert float(np.abs(got - photo).max()) > 0.05  # (the render is not the photo: a test that can fail)
