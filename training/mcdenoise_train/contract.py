"""Model contract v1: the constants and names shared with the engine.

This module mirrors `src/engine/contract.rs`; `docs/model-contract.md` and
`docs/frame-layout.md` are the specification. Everything that the engine checks when it
loads a model (input/output names, channel counts, feature order, kernel size, metadata
keys) is defined here once, so the network, the exporter and the tests agree with it.

Feature tensors are planar, channels first (`[..., C, H, W]`). A `full` feature tensor
has 28 channels; the `nocov` tensor is the same tensor without the four covariance
channels, in the same order, so `select_nocov` turns one into the other.
"""

from __future__ import annotations

CONTRACT_VERSION = 1

KERNEL_SIZE = 21
KERNEL_RADIUS = KERNEL_SIZE // 2
KERNEL_TAPS = KERNEL_SIZE * KERNEL_SIZE

# Albedo offset of the diffuse transform d' = d / (a + EPS).
EPS = 0.00316

# Per-component `color` input: c' (3), variance (1), gx(c') (3), gy(c') (3).
COLOR_CHANNELS = 10

COMPONENTS = ("diffuse", "specular")
VARIANTS = ("full", "nocov")

# ONNX graph names.
INPUT_COLOR = "color"
INPUT_FEATURES = "features"
OUTPUT_KERNEL = "kernel"

# ONNX metadata_props keys.
META_PREFIX = "mcdenoise."
META_KEYS = (
    "mcdenoise.contract",
    "mcdenoise.component",
    "mcdenoise.variant",
    "mcdenoise.kernel_size",
    "mcdenoise.features",
    "mcdenoise.receptive_radius",
    "mcdenoise.flops_per_pixel",
    "mcdenoise.architecture",
)
# Contract v2 only, optional: `graph` (absent) or `engine`, who applies symlog to the inputs.
META_INPUT_COMPRESSION = "mcdenoise.input_compression"
# Contract v2 only, optional: `kernels` (absent) or `filtered` (the reconstruction in the graph).
META_OUTPUTS = "mcdenoise.outputs"
# Contract v2 only, optional: `fp32` (absent) or `fp16`, the precision the network computes in
# (a `filtered` graph's inputs, outputs and reconstruction stay float32).
META_PRECISION = "mcdenoise.precision"
# Contract v2 only, optional: `log` (absent) or `linear`, how the reconstruction's specular
# pyramid averages (recon_ms.color_pyramid).
META_SPECULAR_PYRAMID = "mcdenoise.specular_pyramid"

_BASE = (
    "normal.R", "normal.G", "normal.B",
    "albedo.R", "albedo.G", "albedo.B",
    "depth",
    "covariance",
)

FEATURES_FULL = (
    *_BASE,
    "normalVariance", "albedoVariance", "depthVariance", "covarianceVariance",
    *(f"gx.{n}" for n in _BASE),
    *(f"gy.{n}" for n in _BASE),
)

_COVARIANCE_FEATURES = ("covariance", "covarianceVariance", "gx.covariance", "gy.covariance")

FEATURES_NOCOV = tuple(n for n in FEATURES_FULL if n not in _COVARIANCE_FEATURES)

# Positions of the nocov channels inside a full feature tensor (ascending).
NOCOV_INDICES = tuple(FEATURES_FULL.index(n) for n in FEATURES_NOCOV)

assert len(FEATURES_FULL) == 28 and len(FEATURES_NOCOV) == 24


def feature_names(variant: str) -> tuple[str, ...]:
    """The feature names of `variant` ('full' or 'nocov') in input order."""
    if variant == "full":
        return FEATURES_FULL
    if variant == "nocov":
        return FEATURES_NOCOV
    raise ValueError(f"unknown variant {variant!r}; expected one of {VARIANTS}")


def feature_count(variant: str) -> int:
    """Number of feature channels of `variant`: 28 (full) or 24 (nocov)."""
    return len(feature_names(variant))


def variant_for(in_features: int) -> str:
    """The variant whose feature tensor has `in_features` channels."""
    for v in VARIANTS:
        if feature_count(v) == in_features:
            return v
    raise ValueError(
        f"{in_features} feature channels match no variant "
        f"(full: {len(FEATURES_FULL)}, nocov: {len(FEATURES_NOCOV)})"
    )


def select_nocov(features, axis: int = -3):
    """The nocov channels of a full feature array or tensor, in nocov order.

    `axis` is the channel axis; the default fits both `[C, H, W]` and `[N, C, H, W]`.
    Works on numpy arrays and torch tensors (anything with `.take` or `index_select`).
    """
    if features.shape[axis] != len(FEATURES_FULL):
        raise ValueError(
            f"expected {len(FEATURES_FULL)} full feature channels on axis {axis}, "
            f"got shape {tuple(features.shape)}"
        )
    if hasattr(features, "index_select"):  # torch.Tensor
        import torch

        idx = torch.tensor(NOCOV_INDICES, dtype=torch.long, device=features.device)
        return features.index_select(axis, idx)
    import numpy as np

    return np.take(features, NOCOV_INDICES, axis=axis)
