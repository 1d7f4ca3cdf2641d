"""Kernel-predicting denoiser networks: one `DenoiserNet` per component.

A `DenoiserNet` maps a component's `color` tensor `[N, 10, H, W]` and the shared
`features` tensor `[N, C, H, W]` (C = 28 full / 24 nocov, see `contract.py`) to the 441
logits of a 21x21 kernel per pixel, `[N, 441, H, W]`. The softmax and the filtering are
not part of the network (`recon.py` does them, and so does the engine); the exported ONNX
graph is exactly `forward`.

Architectures (`arch`):

- ``separate`` -- Lin et al. 2020. Two residual extractors of the same shape, one on the
  color tensor and one on the features: conv3x3(in -> w), `blocks` residual blocks
  (ReLU, conv3x3, ReLU, conv3x3, plus the skip), conv3x3(w -> w). Their outputs are
  concatenated (2w channels) and fed to a shallow kernel predictor: `predictor_depth`
  convs, the first `predictor_depth - 1` 3x3 of width `predictor_width` with a ReLU after
  each, then a `head_kernel` x `head_kernel` conv to 441 logits without activation.
  The paper's network is width 64, 8 blocks, predictor 4 x 128 with 3x3 head.
- ``joint`` -- the ablation of the paper's Fig. 13: a single residual extractor on
  concat(color, features), followed by the same kernel predictor. The extractor's last
  conv outputs 2w channels, so the predictor is identical (same shapes, same parameter
  count) to the ``separate`` one; the extractor's inner width `joint_width` is by default
  the integer that brings the extractor's parameter count closest to that of the two
  separate extractors (89 for w = 64, 8 blocks, 28 features: about sqrt(2) w, since one
  extractor replaces two). The resolved width is stored in `config`.
- ``kpcn`` -- the KPCN baseline of Bako et al. 2017: `layers` (9) convs of size
  `conv_kernel` (5) and width `width` (100) on concat(color, features), ReLU after every
  conv but the last, the last outputs 441 logits.

All convs are stride 1 with zero padding k//2, so every conv runs at full resolution and
a conv with kernel k extends the receptive field by (k-1)/2. `receptive_radius()` sums
that along the longest conv chain (residual skips add nothing; the two separate
extractors run in parallel, so the larger of the two counts). `flops_per_pixel()` counts
2 FLOPs per multiply-add of the convs, i.e. 2 * (weights of all convs); biases, ReLUs and
the residual additions (a few thousand operations, < 0.1%) are not counted.

Inputs are compressed with `symlog` (sign(x) ln(1 + |x|)) before the first convolution
(`input_transform`, part of the exported graph): the preprocessed tensors are unbounded.
Weights are initialised Xavier-uniform (the kernel head's scaled by `HEAD_INIT_GAIN`, 0.1,
so that training starts from nearly uniform kernels), biases zero.
"""

from __future__ import annotations

import torch
from torch import nn

from .contract import COLOR_CHANNELS, KERNEL_TAPS, variant_for

ARCHS = ("separate", "joint", "kpcn")
INPUT_TRANSFORMS = ("symlog", "none")
HEAD_INIT_GAIN = 0.1


def symlog(x: torch.Tensor) -> torch.Tensor:
    """sign(x) ln(1 + |x|): compresses the network's inputs.

    The preprocessed tensors are unbounded: the diffuse variance is divided by
    (albedo + 0.00316)^2 (up to ~1e5 where the albedo is near zero), irradiance reaches
    hundreds next to small lights. Fed as they are, such values drive the logits to
    thousands and the softmax to a single, wrong tap. The network sees them compressed;
    the kernels still filter the uncompressed preprocessed color.
    """
    return torch.sign(x) * torch.log1p(torch.abs(x))


def _conv(cin: int, cout: int, k: int = 3) -> nn.Conv2d:
    if k < 1 or k % 2 == 0:
        raise ValueError(f"conv kernel size must be odd and positive, got {k}")
    return nn.Conv2d(cin, cout, k, padding=k // 2)


def _radius(module: nn.Module) -> int:
    """Receptive radius of a module built from the classes of this file."""
    if isinstance(module, nn.Conv2d):
        return (module.kernel_size[0] - 1) // 2
    if hasattr(module, "radius"):
        return module.radius()
    # A plain chain: nn.Sequential, ReLU (0).
    return sum(_radius(m) for m in module.children())


class ResidualBlock(nn.Module):
    """x + conv(relu(conv(relu(x)))), 3x3 convs of constant width."""

    def __init__(self, width: int):
        super().__init__()
        self.conv1 = _conv(width, width)
        self.conv2 = _conv(width, width)
        self.relu = nn.ReLU()

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.conv2(self.relu(self.conv1(self.relu(x))))

    def radius(self) -> int:
        return _radius(self.conv1) + _radius(self.conv2)


class ResidualExtractor(nn.Sequential):
    """conv3x3(cin -> width), `blocks` residual blocks, conv3x3(width -> cout)."""

    def __init__(self, cin: int, width: int, blocks: int, cout: int):
        super().__init__(
            _conv(cin, width),
            *(ResidualBlock(width) for _ in range(blocks)),
            _conv(width, cout),
        )


def _extractor_params(cin: int, width: int, blocks: int, cout: int) -> int:
    """Parameter count of `ResidualExtractor(cin, width, blocks, cout)`."""
    k2 = 9
    return (
        (cin * width * k2 + width)
        + blocks * 2 * (width * width * k2 + width)
        + (width * cout * k2 + cout)
    )


def joint_width_for(width: int, blocks: int, in_features: int) -> int:
    """Width of the joint extractor closest in parameters to two separate ones."""
    target = _extractor_params(COLOR_CHANNELS, width, blocks, width) + _extractor_params(
        in_features, width, blocks, width
    )
    cin = COLOR_CHANNELS + in_features
    return min(
        range(1, 4 * width + 1),
        key=lambda wj: (abs(_extractor_params(cin, wj, blocks, 2 * width) - target), wj),
    )


def _predictor(cin: int, width: int, depth: int, head_kernel: int) -> nn.Sequential:
    layers: list[nn.Module] = []
    for _ in range(depth - 1):
        layers += [_conv(cin, width), nn.ReLU()]
        cin = width
    layers.append(_conv(cin, KERNEL_TAPS, head_kernel))
    return nn.Sequential(*layers)


class DenoiserNet(nn.Module):
    """Kernel predictor for one component (diffuse or specular).

    forward(color [N,10,H,W], features [N,C,H,W]) -> logits [N,441,H,W].
    Construct with keyword arguments (see the module docstring); `config` holds the
    resolved arguments of the chosen architecture, and `DenoiserNet(**config)` rebuilds
    the same network.
    """

    def __init__(
        self,
        arch: str = "separate",
        in_features: int = 28,
        width: int | None = None,
        blocks: int = 8,
        predictor_width: int = 128,
        predictor_depth: int = 4,
        head_kernel: int = 3,
        joint_width: int | None = None,
        layers: int = 9,
        conv_kernel: int = 5,
        input_transform: str = "symlog",
    ):
        super().__init__()
        if input_transform not in INPUT_TRANSFORMS:
            raise ValueError(f"unknown input_transform {input_transform!r}; expected one of {INPUT_TRANSFORMS}")
        self.input_transform = input_transform
        if arch not in ARCHS:
            raise ValueError(f"unknown arch {arch!r}; expected one of {ARCHS}")
        variant_for(in_features)  # validates the channel count
        self.arch = arch
        self.in_features = in_features

        if arch in ("separate", "joint"):
            width = 64 if width is None else width
            if width < 1 or blocks < 0 or predictor_width < 1 or predictor_depth < 1:
                raise ValueError("width, predictor_width, predictor_depth must be >= 1, blocks >= 0")
            self.config = dict(
                arch=arch, in_features=in_features, width=width, blocks=blocks,
                predictor_width=predictor_width, predictor_depth=predictor_depth,
                head_kernel=head_kernel,
            )
            if arch == "separate":
                self.color_extractor = ResidualExtractor(COLOR_CHANNELS, width, blocks, width)
                self.feature_extractor = ResidualExtractor(in_features, width, blocks, width)
            else:
                if joint_width is None:
                    joint_width = joint_width_for(width, blocks, in_features)
                self.config["joint_width"] = joint_width
                self.extractor = ResidualExtractor(
                    COLOR_CHANNELS + in_features, joint_width, blocks, 2 * width
                )
            self.predictor = _predictor(2 * width, predictor_width, predictor_depth, head_kernel)
        else:
            width = 100 if width is None else width
            if width < 1 or layers < 1:
                raise ValueError("width and layers must be >= 1")
            self.config = dict(
                arch=arch, in_features=in_features, width=width, layers=layers,
                conv_kernel=conv_kernel,
            )
            chain: list[nn.Module] = []
            cin = COLOR_CHANNELS + in_features
            for i in range(layers):
                last = i == layers - 1
                chain.append(_conv(cin, KERNEL_TAPS if last else width, conv_kernel))
                if not last:
                    chain.append(nn.ReLU())
                cin = width
            self.net = nn.Sequential(*chain)

        self.config["input_transform"] = input_transform
        self.reset_parameters()

    def reset_parameters(self) -> None:
        convs = [m for m in self.modules() if isinstance(m, nn.Conv2d)]
        for m in convs:
            nn.init.xavier_uniform_(m.weight)
            nn.init.zeros_(m.bias)
        # The kernel head starts small, so the first kernels are close to a uniform 21x21
        # box: a saturated softmax (one tap near 1) passes almost no gradient, and a
        # network that starts there learns one-hot kernels that copy a neighbour.
        with torch.no_grad():
            convs[-1].weight.mul_(HEAD_INIT_GAIN)

    @property
    def variant(self) -> str:
        return variant_for(self.in_features)

    def forward(self, color: torch.Tensor, features: torch.Tensor) -> torch.Tensor:
        if self.input_transform == "symlog":
            color, features = symlog(color), symlog(features)
        if self.arch == "separate":
            x = torch.cat([self.color_extractor(color), self.feature_extractor(features)], 1)
            return self.predictor(x)
        if self.arch == "joint":
            return self.predictor(self.extractor(torch.cat([color, features], 1)))
        return self.net(torch.cat([color, features], 1))

    # ----- analysis -------------------------------------------------------------------

    def receptive_radius(self) -> int:
        """Pixels of input context (Chebyshev distance) that one output logit depends on."""
        if self.arch == "separate":
            ext = max(_radius(self.color_extractor), _radius(self.feature_extractor))
            return ext + _radius(self.predictor)
        if self.arch == "joint":
            return _radius(self.extractor) + _radius(self.predictor)
        return _radius(self.net)

    def flops_per_pixel(self) -> int:
        """2 x conv multiply-adds per output pixel (biases, ReLUs, skip adds not counted)."""
        macs = 0
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                kh, kw = m.kernel_size
                macs += m.in_channels * m.out_channels * kh * kw // m.groups
        return 2 * macs

    def param_count(self) -> int:
        return sum(p.numel() for p in self.parameters())

    def description(self) -> str:
        """One line for the ONNX `mcdenoise.architecture` field."""
        c = self.config
        C = self.in_features
        blocks = f"{c.get('blocks')} residual block{'' if c.get('blocks') == 1 else 's'}"
        if self.arch == "kpcn":
            body = (
                f"kpcn: {c['layers']} convs {c['conv_kernel']}x{c['conv_kernel']} width "
                f"{c['width']} on color+features ({COLOR_CHANNELS}+{C})"
            )
        else:
            hk = c["head_kernel"]
            pred = (
                f"kernel predictor {c['predictor_depth']} convs width {c['predictor_width']} "
                f"(head {hk}x{hk} -> {KERNEL_TAPS})"
            )
            if self.arch == "separate":
                ext = (
                    f"separate: color ({COLOR_CHANNELS}) and feature ({C}) residual "
                    f"extractors width {c['width']}, {blocks} each"
                )
            else:
                ext = (
                    f"joint: one residual extractor on color+features "
                    f"({COLOR_CHANNELS}+{C}) width {c['joint_width']}, {blocks}, "
                    f"out {2 * c['width']}"
                )
            body = f"{ext}; {pred}"
        return (
            f"{body}; params {self.param_count()}, receptive radius "
            f"{self.receptive_radius()}"
        )


def build(config: dict) -> DenoiserNet:
    """A freshly initialised network from a `config` dict."""
    return DenoiserNet(**config)


def paper_config(in_features: int = 28) -> dict:
    """The configuration of Lin et al. 2020 (width 64, 8 blocks, predictor 4 x 128)."""
    return dict(
        arch="separate", in_features=in_features, width=64, blocks=8,
        predictor_width=128, predictor_depth=4, head_kernel=3,
    )


__all__ = [
    "ARCHS", "DenoiserNet", "ResidualBlock", "ResidualExtractor", "build",
    "joint_width_for", "paper_config",
]
