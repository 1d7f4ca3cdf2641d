//! Every ONNX Runtime session of the process allocates from one CPU arena
//! (`src/engine/runtime.rs`): a daemon that has served each variant holds the largest
//! working set, not the sum of one arena per variant. Alone in its test binary (its own
//! process), so that no other test's memory is counted.
//!
//! Measured on 1280×720 frames through the daemon, one job per variant in turn: 3.26 GB
//! resident with an arena per session, 0.97 GB shared. Here on 512×384 frames, the growth of
//! the resident set over the next three jobs (`nocov`, `beauty`, `full` again) must stay
//! below the first job's own growth (with an arena per session each new variant adds about
//! as much as the first).

mod common;

use std::path::PathBuf;

use mcdenoise::engine::{Engine, EngineConfig, Variant};

/// Resident set of this process in bytes (`VmRSS` of /proc/self/status).
fn resident() -> u64 {
    let status = std::fs::read_to_string("/proc/self/status").unwrap();
    let line = status.lines().find(|l| l.starts_with("VmRSS:")).unwrap();
    line.split_whitespace().nth(1).unwrap().parse::<u64>().unwrap() * 1024
}

#[test]
fn variants_share_one_arena() {
    let mut config = EngineConfig::new(PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("models"));
    config.threads = 2;
    let mut engine = Engine::load(&config).expect("shipped models load");
    let (w, h) = (512, 384);
    let frame = common::frame_of(&common::exr_single(w, h, &common::named_planes(w, h, true), common::Sample::F32));
    let beauty = frame.to_beauty();
    let mut run = |variant: Variant| {
        let input = if variant == Variant::Beauty { &beauty } else { &frame };
        let out = engine.denoise(input, Some(variant), &mut |_| true).unwrap();
        assert_eq!(out.variant, variant);
    };
    let start = resident();
    run(Variant::Full);
    let first = resident().saturating_sub(start);
    let after_first = resident();
    for variant in [Variant::Nocov, Variant::Beauty, Variant::Full] {
        run(variant);
    }
    let rest = resident().saturating_sub(after_first);
    assert!(first > 50 << 20, "the first variant's working set is visible ({} MB)", first >> 20);
    assert!(rest < first, "the other variants added {} MB after the first's {} MB", rest >> 20, first >> 20);
}
