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

    let (rw, rh) = (region.w as isize, region.h as isize);
    let cw = core.w;
    let (out_r, rest) = out.split_at_mut(core.pixels());
    let (out_g, out_b) = rest.split_at_mut(core.pixels());
    out_r.par_chunks_mut(cw).zip(out_g.par_chunks_mut(cw)).zip(out_b.par_chunks_mut(cw)).enumerate().for_each(
        |(row, ((or, og), ob))| {
            let ry = (core.y - region.y + row) as isize;
            let rx0 = core.x - region.x;
            let row_start = ry as usize * region.w + rx0;
            let mut max = vec![f32::NEG_INFINITY; cw];
            for k in 0..TAPS {
                let l = &logits[k * n + row_start..][..cw];
                for (m, &v) in max.iter_mut().zip(l) {
                    *m = m.max(v);
                }
            }
            let mut sum = vec![0f32; cw];
            let mut acc = [vec![0f32; cw], vec![0f32; cw], vec![0f32; cw]];
            for ky in 0..KERNEL_SIZE {
                let sy = (ry + ky as isize - KERNEL_RADIUS as isize).clamp(0, rh - 1) as usize;
                let src_rows: [&[f32]; 3] = std::array::from_fn(|c| &color[c * n + sy * region.w..][..region.w]);
                for kx in 0..KERNEL_SIZE {
                    let k = ky * KERNEL_SIZE + kx;
                    let l = &logits[k * n + row_start..][..cw];
                    let dx = kx as isize - KERNEL_RADIUS as isize;
                    for x in 0..cw {
                        let sx = (rx0 as isize + x as isize + dx).clamp(0, rw - 1) as usize;
                        let e = (l[x] - max[x]).exp();
                        sum[x] += e;
                        acc[0][x] += e * src_rows[0][sx];
                        acc[1][x] += e * src_rows[1][sx];
                        acc[2][x] += e * src_rows[2][sx];
                    }
                }
            }
            for x in 0..cw {
                let inv = 1.0 / sum[x];
                or[x] = acc[0][x] * inv;
                og[x] = acc[1][x] * inv;
                ob[x] = acc[2][x] * inv;
            }
        },
    );
}

#[cfg(test)]
mod tests {
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
