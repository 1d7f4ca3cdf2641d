//! The variance scale check (src/engine/variance.rs) on the committed fixture frames, whose
//! variances are those of each pixel's mean: it leaves them alone, and it finds variances
//! of the samples (64 times too large at 64 spp), which the networks would otherwise trust
//! far too much: `warn` reports them, `auto` undoes them.

use crate::common;

use std::path::PathBuf;

use common::fixture_frame as fixture;
use mcdenoise::engine::variance::{self, VarianceCheck, THRESHOLD, TYPICAL};
use mcdenoise::engine::{Engine, EngineConfig, Options};
use mcdenoise::frame::{Buffer, Frame};
use mcdenoise::quality::relmse;

const SCENES: [(&str, &str); 3] = [
    ("cornell-spp8.exr", "cornell-ref.exr"),
    ("caustic-spp8.exr", "caustic-ref.exr"),
    ("shadow-spp8.exr", "shadow-ref.exr"),
];

/// The frame with every variance buffer multiplied by `k`.
fn scaled(frame: &Frame, k: f32) -> Frame {
    let mut out = frame.clone();
    for buffer in Buffer::ALL.into_iter().filter_map(Buffer::variance) {
        if let Some(mut planes) = out.take(buffer) {
            planes.iter_mut().for_each(|p| p.iter_mut().for_each(|x| *x *= k));
            out.set_planes(buffer, planes);
        }
    }
    out
}

fn planes(frame: &Frame, buffer: Buffer) -> Vec<Vec<f32>> {
    frame.planes(buffer).iter().map(|p| p.to_vec()).collect()
}

fn error(engine: &mut Engine, frame: &Frame, reference: &Frame) -> f64 {
    let out = engine.denoise_with(frame, Options::default(), &mut |_| true).unwrap();
    let r = reference.color();
    relmse([&out.color[0], &out.color[1], &out.color[2]], [&r[0], &r[1], &r[2]])
}

#[test]
fn variances_of_the_mean_are_left_as_they_are() {
    for (name, _) in SCENES {
        let frame = fixture(name);
        let measured = variance::measure(&frame).expect("the fixtures have variances");
        println!("{name}: measure {measured:.3}");
        assert!(measured > 3.0 * THRESHOLD, "{name}: measure {measured} near the threshold");
        let mut checked = frame.clone();
        assert_eq!(variance::check(&mut checked, VarianceCheck::Auto), None, "{name}");
        assert_eq!(variance::check(&mut checked, VarianceCheck::Warn), None, "{name}");
        assert_eq!(planes(&checked, Buffer::DiffuseVariance), planes(&frame, Buffer::DiffuseVariance));
    }
}

#[test]
fn variances_of_the_samples_are_scaled_back() {
    let mut config = EngineConfig::new(PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("models"));
    config.threads = 2;
    let mut engine = Engine::load(&config).expect("shipped models load");
    for (name, reference) in SCENES {
        let (frame, reference) = (fixture(name), fixture(reference));
        let wrong = scaled(&frame, 64.0);
        let mut off = wrong.clone();
        assert_eq!(variance::check(&mut off, VarianceCheck::Off), None);
        let mut warned = wrong.clone();
        let warning = variance::check(&mut warned, VarianceCheck::Warn).expect("warned");
        assert!(!warning.applied && warning.warning().contains("--variance-check auto"), "{}", warning.warning());
        assert_eq!(planes(&warned, Buffer::DiffuseVariance), planes(&wrong, Buffer::DiffuseVariance));
        let mut fixed = wrong.clone();
        let scale = variance::check(&mut fixed, VarianceCheck::Auto).expect("64x variances are found");
        assert!(scale.applied && (scale.factor - warning.factor).abs() < 1e-9);
        println!("{name}: measure {:.4}, scaled by {:.4} (1/64 = {:.4})", scale.measured, scale.factor, 1.0 / 64.0);
        assert!(scale.measured < THRESHOLD);
        assert!((scale.factor * 64.0 - 1.0).abs() < 0.6, "{name}: factor {} for variances 64x too large", scale.factor);
        assert!(scale.warning().contains("variance"), "{}", scale.warning());
        let after = variance::measure(&fixed).unwrap();
        // (within the rounding of variances kept in half float)
        assert!((after / TYPICAL - 1.0).abs() < 0.03, "{name}: measure {after} after scaling");
        // Every variance buffer, not only the two the measure reads.
        let (a, b) = (planes(&wrong, Buffer::AlbedoVariance), planes(&fixed, Buffer::AlbedoVariance));
        let ratio = |i: usize| b[0][i] / a[0][i];
        let i = a[0].iter().position(|&x| x > 1e-3).expect("an albedo variance");
        assert!((ratio(i) / scale.factor - 1.0).abs() < 1e-2, "albedo variance scaled by {}", ratio(i));
        // The networks' output gets better for it.
        let (right, wrong_e, fixed_e) = (
            error(&mut engine, &frame, &reference),
            error(&mut engine, &wrong, &reference),
            error(&mut engine, &fixed, &reference),
        );
        println!("{name}: RelMSE {right:.5} as rendered, {wrong_e:.5} with 64x variances, {fixed_e:.5} checked");
        assert!(fixed_e < wrong_e, "{name}: {fixed_e} checked against {wrong_e}");
    }
}

#[test]
fn frames_without_variances_are_not_judged() {
    let mut frame = fixture("cornell-spp8.exr");
    for buffer in [Buffer::DiffuseVariance, Buffer::SpecularVariance] {
        let n = frame.pixels();
        frame.set_planes(buffer, vec![vec![0.0; n]]);
    }
    assert_eq!(variance::measure(&frame), None);
    assert_eq!(variance::check(&mut frame, VarianceCheck::Auto), None);
}
