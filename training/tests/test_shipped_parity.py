"""The shipped models run in the engine as their torch networks do.

For the shipped variants and their torch networks (`full` and `nocov` from
training/checkpoints/msnet.pt, `beauty` from beauty.pt; `lin2020` rebuilt from its own ONNX
files, which carry its configuration and weights, `export.networks_from_onnx`, and which
that network exports again to the same graph and weights), on a committed fixture frame:
`mcdenoise preprocess` gives the networks' inputs, the torch network and the training
side's reconstruction give the expected output, and `mcdenoise run --models models` (tiles
smaller than the frame) must write the same R, G, B and `diffuse.*` / `specular.*` to the
tolerance of test_parity_engine.py (five times it for the paper-width `lin2020`, whose
float32 sums are longer). A shipped file exported from other weights than its checkpoint's,
or an engine that runs a shipped network differently, fails here; the random networks of
test_parity_engine.py check the contracts themselves.
"""

from pathlib import Path

import numpy as np
import onnx
import pytest
import torch
from onnx import numpy_helper

from mcdenoise_train.checkpoint import load_msnet
from mcdenoise_train.contract import COMPONENTS
from mcdenoise_train.export import export_onnx, networks_from_onnx, read_metadata
from mcdenoise_train.model import paper_config
from test_parity_engine import _compare_output, engine, preprocess, require_engine, torch_v1_output, torch_v2_output

ROOT = Path(__file__).resolve().parents[2]
MODELS = ROOT / "models"
CHECKPOINTS = ROOT / "training" / "checkpoints"
FRAME = ROOT / "tests" / "fixtures" / "frames" / "caustic-spp8.exr"  # 96 x 64
H, W = 64, 96
TILE = 48


def test_lin2020_is_the_papers_network_at_its_width(tmp_path):
    nets = networks_from_onnx(MODELS / "lin2020")
    paper = paper_config()
    for c in COMPONENTS:
        config = nets[c].config
        assert {k: config[k] for k in paper} == paper, (c, config)
        head = [m for m in nets[c].modules() if isinstance(m, torch.nn.Conv2d)][-1]
        assert head.out_channels == 21 * 21 and head.in_channels == 128, head
        meta = read_metadata(MODELS / "lin2020" / f"{c}.onnx")
        assert meta["mcdenoise.variant"] == "lin2020" and meta["mcdenoise.kernel_size"] == "21"
        assert int(meta["mcdenoise.flops_per_pixel"]) == nets[c].flops_per_pixel()
        # The rebuilt network is the shipped one: it exports to the same graph and weights.
        export_onnx(nets[c], tmp_path / f"{c}.onnx", c, "full", name="lin2020", verify=False, half_weights=True)
        a, b = onnx.load(str(MODELS / "lin2020" / f"{c}.onnx")), onnx.load(str(tmp_path / f"{c}.onnx"))
        assert [n.SerializeToString() for n in a.graph.node] == [n.SerializeToString() for n in b.graph.node]
        wa = {i.name: numpy_helper.to_array(i) for i in a.graph.initializer}
        wb = {i.name: numpy_helper.to_array(i) for i in b.graph.initializer}
        assert wa.keys() == wb.keys() and all(np.array_equal(wa[k], wb[k]) for k in wa)
        assert read_metadata(tmp_path / f"{c}.onnx") == meta
    narrow = read_metadata(MODELS / "lin2020-narrow" / "diffuse.onnx")
    assert narrow["mcdenoise.variant"] == "lin2020-narrow" and "width 24" in narrow["mcdenoise.architecture"]


def test_shipped_lin2020_runs_as_its_checkpoint(tmp_path):
    exe = require_engine()
    nets = networks_from_onnx(MODELS / "lin2020")
    # lin2020 takes the `full` inputs; its firefly rule is not the `full` network's, so the
    # handling is off on both sides.
    arrs = preprocess(exe, FRAME, tmp_path / "in.npz", "--variant", "full", "--fireflies", "off")
    expect = torch_v1_output(nets, arrs)
    assert expect[""].shape == (3, H, W)
    out = tmp_path / "out.exr"
    engine(exe, "run", FRAME, "-o", out, "--models", MODELS, "--variant", "lin2020",
           "--fireflies", "off", "--layers", "diffuse,specular", "--tile", TILE)
    # Twenty float32 convolutions 64 and 128 wide, in ONNX Runtime and in torch: 1.2e-4 at
    # worst, measured, on the whole frame as on the tiles.
    _compare_output(out, expect, (H, W), float_tol=5e-4)


@pytest.mark.parametrize("variant,checkpoint", [("full", "msnet.pt"), ("nocov", "msnet.pt"), ("beauty", "beauty.pt")])
def test_shipped_multiscale_variants_run_as_their_checkpoints(tmp_path, variant, checkpoint):
    from mcdenoise_train.export_ms import nocov_from_full

    exe = require_engine()
    net = load_msnet(CHECKPOINTS / checkpoint)[0]
    if variant in ("nocov", "beauty"):
        # Both are served with the `nocov` inputs (beauty.pt is trained on full features too).
        net = nocov_from_full(net).eval()
    frame = FRAME
    if variant == "nocov":
        # The frame without its covariance pair: the engine picks `nocov` from the channels.
        from mcdenoise_train.exr import read_exr, write_exr

        channels = {k: v for k, v in read_exr(FRAME).items() if not k.startswith("covariance")}
        frame = tmp_path / "nocov.exr"
        write_exr(frame, channels)
    arrs = preprocess(exe, frame, tmp_path / "in.npz", "--variant", variant)
    expect, _ = torch_v2_output(net, arrs, H, W)
    out = tmp_path / "out.exr"
    engine(exe, "run", frame, "-o", out, "--models", MODELS, "--variant", variant, "--reconstruction", "engine",
           "--layers", "diffuse,specular", "--tile-v2", 32)
    _compare_output(out, expect, (H, W), float_tol=1e-4)
