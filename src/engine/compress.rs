//! The networks' input compression, symlog(x) = sign(x)·ln(1 + |x|), for contract-v2 graphs
//! that leave it to the engine (`mcdenoise.input_compression` `engine`, docs/model-contract.md).
//!
//! Inside a graph the compression is five elementwise passes (Sign, Abs, Add, Log, Mul) over
//! every input tensor, about a quarter of ONNX Runtime's time for the default network; here
//! it is one pass over tensors the preprocessing has just written. `f32::ln_1p` is a libm
//! call per element, which stops vectorisation, hence the polynomial below: the same code
//! compiled for AVX2 with FMA where the CPU has them, chosen once at run time, as the
//! reconstruction's row filter is.

use rayon::prelude::*;

use super::reconstruct::{Fused, MulAdd, Unfused};

/// Elements per parallel chunk: large enough that scheduling costs nothing, small enough
/// that both threads get work on a 256² tile.
const CHUNK: usize = 1 << 14;

/// Replaces every element `x` of `data` by symlog(x), in parallel on the caller's rayon
/// pool. Inputs are finite (the preprocessing saturates them to ±1e20).
pub fn symlog_in_place(data: &mut [f32]) {
    let kernel = kernel();
    data.par_chunks_mut(CHUNK).for_each(kernel);
}

type Kernel = fn(&mut [f32]);

fn kernel() -> Kernel {
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma") {
            return |chunk| {
                // SAFETY: the CPU supports AVX2 and FMA (checked above).
                unsafe { symlog_avx2(chunk) }
            };
        }
    }
    symlog_slice::<Unfused>
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn symlog_avx2(chunk: &mut [f32]) {
    symlog_slice::<Fused>(chunk)
}

#[inline(always)]
fn symlog_slice<M: MulAdd>(chunk: &mut [f32]) {
    for x in chunk {
        *x = symlog::<M>(*x);
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
