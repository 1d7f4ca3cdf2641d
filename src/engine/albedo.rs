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
//! Non-local means with variance-normalised patch distances, the feature prefilter of the
//! Monte Carlo denoising literature (Rousselle, Manzi and Zwicker 2013, after Buades et
//! al.): a pixel `p` becomes the weighted mean of the pixels `q` of the `7 × 7` window
//! around it (`RADIUS` 3),
//!
//! 1. per pixel pair, `d(p, q) = (⅓ Σ_c (a_c(p) − a_c(q))² − α (v_p + min(v_p, v_q))) /
//!    (ε + k² (v_p + v_q))`, `v` the variance of the albedo's pixel mean (a mono
//!    `albedoVariance` as it is, an RGB one as its luminance), `α = 1`, `k = 0.7`,
//!    `ε = 10⁻¹⁰`: the squared difference less what the noise explains, in units of the
//!    noise;
//! 2. the patch distance `D(p, q)`: the mean of `d` over the `3 × 3` patches around `p` and
//!    `q` (`PATCH` 1), taken with the same offset;
//! 3. the weight `exp(−max(D, 0))`, the centre's own weight 1.
//!
//! Coordinates outside the frame are clamped to its edge, for the window and for the patch.
//! A pixel whose albedo exceeds 1 in a channel (an emitter's strength, which some renderers
//! write into the albedo pass, or a pixel that mixes one in) is no surface's reflectance:
//! it keeps its value and takes no part in its neighbours' means, whose variance-normalised
//! distance would otherwise let its huge variance pull them towards it.
//! Pixels within their noise of each other along a patch average; a thin line in focus keeps
//! its value, because its neighbours along the line match its patch and those across it do
//! not. A frame without variance is kept exactly (pairs without variance weigh nothing
//! unless they are equal); a pixel without variance beside noisy ones takes in those within
//! their noise of it.
//! A 4 × 4 block-mean base shrunk by the variance (the first form of this stage) blurred
//! thin geometry (docs/training.md).
//!
//! Frames without an albedo variance (the buffer absent, or filled in as zeros) are left as
//! they are. The result depends only on the whole frame, not on tiling; training applies the
//! same function (`training/mcdenoise_train/preprocess.py`, `prefilter_albedo`).

use rayon::prelude::*;

use super::preprocess::luminance;
use super::reconstruct::{exp_nonpositive, Unfused};
use crate::frame::{Buffer, Frame, Plane, PlaneRef};

/// Radius of the search window (7 × 7).
pub const RADIUS: usize = 3;
/// Radius of the patches compared (3 × 3).
pub const PATCH: usize = 1;
/// Distances in units of `k²` times the pair's variance.
pub const K: f32 = 0.7;
/// Share of the pair's variance subtracted from their squared difference.
const ALPHA: f32 = 1.0;
/// Keeps pairs without variance apart unless they are equal.
const EPS: f32 = 1e-10;
/// Albedos above this in any channel are not a surface's reflectance (a renderer's albedo
/// pass may carry an emitter's strength, and pixels that mix one in): such pixels keep
/// their value and weigh nothing in their neighbours' means.
pub const MAX_REFLECTANCE: f32 = 1.0;

/// Whether the albedo is prefiltered.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum AlbedoPrefilter {
    /// The albedo as the file gives it.
    Off,
    /// Prefiltered where the frame has an albedo variance (the default: lower RelMSE and
    /// DSSIM on every validation and development scene, docs/training.md).
    #[default]
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
            let [vr, vg, vb] = frame.rgb(Buffer::AlbedoVariance);
            (0..w * h).map(|i| luminance(vr.get(i), vg.get(i), vb.get(i))).collect()
        }
    };
    let filtered = nl_means(frame.rgb(Buffer::Albedo), variance, w, h);
    // A clone shares the frame's buffers; the albedo is replaced, not copied. It is kept as
    // the file's albedo is (f16 where it fits, frame/plane.rs): at 4K, 50 MB less than f32
    // through inference, where a frame's memory peaks.
    let mut out = frame.clone();
    out.set_planes(Buffer::Albedo, filtered.into());
    Some(out)
}

/// The method of the module doc on planes of `w × h` (`variance` is cleaned in place:
/// non-finite and negative values become 0). Beyond its output and `variance` it holds only
/// each band's rows, so that a 4K frame costs little memory.
pub fn nl_means(albedo: [PlaneRef<'_>; 3], mut variance: Vec<f32>, w: usize, h: usize) -> [Plane; 3] {
    for v in &mut variance {
        if !(v.is_finite() && *v > 0.0) {
            *v = 0.0;
        }
    }
    let frame = Planes { albedo, variance, w, h };
    let band_filter = band_filter();
    let mut out: [Plane; 3] = std::array::from_fn(|_| vec![0f32; w * h]);
    let [r, g, b] = &mut out;
    // Bands of rows in parallel; each band computes the distances of its rows and a
    // margin of `PATCH` rows for every offset, and keeps its own sums.
    r.par_chunks_mut(BAND * w)
        .zip(g.par_chunks_mut(BAND * w))
        .zip(b.par_chunks_mut(BAND * w))
        .enumerate()
        .for_each(|(band, ((r, g), b))| band_filter(&frame, band * BAND, [r, g, b]));
    out
}

/// Rows per parallel band.
const BAND: usize = 32;

/// The frame's planes as the filter reads them.
struct Planes<'a> {
    albedo: [PlaneRef<'a>; 3],
    variance: Vec<f32>,
    w: usize,
    h: usize,
}

type BandFilter = fn(&Planes<'_>, usize, [&mut [f32]; 3]);

/// The band filter for this CPU: the same code compiled for AVX2 with FMA where the CPU has
/// them, chosen once at run time, as in [`super::reconstruct`], whose vectorising
/// exponential it shares.
fn band_filter() -> BandFilter {
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma") {
            return |planes, y0, out| {
                // SAFETY: the CPU supports AVX2 and FMA (checked above).
                unsafe { filter_band_avx2(planes, y0, out) }
            };
        }
    }
    filter_band
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn filter_band_avx2(planes: &Planes<'_>, y0: usize, out: [&mut [f32]; 3]) {
    filter_band(planes, y0, out)
}

/// `out[x] = row[clamp(x + dx)]`: a row shifted by `dx` with its edge pixels repeated.
#[inline(always)]
fn shifted(row: &[f32], dx: isize, out: &mut [f32]) {
    let w = row.len() as isize;
    // Columns whose neighbour is inside the row: `0 ≤ x + dx < w`.
    let lo = (-dx).clamp(0, w) as usize;
    let hi = (w - dx).clamp(0, w) as usize;
    if lo < hi {
        out[lo..hi].copy_from_slice(&row[(lo as isize + dx) as usize..(hi as isize + dx) as usize]);
    }
    out[..lo].fill(row[0]);
    out[hi.max(lo)..].fill(row[row.len() - 1]);
}

/// Rows `y0 ..` of the output (as many as `out` holds) for every offset of the window.
#[inline(always)]
fn filter_band(planes: &Planes<'_>, y0: usize, out: [&mut [f32]; 3]) {
    let Planes { albedo, variance, w, h } = planes;
    let (w, h) = (*w, *h);
    let rows = out[0].len() / w;
    // The rows the band reads, as f32: its own, the patch margin and the window's reach.
    let reach = PATCH + RADIUS;
    let (lo, hi) = (y0.saturating_sub(reach), (y0 + rows + reach).min(h));
    let albedo: [Vec<f32>; 3] = std::array::from_fn(|c| {
        let mut rows = vec![0f32; (hi - lo) * w];
        albedo[c].read(lo * w, &mut rows);
        rows
    });
    // 1 for a reflectance, 0 for what is not (NaN included); a weight factor.
    let reflectance: Vec<f32> =
        (0..(hi - lo) * w).map(|i| f32::from(u8::from(albedo.iter().all(|p| p[i] <= MAX_REFLECTANCE)))).collect();
    let v = &variance[lo * w..hi * w];
    let local = |y: usize| (y - lo) * w..(y - lo + 1) * w;
    let margin = rows + 2 * PATCH;
    let clamp = |i: isize, n: usize| i.clamp(0, n as isize - 1) as usize;
    let k2 = K * K;
    let inv_area = 1.0 / ((2 * PATCH + 1) * (2 * PATCH + 1)) as f32;
    // Per margin row: the shifted neighbour rows (albedo, variance, reflectance), the pair
    // distances and their sums across the patch's width.
    let mut aq: [Vec<f32>; 3] = std::array::from_fn(|_| vec![0f32; margin * w]);
    let mut vq = vec![0f32; margin * w];
    let mut rq = vec![0f32; margin * w];
    let mut d = vec![0f32; margin * w];
    let mut dh = vec![0f32; margin * w];
    let mut num: [Vec<f32>; 3] = std::array::from_fn(|_| vec![0f32; rows * w]);
    let mut den = vec![0f32; rows * w];
    let mut sum = vec![0f32; w];
    let radius = RADIUS as isize;
    for dy in -radius..=radius {
        for dx in -radius..=radius {
            for m in 0..margin {
                let y = clamp(y0 as isize + m as isize - PATCH as isize, h);
                let yq = clamp(y as isize + dy, h);
                let span = m * w..(m + 1) * w;
                let (p_row, q_row) = (local(y), local(yq));
                for c in 0..3 {
                    shifted(&albedo[c][q_row.clone()], dx, &mut aq[c][span.clone()]);
                }
                shifted(&v[q_row.clone()], dx, &mut vq[span.clone()]);
                shifted(&reflectance[q_row], dx, &mut rq[span.clone()]);
                let (a0, a1, a2) = (&albedo[0][p_row.clone()], &albedo[1][p_row.clone()], &albedo[2][p_row.clone()]);
                let (q0, q1, q2) = (&aq[0][span.clone()], &aq[1][span.clone()], &aq[2][span.clone()]);
                let (vp, vqs) = (&v[p_row], &vq[span.clone()]);
                let row = &mut d[span.clone()];
                let (a0, a1, a2, q0, q1, q2, vp, vqs) =
                    (&a0[..w], &a1[..w], &a2[..w], &q0[..w], &q1[..w], &q2[..w], &vp[..w], &vqs[..w]);
                for x in 0..w {
                    let (e0, e1, e2) = (a0[x] - q0[x], a1[x] - q1[x], a2[x] - q2[x]);
                    let diff = (e0 * e0 + e1 * e1 + e2 * e2) * (1.0 / 3.0);
                    let (vp, vq) = (vp[x], vqs[x]);
                    row[x] = (diff - ALPHA * (vp + vp.min(vq))) / (EPS + k2 * (vp + vq));
                }
                // Sums across the patch's width, edges clamped.
                let (row, sums) = (&d[span.clone()], &mut dh[span]);
                sums.copy_from_slice(row);
                for j in 1..=PATCH {
                    if w > 2 * j {
                        for (s, (l, r)) in sums[j..w - j].iter_mut().zip(row.iter().zip(&row[2 * j..])) {
                            *s += l + r;
                        }
                    }
                    for x in (0..j.min(w)).chain(w.saturating_sub(j).max(j)..w) {
                        sums[x] += row[clamp(x as isize - j as isize, w)] + row[clamp(x as isize + j as isize, w)];
                    }
                }
            }
            for yr in 0..rows {
                let m = yr + PATCH;
                let span = m * w..(m + 1) * w;
                let out_span = yr * w..(yr + 1) * w;
                // Sums across the patch's height.
                sum.copy_from_slice(&dh[yr * w..(yr + 1) * w]);
                for i in 1..=2 * PATCH {
                    for (s, d) in sum.iter_mut().zip(&dh[(yr + i) * w..(yr + i + 1) * w]) {
                        *s += d;
                    }
                }
                let [nr, ng, nb] = &mut num;
                let (nr, ng, nb, den) = (
                    &mut nr[out_span.clone()],
                    &mut ng[out_span.clone()],
                    &mut nb[out_span.clone()],
                    &mut den[out_span],
                );
                let (q0, q1, q2, rq) = (&aq[0][span.clone()], &aq[1][span.clone()], &aq[2][span.clone()], &rq[span]);
                let (nr, ng, nb, den, q0, q1, q2, rq, sum) = (
                    &mut nr[..w],
                    &mut ng[..w],
                    &mut nb[..w],
                    &mut den[..w],
                    &q0[..w],
                    &q1[..w],
                    &q2[..w],
                    &rq[..w],
                    &sum[..w],
                );
                for x in 0..w {
                    let weight = exp_nonpositive::<Unfused>((-sum[x] * inv_area).min(0.0)) * rq[x];
                    nr[x] += weight * q0[x];
                    ng[x] += weight * q1[x];
                    nb[x] += weight * q2[x];
                    den[x] += weight;
                }
            }
        }
    }
    let first = (y0 - lo) * w;
    for (c, o) in out.into_iter().enumerate() {
        for (i, o) in o.iter_mut().enumerate() {
            let p = first + i;
            *o = if reflectance[p] > 0.0 { num[c][i] / den[i] } else { albedo[c][p] };
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn lcg(seed: &mut u64) -> f32 {
        *seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        (*seed >> 40) as f32 / (1u64 << 24) as f32
    }

    #[test]
    fn bands_give_the_method_written_out() {
        // Three bands and a partial one, edges clamped, an emitter above 1: the method of
        // the module doc pixel by pixel in f64; and frames narrower than the window.
        for (w, h) in [(11, 3 * BAND + 5), (1, 1), (1, 9), (9, 1), (2, 2), (3, 5)] {
            written_out(w, h);
        }
    }

    fn written_out(w: usize, h: usize) {
        let mut seed = 3;
        let mut albedo: [Plane; 3] = std::array::from_fn(|_| (0..w * h).map(|_| lcg(&mut seed)).collect());
        if h > 40 {
            albedo[1][40 * w + 4] = 30.0;
        }
        let v: Vec<f32> = (0..w * h).map(|i| if i % 7 == 0 { 0.0 } else { 0.02 * lcg(&mut seed) }).collect();
        let got = nl_means(albedo.each_ref().map(|p| PlaneRef::F32(p)), v.clone(), w, h);
        let at = |y: isize, x: isize| y.clamp(0, h as isize - 1) as usize * w + x.clamp(0, w as isize - 1) as usize;
        let refl = |i: usize| albedo.iter().all(|p| p[i] <= MAX_REFLECTANCE);
        let d = |p: usize, q: usize| {
            let diff: f64 =
                (0..3).map(|c| (f64::from(albedo[c][p]) - f64::from(albedo[c][q])).powi(2)).sum::<f64>() / 3.0;
            let (vp, vq) = (f64::from(v[p]), f64::from(v[q]));
            (diff - (vp + vp.min(vq))) / (1e-10 + f64::from(K * K) * (vp + vq))
        };
        let (r, f) = (RADIUS as isize, PATCH as isize);
        for y in 0..h as isize {
            for x in 0..w as isize {
                let p = at(y, x);
                let (mut num, mut den) = ([0f64; 3], 0f64);
                for dy in -r..=r {
                    for dx in -r..=r {
                        let q = at(y + dy, x + dx);
                        if !refl(q) {
                            continue;
                        }
                        let mut patch = 0.0;
                        for i in -f..=f {
                            for j in -f..=f {
                                let (py, px) = ((y + i).clamp(0, h as isize - 1), (x + j).clamp(0, w as isize - 1));
                                patch += d(at(py, px), at(py + dy, px + dx));
                            }
                        }
                        let weight = (-(patch / ((2 * f + 1) * (2 * f + 1)) as f64).max(0.0)).exp();
                        for c in 0..3 {
                            num[c] += weight * f64::from(albedo[c][q]);
                        }
                        den += weight;
                    }
                }
                for c in 0..3 {
                    let want = if refl(p) { num[c] / den } else { f64::from(albedo[c][p]) };
                    let g = f64::from(got[c][p]);
                    assert!((g - want).abs() <= 1e-5 * want.abs().max(1e-2), "({y}, {x}) channel {c}: {g}, not {want}");
                }
            }
        }
    }

    #[test]
    fn zero_variance_keeps_the_albedo_exactly() {
        let (w, h) = (13, 19);
        let mut seed = 1;
        let albedo: [Plane; 3] = std::array::from_fn(|_| (0..w * h).map(|_| lcg(&mut seed)).collect());
        let out = nl_means(albedo.each_ref().map(|p| PlaneRef::F32(p)), vec![0.0; w * h], w, h);
        assert_eq!(out, albedo);
    }

    #[test]
    fn noise_at_its_variance_is_averaged_and_a_thin_line_is_kept() {
        // A flat 0.5 albedo with ±0.05 noise whose variance says so, crossed by a vertical
        // line one pixel wide (0.9, as noisy): the line's neighbours along it match its
        // patches, those across it do not.
        let (w, h) = (24, 24);
        let mut seed = 7;
        let line = 10;
        let plane: Plane =
            (0..w * h).map(|i| if i % w == line { 0.9 } else { 0.5 } + 0.1 * (lcg(&mut seed) - 0.5)).collect();
        let variance = vec![0.1f32 * 0.1 / 12.0; w * h];
        let out = nl_means([PlaneRef::F32(&plane), PlaneRef::F32(&plane), PlaneRef::F32(&plane)], variance, w, h);
        let err = |p: &[f32]| -> f32 {
            p.iter().enumerate().filter(|(i, _)| i % w != line).map(|(_, v)| (v - 0.5).powi(2)).sum()
        };
        assert!(err(&out[0]) < 0.5 * err(&plane), "noise kept: {} of {}", err(&out[0]), err(&plane));
        for y in 0..h {
            let v = out[0][y * w + line];
            assert!((v - 0.9).abs() < 0.06, "row {y}: the line went to {v}");
        }
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
