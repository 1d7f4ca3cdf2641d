"""Differentiable kernel reconstruction and inverse transforms (frame-layout.md).

`apply_kernel` turns the network's 441 logits per pixel into a normalised 21x21 kernel
(softmax over the taps) and filters the preprocessed color with it:

    out(x, y) = sum_k w_k(x, y) * color(clamp(x + dx), clamp(y + dy)),
    k = (dy + 10) * 21 + (dx + 10),  dy the row offset, dx the column offset,

with edge replication at the frame border, exactly as the engine does. The 441 shifted
copies of the color are never materialised at once: the loop runs over the 21 kernel
rows, and for each row `Tensor.unfold` gives a strided view of the 21 horizontal taps,
so the extra memory is one `[N, C, H, W, 21]` product per row (freed after the row
unless autograd keeps it for the backward pass).

`inverse_diffuse` / `inverse_specular` undo the preprocessing of the two components and
`reconstruct` assembles the denoised frame from both networks' logits.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
import torch.nn.functional as F

from .contract import EPS, KERNEL_RADIUS, KERNEL_SIZE, KERNEL_TAPS


def apply_kernel(logits: torch.Tensor, color: torch.Tensor) -> torch.Tensor:
    """Filter `color [N, C, H, W]` with the kernels `softmax(logits [N, 441, H, W])`."""
    if logits.dim() != 4 or logits.shape[1] != KERNEL_TAPS:
        raise ValueError(f"logits must be [N, {KERNEL_TAPS}, H, W], got {tuple(logits.shape)}")
    n, _, h, w = logits.shape
    if color.dim() != 4 or color.shape[0] != n or color.shape[2:] != logits.shape[2:]:
        raise ValueError(
            f"color must be [N, C, H, W] matching logits {tuple(logits.shape)}, "
            f"got {tuple(color.shape)}"
        )
    if not color.requires_grad:
        return _KernelFilter.apply(logits, color)
    r, k = KERNEL_RADIUS, KERNEL_SIZE
    weights = torch.softmax(logits, dim=1)
    padded = F.pad(color, (r, r, r, r), mode="replicate")  # [N, C, H+2r, W+2r]
    out = torch.zeros_like(color)
    for row in range(k):  # dy = row - r
        window = padded[:, :, row : row + h, :].unfold(3, k, 1)  # [N, C, H, W, 21 (dx)]
        wrow = weights[:, row * k : (row + 1) * k].permute(0, 2, 3, 1).unsqueeze(1)
        out = out + (window * wrow).sum(-1)
    return out


class _KernelFilter(torch.autograd.Function):
    """`apply_kernel` for a color that needs no gradient (the training case), with the
    backward pass written out: with `w = softmax(l)` and `out = sum_k w_k c_k`
    (`c_k` the color shifted by tap k), `dL/dl_k = w_k (g . c_k - g . out)`. Tap by tap,
    nothing of size 441 x C x H x W is kept for autograd; about 3x faster than letting
    autograd differentiate the loop above."""

    @staticmethod
    def forward(ctx, logits, color):
        h, w = logits.shape[2:]
        r, k = KERNEL_RADIUS, KERNEL_SIZE
        weights = torch.softmax(logits, dim=1)
        padded = F.pad(color, (r, r, r, r), mode="replicate")
        out = torch.zeros_like(color)
        for tap in range(k * k):
            dy, dx = divmod(tap, k)
            out.addcmul_(weights[:, tap : tap + 1], padded[:, :, dy : dy + h, dx : dx + w])
        ctx.save_for_backward(weights, padded, out)
        return out

    @staticmethod
    def backward(ctx, grad_out):
        weights, padded, out = ctx.saved_tensors
        h, w = weights.shape[2:]
        k = KERNEL_SIZE
        dots = torch.empty_like(weights)
        for tap in range(k * k):
            dy, dx = divmod(tap, k)
            dots[:, tap] = (grad_out * padded[:, :, dy : dy + h, dx : dx + w]).sum(1)
        return weights * (dots - (grad_out * out).sum(1, keepdim=True)), None


def inverse_diffuse(x: torch.Tensor, albedo: torch.Tensor) -> torch.Tensor:
    """Undo d' = d / (a + EPS) (negative albedos taken as 0, as the engine does)."""
    return x * (albedo.clamp(min=0) + EPS)


def inverse_specular(x: torch.Tensor) -> torch.Tensor:
    """Undo s' = ln(1 + s)."""
    return torch.exp(x) - 1.0


class Reconstruction(NamedTuple):
    diffuse_pre: torch.Tensor  # filtered d' (preprocessed domain)
    specular_pre: torch.Tensor  # filtered s' (preprocessed domain)
    diffuse: torch.Tensor  # d_hat = diffuse_pre * (a + EPS)
    specular: torch.Tensor  # s_hat = exp(specular_pre) - 1
    total: torch.Tensor  # d_hat + s_hat


def reconstruct(
    diffuse_logits: torch.Tensor,
    specular_logits: torch.Tensor,
    diffuse_color: torch.Tensor,
    specular_color: torch.Tensor,
    albedo: torch.Tensor,
) -> Reconstruction:
    """Denoised frame from both components' logits.

    `diffuse_color` / `specular_color` are the networks' `color` inputs (`[N, 10, H, W]`,
    or just the first 3 channels); channels 0-2 are the preprocessed noisy color.
    `albedo` is `[N, 3, H, W]`, the raw albedo used by the diffuse transform.
    """
    d_pre = apply_kernel(diffuse_logits, diffuse_color[:, :3])
    s_pre = apply_kernel(specular_logits, specular_color[:, :3])
    d = inverse_diffuse(d_pre, albedo)
    s = inverse_specular(s_pre)
    return Reconstruction(d_pre, s_pre, d, s, d + s)
