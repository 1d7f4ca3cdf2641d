//! Contract-v2 reconstruction: per-pixel k×k kernels at `L` pyramid levels, blended coarse to
//! fine (docs/model-contract.md, "Model contract v2"; Vogels et al. 2018).
//!
//! ```text
//! c_0 = c,  c_{l+1} = avgpool2x2(c_l)      (linear means: c_{l+1} = ln(1 + avgpool2x2(e^{c_l} − 1)))
//! f_l = Σ_t softmax(kernel_l)_t · c_l(x+dx_t, y+dy_t)      edge replication at the region border
//! o_{L−1} = f_{L−1}
//! o_l = f_l + σ(blend_l) · (up(o_{l+1}) − up(avgpool2x2(f_l)))
//! ```
//!
//! With detail gains (graph outputs `gain_<l>`), each level's own detail is scaled:
//! `o_l = m_l + σ(gain_l) · (f_l − m_l) + σ(blend_l) · (up(o_{l+1}) − m_l)`, `m_l =
//! up(avgpool2x2(f_l))`.
//!
//! `up` is linear, so the engine upsamples the difference `o_{l+1} − avgpool2x2(f_l)` once
//! instead of both terms (and, with gains, `avgpool2x2(f_l)` as well). The filter is v1's (see [`super::reconstruct`]): softmax and
//! weighted sum fused per output row, the weights never stored, tap-major so that logits
//! and color rows are read contiguously, compiled for AVX2+FMA where the CPU has them. With
//! k² = 25 taps the maximum is found in a first pass over the row's logits (they then stay in
//! L1/L2 for the second) rather than online. Rows run in parallel on the caller's rayon pool.
//! At level 0 only the pixels the core needs are filtered and blended.
//!
//! A specular color holds ln(1 + s); with linear means (`mcdenoise.specular_pyramid`
//! `linear`) its coarser levels are ln(1 + the mean of s) rather than the mean of ln(1 + s),
//! which Jensen's inequality puts below it wherever the samples spread.

use rayon::prelude::*;

use super::compress::{expm1_row, log1p_row};
use super::preprocess::Rect;
use super::reconstruct::{accumulate, exp_nonpositive, normalize, Fused, MulAdd, Unfused};

/// One component's network outputs over a region, level by level.
pub struct Pyramid<'a> {
    /// Side of the kernels (odd).
    pub kernel_size: usize,
    /// `kernels[l]`: logits `[k²][h_l][w_l]` of level `l`, `h_l = h / 2^l`.
    pub kernels: Vec<&'a [f32]>,
    /// `blends[l]`: blend logits `[h_l][w_l]` of level `l < L − 1`.
    pub blends: Vec<&'a [f32]>,
    /// `gains[l]`: detail-gain logits `[h_l][w_l]` of level `l < L − 1`; empty for a network
    /// without them.
    pub gains: Vec<&'a [f32]>,
    /// The color is ln(1 + x) (≥ 0) and the coarser levels average x, not the color.
    pub linear_means: bool,
}

/// Reconstructs one component: `color` is `[3][h][w]` (the preprocessed color of a region
/// whose sides are multiples of 2^(L−1)), `core` a rectangle in region coordinates, `out`
/// receives `[3][core.h][core.w]`.
pub fn reconstruct(p: &Pyramid, color: &[f32], w: usize, h: usize, core: Rect, out: &mut [f32]) {
    let levels = p.kernels.len();
    let k = p.kernel_size;
    assert!(levels >= 1 && p.blends.len() == levels - 1, "{levels} kernel levels need {} blends", levels - 1);
    assert!(k % 2 == 1, "kernel size {k} is not odd");
    let m = 1 << (levels - 1);
    assert!(w % m == 0 && h % m == 0, "region {w}x{h} is not a multiple of {m}");
    assert_eq!(color.len(), 3 * w * h, "color does not cover the region");
    assert!(core.x + core.w <= w && core.y + core.h <= h, "core outside the region");
    assert_eq!(out.len(), 3 * core.pixels(), "output does not match the core");
    for (l, kernel) in p.kernels.iter().enumerate() {
        assert_eq!(kernel.len(), k * k * (w >> l) * (h >> l), "level {l} kernel does not cover the level");
    }
    for (l, blend) in p.blends.iter().enumerate() {
        assert_eq!(blend.len(), (w >> l) * (h >> l), "level {l} blend does not cover the level");
    }
    assert!(p.gains.is_empty() || p.gains.len() == levels - 1, "{levels} kernel levels need 0 or {} gains", levels - 1);
    for (l, gain) in p.gains.iter().enumerate() {
        assert_eq!(gain.len(), (w >> l) * (h >> l), "level {l} gain does not cover the level");
    }
    let gain = |l: usize| p.gains.get(l).copied();

    if levels == 1 {
        filter(p.kernels[0], color, w, h, k, core, out);
        return;
    }
    let coarse = coarse_levels(p, color, w, h);
    finest(p.kernels[0], p.blends[0], gain(0), k, color, w, h, &coarse, core, out);
}

/// `o_1` of one component over a whole region (`[3][h/2][w/2]`): the color pyramid and
/// levels L−1 … 1 of [`reconstruct`]; level 0's logits are not read (the staged engine
/// computes this over a whole frame before level 0's logits exist). Needs at least two
/// levels.
pub fn coarse_levels(p: &Pyramid, color: &[f32], w: usize, h: usize) -> Vec<f32> {
    let levels = p.kernels.len();
    let k = p.kernel_size;
    let gain = |l: usize| p.gains.get(l).copied();
    assert!(levels >= 2, "the coarse levels of a {levels}-level pyramid");
    // The color pyramid, levels 1 … L−1.
    let mut pyramid: Vec<Vec<f32>> = Vec::with_capacity(levels - 1);
    if p.linear_means {
        let mut linear = avgpool_expm1(color, w, h);
        for l in 1..levels {
            if l > 1 {
                linear = avgpool(&linear, w >> (l - 1), h >> (l - 1));
            }
            let mut level = linear.clone();
            level.par_chunks_mut(w >> l).for_each(log1p_row);
            pyramid.push(level);
        }
    } else {
        for l in 1..levels {
            let fine = if l == 1 { color } else { &pyramid[l - 2] };
            pyramid.push(avgpool(fine, w >> (l - 1), h >> (l - 1)));
        }
    }
    // Coarsest level: o = f. Then each level from L−2 up to 1, whole.
    let (wc, hc) = (w >> (levels - 1), h >> (levels - 1));
    let mut coarse = vec![0f32; 3 * wc * hc];
    filter(p.kernels[levels - 1], &pyramid[levels - 2], wc, hc, k, whole(wc, hc), &mut coarse);
    for l in (1..levels - 1).rev() {
        let (wl, hl) = (w >> l, h >> l);
        let mut f = vec![0f32; 3 * wl * hl];
        filter(p.kernels[l], &pyramid[l - 1], wl, hl, k, whole(wl, hl), &mut f);
        let mut o = vec![0f32; 3 * wl * hl];
        blend(&f, whole(wl, hl), &coarse, wl, hl, p.blends[l], gain(l), whole(wl, hl), &mut o);
        coarse = o;
    }
    coarse
}

/// Level 0 of [`reconstruct`] over `core` (region coordinates): `kernel`, `blend` and
/// `gain` are level 0's logits over the `w`×`h` region, `coarse` its `o_1`
/// (`[3][h/2][w/2]`, [`coarse_levels`]). Reads the logits and the color only within a few
/// pixels of the core.
#[allow(clippy::too_many_arguments)]
pub fn finest(
    kernel: &[f32],
    blend_logits: &[f32],
    gain: Option<&[f32]>,
    k: usize,
    color: &[f32],
    w: usize,
    h: usize,
    coarse: &[f32],
    core: Rect,
    out: &mut [f32],
) {
    assert_eq!(coarse.len(), 3 * (w / 2) * (h / 2), "o_1 does not cover the region");
    // Level 0, only where the core needs it: the coarse pixels its upsampling reads (one
    // beyond each side of the core's half) and the 2×2 blocks pooled into them.
    let (lo_x, hi_x) = ((core.x / 2).saturating_sub(1), ((core.x + core.w - 1) / 2 + 1).min(w / 2 - 1));
    let (lo_y, hi_y) = ((core.y / 2).saturating_sub(1), ((core.y + core.h - 1) / 2 + 1).min(h / 2 - 1));
    let span = Rect { x: 2 * lo_x, y: 2 * lo_y, w: 2 * (hi_x + 1 - lo_x), h: 2 * (hi_y + 1 - lo_y) };
    let mut f = vec![0f32; 3 * span.pixels()];
    filter(kernel, color, w, h, k, span, &mut f);
    blend(&f, span, coarse, w, h, blend_logits, gain, core, out);
}

fn whole(w: usize, h: usize) -> Rect {
    Rect { x: 0, y: 0, w, h }
}

/// 2×2 average pooling of `[3][h][w]` (`w`, `h` even).
fn avgpool(src: &[f32], w: usize, h: usize) -> Vec<f32> {
    let (wc, hc) = (w / 2, h / 2);
    let mut dst = vec![0f32; 3 * wc * hc];
    dst.par_chunks_mut(wc).enumerate().for_each(|(row, d)| {
        let (c, y) = (row / hc, row % hc);
        let top = &src[c * w * h + 2 * y * w..][..w];
        let bottom = &src[c * w * h + (2 * y + 1) * w..][..w];
        for (x, d) in d.iter_mut().enumerate() {
            *d = (top[2 * x] + top[2 * x + 1] + bottom[2 * x] + bottom[2 * x + 1]) * 0.25;
        }
    });
    dst
}

/// The largest ln(1 + x) a linear pyramid takes (x = 5.5e34), so that e^x and the means stay
/// finite (`recon_ms.LINEAR_PYRAMID_MAX`); real frames never come near it.
const LINEAR_PYRAMID_MAX: f32 = 80.0;

/// 2×2 average pooling of e^x − 1 over `[3][h][w]` (`w`, `h` even), x at most
/// [`LINEAR_PYRAMID_MAX`]: the first linear level of a color that holds ln(1 + x).
fn avgpool_expm1(src: &[f32], w: usize, h: usize) -> Vec<f32> {
    let (wc, hc) = (w / 2, h / 2);
    let mut dst = vec![0f32; 3 * wc * hc];
    dst.par_chunks_mut(wc).enumerate().for_each_init(
        || vec![0f32; 2 * w],
        |rows, (row, d)| {
            let (c, y) = (row / hc, row % hc);
            for (r, s) in rows.iter_mut().zip(&src[c * w * h + 2 * y * w..][..2 * w]) {
                *r = s.min(LINEAR_PYRAMID_MAX);
            }
            expm1_row(rows);
            let (top, bottom) = rows.split_at(w);
            for (x, d) in d.iter_mut().enumerate() {
                *d = (top[2 * x] + top[2 * x + 1] + bottom[2 * x] + bottom[2 * x + 1]) * 0.25;
            }
        },
    );
    dst
}

/// Weight pair of bilinear ×2 upsampling with half-pixel centres (PyTorch's
/// `align_corners=False`) for output index `i` of a level `n` wide: the source indices and
/// their weights, clamped at the edges.
#[inline(always)]
fn up_taps(i: usize, n: usize) -> (usize, usize, f32, f32) {
    let c = i / 2;
    if i % 2 == 0 {
        if c == 0 {
            (0, 0, 1.0, 0.0)
        } else {
            (c - 1, c, 0.25, 0.75)
        }
    } else if c + 1 < n {
        (c, c + 1, 0.75, 0.25)
    } else {
        (c, c, 1.0, 0.0)
    }
}

/// `o = f + σ(b) · up(coarse − avgpool(f))` over `target` (a rectangle of the level, `w`×`h`),
/// written to `out` (`[3][target.h][target.w]`); with detail-gain logits `g`, plus
/// `(σ(g) − 1) · (f − up(avgpool(f)))`. `f` holds `[3][span.h][span.w]` for a `span` of even
/// origin and size that contains the 2×2 blocks behind every coarse pixel the upsampling of
/// `target` reads; `coarse` is the next level's output, `[3][h/2][w/2]`; `blend` the blend
/// logits `[h][w]`, `gain` the gain logits `[h][w]`.
#[allow(clippy::too_many_arguments)]
fn blend(
    f: &[f32],
    span: Rect,
    coarse: &[f32],
    w: usize,
    h: usize,
    blend: &[f32],
    gain: Option<&[f32]>,
    target: Rect,
    out: &mut [f32],
) {
    let (wc, hc) = (w / 2, h / 2);
    let (sx, sy) = (span.x / 2, span.y / 2);
    let (sw, sh) = (span.w / 2, span.h / 2);
    let sn = span.pixels();
    // d = coarse − avgpool(f) over the span's coarse pixels; with gains, p = avgpool(f) as well
    // (a network without them never reads it, so it is not allocated).
    let mut p = vec![0f32; if gain.is_some() { 3 * sw * sh } else { 0 }];
    let mut d = vec![0f32; 3 * sw * sh];
    let pool = |row: usize, d: &mut [f32], mut p: Option<&mut [f32]>| {
        let (c, y) = (row / sh, row % sh);
        let top = &f[c * sn + 2 * y * span.w..][..span.w];
        let bottom = &f[c * sn + (2 * y + 1) * span.w..][..span.w];
        let co = &coarse[c * wc * hc + (sy + y) * wc + sx..][..sw];
        for x in 0..sw {
            let mean = (top[2 * x] + top[2 * x + 1] + bottom[2 * x] + bottom[2 * x + 1]) * 0.25;
            d[x] = co[x] - mean;
            if let Some(p) = p.as_deref_mut() {
                p[x] = mean;
            }
        }
    };
    if gain.is_some() {
        d.par_chunks_mut(sw).zip(p.par_chunks_mut(sw)).enumerate().for_each(|(row, (d, p))| pool(row, d, Some(p)));
    } else {
        d.par_chunks_mut(sw).enumerate().for_each(|(row, d)| pool(row, d, None));
    }
    let tn = target.pixels();
    let (o0, rest) = out.split_at_mut(tn);
    let (o1, o2) = rest.split_at_mut(tn);
    let tw = target.w;
    // The horizontal upsampling's taps of each target column, relative to the span.
    let columns: Vec<(usize, usize, f32, f32)> = (target.x..target.x + tw)
        .map(|x| {
            let (j0, j1, b0, b1) = up_taps(x, wc);
            (j0 - sx, j1 - sx, b0, b1)
        })
        .collect();
    // One coarse row of `src` upsampled vertically (over the span's coarse columns, into
    // `line`), then horizontally over the target's columns (into `up`).
    let upsample =
        |src: &[f32], c: usize, (i0, i1, a0, a1): (usize, usize, f32, f32), line: &mut [f32], up: &mut [f32]| {
            let r0 = &src[c * sw * sh + (i0 - sy) * sw..][..sw];
            let r1 = &src[c * sw * sh + (i1 - sy) * sw..][..sw];
            for ((l, &v0), &v1) in line.iter_mut().zip(r0).zip(r1) {
                *l = a0 * v0 + a1 * v1;
            }
            for (u, &(j0, j1, b0, b1)) in up.iter_mut().zip(&columns) {
                *u = b0 * line[j0] + b1 * line[j1];
            }
        };
    // Per row: the logistic of the blend (and of the gain, less one) once for the three
    // channels, then each channel's upsampled difference (and mean) and a fused update.
    struct Rows {
        line: Vec<f32>,
        up: Vec<f32>,
        mean: Vec<f32>,
        blend: Vec<f32>,
        gain: Vec<f32>,
    }
    let with_gain = gain.is_some();
    o0.par_chunks_mut(tw).zip(o1.par_chunks_mut(tw)).zip(o2.par_chunks_mut(tw)).enumerate().for_each_init(
        || {
            let g = if with_gain { tw } else { 0 };
            Rows {
                line: vec![0f32; sw],
                up: vec![0f32; tw],
                mean: vec![0f32; g],
                blend: vec![0f32; tw],
                gain: vec![0f32; g],
            }
        },
        |rows, (row, ((o0, o1), o2))| {
            let y = target.y + row;
            let taps = up_taps(y, hc);
            for (s, &b) in rows.blend.iter_mut().zip(&blend[y * w + target.x..][..tw]) {
                *s = sigmoid(b);
            }
            if let Some(g) = gain {
                for (s, &g) in rows.gain.iter_mut().zip(&g[y * w + target.x..][..tw]) {
                    *s = sigmoid(g) - 1.0;
                }
            }
            for (c, o) in [o0, o1, o2].into_iter().enumerate() {
                let Rows { line, up, mean, blend, gain } = &mut *rows;
                upsample(&d, c, taps, line, up);
                let fr = &f[c * sn + (y - span.y) * span.w + (target.x - span.x)..][..tw];
                if with_gain {
                    upsample(&p, c, taps, line, mean);
                    for j in 0..tw {
                        o[j] = fr[j] + blend[j] * up[j] + gain[j] * (fr[j] - mean[j]);
                    }
                } else {
                    for j in 0..tw {
                        o[j] = fr[j] + blend[j] * up[j];
                    }
                }
            }
        },
    );
}

/// The logistic function, through the branch-free exponential.
#[inline(always)]
fn sigmoid(x: f32) -> f32 {
    let e = exp_nonpositive::<Unfused>(-x.abs());
    let s = 1.0 / (1.0 + e);
    if x >= 0.0 {
        s
    } else {
        e * s
    }
}

/// The softmax-weighted k×k filter of `color` (`[3][h][w]`) by `logits` (`[k²][h][w]`) over
/// `rect`, into `out` (`[3][rect.h][rect.w]`); neighbours outside the level are clamped to
/// its edge.
fn filter(logits: &[f32], color: &[f32], w: usize, h: usize, k: usize, rect: Rect, out: &mut [f32]) {
    let rn = rect.pixels();
    let (out_r, rest) = out.split_at_mut(rn);
    let (out_g, out_b) = rest.split_at_mut(rn);
    let row = row_filter();
    let level = Level { logits, color, w, h, k };
    out_r
        .par_chunks_mut(rect.w)
        .zip(out_g.par_chunks_mut(rect.w))
        .zip(out_b.par_chunks_mut(rect.w))
        .enumerate()
        .for_each(|(i, ((or, og), ob))| row(&level, rect.y + i, rect.x, [or, og, ob]));
}

/// One level's inputs.
struct Level<'a> {
    logits: &'a [f32],
    color: &'a [f32],
    w: usize,
    h: usize,
    k: usize,
}

type RowFilter = fn(&Level, usize, usize, [&mut [f32]; 3]);

/// The row filter for this CPU, as in [`super::reconstruct`].
fn row_filter() -> RowFilter {
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma") {
            return |level, y, x0, out| {
                // SAFETY: the CPU supports AVX2 and FMA (checked above).
                unsafe { filter_row_avx2(level, y, x0, out) }
            };
        }
    }
    filter_row::<Unfused>
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn filter_row_avx2(level: &Level, y: usize, x0: usize, out: [&mut [f32]; 3]) {
    filter_row::<Fused>(level, y, x0, out)
}

/// Output row `y` of the level, columns `x0 .. x0 + out.len()`: the common kernel sides
/// with the side known at compile time, so that a kernel row's taps update the
/// accumulators once (in registers) instead of once per tap.
#[inline(always)]
fn filter_row<M: MulAdd>(level: &Level, y: usize, x0: usize, out: [&mut [f32]; 3]) {
    match level.k {
        3 => filter_row_k::<M, 3>(level, y, x0, out),
        5 => filter_row_k::<M, 5>(level, y, x0, out),
        7 => filter_row_k::<M, 7>(level, y, x0, out),
        _ => filter_row_k::<M, 1>(level, y, x0, out),
    }
}

/// [`filter_row`] with the taps of a kernel row taken `G` at a time (`G` divides `k`; 1 for
/// any odd `k`).
#[inline(always)]
fn filter_row_k<M: MulAdd, const G: usize>(level: &Level, y: usize, x0: usize, out: [&mut [f32]; 3]) {
    let &Level { logits, color, w, h, k } = level;
    debug_assert!(k % G == 0);
    let n = w * h;
    let r = k / 2;
    let cw = out[0].len();
    let start = y * w + x0;
    let mut max = vec![f32::NEG_INFINITY; cw];
    for t in 0..k * k {
        for (m, &v) in max.iter_mut().zip(&logits[t * n + start..][..cw]) {
            *m = m.max(v);
        }
    }
    let mut sum = vec![0f32; cw];
    let mut acc = [vec![0f32; cw], vec![0f32; cw], vec![0f32; cw]];
    let mut padded = [vec![0f32; cw + 2 * r], vec![0f32; cw + 2 * r], vec![0f32; cw + 2 * r]];
    for ky in 0..k {
        let sy = (y + ky).saturating_sub(r).min(h - 1);
        for (c, dst) in padded.iter_mut().enumerate() {
            pad_row(&color[c * n + sy * w..][..w], x0, r, dst);
        }
        for kx in (0..k).step_by(G) {
            let t = ky * k + kx;
            let l: [&[f32]; G] = std::array::from_fn(|g| &logits[(t + g) * n + start..][..cw]);
            let p: [[&[f32]; G]; 3] = std::array::from_fn(|c| std::array::from_fn(|g| &padded[c][kx + g..][..cw]));
            accumulate::<M, G>(l, p, &max, &mut sum, &mut acc);
        }
    }
    normalize(&acc, &sum, out);
}

/// `dst[j] = src[x0 + j − r]`, the index clamped to `src`.
fn pad_row(src: &[f32], x0: usize, r: usize, dst: &mut [f32]) {
    let first = x0 as isize - r as isize;
    let lo = (-first).clamp(0, dst.len() as isize) as usize;
    let hi = ((src.len() as isize - first).clamp(lo as isize, dst.len() as isize)) as usize;
    dst[..lo].fill(src[0]);
    dst[lo..hi].copy_from_slice(&src[(first + lo as isize) as usize..(first + hi as isize) as usize]);
    dst[hi..].fill(src[src.len() - 1]);
}

/// Pixels of context (at full resolution) the reconstruction of one output pixel reads,
/// from the color and from each level's kernel and blend logits: the halo tiles need for
/// the reconstruction alone, whatever the pixel's position on the pooling grid.
pub fn reach(kernel_size: usize, levels: usize) -> usize {
    let r = (kernel_size / 2) as i64;
    let mut worst = 0i64;
    for p in 0..(1i64 << levels) {
        // Interval of level-l pixels of o_l that o_0[p] depends on.
        let (mut lo, mut hi) = (p, p);
        for l in 0..levels {
            let s = 1i64 << l;
            let (next_lo, next_hi) = (lo.div_euclid(2) - 1, hi.div_euclid(2) + 1);
            // f_l is read where o_l is and, below the coarsest level, in the 2×2 blocks
            // pooled into the coarse pixels the upsampling reads.
            let (flo, fhi) = if l + 1 < levels { (lo.min(2 * next_lo), hi.max(2 * next_hi + 1)) } else { (lo, hi) };
            worst = worst.max(p - (flo - r) * s).max((fhi + r + 1) * s - 1 - p);
            (lo, hi) = (next_lo, next_hi);
        }
    }
    worst as usize
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A small deterministic generator (SplitMix64), so the tests need no crate.
    struct Rng(u64);

    impl Rng {
        fn next(&mut self) -> f32 {
            self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
            let mut z = self.0;
            z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
            ((z ^ (z >> 31)) >> 40) as f32 / (1u64 << 24) as f32
        }

        fn vec(&mut self, n: usize, lo: f32, hi: f32) -> Vec<f32> {
            (0..n).map(|_| lo + (hi - lo) * self.next()).collect()
        }
    }

    /// The spec, literally, in f64: every level whole, both terms upsampled, PyTorch's
    /// bilinear formula with its source-index arithmetic.
    fn scalar(
        k: usize,
        kernels: &[Vec<f32>],
        blends: &[Vec<f32>],
        gains: &[Vec<f32>],
        color: &[f32],
        w: usize,
        h: usize,
        linear_means: bool,
    ) -> Vec<f64> {
        type Img = (Vec<f64>, usize, usize); // [3][h][w]
        let levels = kernels.len();
        let pool = |(x, w, h): &Img| -> Img {
            let (wc, hc) = (w / 2, h / 2);
            let mut o = vec![0.0; 3 * wc * hc];
            for c in 0..3 {
                for y in 0..hc {
                    for i in 0..wc {
                        let at = |yy: usize, xx: usize| x[c * w * h + yy * w + xx];
                        o[c * wc * hc + y * wc + i] =
                            (at(2 * y, 2 * i) + at(2 * y, 2 * i + 1) + at(2 * y + 1, 2 * i) + at(2 * y + 1, 2 * i + 1))
                                / 4.0;
                    }
                }
            }
            (o, wc, hc)
        };
        let up = |(x, w, h): &Img| -> Img {
            let (wo, ho) = (2 * w, 2 * h);
            let src = |d: usize, n: usize| -> (usize, usize, f64) {
                let s = ((d as f64 + 0.5) / 2.0 - 0.5).max(0.0);
                let i0 = s.floor() as usize;
                let i1 = if i0 + 1 < n { i0 + 1 } else { i0 };
                (i0, i1, s - i0 as f64)
            };
            let mut o = vec![0.0; 3 * wo * ho];
            for c in 0..3 {
                for y in 0..ho {
                    let (y0, y1, ly) = src(y, *h);
                    for xx in 0..wo {
                        let (x0, x1, lx) = src(xx, *w);
                        let at = |a: usize, b: usize| x[c * w * h + a * w + b];
                        o[c * wo * ho + y * wo + xx] = (1.0 - ly) * ((1.0 - lx) * at(y0, x0) + lx * at(y0, x1))
                            + ly * ((1.0 - lx) * at(y1, x0) + lx * at(y1, x1));
                    }
                }
            }
            (o, wo, ho)
        };
        let filt = |logits: &[f32], (x, w, h): &Img| -> Img {
            let (w, h) = (*w, *h);
            let (n, r) = (w * h, (k / 2) as isize);
            let mut o = vec![0.0; 3 * n];
            for y in 0..h as isize {
                for xx in 0..w as isize {
                    let p = y as usize * w + xx as usize;
                    let mx = (0..k * k).map(|t| logits[t * n + p] as f64).fold(f64::MIN, f64::max);
                    let (mut s, mut acc) = (0.0, [0.0; 3]);
                    for dy in -r..=r {
                        for dx in -r..=r {
                            let t = ((dy + r) * k as isize + dx + r) as usize;
                            let e = (logits[t * n + p] as f64 - mx).exp();
                            let sy = (y + dy).clamp(0, h as isize - 1) as usize;
                            let sx = (xx + dx).clamp(0, w as isize - 1) as usize;
                            s += e;
                            for (c, a) in acc.iter_mut().enumerate() {
                                *a += e * x[c * n + sy * w + sx];
                            }
                        }
                    }
                    for c in 0..3 {
                        o[c * n + p] = acc[c] / s;
                    }
                }
            }
            (o, w, h)
        };
        let mut cs: Vec<Img> = vec![(color.iter().map(|&v| v as f64).collect(), w, h)];
        for l in 1..levels {
            let next = if linear_means {
                let (x, w, h) = &cs[l - 1];
                let linear = x.iter().map(|v| v.min(LINEAR_PYRAMID_MAX as f64).exp_m1()).collect();
                let (means, wc, hc) = pool(&(linear, *w, *h));
                (means.iter().map(|v| v.ln_1p()).collect(), wc, hc)
            } else {
                pool(&cs[l - 1])
            };
            cs.push(next);
        }
        let mut o = filt(&kernels[levels - 1], &cs[levels - 1]);
        for l in (0..levels - 1).rev() {
            let f = filt(&kernels[l], &cs[l]);
            let (uo, upf) = (up(&o), up(&pool(&f)));
            let (wl, hl) = (f.1, f.2);
            let mut next = vec![0.0; 3 * wl * hl];
            for c in 0..3 {
                for i in 0..wl * hl {
                    let sigmoid = |x: f32| 1.0 / (1.0 + (-(x as f64)).exp());
                    let (a, g) = (sigmoid(blends[l][i]), gains.get(l).map_or(1.0, |g| sigmoid(g[i])));
                    let j = c * wl * hl + i;
                    next[j] = upf.0[j] + g * (f.0[j] - upf.0[j]) + a * (uo.0[j] - upf.0[j]);
                }
            }
            o = (next, wl, hl);
        }
        o.0
    }

    fn case(
        rng: &mut Rng,
        k: usize,
        levels: usize,
        w: usize,
        h: usize,
        spread: f32,
    ) -> (Vec<Vec<f32>>, Vec<Vec<f32>>, Vec<f32>) {
        let kernels = (0..levels).map(|l| rng.vec(k * k * (w >> l) * (h >> l), -spread, spread)).collect();
        let blends = (0..levels - 1).map(|l| rng.vec((w >> l) * (h >> l), -6.0, 6.0)).collect();
        (kernels, blends, rng.vec(3 * w * h, 0.0, 2.0))
    }

    /// Detail-gain logits of every level below the coarsest.
    fn gains(rng: &mut Rng, levels: usize, w: usize, h: usize) -> Vec<Vec<f32>> {
        (0..levels - 1).map(|l| rng.vec((w >> l) * (h >> l), -6.0, 6.0)).collect()
    }

    fn run(
        k: usize,
        kernels: &[Vec<f32>],
        blends: &[Vec<f32>],
        color: &[f32],
        w: usize,
        h: usize,
        core: Rect,
    ) -> Vec<f32> {
        run_means(k, kernels, blends, &[], color, (w, h), core, false)
    }

    #[allow(clippy::too_many_arguments)]
    fn run_means(
        k: usize,
        kernels: &[Vec<f32>],
        blends: &[Vec<f32>],
        gains: &[Vec<f32>],
        color: &[f32],
        (w, h): (usize, usize),
        core: Rect,
        linear_means: bool,
    ) -> Vec<f32> {
        let p = Pyramid {
            kernel_size: k,
            kernels: kernels.iter().map(Vec::as_slice).collect(),
            blends: blends.iter().map(Vec::as_slice).collect(),
            gains: gains.iter().map(Vec::as_slice).collect(),
            linear_means,
        };
        let mut out = vec![0f32; 3 * core.pixels()];
        reconstruct(&p, color, w, h, core, &mut out);
        out
    }

    #[test]
    fn matches_a_scalar_implementation_of_the_spec() {
        let mut rng = Rng(1);
        for levels in 1..=5 {
            for k in [3, 5] {
                let m = 1 << (levels - 1);
                // Odd multiples of the pooling grid, so every level has odd sides somewhere.
                let (w, h) = (m * [7, 5, 3, 3, 3][levels - 1], m * [5, 3, 5, 3, 1][levels - 1]);
                let (kernels, blends, color) = case(&mut rng, k, levels, w, h, 8.0);
                let gains = gains(&mut rng, levels, w, h);
                for (linear, gains) in [(false, &[][..]), (true, &[][..]), (false, &gains[..]), (true, &gains[..])] {
                    let want = scalar(k, &kernels, &blends, gains, &color, w, h, linear);
                    let got = run_means(k, &kernels, &blends, gains, &color, (w, h), whole(w, h), linear);
                    let with_gains = !gains.is_empty();
                    for (i, (g, e)) in got.iter().zip(&want).enumerate() {
                        assert!(
                            (*g as f64 - e).abs() <= 2e-6 * e.abs().max(1.0),
                            "k {k}, L {levels}, {w}x{h}, linear means {linear}, gains {with_gains}, sample {i}: \
                             {g} vs {e}"
                        );
                    }
                }
            }
        }
    }

    #[test]
    fn a_core_equals_the_same_pixels_of_the_whole_region() {
        let mut rng = Rng(2);
        let (k, levels, w, h) = (5, 3, 36, 28);
        let (kernels, blends, color) = case(&mut rng, k, levels, w, h, 4.0);
        let gains = gains(&mut rng, levels, w, h);
        for (linear, gains) in [(false, &[][..]), (true, &[][..]), (true, &gains[..])] {
            let all = run_means(k, &kernels, &blends, gains, &color, (w, h), whole(w, h), linear);
            for core in [
                Rect { x: 0, y: 0, w: 1, h: 1 },
                Rect { x: 5, y: 3, w: 13, h: 11 },
                Rect { x: 35, y: 27, w: 1, h: 1 },
                Rect { x: 8, y: 20, w: 28, h: 8 },
            ] {
                let part = run_means(k, &kernels, &blends, gains, &color, (w, h), core, linear);
                for c in 0..3 {
                    for y in 0..core.h {
                        for x in 0..core.w {
                            let a = part[c * core.pixels() + y * core.w + x];
                            let b = all[c * w * h + (core.y + y) * w + core.x + x];
                            assert_eq!(a, b, "linear means {linear}, core {core:?}, c{c} ({x},{y})");
                        }
                    }
                }
            }
        }
    }

    /// Time of one component's reconstruction over a 768×768 region, 5 levels (run
    /// with `cargo test --release -- --ignored --nocapture reconstruction_speed`).
    #[test]
    #[ignore = "a timing, not a test"]
    fn reconstruction_speed() {
        // k = 9 takes the path without tap groups; the last case is the shipped network's
        // specular (detail gains, a pyramid of linear means).
        for (k, detail_gains) in [(5, false), (9, false), (5, true)] {
            let mut rng = Rng(9);
            let (levels, w, h) = (5, 768, 768);
            let (kernels, blends, color) = case(&mut rng, k, levels, w, h, 4.0);
            let gains = if detail_gains { gains(&mut rng, levels, w, h) } else { Vec::new() };
            let mut best = f64::MAX;
            for _ in 0..5 {
                let t = std::time::Instant::now();
                let out = run_means(k, &kernels, &blends, &gains, &color, (w, h), whole(w, h), detail_gains);
                std::hint::black_box(out);
                best = best.min(t.elapsed().as_secs_f64());
            }
            let taps = (w * h) as f64 * (k * k) as f64 * 4.0 / 3.0;
            println!(
                "768x768, L {levels}, k {k}, gains and linear means {detail_gains}: {:.1} ms, {:.2} ns per pixel-tap",
                best * 1e3,
                best * 1e9 / taps
            );
        }
    }

    #[test]
    fn a_blend_of_zero_keeps_the_fine_level() {
        // σ → 0: the fine filter alone, whatever the coarse levels hold; with an identity
        // kernel at level 0 the output is the input.
        let mut rng = Rng(3);
        let (k, w, h) = (3, 8, 6);
        let (mut kernels, _, color) = case(&mut rng, k, 2, w, h, 5.0);
        kernels[0] = (0..k * k).flat_map(|t| vec![if t == k * k / 2 { 40.0 } else { -40.0 }; w * h]).collect();
        let out = run(k, &kernels, &[vec![-80.0; w * h]], &color, w, h, whole(w, h));
        for (a, b) in out.iter().zip(&color) {
            assert!((a - b).abs() <= 1e-6, "{a} vs {b}");
        }
    }

    #[test]
    fn the_reach_covers_every_pixel_that_changes_the_output() {
        // Perturb one input sample at a time; the output at the centre must not move unless
        // the sample lies within `reach` of it.
        let mut rng = Rng(4);
        for (k, levels) in [(3, 1), (3, 3), (5, 2), (5, 4)] {
            let reach = reach(k, levels) as isize;
            let m = 1 << (levels - 1);
            let n = ((2 * reach as usize + 8) / m + 1) * m;
            let (w, h) = (n, m);
            let (kernels, blends, color) = case(&mut rng, k, levels, w, h, 3.0);
            for px in [w / 2, w / 2 + 1] {
                let core = Rect { x: px, y: 0, w: 1, h: 1 };
                let base = run(k, &kernels, &blends, &color, w, h, core);
                let mut farthest = 0isize;
                for x in 0..w {
                    let mut c = color.clone();
                    for y in 0..h {
                        c[y * w + x] += 1.0;
                    }
                    if run(k, &kernels, &blends, &c, w, h, core)[0] != base[0] {
                        farthest = farthest.max((x as isize - px as isize).abs());
                    }
                }
                assert!(
                    farthest <= reach,
                    "k {k}, L {levels}: a change {farthest} px away moved the output; reach {reach}"
                );
                assert!(farthest > 0);
            }
        }
        assert_eq!(reach(21, 1), 10);
    }
}
