//! The KPCN preprocessing (Bako et al. 2017, Lin et al. 2020) of a frame region into the
//! networks' input tensors. `docs/frame-layout.md` has the math; this is the single
//! implementation of it (training reads its output through `mcdenoise preprocess`).
//!
//! Regions are preprocessed independently: per-frame statistics ([`FrameStats`]) are
//! computed once, and gradients at a region's border read the neighbouring pixels of the
//! frame, so a tile's tensors equal the same pixels of the whole frame's.

use rayon::prelude::*;

use super::contract::{FeatureSet, COLOR_CHANNELS};
use crate::frame::{Buffer, Frame};

/// Added to albedo before dividing the diffuse color by it (KPCN's value).
pub const EPS: f32 = 0.00316;

/// Largest magnitude of a network input. Inputs are saturated to it, so that a sample near
/// the float maximum (divided by a small albedo, or summed into a luminance) cannot overflow
/// into infinities and NaNs: gradients of saturated values stay finite (at most twice
/// this), and so do the networks' activations (ReLU networks scale about linearly with
/// their inputs) and the kernel sums of the reconstruction (at most 441 times this). Far
/// above any rendered radiance: the transforms of ordinary frames never reach it.
pub const INPUT_LIMIT: f32 = 1e20;

/// `x` clamped to `[-limit, limit]` (infinities included); NaN becomes 0.
pub fn saturate(x: f32, limit: f32) -> f32 {
    if x.is_nan() {
        0.0
    } else {
        x.clamp(-limit, limit)
    }
}

/// [`saturate`] to [`INPUT_LIMIT`].
fn bounded(x: f32) -> f32 {
    saturate(x, INPUT_LIMIT)
}

/// Rec. 709 luminance, used to reduce three-channel variances to one.
pub fn luminance(r: f32, g: f32, b: f32) -> f32 {
    0.2126 * r + 0.7152 * g + 0.0722 * b
}

/// A rectangle of the frame, in pixels.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Rect {
    pub x: usize,
    pub y: usize,
    pub w: usize,
    pub h: usize,
}

impl Rect {
    pub fn pixels(&self) -> usize {
        self.w * self.h
    }
}

/// Depths more than this many times the median depth of the frame's hits are "far" and read
/// as 0, "no hit", as a background is (docs/frame-layout.md, "Depth"). The frames of the
/// data sets reach 9.1 times their median (2026-11-28, every frame of `data/` and the test
/// sets), so no frame like them has a far depth.
pub const FAR_DEPTH_RATIO: f32 = 16.0;

/// Largest scaled depth variance: the variance of values in [0, 1] is at most 1/4 (the
/// training frames reach 0.5, an unbiased estimate at 1–2 spp). A pixel whose samples mix
/// a near surface with a far one can have a variance many times the square of the frame's
/// depth scale; it is saturated here instead of reaching the networks as an outlier.
pub const DEPTH_VARIANCE_LIMIT: f32 = 1.0;

/// Statistics of the whole frame that the per-frame scalings need.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FrameStats {
    /// The depth scale: the largest depth of the frame that is not far (0 when none is above 0).
    pub depth_max: f32,
    /// Depths above this are far ([`depth_scale`]; infinite when no depth is above 0).
    pub depth_far: f32,
    /// Largest covariance of the frame (0 without covariance).
    pub covariance_max: f32,
}

impl FrameStats {
    pub fn of(frame: &Frame) -> FrameStats {
        let (depth_max, depth_far) = depth_scale(frame.f32_plane(Buffer::Depth, 0));
        FrameStats {
            depth_max,
            depth_far,
            covariance_max: if frame.has(Buffer::Covariance) { frame.plane(Buffer::Covariance, 0).max() } else { 0.0 },
        }
    }
}

/// The depth scale and the far bound of a depth plane ([`FrameStats`]). The median is the
/// lower one, element `(n − 1) / 2` of the `n` depths above 0 in order. Where a quarter or
/// more of them lie below 1/[`FAR_DEPTH_RATIO`] of that median, the median is of a far
/// part that covers most of the frame (a sky dome behind a landscape), and the bound is
/// taken from the median of those nearer depths instead. No training frame has such a
/// quarter (their depths above 0 reach at most 11.1 times their first quartile).
pub fn depth_scale(depth: &[f32]) -> (f32, f32) {
    let mut hits: Vec<f32> = depth.iter().copied().filter(|d| *d > 0.0).collect();
    if hits.is_empty() {
        return (0.0, f32::INFINITY);
    }
    let mut median = lower_median(&mut hits);
    let mut near: Vec<f32> = hits.iter().copied().filter(|d| *d < median / FAR_DEPTH_RATIO).collect();
    if 4 * near.len() >= hits.len() {
        median = lower_median(&mut near);
    }
    let far = median * FAR_DEPTH_RATIO;
    let max = hits.iter().copied().filter(|d| *d <= far).fold(0f32, f32::max);
    (max, far)
}

/// Element `(n − 1) / 2` of `values` in order (reordering them); `values` is not empty.
fn lower_median(values: &mut [f32]) -> f32 {
    let k = (values.len() - 1) / 2;
    *values.select_nth_unstable_by(k, f32::total_cmp).1
}

/// Network inputs for one region, planar `[channels][h][w]`.
#[derive(Default)]
pub struct Inputs {
    pub rect: Rect,
    /// `color` input of the diffuse network (10 channels; the first 3 are `d'`).
    pub diffuse: Vec<f32>,
    /// `color` input of the specular network (10 channels; the first 3 are `s'`).
    pub specular: Vec<f32>,
    /// `features` input, shared by both networks (28 or 24 channels).
    pub features: Vec<f32>,
}

/// `x / m` with `x` clamped to `[0, m]`, or 0 where `m` is 0.
fn scaled(x: f32, m: f32) -> f32 {
    if m > 0.0 {
        x.clamp(0.0, m) / m
    } else {
        0.0
    }
}

/// Preprocesses `rect` of `frame` for a model taking the feature set `set`.
///
/// # Panics
/// If `set` is `Full` and the frame has no covariance (callers pick the variant from the
/// frame), or if `rect` is not inside the frame.
pub fn preprocess(frame: &Frame, stats: &FrameStats, set: FeatureSet, rect: Rect) -> Inputs {
    let mut inputs = Inputs::default();
    preprocess_into(frame, stats, set, rect, &mut inputs);
    inputs
}

/// `buffer` resized to `len` values for a pass that writes every one of them. A buffer too
/// small is replaced by a fresh zeroed allocation (`calloc`: pages the kernel hands out
/// already zero) instead of being grown and filled: filling 106 MB of a 768×720 region's
/// inputs on one thread faulted in every page there, where the preprocessing's parallel
/// writers now fault them in on all the engine's threads.
fn fit(buffer: &mut Vec<f32>, len: usize) {
    if buffer.capacity() < len {
        *buffer = Vec::new();
        *buffer = vec![0.0; len];
    } else {
        buffer.resize(len, 0.0);
    }
}

/// [`preprocess`] into the buffers of `inputs`, which are resized and every value of which
/// is written: the engine reuses one set of buffers for all the regions of a frame, which
/// would otherwise each map and fault in some 150 MB of fresh memory (at 4K, 28 regions).
pub fn preprocess_into(frame: &Frame, stats: &FrameStats, set: FeatureSet, rect: Rect, inputs: &mut Inputs) {
    assert!(rect.x + rect.w <= frame.width && rect.y + rect.h <= frame.height, "region outside the frame");
    let n = rect.pixels();
    inputs.rect = rect;
    let Inputs { diffuse, specular, features, .. } = inputs;
    fit(diffuse, COLOR_CHANNELS * n);
    fit(specular, COLOR_CHANNELS * n);
    fit(features, set.feature_channels() * n);

    let albedo = frame.rgb(Buffer::Albedo);
    // Diffuse color: d / (a + ε); variance scaled by 1 / (a + ε)². Negative colors and
    // albedos (a malformed frame) are taken as 0: a + ε is then never near zero.
    {
        let d = frame.f32_planes(Buffer::Diffuse);
        let [base, var, gx, gy] = color_layout(diffuse, n);
        for c in 0..3 {
            let (d, a) = (&d[c], albedo[c]);
            with_gradients(
                frame,
                rect,
                |start, out| {
                    a.read(start, out);
                    for (o, d) in out.iter_mut().zip(&d[start..]) {
                        *o = bounded(d.max(0.0) / (o.max(0.0) + EPS));
                    }
                },
                &mut base[c * n..][..n],
                &mut gx[c * n..][..n],
                &mut gy[c * n..][..n],
            );
        }
        let dv = frame.rgb(Buffer::DiffuseVariance);
        variance_luminance(frame, rect, var, 1.0, INPUT_LIMIT, |c, start, v, a| {
            dv[c].read(start, v);
            albedo[c].read(start, a);
            for (v, a) in v.iter_mut().zip(a.iter()) {
                *v = bounded(*v / (a.max(0.0) + EPS).powi(2));
            }
        });
    }
    // Specular color: ln(1 + s); variance scaled by 1 / (1 + s)² (delta method).
    {
        let s = frame.f32_planes(Buffer::Specular);
        let [base, var, gx, gy] = color_layout(specular, n);
        for c in 0..3 {
            let s = &s[c];
            with_gradients(
                frame,
                rect,
                |start, out: &mut [f32]| {
                    for (o, v) in out.iter_mut().zip(&s[start..]) {
                        *o = v.max(0.0);
                    }
                    super::compress::log1p_row(out);
                },
                &mut base[c * n..][..n],
                &mut gx[c * n..][..n],
                &mut gy[c * n..][..n],
            );
        }
        let sv = frame.rgb(Buffer::SpecularVariance);
        variance_luminance(frame, rect, var, 1.0, INPUT_LIMIT, |c, start, v, _| {
            sv[c].read(start, v);
            for (v, s) in v.iter_mut().zip(&s[c][start..]) {
                *v = bounded(*v / (1.0 + s.max(0.0)).powi(2));
            }
        });
    }
    // Features: normal (3), albedo (3), depth, [covariance]; their variances; gx; gy.
    {
        let base_count = if set.uses_covariance() { 8 } else { 7 };
        let var_count = base_count - 4;
        let (base, rest) = features.split_at_mut(base_count * n);
        let (vars, rest) = rest.split_at_mut(var_count * n);
        let (gx, gy) = rest.split_at_mut(base_count * n);
        let normal = frame.planes(Buffer::Normal);
        let depth = frame.f32_plane(Buffer::Depth, 0);
        // One (base, gx, gy) triple of planes per feature, in input order.
        let mut slots = base.chunks_mut(n).zip(gx.chunks_mut(n)).zip(gy.chunks_mut(n)).map(|((b, x), y)| (b, x, y));
        let mut next = || slots.next().expect("one slot per feature");
        for plane in normal.iter().chain(&albedo) {
            let (b, x, y) = next();
            let values = |start: usize, out: &mut [f32]| {
                plane.read(start, out);
                out.iter_mut().for_each(|o| *o = bounded(*o));
            };
            with_gradients(frame, rect, values, b, x, y);
        }
        let (b, x, y) = next();
        let near = |d: f32| if d > stats.depth_far { 0.0 } else { d };
        with_gradients(frame, rect, each_pixel(|i| scaled(near(depth[i]), stats.depth_max)), b, x, y);
        if set.uses_covariance() {
            let cov = frame.plane(Buffer::Covariance, 0);
            let (b, x, y) = next();
            let values = |start: usize, out: &mut [f32]| {
                cov.read(start, out);
                out.iter_mut().for_each(|o| *o = scaled(*o, stats.covariance_max));
            };
            with_gradients(frame, rect, values, b, x, y);
        }

        // In the network's input order (normal, albedo, depth, [covariance]): the index is the
        // slot of `vars` each variance's luminance goes to.
        let mut var_buffers = vec![
            (Buffer::NormalVariance, 1.0, INPUT_LIMIT),
            (Buffer::AlbedoVariance, 1.0, INPUT_LIMIT),
            // Saturated, and 0 where the depth is far (as for a background).
            (Buffer::DepthVariance, inverse_square(stats.depth_max), DEPTH_VARIANCE_LIMIT),
        ];
        if set.uses_covariance() {
            var_buffers.push((Buffer::CovarianceVariance, inverse_square(stats.covariance_max), INPUT_LIMIT));
        }
        for (j, (buffer, scale, limit)) in var_buffers.into_iter().enumerate() {
            let planes = frame.rgb(buffer);
            let far_is_zero = buffer == Buffer::DepthVariance;
            variance_luminance(frame, rect, &mut vars[j * n..][..n], scale, limit, |c, start, v, _| {
                planes[c].read(start, v);
                v.iter_mut().for_each(|v| *v = bounded(*v));
                if far_is_zero {
                    v.iter_mut()
                        .zip(&depth[start..])
                        .filter(|(_, d)| **d > stats.depth_far)
                        .for_each(|(v, _)| *v = 0.0);
                }
            });
        }
    }
}

fn inverse_square(m: f32) -> f32 {
    if m > 0.0 {
        1.0 / (m * m)
    } else {
        0.0
    }
}

/// Splits a 10-channel color tensor into its color (3), variance (1), gx (3) and gy (3) parts.
fn color_layout(t: &mut [f32], n: usize) -> [&mut [f32]; 4] {
    let (base, rest) = t.split_at_mut(3 * n);
    let (var, rest) = rest.split_at_mut(n);
    let (gx, gy) = rest.split_at_mut(3 * n);
    [base, var, gx, gy]
}

/// [`luminance_rows`] of a three-channel variance over the rect's pixels, times `scale`
/// and saturated to `limit` (at most [`INPUT_LIMIT`]).
fn variance_luminance(
    frame: &Frame,
    rect: Rect,
    out: &mut [f32],
    scale: f32,
    limit: f32,
    channel: impl Fn(usize, usize, &mut [f32], &mut [f32]) + Sync,
) {
    let start = |row: usize| (rect.y + row) * frame.width + rect.x;
    luminance_rows(out, rect.w, start, channel, |l| bounded(l * scale).min(limit));
}

/// Fills `out`, rows of `w` pixels, with `finish` of the luminance of three channels, a row
/// at a time: `channel(c, start, row, scratch)` writes channel `c` of the row's pixels,
/// which begin at frame index `start(y)` for row `y`, into `row` (`scratch` is a row of its
/// own for a second plane). On slices, so that the arithmetic vectorises, where reading
/// each sample through its plane's type would not. Parallel over rows.
pub(super) fn luminance_rows(
    out: &mut [f32],
    w: usize,
    start: impl Fn(usize) -> usize + Sync,
    channel: impl Fn(usize, usize, &mut [f32], &mut [f32]) + Sync,
    finish: impl Fn(f32) -> f32 + Sync,
) {
    out.par_chunks_mut(w).enumerate().for_each_init(
        || [(); 4].map(|_| vec![0f32; w]),
        |[r, g, b, scratch], (y, out)| {
            for (c, values) in [&mut *r, &mut *g, &mut *b].into_iter().enumerate() {
                channel(c, start(y), values, scratch);
            }
            for (((o, r), g), b) in out.iter_mut().zip(r.iter()).zip(g.iter()).zip(b.iter()) {
                *o = finish(luminance(*r, *g, *b));
            }
        },
    );
}

/// A row function for [`with_gradients`] from a function of each pixel's frame index.
fn each_pixel(f: impl Fn(usize) -> f32 + Sync) -> impl Fn(usize, &mut [f32]) + Sync {
    move |start, out| {
        for (x, o) in out.iter_mut().enumerate() {
            *o = f(start + x);
        }
    }
}

/// Fills `base` with the values `f` gives and `gx`, `gy` with their forward differences, 0
/// past the frame's last column / row. `f(start, out)` writes the values of the pixels of
/// frame index `start ..` (`out.len()` of them, on one row).
///
/// `f` is evaluated once per pixel (plus one row per block of rows and the column right of
/// the rect): each row's values go to a row buffer, from which the value and both
/// differences are plain slice arithmetic that the compiler vectorises.
fn with_gradients(
    frame: &Frame,
    rect: Rect,
    f: impl Fn(usize, &mut [f32]) + Sync,
    base: &mut [f32],
    gx: &mut [f32],
    gy: &mut [f32],
) {
    /// Rows per parallel task: each task evaluates one row beyond its block.
    const ROWS: usize = 16;
    let (fw, fh, w) = (frame.width, frame.height, rect.w);
    // The rect's columns and, inside the frame, the one to their right (for gx).
    let cols = (w + 1).min(fw - rect.x);
    let row_values = |y: usize, out: &mut [f32]| f(y * fw + rect.x, out);
    let block = ROWS * w;
    base.par_chunks_mut(block).zip(gx.par_chunks_mut(block)).zip(gy.par_chunks_mut(block)).enumerate().for_each(
        |(b, ((base, gx), gy))| {
            let (mut cur, mut next) = (vec![0f32; cols], vec![0f32; cols]);
            let y0 = rect.y + b * ROWS;
            row_values(y0, &mut cur);
            let rows = base.chunks_mut(w).zip(gx.chunks_mut(w)).zip(gy.chunks_mut(w));
            for (r, ((base, gx), gy)) in rows.enumerate() {
                base.copy_from_slice(&cur[..w]);
                for ((g, a), b) in gx.iter_mut().zip(&cur[..cols - 1]).zip(&cur[1..]) {
                    *g = b - a;
                }
                if cols == w {
                    gx[w - 1] = 0.0;
                }
                if y0 + r + 1 < fh {
                    row_values(y0 + r + 1, &mut next);
                    for ((g, a), b) in gy.iter_mut().zip(&cur[..w]).zip(&next[..w]) {
                        *g = b - a;
                    }
                    std::mem::swap(&mut cur, &mut next);
                } else {
                    gy.fill(0.0);
                }
            }
        },
    );
}
