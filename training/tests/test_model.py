"""Networks: shapes, receptive radius (measured), FLOP and parameter counts, configs."""

import math

import pytest
import torch

from mcdenoise_train.checkpoint import load_checkpoint, save_checkpoint
from mcdenoise_train.contract import (
    COLOR_CHANNELS,
    FEATURES_FULL,
    FEATURES_NOCOV,
    KERNEL_TAPS,
    NOCOV_INDICES,
    select_nocov,
)
from mcdenoise_train.model import DenoiserNet, paper_config

SMALL = {
    "separate": dict(arch="separate", width=4, blocks=1, predictor_width=4, predictor_depth=2),
    "joint": dict(arch="joint", width=4, blocks=1, predictor_width=4, predictor_depth=2),
    "kpcn": dict(arch="kpcn", width=4, layers=3, conv_kernel=5),
    "separate-head1": dict(arch="separate", width=4, blocks=2, predictor_width=4,
                           predictor_depth=3, head_kernel=1),
}
# Radii by hand: separate/joint 1 + 2*blocks + 1 + (depth-1) + head//2; kpcn layers * 2.
SMALL_RADIUS = {"separate": 6, "joint": 6, "kpcn": 6, "separate-head1": 8}


def _inputs(n, c, h, w, dtype=torch.float32, seed=0):
    g = torch.Generator().manual_seed(seed)
    return (
        torch.randn(n, COLOR_CHANNELS, h, w, generator=g, dtype=dtype),
        torch.rand(n, c, h, w, generator=g, dtype=dtype),
    )


@pytest.mark.parametrize("name", sorted(SMALL))
@pytest.mark.parametrize("in_features", [28, 24])
def test_output_shape(name, in_features):
    torch.manual_seed(0)
    net = DenoiserNet(in_features=in_features, **SMALL[name])
    color, feats = _inputs(2, in_features, 13, 17)
    with torch.no_grad():
        out = net(color, feats)
    assert out.shape == (2, KERNEL_TAPS, 13, 17)
    assert out.dtype == torch.float32


def test_wrong_feature_count_rejected():
    with pytest.raises(ValueError):
        DenoiserNet(in_features=27)


@pytest.mark.parametrize("name", sorted(SMALL))
def test_receptive_radius_measured(name):
    torch.manual_seed(1)
    net = DenoiserNet(**SMALL[name]).double().eval()
    r = net.receptive_radius()
    assert r == SMALL_RADIUS[name]
    size = 2 * r + 7
    c = size // 2
    color, feats = _inputs(1, 28, size, size, torch.float64, seed=2)
    yy, xx = torch.meshgrid(torch.arange(size), torch.arange(size), indexing="ij")
    dist = torch.maximum((yy - c).abs(), (xx - c).abs())

    def centre(mask):
        col, fea = color.clone(), feats.clone()
        col[..., mask] += 3.0
        fea[..., mask] += 3.0
        with torch.no_grad():
            return net(col, fea)[0, :, c, c]

    base = centre(torch.zeros_like(dist, dtype=torch.bool))
    ring = centre(dist == r)
    outside = centre(dist > r)
    assert (ring - base).abs().max() > 1e-9, "a pixel at the receptive radius must matter"
    assert torch.equal(outside, base), "pixels beyond the receptive radius must not matter"
    # Each input separately reaches exactly as far (the extractors run in parallel).
    for which in ("color", "features"):
        col, fea = color.clone(), feats.clone()
        (col if which == "color" else fea)[..., dist == r] += 3.0
        with torch.no_grad():
            assert (net(col, fea)[0, :, c, c] - base).abs().max() > 1e-9, which


def _conv_macs(cin, cout, k=3):
    return cin * cout * k * k


def test_paper_config_numbers():
    net = DenoiserNet(**paper_config(28))
    w, blocks, pw, pd = 64, 8, 128, 4
    extractor = lambda cin: _conv_macs(cin, w) + 2 * blocks * _conv_macs(w, w) + _conv_macs(w, w)
    predictor = _conv_macs(2 * w, pw) + (pd - 2) * _conv_macs(pw, pw) + _conv_macs(pw, KERNEL_TAPS)
    macs = extractor(COLOR_CHANNELS) + extractor(28) + predictor
    assert macs == 2_225_664
    assert net.flops_per_pixel() == 2 * macs == 4_451_328
    biases = (1 + 2 * blocks + 1) * w * 2 + (pd - 1) * pw + KERNEL_TAPS
    assert net.param_count() == macs + biases == 2_228_793
    # The paper's figures: 2.23 M parameters, 4.45 MFLOP per pixel per component.
    assert round(net.param_count() / 1e6, 2) == 2.23
    assert round(net.flops_per_pixel() / 1e6, 2) == 4.45
    assert net.receptive_radius() == 22


def test_kpcn_defaults():
    net = DenoiserNet(arch="kpcn")
    assert net.config == dict(arch="kpcn", in_features=28, width=100, layers=9, conv_kernel=5, input_transform="symlog")
    assert net.receptive_radius() == 18
    convs = [m for m in net.modules() if isinstance(m, torch.nn.Conv2d)]
    assert len(convs) == 9 and all(m.kernel_size == (5, 5) for m in convs)
    relus = [m for m in net.modules() if isinstance(m, torch.nn.ReLU)]
    assert len(relus) == 8
    macs = 25 * (38 * 100 + 7 * 100 * 100 + 100 * 441)
    assert net.flops_per_pixel() == 2 * macs


def test_joint_matches_separate_parameters():
    sep = DenoiserNet(**paper_config(28))
    joint = DenoiserNet(arch="joint")
    assert joint.config["joint_width"] == 89
    assert abs(joint.param_count() - sep.param_count()) / sep.param_count() < 0.005
    # The kernel predictor is the same network.
    assert [p.shape for p in joint.predictor.parameters()] == [
        p.shape for p in sep.predictor.parameters()
    ]
    assert joint.receptive_radius() == sep.receptive_radius() == 22


@pytest.mark.parametrize("name", sorted(SMALL))
def test_init_and_config_roundtrip(name):
    torch.manual_seed(3)
    net = DenoiserNet(in_features=24, **SMALL[name])
    for m in net.modules():
        if isinstance(m, torch.nn.Conv2d):
            assert torch.count_nonzero(m.bias) == 0
            fan_in = m.in_channels * m.kernel_size[0] * m.kernel_size[1]
            fan_out = m.out_channels * m.kernel_size[0] * m.kernel_size[1]
            assert m.weight.abs().max() <= math.sqrt(6.0 / (fan_in + fan_out)) + 1e-7
    again = DenoiserNet(**net.config)
    again.load_state_dict(net.state_dict())
    assert again.config == net.config
    assert again.param_count() == net.param_count()
    assert net.description().startswith(name.split("-")[0])


def test_checkpoint_roundtrip(tmp_path):
    torch.manual_seed(4)
    models = {
        "diffuse": DenoiserNet(in_features=24, **SMALL["separate"]),
        "specular": DenoiserNet(in_features=24, **SMALL["kpcn"]),
    }
    path = tmp_path / "ck.pt"
    save_checkpoint(path, models, step=12)
    loaded, raw = load_checkpoint(path)
    assert raw["variant"] == "nocov" and raw["step"] == 12
    color, feats = _inputs(1, 24, 9, 11)
    with torch.no_grad():
        for c in models:
            assert torch.equal(loaded[c](color, feats), models[c].eval()(color, feats))
    with pytest.raises(ValueError):
        save_checkpoint(path, {"diffuse": models["diffuse"]})


def test_feature_lists_and_nocov_selection():
    assert len(FEATURES_FULL) == 28 and len(FEATURES_NOCOV) == 24
    assert [FEATURES_FULL[i] for i in NOCOV_INDICES] == list(FEATURES_NOCOV)
    assert not any("covariance" in n for n in FEATURES_NOCOV)
    full = torch.arange(2 * 28 * 2 * 3, dtype=torch.float32).reshape(2, 28, 2, 3)
    sel = select_nocov(full)
    assert sel.shape == (2, 24, 2, 3)
    assert torch.equal(sel[:, 7], full[:, 8])  # normalVariance follows depth
    assert select_nocov(full[0].numpy()).shape == (24, 2, 3)


def test_symlog_compresses_inputs_and_the_head_starts_near_uniform():
    from mcdenoise_train.model import symlog

    x = torch.tensor([-1e5, -1.0, 0.0, 1.0, 1e5])
    assert torch.allclose(symlog(x), torch.sign(x) * torch.log1p(x.abs()))
    torch.manual_seed(0)
    net = DenoiserNet(arch="separate", in_features=28, width=8, blocks=1, predictor_width=8, predictor_depth=2)
    color, features = torch.rand(1, 10, 24, 24) * 1e4, torch.rand(1, 28, 24, 24) * 1e4
    logits = net(color, features)
    # Huge inputs still give a spread of logits far from saturating the softmax.
    assert logits.abs().max() < 5.0
    assert DenoiserNet(arch="separate", in_features=28, input_transform="none").config["input_transform"] == "none"
