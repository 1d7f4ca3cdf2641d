"""ONNX export in model contract v1 (docs/model-contract.md).

`export_onnx(model, path, component, variant)` writes one network as a self-contained
ONNX file: inputs `color [N,10,H,W]` and `features [N,C,H,W]`, output `kernel
[N,441,H,W]`, float32, N/H/W dynamic, opset 17, and the `mcdenoise.*` metadata_props.
It uses the TorchScript exporter (`dynamo=False`): the networks are plain chains of
Conv/Relu/Add/Concat, which that exporter maps one to one, in NCHW, so the graph holds no
Transpose, Reshape or shape arithmetic (the Identity aliases it emits for deduplicated
initializers are folded away). After writing, the file is checked
(`onnx.checker` with shape inference, exact metadata, the op set) and run in onnxruntime
on an input of a different shape than the traced one; the export fails unless
max |ort - torch| <= 1e-4 * max(1, max |torch|).

Command line (files go to OUT/<variant>/<component>.onnx):

    # random-init networks for tests and benchmarks, both variants and both components
    python -m mcdenoise_train.export --random --seed 0 --arch separate --width 8 \\
        --blocks 1 --predictor-width 16 --predictor-depth 2 --out DIR

    # trained networks, one checkpoint per variant (format: checkpoint.py)
    python -m mcdenoise_train.export --checkpoint full.pt --checkpoint nocov.pt --out DIR
"""

from __future__ import annotations

import argparse
import copy
import io
import json
import os
import sys
import warnings
from pathlib import Path

import numpy as np
import onnx
import torch

from .contract import (
    COLOR_CHANNELS,
    COMPONENTS,
    CONTRACT_VERSION,
    INPUT_COLOR,
    INPUT_FEATURES,
    KERNEL_SIZE,
    KERNEL_TAPS,
    OUTPUT_KERNEL,
    VARIANTS,
    feature_names,
    variant_for,
)
from .model import ARCHS, DenoiserNet

OPSET = 17
# Conv, Relu, Add, Concat: the networks; Sign, Abs, Log, Mul, Constant: the symlog input transform;
# Cast: weights stored in float16 (`half_weight_storage`).
ALLOWED_OPS = frozenset({"Conv", "Relu", "Add", "Concat", "Sign", "Abs", "Log", "Mul", "Constant", "Cast"})
_TRACE_HW = (16, 24)
_VERIFY_SHAPE = (2, 19, 27)  # N, H, W: differs from the traced shape on purpose


def metadata_for(model: DenoiserNet, component: str, variant: str) -> dict[str, str]:
    """The `mcdenoise.*` metadata_props of `model` exported as `component`/`variant`."""
    return {
        "mcdenoise.contract": str(CONTRACT_VERSION),
        "mcdenoise.component": component,
        "mcdenoise.variant": variant,
        "mcdenoise.kernel_size": str(KERNEL_SIZE),
        "mcdenoise.features": ",".join(feature_names(variant)),
        "mcdenoise.receptive_radius": str(model.receptive_radius()),
        "mcdenoise.flops_per_pixel": str(model.flops_per_pixel()),
        "mcdenoise.architecture": model.description(),
        "mcdenoise.torch_config": json.dumps(model.config, sort_keys=True),
    }


def read_metadata(path: str | os.PathLike) -> dict[str, str]:
    """metadata_props of an ONNX file as a dict."""
    proto = onnx.load(str(path), load_external_data=False)
    return {p.key: p.value for p in proto.metadata_props}


def networks_from_onnx(directory: str | os.PathLike) -> dict[str, DenoiserNet]:
    """The torch networks ({'diffuse': net, 'specular': net}, eval mode) whose weights a
    contract-v1 variant directory holds: each file's `mcdenoise.torch_config` rebuilds the
    network, its initializers (named as the network's parameters) fill it. So a shipped
    pair is its own checkpoint (`train_ms --arch lin2020 --init DIR`) and the parity tests
    run the shipped weights in torch."""
    from onnx import numpy_helper

    nets = {}
    for c in COMPONENTS:
        path = Path(directory) / f"{c}.onnx"
        proto = onnx.load(str(path))
        meta = {p.key: p.value for p in proto.metadata_props}
        if "mcdenoise.torch_config" not in meta:
            raise ValueError(f"{path}: no mcdenoise.torch_config metadata (exported before it was written): "
                             "export it again from its checkpoint")
        net = DenoiserNet(**json.loads(meta["mcdenoise.torch_config"]))
        stored = {i.name: torch.from_numpy(numpy_helper.to_array(i).astype(np.float32)) for i in proto.graph.initializer}
        # Weights stored in float16 (`half_weight_storage`) reach the graph through a Cast.
        for node in proto.graph.node:
            if node.op_type == "Cast" and node.input[0] in stored:
                stored[node.output[0]] = stored[node.input[0]]
        # The exporter keeps one initializer of several equal ones (zero biases of an
        # untrained network, say): each convolution's own inputs say which it reads. Its
        # node is named after its module's scopes, e.g. `/extractor/extractor.1/conv1/Conv`.
        weights = dict(stored)
        for node in proto.graph.node:
            if node.op_type != "Conv":
                continue
            scopes = node.name.strip("/").split("/")[:-1]
            module = scopes[-1] if "." in scopes[-1] or len(scopes) == 1 else f"{scopes[-2]}.{scopes[-1]}"
            for param, name in zip(("weight", "bias"), node.input[1:]):
                if name in stored:
                    weights.setdefault(f"{module}.{param}", stored[name])
        missing = sorted(set(net.state_dict()) - set(weights))
        if missing:
            raise ValueError(f"{path}: no initializer for {', '.join(missing[:3])}{' ...' if len(missing) > 3 else ''}")
        net.load_state_dict({k: weights[k] for k in net.state_dict()})
        nets[c] = net.eval()
    return nets


def _to_proto(model: DenoiserNet, in_features: int) -> onnx.ModelProto:
    h, w = _TRACE_HW
    args = (torch.zeros(1, COLOR_CHANNELS, h, w), torch.zeros(1, in_features, h, w))
    dyn = {0: "N", 2: "H", 3: "W"}
    buf = io.BytesIO()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(
            model,
            args,
            buf,
            dynamo=False,
            input_names=[INPUT_COLOR, INPUT_FEATURES],
            output_names=[OUTPUT_KERNEL],
            dynamic_axes={INPUT_COLOR: dyn, INPUT_FEATURES: dyn, OUTPUT_KERNEL: dyn},
            opset_version=OPSET,
            do_constant_folding=True,
        )
    proto = onnx.load_from_string(buf.getvalue())
    _drop_initializer_identities(proto.graph)
    return proto


def _drop_initializer_identities(g: onnx.GraphProto) -> None:
    """Remove `Identity(initializer)` nodes by pointing their consumers at the initializer.

    The exporter deduplicates equal initializers (e.g. the all-zero biases of a fresh
    network) and aliases them through Identity nodes; the aliases are pure overhead.
    """
    inits = {i.name for i in g.initializer}
    alias = {
        n.output[0]: n.input[0]
        for n in g.node
        if n.op_type == "Identity" and n.input[0] in inits
    }
    if not alias:
        return
    outputs = {o.name for o in g.output}
    if outputs & alias.keys():
        return
    keep = [n for n in g.node if not (n.op_type == "Identity" and n.output[0] in alias)]
    for n in keep:
        for i, name in enumerate(n.input):
            if name in alias:
                n.input[i] = alias[name]
    del g.node[:]
    g.node.extend(keep)


def _check_graph(proto: onnx.ModelProto, in_features: int) -> None:
    onnx.checker.check_model(proto, full_check=True)
    g = proto.graph
    ops = {n.op_type for n in g.node}
    if not ops <= ALLOWED_OPS:
        raise RuntimeError(f"exported graph has unexpected ops {sorted(ops - ALLOWED_OPS)}")
    inits = {i.name for i in g.initializer}
    inputs = [i for i in g.input if i.name not in inits]
    expect = [(INPUT_COLOR, COLOR_CHANNELS), (INPUT_FEATURES, in_features)]
    for vi, (name, ch) in zip(inputs, expect, strict=True):
        _check_value(vi, name, ch)
    if len(g.output) != 1:
        raise RuntimeError(f"exported graph has {len(g.output)} outputs, expected 1")
    _check_value(g.output[0], OUTPUT_KERNEL, KERNEL_TAPS)


def _check_value(vi: onnx.ValueInfoProto, name: str, channels: int) -> None:
    t = vi.type.tensor_type
    dims = [d.dim_param or d.dim_value for d in t.shape.dim]
    if vi.name != name or t.elem_type != onnx.TensorProto.FLOAT or dims != ["N", channels, "H", "W"]:
        raise RuntimeError(
            f"graph value {vi.name!r} is {onnx.TensorProto.DataType.Name(t.elem_type)} {dims}, "
            f"expected {name!r} FLOAT ['N', {channels}, 'H', 'W']"
        )


def verify_onnx(path: str | os.PathLike, model: DenoiserNet, seed: int = 0) -> float:
    """Max |onnxruntime - torch| on a random input; raises if above 1e-4 * max(1, |torch|)."""
    import onnxruntime as ort

    n, h, w = _VERIFY_SHAPE
    g = torch.Generator().manual_seed(seed)
    color = torch.randn(n, COLOR_CHANNELS, h, w, generator=g)
    feats = torch.rand(n, model.in_features, h, w, generator=g)
    with torch.no_grad():
        ref = model(color, feats).numpy()
    sess = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    out = sess.run([OUTPUT_KERNEL], {INPUT_COLOR: color.numpy(), INPUT_FEATURES: feats.numpy()})[0]
    if out.shape != ref.shape:
        raise RuntimeError(f"{path}: onnxruntime output {out.shape}, torch {ref.shape}")
    diff = float(np.max(np.abs(out - ref)))
    tol = 1e-4 * max(1.0, float(np.max(np.abs(ref))))
    if not diff <= tol:
        raise RuntimeError(f"{path}: onnxruntime differs from torch by {diff:g} (> {tol:g})")
    return diff


def export_onnx(
    model: DenoiserNet,
    path: str | os.PathLike,
    component: str,
    variant: str,
    verify: bool = True,
    name: str | None = None,
    half_weights: bool = False,
) -> onnx.ModelProto:
    """Write `model` as `component` ('diffuse'/'specular') of `variant` ('full'/'nocov',
    its feature set). `name` is the served variant's name (its directory, e.g. `lin2020`)
    when it differs from the feature set's. `half_weights` stores the weights rounded to
    float16, each cast back to float32 in the graph (`half_weight_storage`): the file at
    half the size, the computation in float32 as before; the network verified against is
    the rounded one."""
    if component not in COMPONENTS:
        raise ValueError(f"unknown component {component!r}; expected one of {COMPONENTS}")
    if variant not in VARIANTS:
        raise ValueError(f"unknown variant {variant!r}; expected one of {VARIANTS}")
    if variant_for(model.in_features) != variant:
        raise ValueError(
            f"model takes {model.in_features} feature channels, variant {variant!r} "
            f"has {len(feature_names(variant))}"
        )
    net = copy.deepcopy(model).cpu().float().eval()
    if half_weights:
        with torch.no_grad():
            for p in net.parameters():
                p.copy_(p.half().float())
    proto = _to_proto(net, net.in_features)
    if half_weights:
        half_weight_storage(proto)
    _check_graph(proto, net.in_features)
    name = name or variant
    metadata = {**metadata_for(net, component, variant), "mcdenoise.variant": name}
    write_model(proto, metadata, f"mcdenoise contract v{CONTRACT_VERSION} {name}/{component}", path)
    if verify:
        verify_onnx(path, net)
    return proto


def half_weight_storage(proto: onnx.ModelProto) -> None:
    """Every float32 initializer stored as float16 under `<name>.fp16`, with a Cast node in
    front of the graph giving `<name>` back in float32 (ONNX Runtime folds the casts when it
    loads the graph). The values must already be representable in float16: the caller rounds
    the weights first, so the graph computes exactly what the rounded network does."""
    from onnx import helper, numpy_helper

    g = proto.graph
    inits, casts = [], []
    for init in g.initializer:
        if init.data_type != onnx.TensorProto.FLOAT:
            inits.append(init)
            continue
        a = numpy_helper.to_array(init)
        h = a.astype(np.float16)
        if not np.array_equal(h.astype(np.float32), a):
            raise ValueError(f"initializer {init.name} is not representable in float16: round the weights first")
        inits.append(numpy_helper.from_array(h, f"{init.name}.fp16"))
        casts.append(helper.make_node("Cast", [f"{init.name}.fp16"], [init.name], to=onnx.TensorProto.FLOAT,
                                      name=f"/{init.name}/Cast"))
    del g.initializer[:]
    g.initializer.extend(inits)
    nodes = casts + list(g.node)
    del g.node[:]
    g.node.extend(nodes)


def write_model(proto: onnx.ModelProto, metadata: dict[str, str], doc: str, path: str | os.PathLike) -> None:
    """Save `proto` at `path` (directories created) with exactly `metadata` as its
    metadata_props and `doc` as its doc string: the last step of both contracts' exports."""
    del proto.metadata_props[:]
    for k, v in metadata.items():
        proto.metadata_props.add(key=k, value=v)
    proto.doc_string = doc
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    onnx.save(proto, str(path))


# ----- command line --------------------------------------------------------------------


def random_models(seed: int, variants=VARIANTS, **config) -> dict[tuple[str, str], DenoiserNet]:
    """Freshly initialised networks keyed by (variant, component).

    One `torch.manual_seed(seed)`, then the networks are built in the fixed order
    full/diffuse, full/specular, nocov/diffuse, nocov/specular (skipping absent variants),
    so the weights depend only on the seed, the config and the torch version.
    """
    torch.manual_seed(seed)
    out = {}
    for v in VARIANTS:
        if v not in variants:
            continue
        for c in COMPONENTS:
            out[(v, c)] = DenoiserNet(in_features=len(feature_names(v)), **config).eval()
    return out


def scale_head(model: DenoiserNet, gain: float) -> DenoiserNet:
    """Multiply the last conv's weights by `gain` (sharper random kernels); in place."""
    last = [m for m in model.modules() if isinstance(m, torch.nn.Conv2d)][-1]
    with torch.no_grad():
        last.weight.mul_(gain)
    return model


def _parse(argv) -> argparse.Namespace:
    p = argparse.ArgumentParser(
        prog="python -m mcdenoise_train.export",
        description="Export mcdenoise networks as contract-v1 ONNX into OUT/<variant>/<component>.onnx.",
    )
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--random", action="store_true", help="random-init networks")
    src.add_argument("--checkpoint", action="append", metavar="CKPT",
                     help="trained checkpoint (repeat for several variants)")
    p.add_argument("--out", required=True, help="models directory")
    g = p.add_argument_group("random networks")
    g.add_argument("--seed", type=int, default=0)
    g.add_argument("--arch", choices=ARCHS, default="separate")
    g.add_argument("--width", type=int, help="extractor width (separate/joint: 64) or kpcn width (100)")
    g.add_argument("--blocks", type=int, default=8)
    g.add_argument("--predictor-width", type=int, default=128)
    g.add_argument("--predictor-depth", type=int, default=4)
    g.add_argument("--head-kernel", type=int, default=3, help="kernel size of the predictor's last conv")
    g.add_argument("--joint-width", type=int, help="joint extractor width (default: parameter-matched)")
    g.add_argument("--layers", type=int, default=9, help="kpcn conv layers")
    g.add_argument("--conv-kernel", type=int, default=5, help="kpcn conv kernel size")
    g.add_argument("--kernel-gain", type=float, default=1.0,
                   help="scale of the last conv's weights (sharper random kernels)")
    g.add_argument("--variants", default="full,nocov", help="comma-separated subset of full,nocov")
    return p.parse_args(argv)


def _random_config(a: argparse.Namespace) -> dict:
    if a.arch == "kpcn":
        return dict(arch="kpcn", width=a.width, layers=a.layers, conv_kernel=a.conv_kernel)
    cfg = dict(
        arch=a.arch, width=a.width, blocks=a.blocks, predictor_width=a.predictor_width,
        predictor_depth=a.predictor_depth, head_kernel=a.head_kernel,
    )
    if a.arch == "joint":
        cfg["joint_width"] = a.joint_width
    return cfg


def main(argv=None) -> int:
    a = _parse(argv)
    out = Path(a.out)
    jobs: list[tuple[str, str, DenoiserNet]] = []
    if a.random:
        variants = [v.strip() for v in a.variants.split(",") if v.strip()]
        bad = [v for v in variants if v not in VARIANTS]
        if bad or not variants:
            sys.exit(f"--variants: expected a subset of {','.join(VARIANTS)}, got {a.variants!r}")
        for (v, c), net in random_models(a.seed, variants, **_random_config(a)).items():
            jobs.append((v, c, scale_head(net, a.kernel_gain) if a.kernel_gain != 1.0 else net))
    else:
        from .checkpoint import load_checkpoint

        for ck in a.checkpoint:
            models, raw = load_checkpoint(ck)
            jobs += [(raw["variant"], c, models[c]) for c in COMPONENTS]
        seen = [v for v, c, _ in jobs if c == COMPONENTS[0]]
        if len(seen) != len(set(seen)):
            sys.exit(f"two checkpoints for the same variant: {seen}")
    for v, c, net in jobs:
        path = out / v / f"{c}.onnx"
        export_onnx(net, path, c, v)
        print(
            f"{path}: {path.stat().st_size} bytes, {net.param_count()} params, "
            f"{net.flops_per_pixel()} FLOP/px, receptive radius {net.receptive_radius()}"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
