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
//! 3. the weight `exp(−max(D, 0))`, the centre's own weight 1;
//! 4. a second pass of steps 1–3 over the first's result, with `k = 1` and, for `v`, the
//!    variance of the first pass's weighted mean, `Σ w_q² v_q / (Σ w_q)²` (`PASSES`); a
//!    pixel whose own variance is zero (its samples agree: its albedo is exact) keeps the
//!    first pass's value.
//!
//! The second pass takes out what the first leaves where whole neighbourhoods are noise
//! (the mottling of a defocused albedo at a few samples per pixel), while the reduced
//! variance keeps it from softening what the first pass kept: on the 384² validation
//! scenes, with the shipped networks unchanged, mean DSSIM 0.0306 → 0.0291 and the
//! depth-of-field scene at 4 spp 0.129 → 0.106; thin geometry at 4 spp 0.0266 → 0.0283
//! (docs/training.md, "Two passes of the albedo prefilter"). Letting exact pixels move in
//! the second pass as well gained a little more on defocus but moved a lamp's exact
//! albedo beside noisy ones, and the `beauty` network, which divides the lamp's radiance
//! by it, leaked the lamp into its neighbour (RelMSE 10× on one held-out frame).
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
//! A frame written without an albedo variance (Blender Cycles and most production
//! renderers write no variances) is prefiltered with one estimated from the albedo alone
//! ([`estimated_variance`]): per pixel, a median over the `9 × 9` window around it of the
//! squared difference between the albedo's luminance and its `3 × 3` median. The `3 × 3`
//! median takes out the pixel-to-pixel noise of a defocused albedo and little of a region's
//! texture; the `9 × 9` median keeps a thin line's own difference (a few pixels of the
//! window) from counting as noise, where a defocused region's noise fills the window. On
//! the 384² validation scenes with every variance removed, the shipped networks' DSSIM
//! went from 0.0428 without the prefilter to 0.0358 (the depth-of-field scene 0.152 → 0.107,
//! thin geometry 0.019 → 0.022; per-pixel estimates without the `9 × 9` median fixed the
//! defocus and doubled thin geometry's DSSIM), on the held-out scenes 0.1168 → 0.1144
//! (docs/frame-layout.md, "Frames without variances"). The estimate serves the prefilter
//! only: the networks' albedo variance input stays 0, as for every missing variance. An
//! albedo variance the file gives as zeros is taken as it is (the albedo is exact). The
//! result depends only on the whole frame, not on tiling; training applies the same
//! functions (`training/mcdenoise_train/preprocess.py`, `prefilter_albedo` and
//! `estimated_albedo_variance`).

use rayon::prelude::*;

use super::preprocess::luminance;
use super::reconstruct::{exp_nonpositive, Fused, MulAdd, Unfused};
use crate::frame::{Buffer, Frame, Plane, PlaneRef};

/// Radius of the search window (7 × 7).
pub const RADIUS: usize = 3;
/// Radius of the patches compared (3 × 3).
pub const PATCH: usize = 1;
/// Distances in units of `k²` times the pair's variance: `k` of each pass (step 4 of the
/// method).
pub const PASSES: [f32; 2] = [0.7, 1.0];
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
/// off, or no albedo). A frame without an albedo variance is prefiltered with
/// [`estimated_variance`].
pub fn prefilter(frame: &Frame, mode: AlbedoPrefilter) -> Option<Frame> {
    if mode == AlbedoPrefilter::Off || !frame.has(Buffer::Albedo) {
        return None;
    }
    let (w, h) = (frame.width, frame.height);
    let missing = !frame.has(Buffer::AlbedoVariance)
        || frame.missing_variances.iter().any(|m| m == Buffer::AlbedoVariance.name());
    let variance: Vec<f32> = if missing {
        estimated_variance(frame.rgb(Buffer::Albedo), w, h)
    } else {
        match frame.planes(Buffer::AlbedoVariance).as_slice() {
            [mono] => mono.to_vec(),
            _ => {
                let [vr, vg, vb] = frame.rgb(Buffer::AlbedoVariance);
                (0..w * h).map(|i| luminance(vr.get(i), vg.get(i), vb.get(i))).collect()
            }
        }
    };
    let filtered = passes(frame.rgb(Buffer::Albedo), variance, w, h);
    // A clone shares the frame's buffers; the albedo is replaced, not copied. It is kept as
    // the file's albedo is (f16 where it fits, frame/plane.rs): at 4K, 50 MB less than f32
    // through inference, where a frame's memory peaks.
    let mut out = frame.clone();
    out.set_planes(Buffer::Albedo, filtered.into());
    Some(out)
}

/// Radius of the window whose (pseudo-)median of squared residuals is a pixel's estimated
/// variance ([`estimated_variance`]: 9 × 9, three blocks of three a side).
pub const ESTIMATE_RADIUS: usize = 4;

/// An albedo variance estimated from the albedo alone, for a frame written without one
/// (the module documentation): `r = (l − median₃ₓ₃ l)²` of the luminance `l`, its `3 × 3`
/// median `m`, then the median of `m` at the nine centres of the `3 × 3` blocks that tile
/// the `9 × 9` window around each pixel (offsets −3, 0, 3: Tukey's median of medians, which
/// like the window's median ignores a thin line's few pixels, at 18 samples a pixel instead
/// of 81, and gave the same validation scores: with the window's full median a 720p
/// frame's preprocessing took 0.3–0.4 s more than without the prefilter, with this 0.16–0.25
/// s, about what the prefilter costs a frame that has a variance). Windows and centres are clamped
/// to the frame's edges. Every median is of an odd count, so exact (the training side's
/// numpy medians agree).
pub fn estimated_variance(albedo: [PlaneRef<'_>; 3], w: usize, h: usize) -> Vec<f32> {
    let [r, g, b] = albedo;
    let lum: Vec<f32> = (0..w * h).map(|i| luminance(r.get(i), g.get(i), b.get(i))).collect();
    let clamp = |v: isize, n: usize| v.clamp(0, n as isize - 1) as usize;
    // The median of the 3 × 3 samples of `src` at offsets `step` apart around each pixel of row `y`.
    let median_row = |src: &[f32], step: isize, y: usize, dst: &mut [f32]| {
        let mut window = [0f32; 9];
        for (x, out) in dst.iter_mut().enumerate() {
            let mut k = 0;
            for dy in [-step, 0, step] {
                let row = &src[clamp(y as isize + dy, h) * w..][..w];
                for dx in [-step, 0, step] {
                    window[k] = row[clamp(x as isize + dx, w)];
                    k += 1;
                }
            }
            *out = *window.select_nth_unstable_by(4, f32::total_cmp).1;
        }
    };
    let mut residual = vec![0f32; w * h];
    residual.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        median_row(&lum, 1, y, row);
        for (m, l) in row.iter_mut().zip(&lum[y * w..][..w]) {
            let d = l - *m;
            *m = d * d;
        }
    });
    let mut blocks = vec![0f32; w * h];
    blocks.par_chunks_mut(w).enumerate().for_each(|(y, row)| median_row(&residual, 1, y, row));
    let mut out = residual;
    let block = (2 * ESTIMATE_RADIUS as isize + 1) / 3;
    out.par_chunks_mut(w).enumerate().for_each(|(y, row)| median_row(&blocks, block, y, row));
    out
}

/// Whether a variance sample says nothing is noise: zero, negative or not finite (taken as
/// 0 by the filter; a pixel with it has an exact albedo for the second pass).
fn without_variance(v: f32) -> bool {
    !(v.is_finite() && v > 0.0)
}

/// The method of the module doc, both passes, on planes of `w × h`.
pub fn passes(albedo: [PlaneRef<'_>; 3], variance: Vec<f32>, w: usize, h: usize) -> [Plane; 3] {
    let exact: Vec<bool> = variance.iter().map(|&v| without_variance(v)).collect();
    let (first, variance) = nl_means(albedo, variance, w, h, PASSES[0], None);
    nl_means(first.each_ref().map(|p| PlaneRef::F32(p)), variance, w, h, PASSES[1], Some(&exact)).0
}

/// One pass of the method (steps 1–3 with distance scale `k`) on planes of `w × h`
/// (`variance` is cleaned in place: non-finite and negative values become 0): the filtered
/// albedo and the variance of each pixel's weighted mean (a pixel that is no reflectance
/// keeps its own). The pixels `keep` marks keep their value and variance (their weights are
/// not computed where a whole row of a strip is kept). Beyond its output and `variance` it
/// holds only each band's rows, so that a 4K frame costs little memory.
pub fn nl_means(
    albedo: [PlaneRef<'_>; 3],
    mut variance: Vec<f32>,
    w: usize,
    h: usize,
    k: f32,
    keep: Option<&[bool]>,
) -> ([Plane; 3], Vec<f32>) {
    for v in &mut variance {
        if without_variance(*v) {
            *v = 0.0;
        }
    }
    let frame = Planes { albedo, variance, w, h, k2: k * k, keep };
    let band_filter = band_filter();
    let mut out: [Plane; 3] = std::array::from_fn(|_| vec![0f32; w * h]);
    let mut out_variance = vec![0f32; w * h];
    let [r, g, b] = &mut out;
    // Bands of rows in parallel; each band computes the distances of its rows and a
    // margin of `PATCH` rows for every offset, and keeps its own sums.
    r.par_chunks_mut(BAND * w)
        .zip(g.par_chunks_mut(BAND * w))
        .zip(b.par_chunks_mut(BAND * w))
        .zip(out_variance.par_chunks_mut(BAND * w))
        .enumerate()
        .for_each(|(band, (((r, g), b), v))| band_filter(&frame, band * BAND, [r, g, b, v]));
    (out, out_variance)
}

/// Rows per parallel band.
const BAND: usize = 32;
/// Columns per strip of a band ([`filter_band`]).
const STRIP: usize = 256;
/// Side of the search window.
const SIDE: usize = 2 * RADIUS + 1;
/// Pixels the window-row loop keeps in registers at once (one AVX2 vector).
const LANES: usize = 8;
// The ring of `filter_band` holds the three rows of a 3 × 3 patch.
const _: () = assert!(PATCH == 1, "filter_band's ring is written for 3 × 3 patches");

/// The frame's planes as the filter reads them.
struct Planes<'a> {
    albedo: [PlaneRef<'a>; 3],
    variance: Vec<f32>,
    w: usize,
    h: usize,
    /// `k²` of the pass.
    k2: f32,
    /// The pixels that keep their value.
    keep: Option<&'a [bool]>,
}

type BandFilter = fn(&Planes<'_>, usize, [&mut [f32]; 4]);

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
    filter_band::<Unfused>
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn filter_band_avx2(planes: &Planes<'_>, y0: usize, out: [&mut [f32]; 4]) {
    filter_band::<Fused>(planes, y0, out)
}

/// `lo..hi`: the columns of `x0..x1` whose neighbour at `x + dx` lies inside a row of `w`;
/// columns before `lo` take the row's first pixel as that neighbour, columns from `hi` on
/// its last.
#[inline(always)]
fn inside(x0: usize, x1: usize, w: usize, dx: isize) -> (usize, usize) {
    let lo = (-dx).clamp(x0 as isize, x1 as isize) as usize;
    let hi = (w as isize - dx).clamp(lo as isize, x1 as isize) as usize;
    (lo, hi)
}

/// Step 1 of the method: the distance of pixel `a` to pixel `b` (three albedo channels and
/// the variance each) with distance scale `k2` = `k²`.
#[inline(always)]
fn d<M: MulAdd>(a: [f32; 4], b: [f32; 4], k2: f32) -> f32 {
    let (e0, e1, e2) = (a[0] - b[0], a[1] - b[1], a[2] - b[2]);
    let diff = M::mul_add(e2, e2, M::mul_add(e1, e1, e0 * e0)) * (1.0 / 3.0);
    let (vp, vq) = (a[3], b[3]);
    (diff - ALPHA * (vp + vp.min(vq))) / M::mul_add(k2, vp + vq, EPS)
}

/// `out[x - x0] = d(p_x, q_clamp(x + dx))` for `x` in `x0..x1` (rows of `w`).
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn pair_distances<M: MulAdd>(
    p: [&[f32]; 4],
    q: [&[f32]; 4],
    x0: usize,
    x1: usize,
    dx: isize,
    k2: f32,
    out: &mut [f32],
) {
    let w = p[0].len();
    let at = |s: [&[f32]; 4], x: usize| [s[0][x], s[1][x], s[2][x], s[3][x]];
    let (lo, hi) = inside(x0, x1, w, dx);
    for x in (x0..lo).chain(hi..x1) {
        out[x - x0] = d::<M>(at(p, x), at(q, if x < lo { 0 } else { w - 1 }), k2);
    }
    let n = hi - lo;
    if n == 0 {
        return;
    }
    let qs = (lo as isize + dx) as usize;
    let [p0, p1, p2, vp] = p.map(|s| &s[lo..lo + n]);
    let [q0, q1, q2, vq] = q.map(|s| &s[qs..qs + n]);
    let out = &mut out[lo - x0..lo - x0 + n];
    for x in 0..n {
        out[x] = d::<M>([p0[x], p1[x], p2[x], vp[x]], [q0[x], q1[x], q2[x], vq[x]], k2);
    }
}

/// Step 3: adds the weight of a neighbour `q` (albedo, reflectance and variance) from its
/// patch distance sum `s` into a pixel's sums (`n`: the albedo's three and the variance's).
#[inline(always)]
fn add<M: MulAdd>(s: f32, q: [f32; 5], n: [&mut f32; 4], den: &mut f32) {
    let inv_area = 1.0 / ((2 * PATCH + 1) * (2 * PATCH + 1)) as f32;
    let weight = exp_nonpositive::<M>((-s * inv_area).min(0.0)) * q[3];
    *n[0] = M::mul_add(weight, q[0], *n[0]);
    *n[1] = M::mul_add(weight, q[1], *n[1]);
    *n[2] = M::mul_add(weight, q[2], *n[2]);
    *n[3] = M::mul_add(weight * weight, q[4], *n[3]);
    *den += weight;
}

/// For row `yp` and every offset, the patch-width sums of the distances over `x0..x1`
/// into ring slot `slot`.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn row_sums<'a, M: MulAdd>(
    at: &impl Fn(usize) -> [&'a [f32]; 4],
    h: usize,
    w: usize,
    x0: usize,
    x1: usize,
    offsets: &[(isize, isize)],
    k2: f32,
    yp: usize,
    slot: usize,
    ring: &mut [f32],
    d: &mut [f32],
) {
    let sw = x1 - x0;
    // Distances over the strip and one column each side (clamped at the frame's edges).
    let (xs, xe) = (x0.saturating_sub(1), (x1 + 1).min(w));
    for (k, &(dy, dx)) in offsets.iter().enumerate() {
        let yq = (yp as isize + dy).clamp(0, h as isize - 1) as usize;
        // d[j] is the distance at column clamp(x0 - 1 + j).
        let start = usize::from(x0 == 0);
        pair_distances::<M>(at(yp), at(yq), xs, xe, dx, k2, &mut d[start..]);
        if x0 == 0 {
            d[0] = d[1];
        }
        if x1 == w {
            d[sw + 1] = d[sw];
        }
        let dh = &mut ring[(k * 3 + slot) * STRIP..(k * 3 + slot) * STRIP + sw];
        let (dl, dc, dr) = (&d[..sw], &d[1..sw + 1], &d[2..sw + 2]);
        for i in 0..sw {
            dh[i] = dc[i] + (dl[i] + dr[i]);
        }
    }
}

/// Rows `y0 ..` of the output (as many as `out` holds), in strips of `STRIP` columns.
/// Down a strip, each row's distances are computed once per offset, summed across the
/// patch's width and kept in a ring of the last three rows (`PATCH` 1); a pixel's patch
/// distance is the sum of its column in the three. The ring, `49 × 3 × STRIP` values (150 KB),
/// stays in the core's L2 cache. The weighted sums are taken a window row at a time, eight
/// pixels' sums held in registers across the row's seven offsets (before 2026-12-02 they were
/// read and written back for every offset, and strips were 128 wide: both passes over a
/// 1280×720 albedo took 275 ms on two AVX2 cores, now 225 ms, with the same outputs bit for
/// bit). Each pixel takes its offsets in the method's order; the AVX2 build fuses the
/// multiply-adds (the outputs differ from the plain build's by about 1e-7 relative).
#[inline(always)]
fn filter_band<M: MulAdd>(planes: &Planes<'_>, y0: usize, mut out: [&mut [f32]; 4]) {
    let Planes { albedo, variance, w, h, k2, keep } = planes;
    let (w, h, k2) = (*w, *h, *k2);
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
    fn rows_at(plane: &[f32], first: usize, w: usize, y: usize) -> &[f32] {
        &plane[(y - first) * w..(y - first + 1) * w]
    }
    let row = |plane, y| rows_at(plane, lo, w, y);
    let at = |y| [row(&albedo[0], y), row(&albedo[1], y), row(&albedo[2], y), row(v, y)];
    let clamp = |i: isize, n: usize| i.clamp(0, n as isize - 1) as usize;
    let offsets: Vec<(isize, isize)> = {
        let r = RADIUS as isize;
        (-r..=r).flat_map(|dy| (-r..=r).map(move |dx| (dy, dx))).collect()
    };
    let no = offsets.len();
    // Per offset, the patch-width sums of the last three rows' distances (a ring).
    let mut ring = vec![0f32; no * 3 * STRIP];
    let mut d = vec![0f32; STRIP + 2];
    // The weighted sums of the albedo's three channels and of the variance (by the weights' squares).
    let mut num: [Vec<f32>; 4] = std::array::from_fn(|_| vec![0f32; STRIP]);
    let mut den = vec![0f32; STRIP];
    for x0 in (0..w).step_by(STRIP) {
        let x1 = (x0 + STRIP).min(w);
        let sw = x1 - x0;
        // Rows y0 - 1 and y0 first; row y's sums go to slot y mod 3.
        for r in [-1isize, 0] {
            let y = y0 as isize + r;
            row_sums::<M>(&at, h, w, x0, x1, &offsets, k2, clamp(y, h), (y + 3) as usize % 3, &mut ring, &mut d);
        }
        for yr in 0..rows {
            let y = y0 + yr;
            row_sums::<M>(&at, h, w, x0, x1, &offsets, k2, clamp(y as isize + 1, h), (y + 1) % 3, &mut ring, &mut d);
            let p = (y - lo) * w;
            let kept = keep.map(|k| &k[y * w + x0..y * w + x1]);
            if kept.is_some_and(|k| k.iter().all(|&k| k)) {
                // The whole row of the strip keeps its value: no weights to compute.
                let [o0, o1, o2, ov] = &mut out;
                for (c, o) in [o0, o1, o2].into_iter().enumerate() {
                    o[yr * w + x0..yr * w + x1].copy_from_slice(&albedo[c][p + x0..p + x1]);
                }
                ov[yr * w + x0..yr * w + x1].copy_from_slice(&v[p + x0..p + x1]);
                continue;
            }
            let (s0, s1, s2) = ((y + 2) % 3, y % 3, (y + 1) % 3);
            num.iter_mut().for_each(|n| n[..sw].fill(0.0));
            den[..sw].fill(0.0);
            // Offsets a window row at a time (`dy`), so that each pixel's sums stay in
            // registers across the row's `SIDE` offsets, `LANES` pixels at a time, in the
            // columns whose neighbours all lie inside the frame; the other columns (the
            // frame's edges and what is left over from whole vectors) one at a time, their
            // neighbours clamped. Each pixel still takes its offsets in order.
            let r = RADIUS as isize;
            let (lo_c, n) = {
                let lo = r.clamp(x0 as isize, x1 as isize);
                let hi = (w as isize - r).clamp(lo, x1 as isize);
                (lo as usize, (hi - lo) as usize / LANES * LANES)
            };
            for gy in 0..SIDE {
                let yq = clamp(y as isize + gy as isize - r, h);
                let q =
                    [row(&albedo[0], yq), row(&albedo[1], yq), row(&albedo[2], yq), row(&reflectance, yq), row(v, yq)];
                let hs: [[&[f32]; 3]; SIDE] = std::array::from_fn(|j| {
                    let k = gy * SIDE + j;
                    [s0, s1, s2].map(|s| &ring[(k * 3 + s) * STRIP..(k * 3 + s) * STRIP + sw])
                });
                let [nr, ng, nb, nv] = &mut num;
                for (j, h) in hs.iter().enumerate() {
                    let dx = j as isize - r;
                    for x in (x0..lo_c).chain(lo_c + n..x1) {
                        let i = x - x0;
                        let xq = clamp(x as isize + dx, w);
                        add::<M>(
                            h[0][i] + h[1][i] + h[2][i],
                            [q[0][xq], q[1][xq], q[2][xq], q[3][xq], q[4][xq]],
                            [&mut nr[i], &mut ng[i], &mut nb[i], &mut nv[i]],
                            &mut den[i],
                        );
                    }
                }
                if n == 0 {
                    continue;
                }
                let a = lo_c - x0;
                let qs: [[&[f32]; 5]; SIDE] = std::array::from_fn(|j| {
                    let start = (lo_c as isize + j as isize - r) as usize;
                    q.map(|s| &s[start..start + n])
                });
                let hs: [[&[f32]; 3]; SIDE] = hs.map(|h| h.map(|s| &s[a..a + n]));
                let (nr, ng, nb, nv) = (&mut nr[a..a + n], &mut ng[a..a + n], &mut nb[a..a + n], &mut nv[a..a + n]);
                let den = &mut den[a..a + n];
                let lanes = |s: &[f32], i: usize| -> [f32; LANES] { s[i..i + LANES].try_into().unwrap() };
                for i in (0..n).step_by(LANES) {
                    let mut acc = [lanes(nr, i), lanes(ng, i), lanes(nb, i), lanes(nv, i), lanes(den, i)];
                    for j in 0..SIDE {
                        let (h, q) = (hs[j].map(|s| lanes(s, i)), qs[j].map(|s| lanes(s, i)));
                        let [ar, ag, ab, av, ad] = &mut acc;
                        for l in 0..LANES {
                            add::<M>(
                                h[0][l] + h[1][l] + h[2][l],
                                [q[0][l], q[1][l], q[2][l], q[3][l], q[4][l]],
                                [&mut ar[l], &mut ag[l], &mut ab[l], &mut av[l]],
                                &mut ad[l],
                            );
                        }
                    }
                    for (dst, src) in [&mut *nr, &mut *ng, &mut *nb, &mut *nv, &mut *den].into_iter().zip(acc) {
                        dst[i..i + LANES].copy_from_slice(&src);
                    }
                }
            }
            let [o0, o1, o2, ov] = &mut out;
            let filtered = |i: usize| reflectance[p + x0 + i] > 0.0 && !kept.is_some_and(|k| k[i]);
            for (c, o) in [o0, o1, o2].into_iter().enumerate() {
                for i in 0..sw {
                    let x = x0 + i;
                    o[yr * w + x] = if filtered(i) { num[c][i] / den[i] } else { albedo[c][p + x] };
                }
            }
            for i in 0..sw {
                let x = x0 + i;
                ov[yr * w + x] = if filtered(i) { num[3][i] / (den[i] * den[i]) } else { v[p + x] };
            }
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

    /// Time of both passes over a 1280×720 albedo with variance everywhere, on the rayon
    /// pool's threads (run with `RAYON_NUM_THREADS=2 cargo test --release --lib -- --ignored
    /// --nocapture prefilter_speed`).
    #[test]
    #[ignore = "a timing, not a test"]
    fn prefilter_speed() {
        let (w, h) = (1280, 720);
        let mut seed = 5;
        let albedo: [Plane; 3] = std::array::from_fn(|_| (0..w * h).map(|_| 0.2 + 0.6 * lcg(&mut seed)).collect());
        let variance: Vec<f32> = (0..w * h).map(|_| 0.001 + 0.01 * lcg(&mut seed)).collect();
        let mut best = [f64::MAX; 2];
        for _ in 0..5 {
            let t = std::time::Instant::now();
            let (first, v) =
                nl_means(albedo.each_ref().map(|p| PlaneRef::F32(p)), variance.clone(), w, h, PASSES[0], None);
            best[0] = best[0].min(t.elapsed().as_secs_f64());
            let t = std::time::Instant::now();
            std::hint::black_box(nl_means(first.each_ref().map(|p| PlaneRef::F32(p)), v, w, h, PASSES[1], None));
            best[1] = best[1].min(t.elapsed().as_secs_f64());
        }
        let pairs = (w * h * (2 * RADIUS + 1) * (2 * RADIUS + 1)) as f64;
        println!(
            "1280x720: first pass {:.1} ms, second {:.1} ms, {:.2} ns per pixel pair",
            best[0] * 1e3,
            best[1] * 1e3,
            best[0] * 1e9 / pairs
        );
    }

    #[test]
    fn bands_give_the_method_written_out() {
        // Three bands and a partial one, three strips (the last partial) and one exact,
        // edges clamped, an emitter above 1: the method of the module doc pixel by pixel in
        // f64; and frames narrower than the window.
        for (w, h) in [(11, 3 * BAND + 5), (2 * STRIP + 3, 7), (STRIP, 4), (1, 1), (1, 9), (9, 1), (2, 2), (3, 5)] {
            for k in PASSES {
                written_out(w, h, k);
            }
        }
    }

    fn written_out(w: usize, h: usize, k: f32) {
        let mut seed = 3;
        let mut albedo: [Plane; 3] = std::array::from_fn(|_| (0..w * h).map(|_| lcg(&mut seed)).collect());
        if h > 40 {
            albedo[1][40 * w + 4] = 30.0;
        }
        let v: Vec<f32> = (0..w * h).map(|i| if i % 7 == 0 { 0.0 } else { 0.02 * lcg(&mut seed) }).collect();
        let (got, got_variance) = nl_means(albedo.each_ref().map(|p| PlaneRef::F32(p)), v.clone(), w, h, k, None);
        let at = |y: isize, x: isize| y.clamp(0, h as isize - 1) as usize * w + x.clamp(0, w as isize - 1) as usize;
        let refl = |i: usize| albedo.iter().all(|p| p[i] <= MAX_REFLECTANCE);
        let d = |p: usize, q: usize| {
            let diff: f64 =
                (0..3).map(|c| (f64::from(albedo[c][p]) - f64::from(albedo[c][q])).powi(2)).sum::<f64>() / 3.0;
            let (vp, vq) = (f64::from(v[p]), f64::from(v[q]));
            (diff - (vp + vp.min(vq))) / (1e-10 + f64::from(k * k) * (vp + vq))
        };
        let (r, f) = (RADIUS as isize, PATCH as isize);
        for y in 0..h as isize {
            for x in 0..w as isize {
                let p = at(y, x);
                let (mut num, mut den, mut variance) = ([0f64; 3], 0f64, 0f64);
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
                        variance += weight * weight * f64::from(v[q]);
                        den += weight;
                    }
                }
                for c in 0..3 {
                    let want = if refl(p) { num[c] / den } else { f64::from(albedo[c][p]) };
                    let g = f64::from(got[c][p]);
                    assert!((g - want).abs() <= 1e-5 * want.abs().max(1e-2), "({y}, {x}) channel {c}: {g}, not {want}");
                }
                // The variance of the weighted mean; a pixel that is no reflectance keeps its own.
                let want = if refl(p) { variance / (den * den) } else { f64::from(v[p]) };
                let g = f64::from(got_variance[p]);
                assert!((g - want).abs() <= 1e-5 * want.abs().max(1e-4), "({y}, {x}) variance: {g}, not {want}");
            }
        }
    }

    #[test]
    fn the_second_pass_leaves_exact_pixels_as_the_first_left_them() {
        let (w, h) = (17, 13);
        let mut seed = 11;
        let albedo: [Plane; 3] = std::array::from_fn(|_| (0..w * h).map(|_| 0.4 + 0.2 * lcg(&mut seed)).collect());
        // The first four rows exact (no variance: the second pass skips them), then every
        // third pixel, the rest noisy.
        let exact = |i: usize| i < 4 * w || i % 3 == 0;
        let v: Vec<f32> = (0..w * h).map(|i| if exact(i) { 0.0 } else { 0.01 }).collect();
        let planes = albedo.each_ref().map(|p| PlaneRef::F32(p));
        let (first, v1) = nl_means(planes, v.clone(), w, h, PASSES[0], None);
        let (second, _) = nl_means(first.each_ref().map(|p| PlaneRef::F32(p)), v1, w, h, PASSES[1], None);
        let got = passes(planes, v, w, h);
        let (mut moved, mut skipped) = (0, 0);
        for c in 0..3 {
            for i in 0..w * h {
                let want = if exact(i) { first[c][i] } else { second[c][i] };
                assert_eq!(got[c][i], want, "channel {c}, pixel {i}");
                moved += usize::from(exact(i) && i >= 4 * w && second[c][i] != first[c][i]);
                skipped += usize::from(i < 4 * w && second[c][i] != first[c][i]);
            }
        }
        assert!(moved > 0 && skipped > 0, "the second pass alone would move exact pixels, skipped rows too");
    }

    #[test]
    fn zero_variance_keeps_the_albedo_exactly() {
        let (w, h) = (13, 19);
        let mut seed = 1;
        let albedo: [Plane; 3] = std::array::from_fn(|_| (0..w * h).map(|_| lcg(&mut seed)).collect());
        for k in PASSES {
            let (out, variance) =
                nl_means(albedo.each_ref().map(|p| PlaneRef::F32(p)), vec![0.0; w * h], w, h, k, None);
            assert_eq!(out, albedo);
            assert!(variance.iter().all(|&v| v == 0.0));
        }
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
        let albedo = [PlaneRef::F32(&plane), PlaneRef::F32(&plane), PlaneRef::F32(&plane)];
        let (first, _) = nl_means(albedo, variance.clone(), w, h, PASSES[0], None);
        let both = passes(albedo, variance, w, h);
        let err = |p: &[f32]| -> f32 {
            p.iter().enumerate().filter(|(i, _)| i % w != line).map(|(_, v)| (v - 0.5).powi(2)).sum()
        };
        assert!(err(&first[0]) < 0.5 * err(&plane), "noise kept: {} of {}", err(&first[0]), err(&plane));
        // The second pass takes out more of what the first left.
        assert!(err(&both[0]) < 0.8 * err(&first[0]), "second pass: {} of {}", err(&both[0]), err(&first[0]));
        for out in [&first, &both] {
            for y in 0..h {
                let v = out[0][y * w + line];
                assert!((v - 0.9).abs() < 0.06, "row {y}: the line went to {v}");
            }
        }
    }

    #[test]
    fn a_frame_without_albedo_variance_is_prefiltered_by_its_estimate() {
        let (w, h) = (24, 20);
        let planes = super::super::synthetic_planes(w, h, false);
        // The synthetic albedo is smooth: noise added, as a defocused albedo at a few samples has.
        let mut seed = 3;
        let named: Vec<(String, Plane)> = planes
            .into_iter()
            .filter(|(n, _)| !n.starts_with("albedoVariance"))
            .map(|(n, p)| {
                let noisy = if n.starts_with("albedo.") {
                    p.iter().map(|v| v + 0.1 * (lcg(&mut seed) - 0.5)).collect()
                } else {
                    p
                };
                (n, noisy)
            })
            .collect();
        let maps = crate::frame::ChannelMaps::default();
        let mut frame = Frame::from_planes(w, h, named, crate::frame::layout::REQUIRED, &maps).expect("frame");
        let expect = passes(frame.rgb(Buffer::Albedo), estimated_variance(frame.rgb(Buffer::Albedo), w, h), w, h);
        let albedo = |f: &Frame| f.rgb(Buffer::Albedo).map(|p| (0..w * h).map(|i| p.get(i)).collect::<Vec<f32>>());
        let stored = |p: &[f32]| p.iter().map(|v| half::f16::from_f32(*v).to_f32()).collect::<Vec<f32>>();
        let out = prefilter(&frame, AlbedoPrefilter::On).expect("no albedo variance: estimated");
        assert_eq!(albedo(&out), expect.each_ref().map(|p| stored(p)));
        assert!(albedo(&out) != albedo(&frame), "the noisy albedo is filtered");
        // Filled in as zeros for the networks, the buffer is still missing: estimated too.
        frame.fill_missing_variances();
        assert_eq!(albedo(&prefilter(&frame, AlbedoPrefilter::On).expect("estimated")), albedo(&out));
        let full = super::super::synthetic_frame(8, 8, false);
        assert!(prefilter(&full, AlbedoPrefilter::Off).is_none());
        assert!(prefilter(&full, AlbedoPrefilter::On).is_some());
    }

    #[test]
    fn the_estimate_is_zero_where_flat_and_on_a_thin_line_and_the_noise_elsewhere() {
        let (w, h) = (40, 30);
        let mut seed = 11;
        // Left half: flat 0.5 with a one-pixel line of 0.9 at x = 8; right half: noise of
        // standard deviation 0.1 around 0.5.
        let plane: Plane = (0..w * h)
            .map(|i| match i % w {
                8 => 0.9,
                x if x < w / 2 => 0.5,
                _ => 0.5 + 0.1 * (lcg(&mut seed) + lcg(&mut seed) + lcg(&mut seed) - 1.5) * 2.0,
            })
            .collect();
        let v = estimated_variance([PlaneRef::F32(&plane), PlaneRef::F32(&plane), PlaneRef::F32(&plane)], w, h);
        for y in 0..h {
            for x in 0..w / 2 - ESTIMATE_RADIUS {
                assert_eq!(v[y * w + x], 0.0, "({x}, {y}): flat or on the thin line");
            }
        }
        // The noise (variance 0.01 · 4 · 3/12 = 0.01): its median squared residual to the
        // 3x3 median is about half of it.
        let inner: Vec<f32> =
            (0..h).flat_map(|y| (w / 2 + ESTIMATE_RADIUS..w).map(move |x| (y, x))).map(|(y, x)| v[y * w + x]).collect();
        let mean = inner.iter().sum::<f32>() / inner.len() as f32;
        assert!((0.002..0.02).contains(&mean), "estimate {mean} for a variance of 0.01");
    }
}
