"""ONNX export in model contract v2 (docs/model-contract.md, "Model contract v2").

`export_onnx(model, path, variant)` writes one `MSNet` as `<variant>/model.onnx`: inputs
`diffuse`, `specular` `[N,10,H,W]` and `features` `[N,C,H,W]`; outputs `kernel_<l>`
`[N,2k²,H/2^l,W/2^l]` and `blend_<l>` `[N,2,H/2^l,W/2^l]` (and `gain_<l>` `[N,2,H/2^l,W/2^l]`
for a network with detail gains); float32, N/H/W dynamic, opset
17, the `mcdenoise.*` metadata. The file is checked (onnx.checker, op set, shapes, exact
metadata) and run in onnxruntime on a shape other than the traced one; the export fails
unless max |ort - torch| <= 1e-4 * max(1, max |torch|) for every output.

A `nocov` model can be cut from a network trained with the covariance channels zeroed
(`nocov_from_full`): their input weights are dropped, which changes nothing for inputs
without covariance.

    python -m mcdenoise_train.export_ms --random --seed 0 --variants full,nocov --out DIR [--ext-width 8 ...]
    python -m mcdenoise_train.export_ms --checkpoint best.pt --out DIR [--variants full,nocov | beauty]

A `beauty` model (a network trained with `train_ms --beauty`) is cut like a `nocov` one
and named `beauty`: the engine feeds it the beauty in the diffuse slot (docs/model-contract.md).

The inputs' symlog compression is left to the engine (`mcdenoise.input_compression`
`engine`): in the graph it is five elementwise passes over every input tensor, about a
quarter of ONNX Runtime's time for the default network, where the engine's preprocessing
does it while the tensors are in cache. `--compression graph` keeps it in the graph (the
form models had before the key existed, which the engine still runs).

Beside each `model.onnx` the command writes the same network cut into the three stages the
engine runs it in on the CPU (`front.onnx`, `middle.onnx`, `back.onnx`: `mcdenoise_train.stages`),
where the shape has that cut.

`--recon` also writes `<variant>/model-recon.onnx`: the same network with the multi-scale
reconstruction in the graph (`mcdenoise.outputs` `filtered`: outputs `diffuse_filtered` and
`specular_filtered` `[N,3,H,W]`, the filtered preprocessed colors), which the engine runs
where the reconstruction belongs on the device (a GPU) rather than in its own CPU code. It
compresses its inputs itself: the reconstruction needs them uncompressed.

`--recon --fp16` also writes `<variant>/model-recon-fp16.onnx`: the same, with the network
in half precision (`mcdenoise.precision` `fp16`) for GPUs, where it runs on the tensor cores
at half the memory traffic. Its inputs, outputs and reconstruction stay float32: the inputs
are compressed (symlog) in float32 and only then cast, so HDR values beyond half's range
(65504) reach the network, and the kernels' softmax and the filtering run in float32. The
export fails unless it is within 5e-3 × max(1, max |torch|) of the float32 network.
"""

from __future__ import annotations

import argparse
import copy
import io
import os
import warnings
from pathlib import Path

import numpy as np
import onnx
import torch

from .checkpoint import load_msnet
from .contract import (COLOR_CHANNELS, FEATURES_FULL, META_INPUT_COMPRESSION, META_OUTPUTS, META_PRECISION,
                       META_SPECULAR_PYRAMID, NOCOV_INDICES, feature_names, variant_for)
from .export import read_metadata as read_metadata_v2
from .export import write_model
from .model import symlog
from .msnet import MSNet, add_shape_arguments, from_arguments
from .stages import write_stages

CONTRACT = 2
OPSET = 17
COMPRESSIONS = ("engine", "graph")
RECON_FILE = "model-recon.onnx"
RECON_FP16_FILE = "model-recon-fp16.onnx"
# How far the half-precision network's filtered colors may lie from the float32 network's.
FP16_TOLERANCE = 5e-3
FILTERED_OUTPUTS = ("diffuse_filtered", "specular_filtered")
# The reconstruction's operators, beyond the network's (Shape, Gather, Unsqueeze, Concat: the
# slices' dynamic bounds; Clip and Exp: the linear specular pyramid).
RECON_OPS = frozenset({"Softmax", "Pad", "Slice", "Mul", "Add", "Sub", "AveragePool", "Sigmoid", "Resize", "Shape",
                       "Gather", "Unsqueeze", "Concat", "Constant", "Cast", "Split", "ConstantOfShape", "Div",
                       "Reshape", "Transpose", "Clip", "Exp"})
ALLOWED_OPS = frozenset({"Conv", "Relu", "Add", "Concat", "MaxPool", "Resize", "Sign", "Abs", "Log", "Mul", "Constant"})
_TRACE_HW = (32, 48)
_VERIFY_SHAPE = (2, 48, 80)


def output_names(levels: int, detail_gain: bool = False) -> list[str]:
    return ([f"kernel_{l}" for l in range(levels)] + [f"blend_{l}" for l in range(levels - 1)]
            + [f"gain_{l}" for l in range(levels - 1) if detail_gain])


def metadata_for(model: MSNet, variant: str, compression: str = "engine") -> dict[str, str]:
    if compression not in COMPRESSIONS:
        raise ValueError(f"compression {compression!r}: expected one of {COMPRESSIONS}")
    return {
        "mcdenoise.contract": str(CONTRACT),
        "mcdenoise.variant": variant,
        "mcdenoise.features": ",".join(feature_names(variant_for(model.in_features))),
        "mcdenoise.kernel_size": str(model.kernel_size),
        "mcdenoise.levels": str(model.levels),
        "mcdenoise.size_multiple": str(model.size_multiple),
        "mcdenoise.receptive_radius": str(model.receptive_radius()),
        "mcdenoise.flops_per_pixel": str(model.flops_per_pixel()),
        "mcdenoise.architecture": model.description(),
        META_INPUT_COMPRESSION: compression,
        META_SPECULAR_PYRAMID: model.specular_pyramid,
    }


def nocov_from_full(model: MSNet) -> MSNet:
    """The `nocov` network of a `full` one whose covariance inputs were trained as zeros:
    the same weights without the covariance channels' input weights."""
    if model.in_features != len(FEATURES_FULL):
        raise ValueError(f"expected a full (28-feature) network, got {model.in_features} features")
    cfg = dict(model.config)
    cfg.pop("arch")
    cfg["in_features"] = len(NOCOV_INDICES)
    out = MSNet(**cfg)
    state = {k: v.clone() for k, v in model.state_dict().items()}
    key = "feature_extractor.0.weight"
    state[key] = state[key][:, list(NOCOV_INDICES)]
    out.load_state_dict(state)
    return out.eval()


def compress(x: torch.Tensor) -> torch.Tensor:
    """What the engine applies to each input of an `engine`-compression graph."""
    return symlog(x)


def _to_proto(model: MSNet) -> onnx.ModelProto:
    h, w = _TRACE_HW
    args = (torch.zeros(1, COLOR_CHANNELS, h, w), torch.zeros(1, COLOR_CHANNELS, h, w),
            torch.zeros(1, model.in_features, h, w))
    names = output_names(model.levels, model.detail_gain)
    dyn = {0: "N", 2: "H", 3: "W"}
    dynamic = {"diffuse": dyn, "specular": dyn, "features": dyn}
    for name in names:
        l = name.rsplit("_", 1)[1]
        dynamic[name] = {0: "N", 2: f"H{l}", 3: f"W{l}"}
    buf = io.BytesIO()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(model, args, buf, dynamo=False, input_names=["diffuse", "specular", "features"],
                          output_names=names, dynamic_axes=dynamic, opset_version=OPSET, do_constant_folding=True)
    proto = onnx.load_from_string(buf.getvalue())
    from .export import _drop_initializer_identities

    _drop_initializer_identities(proto.graph)
    return proto


class WithReconstruction(torch.nn.Module):
    """`net` and its reconstruction in one graph: the filtered preprocessed color of each
    component (`recon_ms.reconstruct_component` with the plain filter). With `half` the
    network runs in float16 on inputs compressed in float32 and cast; its kernels and blends
    are cast back, so that the reconstruction runs in float32."""

    def __init__(self, net: MSNet, half: bool = False):
        super().__init__()
        self.net = copy.deepcopy(net).half() if half else net
        self.half = half
        if half:
            self.net.compress_inputs = False

    def forward(self, diffuse: torch.Tensor, specular: torch.Tensor, features: torch.Tensor):
        from .recon_ms import filter_plain, reconstruct_component, split_outputs

        if self.half:
            outputs = [o.float() for o in self.net(*(symlog(x).half() for x in (diffuse, specular, features)))]
        else:
            outputs = self.net(diffuse, specular, features)
        k, b, g = split_outputs(outputs, self.net.levels)
        pyramids = {"diffuse": "log", "specular": self.net.specular_pyramid}
        return tuple(reconstruct_component(k[c], b[c], x[:, :3], filter=filter_plain, pyramid=pyramids[c],
                                           gains=g[c] if g else None)
                     for c, x in (("diffuse", diffuse), ("specular", specular)))


def _recon_proto(model: MSNet, half: bool = False) -> onnx.ModelProto:
    h, w = _TRACE_HW
    args = (torch.zeros(1, COLOR_CHANNELS, h, w), torch.zeros(1, COLOR_CHANNELS, h, w),
            torch.zeros(1, model.in_features, h, w))
    dyn = {0: "N", 2: "H", 3: "W"}
    dynamic = {name: dyn for name in ("diffuse", "specular", "features", *FILTERED_OUTPUTS)}
    buf = io.BytesIO()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(WithReconstruction(model, half), args, buf, dynamo=False,
                          input_names=["diffuse", "specular", "features"], output_names=list(FILTERED_OUTPUTS),
                          dynamic_axes=dynamic, opset_version=OPSET, do_constant_folding=True)
    proto = onnx.load_from_string(buf.getvalue())
    from .export import _drop_initializer_identities

    _drop_initializer_identities(proto.graph)
    onnx.checker.check_model(proto, full_check=True)
    ops = {n.op_type for n in proto.graph.node}
    if not ops <= ALLOWED_OPS | RECON_OPS:
        raise RuntimeError(f"exported graph has unexpected ops {sorted(ops - ALLOWED_OPS - RECON_OPS)}")
    return proto


def verify_recon(path: str | os.PathLike, model: MSNet, seed: int = 0, tolerance: float = 1e-4) -> float:
    """max |onnxruntime - torch| of a `model-recon.onnx` (relative to max(1, max |torch|)),
    against the float32 network; fails above `tolerance`."""
    import onnxruntime as ort

    n, h, w = _VERIFY_SHAPE
    g = torch.Generator().manual_seed(seed)
    d = torch.rand(n, COLOR_CHANNELS, h, w, generator=g) * 4
    s = torch.rand(n, COLOR_CHANNELS, h, w, generator=g)
    f = torch.rand(n, model.in_features, h, w, generator=g)
    with torch.no_grad():
        ref = [t.numpy() for t in WithReconstruction(model)(d, s, f)]
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    out = sess.run(list(FILTERED_OUTPUTS), {"diffuse": d.numpy(), "specular": s.numpy(), "features": f.numpy()})
    worst = 0.0
    for name, o, r in zip(FILTERED_OUTPUTS, out, ref):
        diff = float(np.max(np.abs(o - r))) / max(1.0, float(np.max(np.abs(r))))
        if o.shape != r.shape or not diff <= tolerance:
            raise RuntimeError(f"{path}: {name} differs from torch ({o.shape} vs {r.shape}, {diff:g})")
        worst = max(worst, diff)
    return worst


def export_recon(model: MSNet, path: str | os.PathLike, variant: str, verify: bool = True,
                 half: bool = False) -> onnx.ModelProto:
    """Writes `model` with its reconstruction as `path` (`model-recon.onnx`; with `half`, the
    network in float16: `model-recon-fp16.onnx`)."""
    metadata = {**metadata_for(model, variant, "graph"), META_OUTPUTS: "filtered"}
    if half:
        metadata[META_PRECISION] = "fp16"
    net = copy.deepcopy(model).cpu().float().eval()
    net.compress_inputs = True
    proto = _recon_proto(net, half)
    precision = ", network in float16" if half else ""
    write_model(proto, metadata, f"mcdenoise contract v{CONTRACT} {variant}, reconstruction in the graph{precision}", path)
    if verify:
        verify_recon(path, net, tolerance=FP16_TOLERANCE if half else 1e-4)
    return proto


def _check_graph(proto: onnx.ModelProto, model: MSNet) -> None:
    onnx.checker.check_model(proto, full_check=True)
    ops = {n.op_type for n in proto.graph.node}
    if not ops <= ALLOWED_OPS:
        raise RuntimeError(f"exported graph has unexpected ops {sorted(ops - ALLOWED_OPS)}")
    inits = {i.name for i in proto.graph.initializer}
    inputs = [(i.name, i.type.tensor_type.shape.dim[1].dim_value) for i in proto.graph.input if i.name not in inits]
    expect = [("diffuse", COLOR_CHANNELS), ("specular", COLOR_CHANNELS), ("features", model.in_features)]
    if inputs != expect:
        raise RuntimeError(f"graph inputs {inputs}, expected {expect}")
    taps = model.kernel_size ** 2
    outputs = [(o.name, o.type.tensor_type.shape.dim[1].dim_value) for o in proto.graph.output]
    want = [(name, 2 * taps if name.startswith("kernel_") else 2) for name in output_names(model.levels, model.detail_gain)]
    if outputs != want:
        raise RuntimeError(f"graph outputs {outputs}, expected {want}")


def verify_onnx(path: str | os.PathLike, model: MSNet, seed: int = 0) -> float:
    import onnxruntime as ort

    n, h, w = _VERIFY_SHAPE
    g = torch.Generator().manual_seed(seed)
    d = torch.randn(n, COLOR_CHANNELS, h, w, generator=g)
    s = torch.randn(n, COLOR_CHANNELS, h, w, generator=g)
    f = torch.rand(n, model.in_features, h, w, generator=g)
    with torch.no_grad():
        ref = [t.numpy() for t in model(d, s, f)]
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    meta = {p.key: p.value for p in onnx.load(str(path), load_external_data=False).metadata_props}
    if meta.get(META_INPUT_COMPRESSION, "graph") == "engine":
        d, s, f = compress(d), compress(s), compress(f)
    names = output_names(model.levels, model.detail_gain)
    out = sess.run(names, {"diffuse": d.numpy(), "specular": s.numpy(), "features": f.numpy()})
    worst = 0.0
    for name, o, r in zip(names, out, ref, strict=True):
        if o.shape != r.shape:
            raise RuntimeError(f"{path}: {name} is {o.shape} in onnxruntime, {r.shape} in torch")
        diff = float(np.max(np.abs(o - r)))
        if not diff <= 1e-4 * max(1.0, float(np.max(np.abs(r)))):
            raise RuntimeError(f"{path}: {name} differs from torch by {diff:g}")
        worst = max(worst, diff)
    return worst


def export_onnx(model: MSNet, path: str | os.PathLike, variant: str, verify: bool = True,
                compression: str = "engine") -> onnx.ModelProto:
    """Writes `model` as `path`; with `compression` `engine` the graph takes symlog'd inputs."""
    metadata = metadata_for(model, variant, compression)
    net = copy.deepcopy(model).cpu().float().eval()
    traced = copy.deepcopy(net)
    traced.compress_inputs = compression == "graph"
    proto = _to_proto(traced)
    _check_graph(proto, net)
    write_model(proto, metadata, f"mcdenoise contract v{CONTRACT} {variant}", path)
    if verify:
        verify_onnx(path, net)
    return proto


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m mcdenoise_train.export_ms", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--random", action="store_true")
    src.add_argument("--checkpoint", help="v2 checkpoint trained on full features (exports full and nocov)")
    p.add_argument("--out", required=True, help="models directory (writes OUT/<variant>/model.onnx)")
    p.add_argument("--variants", default="full,nocov")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--compression", choices=COMPRESSIONS, default="engine",
                   help="who applies symlog to the inputs: the engine (default, faster) or the graph")
    p.add_argument("--recon", action="store_true",
                   help=f"also write <variant>/{RECON_FILE}, the reconstruction in the graph (for GPUs)")
    p.add_argument("--fp16", action="store_true",
                   help=f"with --recon, also write <variant>/{RECON_FP16_FILE}: the network in half precision")
    add_shape_arguments(p)
    p.add_argument("--head-gain", type=float, default=1.0, help="scale of the heads' weights (random models)")
    a = p.parse_args(argv)
    variants = [v for v in a.variants.split(",") if v]
    if a.random:
        torch.manual_seed(a.seed)
        net = from_arguments(a, len(FEATURES_FULL)).eval()
        with torch.no_grad():
            for h in net.gain_heads:  # random gains too (a new network's start at one tells nothing)
                torch.nn.init.kaiming_uniform_(h.weight, nonlinearity="relu")
                h.weight.mul_(0.1)
                h.bias.zero_()
            if a.head_gain != 1.0:
                for h in [*net.kernel_heads, *net.blend_heads, *net.gain_heads]:
                    h.weight.mul_(a.head_gain)
    else:
        net, _ = load_msnet(a.checkpoint)
        if a.specular_pyramid:  # the weights do not depend on it; the checkpoint's unless given
            net.specular_pyramid = a.specular_pyramid
    for v in variants:
        m = net if v == "full" else nocov_from_full(net)
        path = Path(a.out) / v / "model.onnx"
        export_onnx(m, path, v, compression=a.compression)
        write_stages(path)
        if a.recon:
            export_recon(m, path.with_name(RECON_FILE), v)
            if a.fp16:
                export_recon(m, path.with_name(RECON_FP16_FILE), v, half=True)
        print(f"{path}: {path.stat().st_size} bytes, {m.param_count()} params, {m.flops_per_pixel()} FLOP/px, "
              f"receptive radius {m.receptive_radius()}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

