"""The contract-v2 network, its reconstruction and its export."""

from __future__ import annotations

import numpy as np
import onnx
import pytest
import torch
import torch.nn.functional as F

from mcdenoise_train.contract import FEATURES_FULL, NOCOV_INDICES
from mcdenoise_train.export_ms import export_onnx, nocov_from_full, read_metadata_v2, verify_onnx
from mcdenoise_train.msnet import MSNet, pad_to_multiple, transplant
from mcdenoise_train.recon_ms import color_pyramid, component_levels, filter_k, reconstruct, reconstruct_component, up2

SMALL = dict(ext_width=4, ext_blocks=1, enc=(6, 6, 8, 8), dec=(6, 6, 8, 8), kernel_size=5, levels=5)


def _inputs(n, h, w, c=28, seed=0):
    g = torch.Generator().manual_seed(seed)
    return (torch.rand(n, 10, h, w, generator=g), torch.rand(n, 10, h, w, generator=g),
            torch.rand(n, c, h, w, generator=g))


def test_output_shapes_and_cost():
    net = MSNet(28, **SMALL)
    out = net(*_inputs(2, 32, 48))
    assert [tuple(o.shape) for o in out] == [
        (2, 50, 32, 48), (2, 50, 16, 24), (2, 50, 8, 12), (2, 50, 4, 6), (2, 50, 2, 3),
        (2, 2, 32, 48), (2, 2, 16, 24), (2, 2, 8, 12), (2, 2, 4, 6)]
    # The production default stays inside the budget of 0.3 MFLOP per pixel, both components.
    assert MSNet(28).flops_per_pixel() < 0.3e6


@pytest.mark.parametrize("y,x", [(64, 64), (65, 70), (79, 77)])
def test_receptive_radius_bounds_the_dependency(y, x):
    torch.manual_seed(1)
    net = MSNet(28, **SMALL).eval()
    h = w = 160
    d, s, f = (t.requires_grad_(True) for t in _inputs(1, h, w, seed=y * x))
    rec = reconstruct(net(d, s, f), net.levels, d, s, torch.rand(1, 3, h, w), specular_pyramid=net.specular_pyramid)
    rec.total[0, :, y, x].sum().backward()
    g = d.grad.abs().sum((0, 1)) + s.grad.abs().sum((0, 1)) + f.grad.abs().sum((0, 1))
    ys, xs = torch.nonzero(g > 0, as_tuple=True)
    reach = max((ys - y).abs().max().item(), (xs - x).abs().max().item())
    assert 0 < reach <= net.receptive_radius()


def test_filter_matches_a_direct_loop():
    g = torch.Generator().manual_seed(3)
    logits = torch.randn(1, 9, 5, 6, generator=g)
    color = torch.rand(1, 3, 5, 6, generator=g)
    out = filter_k(logits, color)
    w = torch.softmax(logits, 1)
    for y in range(5):
        for x in range(6):
            acc = torch.zeros(3)
            for t in range(9):
                dy, dx = divmod(t, 3)
                acc += w[0, t, y, x] * color[0, :, min(max(y + dy - 1, 0), 4), min(max(x + dx - 1, 0), 5)]
            assert torch.allclose(out[0, :, y, x], acc, atol=1e-6)


def test_uniform_kernels_and_zero_blend_keep_a_constant_image():
    color = torch.full((1, 3, 16, 16), 0.7)
    kernels = [torch.zeros(1, 25, 16 >> l, 16 >> l) for l in range(3)]
    blends = [torch.zeros(1, 1, 16 >> l, 16 >> l) for l in range(2)]
    assert torch.allclose(reconstruct_component(kernels, blends, color), color, atol=1e-6)


def test_full_blend_takes_the_coarse_level_low_frequencies():
    """With blend -> 1 and identity kernels, o_0 = c - up(avg(c)) + up(avg(c)) = c."""
    g = torch.Generator().manual_seed(4)
    color = torch.rand(1, 3, 16, 16, generator=g)
    ident = torch.full((1, 9, 1, 1), -30.0)
    ident[:, 4] = 30.0
    kernels = [ident.expand(1, 9, 16 >> l, 16 >> l) for l in range(3)]
    blends = [torch.full((1, 1, 16 >> l, 16 >> l), 30.0) for l in range(2)]
    assert torch.allclose(reconstruct_component(kernels, blends, color), color, atol=1e-5)
    assert torch.allclose(up2(F.avg_pool2d(color, 2)).mean(), color.mean(), atol=1e-6)


def test_component_levels_are_each_levels_reconstruction():
    # o_{L-1} is the coarsest level filtered, o_l the level l filtered with the coarser
    # result blended in, o_0 the component's output.
    g = torch.Generator().manual_seed(6)
    color = torch.rand(1, 3, 16, 24, generator=g)
    kernels = [torch.randn(1, 9, 16 >> l, 24 >> l, generator=g) for l in range(3)]
    blends = [torch.randn(1, 1, 16 >> l, 24 >> l, generator=g) for l in range(2)]
    outs = component_levels(kernels, blends, color)
    assert [tuple(o.shape[-2:]) for o in outs] == [(16, 24), (8, 12), (4, 6)]
    assert torch.equal(outs[0], reconstruct_component(kernels, blends, color))
    assert torch.allclose(outs[2], filter_k(kernels[2], F.avg_pool2d(color, 4)), atol=1e-6)
    f1 = filter_k(kernels[1], F.avg_pool2d(color, 2))
    want1 = f1 + torch.sigmoid(blends[1]) * (up2(outs[2]) - up2(F.avg_pool2d(f1, 2)))
    assert torch.allclose(outs[1], want1, atol=1e-6)
    rec = reconstruct([torch.cat([k, k], 1) for k in kernels] + [torch.cat([b, b], 1) for b in blends], 3,
                      color, color, torch.ones_like(color), specular_pyramid="log")
    assert len(rec.diffuse_levels) == 2 and torch.equal(rec.diffuse_levels[0], outs[1])


def test_linear_pyramid_averages_the_specular_values():
    # A specular color holds ln(1 + s): the linear pyramid's levels are ln(1 + the means of
    # s), the log pyramid's the means of ln(1 + s), which Jensen puts below them.
    g = torch.Generator().manual_seed(5)
    s = torch.rand(1, 3, 16, 24, generator=g) ** 4 * 50  # spread like a few bright samples
    color = torch.log1p(s)
    lin, log = color_pyramid(color, 4, "linear"), color_pyramid(color, 4, "log")
    assert torch.equal(lin[0], color) and torch.equal(log[0], color)
    for l in range(1, 4):
        want = torch.log1p(F.avg_pool2d(s, 2 ** l))
        assert torch.allclose(lin[l], want, rtol=1e-5, atol=1e-6)
        assert torch.allclose(log[l], F.avg_pool2d(color, 2 ** l), rtol=1e-5, atol=1e-6)
        assert (lin[l] >= log[l] - 1e-6).all() and (lin[l] - log[l]).mean() > 0.1
    with pytest.raises(ValueError, match="pyramid"):
        color_pyramid(color, 2, "geometric")


def test_detail_gains_scale_each_levels_own_detail():
    g = torch.Generator().manual_seed(8)
    color = torch.rand(1, 3, 16, 24, generator=g)
    kernels = [torch.randn(1, 9, 16 >> l, 24 >> l, generator=g) for l in range(3)]
    blends = [torch.randn(1, 1, 16 >> l, 24 >> l, generator=g) for l in range(2)]
    gains = [torch.randn(1, 1, 16 >> l, 24 >> l, generator=g) for l in range(2)]
    outs = component_levels(kernels, blends, color, gains=gains)
    f1 = filter_k(kernels[1], F.avg_pool2d(color, 2))
    m1 = up2(F.avg_pool2d(f1, 2))
    want1 = m1 + torch.sigmoid(gains[1]) * (f1 - m1) + torch.sigmoid(blends[1]) * (up2(outs[2]) - m1)
    assert torch.allclose(outs[1], want1, atol=1e-6)
    # Gains of one keep the reconstruction without them; gains of zero drop the detail.
    ones = [torch.full_like(t, 40.0) for t in gains]
    assert torch.allclose(reconstruct_component(kernels, blends, color, gains=ones),
                          reconstruct_component(kernels, blends, color), atol=1e-6)
    zeros = [torch.full_like(t, -40.0) for t in gains]
    smooth = component_levels(kernels, blends, color, gains=zeros)
    f0 = filter_k(kernels[0], color)
    m0 = up2(F.avg_pool2d(f0, 2))
    assert torch.allclose(smooth[0], m0 + torch.sigmoid(blends[0]) * (up2(smooth[1]) - m0), atol=1e-6)
    with pytest.raises(ValueError, match="detail gains"):
        component_levels(kernels, blends, color, gains=gains[:1])


def test_a_network_gains_detail_heads_near_where_it_was(tmp_path):
    from mcdenoise_train.checkpoint import load_msnet, save_msnet
    from mcdenoise_train.msnet import GAIN_START

    torch.manual_seed(2)
    net = MSNet(28, **SMALL).eval()
    d, s, f = _inputs(1, 32, 48)
    with torch.no_grad():
        before = net(d, s, f)
        net.add_detail_gain()
        after = net(d, s, f)
    assert net.detail_gain and "detail gains" in net.description()
    assert len(after) == len(before) + net.levels - 1
    assert all(torch.equal(a, b) for a, b in zip(before, after))  # kernels and blends unchanged
    assert all(torch.all(t == GAIN_START) for t in after[len(before):])
    assert [tuple(t.shape) for t in after[len(before):]] == [(1, 2, 32 >> l, 48 >> l) for l in range(4)]
    with torch.no_grad():
        a = reconstruct(before, net.levels, d, s, torch.ones(1, 3, 32, 48), specular_pyramid="linear").total
        b = reconstruct(after, net.levels, d, s, torch.ones(1, 3, 32, 48), specular_pyramid="linear").total
    assert 0 < (a - b).abs().max() < 0.05 * a.abs().max()
    assert net.flops_per_pixel() > MSNet(28, **SMALL).flops_per_pixel()
    # The heads and the flag survive a checkpoint; a fresh network with them starts the same way.
    with torch.no_grad():
        net.gain_heads[1].bias.sub_(5.0)
    save_msnet(tmp_path / "g.pt", net)
    back = load_msnet(tmp_path / "g.pt")[0]
    assert back.detail_gain and torch.equal(back.gain_heads[1].bias, net.gain_heads[1].bias)
    fresh = MSNet(28, **SMALL, detail_gain=True)
    assert all(torch.all(h.weight == 0) and torch.all(h.bias == GAIN_START) for h in fresh.gain_heads)


def test_export_with_detail_gains(tmp_path):
    from mcdenoise_train.export_ms import export_recon, verify_recon
    from mcdenoise_train.recon_ms import split_outputs

    torch.manual_seed(3)
    net = MSNet(28, **SMALL, detail_gain=True).eval()
    with torch.no_grad():
        for h in net.gain_heads:
            h.weight.normal_(0, 2.0)
    export_onnx(net, tmp_path / "full" / "model.onnx", "full")
    names = [o.name for o in onnx.load(str(tmp_path / "full" / "model.onnx")).graph.output]
    assert names[-4:] == ["gain_0", "gain_1", "gain_2", "gain_3"]
    assert verify_onnx(tmp_path / "full" / "model.onnx", net) < 1e-4
    export_recon(net, tmp_path / "full" / "model-recon.onnx", "full")
    assert verify_recon(tmp_path / "full" / "model-recon.onnx", net) < 1e-4
    # The gains change the filtered output, so the graph must have applied them.
    with torch.no_grad():
        out = net(*_inputs(1, 32, 48))
        k, b, gains = split_outputs(out, net.levels)
        with_gains = reconstruct_component(k["diffuse"], b["diffuse"], _inputs(1, 32, 48)[0][:, :3], gains=gains["diffuse"])
        without = reconstruct_component(k["diffuse"], b["diffuse"], _inputs(1, 32, 48)[0][:, :3])
    assert (with_gains - without).abs().max() > 1e-3
    with torch.no_grad():
        net.gain_heads[0].bias.add_(3.0)
    with pytest.raises(RuntimeError):
        verify_onnx(tmp_path / "full" / "model.onnx", net)
    nocov = nocov_from_full(net)
    assert nocov.detail_gain and len(nocov.gain_heads) == 4


def test_specular_pyramid_follows_the_network_and_old_checkpoints_read_as_log(tmp_path):
    from mcdenoise_train.checkpoint import load_msnet, save_msnet

    net = MSNet(28, **SMALL).eval()
    assert net.specular_pyramid == "linear" and "linear means" in net.description()
    with pytest.raises(ValueError, match="specular_pyramid"):
        MSNet(28, specular_pyramid="median")
    save_msnet(tmp_path / "new.pt", net)
    assert load_msnet(tmp_path / "new.pt")[0].specular_pyramid == "linear"
    # A checkpoint from before the key existed was trained with the log pyramid.
    ck = torch.load(tmp_path / "new.pt", weights_only=False)
    del ck["config"]["specular_pyramid"]
    torch.save(ck, tmp_path / "old.pt")
    old = load_msnet(tmp_path / "old.pt")[0]
    assert old.specular_pyramid == "log"
    export_onnx(old, tmp_path / "full" / "model.onnx", "full")
    assert read_metadata_v2(tmp_path / "full" / "model.onnx")["mcdenoise.specular_pyramid"] == "log"
    # The reconstruction follows it: the same outputs filter to a brighter specular with
    # the linear pyramid wherever a coarse level is blended in.
    d, s, f = _inputs(1, 32, 48)
    s[:, :3] = torch.log1p(torch.rand(1, 3, 32, 48, generator=torch.Generator().manual_seed(2)) ** 4 * 50)
    with torch.no_grad():
        out = net(d, s, f)
        a = reconstruct(out, net.levels, d, s, torch.ones(1, 3, 32, 48), specular_pyramid="linear")
        b = reconstruct(out, net.levels, d, s, torch.ones(1, 3, 32, 48), specular_pyramid="log")
    assert torch.equal(a.diffuse, b.diffuse)
    assert (a.specular - b.specular).mean() > 0


def test_transplant_into_the_same_shape_copies_the_network():
    torch.manual_seed(3)
    src, dst = MSNet(28, **SMALL).eval(), MSNet(28, **SMALL).eval()
    assert transplant(src, dst) == []
    x = _inputs(1, 32, 32)
    for a, b in zip(src(*x), dst(*x)):
        assert torch.equal(a, b)


@torch.no_grad()
def test_transplant_keeps_the_channels_that_carry_the_network():
    """A source whose residual blocks add nothing and whose decoder levels 0 and 1 use only
    some of their channels (the others' weights zero, not in the first positions) is the
    narrower network exactly: the transplant must find those channels."""
    torch.manual_seed(4)
    src = MSNet(28, **SMALL).eval()
    for ext in (src.color_extractor, src.feature_extractor):
        ext[1].conv2.weight.zero_(), ext[1].conv2.bias.zero_()
    for l, used in ((0, [1, 4, 5]), (1, [0, 2, 3, 5])):
        idle = [c for c in range(SMALL["dec"][l]) if c not in used]
        for conv in (src.decoder[l][0], src.decoder[l][2]):
            conv.weight[idle] = 0
            conv.bias[idle] = 0
    dst = MSNet(28, **{**SMALL, "ext_blocks": 0, "dec": (3, 4, 8, 8)}).eval()
    notes = transplant(src, dst)
    assert notes == ["color_extractor: residual blocks 1 -> 0", "feature_extractor: residual blocks 1 -> 0",
                     "decoder level 1: width 6 -> 4", "decoder level 0: width 6 -> 3"]
    x = _inputs(1, 32, 32, seed=5)
    for a, b in zip(src(*x), dst(*x)):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-5)


def test_transplant_refuses_what_it_cannot_map():
    src = MSNet(28, **SMALL)
    with pytest.raises(ValueError, match="only removes"):
        transplant(src, MSNet(28, **{**SMALL, "dec": (8, 6, 8, 8)}))
    with pytest.raises(ValueError, match="same enc"):
        transplant(src, MSNet(28, **{**SMALL, "enc": (8, 6, 8, 8)}))


def test_lean_level0_costs_what_it_computes_and_reaches_no_further_than_its_radius():
    """MSNet(lean0=True): decoder level 0 as 1x1 convs of level 1 (at its resolution) and of
    the skip, then one 3x3; the same outputs, its cost counted where each conv runs, and its
    receptive radius bounding what an output pixel depends on."""
    torch.manual_seed(6)
    net = MSNet(28, **SMALL, lean0=True).eval()
    pair = MSNet(28, **SMALL).eval()
    assert [tuple(o.shape) for o in net(*_inputs(2, 32, 48))] == [tuple(o.shape) for o in pair(*_inputs(2, 32, 48))]
    d0, d1, w0 = SMALL["dec"][0], SMALL["dec"][1], 2 * SMALL["ext_width"]
    pair0 = (d1 + w0) * d0 * 9 + d0 * d0 * 9
    lean0 = d1 * d0 / 4 + w0 * d0 + d0 * d0 * 9
    assert net.flops_per_pixel() == pair.flops_per_pixel() - 2 * pair0 + 2 * lean0
    assert net.receptive_radius() <= pair.receptive_radius()
    assert "level 0 lean" in net.description()
    h = w = 160
    for y, x in ((64, 64), (79, 77)):
        d, s, f = (t.requires_grad_(True) for t in _inputs(1, h, w, seed=y * x))
        rec = reconstruct(net(d, s, f), net.levels, d, s, torch.rand(1, 3, h, w), specular_pyramid=net.specular_pyramid)
        rec.total[0, :, y, x].sum().backward()
        g = d.grad.abs().sum((0, 1)) + s.grad.abs().sum((0, 1)) + f.grad.abs().sum((0, 1))
        ys, xs = torch.nonzero(g > 0, as_tuple=True)
        assert 0 < max((ys - y).abs().max().item(), (xs - x).abs().max().item()) <= net.receptive_radius()


@torch.no_grad()
def test_transplant_into_a_lean_level0():
    """From the production shape, a lean level 0 starts new and the rest is copied; from a
    lean network, a narrower level 1 keeps the channels its lean level 0 reads."""
    torch.manual_seed(7)
    src = MSNet(28, **SMALL).eval()
    dst = MSNet(28, **{**SMALL, "ext_blocks": 0}, lean0=True).eval()
    notes = transplant(src, dst)
    assert notes[-1] == "decoder level 0: lean, new", notes
    assert torch.equal(dst.decoder[1][0].weight, src.decoder[1][0].weight)
    assert torch.equal(dst.kernel_heads[1].weight, src.kernel_heads[1].weight)
    lean = MSNet(28, **SMALL, lean0=True).eval()
    used = [0, 2, 3, 5]
    idle = [c for c in range(SMALL["dec"][1]) if c not in used]
    for conv in (lean.decoder[1][0], lean.decoder[1][2]):
        conv.weight[idle] = 0
        conv.bias[idle] = 0
    narrow = MSNet(28, **{**SMALL, "dec": (SMALL["dec"][0], 4, *SMALL["dec"][2:])}, lean0=True).eval()
    assert transplant(lean, narrow) == ["decoder level 1: width 6 -> 4"]
    x = _inputs(1, 32, 32, seed=8)
    for a, b in zip(lean(*x), narrow(*x)):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-5)
    with pytest.raises(ValueError, match="lean, the target's is not"):
        transplant(lean, MSNet(28, **SMALL))


def test_lean_level0_exports(tmp_path):
    torch.manual_seed(9)
    net = MSNet(28, **SMALL, lean0=True).eval()
    path = tmp_path / "full" / "model.onnx"
    export_onnx(net, path, "full")
    assert verify_onnx(path, net) < 1e-4
    assert int(read_metadata_v2(path)["mcdenoise.receptive_radius"]) == net.receptive_radius()


def test_pad_to_multiple_replicates_the_edge():
    x = torch.arange(12.0).view(1, 1, 3, 4)
    p = pad_to_multiple(x, 4)
    assert p.shape == (1, 1, 4, 4) and torch.equal(p[0, 0, 3], x[0, 0, 2])


def test_nocov_cut_equals_the_full_network_on_zero_covariance():
    torch.manual_seed(2)
    full = MSNet(28, **SMALL).eval()
    nocov = nocov_from_full(full)
    d, s, f = _inputs(1, 32, 32)
    cov = [i for i in range(28) if i not in NOCOV_INDICES]
    f[:, cov] = 0
    with torch.no_grad():
        a, b = full(d, s, f), nocov(d, s, f[:, list(NOCOV_INDICES)])
    for x, y in zip(a, b):
        assert torch.allclose(x, y, atol=1e-5)


@pytest.mark.parametrize("compression", ["engine", "graph"])
def test_export_round_trip(tmp_path, compression):
    torch.manual_seed(0)
    net = MSNet(28, **SMALL).eval()
    path = tmp_path / "full" / "model.onnx"
    export_onnx(net, path, "full", compression=compression)
    meta = read_metadata_v2(path)
    assert meta["mcdenoise.input_compression"] == compression
    # Only a graph that compresses its own inputs holds the symlog's operators.
    ops = {n.op_type for n in onnx.load(str(path)).graph.node}
    assert ("Log" in ops) == (compression == "graph") and ("Sign" in ops) == (compression == "graph")
    assert net.compress_inputs, "the export must not change the network it was given"
    assert meta["mcdenoise.contract"] == "2" and meta["mcdenoise.levels"] == "5"
    assert meta["mcdenoise.size_multiple"] == "16" and meta["mcdenoise.kernel_size"] == "5"
    assert meta["mcdenoise.features"] == ",".join(FEATURES_FULL)
    assert int(meta["mcdenoise.receptive_radius"]) == net.receptive_radius()
    assert verify_onnx(path, net) < 1e-4
    # A broken network is caught by the verification.
    with torch.no_grad():
        net.kernel_heads[0].bias.add_(1.0)
    with pytest.raises(RuntimeError):
        verify_onnx(path, net)
    assert np.isfinite(float(meta["mcdenoise.flops_per_pixel"]))


def test_export_with_reconstruction_round_trip(tmp_path):
    from mcdenoise_train.export_ms import export_recon, verify_recon

    torch.manual_seed(1)
    net = MSNet(28, **SMALL).eval()
    with torch.no_grad():
        for h in [*net.kernel_heads, *net.blend_heads]:
            h.weight.mul_(20)  # kernels far from uniform: tap order and edges matter
    path = tmp_path / "full" / "model-recon.onnx"
    export_recon(net, path, "full")
    meta = read_metadata_v2(path)
    assert meta["mcdenoise.outputs"] == "filtered" and meta["mcdenoise.input_compression"] == "graph"
    assert verify_recon(path, net) < 1e-4
    # The graph's outputs are recon_ms's reconstruction of the network's kernels.
    import onnxruntime as ort
    from mcdenoise_train.recon_ms import reconstruct_component, split_outputs

    g = torch.Generator().manual_seed(3)
    d, s, f = torch.rand(1, 10, 32, 48, generator=g), torch.rand(1, 10, 32, 48, generator=g), torch.rand(1, 28, 32, 48, generator=g)
    with torch.no_grad():
        k, b, _ = split_outputs(net(d, s, f), net.levels)
        want = reconstruct_component(k["specular"], b["specular"], s[:, :3], pyramid=net.specular_pyramid).numpy()
    got = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"]).run(
        ["specular_filtered"], {"diffuse": d.numpy(), "specular": s.numpy(), "features": f.numpy()})[0]
    assert np.abs(got - want).max() <= 1e-4 * max(1.0, np.abs(want).max())
    with torch.no_grad():
        net.blend_heads[0].bias.add_(3.0)
    with pytest.raises(RuntimeError):
        verify_recon(path, net)


def test_half_precision_export_stays_near_the_float_network(tmp_path):
    from mcdenoise_train.export_ms import FP16_TOLERANCE, export_recon, verify_recon

    torch.manual_seed(1)
    net = MSNet(28, **SMALL).eval()
    with torch.no_grad():
        for h in [*net.kernel_heads, *net.blend_heads]:
            h.weight.mul_(20)
    path = tmp_path / "full" / "model-recon-fp16.onnx"
    export_recon(net, path, "full", half=True)
    meta = read_metadata_v2(path)
    assert (meta["mcdenoise.outputs"], meta["mcdenoise.precision"]) == ("filtered", "fp16")
    proto = onnx.load(str(path))
    halves = [i for i in proto.graph.initializer if i.data_type == onnx.TensorProto.FLOAT16]
    assert len(halves) >= len(list(net.parameters())) // 2  # the weights are stored as half
    assert all(i.type.tensor_type.elem_type == onnx.TensorProto.FLOAT for i in proto.graph.input)
    assert all(o.type.tensor_type.elem_type == onnx.TensorProto.FLOAT for o in proto.graph.output)
    worst = verify_recon(path, net, tolerance=FP16_TOLERANCE)
    assert 0 < worst <= FP16_TOLERANCE  # half, not float: not exact
    # HDR inputs beyond half's range are compressed before the cast: finite outputs.
    import onnxruntime as ort

    d = torch.rand(1, 10, 32, 48) * 1e6
    out = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"]).run(
        None, {"diffuse": d.numpy(), "specular": d.numpy(), "features": torch.rand(1, 28, 32, 48).numpy()})
    assert all(np.isfinite(o).all() for o in out)
    with torch.no_grad():
        net.blend_heads[0].bias.add_(3.0)
    with pytest.raises(RuntimeError):
        verify_recon(path, net, tolerance=FP16_TOLERANCE)


def test_filter_gradient_matches_autograd():
    """The written-out backward of the training path equals autograd's on the plain loop."""
    g = torch.Generator().manual_seed(6)
    logits = torch.randn(2, 25, 7, 9, generator=g, requires_grad=True)
    color = torch.rand(2, 3, 7, 9, generator=g)
    weights = torch.rand(2, 3, 7, 9, generator=g)
    (filter_k(logits, color) * weights).sum().backward()
    fast = logits.grad.clone()
    logits.grad = None
    (filter_k(logits, color.clone().requires_grad_(True)) * weights).sum().backward()
    assert torch.allclose(fast, logits.grad, atol=1e-5)
