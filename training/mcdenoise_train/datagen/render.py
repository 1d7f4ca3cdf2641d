"""Sample accumulation, variances of the per-pixel mean, and frame assembly.

Samples are drawn in passes (kernel launches) with Mitsuba's `independent` sampler, each
pass seeded differently, so every sample of every pixel is independent of every other.
Per pixel and channel the passes accumulate the count n, the sum and the sum of squares
(per pass in float32 on the device, combined across passes in float64 with Chan's
formula), and the variance of the per-pixel mean is the per-sample estimator

    Var[mean] = s^2 / n,   s^2 = sum (x_i - mean)^2 / (n - 1).

A frame's variance channel `<buffer>Variance.Z` is the luminance-weighted sum of the
per-channel variances, 0.2126 Var_R + 0.7152 Var_G + 0.0722 Var_B, which is what the engine
computes from a three-channel variance (docs/frame-layout.md), so one channel loses nothing.

The covariance buffer is the energy-weighted mean R = sum(E l) / sum(E) of the per-sample
feature l with weights E (integrator.py); its variance follows from the moments of E, E l
and E + E l by the delta method (`Moments.cov_mean_and_var`). Per frame it is divided by
its maximum (the paper's per-frame scaling to [0, 1]); the scale goes into the metadata.

`render_ladder` renders the noisy frames of a scene as a nested progression (the frame
at 8 spp is the frame at 4 spp plus 4 more samples), and `render` a single frame (the
reference, from its own, disjoint seeds).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import drjit as dr
import mitsuba as mi
import numpy as np

from .integrator import LUM, Options, trace

BUFFERS = {"color": 3, "diffuse": 3, "specular": 3, "albedo": 3, "normal": 3, "depth": 1,
           # covariance: per-sample energy E, E * l and E + E * l (for the ratio's variance)
           "cov_e": 1, "cov_el": 1, "cov_sum": 1}
MAX_LANES = 1 << 20


@dataclass
class Moments:
    """Per-pixel count, mean and M2 (sum of squared deviations) of every channel, float64."""

    h: int
    w: int
    n: int = 0
    mean: dict = field(default_factory=dict)
    m2: dict = field(default_factory=dict)

    def add(self, n_b: int, sums: dict, sqs: dict):
        for k in sums:
            s = sums[k].astype(np.float64)
            q = sqs[k].astype(np.float64)
            mean_b = s / n_b
            m2_b = np.maximum(q - s * mean_b, 0.0)
            if self.n == 0:
                self.mean[k], self.m2[k] = mean_b, m2_b
            else:
                d = mean_b - self.mean[k]
                tot = self.n + n_b
                self.mean[k] = self.mean[k] + d * (n_b / tot)
                self.m2[k] = self.m2[k] + m2_b + d * d * (self.n * n_b / tot)
        self.n += n_b

    def copy(self):
        return Moments(self.h, self.w, self.n, {k: v.copy() for k, v in self.mean.items()},
                       {k: v.copy() for k, v in self.m2.items()})

    def var_of_mean(self, k):
        if k == "cov":
            return self.cov_mean_and_var()[1][..., None]
        if self.n < 2:
            return np.zeros_like(self.m2[k])
        return self.m2[k] / (self.n - 1) / self.n

    def cov_mean_and_var(self):
        """Energy-weighted mean of the per-sample covariance feature l,
        R = sum(E l) / sum(E), and the variance of R by the delta method:
        Var[R] = (Var[E l] + R^2 Var[E] - 2 R Cov[E l, E]) / (n mean(E)^2)."""
        e, el = self.mean["cov_e"][..., 0], self.mean["cov_el"][..., 0]
        ok = e > 0
        r = np.where(ok, el / np.where(ok, e, 1.0), 0.0)
        if self.n < 2:
            return r, np.zeros_like(r)
        v = {k: self.m2[k][..., 0] / (self.n - 1) for k in ("cov_e", "cov_el", "cov_sum")}
        cross = 0.5 * (v["cov_sum"] - v["cov_el"] - v["cov_e"])
        num = np.maximum(v["cov_el"] + r * r * v["cov_e"] - 2.0 * r * cross, 0.0)
        var = np.where(ok, num / (self.n * np.where(ok, e, 1.0) ** 2), 0.0)
        return r, var


def _pass(scene, spp, seed, width, height, pixel_angle, opts):
    """One kernel launch: `spp` samples for every pixel. Returns per-pixel sums/squares."""
    sensor = scene.sensors()[0]
    n_pix = width * height
    n_lanes = n_pix * spp
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(dr.opaque(mi.UInt32, seed & 0xFFFFFFFF), n_lanes)
    out, pix = trace(scene, sensor, sampler, n_lanes, spp, width, height, pixel_angle, opts)
    if "cov" in out:
        ell, e = out.pop("cov"), out.pop("cov_energy")
        out["cov_e"], out["cov_el"] = e, e * ell
        out["cov_sum"] = e + e * ell
    sums, sqs = {}, {}
    for k, v in out.items():
        ch = [v[i] for i in range(3)] if BUFFERS[k] == 3 else [v]
        sums[k] = [dr.zeros(mi.Float, n_pix) for _ in ch]
        sqs[k] = [dr.zeros(mi.Float, n_pix) for _ in ch]
        for i, c in enumerate(ch):
            c = dr.select(dr.isfinite(c), c, 0.0)
            dr.scatter_reduce(dr.ReduceOp.Add, sums[k][i], c, pix)
            dr.scatter_reduce(dr.ReduceOp.Add, sqs[k][i], c * c, pix)
    dr.eval(sums, sqs)
    to_np = lambda lst: np.stack([np.asarray(a, np.float32).reshape(height, width) for a in lst], -1)  # noqa: E731
    return {k: to_np(v) for k, v in sums.items()}, {k: to_np(v) for k, v in sqs.items()}


def accumulate(moments: Moments, scene, spp_total, seed, pixel_angle, opts, max_lanes=MAX_LANES, progress=None):
    """Add `spp_total` samples per pixel to `moments` in passes of at most `max_lanes` lanes;
    pass i uses sampler seed `seed + i`. Returns the next unused seed."""
    n_pix = moments.h * moments.w
    per = max(1, min(spp_total, max_lanes // n_pix))
    done = 0
    while done < spp_total:
        k = min(per, spp_total - done)
        sums, sqs = _pass(scene, k, seed, moments.w, moments.h, pixel_angle, opts)
        moments.add(k, sums, sqs)
        done += k
        seed += 1
        if progress:
            progress(k)
    return seed


def frame_channels(m: Moments, covariance: bool = True) -> tuple[dict, dict]:
    """EXR channels (docs/frame-layout.md) of accumulated moments, and metadata."""
    ch = {}
    meta = {"spp": m.n}
    names = {"diffuse": ("diffuse.R", "diffuse.G", "diffuse.B"), "specular": ("specular.R", "specular.G", "specular.B"),
             "albedo": ("albedo.R", "albedo.G", "albedo.B"), "normal": ("normal.R", "normal.G", "normal.B"),
             "color": ("R", "G", "B")}
    for k, cn in names.items():
        for i, c in enumerate(cn):
            ch[c] = m.mean[k][..., i]
        v = m.var_of_mean(k)
        ch[f"{k}Variance.Z"] = sum(LUM[i] * v[..., i] for i in range(3))
    ch["depth.Z"] = m.mean["depth"][..., 0]
    ch["depthVariance.Z"] = m.var_of_mean("depth")[..., 0]
    if covariance and "cov_e" in m.mean:
        ell, var = m.cov_mean_and_var()
        scale = float(ell.max()) if ell.size and ell.max() > 0 else 1.0
        ch["covariance"] = np.clip(ell / scale, 0.0, 1.0)
        ch["covarianceVariance.Z"] = var / scale**2
        meta["covariance_scale"] = scale
    return {k: np.ascontiguousarray(v, np.float32) for k, v in ch.items()}, meta


def render_ladder(scene, width, height, spps, seed, pixel_angle, opts: Options, max_lanes=MAX_LANES,
                  progress=None, on_frame=None):
    """Nested noisy frames at each spp in `spps` (ascending); calls on_frame(spp, moments,
    seconds) when a level is complete, where seconds is the rendering time of that level."""
    m = Moments(height, width)
    done = 0
    t_total = 0.0
    for spp in sorted(spps):
        t0 = time.perf_counter()
        seed = accumulate(m, scene, spp - done, seed, pixel_angle, opts, max_lanes, progress)
        t_total += time.perf_counter() - t0
        done = spp
        if on_frame:
            on_frame(spp, m.copy(), t_total)
    return m


def render(scene, width, height, spp, seed, pixel_angle, opts: Options, max_lanes=MAX_LANES, progress=None):
    m = Moments(height, width)
    accumulate(m, scene, spp, seed, pixel_angle, opts, max_lanes, progress)
    return m
