"""Multi-scale kernel reconstruction (contract v2), differentiable; the reference the
engine's Rust implementation is tested against.

Per component, with `c` the preprocessed noisy color `[N, 3, H, W]`:

    c_0 = c,  c_{l+1} = avgpool2x2(c_l)
    f_l = sum_t softmax(kernel_l)_t * c_l(x + dx_t, y + dy_t)      (edge replication)
    o_{L-1} = f_{L-1};  o_l = f_l + sigmoid(blend_l) * (up(o_{l+1}) - up(avgpool2x2(f_l)))

With detail gains (`MSNet(detail_gain=True)`, graph outputs `gain_<l>`), the level's own
detail `f_l - up(avgpool2x2(f_l))` is scaled by `sigmoid(gain_l)`:

    o_l = m_l + sigmoid(gain_l) * (f_l - m_l) + sigmoid(blend_l) * (up(o_{l+1}) - m_l),  m_l = up(avgpool2x2(f_l))

`up` is bilinear x2 with half-pixel centres (`align_corners=False`). `reconstruct`
assembles both components and the final color with v1's inverse transforms.

The specular's color is ln(1 + s). With `specular_pyramid="linear"` (metadata
`mcdenoise.specular_pyramid`) its levels average s, not ln(1 + s):
`c_{l+1} = ln(1 + avgpool2x2(e^{c_l} - 1))`. The mean of a log is below the log of the mean
wherever the samples spread (Jensen), so the log pyramid's coarse levels are darker than the
color they stand for; at 4 spp on a defocused glossy wall the shipped network's specular
came out 9 % darker than the reference (docs/training.md, "The specular pyramid").
"""

from __future__ import annotations

from typing import NamedTuple, Sequence

import torch
import torch.nn.functional as F

from .recon import inverse_diffuse, inverse_specular


def filter_k(logits: torch.Tensor, color: torch.Tensor) -> torch.Tensor:
    """`color [N,C,H,W]` filtered with the per-pixel kernels `softmax(logits [N,k²,H,W])`."""
    taps = logits.shape[1]
    k = int(round(taps ** 0.5))
    if k * k != taps or k % 2 == 0:
        raise ValueError(f"logits must have k² channels for an odd k, got {taps}")
    if not color.requires_grad:
        return _FilterK.apply(logits.float(), color)
    r = k // 2
    h, w = logits.shape[2:]
    weights = torch.softmax(logits.float(), dim=1)
    padded = F.pad(color, (r, r, r, r), mode="replicate")
    out = torch.zeros_like(color)
    for t in range(taps):
        dy, dx = divmod(t, k)
        out = out + weights[:, t : t + 1] * padded[:, :, dy : dy + h, dx : dx + w]
    return out


class _FilterK(torch.autograd.Function):
    """`filter_k` for a color that needs no gradient (the training case: the pyramid is
    made of inputs), with the backward written out as in `recon._KernelFilter`:
    `dL/dl_t = w_t (g . c_t - g . out)`; nothing of size taps x C x H x W is kept."""

    @staticmethod
    def forward(ctx, logits, color):
        taps = logits.shape[1]
        k = int(round(taps ** 0.5))
        r = k // 2
        h, w = logits.shape[2:]
        weights = torch.softmax(logits, dim=1)
        padded = F.pad(color, (r, r, r, r), mode="replicate")
        out = torch.zeros_like(color)
        for t in range(taps):
            dy, dx = divmod(t, k)
            out.addcmul_(weights[:, t : t + 1], padded[:, :, dy : dy + h, dx : dx + w])
        ctx.save_for_backward(weights, padded, out)
        ctx.k = k
        return out

    @staticmethod
    def backward(ctx, grad_out):
        weights, padded, out = ctx.saved_tensors
        k = ctx.k
        h, w = weights.shape[2:]
        dots = torch.empty_like(weights)
        for t in range(k * k):
            dy, dx = divmod(t, k)
            dots[:, t] = (grad_out * padded[:, :, dy : dy + h, dx : dx + w]).sum(1)
        return weights * (dots - (grad_out * out).sum(1, keepdim=True)), None


def up2(x: torch.Tensor) -> torch.Tensor:
    return F.interpolate(x, scale_factor=2.0, mode="bilinear", align_corners=False)


def filter_plain(logits: torch.Tensor, color: torch.Tensor) -> torch.Tensor:
    """`filter_k` as plain tensor operators (softmax, edge padding, k² shifted products),
    whatever `color` needs: the form an ONNX export traces (`export_ms --recon`; the tap
    count is static, the sides stay dynamic)."""
    taps = int(logits.shape[1])
    k = int(round(taps ** 0.5))
    r = k // 2
    h, w = logits.shape[2], logits.shape[3]
    weights = torch.softmax(logits, dim=1)
    padded = F.pad(color, (r, r, r, r), mode="replicate")
    out = weights[:, 0:1] * padded[:, :, 0:h, 0:w]
    for t in range(1, taps):
        dy, dx = divmod(t, k)
        out = out + weights[:, t : t + 1] * padded[:, :, dy : dy + h, dx : dx + w]
    return out


#: The largest ln(1 + s) the linear pyramid takes (s = 5.5e34): e^x stays finite in float32
#: (the engine clamps the same; real frames never come near it).
LINEAR_PYRAMID_MAX = 80.0

#: How a component's pyramid averages its color (metadata `mcdenoise.specular_pyramid` for
#: the specular; the diffuse is always `log`, i.e. averaged as it is given).
PYRAMIDS = ("log", "linear")


def color_pyramid(color: torch.Tensor, levels: int, pyramid: str = "log") -> list[torch.Tensor]:
    """`color` and its `levels - 1` coarser levels: 2x2 means of the values as given
    (`log`), or, for a color holding ln(1 + s), ln(1 + the 2x2 means of s) (`linear`)."""
    if pyramid not in PYRAMIDS:
        raise ValueError(f"pyramid {pyramid!r}: expected one of {PYRAMIDS}")
    out = [color]
    if pyramid == "log":
        for _ in range(levels - 1):
            out.append(F.avg_pool2d(out[-1], 2))
        return out
    # ONNX has no expm1: an export writes e^x - 1 (an absolute difference below 1e-7 here).
    x = color.clamp(max=LINEAR_PYRAMID_MAX)
    linear = torch.exp(x) - 1 if torch.onnx.is_in_onnx_export() else torch.expm1(x)
    for _ in range(levels - 1):
        linear = F.avg_pool2d(linear, 2)
        out.append(torch.log1p(linear))
    return out


def component_levels(kernels: Sequence[torch.Tensor], blends: Sequence[torch.Tensor], color: torch.Tensor,
                     filter=filter_k, pyramid: str = "log",
                     gains: Sequence[torch.Tensor] | None = None) -> list[torch.Tensor]:
    """One component at every level: `[o_0, o_1, …, o_{L-1}]`, `o_l` the reconstruction of
    levels l and coarser at 1/2^l of the resolution (`o_0` is the output); arguments as in
    `reconstruct_component`."""
    levels = len(kernels)
    if len(blends) != levels - 1:
        raise ValueError(f"{levels} kernel levels need {levels - 1} blends, got {len(blends)}")
    if gains is not None and len(gains) != levels - 1:
        raise ValueError(f"{levels} kernel levels need {levels - 1} detail gains, got {len(gains)}")
    pyramid = color_pyramid(color, levels, pyramid)
    filtered = [filter(kernels[l], pyramid[l]) for l in range(levels)]
    outs = [filtered[-1]]
    for l in reversed(range(levels - 1)):
        a = torch.sigmoid(blends[l].float())
        f = filtered[l]
        m = up2(F.avg_pool2d(f, 2))
        if gains is None:
            outs.append(f + a * (up2(outs[-1]) - m))
        else:
            outs.append(m + torch.sigmoid(gains[l].float()) * (f - m) + a * (up2(outs[-1]) - m))
    return outs[::-1]


def reconstruct_component(kernels: Sequence[torch.Tensor], blends: Sequence[torch.Tensor], color: torch.Tensor,
                          filter=filter_k, pyramid: str = "log",
                          gains: Sequence[torch.Tensor] | None = None) -> torch.Tensor:
    """One component: `kernels[l] [N,k²,H/2^l,W/2^l]`, `blends[l] [N,1,...]` (logits),
    `gains[l] [N,1,...]` (detail-gain logits, or None for a network without them);
    `pyramid` as in `color_pyramid`."""
    return component_levels(kernels, blends, color, filter, pyramid, gains)[0]


def split_outputs(outputs: Sequence[torch.Tensor], levels: int):
    """The network's outputs as per-component lists: ({comp: kernels}, {comp: blends},
    {comp: detail gains} or None when the network has none)."""
    kernels, blends, gains = outputs[:levels], outputs[levels:2 * levels - 1], outputs[2 * levels - 1:]
    if len(outputs) not in (2 * levels - 1, 3 * levels - 2):
        raise ValueError(f"{levels} levels give {2 * levels - 1} or {3 * levels - 2} outputs, got {len(outputs)}")
    taps = kernels[0].shape[1] // 2
    k = {"diffuse": [t[:, :taps] for t in kernels], "specular": [t[:, taps:] for t in kernels]}
    b = {"diffuse": [t[:, 0:1] for t in blends], "specular": [t[:, 1:2] for t in blends]}
    g = {"diffuse": [t[:, 0:1] for t in gains], "specular": [t[:, 1:2] for t in gains]} if gains else None
    return k, b, g


class Reconstruction(NamedTuple):
    diffuse_pre: torch.Tensor
    specular_pre: torch.Tensor
    diffuse: torch.Tensor
    specular: torch.Tensor
    total: torch.Tensor
    #: Each component's coarser levels `o_1 … o_{L-1}` (`component_levels`), preprocessed domains.
    diffuse_levels: tuple = ()
    specular_levels: tuple = ()


def reconstruct(outputs: Sequence[torch.Tensor], levels: int, diffuse_color: torch.Tensor,
                specular_color: torch.Tensor, albedo: torch.Tensor, *, specular_pyramid: str) -> Reconstruction:
    """Both components and the final color from the network's outputs; `specular_pyramid` is
    the network's (`MSNet.specular_pyramid`)."""
    k, b, g = split_outputs(outputs, levels)
    g = g or {"diffuse": None, "specular": None}
    d_levels = component_levels(k["diffuse"], b["diffuse"], diffuse_color[:, :3].float(), gains=g["diffuse"])
    s_levels = component_levels(k["specular"], b["specular"], specular_color[:, :3].float(),
                                pyramid=specular_pyramid, gains=g["specular"])
    d = inverse_diffuse(d_levels[0], albedo)
    s = inverse_specular(s_levels[0].clamp(max=80.0))
    return Reconstruction(d_levels[0], s_levels[0], d, s, d + s, tuple(d_levels[1:]), tuple(s_levels[1:]))


__all__ = ["PYRAMIDS", "Reconstruction", "color_pyramid", "component_levels", "filter_k", "filter_plain", "reconstruct", "reconstruct_component", "split_outputs", "up2"]
