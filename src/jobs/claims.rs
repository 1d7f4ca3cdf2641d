//! The workers' side of the lifecycle, behind [`WorkerLink`], the only way a worker
//! reaches the core: claim the next job, report progress, hand back the outcome.
//!
//! Locking: `next_job` waits on the work `Condvar` under the state lock and marks the job
//! running in memory; the running state is written afterwards (`persist`), since recovery
//! treats a running job like a queued one. A success's files are written with no lock
//! held; its record then goes through the one `settle` (`lifecycle`).

use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Instant;

use super::lifecycle::{deadline_passed, Ending, Finished};
use super::{lock_poisoned, JobService};
use crate::engine::{ModelInfo, Variant};
use crate::jobs::{FireflyCounts, JobError, JobErrorCode, JobEvent, JobState, Layer, Phase, Progress};
use crate::pipeline;

/// A job handed to a worker.
pub(crate) struct Claim {
    pub id: String,
    pub attempt: u32,
    pub input: PathBuf,
    pub reference: Option<PathBuf>,
    pub variant: Option<Variant>,
    pub fireflies: crate::engine::Fireflies,
    pub layers: Vec<Layer>,
    /// How the frame's AOV names are read; `Err`: the job's channel map is no longer
    /// known (the daemon restarted with another configuration).
    pub channel_maps: Result<crate::frame::ChannelMaps, String>,
    pub deadline_at_ms: Option<i64>,
    /// The submission's trace context ([`crate::otlp`]).
    pub trace_parent: Option<String>,
    /// Milliseconds the job waited in the queue before this run.
    pub queue_ms: f64,
    pub cancel: Arc<AtomicBool>,
}

/// How a worker's run of a job ended.
pub(crate) enum Outcome {
    Succeeded(Box<Success>),
    Failed(JobError, Option<crate::jobs::Timings>),
    Cancelled,
    /// The input could not be read or the result written for a storage reason: back to
    /// the queue after a pause (bounded; see `JobService::retry_later`).
    StorageFault(String),
    /// Stopped by the shutdown deadline: back to the queue for the next start.
    Interrupted,
}

/// A finished run, before its result is written.
pub(crate) struct Success {
    /// Its `timings.queue` is the claim's wait.
    pub output: pipeline::Output,
    /// When the run started: `timings.total` is measured from here once the result is on
    /// disk (the write time is added to `encode`).
    pub started: Instant,
    /// The firefly handling the run used.
    pub fireflies: crate::engine::Fireflies,
}

/// What a worker may ask of the core.
#[derive(Clone)]
pub(crate) struct WorkerLink {
    service: JobService,
}

impl WorkerLink {
    pub(super) fn new(service: JobService) -> WorkerLink {
        WorkerLink { service }
    }

    pub fn settings(&self) -> &super::Settings {
        self.service.settings()
    }

    /// Unix milliseconds by the core's clock (deadlines are checked against it).
    pub fn now(&self) -> i64 {
        self.service.now()
    }

    /// A worker has loaded its models on `device`; the service is ready once every worker
    /// has.
    pub fn ready(&self, models: Vec<ModelInfo>, device: Option<crate::engine::Device>) {
        let s = &self.service;
        if let Some(d) = device {
            let _ = s.inner.device.set(d);
        }
        if s.inner.models.set(models).is_ok() {
            for m in s.models().unwrap_or_default() {
                s.inner.telemetry.model_loaded(m.variant.name(), m.component_name(), &m.architecture, &m.sha256);
            }
        }
        let mut st = s.lock();
        st.workers_ready += 1;
        s.inner.telemetry.set_workers(s.inner.settings.workers, st.workers_ready);
        if st.workers_ready == s.inner.settings.workers && s.phase() == Phase::Loading {
            s.set_phase(Phase::Ready);
            tracing::info!(workers = st.workers_ready, "models loaded and warmed up: ready");
        }
        s.inner.work.notify_all();
    }

    /// A worker cannot load its models: the daemon stops with this message.
    pub fn failed(&self, message: String) {
        tracing::error!(error = %message, "a worker cannot load its models");
        self.service.inner.fatal.send_replace(Some(message));
    }

    /// Whether running jobs must stop at their next tile (the shutdown deadline passed).
    pub fn aborting(&self) -> bool {
        self.service.inner.abort.load(Ordering::SeqCst)
    }

    /// Blocks until a job is available (and returns it, marked running) or the workers
    /// are told to stop or drain (`None`). Queued jobs past their deadline fail on the way.
    pub fn next_job(&self) -> Option<Claim> {
        let s = &self.service;
        if s.shared().is_some() {
            return s.next_shared(self);
        }
        loop {
            let overdue = {
                let mut st = s.lock();
                loop {
                    match s.phase() {
                        Phase::Draining | Phase::Stopped => return None,
                        Phase::Loading => {}
                        // No claims while the data directory cannot take results.
                        Phase::Ready if s.storage_problem().is_some() => {}
                        Phase::Ready => {
                            s.promote_due(&mut st);
                            if let Some(id) = st.queue.pop() {
                                s.update_depth(&st);
                                let now = s.now();
                                let Some(entry) = st.jobs.get(&id) else { continue };
                                if entry.record.deadline_at_ms.is_some_and(|t| t <= now) {
                                    break s.prepare(&mut st, &id, deadline_passed());
                                }
                                let claim = self.claim(&mut st, &id, now);
                                drop(st);
                                s.persist(&claim.id);
                                return Some(claim);
                            }
                        }
                    }
                    st = if st.delayed.is_empty() {
                        s.inner.work.wait(st).unwrap_or_else(lock_poisoned)
                    } else {
                        // A delayed job becomes due without anyone notifying.
                        s.inner
                            .work
                            .wait_timeout(st, std::time::Duration::from_millis(200))
                            .unwrap_or_else(lock_poisoned)
                            .0
                    };
                }
            };
            if let Some(prepared) = overdue {
                let _ = s.commit(&s.journal(), prepared);
            }
        }
    }

    /// Marks a popped job running (in memory) and describes it for the worker.
    pub(super) fn claim(&self, st: &mut super::State, id: &str, now: i64) -> Claim {
        let s = &self.service;
        let entry = st.jobs.get_mut(id).expect("popped from the queue");
        let r = &mut entry.record;
        r.state = JobState::Running;
        r.attempts += 1;
        r.started_at_ms = Some(now);
        // The tiles of the job's variant, cut as the engine will cut them (for `auto`: as
        // for `full`, whose shape the shipped `nocov` shares); the worker's progress reports
        // have the exact count (and the region bound of the device the engine resolved).
        let engine = &s.inner.settings.engine;
        let variant = r.options.variant.unwrap_or(crate::engine::Variant::Full);
        let infos: Vec<_> = s.models().into_iter().flatten().filter(|m| m.variant == variant).collect();
        let plan = if infos.is_empty() {
            crate::engine::Tiling::plain(engine.tile)
        } else {
            crate::engine::Tiling::for_model(
                &infos,
                [engine.tile, engine.tile_v2],
                engine.region_pixels.unwrap_or_else(|| crate::engine::default_region_pixels(engine.device)),
            )
        };
        let tiles = plan.cores(r.width as usize, r.height as usize).len();
        r.progress = Progress { tiles_done: 0, tiles_total: tiles as u32 };
        let queue_ms = (now - r.created_at_ms).max(0) as f64;
        let claim = Claim {
            id: id.to_string(),
            attempt: r.attempts,
            input: s.inner.store.input_path(id),
            reference: r.has_reference.then(|| s.inner.store.reference_path(id)),
            variant: r.options.variant,
            fireflies: r.options.fireflies(s.inner.settings.fireflies),
            layers: r.options.layers.clone(),
            channel_maps: s.channel_maps(&r.options).map_err(|e| e.to_string()),
            deadline_at_ms: r.deadline_at_ms,
            trace_parent: r.trace_parent.clone(),
            queue_ms,
            cancel: entry.cancel.clone(),
        };
        let _ = entry.events.send(JobEvent::Started { attempt: r.attempts });
        let _ = entry.events.send(JobEvent::Progress(r.progress));
        st.running += 1;
        s.inner.running.send_replace(st.running);
        s.inner.telemetry.set_in_flight(st.running);
        s.inner.telemetry.observe_stage("queue", queue_ms);
        claim
    }

    /// Progress of a running job (memory only).
    pub fn progress(&self, id: &str, progress: Progress) {
        let s = &self.service;
        let mut st = s.lock();
        // Only while running: in shared mode a run that lost its job to another replica
        // goes on to its next tile after the job has ended there.
        if let Some(entry) = st.jobs.get_mut(id).filter(|e| e.record.state == JobState::Running) {
            entry.record.progress = progress;
            let _ = entry.events.send(JobEvent::Progress(progress));
        }
        drop(st);
        if let Some(shared) = s.shared() {
            shared.heartbeat(id);
            shared.publish_progress(id, progress);
        }
        s.inner.telemetry.tile_done();
    }

    /// Records how a run ended; the job no longer counts as running afterwards.
    pub fn finish(&self, claim: Claim, outcome: Outcome) {
        let s = &self.service;
        let id = claim.id.as_str();
        if s.shared().is_some() && s.lock().jobs.get(id).is_some_and(|e| e.record.attempts != claim.attempt) {
            // Another replica took the job over while this run went on: its end is not this
            // run's to write.
            s.settle_message(id, claim.attempt, None);
            self.release(claim);
            return;
        }
        let attempt = claim.attempt;
        let mut requeue_after = None;
        let ending = match outcome {
            Outcome::Interrupted => Ok(None),
            Outcome::StorageFault(message) => Err(message),
            Outcome::Succeeded(success) => self.write_result(id, *success),
            Outcome::Failed(error, timings) => Ok(Some(Ending::Failed(error, timings))),
            Outcome::Cancelled => Ok(Some(Ending::Cancelled)),
        };
        match ending {
            Ok(None) => s.requeue(id),
            Ok(Some(ending)) => {
                let settled = s.settle(&s.journal(), id, ending);
                match settled {
                    Ok(_) => {}
                    Err(crate::error::Error::Conflict(_)) => {
                        // Changed by another replica meanwhile (cancelled, deleted or taken
                        // over): read it again and end it as it now says.
                        s.end_after_conflict(id, attempt);
                    }
                    // Its end could not be written: it stays running in memory; run it again.
                    Err(e) => requeue_after = s.retry_later(id, format!("cannot record the job's end: {e}")),
                }
            }
            Err(message) => requeue_after = s.retry_later(id, message),
        }
        s.settle_message(id, attempt, requeue_after);
        if !s.lock().jobs.contains_key(id) {
            // Deleted while it ran: whatever it wrote goes.
            s.inner.store.remove_files(id);
        }
        self.release(claim);
    }

    /// The end of a run, whatever became of its job: no longer counted as running.
    pub(super) fn release(&self, claim: Claim) {
        let s = &self.service;
        drop(claim);
        let mut st = s.lock();
        st.running -= 1;
        s.inner.running.send_replace(st.running);
        s.inner.telemetry.set_in_flight(st.running);
    }

    /// Writes the result (summary, then the EXR, each atomically) before the record says
    /// `succeeded`; the ending to settle. `None` if the job was deleted while it ran; the
    /// message of a storage fault when the result cannot be written for a storage reason.
    fn write_result(&self, id: &str, s: Success) -> Result<Option<Ending>, String> {
        let service = &self.service;
        let Some(record) = service.lock().jobs.get(id).map(|e| e.record.clone()) else { return Ok(None) };
        let t = Instant::now();
        let out = s.output;
        service.keep_preview_sources(id, out.input_color.as_ref(), out.reference_color.as_ref());
        let mut finished = Finished {
            variant: out.variant,
            progress: Progress { tiles_done: out.tiles as u32, tiles_total: out.tiles as u32 },
            timings: out.timings,
            metrics: out.metrics,
            sanitized: out.sanitized,
            fireflies: FireflyCounts {
                mode: s.fireflies.mode,
                strength: s.fireflies.strength,
                handled: out.fireflies.total(),
                by_component: out.fireflies,
            },
            missing_variances: out.missing_variances,
            warnings: out.warnings,
            result_bytes: out.encoded.len() as u64,
        };
        // The summary, with the estimated timings: recovery adopts it if the process stops
        // before the record is written.
        let now = service.now();
        let mut summary = record;
        finished.clone().apply(&mut summary);
        summary.finished_at_ms = Some(now);
        summary.expires_at_ms = Some(now + service.inner.settings.ttl_ms());
        let written = serde_json::to_vec(&summary)
            .map_err(std::io::Error::other)
            .and_then(|json| crate::atomic::write(&service.inner.store.summary_path(id), &json))
            .and_then(|()| crate::atomic::write(&service.inner.store.result_path(id), &out.encoded));
        if let Err(e) = written {
            if !service.lock().jobs.contains_key(id) {
                // Deleted while it ran (its directory went with it): not a storage fault.
                return Ok(None);
            }
            let e = crate::error::Error::storage("cannot write the result", &e);
            if e.storage_kind().is_some() {
                service.storage_failed(&e);
                return Err(e.to_string());
            }
            return Ok(Some(Ending::Failed(JobError { code: JobErrorCode::Internal, message: e.to_string() }, None)));
        }
        if let Err(e) = service.share_result(id) {
            return Err(e.to_string());
        }
        finished.timings.encode += t.elapsed().as_secs_f64() * 1e3;
        finished.timings.total = s.started.elapsed().as_secs_f64() * 1e3;
        let timings = finished.timings;
        let tel = &service.inner.telemetry;
        for (stage, ms) in [
            ("decode", timings.decode),
            ("preprocess", timings.preprocess),
            ("inference", timings.inference),
            ("reconstruction", timings.reconstruction),
            ("encode", timings.encode),
            ("total", timings.total),
        ] {
            tel.observe_stage(stage, ms);
        }
        tel.job_output((out.width * out.height) as u64, finished.sanitized.total);
        tel.fireflies_handled(finished.fireflies.handled);
        Ok(Some(Ending::Succeeded(Box::new(finished))))
    }
}
