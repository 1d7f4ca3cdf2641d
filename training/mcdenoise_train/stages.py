"""A contract-v2 network cut into the three stages the engine runs it in on the CPU
(docs/model-contract.md, "Stages"): `front.onnx`, `middle.onnx` and `back.onnx` beside
`model.onnx`.

    python -m mcdenoise_train.stages models/full models/nocov models/beauty

- `front`: `diffuse`, `specular`, `features` → `level0` (the level-0 features, the
  extractors' concatenation after its ReLU) and `pooled` (their 2×2 max-pool);
- `middle`: `pooled` → `decoder1` (decoder level 1's output) and the logits of levels
  1 … L−1 (`kernel_<l>`, `blend_<l>`, `gain_<l>`);
- `back`: `decoder1` and `level0` → the logits of level 0.

The full-resolution stages reach a few pixels, the middle one runs at half resolution, so
the engine runs `front` and `back` per core with a small margin and `middle` once over the
frame, where the whole graph needs the receptive radius around every core (the measurement:
benches/staged_cost.py). The cut is found in the graph, not by name: the first max-pool's
input and output, and the input of the upsampling concatenated with that input. Each stage
carries `model.onnx`'s metadata, `mcdenoise.stage` (its name) and `mcdenoise.stage_of`
(the SHA-256 of the `model.onnx` it was cut from: the engine uses the stages only beside
that file). The stages hold no weights of their own: each initializer of 64 bytes or more
is ONNX external data pointing at the same bytes inside `model.onnx` (its offset and
length there), so the three files add some 30 KB beside it rather than a second copy of
the network. The three are checked against the whole graph on a small random frame.
"""

from __future__ import annotations

import argparse
import hashlib
import sys
import tempfile
from pathlib import Path

import numpy as np
import onnx
import onnx.utils

STAGES = ("front", "middle", "back")
# The boundary tensors' names in the stage files.
LEVEL0, POOLED, DECODER1 = "level0", "pooled", "decoder1"


def boundary(model: onnx.ModelProto) -> dict[str, str]:
    """The graph's names of the level-0 features, their max-pool and decoder level 1's output."""
    nodes = list(model.graph.node)
    pool = next((n for n in nodes if n.op_type == "MaxPool"), None)
    if pool is None:
        raise ValueError("no max-pool: not a multi-scale U-Net (msnet)")
    level0 = pool.input[0]
    concat = next((n for n in nodes if n.op_type == "Concat" and level0 in n.input), None)
    if concat is None:
        raise ValueError(f"the level-0 features `{level0}` are not concatenated into decoder level 0 "
                         "(a shape without it, such as --lean0, has no such cut)")
    producers = {o: n for n in nodes for o in n.output}
    ups = [producers.get(i) for i in concat.input if i != level0]
    if len(ups) != 1 or ups[0] is None or ups[0].op_type != "Resize":
        raise ValueError("decoder level 0 does not concatenate one upsampled tensor with the level-0 features")
    return {LEVEL0: level0, POOLED: pool.output[0], DECODER1: ups[0].input[0]}


def _rename(model: onnx.ModelProto, names: dict[str, str]) -> None:
    """Renames tensors `old → new` throughout `model`'s graph."""
    g = model.graph
    for n in g.node:
        n.input[:] = [names.get(i, i) for i in n.input]
        n.output[:] = [names.get(o, o) for o in n.output]
    for v in [*g.input, *g.output, *g.value_info]:
        v.name = names.get(v.name, v.name)


def cut(model_path: Path, out_dir: Path) -> dict[str, Path]:
    """Writes the three stages of `model_path` into `out_dir`; their paths."""
    model = onnx.load(str(model_path))
    b = boundary(model)
    outputs = [o.name for o in model.graph.output]
    level0_logits = [o for o in outputs if o.endswith("_0")]
    inputs = [i.name for i in model.graph.input]
    plan = {
        "front": (inputs, [b[LEVEL0], b[POOLED]]),
        "middle": ([b[POOLED]], [b[DECODER1]] + [o for o in outputs if o not in level0_logits]),
        "back": ([b[DECODER1], b[LEVEL0]], level0_logits),
    }
    blob = model_path.read_bytes()
    sha = hashlib.sha256(blob).hexdigest()
    meta = {p.key: p.value for p in model.metadata_props}
    paths = {}
    with tempfile.TemporaryDirectory() as tmp:
        for stage, (ins, outs) in plan.items():
            raw = Path(tmp) / f"{stage}.onnx"
            onnx.utils.extract_model(str(model_path), str(raw), ins, outs)
            m = onnx.load(str(raw))
            _rename(m, {v: k for k, v in b.items()})
            del m.metadata_props[:]
            for k, v in {**meta, "mcdenoise.stage": stage, "mcdenoise.stage_of": sha}.items():
                m.metadata_props.add(key=k, value=v)
            m.graph.name = f"{model.graph.name} {stage}"
            _point_into(m, blob)
            paths[stage] = out_dir / f"{stage}.onnx"
            onnx.save(m, str(paths[stage]))
            onnx.checker.check_model(str(paths[stage]))
    return paths


def _point_into(model: onnx.ModelProto, blob: bytes, source: str = "model.onnx", least: int = 64) -> None:
    """Replaces the raw data of `model`'s initializers of at least `least` bytes by references
    to the same bytes in `blob`, the file `source` beside it (ONNX external data)."""
    for t in model.graph.initializer:
        if not t.HasField("raw_data") or len(t.raw_data) < least:
            continue
        offset = blob.find(t.raw_data)
        if offset < 0:
            raise ValueError(f"initializer `{t.name}` is not in {source}")
        length = len(t.raw_data)
        t.ClearField("raw_data")
        t.data_location = onnx.TensorProto.EXTERNAL
        for key, value in (("location", source), ("offset", str(offset)), ("length", str(length))):
            entry = t.external_data.add()
            entry.key, entry.value = key, value


def check(model_path: Path, paths: dict[str, Path], h: int = 64, w: int = 96) -> float:
    """Largest difference between the whole graph's outputs and the stages' on an `h`×`w` frame."""
    import onnxruntime as ort

    def session(p):
        return ort.InferenceSession(str(p), providers=["CPUExecutionProvider"])

    whole = session(model_path)
    rng = np.random.default_rng(0)
    feeds = {i.name: rng.standard_normal((1, i.shape[1], h, w)).astype(np.float32) for i in whole.get_inputs()}
    ref = dict(zip([o.name for o in whole.get_outputs()], whole.run(None, feeds)))
    level0, pooled = session(paths["front"]).run([LEVEL0, POOLED], feeds)
    middle = session(paths["middle"])
    got = dict(zip([o.name for o in middle.get_outputs()], middle.run(None, {POOLED: pooled})))
    back = session(paths["back"])
    got.update(zip([o.name for o in back.get_outputs()],
                   back.run(None, {DECODER1: got[DECODER1], LEVEL0: level0})))
    return max(float(np.abs(ref[k] - got[k]).max()) for k in ref)


def write_stages(model_path: Path) -> dict[str, Path] | None:
    """The stages of `model_path` beside it, checked; for a shape without the cut, none (and
    any stage files there removed, so that none is left from an earlier model)."""
    model_path = Path(model_path)
    try:
        boundary(onnx.load(str(model_path), load_external_data=False))
    except ValueError as e:
        for stage in STAGES:
            (model_path.parent / f"{stage}.onnx").unlink(missing_ok=True)
        print(f"{model_path}: no stages ({e})", file=sys.stderr)
        return None
    paths = cut(model_path, model_path.parent)
    diff = check(model_path, paths)
    if diff != 0.0:
        raise ValueError(f"{model_path}: the stages differ from the whole graph by {diff}")
    return paths


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m mcdenoise_train.stages", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("variants", nargs="+", help="variant directories holding model.onnx")
    a = p.parse_args(argv)
    for d in map(Path, a.variants):
        model = d / "model.onnx"
        if not model.exists():
            raise SystemExit(f"{model}: no such file")
        try:
            paths = write_stages(model)
        except ValueError as e:
            raise SystemExit(str(e)) from None
        if paths is None:
            raise SystemExit(f"{model}: this shape has no stages")
        sizes = ", ".join(f"{s} {paths[s].stat().st_size} bytes" for s in STAGES)
        print(f"{d}: {sizes}; outputs equal to model.onnx's", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
