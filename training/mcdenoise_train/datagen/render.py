"""Sample accumulation, variances of the per-pixel mean, and frame assembly.

A frame's samples are rendered in as few kernel launches as memory allows (usually one):
the samples of every pixel are split into chunks, each lane of the launch is one
(chunk, pixel) pair and loops over its chunk's samples inside the kernel (a symbolic loop
around the path tracer's), keeping the running mean and M2 of every accumulated value in
float32 (Welford's update). Samples are independent: Mitsuba's `independent` sampler gives
every lane its own random stream, every launch its own seed. Chunks are combined on the
host in float64 (Chan's formula), and the variance of the per-pixel mean is the per-sample
estimator

    Var[mean] = s^2 / n,   s^2 = sum (x_i - mean)^2 / (n - 1).

A frame's variance channel `<buffer>Variance.Z` is the luminance-weighted sum of the
per-channel variances, 0.2126 Var_R + 0.7152 Var_G + 0.0722 Var_B, which is what the engine
computes from a three-channel variance (docs/frame-layout.md), so one channel loses nothing.

The covariance buffer is the energy-weighted mean R = sum(E l) / sum(E) of the per-sample
feature l with weights E (integrator.py); its variance follows from the moments of E, E l
and E + E l by the delta method (`Moments.cov_mean_and_var`). Per frame it is divided by
its maximum (the paper's per-frame scaling to [0, 1]); the scale goes into the metadata.

`render_ladder` renders all noisy frames of a scene in one launch as a nested progression
(segments [0, s1), [s1, s2), ... of each pixel's samples; the frame at 8 spp is the frame at
4 spp plus 4 more samples), and `render` a single frame (the reference, from its own seed).
Per-scene values reach the kernel as opaque variables (integrator.Camera), so a new seed,
sample count or chunk table reuses the compiled kernel.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import drjit as dr
import mitsuba as mi
import numpy as np

from .integrator import LUM, Camera, Options, trace

BUFFERS = {"color": 3, "diffuse": 3, "specular": 3, "albedo": 3, "normal": 3, "depth": 1,
           # covariance: per-sample energy E, E * l and E + E * l (for the ratio's variance)
           "cov_e": 1, "cov_el": 1, "cov_sum": 1}
MAX_LANES = 1 << 22


@dataclass
class Moments:
    """Per-pixel count, mean and M2 (sum of squared deviations) of every channel, float64."""

    h: int
    w: int
    n: int = 0
    mean: dict = field(default_factory=dict)
    m2: dict = field(default_factory=dict)
    #: moments of more samples (a superset) from which the per-sample variance is taken
    #: when this frame has a single sample per pixel (see render_ladder)
    var_source: "Moments | None" = None

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

    def add_moments(self, n_b: int, mean_b: dict, m2_b: dict):
        """Chan's parallel combination with a batch of n_b samples given as means and M2."""
        for k in mean_b:
            mb = mean_b[k].astype(np.float64)
            qb = np.maximum(m2_b[k].astype(np.float64), 0.0)
            if self.n == 0:
                self.mean[k], self.m2[k] = mb, qb
            else:
                d = mb - self.mean[k]
                tot = self.n + n_b
                self.mean[k] = self.mean[k] + d * (n_b / tot)
                self.m2[k] = self.m2[k] + qb + d * d * (self.n * n_b / tot)
        self.n += n_b

    def combined(self, other: "Moments") -> "Moments":
        out = self.copy()
        if other.n:
            out.add_moments(other.n, other.mean, other.m2)
        return out

    def copy(self):
        return Moments(self.h, self.w, self.n, {k: v.copy() for k, v in self.mean.items()},
                       {k: v.copy() for k, v in self.m2.items()}, self.var_source)

    def _var_moments(self):
        return self.var_source if self.n < 2 and self.var_source is not None else self

    def var_of_mean(self, k):
        if k == "cov":
            return self.cov_mean_and_var()[1][..., None]
        src = self._var_moments()
        if src.n < 2:
            return np.zeros_like(self.m2[k])
        return src.m2[k] / (src.n - 1) / self.n

    def cov_mean_and_var(self):
        """Energy-weighted mean of the per-sample covariance feature l,
        R = sum(E l) / sum(E), and the variance of R by the delta method:
        Var[R] = (Var[E l] + R^2 Var[E] - 2 R Cov[E l, E]) / (n mean(E)^2)."""
        e, el = self.mean["cov_e"][..., 0], self.mean["cov_el"][..., 0]
        ok = e > 0
        r = np.where(ok, el / np.where(ok, e, 1.0), 0.0)
        src = self._var_moments()
        if src.n < 2:
            return r, np.zeros_like(r)
        v = {k: src.m2[k][..., 0] / (src.n - 1) for k in ("cov_e", "cov_el", "cov_sum")}
        cross = 0.5 * (v["cov_sum"] - v["cov_el"] - v["cov_e"])
        num = np.maximum(v["cov_el"] + r * r * v["cov_e"] - 2.0 * r * cross, 0.0)
        var = np.where(ok, num / (self.n * np.where(ok, e, 1.0) ** 2), 0.0)
        return r, var


#: Lanes per launch on the GPU: enough threads to fill it, each looping over its chunk.
GPU_LANES = 1 << 21
#: Lanes per launch on the CPU: Dr.Jit's LLVM backend hands out work in blocks of 16K
#: lanes, so a launch needs several blocks per core to keep every core busy to the end.
CPU_LANES = 1 << 18


def kernel_channels(opts: Options) -> list[tuple[str, int]]:
    """The per-sample values the kernel accumulates, as (buffer, channels)."""
    keys = ["color", "diffuse", "specular", "albedo", "normal", "depth"]
    if opts.covariance:
        keys += ["cov_e", "cov_el", "cov_sum"]
    return [(k, BUFFERS[k]) for k in keys]


@dataclass
class LaunchStats:
    """Where the time of one launch went: Python tracing, code generation and compilation
    (0 when the kernel came from Dr.Jit's cache), and execution (Dr.Jit's kernel history)."""

    seconds: float = 0.0
    trace_seconds: float = 0.0
    compile_seconds: float = 0.0
    execute_seconds: float = 0.0
    cache_hit: bool = True
    lanes: int = 0
    kernels: tuple = ()

    def plus(self, o: "LaunchStats") -> "LaunchStats":
        return LaunchStats(self.seconds + o.seconds, self.trace_seconds + o.trace_seconds,
                           self.compile_seconds + o.compile_seconds, self.execute_seconds + o.execute_seconds,
                           self.cache_hit and o.cache_hit, max(self.lanes, o.lanes), self.kernels + o.kernels)

    def as_dict(self) -> dict:
        return {"seconds": round(self.seconds, 3), "trace_seconds": round(self.trace_seconds, 3),
                "compile_seconds": round(self.compile_seconds, 3), "execute_seconds": round(self.execute_seconds, 3),
                "kernel_cache_hit": self.cache_hit, "lanes": self.lanes}


def _launch(scene, width, height, pix0, n_pix, chunks, seed, cam: Camera, opts: Options):
    """One kernel launch: lane (c, p) renders `chunks[c]` samples of pixel pix0 + p, with
    a sample loop inside the kernel, and keeps the running mean and M2 (Welford) of every
    accumulated value. Returns per-chunk arrays [len(chunks), n_pix, C] and the stats."""
    t0 = time.perf_counter()
    sensor = scene.sensors()[0]
    n_lanes = n_pix * len(chunks)
    table = mi.UInt32(np.asarray(chunks, np.uint32))
    dr.make_opaque(table)
    idx = dr.arange(mi.UInt32, n_lanes)
    n_pix_o = dr.opaque(mi.UInt32, n_pix)
    chunk = idx // n_pix_o
    pix = idx - chunk * n_pix_o + dr.opaque(mi.UInt32, pix0)
    length = dr.gather(mi.UInt32, table, chunk)
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(dr.opaque(mi.UInt32, seed & 0xFFFFFFFF), n_lanes)
    layout = kernel_channels(opts)
    n_ch = sum(c for _, c in layout)
    mean = [dr.zeros(mi.Float, n_lanes) for _ in range(n_ch)]
    m2 = [dr.zeros(mi.Float, n_lanes) for _ in range(n_ch)]
    i = dr.zeros(mi.UInt32, n_lanes)

    def body(sampler, i, mean, m2):
        out = trace(scene, sensor, sampler, pix, cam, opts)
        if opts.covariance:
            ell, e = out.pop("cov"), out.pop("cov_energy")
            out["cov_e"], out["cov_el"], out["cov_sum"] = e, e * ell, e + e * ell
        xs = []
        for k, c in layout:
            xs += [out[k][j] for j in range(3)] if c == 3 else [out[k]]
        inv_n = dr.rcp(mi.Float(i + 1))
        mean, m2 = list(mean), list(m2)
        for j, x in enumerate(xs):
            x = dr.select(dr.isfinite(x), x, 0.0)
            d = x - mean[j]
            mean[j] = mean[j] + d * inv_n
            m2[j] = m2[j] + d * (x - mean[j])
        return sampler, i + 1, mean, m2

    with dr.scoped_set_flag(dr.JitFlag.KernelHistory, True):
        dr.kernel_history()  # clear
        sampler, i, mean, m2 = dr.while_loop(state=(sampler, i, mean, m2), cond=lambda s, i, a, b: i < length,
                                             body=body, labels=("sampler", "i", "mean", "m2"),
                                             label="mcdenoise_samples")
        t_traced = time.perf_counter()
        dr.eval(mean, m2)
        dr.sync_thread()
        hist = [h for h in dr.kernel_history() if h.get("type") == dr.KernelType.JIT]
    shape = (len(chunks), n_pix)
    mean_np = np.stack([np.asarray(a, np.float32).reshape(shape) for a in mean], -1)
    m2_np = np.stack([np.asarray(a, np.float32).reshape(shape) for a in m2], -1)
    stats = LaunchStats(seconds=time.perf_counter() - t0, trace_seconds=t_traced - t0,
                        compile_seconds=sum(h.get("codegen_time", 0.0) + h.get("backend_time", 0.0) for h in hist) / 1e3,
                        execute_seconds=sum(h.get("execution_time", 0.0) for h in hist) / 1e3,
                        cache_hit=all(bool(h.get("cache_hit")) or bool(h.get("cache_disk")) for h in hist),
                        lanes=n_lanes, kernels=tuple(str(h.get("hash", ""))[:12] for h in hist))
    return mean_np, m2_np, stats


def _split(n: int, parts: int) -> list[int]:
    parts = max(1, min(n, parts))
    return [n // parts + (1 if j < n % parts else 0) for j in range(parts)]


def lanes_target(n_pix: int) -> int:
    """Lanes per launch: a GPU wants millions of threads, a CPU a few blocks per core;
    samples are split into chunks (one per lane) until the launch has that many."""
    return max(n_pix, GPU_LANES if mi.variant().startswith("cuda") else CPU_LANES)


def render_segments(scene, width, height, segments, seed, pixel_angle, opts: Options, max_lanes=MAX_LANES,
                    lanes=None):
    """Render consecutive sample ranges of every pixel (`segments`: sample counts) in as
    few launches as `max_lanes` allows, each segment split into chunks to give the device
    about `lanes` threads. Returns one Moments per segment and the launch stats."""
    n_pix = width * height
    lanes = lanes or lanes_target(n_pix)
    total = sum(segments)
    # chunks per segment, proportional to its length, so that all chunks are similar in size
    want = max(1, lanes // n_pix)
    chunk_len = max(1, -(-total // want))
    chunks, owner = [], []
    for s_i, n in enumerate(segments):
        for c in _split(n, -(-n // chunk_len)):
            chunks.append(c)
            owner.append(s_i)
    cam = Camera.of(scene, width, height, pixel_angle)
    layout = kernel_channels(opts)
    means = np.zeros((len(chunks), n_pix, sum(c for _, c in layout)), np.float32)
    m2s = np.zeros_like(means)
    stats = LaunchStats()
    # pixel blocks so that one launch stays under max_lanes (large frames)
    block = max(1, min(n_pix, max_lanes // len(chunks)))
    for p0 in range(0, n_pix, block):
        npx = min(block, n_pix - p0)
        mean, m2, st = _launch(scene, width, height, p0, npx, chunks, seed, cam, opts)
        means[:, p0:p0 + npx], m2s[:, p0:p0 + npx] = mean, m2
        stats = stats.plus(st)
        seed += 1
    out = []
    for s_i in range(len(segments)):
        m = Moments(height, width)
        for c_i in (j for j, o in enumerate(owner) if o == s_i):
            mean_c, m2_c, off = {}, {}, 0
            for k, c in layout:
                mean_c[k] = means[c_i, :, off:off + c].reshape(height, width, c)
                m2_c[k] = m2s[c_i, :, off:off + c].reshape(height, width, c)
                off += c
            m.add_moments(chunks[c_i], mean_c, m2_c)
        out.append(m)
    return out, stats


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
                  progress=None, on_frame=None, lanes=None):
    """Nested noisy frames at each spp in `spps`: all levels in one launch (segments
    [0, s1), [s1, s2), ... of every pixel's samples), then combined cumulatively; calls
    on_frame(spp, moments, seconds) per level, seconds being the launch's time. Returns the
    moments of the last level and the launch stats."""
    spps = sorted(int(s) for s in spps)
    # a 1-spp frame takes its per-sample variance from its sample and the next one
    levels = sorted(set(spps) | ({2} if spps[0] == 1 else set()))
    segments = [b - a for a, b in zip([0] + levels[:-1], levels)]
    parts, stats = render_segments(scene, width, height, segments, seed, pixel_angle, opts, max_lanes, lanes)
    if progress:
        progress(levels[-1])
    m = Moments(height, width)
    cum = {}
    for spp, part in zip(levels, parts):
        m = m.combined(part)
        cum[spp] = m
    if 1 in cum:
        cum[1].var_source = cum[2]
    for spp in spps:
        if on_frame:
            on_frame(spp, cum[spp], stats.seconds)
    return cum[spps[-1]], stats


def render(scene, width, height, spp, seed, pixel_angle, opts: Options, max_lanes=MAX_LANES, progress=None,
           lanes=None, with_stats=False):
    """One frame of `spp` samples per pixel (moments; with the launch stats if asked)."""
    (m,), stats = render_segments(scene, width, height, [spp], seed, pixel_angle, opts, max_lanes, lanes)
    if progress:
        progress(spp)
    return (m, stats) if with_stats else m
