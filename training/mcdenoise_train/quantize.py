"""Static int8 quantisation of a contract-v2 model for ONNX Runtime's CPU execution.

    python -m mcdenoise_train.quantize --model models/full/model.onnx --data data \
        --out models-int8/full/model.onnx

The result is a QDQ model (QuantizeLinear/DequantizeLinear around each convolution, which
ONNX Runtime fuses into int8 convolutions: u8 activations, s8 per-channel weights, the form
the VNNI instructions take; `--ops all` quantises the other operators too, pooling,
resizing, concatenations and adds, so that int8 tensors flow between convolutions instead
of being dequantised and quantised again around each). Activation ranges are calibrated on
training frames put through the engine's preprocessing (`preprocess.py`, the same code the
trainer uses), never on validation or test frames. The per-level kernel and blend heads
stay in float: their logits go through a softmax, where a quantisation step is an error in
every tap.

`--frames-from EXR...` calibrates on the given noisy frames when `--data` has no training
split (or is not given): `make bench` falls back to the repository's fixtures, for a model
whose speed alone is measured. The model's `mcdenoise.calibration` metadata says which.

The contract metadata is copied, so the engine loads the file like the float one; whether
it is kept is decided by measurement (`evaluate.py` on the validation split, docs/training.md).
"""

from __future__ import annotations

import argparse
import os
import random
import sys
import tempfile
from pathlib import Path

import numpy as np
import onnx
import torch

from .contract import META_INPUT_COMPRESSION
from .data import manifest_frames
from .exr import read_exr
from .model import symlog
from .preprocess import preprocess, raw_from_channels


def calibration_frames(data: str | os.PathLike | None, frames_from: list[str] | None = None) -> tuple[list[str], str]:
    """The noisy frames that calibrate the ranges, and where they come from: the training
    split of `data` when it has one, else the files `frames_from`."""
    if data is not None and (Path(data) / "manifest.jsonl").exists():
        paths = [r["noisy"] for r in manifest_frames(data) if r.get("split", "train") == "train"]
        if paths:
            return paths, f"training frames of {Path(data).resolve().name}"
    if frames_from:
        return list(frames_from), "frames " + ", ".join(Path(f).name for f in frames_from)
    raise SystemExit(f"{data}: no training frames in a manifest.jsonl there, and no --frames-from")


def calibration_inputs(paths: list[str], variant: str, frames: int, crop: int, seed: int = 0):
    """Network inputs of `frames` random crops of the noisy frames `paths`."""
    rng = random.Random(seed)
    out = []
    for path in rng.sample(paths, min(frames, len(paths))):
        raw, dmax, cmax = raw_from_channels(read_exr(path))
        _, h, w = raw.shape
        c = min(crop, h, w) // 16 * 16
        y, x = rng.randrange(h - c + 1), rng.randrange(w - c + 1)
        t = torch.from_numpy(raw[:, y:y + c, x:x + c][None].copy())
        inp = preprocess(t, torch.tensor([dmax]), torch.tensor([cmax]), variant)
        out.append({k: inp[k].numpy().astype(np.float32) for k in ("diffuse", "specular", "features")})
    return out


def head_nodes(model: onnx.ModelProto) -> list[str]:
    """The convolutions that produce a graph output (the kernel and blend heads)."""
    outputs = {o.name for o in model.graph.output}
    return [n.name for n in model.graph.node if n.op_type == "Conv" and set(n.output) & outputs]


def first_nodes(model: onnx.ModelProto) -> list[str]:
    """The first convolution on each path from a graph input (they see the inputs' full
    dynamic range)."""
    produced_by = {o: n for n in model.graph.node for o in n.output}
    inputs = {i.name for i in model.graph.input}

    def from_input(name: str, depth: int = 0) -> bool:
        if name in inputs:
            return True
        n = produced_by.get(name)
        return n is not None and n.op_type != "Conv" and depth < 16 and any(from_input(i, depth + 1) for i in n.input)

    return [n.name for n in model.graph.node if n.op_type == "Conv" and from_input(n.input[0])]


# What `--ops` quantises: the convolutions alone, or every operator ONNX Runtime has an
# int8 form of (None: the quantiser's whole list).
OPS = {"conv": ["Conv"], "all": None}


def quantize(model_path: str | os.PathLike, data: str | os.PathLike | None, out: str | os.PathLike,
             frames: int = 32, crop: int = 128, keep_first: bool = False, method: str = "minmax",
             ops: str = "conv", frames_from: list[str] | None = None) -> Path:
    from onnxruntime.quantization import (CalibrationDataReader, CalibrationMethod, QuantFormat, QuantType,
                                          quantize_static)
    from onnxruntime.quantization.shape_inference import quant_pre_process

    model = onnx.load(str(model_path))
    meta = {p.key: p.value for p in model.metadata_props}
    variant = "nocov" if meta.get("mcdenoise.variant") == "nocov" else "full"
    # Node names are needed to exclude the heads.
    for i, n in enumerate(model.graph.node):
        if not n.name:
            n.name = f"{n.op_type}_{i}"
    paths, source = calibration_frames(data, frames_from)
    print(f"calibrating on {source}", file=sys.stderr)
    batches = calibration_inputs(paths, variant, frames, crop)
    if meta.get(META_INPUT_COMPRESSION, "graph") == "engine":
        # The graph takes its inputs compressed (the engine applies symlog before it).
        batches = [{k: symlog(torch.from_numpy(v)).numpy() for k, v in b.items()} for b in batches]

    class Reader(CalibrationDataReader):
        def __init__(self):
            self.it = iter(batches)

        def get_next(self):
            return next(self.it, None)

    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        named = Path(tmp) / "named.onnx"
        prepared = Path(tmp) / "prepared.onnx"
        onnx.save(model, str(named))
        quant_pre_process(str(named), str(prepared), skip_symbolic_shape=True)
        quantize_static(str(prepared), str(out), Reader(), quant_format=QuantFormat.QDQ,
                        activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8, per_channel=True,
                        nodes_to_exclude=head_nodes(model) + (first_nodes(model) if keep_first else []),
                        op_types_to_quantize=OPS[ops],
                        calibrate_method={"minmax": CalibrationMethod.MinMax,
                                          "percentile": CalibrationMethod.Percentile,
                                          "entropy": CalibrationMethod.Entropy}[method],
                        extra_options={"ActivationSymmetric": False, "WeightSymmetric": True})
    q = onnx.load(str(out))
    del q.metadata_props[:]
    for k, v in meta.items():
        q.metadata_props.add(key=k, value=v)
    what = "convolutions" if ops == "conv" else "all operators"
    q.metadata_props.add(key="mcdenoise.precision", value=f"int8 (QDQ {what}, per-channel weights; heads in float)")
    q.metadata_props.add(key="mcdenoise.calibration", value=source)
    onnx.save(q, str(out))
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m mcdenoise_train.quantize", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--model", required=True, help="a contract-v2 model.onnx")
    p.add_argument("--data", help="data set whose training frames calibrate the ranges")
    p.add_argument("--frames-from", nargs="+", metavar="EXR",
                   help="noisy frames that calibrate the ranges when --data has no training frames (or is not given)")
    p.add_argument("--out", required=True)
    p.add_argument("--frames", type=int, default=32)
    p.add_argument("--crop", type=int, default=128)
    p.add_argument("--keep-first", action="store_true", help="keep the first convolution after each input in float")
    p.add_argument("--calibration", choices=("minmax", "percentile", "entropy"), default="minmax")
    p.add_argument("--ops", choices=tuple(OPS), default="conv", help="quantise the convolutions alone or every operator")
    a = p.parse_args(argv)
    path = quantize(a.model, a.data, a.out, a.frames, a.crop, a.keep_first, a.calibration, a.ops, a.frames_from)
    print(f"{path}: {path.stat().st_size} bytes", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
