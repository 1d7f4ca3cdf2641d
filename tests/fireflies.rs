//! Firefly handling with the shipped models on the committed fixture frames: isolated
//! outliers injected into a frame must barely change the denoised result's error, and a
//! frame without injected outliers must come out as well as without the handling. The
//! numbers are printed (`cargo test --release --test integration -- --nocapture fireflies::`);
//! docs/fireflies.md lists them.

use crate::common;

use std::path::PathBuf;

use common::fixture_frame as fixture;
use mcdenoise::engine::preprocess::luminance;
use mcdenoise::engine::{Engine, EngineConfig, Fireflies, Options, Variant};
use mcdenoise::frame::{Buffer, Frame};
use mcdenoise::quality::relmse;

/// A small deterministic generator (SplitMix64).
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    fn uniform(&mut self) -> f64 {
        (self.next() >> 11) as f64 / (1u64 << 53) as f64
    }

    fn below(&mut self, n: usize) -> usize {
        (self.next() % n as u64) as usize
    }
}

/// Injects `count` isolated outliers (at least 6 pixels apart and 2 from the border) of
/// 10–1000× (log-uniform) the local level, the mean luminance of the frame's color over
/// the pixel's 5×5 neighbourhood, into the diffuse or the specular buffer (alternately): the
/// component gains a white `Δ` that makes the pixel's luminance that multiple, and its
/// variance gains `Δ²`, as a renderer's variance of the pixel mean would with one sample
/// carrying the outlier. Pixels darker than a tenth of the frame's median are skipped (a
/// multiple of black is black). Returns the pixels.
fn inject(frame: &mut Frame, count: usize, seed: u64) -> Vec<usize> {
    let (w, h) = (frame.width, frame.height);
    let color = frame.diffuse_plus_specular();
    let lum: Vec<f32> = (0..w * h).map(|i| luminance(color[0][i], color[1][i], color[2][i])).collect();
    let mut sorted = lum.clone();
    sorted.sort_by(f32::total_cmp);
    let median = sorted[sorted.len() / 2];
    let mut rng = Rng(seed);
    let mut chosen: Vec<usize> = Vec::new();
    let mut tries = 0;
    while chosen.len() < count {
        tries += 1;
        assert!(tries < 100_000, "cannot place {count} outliers in a {w}x{h} frame");
        let (x, y) = (2 + rng.below(w - 4), 2 + rng.below(h - 4));
        if chosen.iter().any(|&j| (j % w).abs_diff(x).max((j / w).abs_diff(y)) < 6) {
            continue;
        }
        let mut level = 0.0;
        for yy in y - 2..=y + 2 {
            for xx in x - 2..=x + 2 {
                level += lum[yy * w + xx] / 25.0;
            }
        }
        if level < 0.1 * median {
            continue;
        }
        let i = y * w + x;
        let factor = 10f64.powf(1.0 + 2.0 * rng.uniform()) as f32;
        let delta = factor * level - lum[i];
        let (col, var) = if chosen.len() % 2 == 0 {
            (Buffer::Diffuse, Buffer::DiffuseVariance)
        } else {
            (Buffer::Specular, Buffer::SpecularVariance)
        };
        for p in frame.planes_mut(col) {
            p[i] += delta;
        }
        for p in frame.planes_mut(var) {
            p[i] += delta * delta;
        }
        chosen.push(i);
    }
    chosen
}

fn engine() -> Engine {
    let mut config = EngineConfig::new(PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("models"));
    config.threads = 2;
    Engine::load(&config).expect("shipped models load")
}

/// RelMSE of `frame` denoised by `variant` (the engine's choice for `None`), and the samples
/// the firefly handling took.
fn error_of(
    engine: &mut Engine,
    variant: Option<Variant>,
    frame: &Frame,
    reference: &Frame,
    fireflies: Fireflies,
) -> (f64, u64) {
    let out = engine.denoise_with(frame, Options { variant, fireflies, components: false }, &mut |_| true).unwrap();
    let r = reference.color();
    (relmse([&out.color[0], &out.color[1], &out.color[2]], [&r[0], &r[1], &r[2]]), out.fireflies.total())
}

fn error(engine: &mut Engine, frame: &Frame, reference: &Frame, fireflies: Fireflies) -> (f64, u64) {
    error_of(engine, None, frame, reference, fireflies)
}

const SCENES: [(&str, &str); 3] = [
    ("cornell-spp8.exr", "cornell-ref.exr"),
    ("caustic-spp8.exr", "caustic-ref.exr"),
    ("shadow-spp8.exr", "shadow-ref.exr"),
];

#[test]
fn injected_outliers_barely_change_the_error() {
    let mut engine = engine();
    let auto = Fireflies::default();
    for (noisy, reference) in SCENES {
        let clean = fixture(noisy);
        let reference = fixture(reference);
        let mut injected = clean.clone();
        let pixels = inject(&mut injected, 20, 22);
        let (base_auto, _) = error(&mut engine, &clean, &reference, auto);
        let (base_off, _) = error(&mut engine, &clean, &reference, Fireflies::OFF);
        let (inj_auto, handled) = error(&mut engine, &injected, &reference, auto);
        let (inj_off, _) = error(&mut engine, &injected, &reference, Fireflies::OFF);
        println!(
            "{noisy}: RelMSE clean {base_auto:.5} (off {base_off:.5}); with {} outliers: auto {inj_auto:.5} \
             ({:.3}x, {handled} samples handled), off {inj_off:.4} ({:.0}x)",
            pixels.len(),
            inj_auto / base_auto,
            inj_off / base_off
        );
        assert!(inj_auto <= 1.2 * base_auto, "{noisy}: RelMSE {base_auto} -> {inj_auto} with the handling on");
        // The outliers must matter for the test to mean anything: they do for the paper's
        // network without the handling. (The default network, trained with injected
        // fireflies, damps them partly itself: `inj_off` is 4x on the Cornell box, 1x on the
        // caustic.)
        let lin2020 = Variant::parse("lin2020");
        let (paper_clean, _) = error_of(&mut engine, lin2020, &clean, &reference, Fireflies::OFF);
        let (paper_injected, _) = error_of(&mut engine, lin2020, &injected, &reference, Fireflies::OFF);
        assert!(paper_injected >= 10.0 * paper_clean, "{noisy}: the injection should hurt without the handling");
        assert!(handled >= pixels.len() as u64, "{noisy}: {handled} handled, {} injected", pixels.len());
    }
}

#[test]
fn frames_without_injected_outliers_lose_nothing() {
    let mut engine = engine();
    for (noisy, reference) in SCENES {
        let frame = fixture(noisy);
        let reference = fixture(reference);
        let (auto, handled) = error(&mut engine, &frame, &reference, Fireflies::default());
        let (off, _) = error(&mut engine, &frame, &reference, Fireflies::OFF);
        println!("{noisy}: RelMSE auto {auto:.5} ({handled} samples handled), off {off:.5}");
        assert!(auto <= 1.02 * off, "{noisy}: RelMSE {off} without the handling, {auto} with it");
    }
}
