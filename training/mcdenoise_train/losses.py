"""Losses and image metrics for training, in PyTorch.

`smape` is the paper's pixel loss (Lin et al. 2020, eq. 7); `relmse` and `dssim` mirror
the engine's image metrics (src/metrics.rs: RelMSE with 0.01 in the denominator, SSIM of
the [0, 1]-clamped channels with an 11-tap Gaussian of σ 1.5 over the valid region), so
that checkpoint selection ranks networks as `make eval` does. `log_l1` is the contract-v1
trainer's (train.py) log-domain L1 term, `ms_loss` the contract-v2 training objective.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

SMAPE_EPS = 1e-2
# RelMSE's denominator r² + RELMSE_EPS (src/metrics.rs).
RELMSE_EPS = 0.01


def smape(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Symmetric mean absolute percentage error; ε = 1e-2 keeps dark pixels from dominating."""
    return (2.0 * (x - y).abs() / (x.abs() + y.abs() + SMAPE_EPS)).mean()


def relmse(x: torch.Tensor, r: torch.Tensor) -> torch.Tensor:
    """Relative MSE, (x - r)² / (r² + 0.01) averaged; works on numpy arrays as well."""
    return ((x - r) ** 2 / (r * r + RELMSE_EPS)).mean()


def relmse_huber(x: torch.Tensor, r: torch.Tensor, delta: float = 10.0) -> torch.Tensor:
    """RelMSE as a loss: the Huber function of the normalised error e = (x − r) / √(r² + 0.01),
    e² (the metric's per-pixel term) where |e| < δ and linear beyond, averaged.

    The metric's mean is made by a few pixels: beside an emitter's edge a kernel that gives
    the emitter a small weight lifts a dark pixel to ten times its value, e² ≈ 100, and 15
    such pixels of 150,000 carry half a frame's RelMSE. SMAPE saturates there and L1 of
    log(1 + x) weighs them like any other pixel; e² weighs them by their error. Beyond δ
    (a pixel δ times its own scale away) the gradient stops growing, so that a reference's
    stray firefly cannot swamp a batch.
    """
    e = ((x - r) / torch.sqrt(r * r + RELMSE_EPS)).abs()
    return torch.where(e < delta, e * e, 2.0 * delta * e - delta * delta).mean()


def log_l1(x: torch.Tensor, y: torch.Tensor, component: str) -> torch.Tensor:
    """L1 in a log domain: the specular tensors already are (ln(1 + s)); the diffuse
    irradiance is taken to ln(1 + max(x, 0)) first.

    SMAPE alone saturates: where the target is ~0 (a diffuse wall has no specular, a
    shadow little irradiance) and the output is large, |x - y| / (|x| + |y| + eps) is ~1
    whatever x is, so its gradient vanishes and a kernel that leaks a bright light into
    its neighbours is never corrected. L1 keeps a constant gradient there.
    """
    if component == "diffuse":
        x, y = torch.log1p(x.clamp_min(0)), torch.log1p(y.clamp_min(0))
    return (x - y).abs().mean()


def _gaussian(device, dtype, radius: int = 5, sigma: float = 1.5) -> torch.Tensor:
    t = torch.arange(-radius, radius + 1, device=device, dtype=dtype)
    g = torch.exp(-(t * t) / (2 * sigma * sigma))
    return g / g.sum()


def ssim_map(x: torch.Tensor, r: torch.Tensor) -> torch.Tensor:
    """Per-pixel SSIM of [N, C, H, W] images clamped to [0, 1] (valid region)."""
    luminance, contrast_structure = _ssim_terms(x, r)
    return luminance * contrast_structure


def _ssim_terms(x: torch.Tensor, r: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """SSIM's luminance term and its contrast-structure term, per pixel (valid region), of
    images clamped to [0, 1]."""
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    x, r = x.clamp(0, 1), r.clamp(0, 1)
    c = x.shape[1]
    g = _gaussian(x.device, x.dtype)
    gh = g.view(1, 1, 1, -1).expand(c, 1, 1, -1)
    gv = g.view(1, 1, -1, 1).expand(c, 1, -1, 1)

    def blur(t):
        return F.conv2d(F.conv2d(t, gh, groups=c), gv, groups=c)

    ma, mb = blur(x), blur(r)
    va, vb, cov = blur(x * x) - ma * ma, blur(r * r) - mb * mb, blur(x * r) - ma * mb
    return (2 * ma * mb + c1) / (ma * ma + mb * mb + c1), (2 * cov + c2) / (va + vb + c2)


def dssim(x: torch.Tensor, r: torch.Tensor) -> torch.Tensor:
    return 1.0 - ssim_map(x, r).mean()


# Wang, Simoncelli and Bovik 2003: the exponents of the five scales, finest first.
MS_SSIM_WEIGHTS = (0.0448, 0.2856, 0.3001, 0.2363, 0.1333)


def ms_ssim(x: torch.Tensor, r: torch.Tensor) -> torch.Tensor:
    """Multi-scale SSIM of [N, C, H, W] images clamped to [0, 1], one value per image: the
    contrast-structure term at each scale but the coarsest, the whole SSIM there, each to its
    exponent (MS_SSIM_WEIGHTS), halving the images by 2x2 means between scales. Images too
    small for five scales (the 11-pixel window at the coarsest) use the scales they have,
    their exponents renormalised. Each scale's mean is floored at 1e-4, so that a fractional
    power stays real."""
    if min(x.shape[-2:]) < 11:
        raise ValueError(f"ms_ssim needs images of at least 11x11, got {tuple(x.shape[-2:])}")
    scales = 1
    while scales < len(MS_SSIM_WEIGHTS) and min(x.shape[-2:]) >> scales >= 11:
        scales += 1
    # Clamped before the first 2x2 mean, as the metric sees the image (_ssim_terms clamps too).
    x, r = x.clamp(0, 1), r.clamp(0, 1)
    w = torch.tensor(MS_SSIM_WEIGHTS[:scales], device=x.device, dtype=x.dtype)
    w = w / w.sum()
    out = torch.ones(x.shape[0], device=x.device, dtype=x.dtype)
    for i in range(scales):
        luminance, cs = _ssim_terms(x, r)
        term = cs if i < scales - 1 else luminance * cs
        out = out * term.mean((1, 2, 3)).clamp_min(1e-4) ** w[i]
        x, r = F.avg_pool2d(x, 2), F.avg_pool2d(r, 2)
    return out


def tonemap(x: torch.Tensor) -> torch.Tensor:
    """log(1 + x) of the non-negative part: the HDR transfer function of the color loss."""
    return torch.log1p(x.clamp(min=0))


def level_smape(rec, b: dict, specular_pyramid: str) -> torch.Tensor:
    """Mean over both components and every coarser pyramid level l ≥ 1 of the SMAPE between
    the reconstruction of levels l and below (`recon_ms.component_levels`) and the target
    averaged to that level the way the network's pyramid averages its color
    (`specular_pyramid`): each level is held to be a denoised image at its own scale, whether
    or not the blend above it passes it on yet."""
    from .recon_ms import color_pyramid

    levels = len(rec.diffuse_levels) + 1
    targets = (color_pyramid(b["diffuse_target"], levels, "log")[1:],
               color_pyramid(b["specular_target"], levels, specular_pyramid)[1:])
    terms = [smape(o, t) for outs, tgts in zip((rec.diffuse_levels, rec.specular_levels), targets)
             for o, t in zip(outs, tgts)]
    if not terms:
        raise ValueError("level_smape needs a multi-scale reconstruction (recon_ms.reconstruct) of 2 levels or more")
    return sum(terms) / len(terms)


def ms_loss(rec, b: dict, l1_weight: float = 1.0, ssim_weight: float = 0.0, perceptual=None,
            perceptual_weight: float = 0.0, relmse_weight: float = 0.0, level_weight: float = 0.0,
            specular_pyramid: str = "log", msssim_weight: float = 0.0) -> tuple[torch.Tensor, dict[str, float]]:
    """SMAPE of both components in their preprocessed domains, L1 of the tonemapped final
    color, optionally DSSIM of the final color, 1 − its MS-SSIM, the perceptual loss on it,
    RelMSE (`relmse_huber`) of it and `level_smape` of the coarser levels (the network's
    `specular_pyramid`)."""
    d = smape(rec.diffuse_pre, b["diffuse_target"])
    s = smape(rec.specular_pre, b["specular_target"])
    loss = d + s
    parts = {"smape_diffuse": float(d.detach()), "smape_specular": float(s.detach())}
    if l1_weight > 0:
        l1 = (tonemap(rec.total) - tonemap(b["reference"])).abs().mean()
        parts["l1"] = float(l1.detach())
        loss = loss + l1_weight * l1
    if ssim_weight > 0:
        ds = dssim(rec.total, b["reference"])
        parts["dssim"] = float(ds.detach())
        loss = loss + ssim_weight * ds
    if msssim_weight > 0:
        ms = 1.0 - ms_ssim(rec.total, b["reference"]).mean()
        parts["msssim"] = float(ms.detach())
        loss = loss + msssim_weight * ms
    if relmse_weight > 0:
        rm = relmse_huber(rec.total, b["reference"])
        parts["relmse"] = float(rm.detach())
        loss = loss + relmse_weight * rm
    if perceptual is not None and perceptual_weight > 0:
        p = perceptual(tonemap(rec.total), tonemap(b["reference"]))
        parts["perceptual"] = float(p.detach())
        loss = loss + perceptual_weight * p
    if level_weight > 0:
        lv = level_smape(rec, b, specular_pyramid)
        parts["levels"] = float(lv.detach())
        loss = loss + level_weight * lv
    return loss, parts


__all__ = ["dssim", "level_smape", "log_l1", "ms_loss", "ms_ssim", "relmse", "relmse_huber", "smape", "ssim_map", "tonemap"]
