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
    batches = quantize.calibration_inputs(tmp_path / "data", "full", frames=10, crop=32)
    assert len(batches) == 2 and all(b["diffuse"].shape == (1, 10, 32, 32) for b in batches)
    assert sorted(seen) == ["s0-spp8.exr", "s1-spp8.exr"], "the validation scene s2 is never read"


@needs_engine
@pytest.mark.parametrize("models", ["tiny-v2", "tiny-v2-engine"])
def test_the_quantized_model_keeps_its_contract_and_runs_in_the_engine(tmp_path, models):
    # tiny-v2 compresses its inputs in the graph, tiny-v2-engine takes them compressed: the
    # calibration must feed each what the engine does.
    make_dataset(tmp_path / "data", frames=3, size=48)
    src = os.path.join(os.path.dirname(TINY), models, "full", "model.onnx")
    out = quantize.quantize(src, tmp_path / "data", tmp_path / "q" / "full" / "model.onnx", frames=2, crop=32)
    q = onnx.load(str(out))
    meta = {p.key: p.value for p in q.metadata_props}
    float_meta = {p.key: p.value for p in onnx.load(src).metadata_props}
    assert {k: meta[k] for k in float_meta} == float_meta and meta["mcdenoise.precision"].startswith("int8")
    ops = [n.op_type for n in q.graph.node]
    assert "QuantizeLinear" in ops and "DequantizeLinear" in ops
    # The heads' outputs come straight from a float convolution.
    produced = {o: n for n in q.graph.node for o in n.output}
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
