//! Albedo prefiltering: the noise of the albedo buffer shrunk, by its own variance, before
//! the networks see the frame.
//!
//! The diffuse component is divided by `albedo + ε` before filtering and multiplied by it
//! afterwards (KPCN's demodulation). Where a pixel's samples see different surfaces
//! (defocus, thin geometry, motion) its albedo is a noisy mean, and that noise comes back
//! into the output unfiltered with the remodulation. This stage replaces the albedo by a
//! shrunk version wherever its variance says its detail is noise, and keeps it exactly
//! where the variance is zero (in focus, every sample sees the same surface); the division,
//! the network's albedo features and the remodulation all use the result. docs/training.md
//! ("Where the DSSIM gap is") has the measurements.
//!
//! # Method
//!
//! 1. **Base**: the mean of each 4×4 block (blocks at the right and bottom edges average
//!    the pixels they have), upsampled bilinearly with half-pixel centres: for a pixel at
//!    `x`, the block coordinate `u = (x + ½) / 4 − ½`, clamped to `[0, n − 1]` for `n`
//!    blocks; likewise in `y`.
//! 2. **Detail** `δ_c = a_c − base_c` and its power `d² = (δ_R² + δ_G² + δ_B²) / 3`.
//! 3. **Shrinkage** of the detail by the albedo variance `v` (of the pixel mean; a mono
//!    `albedoVariance` as it is, an RGB one as its luminance):
//!    `s = τv / (τv + d² + 10⁻¹²)`, `τ = 4`, and
//!    `a'_c = a_c − s · δ_c`. Detail well above its noise (`d² ≫ τv`: an in-focus texture
//!    edge) is kept; detail at the level of the noise is pulled towards the base.
//!
//! Frames without an albedo variance (the buffer absent, or filled in as zeros) are left as
//! they are. The stage is off unless asked (`--albedo-prefilter on`): it lowers DSSIM in
//! defocus and raises it on thin in-focus geometry, whose edge pixels mix two surfaces and
//! have the variance of noise while their mean is right. The result depends only on the whole frame, not on tiling; training applies
//! the same function (`training/mcdenoise_train/preprocess.py`, `prefilter_albedo`).

use rayon::prelude::*;

use super::preprocess::luminance;
use crate::frame::{Buffer, Frame, Plane};

/// Side of the blocks whose means form the base.
pub const BLOCK: usize = 4;
/// Weight of the variance against the detail's power.
pub const TAU: f32 = 4.0;

/// Whether the albedo is prefiltered.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum AlbedoPrefilter {
    /// The albedo as the file gives it (the default: the prefilter costs thin geometry what
    /// it gains in defocus, docs/training.md).
    #[default]
    Off,
    /// Prefiltered where the frame has an albedo variance.
    On,
}

impl std::str::FromStr for AlbedoPrefilter {
    type Err = String;

    fn from_str(s: &str) -> Result<AlbedoPrefilter, String> {
        match s {
            "on" => Ok(Self::On),
            "off" => Ok(Self::Off),
            _ => Err(format!("unknown albedo prefilter `{s}` (expected on or off)")),
        }
    }
}

/// The frame with its albedo prefiltered, or `None` where nothing changes (prefiltering
/// off, or no albedo variance).
pub fn prefilter(frame: &Frame, mode: AlbedoPrefilter) -> Option<Frame> {
    if mode == AlbedoPrefilter::Off || !frame.has(Buffer::Albedo) || !frame.has(Buffer::AlbedoVariance) {
        return None;
    }
    if frame.missing_variances.iter().any(|m| m == Buffer::AlbedoVariance.name()) {
        return None;
    }
    let (w, h) = (frame.width, frame.height);
    let planes = frame.planes(Buffer::AlbedoVariance);
    let variance: Vec<f32> = match planes.as_slice() {
        [mono] => mono.to_vec(),
        _ => {
            let [vr, vg, vb] = frame.rgb(Buffer::AlbedoVariance).map(|p| p.to_vec());
            (0..w * h).map(|i| luminance(vr[i], vg[i], vb[i])).collect()
        }
    };
    let albedo: [Plane; 3] = std::array::from_fn(|c| frame.plane(Buffer::Albedo, c).to_vec());
    let filtered = shrink(&albedo, &variance, w, h);
    let mut out = frame.clone();
    for (plane, f) in out.planes_mut(Buffer::Albedo).iter_mut().zip(filtered) {
        *plane = f;
    }
    Some(out)
}

/// The method of the module doc on planes of `w × h`.
pub fn shrink(albedo: &[Plane; 3], variance: &[f32], w: usize, h: usize) -> [Plane; 3] {
    let base: [Plane; 3] = std::array::from_fn(|c| upsample(&block_means(&albedo[c], w, h), w, h));
    let mut out: [Plane; 3] = std::array::from_fn(|_| vec![0f32; w * h]);
    let [r, g, b] = &mut out;
    r.par_chunks_mut(w).zip(g.par_chunks_mut(w)).zip(b.par_chunks_mut(w)).enumerate().for_each(|(y, ((r, g), b))| {
        let rows = [r, g, b];
        for x in 0..w {
            let i = y * w + x;
            let detail: [f32; 3] = std::array::from_fn(|c| albedo[c][i] - base[c][i]);
            let power = (detail[0] * detail[0] + detail[1] * detail[1] + detail[2] * detail[2]) / 3.0;
            let v = variance[i];
            let v = if v.is_finite() && v > 0.0 { TAU * v } else { 0.0 };
            let s = (v / (v + power + 1e-12)).clamp(0.0, 1.0);
            for c in 0..3 {
                rows[c][x] = albedo[c][i] - s * detail[c];
            }
        }
    });
    out
}

/// Number of blocks along a side of `n` pixels.
fn blocks(n: usize) -> usize {
    n.div_ceil(BLOCK)
}

/// The mean of each block (row-major, `blocks(w) × blocks(h)`).
fn block_means(plane: &[f32], w: usize, h: usize) -> Vec<f32> {
    let (bw, bh) = (blocks(w), blocks(h));
    let mut sums = vec![0f64; bw * bh];
    for y in 0..h {
        let row = &plane[y * w..(y + 1) * w];
        let out = &mut sums[(y / BLOCK) * bw..(y / BLOCK + 1) * bw];
        for (x, v) in row.iter().enumerate() {
            out[x / BLOCK] += f64::from(*v);
        }
    }
    for by in 0..bh {
        let rows = (h - by * BLOCK).min(BLOCK);
        for bx in 0..bw {
            let cols = (w - bx * BLOCK).min(BLOCK);
            sums[by * bw + bx] /= (rows * cols) as f64;
        }
    }
    sums.into_iter().map(|s| s as f32).collect()
}

/// The two blocks around pixel `i` of a side with `n` blocks, and the weight of the second.
fn taps(i: usize, n: usize) -> (usize, usize, f32) {
    let u = ((i as f32 + 0.5) / BLOCK as f32 - 0.5).clamp(0.0, (n - 1) as f32);
    let j0 = u.floor() as usize;
    (j0, (j0 + 1).min(n - 1), u - j0 as f32)
}

/// Block means back to `w × h`, bilinearly.
fn upsample(means: &[f32], w: usize, h: usize) -> Plane {
    let (bw, bh) = (blocks(w), blocks(h));
    let xs: Vec<(usize, usize, f32)> = (0..w).map(|x| taps(x, bw)).collect();
    let mut out = vec![0f32; w * h];
    out.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        let (y0, y1, ty) = taps(y, bh);
        let (r0, r1) = (&means[y0 * bw..(y0 + 1) * bw], &means[y1 * bw..(y1 + 1) * bw]);
        for (o, &(x0, x1, tx)) in row.iter_mut().zip(&xs) {
            let top = r0[x0] + tx * (r0[x1] - r0[x0]);
            let bottom = r1[x0] + tx * (r1[x1] - r1[x0]);
            *o = top + ty * (bottom - top);
        }
    });
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn lcg(seed: &mut u64) -> f32 {
        *seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        (*seed >> 40) as f32 / (1u64 << 24) as f32
    }

    #[test]
    fn zero_variance_keeps_the_albedo_exactly() {
        let (w, h) = (13, 9);
        let mut seed = 1;
        let albedo: [Plane; 3] = std::array::from_fn(|_| (0..w * h).map(|_| lcg(&mut seed)).collect());
        let out = shrink(&albedo, &vec![0.0; w * h], w, h);
        assert_eq!(out, albedo);
    }

    #[test]
    fn noise_at_its_variance_is_pulled_to_the_base_and_strong_detail_is_kept() {
        // A flat 0.5 albedo with ±0.05 noise whose variance says so, and one pixel of an
        // in-focus texture edge (0.5 → 0.9) with no variance.
        let (w, h) = (16, 16);
        let mut seed = 7;
        let noisy: Plane = (0..w * h).map(|_| 0.5 + 0.1 * (lcg(&mut seed) - 0.5)).collect();
        let mut variance = vec![0.05f32 * 0.05 / 3.0; w * h];
        let mut plane = noisy.clone();
        plane[5 * w + 5] = 0.9;
        variance[5 * w + 5] = 0.0;
        let out = shrink(&[plane.clone(), plane.clone(), plane.clone()], &variance, w, h);
        let err = |p: &[f32]| {
            p.iter().enumerate().filter(|(i, _)| *i != 5 * w + 5).map(|(_, v)| (v - 0.5).powi(2)).sum::<f32>()
        };
        assert!(err(&out[0]) < 0.5 * err(&plane), "noise kept: {} of {}", err(&out[0]), err(&plane));
        assert_eq!(out[0][5 * w + 5], 0.9, "a pixel without variance keeps its value");
    }

    #[test]
    fn the_base_is_bilinear_between_block_centres() {
        // A ramp along x, constant along y: block means are the ramp at the block centres
        // (x = 4j + 1.5), and the upsampled base is the ramp itself between the first and
        // last centres.
        let (w, h) = (16, 5);
        let plane: Plane = (0..w * h).map(|i| (i % w) as f32).collect();
        let means = block_means(&plane, w, h);
        assert_eq!(&means[..4], &[1.5, 5.5, 9.5, 13.5]);
        assert_eq!(means[4], 1.5, "the partial bottom block row averages the rows it has");
        let base = upsample(&means, w, h);
        for x in 2..14 {
            assert!((base[x] - x as f32).abs() < 1e-5, "x {x}: {}", base[x]);
        }
        assert_eq!(base[0], 1.5, "clamped before the first centre");
        assert_eq!(base[15], 13.5, "clamped after the last centre");
    }

    #[test]
    fn a_frame_without_albedo_variance_is_left_alone() {
        let planes = super::super::synthetic_planes(8, 8, false);
        let named: Vec<(String, Plane)> =
            planes.into_iter().filter(|(n, _)| !n.starts_with("albedoVariance")).collect();
        let maps = crate::frame::ChannelMaps::default();
        let mut frame = Frame::from_planes(8, 8, named, crate::frame::layout::REQUIRED, &maps).expect("frame");
        assert!(prefilter(&frame, AlbedoPrefilter::On).is_none(), "no albedo variance");
        frame.fill_missing_variances();
        assert!(prefilter(&frame, AlbedoPrefilter::On).is_none(), "an albedo variance filled in as zeros");
        let full = super::super::synthetic_frame(8, 8, false);
        assert!(prefilter(&full, AlbedoPrefilter::Off).is_none());
        assert!(prefilter(&full, AlbedoPrefilter::On).is_some());
    }
}
