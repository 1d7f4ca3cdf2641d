//! Image-quality metrics of a denoised image against a reference, as used in the
//! Monte Carlo denoising literature (KPCN, Lin et al. 2020).
//!
//! All take three planes (R, G, B) of `width * height` samples.
//!
//! - RelMSE: mean over pixels and channels of `(x − r)² / (r² + 0.01)`.
//! - DSSIM: `1 − SSIM`, SSIM with an 11×11 Gaussian window (σ = 1.5), `C1 = 0.01²`,
//!   `C2 = 0.03²`, on values clamped to [0, 1], averaged over the windows that fit inside
//!   the image and over the channels.
//! - PSNR: `10 log10(1 / MSE)` on values clamped to [0, 1].
//! - SMAPE: mean of `|x − r| / (|x| + |r| + 0.01)`.

use serde::{Deserialize, Serialize};

/// The four metrics of one image against its reference. PSNR of identical images is
/// infinite and is written as `null` in JSON.
#[derive(Clone, Copy, Debug, Serialize, Deserialize, PartialEq)]
pub struct Metrics {
    pub relmse: f64,
    pub dssim: f64,
    #[serde(with = "finite_or_null")]
    pub psnr: f64,
    pub smape: f64,
}

/// The noisy input and the denoised output, each against the reference.
#[derive(Clone, Copy, Debug, Serialize, Deserialize, PartialEq)]
pub struct Comparison {
    pub input: Metrics,
    pub output: Metrics,
}

impl Comparison {
    /// Metrics of `noisy` and `denoised` against `reference`, all `width * height`.
    pub fn of(noisy: Rgb<'_>, denoised: Rgb<'_>, reference: Rgb<'_>, width: usize, height: usize) -> Comparison {
        Comparison {
            input: Metrics::compute(noisy, reference, width, height),
            output: Metrics::compute(denoised, reference, width, height),
        }
    }
}

mod finite_or_null {
    use serde::{Deserialize, Deserializer, Serializer};

    pub fn serialize<S: Serializer>(v: &f64, s: S) -> Result<S::Ok, S::Error> {
        if v.is_finite() {
            s.serialize_f64(*v)
        } else {
            s.serialize_none()
        }
    }

    pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<f64, D::Error> {
        Ok(Option::<f64>::deserialize(d)?.unwrap_or(f64::INFINITY))
    }
}

pub type Rgb<'a> = [&'a [f32]; 3];

impl Metrics {
    pub fn compute(x: Rgb<'_>, r: Rgb<'_>, width: usize, height: usize) -> Metrics {
        Metrics { relmse: relmse(x, r), dssim: dssim(x, r, width, height), psnr: psnr(x, r), smape: smape(x, r) }
    }
}

fn mean_over(x: Rgb<'_>, r: Rgb<'_>, f: impl Fn(f64, f64) -> f64) -> f64 {
    let mut total = 0f64;
    let mut count = 0usize;
    for c in 0..3 {
        assert_eq!(x[c].len(), r[c].len(), "image and reference differ in size");
        total += x[c].iter().zip(r[c]).map(|(&a, &b)| f(a as f64, b as f64)).sum::<f64>();
        count += x[c].len();
    }
    total / count.max(1) as f64
}

pub fn relmse(x: Rgb<'_>, r: Rgb<'_>) -> f64 {
    mean_over(x, r, |a, b| (a - b).powi(2) / (b * b + 0.01))
}

pub fn smape(x: Rgb<'_>, r: Rgb<'_>) -> f64 {
    mean_over(x, r, |a, b| (a - b).abs() / (a.abs() + b.abs() + 0.01))
}

pub fn psnr(x: Rgb<'_>, r: Rgb<'_>) -> f64 {
    let mse = mean_over(x, r, |a, b| (a.clamp(0.0, 1.0) - b.clamp(0.0, 1.0)).powi(2));
    if mse == 0.0 {
        f64::INFINITY
    } else {
        10.0 * (1.0 / mse).log10()
    }
}

const SSIM_RADIUS: usize = 5;
const SSIM_SIGMA: f64 = 1.5;

fn gaussian_window() -> [f64; 2 * SSIM_RADIUS + 1] {
    let mut g = [0f64; 2 * SSIM_RADIUS + 1];
    for (i, v) in g.iter_mut().enumerate() {
        let d = i as f64 - SSIM_RADIUS as f64;
        *v = (-d * d / (2.0 * SSIM_SIGMA * SSIM_SIGMA)).exp();
    }
    let s: f64 = g.iter().sum();
    g.map(|v| v / s)
}

/// Separable Gaussian filter, "valid" region: `(w − 10) × (h − 10)` outputs.
fn blur_valid(p: &[f64], w: usize, h: usize, g: &[f64]) -> Vec<f64> {
    let k = g.len();
    let (ow, oh) = (w + 1 - k, h + 1 - k);
    let mut horiz = vec![0f64; ow * h];
    for y in 0..h {
        for x in 0..ow {
            horiz[y * ow + x] = (0..k).map(|i| g[i] * p[y * w + x + i]).sum();
        }
    }
    let mut out = vec![0f64; ow * oh];
    for y in 0..oh {
        for x in 0..ow {
            out[y * ow + x] = (0..k).map(|i| g[i] * horiz[(y + i) * ow + x]).sum();
        }
    }
    out
}

/// Mean SSIM of one channel; images smaller than the window are compared as one window.
fn ssim_channel(x: &[f32], r: &[f32], w: usize, h: usize) -> f64 {
    const C1: f64 = 0.01 * 0.01;
    const C2: f64 = 0.03 * 0.03;
    let a: Vec<f64> = x.iter().map(|&v| (v as f64).clamp(0.0, 1.0)).collect();
    let b: Vec<f64> = r.iter().map(|&v| (v as f64).clamp(0.0, 1.0)).collect();
    let (mu_a, mu_b, s_aa, s_bb, s_ab) = if w > 2 * SSIM_RADIUS && h > 2 * SSIM_RADIUS {
        let g = gaussian_window();
        let prod = |p: &[f64], q: &[f64]| p.iter().zip(q).map(|(u, v)| u * v).collect::<Vec<_>>();
        (
            blur_valid(&a, w, h, &g),
            blur_valid(&b, w, h, &g),
            blur_valid(&prod(&a, &a), w, h, &g),
            blur_valid(&prod(&b, &b), w, h, &g),
            blur_valid(&prod(&a, &b), w, h, &g),
        )
    } else {
        let n = a.len() as f64;
        let mean = |p: &[f64]| p.iter().sum::<f64>() / n;
        let m2 = |p: &[f64], q: &[f64]| p.iter().zip(q).map(|(u, v)| u * v).sum::<f64>() / n;
        (vec![mean(&a)], vec![mean(&b)], vec![m2(&a, &a)], vec![m2(&b, &b)], vec![m2(&a, &b)])
    };
    let n = mu_a.len();
    (0..n)
        .map(|i| {
            let (ma, mb) = (mu_a[i], mu_b[i]);
            let va = s_aa[i] - ma * ma;
            let vb = s_bb[i] - mb * mb;
            let cov = s_ab[i] - ma * mb;
            ((2.0 * ma * mb + C1) * (2.0 * cov + C2)) / ((ma * ma + mb * mb + C1) * (va + vb + C2))
        })
        .sum::<f64>()
        / n as f64
}

pub fn dssim(x: Rgb<'_>, r: Rgb<'_>, width: usize, height: usize) -> f64 {
    1.0 - (0..3).map(|c| ssim_channel(x[c], r[c], width, height)).sum::<f64>() / 3.0
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rgb(v: &[f32]) -> Rgb<'_> {
        [v, v, v]
    }

    #[test]
    fn relmse_by_hand() {
        // (0.5 − 1)² / (1 + 0.01) and (0 − 0)² / 0.01, averaged.
        let x = [0.5f32, 0.0];
        let r = [1.0f32, 0.0];
        let want = (0.25 / 1.01) / 2.0;
        assert!((relmse(rgb(&x), rgb(&r)) - want).abs() < 1e-12);
    }

    #[test]
    fn smape_by_hand() {
        let x = [2.0f32, 1.0];
        let r = [1.0f32, 1.0];
        let want = (1.0 / 3.01) / 2.0;
        assert!((smape(rgb(&x), rgb(&r)) - want).abs() < 1e-12);
    }

    #[test]
    fn psnr_by_hand() {
        // One of four samples off by 0.1 (after clamping 1.7 → 1): MSE = 0.01 / 4.
        let x = [0.5f32, 1.7, 0.2, 0.3];
        let r = [0.5f32, 0.9, 0.2, 0.3];
        let want = 10.0 * (4.0f64 / 0.01).log10();
        assert!((psnr(rgb(&x), rgb(&r)) - want).abs() < 1e-5, "{}", psnr(rgb(&x), rgb(&r)));
        assert_eq!(psnr(rgb(&r), rgb(&r)), f64::INFINITY);
    }

    #[test]
    fn dssim_of_identical_images_is_zero_and_of_constants_by_hand() {
        let (w, h) = (16, 13);
        let img: Vec<f32> = (0..w * h).map(|i| (i as f32 * 0.13).sin() * 0.5 + 0.5).collect();
        assert!(dssim(rgb(&img), rgb(&img), w, h).abs() < 1e-12);
        // Two constant images a, b: SSIM = (2ab + C1) / (a² + b² + C1) (variances are 0).
        let a = vec![0.2f32; w * h];
        let b = vec![0.6f32; w * h];
        let (fa, fb) = (0.2f32 as f64, 0.6f32 as f64);
        let c1 = 1e-4;
        let want = 1.0 - (2.0 * fa * fb + c1) / (fa * fa + fb * fb + c1);
        assert!((dssim(rgb(&a), rgb(&b), w, h) - want).abs() < 1e-9);
    }

    #[test]
    fn dssim_grows_with_noise() {
        let (w, h) = (32, 32);
        let img: Vec<f32> = (0..w * h).map(|i| (i % w) as f32 / w as f32).collect();
        let noisy = |amp: f32| -> Vec<f32> {
            img.iter().enumerate().map(|(i, v)| v + amp * (((i * 7919) % 17) as f32 / 8.0 - 1.0)).collect()
        };
        let (n1, n2) = (noisy(0.02), noisy(0.1));
        let d1 = dssim(rgb(&n1), rgb(&img), w, h);
        let d2 = dssim(rgb(&n2), rgb(&img), w, h);
        assert!(0.0 < d1 && d1 < d2, "{d1} {d2}");
    }
}
