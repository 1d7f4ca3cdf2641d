//! The networks' input compression, symlog(x) = sign(x)·ln(1 + |x|), for contract-v2 graphs
//! that leave it to the engine (`mcdenoise.input_compression` `engine`, docs/model-contract.md).
//!
//! Inside a graph the compression is five elementwise passes (Sign, Abs, Add, Log, Mul) over
//! every input tensor, about a quarter of ONNX Runtime's time for the default network; here
//! it is one pass over tensors the preprocessing has just written. `f32::ln_1p` is a libm
//! call per element, which stops vectorisation, hence the polynomial below: the same code
//! compiled for AVX2 with FMA where the CPU has them, chosen once at run time, as the
//! reconstruction's row filter is.
//!
//! The same polynomial gives the specular color's ln(1 + s) before the networks
//! ([`log1p_row`]), and [`expm1_row`] takes their specular output back from log space.

use rayon::prelude::*;

use super::reconstruct::{Fused, MulAdd, Unfused};

/// Elements per parallel chunk: large enough that scheduling costs nothing, small enough
/// that both threads get work on a 256² tile.
const CHUNK: usize = 1 << 14;

/// Replaces every element `x` of `data` by symlog(x), in parallel on the caller's rayon
/// pool. Inputs are finite (the preprocessing saturates them to ±1e20).
pub fn symlog_in_place(data: &mut [f32]) {
    let kernel = kernel::<Symlog>();
    data.par_chunks_mut(CHUNK).for_each(kernel);
}

/// A function applied to every element of a slice, written once for both builds.
trait Elementwise {
    fn at<M: MulAdd>(x: f32) -> f32;
}

struct Symlog;
struct Expm1;

impl Elementwise for Symlog {
    #[inline(always)]
    fn at<M: MulAdd>(x: f32) -> f32 {
        symlog::<M>(x)
    }
}

impl Elementwise for Expm1 {
    #[inline(always)]
    fn at<M: MulAdd>(x: f32) -> f32 {
        expm1::<M>(x)
    }
}

type Kernel = fn(&mut [f32]);

/// `E` over a slice in place, for this CPU.
fn kernel<E: Elementwise>() -> Kernel {
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma") {
            return |chunk| {
                // SAFETY: the CPU supports AVX2 and FMA (checked above).
                unsafe { slice_avx2::<E>(chunk) }
            };
        }
    }
    slice::<E, Unfused>
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn slice_avx2<E: Elementwise>(chunk: &mut [f32]) {
    slice::<E, Fused>(chunk)
}

#[inline(always)]
fn slice<E: Elementwise, M: MulAdd>(chunk: &mut [f32]) {
    for x in chunk {
        *x = E::at::<M>(*x);
    }
}

/// sign(x)·ln(1 + |x|) with log1p's accuracy (relative error below 3e-7 over the whole
/// finite range; `fast_symlog_is_accurate` checks it against f64).
///
/// `y = 1 + |x|` is split as `y = 2^k·m` with `m` in [√½, √2) through its bits; with
/// `f = m − 1` and `s = f / (2 + f)`, ln m = f − f²/2 + s·(f²/2 + R(s²)), where R is the
/// classic minimax polynomial of fdlibm's `logf` (error below 2^−25 on that interval); ln 2
/// is split in two so that `k·ln 2` is exact. The rounding of `1 + |x|` is undone by
/// scaling with `|x| / (y − 1)` (Goldberg's log1p), exact for small `|x|` where it matters.
#[inline(always)]
pub(super) fn symlog<M: MulAdd>(x: f32) -> f32 {
    // Given by their bits, as fdlibm does: ln 2 = LN2_HI + LN2_LO with LN2_HI's low 12
    // mantissa bits zero; LG1 … LG4 ≈ 2/3, 2/5, 2/7, 2/9 adjusted for minimax.
    const LN2_HI: f32 = f32::from_bits(0x3f31_7180);
    const LN2_LO: f32 = f32::from_bits(0x3717_f7d1);
    const LG1: f32 = f32::from_bits(0x3f2a_aaaa);
    const LG2: f32 = f32::from_bits(0x3ecc_ce13);
    const LG3: f32 = f32::from_bits(0x3e91_e9ee);
    const LG4: f32 = f32::from_bits(0x3e78_9e26);
    // Bits of √½: adding (1 − √½)'s offset moves the exponent boundary from 1 to √½.
    const SQRT_HALF_BITS: u32 = 0x3f35_04f3;
    let a = x.abs();
    let y = 1.0 + a;
    let bits = y.to_bits().wrapping_add(0x3f80_0000 - SQRT_HALF_BITS);
    let k = ((bits >> 23) as i32 - 0x7f) as f32;
    let m = f32::from_bits((bits & 0x007f_ffff) + SQRT_HALF_BITS);
    let f = m - 1.0;
    let s = f / (2.0 + f);
    let z = s * s;
    let w = z * z;
    let r = M::mul_add(w, M::mul_add(w, LG4, LG2), z * M::mul_add(w, LG3, LG1));
    let half_f2 = 0.5 * f * f;
    let ln_y = M::mul_add(k, LN2_HI, f - half_f2 + M::mul_add(s, half_f2 + r, k * LN2_LO));
    let d = y - 1.0;
    let log1p = if d == 0.0 { a } else { ln_y * (a / d) };
    log1p.copysign(x)
}

/// ln(1 + x) of every element of `row` (all ≥ 0: the specular color before the networks)
/// in place, on the calling thread: [`symlog`], which equals log1p on non-negative values,
/// compiled for AVX2 with FMA where the CPU has them. `f32::ln_1p` is a libm call per
/// element.
pub fn log1p_row(row: &mut [f32]) {
    kernel::<Symlog>()(row)
}

/// e^x − 1 of every element of `row` in place (the specular output back from log space),
/// on the calling thread, vectorised as [`log1p_row`] is; [`expm1`].
pub fn expm1_row(row: &mut [f32]) {
    kernel::<Expm1>()(row)
}

/// e^x − 1 with expm1's accuracy (relative error below 3e-7 where the result is finite;
/// `fast_expm1_is_accurate` checks it against f64), branch-free so that loops vectorise.
///
/// `x = n·ln 2 + f` with `n` an integer and `|f| ≤ ln 2 / 2` (Cody–Waite split of ln 2, as
/// in `reconstruct::exp_nonpositive`); `e^f − 1` is its Taylor series to `f⁸/8!` without
/// the constant term (relative error below 3e-8 on that interval), and
/// `e^x − 1 = 2^n·(e^f − 1) + (2^n − 1)`, exact in `f` for `n = 0`, where the result is
/// small, and without cancellation otherwise (|e^x − 1| > 0.29 there). `x` is clamped to
/// [−88, 88]: below, the result is −1 to f32 precision; above, the exponent saturates to
/// infinity, as `f32::exp_m1` does.
#[inline(always)]
pub(super) fn expm1<M: MulAdd>(x: f32) -> f32 {
    const LN2_HI: f32 = 0.693_359_4;
    const LN2_LO: f32 = -2.121_944_4e-4;
    const ROUND: f32 = 12_582_912.0;
    let big = x > 88.0;
    let x = x.clamp(-88.0, 88.0);
    let t = M::mul_add(x, std::f32::consts::LOG2_E, ROUND);
    let n = t - ROUND;
    let f = M::mul_add(n, -LN2_LO, M::mul_add(n, -LN2_HI, x));
    // (e^f − 1) / f = 1 + f/2 + f²/6 + … + f⁷/8!, by Horner.
    let mut p = 1.0 / 40320.0;
    for c in [1.0 / 5040.0, 1.0 / 720.0, 1.0 / 120.0, 1.0 / 24.0, 1.0 / 6.0, 0.5, 1.0] {
        p = M::mul_add(p, f, c);
    }
    let em1_f = p * f;
    // 2^n from its bits; n in [−127, 127] after the clamp, so 2^n is a normal or 2^−127.
    let ni = t.to_bits().wrapping_sub(ROUND.to_bits()) as i32;
    let two_n = f32::from_bits((ni.wrapping_add(127).max(0) << 23) as u32);
    let r = M::mul_add(two_n, em1_f, two_n - 1.0);
    if big {
        f32::INFINITY
    } else {
        r
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn worst_error<M: MulAdd>() -> (f64, f32) {
        let mut worst = (0f64, 0f32);
        let mut check = |x: f32| {
            let want = (x.abs() as f64).ln_1p().copysign(x as f64);
            let got = symlog::<M>(x) as f64;
            let err = if want == 0.0 { got.abs() } else { ((got - want) / want).abs() };
            if err > worst.0 {
                worst = (err, x);
            }
        };
        for x in [0.0, -0.0, f32::MIN_POSITIVE, 1e-30, 1e-8, 1.0, 2.0, 1e20, -1e20] {
            check(x);
        }
        // Logarithmic sweep from 1e-30 to 1e20, both signs, plus a dense linear sweep of
        // [0, 4] where the exponent boundaries of 1 + |x| lie.
        for i in 0..=500_000 {
            let x = 10f64.powf(-30.0 + 50.0 * i as f64 / 500_000.0) as f32;
            check(x);
            check(-x);
            check(4.0 * i as f32 / 500_000.0);
        }
        worst
    }

    #[test]
    fn fast_symlog_is_accurate() {
        for (name, (err, at)) in [("mul+add", worst_error::<Unfused>()), ("fma", worst_error::<Fused>())] {
            assert!(err < 3e-7, "{name}: relative error {err:e} at x = {at:e}");
        }
    }

    fn worst_expm1_error<M: MulAdd>() -> (f64, f32) {
        let mut worst = (0f64, 0f32);
        let mut check = |x: f32| {
            let want = (x as f64).exp_m1();
            let got = expm1::<M>(x) as f64;
            let err = if want == 0.0 { got.abs() } else { ((got - want) / want).abs() };
            if want.is_finite() && want < f32::MAX as f64 && err > worst.0 {
                worst = (err, x);
            }
        };
        for x in
            [0.0, -0.0, 1e-30, -1e-30, 1e-8, -1e-8, 0.3466, -0.3466, 0.3467, -0.3467, 1.0, -1.0, 88.0, -88.0, -100.0]
        {
            check(x);
        }
        // Dense over [−2, 2], where n goes from −3 to 3, and logarithmic to ±88.
        for i in 0..=400_000 {
            check(-2.0 + 4.0 * i as f32 / 400_000.0);
            let x = 10f64.powf(-30.0 + 31.94 * i as f64 / 400_000.0) as f32;
            check(x);
            check(-x);
        }
        worst
    }

    #[test]
    fn fast_expm1_is_accurate() {
        for (name, (err, at)) in [("mul+add", worst_expm1_error::<Unfused>()), ("fma", worst_expm1_error::<Fused>())] {
            assert!(err < 3e-7, "{name}: relative error {err:e} at x = {at:e}");
        }
        assert_eq!(expm1::<Unfused>(89.0), f32::INFINITY);
        assert_eq!(expm1::<Unfused>(-200.0), -1.0);
        let mut row: Vec<f32> = (0..1000).map(|i| (i as f32 - 500.0) * 0.01).collect();
        let want: Vec<f64> = row.iter().map(|&x| (x as f64).exp_m1()).collect();
        expm1_row(&mut row);
        for (g, w) in row.iter().zip(&want) {
            assert!((*g as f64 - w).abs() <= 3e-7 * w.abs(), "{g} vs {w}");
        }
        let mut row: Vec<f32> = (0..1000).map(|i| i as f32 * 0.37).collect();
        let want: Vec<f64> = row.iter().map(|&x| (x as f64).ln_1p()).collect();
        log1p_row(&mut row);
        for (g, w) in row.iter().zip(&want) {
            assert!((*g as f64 - w).abs() <= 3e-7 * w.abs(), "{g} vs {w}");
        }
    }

    #[test]
    fn in_place_matches_the_scalar_function_and_keeps_signs() {
        let mut data: Vec<f32> = (0..100_000).map(|i| (i as f32 - 50_000.0) * 0.37).collect();
        let want: Vec<f32> = data.iter().map(|&x| symlog::<Unfused>(x)).collect();
        symlog_in_place(&mut data);
        for (g, w) in data.iter().zip(&want) {
            assert!((g - w).abs() <= 2e-7 * w.abs().max(1e-30), "{g} vs {w}");
            assert_eq!(g.is_sign_negative(), w.is_sign_negative());
        }
        assert_eq!(data[50_000], 0.0);
    }
}
