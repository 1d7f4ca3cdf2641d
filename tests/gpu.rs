//! The GPU path against the CPU path, where ONNX Runtime's CUDA build and a GPU are present
//! (`ORT_DYLIB_PATH` at the onnxruntime-gpu library: docs/training.md, "The engine on the
//! GPU"). Elsewhere, CI included, each test says why it skipped.

use crate::common;

use std::path::PathBuf;

use common::{fixture_frame, max_rel_diff};
use mcdenoise::engine::device::{cuda_devices, cuda_provider_available};
use mcdenoise::engine::{Device, Engine, EngineConfig, Options, Precision, Reconstruction};

/// Why the GPU tests cannot run here, if they cannot.
fn no_gpu() -> Option<String> {
    mcdenoise::engine::runtime::environment(None).expect("the ONNX Runtime library");
    if !cuda_provider_available() {
        return Some("this ONNX Runtime library has no CUDA execution provider (the CPU build)".into());
    }
    match cuda_devices() {
        Ok(0) => Some("the NVIDIA driver reports no GPU".into()),
        Ok(_) => None,
        Err(e) => Some(e),
    }
}

fn engine(device: Device, reconstruction: Reconstruction, precision: Precision) -> Engine {
    let mut config = EngineConfig::new(PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("models"));
    (config.device, config.reconstruction, config.precision) = (device, reconstruction, precision);
    Engine::load(&config).unwrap_or_else(|e| panic!("{device:?}: {e}"))
}

#[test]
fn the_gpu_denoises_as_the_cpu_does() {
    if let Some(why) = no_gpu() {
        eprintln!("skipped: {why}");
        return;
    }
    // The bench's parity on an H100 (docs/results.md, "GPU"): 7.5e-4 of the largest value in
    // float32 (ONNX Runtime's CUDA convolutions use TF32) and 5.8e-4 in half precision; the
    // tolerances leave room for other frames and cards.
    let mut cpu = engine(Device::Cpu, Reconstruction::Engine, Precision::Fp32);
    for (precision, tolerance) in [(Precision::Fp32, 3e-3), (Precision::Fp16, 1e-2)] {
        let mut gpu = engine(Device::Cuda(0), Reconstruction::Graph, precision);
        for name in ["cornell-spp8.exr", "caustic-spp8.exr", "cornell-nocov-spp8.exr"] {
            let frame = fixture_frame(name);
            let a = gpu.denoise_with(&frame, Options::default(), &mut |_| true).unwrap();
            let b = cpu.denoise_with(&frame, Options::default(), &mut |_| true).unwrap();
            for c in 0..3 {
                assert!(a.color[c].iter().all(|v| v.is_finite()), "{name} {precision:?}: not finite");
                let d = max_rel_diff(&a.color[c], &b.color[c]);
                println!("{name} {precision:?} channel {c}: {d:.2e} of the largest value");
                assert!(d <= tolerance, "{name} {precision:?} channel {c}: {d:.2e} > {tolerance:.0e}");
            }
        }
    }
}
