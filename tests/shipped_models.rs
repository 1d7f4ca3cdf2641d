//! The shipped models (models/) on the committed fixture frames: they must lower the error
//! of the noisy input clearly. Measured when the models were committed (RelMSE input →
//! output, default multi-scale `full`/`nocov` | the paper's network at its width `lin2020` |
//! at reduced width `lin2020-narrow`): cornell 0.041 → 0.0064 | 0.0091 | 0.0070, caustic
//! 0.44 → 0.025 | 0.031 | 0.030, shadow 0.0027 → 0.00043 | 0.00061 | 0.0014, cornell without
//! covariance (nocov) 0.041 → 0.0064; `beauty` (the frames without the split, as a
//! beauty-only file gives them) cornell 0.041 → 0.0071, caustic 0.44 → 0.026, shadow 0.0027
//! → 0.00040. The test asks for a factor of 1.5 on every frame and 3 on the Cornell box, in
//! RelMSE and in DSSIM.

use std::path::PathBuf;

use mcdenoise::engine::{Engine, EngineConfig, Precision, Reconstruction, Variant};
use mcdenoise::frame::{Buffer, Frame, Limits, SampleType};
use mcdenoise::quality::Metrics;

fn fixture(name: &str) -> Vec<u8> {
    std::fs::read(PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/frames").join(name)).unwrap()
}

fn metrics(frame: [&[f32]; 3], reference: &Frame) -> Metrics {
    let r = reference.color();
    Metrics::compute(frame, [&r[0], &r[1], &r[2]], reference.width, reference.height)
}

#[test]
fn shipped_models_denoise_the_fixtures() {
    let mut config = EngineConfig::new(PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("models"));
    config.threads = 2;
    let mut engine = Engine::load(&config).expect("shipped models load");
    let lin2020 = Variant::parse("lin2020").unwrap();
    let narrow = Variant::parse("lin2020-narrow").unwrap();
    assert_eq!(engine.variants(), [Variant::Beauty, Variant::Full, lin2020, narrow, Variant::Nocov]);
    // `None`: the engine's own choice; `beauty` frames are the fixtures without their split.
    for (noisy, reference, asked, variant, factor) in [
        ("cornell-spp8.exr", "cornell-ref.exr", None, Variant::Full, 3.0),
        ("cornell-nocov-spp8.exr", "cornell-ref.exr", None, Variant::Nocov, 3.0),
        ("caustic-spp8.exr", "caustic-ref.exr", None, Variant::Full, 1.5),
        ("shadow-spp8.exr", "shadow-ref.exr", None, Variant::Full, 1.5),
        ("cornell-spp8.exr", "cornell-ref.exr", Some(lin2020), lin2020, 3.0),
        ("caustic-spp8.exr", "caustic-ref.exr", Some(lin2020), lin2020, 1.5),
        ("shadow-spp8.exr", "shadow-ref.exr", Some(lin2020), lin2020, 1.5),
        ("cornell-spp8.exr", "cornell-ref.exr", Some(narrow), narrow, 3.0),
        ("caustic-spp8.exr", "caustic-ref.exr", Some(narrow), narrow, 1.5),
        ("shadow-spp8.exr", "shadow-ref.exr", Some(narrow), narrow, 1.5),
        ("cornell-spp8.exr", "cornell-ref.exr", None, Variant::Beauty, 3.0),
        ("caustic-spp8.exr", "caustic-ref.exr", None, Variant::Beauty, 1.5),
        ("shadow-spp8.exr", "shadow-ref.exr", None, Variant::Beauty, 1.5),
    ] {
        let mut frame = Frame::from_exr_bytes(&fixture(noisy), &Limits::default()).unwrap();
        if variant == Variant::Beauty {
            frame = frame.to_beauty();
        }
        let reference = Frame::reference_from_exr_bytes(&fixture(reference), &Limits::default()).unwrap();
        let out = engine.denoise(&frame, asked, &mut |_| true).unwrap();
        assert_eq!(out.variant, variant, "{noisy}");
        let c = frame.color();
        let before = metrics([&c[0], &c[1], &c[2]], &reference);
        let after = metrics([&out.color[0], &out.color[1], &out.color[2]], &reference);
        assert!(after.relmse * factor <= before.relmse, "{noisy}: RelMSE {} -> {}", before.relmse, after.relmse);
        assert!(after.dssim * factor <= before.dssim, "{noisy}: DSSIM {} -> {}", before.dssim, after.dssim);
    }
}

/// The shipped variants' `model-recon.onnx` (their reconstruction in the graph, which a GPU
/// runs) give what the engine's reconstruction of `model.onnx` gives, here on the CPU; their
/// `model-recon-fp16.onnx` (the network in half precision) stays near it.
#[test]
fn shipped_models_reconstruct_alike_in_the_graph() {
    let load = |reconstruction, precision| {
        let mut config = EngineConfig::new(PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("models"));
        (config.threads, config.reconstruction, config.precision) = (2, reconstruction, precision);
        Engine::load(&config).expect("shipped models load")
    };
    let mut rust = load(Reconstruction::Engine, Precision::Fp32);
    let mut graph = load(Reconstruction::Graph, Precision::Fp32);
    let mut half = load(Reconstruction::Graph, Precision::Fp16);
    let frame = Frame::from_exr_bytes(&fixture("caustic-spp8.exr"), &Limits::default()).unwrap();
    for variant in [Variant::Full, Variant::Nocov, Variant::Beauty] {
        let a = rust.denoise(&frame, Some(variant), &mut |_| true).unwrap();
        for (engine, tolerance) in [(&mut graph, 1e-4), (&mut half, 2e-2)] {
            let b = engine.denoise(&frame, Some(variant), &mut |_| true).unwrap();
            for c in 0..3 {
                let scale = a.color[c].iter().fold(1f32, |m, v| m.max(v.abs()));
                let worst = a.color[c].iter().zip(&b.color[c]).fold(0f32, |m, (x, y)| m.max((x - y).abs()));
                assert!(worst <= tolerance * scale, "{variant}: channel {c} differs by {worst} (scale {scale})");
            }
        }
    }
}

/// A file with only a beauty, albedo and normal (no split, no depth, no variances), as most
/// renderers write by default: `mcdenoise run` picks `beauty`, says nothing is approximated
/// and beats the input as the engine test above asks.
#[test]
fn a_beauty_only_file_is_denoised_by_the_beauty_variant() {
    let frame = Frame::from_exr_bytes(&fixture("cornell-spp8.exr"), &Limits::default()).unwrap();
    let beauty = frame.diffuse_plus_specular();
    let f32_planes = |b: Buffer| frame.planes(b).iter().map(|p| p.to_vec()).collect::<Vec<_>>();
    let (albedo, normal) = (f32_planes(Buffer::Albedo), f32_planes(Buffer::Normal));
    let mut planes: Vec<(String, &[f32])> = Vec::new();
    for (c, name) in ["R", "G", "B"].iter().enumerate() {
        planes.push((name.to_string(), &beauty[c]));
        planes.push((format!("albedo.{name}"), &albedo[c]));
        planes.push((format!("normal.{name}"), &normal[c]));
    }
    let bytes = mcdenoise::frame::write_planes(
        frame.width,
        frame.height,
        planes.iter().map(|(n, p)| (n.as_str(), *p)),
        SampleType::F32,
        exr::prelude::Encoding::FAST_LOSSLESS,
    )
    .unwrap();
    let tmp = tempfile::tempdir().unwrap();
    let (input, output) = (tmp.path().join("beauty.exr"), tmp.path().join("out.exr"));
    std::fs::write(&input, bytes).unwrap();
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    let res = std::process::Command::new(env!("CARGO_BIN_EXE_mcdenoise"))
        .args(["run", input.to_str().unwrap(), "-o", output.to_str().unwrap(), "--threads", "2"])
        .args(["--models", root.join("models").to_str().unwrap()])
        .args(["--reference", root.join("tests/fixtures/frames/cornell-ref.exr").to_str().unwrap()])
        .output()
        .unwrap();
    assert!(res.status.success(), "{}", String::from_utf8_lossy(&res.stderr));
    let report: serde_json::Value = serde_json::from_slice(&res.stdout).unwrap();
    assert_eq!(report["variant"], "beauty", "{report}");
    assert_eq!(report["warnings"], serde_json::json!([]), "{report}");
    let (before, after) = (&report["metrics"]["input"], &report["metrics"]["output"]);
    for m in ["relmse", "dssim"] {
        assert!(after[m].as_f64().unwrap() * 3.0 <= before[m].as_f64().unwrap(), "{m}: {before} -> {after}");
    }
}
