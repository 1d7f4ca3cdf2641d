"""The production denoiser: multi-scale kernel prediction on a U-Net trunk (contract v2).

One `MSNet` serves both components. It keeps the ideas of Lin et al. 2020 — separate
residual extractors for the color (both components' 10-channel tensors) and for the
auxiliary features (normal, albedo, depth, light-transport covariance, their variances and
gradients) at full resolution, kernels that filter the preprocessed noisy color, the
diffuse/specular split — and moves most of the work to low resolution, where a U-Net sees
far more context for the same cost (Vogels et al. 2018; RenderKit/oidn's U-Nets):

    diffuse [N,10,H,W], specular [N,10,H,W] -> color extractor (conv, residual blocks)  \\
    features [N,C,H,W]                      -> feature extractor (conv, residual blocks) -> concat = level 0
    level l -> maxpool 2x2 -> two 3x3 convs -> level l+1            (encoder, l = 0 … L-2)
    level l+1 -> nearest x2 -> concat skip l -> two 3x3 convs        (decoder, l = L-2 … 0)
    at every level: a 1x1 head -> kernel logits [N, 2k², H/2^l, W/2^l] (diffuse taps, then
    specular taps) and, below the coarsest level, blend logits [N, 2, H/2^l, W/2^l]
    (and, with `detail_gain`, detail-gain logits [N, 2, H/2^l, W/2^l])

With `lean0`, decoder level 0 is cheaper: instead of two 3x3 convs over the upsampled level
below concatenated with the skip (the costliest operators on a CPU, at full resolution over
64 channels), a 1x1 conv of the level below at its own resolution, upsampled, plus a 1x1 conv
of the skip, then one 3x3 conv (`Lean0`): the same fusion of context and full-resolution
features. With the extractors' residual blocks removed as well, a 768x720 region takes 0.27 s
in ONNX Runtime against the shipped shape's 0.45 s (docs/training.md, "A cheaper level 0").

`recon_ms.py` turns these into the filtered color (docs/model-contract.md, "Model contract
v2"): a k x k kernel at each pyramid level of the preprocessed color, blended coarse to
fine. Inputs are compressed with `symlog` first, as in contract v1; an exported graph
leaves that to the engine (`compress_inputs = False`, metadata `mcdenoise.input_compression`
`engine`), whose preprocessing writes the tensors anyway and does it in the same pass for
a quarter of the graph's time (docs/model-contract.md).

`forward` returns `(kernel_0, …, kernel_{L-1}, blend_0, …, blend_{L-2})`, the graph's
outputs in order, followed by `(gain_0, …, gain_{L-2})` with `detail_gain`: per pixel, how
much of each level's own detail (its filtered color less the upsampled mean of that) the
reconstruction keeps. A k×k kernel that reweights noisy pixels keeps some of their noise in
that band at low sample counts, which the blends alone cannot remove (docs/training.md,
"Detail gains"). H and W must be multiples of `size_multiple` (2^(L-1)).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from .contract import COLOR_CHANNELS, variant_for
from .model import ResidualBlock, symlog
from .recon_ms import PYRAMIDS

COMPONENT_COUNT = 2


def _conv(cin: int, cout: int, k: int = 3) -> nn.Conv2d:
    return nn.Conv2d(cin, cout, k, padding=k // 2)


class Extractor(nn.Sequential):
    """conv3x3(cin -> width) then `blocks` residual blocks, at full resolution."""

    def __init__(self, cin: int, width: int, blocks: int):
        super().__init__(_conv(cin, width), *(ResidualBlock(width) for _ in range(blocks)))


class _Pair(nn.Sequential):
    """Two 3x3 convs with ReLUs."""

    def __init__(self, cin: int, cout: int):
        super().__init__(_conv(cin, cout), nn.ReLU(), _conv(cout, cout), nn.ReLU())


class Lean0(nn.Module):
    """Decoder level 0 of `MSNet(lean0=True)`: relu(up(1x1(below)) + 1x1(skip)), then a 3x3
    conv and a relu. The 1x1 conv of the level below runs at its resolution (a 1x1 conv
    commutes with nearest upsampling), so nothing at full resolution reads more than the
    skip's channels."""

    def __init__(self, below: int, skip: int, width: int):
        super().__init__()
        self.up, self.skip, self.mid = _conv(below, width, 1), _conv(skip, width, 1), _conv(width, width)

    def forward(self, below: torch.Tensor, skip: torch.Tensor) -> torch.Tensor:
        x = F.interpolate(self.up(below), scale_factor=2.0, mode="nearest") + self.skip(skip)
        return torch.relu(self.mid(torch.relu(x)))


DEFAULT = dict(ext_width=16, ext_blocks=1, enc=(32, 48, 64, 80), dec=(32, 32, 48, 64), kernel_size=5, levels=5,
               specular_pyramid="linear")

# The detail-gain heads start with zero weights and this bias: every gain at sigmoid(4) =
# 0.982, nearly the network without them, so that a fine-tune adding them starts where its
# checkpoint is.
GAIN_START = 4.0


class MSNet(nn.Module):
    """Multi-scale kernel predictor for both components (see the module docstring).

    `enc[i]` is the width of encoder level i+1, `dec[l]` of decoder level l (l = 0 … L-2);
    level 0's encoder width is 2 * ext_width (the two extractors concatenated).
    """

    def __init__(
        self,
        in_features: int = 28,
        ext_width: int = DEFAULT["ext_width"],
        ext_blocks: int = DEFAULT["ext_blocks"],
        enc: tuple[int, ...] | list[int] = DEFAULT["enc"],
        dec: tuple[int, ...] | list[int] = DEFAULT["dec"],
        kernel_size: int = DEFAULT["kernel_size"],
        levels: int = DEFAULT["levels"],
        specular_pyramid: str = DEFAULT["specular_pyramid"],
        detail_gain: bool = False,
        lean0: bool = False,
    ):
        super().__init__()
        variant_for(in_features)
        enc, dec = list(enc)[: levels - 1], list(dec)[: levels - 1]
        if levels < 1 or len(enc) != levels - 1 or len(dec) != levels - 1:
            raise ValueError(f"levels={levels} needs {levels - 1} encoder and decoder widths, got enc={enc} dec={dec}")
        if kernel_size < 1 or kernel_size % 2 == 0:
            raise ValueError(f"kernel_size must be odd and positive, got {kernel_size}")
        self.in_features, self.levels, self.kernel_size = in_features, levels, kernel_size
        # Whether forward applies symlog to its inputs (training, validation); an export for
        # the engine turns it off and feeds symlog'd inputs instead. Not part of the weights.
        self.compress_inputs = True
        self.config = dict(
            arch="msnet", in_features=in_features, ext_width=ext_width, ext_blocks=ext_blocks,
            enc=enc, dec=dec, kernel_size=kernel_size, levels=levels, detail_gain=bool(detail_gain),
            lean0=bool(lean0),
        )
        if lean0 and levels < 2:
            raise ValueError("lean0 needs a decoder level 0 (levels >= 2)")
        self.specular_pyramid = specular_pyramid
        taps = kernel_size * kernel_size
        self.color_extractor = Extractor(COMPONENT_COUNT * COLOR_CHANNELS, ext_width, ext_blocks)
        self.feature_extractor = Extractor(in_features, ext_width, ext_blocks)
        widths = [2 * ext_width, *enc]  # encoder width per level
        self.encoder = nn.ModuleList(_Pair(widths[l], widths[l + 1]) for l in range(levels - 1))
        self.decoder = nn.ModuleList()
        for l in range(levels - 1):
            below = dec[l + 1] if l + 1 < levels - 1 else widths[levels - 1]
            self.decoder.append(Lean0(below, widths[0], dec[0]) if l == 0 and lean0 else _Pair(below + widths[l], dec[l]))
        self._head_in = [*dec, widths[levels - 1]]
        self.kernel_heads = nn.ModuleList(_conv(self._head_in[l], COMPONENT_COUNT * taps, 1) for l in range(levels))
        self.blend_heads = nn.ModuleList(_conv(self._head_in[l], COMPONENT_COUNT, 1) for l in range(levels - 1))
        self.gain_heads = nn.ModuleList()
        self.reset_parameters()
        if detail_gain:
            self.add_detail_gain()

    @property
    def lean0(self) -> bool:
        """Whether decoder level 0 is a `Lean0` (see the module docstring)."""
        return bool(self.config.get("lean0"))

    @property
    def detail_gain(self) -> bool:
        return bool(self.config.get("detail_gain"))

    def add_detail_gain(self) -> None:
        """Adds the detail-gain heads (one 1x1 conv per level below the coarsest, both
        components), zero weights and every logit at `GAIN_START`: a trained network gains
        them for a fine-tune."""
        if len(self.gain_heads):
            return
        device = self.kernel_heads[0].weight.device
        for l in range(self.levels - 1):
            self.gain_heads.append(_conv(self._head_in[l], COMPONENT_COUNT, 1).to(device))
        self._start_gains()
        self.config["detail_gain"] = True

    @torch.no_grad()
    def _start_gains(self) -> None:
        """Every detail-gain head at its start: zero weights, every logit at `GAIN_START`."""
        for h in self.gain_heads:
            nn.init.zeros_(h.weight)
            nn.init.constant_(h.bias, GAIN_START)

    @property
    def specular_pyramid(self) -> str:
        """How the reconstruction's specular pyramid averages (recon_ms.color_pyramid), kept
        in `config`. The graph does not depend on it, the kernels it learns do, so a
        fine-tune or an export may set it."""
        return self.config["specular_pyramid"]

    @specular_pyramid.setter
    def specular_pyramid(self, value: str) -> None:
        if value not in PYRAMIDS:
            raise ValueError(f"specular_pyramid must be one of {PYRAMIDS}, got {value!r}")
        self.config["specular_pyramid"] = value

    @property
    def size_multiple(self) -> int:
        return 1 << (self.levels - 1)

    @property
    def variant(self) -> str:
        return variant_for(self.in_features)

    def reset_parameters(self) -> None:
        for m in self.modules():
            if isinstance(m, nn.Conv2d):
                nn.init.kaiming_uniform_(m.weight, nonlinearity="relu")
                nn.init.zeros_(m.bias)
        # Heads start small: nearly uniform kernels and blends of one half, so that every
        # level passes gradient from the first step.
        with torch.no_grad():
            for h in [*self.kernel_heads, *self.blend_heads]:
                h.weight.mul_(0.1)
        self._start_gains()

    def forward(self, diffuse: torch.Tensor, specular: torch.Tensor, features: torch.Tensor):
        color = torch.cat([diffuse, specular], 1)
        if self.compress_inputs:
            color, features = symlog(color), symlog(features)
        x = torch.relu(torch.cat([self.color_extractor(color), self.feature_extractor(features)], 1))
        skips = [x]
        for l in range(self.levels - 1):
            x = self.encoder[l](F.max_pool2d(x, 2))
            skips.append(x)
        kernels: list[torch.Tensor] = [None] * self.levels  # type: ignore[list-item]
        blends: list[torch.Tensor] = [None] * (self.levels - 1)  # type: ignore[list-item]
        gains: list[torch.Tensor] = [None] * len(self.gain_heads)  # type: ignore[list-item]
        kernels[-1] = self.kernel_heads[-1](x)
        for l in reversed(range(self.levels - 1)):
            if l == 0 and self.lean0:
                x = self.decoder[0](x, skips[0])
            else:
                x = F.interpolate(x, scale_factor=2.0, mode="nearest")
                x = self.decoder[l](torch.cat([x, skips[l]], 1))
            kernels[l] = self.kernel_heads[l](x)
            blends[l] = self.blend_heads[l](x)
            if gains:
                gains[l] = self.gain_heads[l](x)
        return (*kernels, *blends, *gains)

    # ----- analysis -------------------------------------------------------------------

    def receptive_radius(self) -> int:
        """Pixels of input context an output pixel depends on, the reconstruction included
        (docs/model-contract.md, v2 metadata). Exact interval arithmetic: a value at level l,
        pixel i depends on the full-resolution pixels [i 2^l + a, i 2^l + b]; each operation
        widens (a, b) as below, and the radius is max(-a, b) at level 0."""
        def conv(iv, s):  # 3x3 conv at stride s
            return (iv[0] - s, iv[1] + s)

        def pool(iv, s):  # 2x2 max or average pool from stride s
            return (iv[0], iv[1] + s)

        def nearest(iv, s):  # nearest x2 to stride s
            return (iv[0] - s, iv[1])

        def bilinear(iv, s):  # bilinear x2 to stride s
            return (iv[0] - 2 * s, iv[1] + s)

        def union(*ivs):
            return (min(i[0] for i in ivs), max(i[1] for i in ivs))

        iv = (0, 0)
        for _ in range(1 + 2 * self.config["ext_blocks"]):
            iv = conv(iv, 1)
        skips = [iv]
        for l in range(self.levels - 1):
            iv = conv(conv(pool(iv, 1 << l), 2 << l), 2 << l)
            skips.append(iv)
        logits = [None] * self.levels
        logits[-1] = iv
        for l in reversed(range(self.levels - 1)):
            s = 1 << l
            if l == 0 and self.lean0:  # 1x1 convs, then one 3x3
                iv = conv(union(nearest(iv, s), skips[0]), s)
            else:
                iv = conv(conv(union(nearest(iv, s), skips[l]), s), s)
            logits[l] = iv
        k = self.kernel_size // 2
        pyramid = [(0, 0)]
        for l in range(self.levels - 1):
            pyramid.append(pool(pyramid[-1], 1 << l))
        filt = [union(logits[l], (pyramid[l][0] - k * (1 << l), pyramid[l][1] + k * (1 << l)))
                for l in range(self.levels)]
        out = filt[-1]
        for l in reversed(range(self.levels - 1)):
            s = 1 << l
            out = union(filt[l], logits[l], bilinear(out, s), bilinear(pool(filt[l], s), s))
        return max(-out[0], out[1])

    def flops_per_pixel(self) -> int:
        """2 x multiply-adds of every conv per full-resolution pixel (both components)."""
        macs = 0.0

        def visit(module: nn.Module, scale: float) -> None:
            nonlocal macs
            for m in module.modules():
                if isinstance(m, nn.Conv2d):
                    kh, kw = m.kernel_size
                    macs += m.in_channels * m.out_channels * kh * kw / scale

        visit(self.color_extractor, 1)
        visit(self.feature_extractor, 1)
        for l in range(self.levels - 1):
            visit(self.encoder[l], 4 ** (l + 1))
            if l == 0 and self.lean0:  # its 1x1 conv of the level below runs there
                visit(self.decoder[0].up, 4)
                visit(self.decoder[0].skip, 1)
                visit(self.decoder[0].mid, 1)
            else:
                visit(self.decoder[l], 4 ** l)
            visit(self.blend_heads[l], 4 ** l)
        for l in range(len(self.gain_heads)):
            visit(self.gain_heads[l], 4 ** l)
        for l in range(self.levels):
            visit(self.kernel_heads[l], 4 ** l)
        return int(round(2 * macs))

    def param_count(self) -> int:
        return sum(p.numel() for p in self.parameters())

    def description(self) -> str:
        c = self.config
        return (
            f"msnet: color ({COMPONENT_COUNT}x{COLOR_CHANNELS}) and feature ({self.in_features}) extractors "
            f"width {c['ext_width']}, {c['ext_blocks']} residual block(s); U-Net {self.levels} levels, "
            f"encoder {c['enc']}, decoder {c['dec']}" + (" (level 0 lean)" if self.lean0 else "")
            + f"; {c['kernel_size']}x{c['kernel_size']} kernels per level "
            f"and blends; params {self.param_count()}, receptive radius {self.receptive_radius()}"
            + ("; specular pyramid of linear means" if self.specular_pyramid == "linear" else "")
            + ("; detail gains" if self.detail_gain else "")
        )


def add_shape_arguments(parser) -> None:
    """The command-line options of an `MSNet`'s shape (defaults: `DEFAULT`)."""
    parser.add_argument("--ext-width", type=int, default=DEFAULT["ext_width"])
    parser.add_argument("--ext-blocks", type=int, default=DEFAULT["ext_blocks"])
    parser.add_argument("--enc", default=",".join(map(str, DEFAULT["enc"])), help="encoder widths, levels 1 … L-1")
    parser.add_argument("--dec", default=",".join(map(str, DEFAULT["dec"])), help="decoder widths, levels 0 … L-2")
    parser.add_argument("--kernel-size", type=int, default=DEFAULT["kernel_size"])
    parser.add_argument("--levels", type=int, default=DEFAULT["levels"])
    parser.add_argument("--specular-pyramid", choices=PYRAMIDS, default=None,
                        help="how the reconstruction's specular pyramid averages: `linear` (ln(1 + the mean of s), "
                             f"the default for a new network: {DEFAULT['specular_pyramid']}) or `log` (the mean of "
                             "ln(1 + s), networks before 2026-11-29); a fine-tune keeps its checkpoint's unless given")
    parser.add_argument("--lean0", action="store_true",
                        help="decoder level 0 as 1x1 convs of the level below and of the skip, then one 3x3 conv "
                             "(MSNet.lean0): a cheaper network; with --reshape its level 0 starts new")
    parser.add_argument("--detail-gain", action="store_true",
                        help="per-pixel gains on each pyramid level's own detail (MSNet.add_detail_gain); a fine-tune "
                             "of a checkpoint without them adds them, starting near the checkpoint")


def from_arguments(a, in_features: int) -> MSNet:
    """A fresh `MSNet` of the shape given by `add_shape_arguments`' options."""
    return MSNet(in_features=in_features, ext_width=a.ext_width, ext_blocks=a.ext_blocks,
                 enc=[int(x) for x in a.enc.split(",")], dec=[int(x) for x in a.dec.split(",")],
                 kernel_size=a.kernel_size, levels=a.levels,
                 specular_pyramid=a.specular_pyramid or DEFAULT["specular_pyramid"],
                 detail_gain=getattr(a, "detail_gain", False), lean0=getattr(a, "lean0", False))


@torch.no_grad()
def transplant(source: MSNet, target: MSNet) -> list[str]:
    """Copies `source`'s weights into `target`, a network of the same inputs, levels,
    kernel size and encoder but possibly fewer extractor blocks or narrower decoder levels:
    the start of a fine-tuning into a cheaper shape. Extractor blocks beyond the target's
    are dropped (a residual block left out is the identity plus what fine-tuning must make
    up); a narrowed decoder level keeps the channels that carry the most weight, an output
    channel's importance being the norm of its weights times the norm of what reads it.
    Returns what was not copied unchanged, one line each."""
    s, t = source.config, target.config
    for key in ("in_features", "levels", "kernel_size", "enc", "ext_width"):
        if s[key] != t[key]:
            raise ValueError(f"transplant needs the same {key}: source {s[key]}, target {t[key]}")
    if t["ext_blocks"] > s["ext_blocks"] or any(b > a for a, b in zip(s["dec"], t["dec"])):
        raise ValueError(f"transplant only removes: source ext_blocks {s['ext_blocks']} dec {s['dec']}, "
                         f"target ext_blocks {t['ext_blocks']} dec {t['dec']}")
    notes = []
    for name in ("color_extractor", "feature_extractor"):
        src, dst = getattr(source, name), getattr(target, name)
        dst.load_state_dict({k: v for k, v in src.state_dict().items() if int(k.split(".")[0]) < len(dst)})
        if len(src) > len(dst):
            notes.append(f"{name}: residual blocks {len(src) - 1} -> {len(dst) - 1}")
    target.encoder.load_state_dict(source.encoder.state_dict())
    levels = source.levels
    # `keep[l]`: the channels of decoder level l's output kept (all of the coarsest level's).
    keep: list[torch.Tensor | None] = [None] * levels

    def norms(w: torch.Tensor, dim: int) -> torch.Tensor:
        return w.pow(2).sum(dim=[d for d in range(w.dim()) if d != dim]).sqrt()

    if source.lean0 and not target.lean0:
        raise ValueError("transplant only removes: the source's decoder level 0 is lean, the target's is not")
    # The per-level heads that both networks have (the detail gains only where both have them).
    heads_copied = ("kernel_heads", "blend_heads", "gain_heads")[: 3 if source.detail_gain and target.detail_gain else 2]
    for l in reversed(range(levels - 1)):
        if l == 0 and target.lean0:
            sp, tp = source.decoder[0], target.decoder[0]
            if not source.lean0:
                notes.append("decoder level 0: lean, new")
                break
            if tp.mid.out_channels != sp.mid.out_channels:
                raise ValueError(f"transplant keeps a lean level 0's width: source {sp.mid.out_channels}, "
                                 f"target {tp.mid.out_channels}")
            # Its 1x1 conv of level 1 reads that level's kept channels.
            cols = keep[1] if keep[1] is not None else torch.arange(sp.up.in_channels)
            tp.load_state_dict({k: v for k, v in sp.state_dict().items() if k != "up.weight"}, strict=False)
            tp.up.weight.copy_(sp.up.weight[:, cols])
            for heads in heads_copied:
                getattr(target, heads)[0].load_state_dict(getattr(source, heads)[0].state_dict())
            break
        sp, tp = source.decoder[l], target.decoder[l]
        a, b = sp[0].weight, sp[2].weight  # conv_a: [dec, below + skip, 3, 3], conv_b: [dec, dec, 3, 3]
        # input columns of conv_a: the level below's output (its kept channels), then the skip
        n_below = source.decoder[l + 1][2].out_channels if l + 1 < levels - 1 else source.encoder[-1][2].out_channels
        cols = torch.arange(a.shape[1])
        if keep[l + 1] is not None:
            cols = torch.cat([keep[l + 1], torch.arange(n_below, a.shape[1])])
        width = tp[0].out_channels
        mid = torch.argsort(norms(a, 0) * norms(b, 1), descending=True)[:width].sort().values
        readers = norms(source.kernel_heads[l].weight, 1).pow(2) + norms(source.blend_heads[l].weight, 1).pow(2)
        if l == 1 and source.lean0:
            readers = readers + norms(source.decoder[0].up.weight, 1).pow(2)
        elif l > 0:
            readers = readers + norms(source.decoder[l - 1][0].weight[:, : b.shape[0]], 1).pow(2)
        out = torch.argsort(norms(b, 0) * readers.sqrt(), descending=True)[:width].sort().values
        tp[0].weight.copy_(a[mid][:, cols])
        tp[0].bias.copy_(sp[0].bias[mid])
        tp[2].weight.copy_(b[out][:, mid])
        tp[2].bias.copy_(sp[2].bias[out])
        for heads in heads_copied:
            sh, th = getattr(source, heads)[l], getattr(target, heads)[l]
            th.weight.copy_(sh.weight[:, out])
            th.bias.copy_(sh.bias)
        if width < a.shape[0]:
            keep[l] = out
            notes.append(f"decoder level {l}: width {a.shape[0]} -> {width}")
    target.kernel_heads[-1].load_state_dict(source.kernel_heads[-1].state_dict())
    return notes


def pad_to_multiple(x: torch.Tensor, m: int) -> torch.Tensor:
    """Replicates the last row and column of `x [N,C,H,W]` up to multiples of `m` (as the
    engine does before inference)."""
    h, w = x.shape[-2:]
    ph, pw = (-h) % m, (-w) % m
    if ph == 0 and pw == 0:
        return x
    return F.pad(x, (0, pw, 0, ph), mode="replicate")


__all__ = ["DEFAULT", "Lean0", "MSNet", "add_shape_arguments", "from_arguments", "pad_to_multiple", "transplant"]
