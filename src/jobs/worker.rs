//! Workers: OS threads that each own a [`Denoiser`] (for the real engine: its own ONNX
//! Runtime sessions and thread pool) and run one job at a time through
//! [`crate::pipeline`]. Nothing here touches the async runtime or the core's state: a
//! worker only talks to the core through its [`WorkerLink`].
//!
//! Locking: none held here; every call on the link takes the locks it needs, briefly.

use std::sync::atomic::Ordering;
use std::thread::JoinHandle;
use std::time::Instant;

use super::claims::{Claim, Outcome, Success, WorkerLink};
use crate::engine::{Denoiser, DenoiserFactory, EngineError};
use crate::jobs::{JobError, JobErrorCode, Progress};
use crate::pipeline::{self, Failure, Input};

pub(super) fn spawn(
    link: WorkerLink,
    denoisers: DenoiserFactory,
    count: usize,
) -> std::io::Result<Vec<JoinHandle<()>>> {
    (0..count)
        .map(|index| {
            let (link, denoisers) = (link.clone(), denoisers.clone());
            std::thread::Builder::new()
                .name(format!("mcdenoise-worker-{index}"))
                .spawn(move || worker_main(link, denoisers, index))
        })
        .collect()
}

fn worker_main(link: WorkerLink, denoisers: DenoiserFactory, index: usize) {
    let span = tracing::info_span!("worker", worker = index);
    let _guard = span.enter();
    let t = Instant::now();
    let mut denoiser = match denoisers() {
        Ok(d) => d,
        Err(e) => {
            link.failed(format!("worker {index}: {e}"));
            return;
        }
    };
    tracing::info!(ms = t.elapsed().as_secs_f64() * 1e3, "models loaded and warmed up");
    link.ready(denoiser.models(), denoiser.device());
    while let Some(claim) = link.next_job() {
        // Each run is a trace of its own, or continues its submission's ([`crate::otlp`]).
        let span = tracing::info_span!(
            parent: None,
            "job",
            job_id = %claim.id,
            attempt = claim.attempt,
            worker = index,
            variant = tracing::field::Empty,
            outcome = tracing::field::Empty,
        );
        crate::otlp::continue_trace(&span, claim.trace_parent.as_deref(), None);
        let _guard = span.enter();
        tracing::info!("started");
        // A panic fails this job only; the worker and its denoiser go on.
        let outcome = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| run(&link, denoiser.as_mut(), &claim)))
            .unwrap_or_else(|panic| {
                let message = crate::error::panic_message(panic.as_ref());
                tracing::error!(error = %message, "the job panicked");
                failed(JobErrorCode::Internal, format!("the denoiser failed: {message}"))
            });
        let (ended, variant) = match &outcome {
            Outcome::Succeeded(s) => ("succeeded", Some(s.output.variant.name())),
            Outcome::Failed(e, _) => (e.code.name(), None),
            Outcome::Cancelled => ("cancelled", None),
            Outcome::StorageFault(_) => ("storage_fault", None),
            Outcome::Interrupted => ("interrupted", None),
        };
        span.record("outcome", ended);
        if let Some(v) = variant {
            span.record("variant", v);
        }
        link.finish(claim, outcome);
    }
    tracing::debug!("worker stopped");
}

fn failed(code: JobErrorCode, message: impl Into<String>) -> Outcome {
    Outcome::Failed(JobError { code, message: message.into() }, None)
}

/// Why the denoiser was asked to stop between tiles.
#[derive(Clone, Copy, PartialEq, Eq)]
enum Stop {
    No,
    Cancel,
    Deadline,
    Shutdown,
}

fn run(link: &WorkerLink, denoiser: &mut dyn Denoiser, claim: &Claim) -> Outcome {
    let started = Instant::now();
    let channel_maps = match &claim.channel_maps {
        Ok(maps) => maps.clone(),
        Err(e) => return failed(JobErrorCode::InvalidFrame, e.clone()),
    };
    let request = pipeline::Request {
        frame: &claim.input,
        reference: claim.reference.as_deref(),
        variant: claim.variant,
        fireflies: claim.fireflies,
        variance_check: link.settings().variance_check,
        layers: &claim.layers,
        limits: link.settings().limits,
        channel_maps,
        keep_colors: true,
    };
    let mut stop = Stop::No;
    let result = pipeline::run(denoiser, &request, &mut |p| {
        link.progress(&claim.id, Progress { tiles_done: p.tiles_done as u32, tiles_total: p.tiles_total as u32 });
        stop = if claim.cancel.load(Ordering::SeqCst) {
            Stop::Cancel
        } else if claim.deadline_at_ms.is_some_and(|d| link.now() >= d) {
            Stop::Deadline
        } else if link.aborting() {
            Stop::Shutdown
        } else {
            Stop::No
        };
        stop == Stop::No
    });
    let mut output = match result {
        Ok(output) => output,
        Err(Failure::Engine(EngineError::Cancelled)) => {
            return match stop {
                Stop::Cancel | Stop::No => Outcome::Cancelled,
                Stop::Deadline => failed(JobErrorCode::DeadlineExceeded, "the job's deadline passed while it ran"),
                Stop::Shutdown => Outcome::Interrupted,
            }
        }
        Err(e) => return failed_by(e),
    };
    if claim.cancel.load(Ordering::SeqCst) {
        return Outcome::Cancelled;
    }
    output.timings.queue = claim.queue_ms;
    Outcome::Succeeded(Box::new(Success { output, started, fireflies: claim.fireflies }))
}

/// The job error of a pipeline failure.
fn failed_by(e: Failure) -> Outcome {
    match e {
        // The upload was on disk when the job was accepted: not reading it now is a
        // storage fault (retried), not the job's.
        Failure::Read { which: Input::Frame, error } => {
            Outcome::StorageFault(crate::error::Error::storage("cannot read the uploaded frame", &error).to_string())
        }
        e @ (Failure::Read { which: Input::Reference, .. } | Failure::Invalid { .. } | Failure::SizeMismatch(_)) => {
            failed(JobErrorCode::InvalidFrame, e.to_string())
        }
        Failure::Engine(EngineError::NoModel(m)) => failed(JobErrorCode::NoModel, m),
        Failure::Engine(EngineError::Inference(m)) => failed(JobErrorCode::Inference, m),
        Failure::Engine(e @ (EngineError::Runtime(_) | EngineError::Model { .. } | EngineError::Cancelled)) => {
            failed(JobErrorCode::Internal, e.to_string())
        }
        Failure::Encode(m) => failed(JobErrorCode::Internal, format!("cannot encode the result: {m}")),
    }
}
