//! Firefly handling: isolated, very bright samples (rare paths through small lights,
//! caustics, rough metals) are found from the frame's own statistics and clamped before
//! the networks see the frame.
//!
//! A kernel-predicting network keeps such a pixel at nearly full strength (its kernel
//! weights the centre tap), so this runs as its own stage, on the whole frame, before
//! [`preprocess`](super::preprocess) and tiling. It depends on the network only through the
//! frame's buffers: every variant and contract calls [`detect`] on each color buffer it
//! denoises (diffuse and specular today; a beauty-only variant calls it on its color).
//!
//! # Method
//!
//! Per component, on the luminance `g` of the color (the diffuse color divided by
//! `albedo + ε` first, as the network sees it, so that texture is not mistaken for
//! outliers), in the log domain `y = ln(g + δ)`, where `δ` is a tenth of the component's
//! median positive luminance (dark regions then count as that level, not as minus
//! infinity). A pixel is an outlier when all of these hold:
//!
//! 1. **Isolated, alone or as a pair**: each of its 8 neighbours is below half of it
//!    (`g_q + δ < (g_p + δ) / 2`), or all but one, whose own other neighbours are below half
//!    of that one (a bright path found twice in adjacent pixels). A light, a highlight or a
//!    bright edge or line has more bright neighbours, so it is never touched.
//! 2. **Far above its neighbourhood**: `y_p > min(m + τ / s, y_max + ln 4 / s)`, with `m`
//!    the median, `σ` the normalised MAD (1.4826 × median absolute deviation) and `y_max`
//!    the largest `y` of the 5×5 neighbourhood without the centre, `τ = max(3σ, ln 4)` and
//!    `s` the strength. The MAD makes the bound follow the local noise: a noisy glossy
//!    region tolerates larger excursions than a smooth wall. Where the neighbourhood spans
//!    orders of magnitude (sparse samples at a low level) the MAD is large, so a pixel more
//!    than 4× above every neighbour is an outlier whatever the MAD says.
//! 3. **Noisy by its own variance** (when the frame has the component's variance buffer):
//!    `Var / g² ≥ 1/4`. The variance of a pixel mean whose value comes from `k` of its
//!    samples is about `g² / k`, so this keeps bright values that four or more samples
//!    agree on (a small light seen directly, a stable one-pixel glint), whatever their
//!    neighbours say. Variance alone cannot find outliers (a renderer raises it with the
//!    outlier), so it only vetoes.
//! 4. **Not one of a sparse signal**: fewer than 2 other pixels that pass 1–3 within its
//!    15×15 window are at least a quarter as bright (its peers). A caustic, a sunlit floor
//!    or small lights at a few samples per pixel are fields of isolated bright samples,
//!    each a candidate by 1–3, that the networks were trained on as they are (training
//!    does not clamp); clamping them took the energy out of whole regions (on 18 Cycles
//!    frames of caustics, interiors and small lights, mean DSSIM 0.0414 against 0.0383
//!    without the handling; docs/fireflies.md). An outlier far above such a field has no
//!    peers in it, and a few outliers near each other stay outliers. Applied where the
//!    layer says so ([`Layer::fields`]): the engine applies it for the `full` and `nocov`
//!    networks only ([`super::firefly_fields`]).
//!
//! An outlier's color is scaled (all three channels, chroma kept) so that its luminance is
//! that bound (minus `δ`) or the luminance of the brightest pixel of its neighbourhood,
//! whichever is lower: the pixel then holds a value its neighbours make plausible, at the
//! top of their range. Its variance is left as it is, raised by the outlier: it tells the
//! network that the pixel is unreliable. docs/fireflies.md gives the measurements behind
//! these choices (clamping to the bound alone, or to the median; setting the variance to
//! the neighbourhood's or scaling it).
//!
//! Detection reads the original frame only, and every decision depends on a neighbourhood
//! of at most 15×15 pixels, so the result does not depend on tiling; the engine runs it once per
//! frame, parallel over rows.

use rayon::prelude::*;

use super::preprocess::{luminance, luminance_rows, EPS};
use crate::frame::{Plane, PlaneRef};

/// Whether outliers are handled.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum FireflyMode {
    /// Detect and clamp (the default).
    #[default]
    Auto,
    /// Leave the frame as it is.
    Off,
}

impl FireflyMode {
    pub const ALL: [FireflyMode; 2] = [FireflyMode::Auto, FireflyMode::Off];

    pub fn name(self) -> &'static str {
        match self {
            FireflyMode::Auto => "auto",
            FireflyMode::Off => "off",
        }
    }

    pub fn parse(s: &str) -> Option<FireflyMode> {
        FireflyMode::ALL.into_iter().find(|m| m.name() == s)
    }
}

impl std::str::FromStr for FireflyMode {
    type Err = String;

    fn from_str(s: &str) -> Result<FireflyMode, String> {
        FireflyMode::parse(s).ok_or_else(|| format!("unknown fireflies mode `{s}` (expected auto or off)"))
    }
}

/// Default strength: the thresholds of the module documentation as written.
pub const DEFAULT_STRENGTH: f32 = 1.0;
/// Accepted strengths. Below 0.1 the bound is 10× further than at 1 (nothing is
/// detected in practice; use `off`); above 10 nearly every isolated local maximum is.
pub const STRENGTH_RANGE: std::ops::RangeInclusive<f32> = 0.1..=10.0;

/// How outliers are handled: the mode and the strength `s` (the log-domain bound above the
/// neighbourhood median is divided by `s`: 2 halves it, 0.5 doubles it).
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Fireflies {
    pub mode: FireflyMode,
    pub strength: f32,
}

impl Default for Fireflies {
    fn default() -> Self {
        Fireflies { mode: FireflyMode::Auto, strength: DEFAULT_STRENGTH }
    }
}

impl Fireflies {
    pub const OFF: Fireflies = Fireflies { mode: FireflyMode::Off, strength: DEFAULT_STRENGTH };

    /// Checks the strength; the message names the accepted range.
    pub fn validate(self) -> Result<Fireflies, String> {
        if !STRENGTH_RANGE.contains(&self.strength) {
            return Err(format!(
                "firefly strength {} is outside {}..={}",
                self.strength,
                STRENGTH_RANGE.start(),
                STRENGTH_RANGE.end()
            ));
        }
        Ok(self)
    }

    pub fn enabled(self) -> bool {
        self.mode == FireflyMode::Auto
    }
}

/// One color buffer to examine: its three planes, its variance planes (a mono variance
/// stands in all three; `None` when the frame has none, or only zeros filled in for a
/// missing buffer), for a buffer the network sees divided by albedo, the albedo, and
/// whether rule 4 applies (`fields`: fields of peers are signal).
#[derive(Clone, Copy)]
pub struct Layer<'a> {
    pub color: [&'a [f32]; 3],
    pub variance: Option<[PlaneRef<'a>; 3]>,
    pub albedo: Option<[PlaneRef<'a>; 3]>,
    pub fields: bool,
}

/// The change to one outlier pixel.
#[derive(Clone, Debug, PartialEq)]
pub struct Fix {
    /// Row-major pixel index.
    pub index: usize,
    /// Factor applied to the three color channels.
    pub scale: f32,
}

/// Isolation: every neighbour below this fraction of the pixel (in `g + δ`).
const ISOLATION: f32 = 0.5;
/// `δ` as a fraction of the component's median positive luminance.
const DELTA_FRACTION: f32 = 0.1;
/// The bound is at least this many normalised MADs above the median...
const MAD_FACTOR: f32 = 3.0;
/// ... and at least this factor above it.
const MIN_FACTOR: f32 = 4.0;
/// ... unless it is this factor above the brightest pixel of the neighbourhood.
const MAX_FACTOR: f32 = 4.0;
/// Smallest relative variance `Var / g²` of a pixel that is treated.
const MIN_RELATIVE_VARIANCE: f32 = 0.25;
/// Radius of the window in which candidates are counted (15×15) ...
const CLUSTER_RADIUS: usize = 7;
/// ... how many peers there make a candidate part of a sparse signal, not an outlier ...
const CLUSTER_LIMIT: usize = 2;
/// ... and how bright a peer is at least, as a fraction of the candidate (in `g + δ`).
const PEER: f32 = 0.25;
/// Neighbourhood radius of the median and MAD (5×5).
const RADIUS: usize = 2;
const NEIGHBOURS: usize = (2 * RADIUS + 1) * (2 * RADIUS + 1) - 1;

/// `x`, with ±∞ replaced by ±`f32::MAX` and NaN by 0.
fn finite(x: f32) -> f32 {
    if x.is_nan() {
        0.0
    } else {
        x.clamp(-f32::MAX, f32::MAX)
    }
}

/// The outliers of one color buffer of a `w`×`h` frame, by pixel index. Runs on the current
/// rayon pool.
pub fn detect(layer: Layer<'_>, w: usize, h: usize, settings: Fireflies) -> Vec<Fix> {
    if !settings.enabled() || w == 0 || h == 0 {
        return Vec::new();
    }
    let g = network_luminance(layer, w, h);
    let delta = {
        let mut positive: Vec<f32> = g.par_iter().copied().filter(|v| *v > 0.0).collect();
        if positive.is_empty() {
            return Vec::new();
        }
        let mid = positive.len() / 2;
        let (_, median, _) = positive.select_nth_unstable_by(mid, f32::total_cmp);
        (*median * DELTA_FRACTION).max(f32::MIN_POSITIVE)
    };
    let strength = settings.strength;
    let found: Vec<Fix> = (0..h)
        .into_par_iter()
        .flat_map_iter(|y| {
            let g = &g;
            (0..w).filter_map(move |x| examine(layer, g, w, h, x, y, delta, strength))
        })
        .collect();
    if layer.fields {
        unclustered(&found, &g, delta, w, h)
    } else {
        found
    }
}

/// `found` (row-major, as [`detect`] collects it) without the candidates that have at least
/// `CLUSTER_LIMIT` peers: other candidates within `CLUSTER_RADIUS` at least `PEER` times as
/// bright (in `g + δ`). Rule 4 of the module documentation.
fn unclustered(found: &[Fix], g: &[f32], delta: f32, w: usize, h: usize) -> Vec<Fix> {
    found
        .par_iter()
        .filter(|f| {
            let i = f.index;
            let (x, y) = (i % w, i / w);
            let (x0, x1) = (x.saturating_sub(CLUSTER_RADIUS), (x + CLUSTER_RADIUS).min(w - 1));
            let floor = PEER * (g[i] + delta);
            let mut peers = 0usize;
            for yy in y.saturating_sub(CLUSTER_RADIUS)..=(y + CLUSTER_RADIUS).min(h - 1) {
                let lo = found.partition_point(|q| q.index < yy * w + x0);
                let hi = found.partition_point(|q| q.index <= yy * w + x1);
                peers += found[lo..hi].iter().filter(|q| q.index != i && g[q.index] + delta >= floor).count();
            }
            peers < CLUSTER_LIMIT
        })
        .cloned()
        .collect()
}

/// The luminance of each pixel in the network's domain (the color divided by `albedo + ε`
/// where the layer has an albedo), finite; a row at a time ([`luminance_rows`]): per sample
/// through the albedo plane's type it was three quarters of the stage's time.
fn network_luminance(layer: Layer<'_>, w: usize, h: usize) -> Vec<f32> {
    let mut g = vec![0f32; w * h];
    let channel = |k: usize, start: usize, values: &mut [f32], albedo: &mut [f32]| {
        let color = &layer.color[k][start..][..w];
        match layer.albedo {
            Some(a) => {
                a[k].read(start, albedo);
                for ((v, c), a) in values.iter_mut().zip(color).zip(albedo.iter()) {
                    *v = finite(c.max(0.0) / (a.max(0.0) + EPS));
                }
            }
            None => {
                for (v, c) in values.iter_mut().zip(color) {
                    *v = finite(c.max(0.0));
                }
            }
        }
    };
    luminance_rows(&mut g, w, |y| y * w, channel, finite);
    g
}

/// The fix of pixel (x, y), if it is an outlier.
#[allow(clippy::too_many_arguments)]
fn examine(
    layer: Layer<'_>,
    g: &[f32],
    w: usize,
    h: usize,
    x: usize,
    y: usize,
    delta: f32,
    strength: f32,
) -> Option<Fix> {
    let i = y * w + x;
    let centre = g[i] + delta;
    // 1. Isolated, alone or as a pair (cheap; most pixels stop here).
    if !isolated(g, w, h, x, y, delta) {
        return None;
    }
    // 3. Noisy by its own variance.
    if let Some(var) = layer.variance {
        let v = variance_luminance(layer, var, i);
        if v < MIN_RELATIVE_VARIANCE * g[i] * g[i] {
            return None;
        }
    }
    // 2. Far above the 5×5 neighbourhood: median and MAD of ln(g + δ) without the centre.
    let mut logs = [0f32; NEIGHBOURS];
    let mut k = 0;
    let mut brightest = 0f32;
    for_neighbourhood(w, h, x, y, |j| {
        logs[k] = (g[j] + delta).ln();
        brightest = brightest.max(g[j]);
        k += 1;
    });
    if k == 0 {
        // A 1×1 frame: nothing to compare with.
        return None;
    }
    let logs = &mut logs[..k];
    let m = median(logs);
    for v in logs.iter_mut() {
        *v = (*v - m).abs();
    }
    let sigma = 1.4826 * median(logs);
    let tau = (MAD_FACTOR * sigma).max(MIN_FACTOR.ln()) / strength;
    // Where the neighbourhood spans orders of magnitude (sparse samples at low levels) the
    // MAD is large; a pixel far above everything around it is an outlier all the same.
    let bound = (m + tau).min((brightest + delta).ln() + MAX_FACTOR.ln() / strength);
    if centre.ln() <= bound {
        return None;
    }
    // The clamp target: the bound, and no brighter than the brightest neighbour.
    let target = (bound.exp() - delta).min(brightest).max(0.0);
    let scale = if g[i] > 0.0 { (target / g[i]).min(1.0) } else { 1.0 };
    Some(Fix { index: i, scale })
}

/// Whether (x, y) stands alone above its 8 neighbours (each below half of it), or with one
/// partner: a single neighbour not below half, whose own other neighbours are all below half
/// of the partner. Two-sample clusters are as common as single outliers where a bright path
/// is found twice (a caustic seen through a small lens); three or more bright neighbours
/// (a highlight, an edge, a line) are left alone.
fn isolated(g: &[f32], w: usize, h: usize, x: usize, y: usize, delta: f32) -> bool {
    // The neighbours of (x, y) other than `except` not below `limit`: `Ok(None)` for none,
    // `Ok(Some(j))` for one, `Err(())` for more (stops at the second).
    let bright_around = |x: usize, y: usize, except: usize, limit: f32| -> Result<Option<usize>, ()> {
        let (x0, x1) = (x.saturating_sub(1), (x + 1).min(w - 1));
        let (y0, y1) = (y.saturating_sub(1), (y + 1).min(h - 1));
        let mut found = None;
        for yy in y0..=y1 {
            for xx in x0..=x1 {
                let j = yy * w + xx;
                if (yy != y || xx != x) && j != except && g[j] + delta >= limit {
                    if found.is_some() {
                        return Err(());
                    }
                    found = Some(j);
                }
            }
        }
        Ok(found)
    };
    let i = y * w + x;
    match bright_around(x, y, usize::MAX, ISOLATION * (g[i] + delta)) {
        Ok(None) => true,
        Ok(Some(j)) => bright_around(j % w, j / w, i, ISOLATION * (g[j] + delta)) == Ok(None),
        Err(()) => false,
    }
}

/// Luminance of the variance of pixel `i`, in the same domain as `g` (divided by
/// `(albedo + ε)²` where the color is divided by `albedo + ε`).
fn variance_luminance(layer: Layer<'_>, var: [PlaneRef<'_>; 3], i: usize) -> f32 {
    let v = |k: usize| {
        let v = finite(var[k].get(i).max(0.0));
        match layer.albedo {
            Some(a) => v / (a[k].get(i).max(0.0) + EPS).powi(2),
            None => v,
        }
    };
    finite(luminance(finite(v(0)), finite(v(1)), finite(v(2))))
}

/// Calls `f` with the index of each pixel of the 5×5 neighbourhood of (x, y) inside the
/// frame, the centre excluded.
fn for_neighbourhood(w: usize, h: usize, x: usize, y: usize, mut f: impl FnMut(usize)) {
    let (x0, x1) = (x.saturating_sub(RADIUS), (x + RADIUS).min(w - 1));
    let (y0, y1) = (y.saturating_sub(RADIUS), (y + RADIUS).min(h - 1));
    for yy in y0..=y1 {
        for xx in x0..=x1 {
            if yy != y || xx != x {
                f(yy * w + xx);
            }
        }
    }
}

/// The median of `v` (the upper one of an even count); `v` is reordered. 0 when empty.
fn median(v: &mut [f32]) -> f32 {
    if v.is_empty() {
        return 0.0;
    }
    let mid = v.len() / 2;
    *v.select_nth_unstable_by(mid, f32::total_cmp).1
}

/// Applies `fixes` (from [`detect`] on the same buffer) to a color buffer. The variance
/// planes are left as they are (docs/fireflies.md: the variance that the outlier raised
/// tells the network the pixel is unreliable, which measured best).
pub fn apply(fixes: &[Fix], color: &mut [Plane]) {
    for fix in fixes {
        for plane in color.iter_mut() {
            plane[fix.index] *= fix.scale;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A smooth, mildly noisy field (deterministic), level about `level`.
    fn field(w: usize, h: usize, level: f32, seed: u64) -> Plane {
        let mut s = seed;
        (0..w * h)
            .map(|i| {
                s = s.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
                let noise = ((s >> 40) as f32 / (1u64 << 24) as f32 - 0.5) * 0.4;
                let (x, y) = ((i % w) as f32, (i / w) as f32);
                level * (1.0 + 0.2 * (x * 0.2).sin() * (y * 0.15).cos() + noise)
            })
            .collect()
    }

    fn layer<'a>(c: &'a [Plane; 3], var: Option<&'a [Plane]>) -> Layer<'a> {
        let variance = var.map(|v| std::array::from_fn(|k| PlaneRef::F32(&v[k.min(v.len() - 1)])));
        Layer { color: [&c[0], &c[1], &c[2]], variance, albedo: None, fields: true }
    }

    fn rgb(w: usize, h: usize, level: f32) -> [Plane; 3] {
        [field(w, h, level, 1), field(w, h, level, 2), field(w, h, level, 3)]
    }

    #[test]
    fn a_single_outlier_of_any_magnitude_is_clamped_to_its_neighbourhood() {
        let (w, h) = (32, 24);
        for magnitude in [1e4f32, 1e8, 1e15, 1e22, 1e30, f32::MAX] {
            let mut c = rgb(w, h, 0.5);
            let i = 11 * w + 17;
            for p in c.iter_mut() {
                p[i] = magnitude;
            }
            let fixes = detect(layer(&c, None), w, h, Fireflies::default());
            assert_eq!(fixes.len(), 1, "{magnitude:e}: {fixes:?}");
            assert_eq!(fixes[0].index, i);
            apply(&fixes, &mut c);
            let v = luminance(c[0][i], c[1][i], c[2][i]);
            // No brighter than the brightest neighbour (the field's level is ~0.5).
            assert!(v > 0.3 && v < 0.8, "{magnitude:e} became {v}");
        }
    }

    #[test]
    fn a_pair_of_outliers_is_clamped_and_a_two_pixel_line_is_not() {
        let (w, h) = (32, 24);
        let mut c = rgb(w, h, 0.05);
        // The measured case: a bright path found in two vertically adjacent pixels.
        let (a, b) = (11 * w + 17, 12 * w + 17);
        for p in c.iter_mut() {
            (p[a], p[b]) = (6.3, 8.8);
        }
        let mut fixes = detect(layer(&c, None), w, h, Fireflies::default());
        fixes.sort_by_key(|f| f.index);
        assert_eq!(fixes.iter().map(|f| f.index).collect::<Vec<_>>(), [a, b], "{fixes:?}");
        apply(&fixes, &mut c);
        assert!(luminance(c[0][b], c[1][b], c[2][b]) < 0.5, "clamped to its neighbourhood");
        // Three in a row is a line (or a highlight): left alone.
        let mut c = rgb(w, h, 0.05);
        for i in [a, b, 13 * w + 17] {
            for p in c.iter_mut() {
                p[i] = 8.0;
            }
        }
        assert!(detect(layer(&c, None), w, h, Fireflies::default()).is_empty());
    }

    #[test]
    fn a_clean_field_is_left_alone() {
        let (w, h) = (40, 30);
        let c = rgb(w, h, 2.0);
        assert!(detect(layer(&c, None), w, h, Fireflies::default()).is_empty());
    }

    #[test]
    fn small_lights_highlights_and_edges_survive() {
        let (w, h) = (48, 40);
        let mut c = rgb(w, h, 0.3);
        let put = |c: &mut [Plane; 3], x: usize, y: usize, v: f32| {
            for p in c.iter_mut() {
                p[y * w + x] = v;
            }
        };
        // A 2×2 light at 1000× the background.
        for (x, y) in [(5, 5), (6, 5), (5, 6), (6, 6)] {
            put(&mut c, x, y, 300.0);
        }
        // A specular highlight 3 pixels wide with a bright core and falloff.
        for (dx, dy, v) in [(0, 0, 80.0), (1, 0, 50.0), (-1, 0, 50.0), (0, 1, 45.0), (0, -1, 45.0)] {
            put(&mut c, (20 + dx) as usize, (10 + dy) as usize, v);
        }
        // A one-pixel-wide bright line (a lit edge).
        for y in 20..35 {
            put(&mut c, 30, y, 40.0 + (y as f32).sin());
        }
        // A bright region with a hard edge (half the frame's width, rows 30..).
        for y in 30..40 {
            for x in 0..20 {
                put(&mut c, x, y, 25.0);
            }
        }
        let fixes = detect(layer(&c, None), w, h, Fireflies::default());
        assert!(fixes.is_empty(), "{fixes:?}");
        // Even at the strongest setting.
        let strong = Fireflies { mode: FireflyMode::Auto, strength: *STRENGTH_RANGE.end() };
        let fixes = detect(layer(&c, None), w, h, strong);
        assert!(fixes.is_empty(), "{fixes:?}");
    }

    #[test]
    fn a_sparse_caustic_is_signal_and_a_lone_outlier_beside_it_is_not() {
        let (w, h) = (64, 40);
        let mut c = rgb(w, h, 0.1);
        let put = |c: &mut [Plane; 3], i: usize, v: f32| {
            for p in c.iter_mut() {
                p[i] = v;
            }
        };
        // A caustic at a few samples per pixel: isolated bright samples, one pixel in nine,
        // over a 21×21 region (each with 24 others in its 15×15 window).
        let caustic: Vec<usize> = (5..26).step_by(3).flat_map(|y| (5..26).step_by(3).map(move |x| y * w + x)).collect();
        for &i in &caustic {
            put(&mut c, i, 20.0);
        }
        let lone = 20 * w + 50;
        put(&mut c, lone, 20.0);
        let fixes = detect(layer(&c, None), w, h, Fireflies::default());
        assert_eq!(fixes.iter().map(|f| f.index).collect::<Vec<_>>(), [lone], "{fixes:?}");
        // An outlier a hundred times brighter inside the field has no peers there.
        let inside = 15 * w + 16;
        put(&mut c, inside, 2000.0);
        let fixes = detect(layer(&c, None), w, h, Fireflies::default());
        assert_eq!(fixes.iter().map(|f| f.index).collect::<Vec<_>>(), [inside, lone], "{fixes:?}");
        // Without rule 4 (the `beauty` and `lin2020` variants' inputs) every speckle is an outlier.
        let plain = Layer { fields: false, ..layer(&c, None) };
        assert_eq!(detect(plain, w, h, Fireflies::default()).len(), caustic.len() + 2);
        // Each speckle alone would be an outlier.
        let mut one = rgb(w, h, 0.1);
        put(&mut one, caustic[20], 20.0);
        assert_eq!(detect(layer(&one, None), w, h, Fireflies::default()).len(), 1);
        // Up to CLUSTER_LIMIT outliers in one window stay outliers (each has fewer others).
        let mut few = rgb(w, h, 0.1);
        let near: Vec<usize> = (0..CLUSTER_LIMIT).map(|k| 20 * w + 20 + 3 * k).collect();
        for &i in &near {
            put(&mut few, i, 20.0);
        }
        let found: Vec<usize> = detect(layer(&few, None), w, h, Fireflies::default()).iter().map(|f| f.index).collect();
        assert_eq!(found, near);
    }

    #[test]
    fn a_one_pixel_light_with_low_variance_survives_and_with_high_variance_does_not() {
        let (w, h) = (24, 24);
        let mut c = rgb(w, h, 0.5);
        let i = 12 * w + 12;
        for p in c.iter_mut() {
            p[i] = 500.0;
        }
        // Variance of a pixel mean: the background's small; the light's as if all 16
        // samples agreed (small) or one carried it all (about the value squared).
        let mut var = vec![vec![0.01f32; w * h]];
        var[0][i] = 0.5;
        assert!(detect(layer(&c, Some(&var)), w, h, Fireflies::default()).is_empty());
        var[0][i] = 500.0 * 500.0;
        let fixes = detect(layer(&c, Some(&var)), w, h, Fireflies::default());
        assert_eq!(fixes.len(), 1);
        apply(&fixes, &mut c);
        // No brighter than the brightest neighbour (the field reaches about 0.5 × 1.4).
        assert!(c[1][i] < 0.8, "{}", c[1][i]);
    }

    #[test]
    fn texture_is_not_an_outlier_once_divided_by_albedo() {
        // Texels of albedo 0.9, one pixel each, on a surface of albedo 0.02, lit smoothly:
        // in the color they are isolated pixels 45× brighter than their neighbours, 8 pixels
        // apart (so that none has a peer within rule 4's window).
        let (w, h) = (24, 24);
        let albedo: Plane = (0..w * h).map(|i| if i % w % 8 == 0 && i / w % 8 == 0 { 0.9 } else { 0.02 }).collect();
        let light = field(w, h, 1.0, 9);
        let c: [Plane; 3] = std::array::from_fn(|_| light.iter().zip(&albedo).map(|(l, a)| l * a).collect());
        let l = Layer {
            color: [&c[0], &c[1], &c[2]],
            variance: None,
            albedo: Some([PlaneRef::F32(&albedo); 3]),
            fields: true,
        };
        assert!(detect(l, w, h, Fireflies::default()).is_empty());
        // Without the albedo the bright texels look isolated.
        assert!(!detect(layer(&c, None), w, h, Fireflies::default()).is_empty());
    }

    #[test]
    fn strength_moves_the_bound_and_off_does_nothing() {
        let (w, h) = (30, 30);
        let mut c = rgb(w, h, 1.0);
        let i = 15 * w + 15;
        for p in c.iter_mut() {
            p[i] = 6.0;
        }
        // 6× the level: above the default bound (4×), below the bound at strength 0.5 (16×).
        assert_eq!(detect(layer(&c, None), w, h, Fireflies::default()).len(), 1);
        let weak = Fireflies { mode: FireflyMode::Auto, strength: 0.5 };
        assert!(detect(layer(&c, None), w, h, weak).is_empty());
        assert!(detect(layer(&c, None), w, h, Fireflies::OFF).is_empty());
        assert!(Fireflies { mode: FireflyMode::Auto, strength: 0.0 }.validate().is_err());
        assert!(Fireflies { mode: FireflyMode::Auto, strength: f32::NAN }.validate().is_err());
    }

    #[test]
    fn a_black_frame_and_tiny_frames_are_handled() {
        for (w, h) in [(1, 1), (2, 1), (1, 5), (3, 3)] {
            let mut c: [Plane; 3] = std::array::from_fn(|_| vec![0.0; w * h]);
            assert!(detect(layer(&c, None), w, h, Fireflies::default()).is_empty());
            c[0][0] = 1e30;
            let fixes = detect(layer(&c, None), w, h, Fireflies::default());
            if w * h == 1 {
                // A lone pixel has no neighbourhood to compare with.
                assert!(fixes.is_empty());
            } else {
                assert_eq!(fixes.len(), 1, "{w}x{h}");
                apply(&fixes, &mut c);
                assert!(c[0][0].is_finite() && c[0][0] < 1e30, "{w}x{h}: {}", c[0][0]);
            }
        }
    }
}
