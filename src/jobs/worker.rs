//! Workers: OS threads that each own an [`Engine`] (their own ONNX Runtime sessions and
//! thread pool) and run one job at a time. The engine is synchronous; nothing here touches
//! the async runtime.

use std::sync::atomic::Ordering;
use std::thread::JoinHandle;
use std::time::Instant;

use sha2::{Digest, Sha256};

use super::{
    Claim, FireflyCounts, JobError, JobErrorCode, JobMetrics, JobService, Layer, ModelDescription, Outcome, Progress,
    SanitizedCounts, Success, Timings,
};
use crate::engine::{Engine, EngineError};
use crate::frame::{write_exr, Frame, OutputLayer};
use crate::metrics::Metrics;

pub(super) fn spawn(service: &JobService) -> std::io::Result<Vec<JoinHandle<()>>> {
    (0..service.inner.settings.workers)
        .map(|index| {
            let service = service.clone();
            std::thread::Builder::new()
                .name(format!("mcdenoise-worker-{index}"))
                .spawn(move || worker_main(service, index))
        })
        .collect()
}

fn worker_main(service: JobService, index: usize) {
    let span = tracing::info_span!("worker", worker = index);
    let _guard = span.enter();
    let settings = &service.inner.settings;
    if !settings.startup_delay.is_zero() {
        std::thread::sleep(settings.startup_delay);
    }
    let t = Instant::now();
    let mut engine = match load(&service) {
        Ok(e) => e,
        Err(e) => {
            service.worker_failed(format!("worker {index}: {e}"));
            return;
        }
    };
    tracing::info!(ms = t.elapsed().as_secs_f64() * 1e3, "models loaded and warmed up");
    let descriptions = describe(&engine);
    service.worker_ready(descriptions);
    while let Some(claim) = service.next_job() {
        let span = tracing::info_span!("job", job_id = %claim.id, attempt = claim.attempt);
        let _guard = span.enter();
        tracing::info!("started");
        // A panic fails this job only; the worker and its engine go on.
        let outcome = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| run(&service, &mut engine, &claim)))
            .unwrap_or_else(|panic| {
                let message = crate::error::panic_message(panic.as_ref());
                tracing::error!(error = %message, "the job panicked");
                failed(JobErrorCode::Internal, format!("the denoiser failed: {message}"))
            });
        service.finish(claim, outcome);
    }
    tracing::debug!("worker stopped");
}

fn load(service: &JobService) -> Result<Engine, EngineError> {
    let mut engine = Engine::load(&service.inner.settings.engine)?;
    engine.warm_up()?;
    Ok(engine)
}

fn describe(engine: &Engine) -> Vec<ModelDescription> {
    engine
        .models()
        .into_iter()
        .map(|m| ModelDescription {
            variant: m.variant.name().to_string(),
            component: m.component_name().to_string(),
            file: m.path.display().to_string(),
            contract: m.contract.to_string(),
            receptive_radius: m.receptive_radius,
            flops_per_pixel: m.flops_per_pixel,
            architecture: m.architecture.clone(),
            sha256: std::fs::read(&m.path)
                .map(|b| Sha256::digest(&b).iter().map(|x| format!("{x:02x}")).collect())
                .unwrap_or_default(),
        })
        .collect()
}

fn ms(t: Instant) -> f64 {
    t.elapsed().as_secs_f64() * 1e3
}

fn failed(code: JobErrorCode, message: impl Into<String>) -> Outcome {
    Outcome::Failed(JobError { code, message: message.into() }, None)
}

/// Why the engine was asked to stop between tiles.
#[derive(Clone, Copy, PartialEq, Eq)]
enum Stop {
    No,
    Cancel,
    Deadline,
    Shutdown,
}

fn run(service: &JobService, engine: &mut Engine, claim: &Claim) -> Outcome {
    let started = Instant::now();
    let settings = &service.inner.settings;
    let limits = settings.limits;

    let t = Instant::now();
    let bytes = match std::fs::read(&claim.input) {
        Ok(b) => b,
        Err(e) => return failed(JobErrorCode::Internal, format!("cannot read the uploaded frame: {e}")),
    };
    let frame = match Frame::from_exr_bytes(&bytes, &limits) {
        Ok(f) => f,
        Err(e) => return failed(JobErrorCode::InvalidFrame, format!("frame: {e}")),
    };
    drop(bytes);
    let reference = match &claim.reference {
        None => None,
        Some(path) => {
            let decoded = std::fs::read(path)
                .map_err(|e| format!("cannot read the reference: {e}"))
                .and_then(|b| Frame::reference_from_exr_bytes(&b, &limits).map_err(|e| format!("reference: {e}")));
            match decoded {
                Ok(r) if (r.width, r.height) == (frame.width, frame.height) => Some(r),
                Ok(r) => {
                    return failed(
                        JobErrorCode::InvalidFrame,
                        format!(
                            "reference is {}x{} but the frame is {}x{}",
                            r.width, r.height, frame.width, frame.height
                        ),
                    )
                }
                Err(e) => return failed(JobErrorCode::InvalidFrame, e),
            }
        }
    };
    let decode_ms = ms(t);
    if frame.sanitized.total > 0 {
        tracing::warn!(samples = frame.sanitized.total, "non-finite samples replaced by 0");
    }
    if !frame.missing_variances.is_empty() {
        tracing::info!(buffers = ?frame.missing_variances, "variance buffers missing; taken as 0");
    }

    let mut stop = Stop::No;
    let delay = settings.tile_delay;
    let result = engine.denoise_with(&frame, claim.variant, claim.fireflies, &mut |p| {
        service.progress(&claim.id, Progress { tiles_done: p.tiles_done as u32, tiles_total: p.tiles_total as u32 });
        if !delay.is_zero() {
            std::thread::sleep(delay);
        }
        stop = if claim.cancel.load(Ordering::SeqCst) {
            Stop::Cancel
        } else if claim.deadline_at_ms.is_some_and(|d| super::now_ms() >= d) {
            Stop::Deadline
        } else if service.aborting() {
            Stop::Shutdown
        } else {
            Stop::No
        };
        stop == Stop::No
    });
    let out = match result {
        Ok(out) => out,
        Err(EngineError::Cancelled) => {
            return match stop {
                Stop::Cancel | Stop::No => Outcome::Cancelled,
                Stop::Deadline => failed(JobErrorCode::DeadlineExceeded, "the job's deadline passed while it ran"),
                Stop::Shutdown => Outcome::Interrupted,
            }
        }
        Err(EngineError::NoModel(m)) => return failed(JobErrorCode::NoModel, m),
        Err(EngineError::Inference(m)) => return failed(JobErrorCode::Inference, m),
        Err(e @ (EngineError::Runtime(_) | EngineError::Model { .. })) => {
            return failed(JobErrorCode::Internal, e.to_string())
        }
    };
    if claim.cancel.load(Ordering::SeqCst) {
        return Outcome::Cancelled;
    }

    let t = Instant::now();
    let mut layers = vec![OutputLayer { prefix: "", planes: [&out.color[0], &out.color[1], &out.color[2]] }];
    for layer in &claim.layers {
        let planes = match layer {
            Layer::Diffuse => &out.diffuse,
            Layer::Specular => &out.specular,
        };
        layers.push(OutputLayer { prefix: layer.name(), planes: [&planes[0], &planes[1], &planes[2]] });
    }
    let encoded = match write_exr(out.width, out.height, &layers) {
        Ok(b) => b,
        Err(e) => return failed(JobErrorCode::Internal, format!("cannot encode the result: {e}")),
    };
    let encode_ms = ms(t);

    let metrics = reference.as_ref().map(|r| {
        let rc = r.color();
        let rgb = [&rc[0][..], &rc[1][..], &rc[2][..]];
        let noisy = frame.color();
        JobMetrics {
            input: Metrics::compute([&noisy[0], &noisy[1], &noisy[2]], rgb, frame.width, frame.height).into(),
            output: Metrics::compute([&out.color[0], &out.color[1], &out.color[2]], rgb, frame.width, frame.height)
                .into(),
        }
    });
    let timings = Timings {
        queue: claim.queue_ms,
        decode: decode_ms,
        // Firefly handling is counted as preprocessing.
        preprocess: (out.timings.fireflies + out.timings.preprocess).as_secs_f64() * 1e3,
        inference: out.timings.inference.as_secs_f64() * 1e3,
        reconstruction: out.timings.reconstruction.as_secs_f64() * 1e3,
        encode: encode_ms,
        total: ms(started),
    };
    Outcome::Succeeded(Box::new(Success {
        variant: out.variant,
        progress: Progress { tiles_done: out.tiles as u32, tiles_total: out.tiles as u32 },
        timings,
        metrics,
        sanitized: SanitizedCounts { total: frame.sanitized.total, by_buffer: frame.sanitized.by_buffer.clone() },
        fireflies: FireflyCounts {
            mode: claim.fireflies.mode,
            strength: claim.fireflies.strength,
            handled: out.fireflies.total(),
            by_component: out.fireflies,
        },
        missing_variances: frame.missing_variances.clone(),
        pixels: (out.width * out.height) as u64,
        result: encoded,
        started,
    }))
}
