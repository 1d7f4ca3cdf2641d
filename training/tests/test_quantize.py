"""Static int8 quantisation of a contract-v2 model: calibrated on training frames only, the
heads kept in float, the contract metadata kept, and the engine loads and runs the result
close to the float model."""

import os
import subprocess

import numpy as np
import onnx
import pytest

from mcdenoise_train import quantize
from mcdenoise_train.exr import read_exr

from test_train import BIN, make_dataset, needs_engine

TINY = os.path.join(os.path.dirname(__file__), "..", "..", "tests", "fixtures", "models", "tiny-v2")


def test_calibration_uses_training_frames_only(tmp_path, monkeypatch):
    make_dataset(tmp_path / "data", frames=3, size=48)
    seen = []
    real = quantize.read_exr
    monkeypatch.setattr(quantize, "read_exr", lambda p: seen.append(os.path.basename(p)) or real(p))
    paths, source = quantize.calibration_frames(tmp_path / "data", frames_from=["elsewhere.exr"])
    assert source == "training frames of data", "a data set with training frames wins over --frames-from"
    batches = quantize.calibration_inputs(paths, "full", frames=10, crop=32)
    assert len(batches) == 2 and all(b["diffuse"].shape == (1, 10, 32, 32) for b in batches)
    assert sorted(seen) == ["s0-spp8.exr", "s1-spp8.exr"], "the validation scene s2 is never read"


def test_calibration_falls_back_to_the_frames_given_and_says_so(tmp_path):
    fixtures = ["a-spp8.exr", "b-spp8.exr"]
    assert quantize.calibration_frames(tmp_path / "no-data", fixtures) == (fixtures, "frames a-spp8.exr, b-spp8.exr")
    (tmp_path / "data").mkdir()
    (tmp_path / "data" / "manifest.jsonl").write_text("")
    assert quantize.calibration_frames(tmp_path / "data", fixtures)[0] == fixtures, "a data set without training frames"
    with pytest.raises(SystemExit, match="no training frames"):
        quantize.calibration_frames(tmp_path / "data")


@needs_engine
@pytest.mark.parametrize("models,ops", [("tiny-v2", "conv"), ("tiny-v2-engine", "conv"), ("tiny-v2-engine", "all")])
def test_the_quantized_model_keeps_its_contract_and_runs_in_the_engine(tmp_path, models, ops):
    # tiny-v2 compresses its inputs in the graph, tiny-v2-engine takes them compressed: the
    # calibration must feed each what the engine does.
    make_dataset(tmp_path / "data", frames=3, size=48)
    src = os.path.join(os.path.dirname(TINY), models, "full", "model.onnx")
    out = quantize.quantize(src, tmp_path / "data", tmp_path / "q" / "full" / "model.onnx", frames=2, crop=32, ops=ops)
    q = onnx.load(str(out))
    meta = {p.key: p.value for p in q.metadata_props}
    float_meta = {p.key: p.value for p in onnx.load(src).metadata_props}
    assert {k: meta[k] for k in float_meta} == float_meta and meta["mcdenoise.precision"].startswith("int8")
    assert meta["mcdenoise.calibration"] == "training frames of data"
    nodes = [n.op_type for n in q.graph.node]
    assert "QuantizeLinear" in nodes and "DequantizeLinear" in nodes
    # `all` also quantises what lies between the convolutions (pooling, resizing,
    # concatenations): they take dequantised int8 tensors too.
    produced = {o: n for n in q.graph.node for o in n.output}
    between = {n.op_type for n in q.graph.node if n.op_type in ("MaxPool", "Resize", "Concat")
               and any(i in produced and produced[i].op_type == "DequantizeLinear" for i in n.input)}
    assert bool(between) == (ops == "all"), between
    # The heads' outputs come straight from a float convolution.
    assert all(produced[o.name].op_type == "Conv" for o in q.graph.output if o.name.startswith("kernel"))
    noisy = tmp_path / "data" / "s2-spp8.exr"
    out = {}
    for name, models in (("float", os.path.dirname(os.path.dirname(src))), ("int8", str(tmp_path / "q"))):
        subprocess.run([BIN, "run", str(noisy), "-o", str(tmp_path / f"{name}.exr"), "--models", models,
                        "--variant", "full"], check=True, capture_output=True)
        out[name] = read_exr(tmp_path / f"{name}.exr")["R"]
    assert np.isfinite(out["int8"]).all()
    err = np.abs(out["float"] - out["int8"]).mean()
    assert err <= 0.05 * np.abs(out["float"]).mean() + 1e-6, f"int8 output far from the float model's ({err})"
