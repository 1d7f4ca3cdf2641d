//! Kernel reconstruction: softmax over the 441 taps and the weighted sum of the 21×21
//! neighbourhood, fused.
//!
//! Each output row keeps only its running maximum, normalizer and three accumulators; the
//! softmax weights are never stored. The loops run tap-major over a row so that both the
//! planar logits and the color rows are read contiguously.

use rayon::prelude::*;

use super::contract::{KERNEL_RADIUS, KERNEL_SIZE, TAPS};
use super::preprocess::Rect;

/// Filters the pixels of `core` (frame coordinates, inside `region`).
///
/// `logits` is `[441][region.h][region.w]` and `color` `[3][region.h][region.w]`, both over
/// `region`. Neighbours outside the region are clamped to its edge; callers make the region
/// reach at least [`KERNEL_RADIUS`] past the core unless it stops at the frame's edge, so
/// this is the frame's edge replication. `out` receives `[3][core.h][core.w]`.
pub fn apply_kernels(logits: &[f32], color: &[f32], region: Rect, core: Rect, out: &mut [f32]) {
    let n = region.pixels();
    assert_eq!(logits.len(), TAPS * n, "logits do not cover the region");
    assert_eq!(color.len(), 3 * n, "color does not cover the region");
    assert_eq!(out.len(), 3 * core.pixels(), "output does not match the core");
    assert!(
        core.x >= region.x
            && core.y >= region.y
            && core.x + core.w <= region.x + region.w
            && core.y + core.h <= region.y + region.h
    );

    let cw = core.w;
    let (out_r, rest) = out.split_at_mut(core.pixels());
    let (out_g, out_b) = rest.split_at_mut(core.pixels());
    let filter = row_filter();
    out_r
        .par_chunks_mut(cw)
        .zip(out_g.par_chunks_mut(cw))
        .zip(out_b.par_chunks_mut(cw))
        .enumerate()
        .for_each(|(row, ((or, og), ob))| filter(logits, color, region, core, row, [or, og, ob]));
}

type RowFilter = fn(&[f32], &[f32], Rect, Rect, usize, [&mut [f32]; 3]);

/// The row filter for this CPU: the same code compiled for AVX2 with FMA where the CPU has
/// them (8 lanes and fused multiply-adds instead of SSE2's 4 lanes), chosen once at run time.
/// Written out rather than taken from a multiversioning crate because it is one function and
/// one feature test.
fn row_filter() -> RowFilter {
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma") {
            return |l, c, region, core, row, out| {
                // SAFETY: the CPU supports AVX2 and FMA (checked above).
                unsafe { filter_row_avx2(l, c, region, core, row, out) }
            };
        }
    }
    filter_row::<Unfused>
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn filter_row_avx2(logits: &[f32], color: &[f32], region: Rect, core: Rect, row: usize, out: [&mut [f32]; 3]) {
    filter_row::<Fused>(logits, color, region, core, row, out)
}

/// `a * b + c`, fused where the build has FMA. Without it `f32::mul_add` is a library call,
/// so the portable build multiplies and adds.
pub(super) trait MulAdd {
    fn mul_add(a: f32, b: f32, c: f32) -> f32;
}

pub(super) struct Fused;
pub(super) struct Unfused;

impl MulAdd for Fused {
    #[inline(always)]
    fn mul_add(a: f32, b: f32, c: f32) -> f32 {
        a.mul_add(b, c)
    }
}

impl MulAdd for Unfused {
    #[inline(always)]
    fn mul_add(a: f32, b: f32, c: f32) -> f32 {
        a * b + c
    }
}

/// Kernel taps handled per update of the accumulators: a kernel row's 21 taps in 7 groups of
/// 3, so that the row accumulators are read and written once per group instead of per tap.
const GROUP: usize = 3;
const _: () = assert!(KERNEL_SIZE % GROUP == 0, "a group must not straddle two kernel rows");

/// Output row `row` of `core`, in one pass over the logits, tap-major so that each tap's
/// logits and color row are read contiguously. The softmax runs online, one kernel row at a
/// time: that row's maximum is found first (its 21 logit rows then stay in L1 for the
/// weights), and the sums so far are rescaled when the running maximum grows. A separate
/// pass for the maximum would read all 441 logit rows from memory twice.
#[inline(always)]
fn filter_row<M: MulAdd>(logits: &[f32], color: &[f32], region: Rect, core: Rect, row: usize, out: [&mut [f32]; 3]) {
    let n = region.pixels();
    let rh = region.h as isize;
    let cw = core.w;
    let ry = (core.y - region.y + row) as isize;
    let rx0 = core.x - region.x;
    let row_start = ry as usize * region.w + rx0;
    let mut max = vec![f32::NEG_INFINITY; cw];
    let mut row_max = vec![f32::NEG_INFINITY; cw];
    let mut sum = vec![0f32; cw];
    let mut acc = [vec![0f32; cw], vec![0f32; cw], vec![0f32; cw]];
    // The three color rows a kernel row reads, edge-replicated by KERNEL_RADIUS on both
    // sides so that the inner loop reads them without bounds arithmetic.
    let mut padded =
        [vec![0f32; cw + 2 * KERNEL_RADIUS], vec![0f32; cw + 2 * KERNEL_RADIUS], vec![0f32; cw + 2 * KERNEL_RADIUS]];
    for ky in 0..KERNEL_SIZE {
        let taps = ky * KERNEL_SIZE..(ky + 1) * KERNEL_SIZE;
        row_max.copy_from_slice(&max);
        for k in taps.clone() {
            for (m, &v) in row_max.iter_mut().zip(&logits[k * n + row_start..][..cw]) {
                *m = m.max(v);
            }
        }
        {
            let [a0, a1, a2] = &mut acc;
            let (a0, a1, a2, sum, max, row_max) =
                (&mut a0[..cw], &mut a1[..cw], &mut a2[..cw], &mut sum[..cw], &mut max[..cw], &row_max[..cw]);
            for x in 0..cw {
                let scale = exp_nonpositive::<M>(max[x] - row_max[x]);
                (sum[x], a0[x], a1[x], a2[x], max[x]) =
                    (sum[x] * scale, a0[x] * scale, a1[x] * scale, a2[x] * scale, row_max[x]);
            }
        }
        let sy = (ry + ky as isize - KERNEL_RADIUS as isize).clamp(0, rh - 1) as usize;
        for (c, dst) in padded.iter_mut().enumerate() {
            pad_row(&color[c * n + sy * region.w..][..region.w], rx0, dst);
        }
        for kx in (0..KERNEL_SIZE).step_by(GROUP) {
            let k = taps.start + kx;
            let l: [&[f32]; GROUP] = std::array::from_fn(|g| &logits[(k + g) * n + row_start..][..cw]);
            let p: [[&[f32]; GROUP]; 3] = std::array::from_fn(|c| std::array::from_fn(|g| &padded[c][kx + g..][..cw]));
            accumulate::<M, GROUP>(l, p, &max[..cw], &mut sum[..cw], &mut acc);
        }
    }
    normalize(&acc, &sum[..cw], out);
}

/// Adds `G` taps of one kernel row to the softmax-weighted sums of a row of pixels, relative
/// to the running maximum `max`: `e = exp(l − max)`, `sum += e`, `acc[c] += e · p[c]`. The
/// inner loop of both reconstructions (contract v1 here, each pyramid level of v2 in
/// `multiscale`).
#[inline(always)]
pub(super) fn accumulate<M: MulAdd, const G: usize>(
    l: [&[f32]; G],
    p: [[&[f32]; G]; 3],
    max: &[f32],
    sum: &mut [f32],
    acc: &mut [Vec<f32>; 3],
) {
    let cw = sum.len();
    let [a0, a1, a2] = acc;
    let (a0, a1, a2, max) = (&mut a0[..cw], &mut a1[..cw], &mut a2[..cw], &max[..cw]);
    for x in 0..cw {
        let e: [f32; G] = std::array::from_fn(|g| exp_nonpositive::<M>(l[g][x] - max[x]));
        let (mut s, mut r, mut gr, mut b) = (sum[x], a0[x], a1[x], a2[x]);
        for g in 0..G {
            s += e[g];
            r = M::mul_add(e[g], p[0][g][x], r);
            gr = M::mul_add(e[g], p[1][g][x], gr);
            b = M::mul_add(e[g], p[2][g][x], b);
        }
        (sum[x], a0[x], a1[x], a2[x]) = (s, r, gr, b);
    }
}

/// `out[c] = acc[c] / sum`, pixel by pixel.
pub(super) fn normalize(acc: &[Vec<f32>; 3], sum: &[f32], out: [&mut [f32]; 3]) {
    let [or, og, ob] = out;
    for x in 0..sum.len() {
        let inv = 1.0 / sum[x];
        or[x] = acc[0][x] * inv;
        og[x] = acc[1][x] * inv;
        ob[x] = acc[2][x] * inv;
    }
}

/// `dst[j] = src[rx0 + j - KERNEL_RADIUS]`, the index clamped to `src`: a copy for the
/// columns inside the row, its end values beyond.
fn pad_row(src: &[f32], rx0: usize, dst: &mut [f32]) {
    let first = rx0 as isize - KERNEL_RADIUS as isize;
    let lo = (-first).clamp(0, dst.len() as isize) as usize;
    let hi = ((src.len() as isize - first).clamp(lo as isize, dst.len() as isize)) as usize;
    dst[..lo].fill(src[0]);
    dst[lo..hi].copy_from_slice(&src[(first + lo as isize) as usize..(first + hi as isize) as usize]);
    dst[hi..].fill(src[src.len() - 1]);
}

/// `exp(x)` for `x ≤ 0`, branch-free so that the loops above vectorize (Cephes' `expf`
/// scheme): `x = n ln 2 + f` with `n` an integer and `|f| ≤ ln 2 / 2` (Cody–Waite split of
/// ln 2 so `f` is exact), `e^f` by its degree-7 Taylor polynomial, `2^n` through the
/// exponent bits. Relative error below 3e-7. Arguments below −87 give ~1e-38, not 0, which
/// no softmax weight can tell apart.
#[inline(always)]
pub(super) fn exp_nonpositive<M: MulAdd>(x: f32) -> f32 {
    const LN2_HI: f32 = 0.693_359_4;
    const LN2_LO: f32 = -2.121_944_4e-4;
    // Adding and removing 1.5 * 2^23 rounds to the nearest integer without `floor`, which
    // SSE2 has no instruction for (a call per element would stop vectorization); the same
    // sum holds that integer in its low mantissa bits.
    const ROUND: f32 = 12_582_912.0;
    let x = if x > -87.0 { x } else { -87.0 };
    let t = M::mul_add(x, std::f32::consts::LOG2_E, ROUND);
    let n = t - ROUND;
    let f = M::mul_add(n, -LN2_LO, M::mul_add(n, -LN2_HI, x));
    let mut p = 1.0 / 5040.0;
    for c in [1.0 / 720.0, 1.0 / 120.0, 1.0 / 24.0, 1.0 / 6.0, 0.5, 1.0, 1.0] {
        p = M::mul_add(p, f, c);
    }
    let ni = t.to_bits().wrapping_sub(ROUND.to_bits()) as i32;
    f32::from_bits((ni.wrapping_add(127) << 23) as u32) * p
}

#[cfg(test)]
mod tests {
    #[test]
    fn fast_exp_is_accurate_on_the_softmax_range() {
        let mut worst = 0f64;
        for i in 0..=200_000 {
            let x = -(i as f32) * 87.0 / 200_000.0;
            let want = (x as f64).exp();
            let got = super::exp_nonpositive::<super::Unfused>(x) as f64;
            let fused = super::exp_nonpositive::<super::Fused>(x) as f64;
            worst = worst.max((fused - want).abs() / want);
            worst = worst.max((got - want).abs() / want);
        }
        assert!(worst < 3e-7, "worst relative error {worst}");
    }

    use super::*;

    fn ramp(n: usize, seed: f32) -> Vec<f32> {
        (0..n).map(|i| ((i as f32 * 0.37 + seed).sin() + 1.5) * 0.5).collect()
    }

    fn whole(w: usize, h: usize) -> Rect {
        Rect { x: 0, y: 0, w, h }
    }

    #[test]
    fn identity_kernel_reproduces_input() {
        let (w, h) = (23, 17);
        let n = w * h;
        let color = ramp(3 * n, 0.3);
        let mut logits = vec![-30.0f32; TAPS * n];
        let centre = KERNEL_RADIUS * KERNEL_SIZE + KERNEL_RADIUS;
        logits[centre * n..(centre + 1) * n].fill(30.0);
        let mut out = vec![0f32; 3 * n];
        apply_kernels(&logits, &color, whole(w, h), whole(w, h), &mut out);
        for (a, b) in out.iter().zip(&color) {
            assert!((a - b).abs() <= 1e-6 * b.abs().max(1.0), "{a} vs {b}");
        }
    }

    #[test]
    fn uniform_kernel_is_an_edge_replicated_box_filter() {
        let (w, h) = (30, 26);
        let n = w * h;
        let color = ramp(3 * n, 1.1);
        let logits = vec![0.25f32; TAPS * n];
        let mut out = vec![0f32; 3 * n];
        apply_kernels(&logits, &color, whole(w, h), whole(w, h), &mut out);
        let r = KERNEL_RADIUS as isize;
        for c in 0..3 {
            for y in 0..h as isize {
                for x in 0..w as isize {
                    let mut s = 0f64;
                    for dy in -r..=r {
                        for dx in -r..=r {
                            let sx = (x + dx).clamp(0, w as isize - 1) as usize;
                            let sy = (y + dy).clamp(0, h as isize - 1) as usize;
                            s += color[c * n + sy * w + sx] as f64;
                        }
                    }
                    let want = s / TAPS as f64;
                    let got = out[c * n + y as usize * w + x as usize] as f64;
                    assert!((got - want).abs() <= 1e-5 * want.abs(), "c{c} ({x},{y}): {got} vs {want}");
                }
            }
        }
    }

    #[test]
    fn matches_a_direct_softmax_whatever_row_holds_the_maximum() {
        // Logits spanning ±60 so that the online rescaling matters: early kernel rows hold
        // small values and a later row the maximum, or the other way round.
        let (w, h) = (31, 27);
        let n = w * h;
        let color = ramp(3 * n, 0.7);
        let logits: Vec<f32> =
            (0..TAPS * n).map(|i| (((i / n) * 37 + (i % n) * 11) % 240) as f32 * 0.5 - 60.0).collect();
        let mut out = vec![0f32; 3 * n];
        apply_kernels(&logits, &color, whole(w, h), whole(w, h), &mut out);
        let r = KERNEL_RADIUS as isize;
        for y in 0..h as isize {
            for x in 0..w as isize {
                let p = y as usize * w + x as usize;
                let max = (0..TAPS).map(|k| logits[k * n + p] as f64).fold(f64::MIN, f64::max);
                let (mut s, mut acc) = (0f64, [0f64; 3]);
                for dy in -r..=r {
                    for dx in -r..=r {
                        let k = ((dy + r) * KERNEL_SIZE as isize + dx + r) as usize;
                        let e = (logits[k * n + p] as f64 - max).exp();
                        let sx = (x + dx).clamp(0, w as isize - 1) as usize;
                        let sy = (y + dy).clamp(0, h as isize - 1) as usize;
                        s += e;
                        for (c, a) in acc.iter_mut().enumerate() {
                            *a += e * color[c * n + sy * w + sx] as f64;
                        }
                    }
                }
                for c in 0..3 {
                    let (got, want) = (out[c * n + p] as f64, acc[c] / s);
                    assert!((got - want).abs() <= 1e-5 * want.abs().max(1e-3), "c{c} ({x},{y}): {got} vs {want}");
                }
            }
        }
    }

    #[test]
    fn core_of_a_region_equals_the_same_pixels_of_the_whole() {
        let (w, h) = (40, 35);
        let n = w * h;
        let color = ramp(3 * n, 2.0);
        let logits: Vec<f32> = (0..TAPS * n).map(|i| ((i * 7919) % 113) as f32 * 0.05).collect();
        let mut full = vec![0f32; 3 * n];
        apply_kernels(&logits, &color, whole(w, h), whole(w, h), &mut full);

        // A core in the middle, with a region reaching KERNEL_RADIUS around it.
        let core = Rect { x: 12, y: 11, w: 9, h: 8 };
        let region = Rect { x: 2, y: 1, w: 29, h: 28 };
        let crop = |src: &[f32], channels: usize| -> Vec<f32> {
            let mut v = Vec::new();
            for c in 0..channels {
                for y in region.y..region.y + region.h {
                    v.extend_from_slice(&src[c * n + y * w + region.x..][..region.w]);
                }
            }
            v
        };
        let mut part = vec![0f32; 3 * core.pixels()];
        apply_kernels(&crop(&logits, TAPS), &crop(&color, 3), region, core, &mut part);
        for c in 0..3 {
            for y in 0..core.h {
                for x in 0..core.w {
                    let a = part[c * core.pixels() + y * core.w + x];
                    let b = full[c * n + (core.y + y) * w + core.x + x];
                    assert_eq!(a, b);
                }
            }
        }
    }
}
