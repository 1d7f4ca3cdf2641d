//! The scale of a frame's variances, checked against the noise its image shows.
//!
//! Every variance buffer is meant to hold the variance of the pixel's *mean* (the samples'
//! variance divided by their count, docs/frame-layout.md). A renderer or a script that
//! writes the samples' variance instead hands the networks variances n times too large at
//! n samples per pixel, and they then take the noisy color for far less noisy than it is:
//! with the variances of the validation frames of both renderers multiplied by 64, the
//! shipped network's DSSIM rose by 17–35 % and its RelMSE by 1.8–20× (docs/frame-layout.md,
//! "Variance scale").
//!
//! # Method
//!
//! For the diffuse and the specular color, the luminance's difference from the mean of its
//! four neighbours, `d = x − ¼ Σ x_n`, has `E[d²] = 1.25 σ²` where the image is flat and its
//! noise, of variance `σ²`, independent from pixel to pixel; edges and texture only add to
//! it. The ratio `r = d² / (1.25 v)`, `v` the luminance of the pixel's variance, is taken
//! over the interior pixels with `v > 0` (at most [`MAX_SAMPLES`] per component, evenly
//! spaced), and its median over both components is the check's measure.
//!
//! On the training, validation and development frames of both renderers (Mitsuba's variance
//! of the mean, and the Cycles frames' estimate from independent renders; 290 frames of 1
//! to 128 spp, none of the test sets) the median lies between 0.31 and 42, typically
//! 0.6–0.7: the pixel filter spreads a sample over neighbouring pixels, whose noise is then
//! correlated, which lowers `d²`. Variances of the samples at `n` spp give about `0.65 / n`.
//! Below [`THRESHOLD`], six times under the lowest median measured, the result warns
//! ([`VarianceCheck::Warn`], the default), and with [`VarianceCheck::Auto`] every variance
//! buffer is multiplied by `median / TYPICAL`, which brings the measure back to its typical
//! value. Warning only is the default because a noiseless image with variances (a frame
//! already filtered by the renderer, or a synthetic one) measures near 0 as well.

use rayon::prelude::*;

use super::preprocess::luminance;
use crate::frame::{Buffer, Frame};

/// Medians below this mean variances far larger than the noise of the image.
pub const THRESHOLD: f32 = 0.05;
/// The median on frames whose variances are right (see the module's text).
pub const TYPICAL: f32 = 0.65;
/// Pixels sampled per color buffer, at most.
pub const MAX_SAMPLES: usize = 250_000;
/// Fewer valid pixels than this (over both components) decide nothing.
pub const MIN_SAMPLES: usize = 1_000;

/// Whether the variances' scale is checked.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum VarianceCheck {
    /// Variances used as the file gives them, not measured.
    Off,
    /// Variances far larger than the image's noise are reported in the result's warnings
    /// and used as they are (the default).
    #[default]
    Warn,
    /// Variances far larger than the image's noise are scaled down, and the warning says so.
    Auto,
}

impl std::str::FromStr for VarianceCheck {
    type Err = String;

    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "auto" => Ok(VarianceCheck::Auto),
            "warn" => Ok(VarianceCheck::Warn),
            "off" => Ok(VarianceCheck::Off),
            other => Err(format!("unknown variance check `{other}`: expected `warn`, `auto` or `off`")),
        }
    }
}

impl std::fmt::Display for VarianceCheck {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            VarianceCheck::Off => "off",
            VarianceCheck::Warn => "warn",
            VarianceCheck::Auto => "auto",
        })
    }
}

/// The median ratio of the image's local noise to its variances ([module](self)), or `None`
/// when the frame has too few pixels with a variance to tell (variances absent or zero).
pub fn measure(frame: &Frame) -> Option<f32> {
    let mut ratios = Vec::new();
    for (color, variance) in [(Buffer::Diffuse, Buffer::DiffuseVariance), (Buffer::Specular, Buffer::SpecularVariance)]
    {
        let known =
            frame.has(color) && frame.has(variance) && !frame.missing_variances.iter().any(|m| m == variance.name());
        if known {
            ratios.extend(component_ratios(frame, color, variance));
        }
    }
    if ratios.len() < MIN_SAMPLES {
        return None;
    }
    let mid = ratios.len() / 2;
    let (_, median, _) = ratios.select_nth_unstable_by(mid, f32::total_cmp);
    Some(*median)
}

fn component_ratios(frame: &Frame, color: Buffer, variance: Buffer) -> Vec<f32> {
    let (w, h) = (frame.width, frame.height);
    if w < 3 || h < 3 {
        return Vec::new();
    }
    let c = frame.f32_planes(color);
    let lum = |i: usize| luminance(c[0][i], c[1][i], c[2][i]);
    let v = frame.rgb(variance);
    let var = |i: usize| luminance(v[0].get(i), v[1].get(i), v[2].get(i));
    let interior = (w - 2) * (h - 2);
    let step = interior.div_ceil(MAX_SAMPLES).max(1);
    (0..interior)
        .into_par_iter()
        .step_by(step)
        .filter_map(|k| {
            let (x, y) = (1 + k % (w - 2), 1 + k / (w - 2));
            let i = y * w + x;
            let v = var(i);
            if v <= 0.0 {
                return None;
            }
            let d = lum(i) - 0.25 * (lum(i - 1) + lum(i + 1) + lum(i - w) + lum(i + w));
            Some(d * d / (1.25 * v))
        })
        .collect()
}

/// What the check did to a frame's variances.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct VarianceScale {
    /// The measure before ([`measure`]).
    pub measured: f32,
    /// The factor that brings the measure to [`TYPICAL`].
    pub factor: f32,
    /// Whether every variance buffer was multiplied by it ([`VarianceCheck::Auto`]).
    pub applied: bool,
}

impl VarianceScale {
    /// The result's warning.
    pub fn warning(&self) -> String {
        let done = if self.applied {
            format!("every variance buffer was scaled by {:.3e} (--variance-check warn keeps them)", self.factor)
        } else {
            format!("they were used as they are (--variance-check auto scales them by {:.3e})", self.factor)
        };
        format!(
            "the frame's variances are about {:.0}x the noise its image shows (measure {:.3}, typical {TYPICAL}): \
             a variance buffer holds the variance of the pixel's mean, the samples' variance divided by their \
             count; {done}",
            1.0 / self.factor,
            self.measured,
        )
    }
}

/// Checks the frame's variances ([module](self)); with [`VarianceCheck::Auto`] scales them
/// down where they are far too large. `None` when they are not (or `Off`).
pub fn check(frame: &mut Frame, mode: VarianceCheck) -> Option<VarianceScale> {
    if mode == VarianceCheck::Off {
        return None;
    }
    let measured = measure(frame)?;
    if measured >= THRESHOLD {
        return None;
    }
    let factor = measured.max(f32::MIN_POSITIVE) / TYPICAL;
    if mode == VarianceCheck::Warn {
        return Some(VarianceScale { measured, factor, applied: false });
    }
    for buffer in Buffer::ALL.into_iter().filter_map(Buffer::variance) {
        if let Some(mut planes) = frame.take(buffer) {
            planes.par_iter_mut().for_each(|p| p.iter_mut().for_each(|x| *x *= factor));
            frame.set_planes(buffer, planes);
        }
    }
    Some(VarianceScale { measured, factor, applied: true })
}
