"""The engine's preprocessing (src/engine/preprocess.rs) in PyTorch, batched, on any device.

Training draws crops of raw frames, augments them (flips, transposes, colour permutation,
exposure, injected fireflies) and preprocesses them here, on the GPU when there is one;
`tests/test_preprocess.py` checks the result against `mcdenoise preprocess` to float
rounding, so training and serving still see the same tensors.

Raw frames are `[N, RAW_CHANNELS, H, W]` tensors with the channels of `RAW` in order (the
variance buffers as one channel each, as the data generator writes them), and the
per-frame statistics `depth_max` and `covariance_max` `[N]` taken over the whole frame
before cropping (the engine scales depth and covariance by them).
"""

from __future__ import annotations

import numpy as np
import torch

from .contract import EPS, select_nocov

LUMINANCE = (0.2126, 0.7152, 0.0722)

RAW = (
    "diffuse.R", "diffuse.G", "diffuse.B",
    "specular.R", "specular.G", "specular.B",
    "albedo.R", "albedo.G", "albedo.B",
    "normal.R", "normal.G", "normal.B",
    "depth", "covariance",
    "diffuseVariance", "specularVariance", "albedoVariance", "normalVariance", "depthVariance",
    "covarianceVariance",
)
RAW_INDEX = {n: i for i, n in enumerate(RAW)}
DIFFUSE, SPECULAR, ALBEDO, NORMAL = slice(0, 3), slice(3, 6), slice(6, 9), slice(9, 12)
DEPTH, COV = 12, 13
# Depths at or above this are a renderer's "infinitely far", read as 0 ("no hit"), as the
# engine does (`NO_HIT_DEPTH` in src/frame/layout.rs).
NO_HIT_DEPTH = 1e9
# Depths more than this many times the median of a frame's depths above 0 are "far", read as
# 0 with their variance, and the depth scale is the largest depth that is not far; scaled
# depth variances are saturated at DEPTH_VARIANCE_LIMIT (`FAR_DEPTH_RATIO`,
# `DEPTH_VARIANCE_LIMIT` and `depth_scale` in src/engine/preprocess.rs).
FAR_DEPTH_RATIO = 16.0
DEPTH_VARIANCE_LIMIT = 1.0
VAR = {"diffuse": 14, "specular": 15, "albedo": 16, "normal": 17, "depth": 18, "covariance": 19}

# Frame channel names (as written by the data generator) of each raw channel.
FILE_NAMES = {
    **{f"{b}.{c}": f"{b}.{c}" for b in ("diffuse", "specular", "albedo", "normal") for c in "RGB"},
    "depth": "depth.Z", "covariance": "covariance",
    **{f"{b}Variance": f"{b}Variance.Z" for b in ("diffuse", "specular", "albedo", "normal", "depth", "covariance")},
}


# The buffers the engine keeps as half floats when every sample of the buffer fits half's
# range, else as float32 (docs/frame-layout.md, src/frame/plane.rs): all but the colors and
# the depth. A buffer is the part of a channel name before its first dot.
HALF_BUFFERS = frozenset(("albedo", "normal", "covariance") + tuple(
    f"{b}Variance" for b in ("diffuse", "specular", "albedo", "normal", "depth", "covariance")))
HALF_MAX = 65504.0


def stored_as_engine(ch: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """A frame's channels as the engine holds them in memory: those of `HALF_BUFFERS` rounded
    to half float where all of their buffer's samples fit (exact for channels a file stores
    as half); non-finite samples taken as 0 first, as the engine does."""
    out = dict(ch)
    groups: dict[str, list[str]] = {}
    for name in ch:
        groups.setdefault(name.split(".")[0], []).append(name)
    for buffer, names in groups.items():
        if buffer not in HALF_BUFFERS:
            continue
        planes = [np.nan_to_num(np.asarray(ch[n], np.float32), nan=0.0, posinf=0.0, neginf=0.0) for n in names]
        if all(np.abs(p).max(initial=0.0) <= HALF_MAX for p in planes):
            out.update({n: p.astype(np.float16).astype(np.float32) for n, p in zip(names, planes)})
    return out


# The engine's albedo prefilter (src/engine/albedo.rs): window and patch radii, the distance
# scale of each pass, the share of the variance subtracted, and the floor of the normalisation.
ALBEDO_RADIUS = 3
ALBEDO_PATCH = 1
ALBEDO_PASSES = (0.7, 1.0)
ALBEDO_ALPHA = 1.0
ALBEDO_EPS = 1e-10
ALBEDO_MAX_REFLECTANCE = 1.0
# Radius of the window of the albedo variance's estimate for frames written without one.
ALBEDO_ESTIMATE_RADIUS = 4


def nl_means_pass(albedo: np.ndarray, variance: np.ndarray, k: float) -> tuple[np.ndarray, np.ndarray]:
    """One pass of the engine's albedo prefilter (`nl_means` in src/engine/albedo.rs) of
    `albedo [3, H, W]` with the variance of its pixel means `variance [H, W]`: non-local
    means over a 7×7 window with 3×3 patches, the pair distance `(mean_c (a_p − a_q)² −
    α (v_p + min(v_p, v_q))) / (ε + k² (v_p + v_q))`, the weight `exp(−max(patch mean, 0))`,
    coordinates clamped to the frame. A pixel above 1 in a channel (an emitter's strength in
    the albedo pass) keeps its value and weighs nothing in its neighbours' means. Returns the
    filtered albedo and the variance of each pixel's weighted mean, `Σ w² v_q / (Σ w)²` (a
    pixel that is no reflectance keeps its own)."""
    a = np.asarray(albedo, np.float32)
    _, h, w = a.shape
    v = np.asarray(variance, np.float32)
    v = np.where(np.isfinite(v) & (v > 0), v, np.float32(0.0))
    r, f = ALBEDO_RADIUS, ALBEDO_PATCH
    reflectance = (a <= np.float32(ALBEDO_MAX_REFLECTANCE)).all(0)
    ap = np.pad(a, ((0, 0), (r, r), (r, r)), mode="edge")
    rp = np.pad(reflectance, r, mode="edge")
    vp = np.pad(v, r, mode="edge")
    k2 = np.float32(k * k)
    num = np.zeros_like(a)
    den = np.zeros_like(v)
    vnum = np.zeros_like(v)
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            aq = ap[:, r + dy:r + dy + h, r + dx:r + dx + w]
            vq = vp[r + dy:r + dy + h, r + dx:r + dx + w]
            diff = ((a - aq) ** 2).sum(0) / np.float32(3.0)
            d = (diff - np.float32(ALBEDO_ALPHA) * (v + np.minimum(v, vq))) / (np.float32(ALBEDO_EPS) + k2 * (v + vq))
            dp = np.pad(d, f, mode="edge")
            patch = sum(dp[i:i + h, j:j + w] for i in range(2 * f + 1) for j in range(2 * f + 1))
            weight = np.exp(-np.maximum(patch / np.float32((2 * f + 1) ** 2), 0)).astype(np.float32)
            weight *= rp[r + dy:r + dy + h, r + dx:r + dx + w]
            num += weight * aq
            vnum += weight * weight * vq
            den += weight
    safe = np.where(reflectance, den, 1)
    filtered = np.where(reflectance, num / safe, a).astype(np.float32)
    return filtered, np.where(reflectance, vnum / (safe * safe), v).astype(np.float32)


def prefilter_albedo(albedo: np.ndarray, variance: np.ndarray) -> np.ndarray:
    """The engine's albedo prefilter (`passes` in src/engine/albedo.rs, `--albedo-prefilter
    on`): `nl_means_pass` with the first distance scale of `ALBEDO_PASSES`, then again over
    its result and the variance of its weighted means with the second, where a pixel without
    variance of its own (an exact albedo) keeps the first pass's value."""
    v = np.asarray(variance, np.float32)
    exact = ~(np.isfinite(v) & (v > 0))
    first, v1 = nl_means_pass(albedo, v, ALBEDO_PASSES[0])
    second, _ = nl_means_pass(first, v1, ALBEDO_PASSES[1])
    return np.where(exact[None], first, second)


def _median3(x: np.ndarray, step: int) -> np.ndarray:
    """The median of the 3x3 samples `step` apart around each pixel, clamped to the edges
    (`median_row` in src/engine/albedo.rs; nine samples: the middle one, exact)."""
    h, w = x.shape
    p = np.pad(x, step, mode="edge")
    samples = np.stack([p[step + dy:step + dy + h, step + dx:step + dx + w]
                        for dy in (-step, 0, step) for dx in (-step, 0, step)])
    return np.partition(samples, 4, axis=0)[4]


def estimated_albedo_variance(albedo: np.ndarray) -> np.ndarray:
    """The engine's albedo variance for a frame written without one (`estimated_variance` in
    src/engine/albedo.rs): the squared difference between the albedo's luminance and its
    3x3 median, its 3x3 median, then the median of that at the nine block centres (offsets
    -3, 0, 3, clamped) that tile the 9x9 window around each pixel."""
    a = np.asarray(albedo, np.float32)
    lum = np.float32(LUMINANCE[0]) * a[0] + np.float32(LUMINANCE[1]) * a[1] + np.float32(LUMINANCE[2]) * a[2]
    blocks = _median3(np.square(lum - _median3(lum, 1)), 1)
    return _median3(blocks, (2 * ALBEDO_ESTIMATE_RADIUS + 1) // 3).astype(np.float32)


def raw_from_channels(ch: dict[str, np.ndarray], albedo_prefilter: bool = True) -> tuple[np.ndarray, float, float]:
    """A frame's channels (name -> [H, W]) as a raw `[RAW_CHANNELS, H, W]` float32 array and
    its depth and covariance maxima, the auxiliary buffers rounded as the engine stores them
    (`stored_as_engine`) and the albedo prefiltered by its variance as the engine does by
    default (`prefilter_albedo`; `albedo_prefilter=False`: as `--albedo-prefilter off`), by
    `estimated_albedo_variance` where the frame has no albedo variance. Missing covariance
    (frames of renderers without it) and missing variances are zeros."""
    ch = stored_as_engine(ch)
    h, w = next(iter(ch.values())).shape
    out = np.zeros((len(RAW), h, w), np.float32)
    for i, n in enumerate(RAW):
        src = ch.get(FILE_NAMES[n])
        if src is None and n == "covariance":
            src = ch.get("covariance.Y")
        if src is not None:
            out[i] = src
    # Depth as the engine reads it: non-finite and "infinitely far" samples are "no hit", 0.
    out[DEPTH] = np.where(np.isfinite(out[DEPTH]) & (out[DEPTH] < NO_HIT_DEPTH), out[DEPTH], 0.0)
    out = np.nan_to_num(out, nan=0.0, posinf=65504.0, neginf=0.0)  # half-float files overflow to inf
    depth_max, far = depth_scale(out[DEPTH])
    far_pixels = out[DEPTH] > far
    out[DEPTH][far_pixels] = out[VAR["depth"]][far_pixels] = 0.0
    if albedo_prefilter:
        given = FILE_NAMES["albedoVariance"] in ch
        a = prefilter_albedo(out[ALBEDO], out[VAR["albedo"]] if given else estimated_albedo_variance(out[ALBEDO]))
        # Stored as the engine stores it: in half float where every sample fits.
        out[ALBEDO] = a.astype(np.float16).astype(np.float32) if np.abs(a).max(initial=0.0) <= HALF_MAX else a
    return out, depth_max, float(max(out[COV].max(), 0.0))


def depth_scale(depth: np.ndarray) -> tuple[float, float]:
    """The depth scale of a frame (its largest depth that is not far; 0 without depths above
    0) and the bound above which depths are far (FAR_DEPTH_RATIO times the lower median of
    the depths above 0, or of those below 1/FAR_DEPTH_RATIO of it where they are a quarter
    or more; infinite without depths above 0), as the engine computes them."""
    hits = depth[depth > 0]
    if hits.size == 0:
        return 0.0, float("inf")
    median = _lower_median(hits)
    near = hits[hits < median / np.float32(FAR_DEPTH_RATIO)]
    if 4 * near.size >= hits.size:
        median = _lower_median(near)
    far = float(median * np.float32(FAR_DEPTH_RATIO))
    return float(hits[hits <= far].max()), far


def _lower_median(values: np.ndarray) -> np.float32:
    k = (values.size - 1) // 2
    return np.float32(np.partition(values, k)[k])


def _gradients(x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Forward differences along W and H, 0 at the last column / row."""
    gx = torch.zeros_like(x)
    gy = torch.zeros_like(x)
    gx[..., :, :-1] = x[..., :, 1:] - x[..., :, :-1]
    gy[..., :-1, :] = x[..., 1:, :] - x[..., :-1, :]
    return gx, gy


def _lum(v: torch.Tensor) -> torch.Tensor:
    """Luminance of a [N, 3, H, W] tensor, as [N, 1, H, W]."""
    return LUMINANCE[0] * v[:, 0:1] + LUMINANCE[1] * v[:, 1:2] + LUMINANCE[2] * v[:, 2:3]


def _scaled(x: torch.Tensor, m: torch.Tensor) -> torch.Tensor:
    m = m.view(-1, 1, 1, 1)
    return torch.where(m > 0, torch.minimum(x.clamp(min=0), m) / m.clamp(min=1e-30), torch.zeros_like(x))


def preprocess(raw: torch.Tensor, depth_max: torch.Tensor, cov_max: torch.Tensor, variant: str = "full") -> dict[str, torch.Tensor]:
    """Network inputs of raw frames `[N, 20, H, W]`: `diffuse`, `specular` `[N, 10, H, W]`,
    `features` `[N, 28|24, H, W]`, and `albedo` `[N, 3, H, W]` for the inverse transform.

    Gradients at the crop's last column and row are 0, as at a frame's edge in the engine;
    crop one pixel more than needed and drop it to get interior gradients."""
    raw = raw.float()
    albedo = raw[:, ALBEDO]
    a = albedo.clamp(min=0) + EPS
    d = raw[:, DIFFUSE].clamp(min=0) / a
    dvar = _lum(raw[:, VAR["diffuse"]:VAR["diffuse"] + 1] / (a * a))
    s_raw = raw[:, SPECULAR].clamp(min=0)
    s = torch.log1p(s_raw)
    svar = _lum(raw[:, VAR["specular"]:VAR["specular"] + 1] / (1 + s_raw) ** 2)
    out = {}
    for name, base, var in (("diffuse", d, dvar), ("specular", s, svar)):
        gx, gy = _gradients(base)
        out[name] = torch.cat([base, var, gx, gy], 1)
    depth = _scaled(raw[:, DEPTH:DEPTH + 1], depth_max)
    cov = _scaled(raw[:, COV:COV + 1], cov_max)
    base = torch.cat([raw[:, NORMAL], albedo, depth, cov], 1)
    inv_sq = lambda m: torch.where(m > 0, 1.0 / (m.clamp(min=1e-30) ** 2), torch.zeros_like(m)).view(-1, 1, 1, 1)
    variances = torch.cat([
        raw[:, VAR["normal"]:VAR["normal"] + 1],
        raw[:, VAR["albedo"]:VAR["albedo"] + 1],
        (raw[:, VAR["depth"]:VAR["depth"] + 1] * inv_sq(depth_max)).clamp(max=DEPTH_VARIANCE_LIMIT),
        raw[:, VAR["covariance"]:VAR["covariance"] + 1] * inv_sq(cov_max),
    ], 1)
    gx, gy = _gradients(base)
    features = torch.cat([base, variances, gx, gy], 1)
    if variant == "nocov":
        features = select_nocov(features)
    out["features"] = features
    out["albedo"] = albedo
    return out


def as_beauty(raw: torch.Tensor, ref: torch.Tensor | None = None, keep_depth: torch.Tensor | None = None):
    """Raw frames as the engine sees a frame with only a beauty, albedo and normal (the
    `beauty` variant, docs/model-contract.md): the beauty (diffuse + specular) in the diffuse
    slot, the specular zero, no variances, no covariance, and the depth kept only where
    `keep_depth [N]` is true (all frames when None; a beauty frame may or may not carry one).
    References `[N, 6, H, W]` become (diffuse + specular, 0) alike. Returns new tensors."""
    raw = raw.clone()
    raw[:, DIFFUSE] += raw[:, SPECULAR]
    raw[:, SPECULAR] = 0
    raw[:, COV] = 0
    raw[:, VAR["diffuse"]:VAR["covariance"] + 1] = 0
    if keep_depth is not None:
        raw[:, DEPTH] *= keep_depth.to(raw.device, raw.dtype).view(-1, 1, 1)
    if ref is None:
        return raw
    ref = torch.cat([ref[:, 0:3] + ref[:, 3:6], torch.zeros_like(ref[:, 3:6])], 1)
    return raw, ref


def targets(ref_diffuse: torch.Tensor, ref_specular: torch.Tensor, albedo: torch.Tensor) -> dict[str, torch.Tensor]:
    """Training targets in the preprocessed domains (the noisy frame's albedo divides the
    reference diffuse, as in `mcdenoise preprocess --reference`), and the reference color."""
    return {
        "diffuse_target": ref_diffuse / (albedo + EPS),
        "specular_target": torch.log1p(ref_specular.clamp(min=0)),
        "reference": ref_diffuse + ref_specular,
    }


__all__ = ["FILE_NAMES", "RAW", "RAW_INDEX", "as_beauty", "estimated_albedo_variance", "preprocess", "raw_from_channels",
           "targets"]
