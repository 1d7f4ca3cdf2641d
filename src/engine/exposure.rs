//! Exposure: a frame far brighter than every frame the networks trained on is brought down
//! into their range before the networks, and the result back up after.
//!
//! The networks are not scale-equivariant: the KPCN inputs (irradiance, log specular,
//! variances) depend on the radiance's units, and the training frames span about 8 stops
//! (exposure augmentation adds ±2). Renderers' units differ far more than that (a sunlit
//! exterior in physical units averages hundreds). Measured with the shipped network on 30
//! Mitsuba training frames of 4–64 spp, every frame's radiance scaled by k: RelMSE
//! 0.0078 at k = 1, 0.0083 at 8, 0.0109 at 64 and 0.0284 at 512 (docs/frame-layout.md,
//! "Exposure"). So a frame whose [`level`] is above [`LEVEL_MAX`] has its diffuse and
//! specular scaled by `s` (variances by `s²`) to that level, and the results by `1/s`; any
//! other frame is left exactly as it is. Darker frames are not brought up: at k = 1/64 the
//! same frames gave 0.0080 as they are and 0.0084 brought up to a floor of 0.001, so the
//! networks need no help there.
//!
//! The level is the geometric mean over 16×16 blocks of each block's mean luminance of the
//! noisy diffuse + specular (the statistic of Intel Open Image Denoise's auto-exposure,
//! which does the same for every frame): block means are robust to fireflies, and the
//! logarithm to a few very bright or black regions.

use rayon::prelude::*;

use super::preprocess::luminance;
use crate::frame::{Buffer, Frame};

/// The highest level the networks are trusted with. The procedural scenes they trained on
/// reach about 3.3 (the 136 training frames of `data/` on 2026-11-28, Mitsuba and Cycles,
/// every sample count: 0.0023 to 0.58; the Cycles test frames: 0.048 to 3.25), and training
/// shows each frame up to 2 stops brighter (exposure augmentation): every frame of the
/// generator stays as it is, and a brighter one is brought down to this level.
pub const LEVEL_MAX: f64 = 4.0;

/// Side of the blocks whose mean luminances the level averages.
const BLOCK: usize = 16;

/// Block means at or below this are unlit (black) and left out of the level.
const UNLIT: f64 = 1e-8;

/// The frame's exposure level (see the module documentation); `None` when no block is lit.
pub fn level(frame: &Frame) -> Option<f64> {
    let (w, h) = (frame.width, frame.height);
    let d = frame.f32_planes(Buffer::Diffuse);
    let s = frame.f32_planes(Buffer::Specular);
    let (bw, bh) = (w.div_ceil(BLOCK), h.div_ceil(BLOCK));
    // One band of blocks per task: each block's sum over its rows, then the log of its mean.
    let (sum, lit) = (0..bh)
        .into_par_iter()
        .map(|by| {
            let rows = by * BLOCK..((by + 1) * BLOCK).min(h);
            let mut sums = vec![0f64; bw];
            for y in rows.clone() {
                let row = y * w..(y + 1) * w;
                let (dr, dg, db) = (&d[0][row.clone()], &d[1][row.clone()], &d[2][row.clone()]);
                let (sr, sg, sb) = (&s[0][row.clone()], &s[1][row.clone()], &s[2][row]);
                for x in 0..w {
                    let l = luminance(dr[x] + sr[x], dg[x] + sg[x], db[x] + sb[x]);
                    sums[x / BLOCK] += f64::from(l);
                }
            }
            let mut acc = (0f64, 0usize);
            for (bx, total) in sums.into_iter().enumerate() {
                let pixels = ((bx + 1) * BLOCK).min(w) - bx * BLOCK;
                let mean = total / (pixels * rows.len()) as f64;
                if mean > UNLIT && mean.is_finite() {
                    acc = (acc.0 + mean.ln(), acc.1 + 1);
                }
            }
            acc
        })
        .reduce(|| (0.0, 0), |a, b| (a.0 + b.0, a.1 + b.1));
    (lit > 0).then(|| (sum / lit as f64).exp())
}

/// The factor that brings `level` down to [`LEVEL_MAX`]: 1 at or below it, and for a frame
/// with no lit block.
pub fn scale_for(level: Option<f64>) -> f32 {
    match level {
        Some(l) if l > LEVEL_MAX => Some((LEVEL_MAX / l) as f32).filter(|s| *s > 0.0).unwrap_or(1.0),
        _ => 1.0,
    }
}

/// `frame` with its diffuse and specular multiplied by `s` and their variances by `s²`;
/// `None` for `s` = 1 (the frame is used as it is).
pub fn apply(frame: &Frame, s: f32) -> Option<Frame> {
    if s == 1.0 {
        return None;
    }
    let mut out = frame.clone();
    for (buffer, factor) in [
        (Buffer::Diffuse, s),
        (Buffer::Specular, s),
        (Buffer::DiffuseVariance, s * s),
        (Buffer::SpecularVariance, s * s),
    ] {
        if out.has(buffer) {
            out.planes_mut(buffer).par_iter_mut().for_each(|p| p.iter_mut().for_each(|v| *v *= factor));
        }
    }
    Some(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_scale_brings_a_brighter_level_down_to_the_top_and_leaves_the_rest() {
        assert_eq!(scale_for(Some(LEVEL_MAX)), 1.0);
        assert_eq!(scale_for(Some(1e-6)), 1.0);
        assert_eq!(scale_for(None), 1.0);
        assert!((f64::from(scale_for(Some(LEVEL_MAX * 100.0))) * 100.0 - 1.0).abs() < 1e-6);
    }
}
