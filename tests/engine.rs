//! The engine on real contract-v1 graphs (the tiny random test models): preprocessing
//! values, tiling, variant choice, contract checks, cancellation.

use crate::common;

use common::*;
use mcdenoise::engine::contract::COLOR_CHANNELS;
use mcdenoise::engine::preprocess::{luminance, preprocess, preprocess_into, Inputs};
use mcdenoise::engine::{
    synthetic_frame, Engine, EngineConfig, EngineError, FeatureSet, FrameStats, Options, Rect, Variant, EPS,
};
use mcdenoise::frame::{layout::REQUIRED, Buffer, Frame};

/// A 3×2 frame with hand-picked values; those of the buffers kept as f16 (every one but the
/// colors and the depth) are exact in f16, so that the closed forms below hold to f32.
fn hand_frame() -> Frame {
    Frame::from_planes(3, 2, hand_planes(), REQUIRED, &Default::default()).unwrap()
}

fn hand_planes() -> Vec<(String, Vec<f32>)> {
    let p = |v: [f32; 6]| v.to_vec();
    let planes = vec![
        ("diffuse.R".into(), p([1.0, 2.0, 3.0, 4.0, 5.0, 6.0])),
        ("diffuse.G".into(), p([0.5; 6])),
        ("diffuse.B".into(), p([0.0; 6])),
        ("albedo.R".into(), p([0.5, 0.25, 1.0, 0.5, 0.5, 0.5])),
        ("albedo.G".into(), p([1.0; 6])),
        ("albedo.B".into(), p([0.0; 6])),
        ("specular.R".into(), p([0.0, 1.0, 3.0, -1.0, 0.5, 0.0])),
        ("specular.G".into(), p([0.0; 6])),
        ("specular.B".into(), p([0.0; 6])),
        ("normal.R".into(), p([0.0, 0.5, 1.0, 0.0, 0.0, 0.0])),
        ("normal.G".into(), p([0.0; 6])),
        ("normal.B".into(), p([1.0; 6])),
        ("depth.Z".into(), p([1.0, 2.0, 4.0, 8.0, 0.0, 2.0])),
        ("covariance".into(), p([0.0, 0.125, 0.25, 0.5, 0.125, 0.0])),
        ("diffuseVariance.R".into(), p([0.125; 6])),
        ("diffuseVariance.G".into(), p([0.25; 6])),
        ("diffuseVariance.B".into(), p([0.375; 6])),
        ("specularVariance.Z".into(), p([0.5; 6])),
        ("albedoVariance.Z".into(), p([0.0078125; 6])),
        ("normalVariance.Z".into(), p([0.015625; 6])),
        ("depthVariance.Z".into(), p([1.5; 6])),
        ("covarianceVariance.Z".into(), p([0.03125; 6])),
    ];
    planes
}

fn close(a: f32, b: f32) -> bool {
    (a - b).abs() <= 1e-6 * b.abs().max(1.0)
}

#[test]
fn preprocessing_matches_closed_form() {
    let frame = hand_frame();
    let stats = FrameStats::of(&frame);
    // Hit depths 1, 2, 2, 4, 8: median 2, so depths above 32 would be far.
    assert_eq!(stats, FrameStats { depth_max: 8.0, depth_far: 32.0, covariance_max: 0.5 });
    let t = preprocess(&frame, &stats, FeatureSet::Full, Rect { x: 0, y: 0, w: 3, h: 2 });
    let n = 6;
    let ch = |v: &[f32], c: usize| v[c * n..(c + 1) * n].to_vec();

    // Diffuse color d / (a + ε), its gradients, and its variance lum(σ² / (a + ε)²).
    let d = ch(&t.diffuse, 0);
    assert!(close(d[0], 1.0 / (0.5 + EPS)) && close(d[1], 2.0 / (0.25 + EPS)));
    let gx = ch(&t.diffuse, 4);
    assert!(close(gx[0], d[1] - d[0]) && close(gx[1], d[2] - d[1]) && gx[2] == 0.0, "{gx:?}");
    let gy = ch(&t.diffuse, 7);
    assert!(close(gy[0], d[3] - d[0]) && gy[3] == 0.0 && gy[5] == 0.0);
    let var = ch(&t.diffuse, 3);
    let want = luminance(0.125 / (0.5 + EPS).powi(2), 0.25 / (1.0 + EPS).powi(2), 0.375 / EPS.powi(2));
    assert!(close(var[0], want), "{} vs {want}", var[0]);

    // Specular ln(1 + max(s, 0)) and variance σ² / (1 + s)² per channel, then luminance.
    let s = ch(&t.specular, 0);
    assert!(close(s[1], 2f32.ln()) && close(s[2], 4f32.ln()) && s[3] == 0.0);
    let svar = ch(&t.specular, 3);
    assert!(close(svar[2], luminance(0.5 / 16.0, 0.5, 0.5)), "{}", svar[2]);

    // Features: depth and covariance divided by the frame's maximum; variances by its square.
    assert_eq!(t.features.len(), 28 * n);
    let f = |k: usize| ch(&t.features, k);
    assert_eq!(f(0)[1], 0.5); // normal.R
    assert_eq!(f(3)[0], 0.5); // albedo.R
    assert!(close(f(6)[2], 0.5) && close(f(6)[3], 1.0)); // depth / 8
    assert!(close(f(7)[2], 0.5)); // covariance / 0.5
    assert!(close(f(8)[0], 0.015625)); // normalVariance
    assert!(close(f(9)[0], 0.0078125)); // albedoVariance
    assert!(close(f(10)[0], 1.5 / 64.0)); // depthVariance / 8²
    assert!(close(f(11)[0], 0.03125 / 0.25)); // covarianceVariance / 0.5²
    assert!(close(f(12)[0], 0.5)); // gx normal.R
    assert!(close(f(18)[0], 0.125)); // gx depth
    assert!(close(f(26)[0], 7.0 / 8.0)); // gy depth: (8 − 1) / 8
    assert!(close(f(27)[1], 0.0)); // gy covariance: 0.125 − 0.125

    // The nocov variant is the full one without the covariance channels.
    let nocov = preprocess(&frame, &stats, FeatureSet::Nocov, Rect { x: 0, y: 0, w: 3, h: 2 });
    let keep: Vec<usize> = (0..28).filter(|k| ![7, 11, 19, 27].contains(k)).collect();
    for (j, &k) in keep.iter().enumerate() {
        assert_eq!(ch(&nocov.features, j), f(k), "feature {k}");
    }
}

#[test]
fn depths_far_beyond_the_frames_median_are_read_as_no_hit() {
    // A sky dome 10⁵ away behind the hand frame's background pixel, and a huge variance
    // where a pixel's samples mixed it with a near surface.
    let mut planes = hand_planes();
    for (name, plane) in planes.iter_mut() {
        match name.as_str() {
            "depth.Z" => plane[4] = 1e5,
            "depthVariance.Z" => plane[5] = 1e6,
            _ => {}
        }
    }
    let frame = Frame::from_planes(3, 2, planes, REQUIRED, &Default::default()).unwrap();
    let stats = FrameStats::of(&frame);
    // Hits 1, 2, 2, 4, 8, 1e5: the lower median 2; 1e5 > 16 × 2 is far.
    assert_eq!(stats, FrameStats { depth_max: 8.0, depth_far: 32.0, covariance_max: 0.5 });
    let t = preprocess(&frame, &stats, FeatureSet::Full, Rect { x: 0, y: 0, w: 3, h: 2 });
    // The same inputs as with the background at 0 (the hand frame), but for the saturated variance.
    let plain =
        preprocess(&hand_frame(), &FrameStats::of(&hand_frame()), FeatureSet::Full, Rect { x: 0, y: 0, w: 3, h: 2 });
    let n = 6;
    for k in 0..28 {
        let (a, b) = (&t.features[k * n..][..n], &plain.features[k * n..][..n]);
        if k == 10 {
            // depthVariance / 8²: 0 where the depth is far, at most 1 elsewhere.
            assert_eq!(a[4], 0.0);
            assert_eq!(a[5], 1.0);
            assert_eq!(a[..4], b[..4]);
        } else {
            assert_eq!(a, b, "feature {k}");
        }
    }
    // A frame without hits: no scale, nothing far.
    assert_eq!(mcdenoise::engine::depth_scale(&[0.0; 4]), (0.0, f32::INFINITY));
    // A dome over most of the frame: the median is the dome's, but the four nearer depths
    // (a quarter or more) give the bound: their lower median 2, far above 32.
    let mut dome = vec![1e5f32; 6];
    dome.extend([1.0, 2.0, 3.0, 4.0]);
    assert_eq!(mcdenoise::engine::depth_scale(&dome), (4.0, 32.0));
    // Two nearer depths of ten are not a quarter: the dome is the scene.
    let mut mostly = vec![1e5f32; 8];
    mostly.extend([1.0, 2.0]);
    assert_eq!(mcdenoise::engine::depth_scale(&mostly), (1e5, 16e5));
}

#[test]
fn a_region_preprocesses_like_the_same_pixels_of_the_whole_frame() {
    let frame = synthetic_frame(21, 17, true);
    let stats = FrameStats::of(&frame);
    let whole = preprocess(&frame, &stats, FeatureSet::Full, Rect { x: 0, y: 0, w: 21, h: 17 });
    let rect = Rect { x: 5, y: 4, w: 16, h: 9 };
    let part = preprocess(&frame, &stats, FeatureSet::Full, rect);
    for (a, b, c) in [(&part.diffuse, &whole.diffuse, COLOR_CHANNELS), (&part.features, &whole.features, 28)] {
        for k in 0..c {
            for y in 0..rect.h {
                for x in 0..rect.w {
                    assert_eq!(a[k * rect.pixels() + y * rect.w + x], b[k * 21 * 17 + (rect.y + y) * 21 + rect.x + x]);
                }
            }
        }
    }
}

#[test]
fn buffers_reused_for_another_region_are_written_whole() {
    // The engine hands the buffers of one region to the next: stale values, here NaN,
    // must all be overwritten, for both feature sets.
    let frame = synthetic_frame(21, 17, true);
    let stats = FrameStats::of(&frame);
    let rect = Rect { x: 3, y: 2, w: 15, h: 11 };
    for set in FeatureSet::ALL {
        let fresh = preprocess(&frame, &stats, set, rect);
        // Longer and shorter than needed (10 and 24 or 28 channels of 165 pixels).
        let stale = |len| vec![f32::NAN; len];
        let mut reused = Inputs { rect, diffuse: stale(5000), specular: stale(1000), features: stale(3000) };
        preprocess_into(&frame, &stats, set, rect, &mut reused);
        assert_eq!(reused.diffuse, fresh.diffuse, "{set:?}");
        assert_eq!(reused.specular, fresh.specular, "{set:?}");
        assert_eq!(reused.features, fresh.features, "{set:?}");
    }
}

#[test]
fn tiled_output_equals_whole_frame_output() {
    let frame = synthetic_frame(53, 41, true);
    let whole = engine(0).denoise(&frame, None, &mut |_| true).unwrap();
    assert_eq!(whole.tiles, 1);
    for tile in [16, 25] {
        let tiled = engine(tile).denoise(&frame, None, &mut |_| true).unwrap();
        assert!(tiled.tiles > 4);
        for c in 0..3 {
            let d = max_rel_diff(&tiled.color[c], &whole.color[c]);
            assert!(d <= 1e-5, "tile {tile}, channel {c}: relative difference {d}");
        }
    }
}

#[test]
fn the_variant_follows_the_frames_channels() {
    let mut e = engine(32);
    let full = e.denoise(&synthetic_frame(20, 20, true), None, &mut |_| true).unwrap();
    assert_eq!(full.variant, Variant::Full);
    let nocov = e.denoise(&synthetic_frame(20, 20, false), None, &mut |_| true).unwrap();
    assert_eq!(nocov.variant, Variant::Nocov);
    let err = e.denoise(&synthetic_frame(20, 20, false), Some(Variant::Full), &mut |_| true).err().unwrap();
    assert!(err.to_string().contains("needs a `covariance` channel"), "{err}");
}

#[test]
fn output_is_finite_and_positive_where_input_is() {
    let out = engine(32).denoise(&synthetic_frame(40, 30, true), None, &mut |_| true).unwrap();
    for c in 0..3 {
        assert!(out.color[c].iter().all(|v| v.is_finite() && *v >= 0.0));
        for i in 0..out.color[c].len() {
            assert!((out.color[c][i] - parts(&out).diffuse[c][i] - parts(&out).specular[c][i]).abs() <= 1e-6);
        }
    }
}

#[test]
fn negative_colors_and_albedos_give_a_finite_output() {
    // An albedo of exactly -EPS would divide by zero if it were not taken as 0.
    let mut planes = named_planes(24, 16, false);
    for (name, plane) in planes.iter_mut() {
        if name.starts_with("albedo.") {
            plane.iter_mut().enumerate().for_each(|(i, v)| *v = if i % 2 == 0 { -EPS } else { -0.5 });
        }
        if name.starts_with("diffuse.") || name.starts_with("specular.") {
            plane.iter_mut().step_by(3).for_each(|v| *v = -2.0);
        }
    }
    let frame = frame_of(&exr_single(24, 16, &planes, Sample::F32));
    let out = engine(16).denoise(&frame, None, &mut |_| true).unwrap();
    assert!(out.color.iter().flatten().all(|v| v.is_finite()));
}

#[test]
fn cancellation_stops_between_tiles() {
    let mut e = engine(16);
    let mut seen = 0;
    let err = e
        .denoise(&synthetic_frame(64, 64, true), None, &mut |p| {
            seen = p.tiles_done;
            p.tiles_done < 3
        })
        .err()
        .unwrap();
    assert!(matches!(err, EngineError::Cancelled));
    assert_eq!(seen, 3);
}

fn copy_model(dir: &std::path::Path, variant: &str, component: &str, from_variant: &str, from_component: &str) {
    std::fs::create_dir_all(dir.join(variant)).unwrap();
    std::fs::copy(
        tiny_models().join(from_variant).join(format!("{from_component}.onnx")),
        dir.join(variant).join(format!("{component}.onnx")),
    )
    .unwrap();
}

fn load_error(dir: &std::path::Path) -> String {
    let mut config = EngineConfig::new(dir);
    config.threads = 1;
    match Engine::load(&config) {
        Ok(_) => panic!("loaded a mismatched model set"),
        Err(e) => e.to_string(),
    }
}

#[test]
fn mismatched_models_are_refused_with_the_field_named() {
    let tmp = tempfile::tempdir().unwrap();
    // A full-variant model placed under nocov/.
    copy_model(tmp.path(), "nocov", "diffuse", "full", "diffuse");
    copy_model(tmp.path(), "nocov", "specular", "nocov", "specular");
    let msg = load_error(tmp.path());
    assert!(
        msg.contains("nocov/diffuse.onnx") && msg.contains("`mcdenoise.variant` is `full`, expected `nocov`"),
        "{msg}"
    );

    // A specular network named diffuse.onnx.
    let tmp = tempfile::tempdir().unwrap();
    copy_model(tmp.path(), "full", "diffuse", "full", "specular");
    copy_model(tmp.path(), "full", "specular", "full", "specular");
    let msg = load_error(tmp.path());
    assert!(msg.contains("`mcdenoise.component` is `specular`, expected `diffuse`"), "{msg}");

    // A missing file, and a directory without variants.
    let tmp = tempfile::tempdir().unwrap();
    copy_model(tmp.path(), "full", "diffuse", "full", "diffuse");
    assert!(load_error(tmp.path()).contains("full/specular.onnx: file not found"));
    let tmp = tempfile::tempdir().unwrap();
    assert!(load_error(tmp.path()).contains("no model variants found"));

    // Not an ONNX file at all.
    let tmp = tempfile::tempdir().unwrap();
    std::fs::create_dir_all(tmp.path().join("full")).unwrap();
    std::fs::write(tmp.path().join("full/diffuse.onnx"), b"not a model").unwrap();
    copy_model(tmp.path(), "full", "specular", "full", "specular");
    assert!(load_error(tmp.path()).contains("cannot load"));
}

#[test]
fn models_report_their_contract_fields() {
    let e = engine(0);
    assert_eq!(e.variants(), vec![Variant::Full, Variant::Nocov]);
    for info in e.models() {
        assert_eq!(info.receptive_radius, 6);
        assert!(info.flops_per_pixel > 1000.0);
    }
    assert!(e.flops_per_pixel(Variant::Full).unwrap() > e.flops_per_pixel(Variant::Nocov).unwrap());
    assert!(Buffer::ALL.len() == 13);
}

/// Finite in, finite out at every magnitude: a seeded sweep sets one pixel, then a whole
/// plane, of each channel of each buffer to magnitudes from 1e-30 to the float maximum
/// (the ends, every decade between, and seeded log-uniform draws; either sign), and runs the
/// engine (both variants, tiled, fireflies `auto` and `off`): every output pixel must be
/// finite.
#[test]
fn every_magnitude_in_every_channel_gives_a_finite_output() {
    use mcdenoise::engine::Fireflies;
    let (w, h) = (20, 18);
    let mut engine = engine(8);
    let base = synthetic_planes_named(w, h);
    let mut seed = 0x5EED_u64;
    let mut next = move || {
        seed = seed.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = seed;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    };
    let mut magnitudes: Vec<f32> = vec![1e-30, f32::MAX, 3.4e38, 1e38];
    magnitudes.extend((-30..=38).step_by(4).map(|e| 10f32.powi(e)));
    for _ in 0..8 {
        let u = (next() >> 11) as f64 / (1u64 << 53) as f64;
        magnitudes.push(10f64.powf(-30.0 + u * (38.5 - -30.0)).min(f32::MAX as f64) as f32);
    }
    let mut runs = 0;
    for (index, (name, _)) in base.iter().enumerate() {
        for (k, &m) in magnitudes.iter().enumerate() {
            let value = if k % 3 == 2 { -m } else { m };
            for whole_plane in [false, true] {
                let mut planes = base.clone();
                let pixel = (next() % (w * h) as u64) as usize;
                if whole_plane {
                    planes[index].1.fill(value);
                } else {
                    planes[index].1[pixel] = value;
                }
                let frame = Frame::from_planes(w, h, planes, REQUIRED, &Default::default()).unwrap();
                for variant in [Variant::Full, Variant::Nocov] {
                    for fireflies in [Fireflies::default(), Fireflies::OFF] {
                        if fireflies == Fireflies::OFF && whole_plane {
                            continue;
                        }
                        let out = engine
                            .denoise_with(
                                &frame,
                                Options { variant: Some(variant), fireflies, components: true },
                                &mut |_| true,
                            )
                            .unwrap();
                        runs += 1;
                        for (layer, planes) in [
                            ("color", &out.color),
                            ("diffuse", &parts(&out).diffuse),
                            ("specular", &parts(&out).specular),
                        ] {
                            for (c, p) in planes.iter().enumerate() {
                                if let Some(bad) = p.iter().position(|v| !v.is_finite()) {
                                    panic!(
                                        "{name} = {value:e} ({}) with {variant:?}, fireflies {:?}: {layer}[{c}] \
                                         pixel {bad} is {}",
                                        if whole_plane { "whole plane" } else { "one pixel" },
                                        fireflies.mode,
                                        p[bad]
                                    );
                                }
                            }
                        }
                    }
                }
            }
        }
    }
    assert!(runs > 1000, "{runs} runs");
}

/// The synthetic frame's planes with every variance as three channels, so that the sweep
/// reaches each channel of each buffer.
fn synthetic_planes_named(w: usize, h: usize) -> Vec<(String, Vec<f32>)> {
    let mut planes = Vec::new();
    for (name, plane) in mcdenoise::engine::synthetic_planes(w, h, true) {
        match name.strip_suffix(".Z").filter(|n| n.ends_with("Variance") && !n.starts_with("depth")) {
            Some(base) if !base.starts_with("covariance") => {
                for ch in ["R", "G", "B"] {
                    planes.push((format!("{base}.{ch}"), plane.clone()));
                }
            }
            _ => planes.push((name, plane)),
        }
    }
    planes
}
