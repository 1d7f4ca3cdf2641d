"""mcdenoise_train.stages: the cut of a contract-v2 network into the engine's three stages."""

import hashlib
import shutil
from pathlib import Path

import onnx
import pytest

from mcdenoise_train import stages

ROOT = Path(__file__).resolve().parents[2]


def _meta(path):
    return {p.key: p.value for p in onnx.load(str(path), load_external_data=False).metadata_props}


@pytest.mark.parametrize("variant", ["full", "nocov", "beauty"])
def test_the_shipped_stages_are_cut_from_the_shipped_network(variant):
    # The engine refuses stage files cut from another model.onnx: a network exported again
    # without its stages would stop the daemon loading. Cut again with
    # `python -m mcdenoise_train.stages models/<variant>` (export_ms writes them).
    d = ROOT / "models" / variant
    sha = hashlib.sha256((d / "model.onnx").read_bytes()).hexdigest()
    paths = {s: d / f"{s}.onnx" for s in stages.STAGES}
    for stage, path in paths.items():
        meta = _meta(path)
        assert meta["mcdenoise.stage"] == stage and meta["mcdenoise.stage_of"] == sha, path
        assert meta["mcdenoise.variant"] == variant
    assert stages.check(d / "model.onnx", paths) == 0.0
    # Their weights are model.onnx's own bytes (external data), not a second copy.
    assert sum(p.stat().st_size for p in paths.values()) < 64_000
    middle = onnx.load(str(paths["middle"]), load_external_data=False)
    assert {e.value for t in middle.graph.initializer for e in t.external_data if e.key == "location"} == {"model.onnx"}


def test_a_cut_gives_the_whole_graphs_outputs_with_the_boundary_renamed(tmp_path):
    src = ROOT / "tests/fixtures/models/tiny-v2-gain/full/model.onnx"
    shutil.copy(src, tmp_path / "model.onnx")
    paths = stages.write_stages(tmp_path / "model.onnx")
    assert sorted(p.name for p in paths.values()) == ["back.onnx", "front.onnx", "middle.onnx"]
    io = {s: ([i.name for i in onnx.load(str(p)).graph.input], [o.name for o in onnx.load(str(p)).graph.output])
          for s, p in paths.items()}
    assert io["front"] == (["diffuse", "specular", "features"], ["level0", "pooled"])
    assert io["middle"][0] == ["pooled"] and io["middle"][1][0] == "decoder1"
    assert sorted(io["middle"][1][1:]) == ["blend_1", "gain_1", "kernel_1", "kernel_2"]
    assert io["back"] == (["decoder1", "level0"], ["kernel_0", "blend_0", "gain_0"])
    assert stages.check(tmp_path / "model.onnx", paths, h=36, w=52) == 0.0


def test_a_shape_without_the_cut_gets_no_stages_and_loses_stale_ones(tmp_path):
    src = ROOT / "tests/fixtures/models/tiny-v2/full/model.onnx"
    m = onnx.load(str(src))
    # Decoder level 0 without the concatenation of the level-0 features (as --lean0 is).
    for n in m.graph.node:
        if n.op_type == "Concat" and any(i == stages.boundary(onnx.load(str(src)))["level0"] for i in n.input):
            n.op_type = "Sum"
    onnx.save(m, str(tmp_path / "model.onnx"))
    (tmp_path / "front.onnx").write_bytes(b"stale")
    assert stages.write_stages(tmp_path / "model.onnx") is None
    assert not (tmp_path / "front.onnx").exists()
    with pytest.raises(SystemExit, match="no stages"):
        stages.main([str(tmp_path)])
