"""ONNX export: graph shape, metadata, onnxruntime agreement, CLI, committed fixtures."""

import json
import re
import shlex
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import pytest
import torch

from mcdenoise_train.checkpoint import save_checkpoint
from mcdenoise_train.contract import FEATURES_FULL, FEATURES_NOCOV
from mcdenoise_train.export import export_onnx, main, random_models, read_metadata
from mcdenoise_train.model import DenoiserNet

REPO = Path(__file__).resolve().parents[2]
FIXTURES = REPO / "tests" / "fixtures" / "models"
SMALL = {
    "separate": dict(arch="separate", width=4, blocks=2, predictor_width=8, predictor_depth=3),
    "joint": dict(arch="joint", width=4, blocks=1, predictor_width=8, predictor_depth=2),
    "kpcn": dict(arch="kpcn", width=6, layers=3, conv_kernel=5),
}


def run_ort(path, color, feats):
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    return sess.run(["kernel"], {"color": color, "features": feats})[0]


def test_feature_names_match_contract_doc():
    doc = (REPO / "docs" / "model-contract.md").read_text()
    block = re.search(r"Feature names, in order \(`full`\):\s*```\n(.*?)```", doc, re.S).group(1)
    names = [n for n in block.replace("\n", "").split(",") if n]
    assert tuple(names) == FEATURES_FULL
    dropped = ["covariance", "covarianceVariance", "gx.covariance", "gy.covariance"]
    assert tuple(n for n in names if n not in dropped) == FEATURES_NOCOV


@pytest.mark.parametrize("arch", sorted(SMALL))
@pytest.mark.parametrize("variant", ["full", "nocov"])
def test_export_graph_metadata_and_ort(tmp_path, arch, variant):
    torch.manual_seed(5)
    c = 28 if variant == "full" else 24
    net = DenoiserNet(in_features=c, **SMALL[arch]).eval()
    path = tmp_path / variant / "specular.onnx"
    export_onnx(net, path, "specular", variant)

    proto = onnx.load(str(path))
    onnx.checker.check_model(proto, full_check=True)
    assert max(o.version for o in proto.opset_import if o.domain in ("", "ai.onnx")) >= 17
    g = proto.graph
    from mcdenoise_train.export import ALLOWED_OPS

    ops = {n.op_type for n in g.node}
    assert ops <= ALLOWED_OPS
    assert {"Conv", "Relu", "Sign", "Log"} <= ops  # the network and its symlog input transform
    inits = {i.name for i in g.initializer}
    assert all(i.data_type == onnx.TensorProto.FLOAT for i in g.initializer)

    def sig(v):
        t = v.type.tensor_type
        return v.name, t.elem_type, [d.dim_param or d.dim_value for d in t.shape.dim]

    f32 = onnx.TensorProto.FLOAT
    assert [sig(v) for v in g.input if v.name not in inits] == [
        ("color", f32, ["N", 10, "H", "W"]),
        ("features", f32, ["N", c, "H", "W"]),
    ]
    assert [sig(v) for v in g.output] == [("kernel", f32, ["N", 441, "H", "W"])]

    names = FEATURES_FULL if variant == "full" else FEATURES_NOCOV
    assert read_metadata(path) == {
        "mcdenoise.contract": "1",
        "mcdenoise.component": "specular",
        "mcdenoise.variant": variant,
        "mcdenoise.kernel_size": "21",
        "mcdenoise.features": ",".join(names),
        "mcdenoise.receptive_radius": str(net.receptive_radius()),
        "mcdenoise.flops_per_pixel": str(net.flops_per_pixel()),
        "mcdenoise.architecture": net.description(),
        "mcdenoise.torch_config": json.dumps(net.config, sort_keys=True),
    }

    rng = np.random.default_rng(6)
    for n, h, w in [(1, 5, 3), (3, 31, 22)]:
        color = rng.normal(size=(n, 10, h, w)).astype(np.float32)
        feats = rng.uniform(size=(n, c, h, w)).astype(np.float32)
        with torch.no_grad():
            ref = net(torch.from_numpy(color), torch.from_numpy(feats)).numpy()
        out = run_ort(path, color, feats)
        assert out.shape == (n, 441, h, w)
        assert np.max(np.abs(out - ref)) <= 1e-4 * max(1.0, np.max(np.abs(ref)))


def test_a_pair_is_rebuilt_from_its_onnx_files(tmp_path):
    from mcdenoise_train.export import networks_from_onnx

    torch.manual_seed(4)
    nets = {c: DenoiserNet(in_features=28, **SMALL["separate"]) for c in ("diffuse", "specular")}
    for c, net in nets.items():
        export_onnx(net, tmp_path / "v" / f"{c}.onnx", c, "full", name="v")
    back = networks_from_onnx(tmp_path / "v")
    for c, net in nets.items():
        assert back[c].config == net.config
        for k, v in net.state_dict().items():
            assert torch.equal(back[c].state_dict()[k], v), (c, k)
    # A file exported before the key existed says what to do.
    m = onnx.load(str(tmp_path / "v" / "specular.onnx"))
    keep = [p for p in m.metadata_props if p.key != "mcdenoise.torch_config"]
    del m.metadata_props[:]
    m.metadata_props.extend(keep)
    onnx.save(m, str(tmp_path / "v" / "specular.onnx"))
    with pytest.raises(ValueError, match="specular.onnx: no mcdenoise.torch_config"):
        networks_from_onnx(tmp_path / "v")


def test_export_rejects_mismatches(tmp_path):
    net = DenoiserNet(in_features=24, **SMALL["kpcn"])
    with pytest.raises(ValueError):
        export_onnx(net, tmp_path / "x.onnx", "diffuse", "full")
    with pytest.raises(ValueError):
        export_onnx(net, tmp_path / "x.onnx", "color", "nocov")


def test_cli_random_writes_model_dir(tmp_path):
    args = ["--random", "--seed", "3", "--width", "4", "--blocks", "1", "--predictor-width", "8",
            "--predictor-depth", "2", "--arch", "separate", "--out", str(tmp_path)]
    assert main(args) == 0
    for v in ("full", "nocov"):
        for c in ("diffuse", "specular"):
            meta = read_metadata(tmp_path / v / f"{c}.onnx")
            assert (meta["mcdenoise.variant"], meta["mcdenoise.component"]) == (v, c)
            assert meta["mcdenoise.receptive_radius"] == "6"  # 1 + 2 + 1 + 1 + 1
    # Same seed and config, same weights as random_models().
    nets = random_models(3, **dict(width=4, blocks=1, predictor_width=8, predictor_depth=2))
    rng = np.random.default_rng(0)
    color = rng.normal(size=(1, 10, 8, 9)).astype(np.float32)
    feats = rng.uniform(size=(1, 24, 8, 9)).astype(np.float32)
    with torch.no_grad():
        ref = nets[("nocov", "specular")](torch.from_numpy(color), torch.from_numpy(feats)).numpy()
    np.testing.assert_allclose(run_ort(tmp_path / "nocov" / "specular.onnx", color, feats), ref, atol=1e-5)


def test_cli_checkpoint(tmp_path):
    torch.manual_seed(9)
    models = {c: DenoiserNet(in_features=28, **SMALL["joint"]) for c in ("diffuse", "specular")}
    save_checkpoint(tmp_path / "full.pt", models)
    assert main(["--checkpoint", str(tmp_path / "full.pt"), "--out", str(tmp_path / "m")]) == 0
    assert not (tmp_path / "m" / "nocov").exists()
    rng = np.random.default_rng(1)
    color = rng.normal(size=(1, 10, 6, 7)).astype(np.float32)
    feats = rng.uniform(size=(1, 28, 6, 7)).astype(np.float32)
    for c, net in models.items():
        with torch.no_grad():
            ref = net.eval()(torch.from_numpy(color), torch.from_numpy(feats)).numpy()
        np.testing.assert_allclose(run_ort(tmp_path / "m" / "full" / f"{c}.onnx", color, feats), ref, atol=1e-5)


def _readme_command():
    text = (FIXTURES / "README.md").read_text()
    line = next(ln for ln in text.splitlines() if "-m mcdenoise_train.export" in ln)
    return shlex.split(line.split("-m mcdenoise_train.export", 1)[1])


def test_tiny_fixtures_are_small_and_reproducible(tmp_path):
    args = _readme_command()
    out = args.index("--out")
    assert args[out + 1] == "../tests/fixtures/models/tiny"
    args[out + 1] = str(tmp_path)
    assert main(args) == 0
    for v in ("full", "nocov"):
        for c in ("diffuse", "specular"):
            committed = FIXTURES / "tiny" / v / f"{c}.onnx"
            assert committed.stat().st_size <= 50_000
            meta = read_metadata(committed)
            assert int(meta["mcdenoise.receptive_radius"]) <= 8
            assert (meta["mcdenoise.variant"], meta["mcdenoise.component"]) == (v, c)
            assert meta == read_metadata(tmp_path / v / f"{c}.onnx")
            a, b = onnx.load(str(committed)), onnx.load(str(tmp_path / v / f"{c}.onnx"))
            wa = {i.name: onnx.numpy_helper.to_array(i) for i in a.graph.initializer}
            wb = {i.name: onnx.numpy_helper.to_array(i) for i in b.graph.initializer}
            assert wa.keys() == wb.keys()
            assert all(np.array_equal(wa[k], wb[k]) for k in wa), f"{committed} differs from its command"
