//! The transport-free core of the daemon: admission, the persistent job store, the
//! priority queue, the workers, progress events, cancellation, deadlines and retention.
//!
//! [`JobService`] is a cheap `Clone` handle; the HTTP and gRPC transports both call it.
//!
//! # Layout
//!
//! - [`model`]: job options, records, states and events.
//! - [`store`]: the redb database and the files of each job.
//! - [`queue`]: priority classes, FIFO within a class.
//! - [`validate`]: the EXR header checks done at submission.
//! - `worker`: OS threads, each owning an [`Engine`](crate::engine::Engine) (its own ONNX
//!   Runtime sessions).
//!
//! # Concurrency
//!
//! All job state lives in one `std::sync::Mutex<State>`, held for short sections only
//! (never across an `.await`, never while pixels are processed). Record writes to the
//! store happen under that lock so the database never goes back in time; they are small
//! (one JSON record per state change, not per tile). Uploads and results are written to
//! files outside the lock. Workers wait on a `Condvar` for work; async callers reach the
//! blocking parts through `spawn_blocking`.
//!
//! Events are sent under the same lock that a watcher's snapshot is taken under, so a
//! watcher sees every change after its snapshot exactly once.

pub mod model;
pub mod queue;
pub mod store;
pub mod validate;
mod worker;

use std::collections::{HashMap, HashSet};
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard, OnceLock, PoisonError};
use std::time::Duration;

use futures_util::stream::{self, BoxStream, StreamExt};
use serde::Serialize;
use tokio::io::AsyncWriteExt;
use tokio::sync::{broadcast, watch};

use crate::auth::ClientId;
use crate::config::ServeArgs;
use crate::engine::{EngineConfig, Fireflies, Variant};
use crate::error::{Error, Result};
use crate::frame::Limits;
use crate::telemetry::Telemetry;
pub use model::*;
use queue::Queue;
use store::Store;

/// Buffered events per job; a watcher that falls further behind skips progress events
/// (never the terminal one, which is the last).
const EVENT_BUFFER: usize = 256;

/// Where the daemon is in its life.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Phase {
    /// Workers are loading and warming up their models.
    Loading,
    /// Accepting and running jobs.
    Ready,
    /// Shutting down: no new jobs; running ones finish (or are interrupted at the deadline).
    Draining,
    /// Workers have stopped.
    Stopped,
}

/// A loaded network as reported by `/v1/models` and `ListModels`.
#[derive(Clone, Debug, Serialize)]
pub struct ModelDescription {
    pub variant: String,
    pub component: String,
    pub file: String,
    pub contract: String,
    pub receptive_radius: usize,
    pub flops_per_pixel: f64,
    pub architecture: String,
    pub sha256: String,
}

/// Settings the core needs, taken from [`ServeArgs`].
#[derive(Clone, Debug)]
pub struct Settings {
    pub capacity: usize,
    pub result_ttl: Duration,
    pub default_deadline: Option<Duration>,
    pub limits: Limits,
    pub max_body_bytes: u64,
    /// Uploads one client may have in flight at once.
    pub max_uploads_per_client: usize,
    /// Unfinished (uploading, queued or running) jobs one client may have.
    pub max_jobs_per_client: usize,
    pub workers: usize,
    pub engine: EngineConfig,
    /// Firefly handling of jobs that do not choose their own.
    pub fireflies: Fireflies,
    pub tile_delay: Duration,
    pub startup_delay: Duration,
}

impl Settings {
    pub fn from_args(args: &ServeArgs) -> Settings {
        let mut engine = EngineConfig::new(&args.models);
        engine.tile = args.tile;
        engine.tile_v2 = args.tile_v2;
        engine.threads = args.threads_per_worker();
        engine.ort_library = args.ort_library.clone();
        Settings {
            capacity: args.queue_capacity,
            result_ttl: args.result_ttl,
            default_deadline: Some(args.job_deadline).filter(|d| !d.is_zero()),
            limits: args.limits(),
            max_body_bytes: args.max_body_bytes,
            max_uploads_per_client: args.max_uploads_per_client,
            max_jobs_per_client: args.max_jobs_per_client(),
            workers: args.workers(),
            engine,
            fireflies: args.fireflies.settings(),
            tile_delay: args.debug_tile_delay,
            startup_delay: args.debug_startup_delay,
        }
    }
}

/// A job in memory: its record, its event channel and its cancellation flag.
struct Entry {
    record: JobRecord,
    events: broadcast::Sender<JobEvent>,
    cancel: Arc<AtomicBool>,
}

impl Entry {
    fn new(record: JobRecord) -> Entry {
        Entry { record, events: broadcast::channel(EVENT_BUFFER).0, cancel: Arc::new(AtomicBool::new(false)) }
    }
}

#[derive(Default)]
struct State {
    jobs: HashMap<String, Entry>,
    queue: Queue,
    /// Admissions whose upload is in progress; they count against the capacity.
    reserved: usize,
    /// Idempotency keys of committed jobs.
    keys: HashMap<String, String>,
    /// Idempotency keys of uploads in progress.
    uploading: HashSet<String>,
    /// Uploads in progress per client.
    uploads: HashMap<ClientId, usize>,
    next_seq: u64,
    running: usize,
    workers_ready: usize,
    /// Moving average of the run time of recent jobs, for `Retry-After`.
    avg_run_ms: f64,
}

struct Inner {
    state: Mutex<State>,
    /// Workers wait here for queued jobs (and for the stop signal).
    work: Condvar,
    store: Store,
    settings: Settings,
    telemetry: Arc<Telemetry>,
    phase: watch::Sender<Phase>,
    running: watch::Sender<usize>,
    /// Set when a worker cannot load its models: the daemon exits with this message.
    fatal: watch::Sender<Option<String>>,
    /// Set at the shutdown deadline: running jobs stop at their next tile and are requeued.
    abort: AtomicBool,
    models: OnceLock<Vec<ModelDescription>>,
}

/// The core handle. Cheap to clone.
#[derive(Clone)]
pub struct JobService {
    inner: Arc<Inner>,
}

/// The result of an admission (short-lived: the size of its variants does not matter).
#[allow(clippy::large_enum_variant)]
pub enum Admission {
    /// A new job: upload its frame through the ticket, then [`Ticket::commit`].
    New(Ticket),
    /// A job with the same idempotency key exists: this is it.
    Existing(JobStatus),
}

/// How a worker's run of a job ended.
pub(crate) enum Outcome {
    Succeeded(Box<Success>),
    Failed(JobError, Option<Timings>),
    Cancelled,
    /// Stopped by the shutdown deadline: back to the queue for the next start.
    Interrupted,
}

pub(crate) struct Success {
    pub variant: Variant,
    pub progress: Progress,
    pub timings: Timings,
    pub metrics: Option<JobMetrics>,
    pub sanitized: SanitizedCounts,
    pub fireflies: FireflyCounts,
    pub missing_variances: Vec<String>,
    pub pixels: u64,
    pub result: Vec<u8>,
    /// Milliseconds spent before the result file was written (the write time is added to
    /// `encode` and `total`).
    pub started: std::time::Instant,
}

/// A job handed to a worker.
pub(crate) struct Claim {
    pub id: String,
    pub attempt: u32,
    pub input: PathBuf,
    pub reference: Option<PathBuf>,
    pub variant: Option<Variant>,
    pub fireflies: Fireflies,
    pub layers: Vec<Layer>,
    pub deadline_at_ms: Option<i64>,
    pub queue_ms: f64,
    pub cancel: Arc<AtomicBool>,
}

fn lock_poisoned<T>(e: PoisonError<T>) -> T {
    e.into_inner()
}

fn not_found(id: &str) -> Error {
    Error::NotFound(format!("no job {id}"))
}

impl JobService {
    /// Opens the store under `data_dir`, recovers its jobs (queued and interrupted ones
    /// are queued again, finished ones kept until they expire) and starts the workers.
    /// Workers load their models in the background; the service is ready when all have.
    pub fn start(
        data_dir: &std::path::Path,
        settings: Settings,
        telemetry: Arc<Telemetry>,
    ) -> Result<(JobService, Vec<std::thread::JoinHandle<()>>)> {
        let store = Store::open(data_dir)?;
        let state = recover(&store, &settings, &telemetry)?;
        telemetry.set_queue_capacity(settings.capacity);
        telemetry.set_workers(settings.workers, 0);
        telemetry.set_ready(false);
        for p in Priority::ALL {
            telemetry.set_queue_depth(p, state.queue.depth(p));
        }
        let service = JobService {
            inner: Arc::new(Inner {
                state: Mutex::new(state),
                work: Condvar::new(),
                store,
                settings,
                telemetry,
                phase: watch::channel(Phase::Loading).0,
                running: watch::channel(0).0,
                fatal: watch::channel(None).0,
                abort: AtomicBool::new(false),
                models: OnceLock::new(),
            }),
        };
        let workers = worker::spawn(&service).map_err(|e| Error::internal("cannot start the workers", e))?;
        Ok((service, workers))
    }

    fn lock(&self) -> MutexGuard<'_, State> {
        self.inner.state.lock().unwrap_or_else(lock_poisoned)
    }

    pub fn settings(&self) -> &Settings {
        &self.inner.settings
    }

    pub fn telemetry(&self) -> &Arc<Telemetry> {
        &self.inner.telemetry
    }

    pub fn phase(&self) -> Phase {
        *self.inner.phase.borrow()
    }

    pub fn subscribe_phase(&self) -> watch::Receiver<Phase> {
        self.inner.phase.subscribe()
    }

    pub fn subscribe_fatal(&self) -> watch::Receiver<Option<String>> {
        self.inner.fatal.subscribe()
    }

    /// The loaded models; `None` until the first worker has loaded them.
    pub fn models(&self) -> Option<&[ModelDescription]> {
        self.inner.models.get().map(Vec::as_slice)
    }

    fn set_phase(&self, phase: Phase) {
        self.inner.phase.send_replace(phase);
        self.inner.telemetry.set_ready(phase == Phase::Ready);
    }

    fn status_of(&self, st: &State, entry: &Entry) -> JobStatus {
        let r = &entry.record;
        let queue_position = if r.state == JobState::Queued { st.queue.position(r.options.priority, r.seq) } else { 0 };
        JobStatus { record: r.clone(), queue_position }
    }

    fn update_depth(&self, st: &State) {
        for p in Priority::ALL {
            self.inner.telemetry.set_queue_depth(p, st.queue.depth(p));
        }
    }

    fn retry_after_s(&self, st: &State) -> u64 {
        let per_job = if st.avg_run_ms > 0.0 { st.avg_run_ms / 1e3 } else { 5.0 };
        let waiting = (st.queue.len() + st.reserved + st.running) as f64;
        ((per_job * waiting / self.inner.settings.workers as f64).ceil() as u64).clamp(1, 600)
    }

    // --- Admission -----------------------------------------------------------------

    /// Admits a submission before its frame is read: checks readiness, the idempotency key
    /// and the capacity, and reserves a place in the queue.
    pub fn admit(&self, options: JobOptions, transport: &'static str, client: &ClientId) -> Result<Admission> {
        let options = options.normalize().map_err(Error::BadRequest)?;
        let mut st = self.lock();
        match self.phase() {
            Phase::Ready => {}
            Phase::Loading => return Err(Error::Unavailable("not ready: the models are still loading".into())),
            Phase::Draining | Phase::Stopped => {
                return Err(Error::Unavailable("shutting down: not accepting new jobs".into()))
            }
        }
        if let (Some(v), Some(models)) = (options.variant, self.models()) {
            if !models.iter().any(|m| m.variant == v.name()) {
                let mut loaded: Vec<&str> = models.iter().map(|m| m.variant.as_str()).collect();
                loaded.dedup();
                return Err(Error::BadRequest(format!("no `{v}` model is loaded (loaded: {})", loaded.join(", "))));
            }
        }
        if let Some(key) = &options.idempotency_key {
            if let Some(id) = st.keys.get(key) {
                if let Some(entry) = st.jobs.get(id) {
                    return Ok(Admission::Existing(self.status_of(&st, entry)));
                }
            }
            if st.uploading.contains(key) {
                return Err(Error::InProgress(format!(
                    "a submission with idempotency key `{key}` is still being uploaded; retry when it completes"
                )));
            }
        }
        let capacity = self.inner.settings.capacity;
        if st.queue.len() + st.reserved >= capacity {
            return Err(Error::QueueFull { capacity, retry_after_s: self.retry_after_s(&st) });
        }
        self.check_client(&st, client)?;
        st.reserved += 1;
        *st.uploads.entry(client.clone()).or_default() += 1;
        if let Some(key) = &options.idempotency_key {
            st.uploading.insert(key.clone());
        }
        drop(st);
        let id = uuid::Uuid::now_v7().to_string();
        Ok(Admission::New(Ticket {
            service: self.clone(),
            id,
            options,
            transport,
            received: 0,
            frame: None,
            reference: None,
            done: false,
            client: client.clone(),
        }))
    }

    /// Refuses a new upload when `client` is at its own limits.
    fn check_client(&self, st: &State, client: &ClientId) -> Result<()> {
        let s = &self.inner.settings;
        let uploads = st.uploads.get(client).copied().unwrap_or(0);
        if uploads >= s.max_uploads_per_client {
            return Err(Error::ClientLimit {
                message: format!(
                    "{} has {uploads} uploads in progress, the most one client may have at once \
                     (--max-uploads-per-client); retry when one completes",
                    client.as_str()
                ),
                retry_after_s: 1,
            });
        }
        let unfinished = st
            .jobs
            .values()
            .filter(|e| !e.record.state.is_terminal() && e.record.client.as_deref() == Some(client.as_str()))
            .count();
        if unfinished + uploads >= s.max_jobs_per_client {
            return Err(Error::ClientLimit {
                message: format!(
                    "{} has {} unfinished jobs, the most one client may have (--max-jobs-per-client); \
                     retry when some finish",
                    client.as_str(),
                    unfinished + uploads
                ),
                retry_after_s: self.retry_after_s(st),
            });
        }
        Ok(())
    }

    /// Counts a refused submission in the metrics.
    pub fn note_rejection(&self, e: &Error) {
        let reason = match e {
            Error::QueueFull { .. } => "queue_full",
            Error::ClientLimit { .. } => "client_limit",
            Error::BadRequest(_) | Error::InvalidFrame(_) => "invalid",
            Error::TooLarge(_) => "too_large",
            Error::Unavailable(_) => "unavailable",
            Error::Unauthenticated(_) => "unauthenticated",
            Error::NotFound(_) | Error::Conflict(_) | Error::InProgress(_) | Error::Internal(_) => "other",
        };
        self.inner.telemetry.job_rejected(reason);
    }

    fn enqueue(&self, ticket: &Ticket, info: crate::frame::HeaderInfo) -> Result<JobStatus> {
        let now = now_ms();
        let deadline = ticket
            .options
            .deadline_seconds
            .map(Duration::from_secs)
            .or(self.inner.settings.default_deadline)
            .map(|d| now + d.as_millis() as i64);
        let mut st = self.lock();
        let record = JobRecord {
            id: ticket.id.clone(),
            seq: st.next_seq,
            state: JobState::Queued,
            options: ticket.options.clone(),
            width: info.width as u32,
            height: info.height as u32,
            input_bytes: ticket.received,
            has_reference: ticket.reference.is_some(),
            created_at_ms: now,
            started_at_ms: None,
            finished_at_ms: None,
            deadline_at_ms: deadline,
            expires_at_ms: None,
            attempts: 0,
            cancel_requested: false,
            variant: None,
            progress: Progress::default(),
            timings: None,
            metrics: None,
            sanitized: None,
            fireflies: None,
            missing_variances: Vec::new(),
            error: None,
            result_bytes: None,
            client: Some(ticket.client.as_str().to_string()),
        };
        self.inner.store.put(&record)?;
        st.next_seq += 1;
        st.reserved -= 1;
        release_upload(&mut st, &ticket.client);
        if let Some(key) = &record.options.idempotency_key {
            st.uploading.remove(key);
            st.keys.insert(key.clone(), record.id.clone());
        }
        st.queue.push(record.options.priority, record.seq, record.id.clone());
        let id = record.id.clone();
        st.jobs.insert(id.clone(), Entry::new(record));
        self.update_depth(&st);
        self.inner.telemetry.job_submitted(ticket.transport);
        self.inner.work.notify_one();
        let entry = &st.jobs[&id];
        let status = self.status_of(&st, entry);
        let _ = entry.events.send(JobEvent::Queued { status: Box::new(status.clone()) });
        Ok(status)
    }

    fn release(&self, key: Option<&str>, client: &ClientId) {
        let mut st = self.lock();
        st.reserved -= 1;
        release_upload(&mut st, client);
        if let Some(key) = key {
            st.uploading.remove(key);
        }
    }

    // --- Queries -----------------------------------------------------------------------

    pub fn get(&self, id: &str) -> Result<JobStatus> {
        let st = self.lock();
        let entry = st.jobs.get(id).ok_or_else(|| not_found(id))?;
        Ok(self.status_of(&st, entry))
    }

    /// Jobs in submission order, filtered; `after` is the `next_page_token` of the
    /// previous page.
    pub fn list(&self, filter: &ListFilter) -> Result<(Vec<JobStatus>, Option<String>)> {
        let after = match filter.after.as_deref() {
            None | Some("") => None,
            Some(t) => Some(t.parse::<u64>().map_err(|_| Error::BadRequest(format!("bad page token `{t}`")))?),
        };
        let limit = filter.limit.unwrap_or(100).clamp(1, 1000);
        let st = self.lock();
        let mut matching: Vec<&Entry> = st
            .jobs
            .values()
            .filter(|e| {
                let r = &e.record;
                after.is_none_or(|a| r.seq > a)
                    && filter.state.is_none_or(|s| r.state == s)
                    && filter.priority.is_none_or(|p| r.options.priority == p)
                    && filter.label.as_deref().is_none_or(|l| r.options.label.as_deref() == Some(l))
            })
            .collect();
        matching.sort_by_key(|e| e.record.seq);
        let more = matching.len() > limit;
        matching.truncate(limit);
        let next = if more { matching.last().map(|e| e.record.seq.to_string()) } else { None };
        Ok((matching.into_iter().map(|e| self.status_of(&st, e)).collect(), next))
    }

    /// The current status and a receiver of every later event, taken atomically.
    pub fn watch(&self, id: &str) -> Result<(JobStatus, broadcast::Receiver<JobEvent>)> {
        let st = self.lock();
        let entry = st.jobs.get(id).ok_or_else(|| not_found(id))?;
        Ok((self.status_of(&st, entry), entry.events.subscribe()))
    }

    /// The job's events: its current state first (`queued`; or `started` and `progress`;
    /// or the terminal event), then every change, ending after the terminal event (or
    /// when the job is deleted).
    pub fn events(&self, id: &str) -> Result<BoxStream<'static, JobEvent>> {
        let (status, rx) = self.watch(id)?;
        let r = &status.record;
        let initial = match r.state {
            JobState::Queued => vec![JobEvent::Queued { status: Box::new(status.clone()) }],
            JobState::Running => vec![JobEvent::Started { attempt: r.attempts }, JobEvent::Progress(r.progress)],
            JobState::Succeeded | JobState::Failed | JobState::Cancelled => {
                let terminal = JobEvent::terminal(status).expect("terminal state");
                return Ok(stream::iter([terminal]).boxed());
            }
        };
        let live = stream::unfold(Some(rx), |rx| async move {
            let mut rx = rx?;
            loop {
                match rx.recv().await {
                    Ok(ev) => {
                        let next = if ev.is_terminal() { None } else { Some(rx) };
                        return Some((ev, next));
                    }
                    Err(broadcast::error::RecvError::Lagged(_)) => continue,
                    Err(broadcast::error::RecvError::Closed) => return None,
                }
            }
        });
        Ok(stream::iter(initial).chain(live).boxed())
    }

    /// Opens the result of a succeeded job: the file and its size.
    pub fn open_result(&self, id: &str) -> Result<(std::fs::File, u64)> {
        let st = self.lock();
        let entry = st.jobs.get(id).ok_or_else(|| not_found(id))?;
        match entry.record.state {
            JobState::Succeeded => {}
            s => {
                return Err(Error::Conflict(format!(
                    "job {id} is {}; a result exists only once it has succeeded",
                    s.name()
                )))
            }
        }
        let path = self.inner.store.result_path(id);
        let file =
            std::fs::File::open(&path).map_err(|e| Error::internal(&format!("cannot open {}", path.display()), e))?;
        let len = file.metadata().map_err(|e| Error::internal("cannot stat the result", e))?.len();
        Ok((file, len))
    }

    // --- Changes -----------------------------------------------------------------------

    /// Cancels a queued job at once, or asks a running one to stop at its next tile.
    pub fn cancel(&self, id: &str) -> Result<JobStatus> {
        let mut st = self.lock();
        let st = &mut *st;
        let entry = st.jobs.get_mut(id).ok_or_else(|| not_found(id))?;
        match entry.record.state {
            JobState::Queued => {
                let mut record = entry.record.clone();
                let now = now_ms();
                record.state = JobState::Cancelled;
                record.cancel_requested = true;
                record.finished_at_ms = Some(now);
                record.expires_at_ms = Some(now + self.inner.settings.result_ttl.as_millis() as i64);
                self.inner.store.put(&record)?;
                st.queue.remove(record.options.priority, record.seq);
                entry.record = record;
                entry.cancel.store(true, Ordering::SeqCst);
                self.update_depth(st);
                self.inner.telemetry.job_finished("cancelled");
                let entry = &st.jobs[id];
                let status = self.status_of(st, entry);
                let _ = entry.events.send(JobEvent::Cancelled(Box::new(status.clone())));
                tracing::info!(job_id = id, "cancelled while queued");
                self.inner.store.remove_inputs(id);
                Ok(status)
            }
            JobState::Running => {
                entry.cancel.store(true, Ordering::SeqCst);
                entry.record.cancel_requested = true;
                tracing::info!(job_id = id, "cancellation requested");
                let entry = &st.jobs[id];
                Ok(self.status_of(st, entry))
            }
            s @ (JobState::Succeeded | JobState::Failed | JobState::Cancelled) => {
                Err(Error::Conflict(format!("job {id} has already {}", s.name())))
            }
        }
    }

    /// Removes a job with its files (a running job is cancelled first).
    pub fn delete(&self, id: &str) -> Result<()> {
        let mut st = self.lock();
        if !st.jobs.contains_key(id) {
            return Err(not_found(id));
        }
        self.inner.store.remove(&[id])?;
        let entry = st.jobs.remove(id).expect("present");
        entry.cancel.store(true, Ordering::SeqCst);
        let r = &entry.record;
        if r.state == JobState::Queued && st.queue.remove(r.options.priority, r.seq) {
            self.update_depth(&st);
        }
        if let Some(key) = &r.options.idempotency_key {
            st.keys.remove(key);
        }
        drop(st);
        // Dropping `entry` closes its event channel: watchers' streams end.
        drop(entry);
        self.inner.store.remove_files(id);
        tracing::info!(job_id = id, "deleted");
        Ok(())
    }

    /// Removes finished jobs past their retention time and fails queued jobs past their
    /// deadline. Returns how many jobs were removed.
    pub fn sweep(&self) -> Result<usize> {
        let now = now_ms();
        let mut st = self.lock();
        let expired: Vec<String> = st
            .jobs
            .values()
            .filter(|e| e.record.state.is_terminal() && e.record.expires_at_ms.is_some_and(|t| t <= now))
            .map(|e| e.record.id.clone())
            .collect();
        if !expired.is_empty() {
            let ids: Vec<&str> = expired.iter().map(String::as_str).collect();
            self.inner.store.remove(&ids)?;
            for id in &expired {
                if let Some(entry) = st.jobs.remove(id) {
                    if let Some(key) = &entry.record.options.idempotency_key {
                        st.keys.remove(key);
                    }
                }
            }
        }
        let overdue: Vec<String> = st
            .jobs
            .values()
            .filter(|e| e.record.state == JobState::Queued && e.record.deadline_at_ms.is_some_and(|t| t <= now))
            .map(|e| e.record.id.clone())
            .collect();
        for id in overdue {
            self.fail_queued_past_deadline(&mut st, &id)?;
        }
        drop(st);
        for id in &expired {
            self.inner.store.remove_files(id);
            tracing::info!(job_id = id.as_str(), "expired and removed");
        }
        Ok(expired.len())
    }

    fn fail_queued_past_deadline(&self, st: &mut State, id: &str) -> Result<()> {
        let entry = st.jobs.get_mut(id).expect("present");
        let mut record = entry.record.clone();
        let now = now_ms();
        record.state = JobState::Failed;
        record.error = Some(JobError {
            code: JobErrorCode::DeadlineExceeded,
            message: "the job's deadline passed while it was queued".into(),
        });
        record.finished_at_ms = Some(now);
        record.expires_at_ms = Some(now + self.inner.settings.result_ttl.as_millis() as i64);
        self.inner.store.put(&record)?;
        st.queue.remove(record.options.priority, record.seq);
        entry.record = record;
        self.update_depth(st);
        self.inner.telemetry.job_finished("failed");
        let entry = &st.jobs[id];
        let status = self.status_of(st, entry);
        let _ = entry.events.send(JobEvent::Failed(Box::new(status)));
        self.inner.store.remove_inputs(id);
        tracing::warn!(job_id = id, "deadline passed while queued");
        Ok(())
    }

    // --- Shutdown ------------------------------------------------------------------------

    /// Stops admitting jobs and starting queued ones; readiness turns false.
    pub fn begin_drain(&self) {
        let _st = self.lock();
        if matches!(self.phase(), Phase::Loading | Phase::Ready) {
            self.set_phase(Phase::Draining);
        }
        self.inner.work.notify_all();
    }

    /// Waits until no job is running, at most `timeout`. True if idle.
    pub async fn wait_idle(&self, timeout: Duration) -> bool {
        let mut rx = self.inner.running.subscribe();
        let idle = tokio::time::timeout(timeout, rx.wait_for(|n| *n == 0)).await.is_ok();
        idle
    }

    /// Makes running jobs stop at their next tile; they go back to the queue (persisted)
    /// and run again at the next start.
    pub fn abort_running(&self) {
        self.inner.abort.store(true, Ordering::SeqCst);
    }

    /// Tells the workers to exit once their current job is over.
    pub fn stop_workers(&self) {
        let _st = self.lock();
        self.set_phase(Phase::Stopped);
        self.inner.work.notify_all();
    }

    pub fn running(&self) -> usize {
        self.lock().running
    }

    // --- Worker side -----------------------------------------------------------------------

    fn worker_ready(&self, descriptions: Vec<ModelDescription>) {
        if self.inner.models.set(descriptions).is_ok() {
            for m in self.models().unwrap_or_default() {
                self.inner.telemetry.model_loaded(&m.variant, &m.component, &m.architecture, &m.sha256);
            }
        }
        let mut st = self.lock();
        st.workers_ready += 1;
        self.inner.telemetry.set_workers(self.inner.settings.workers, st.workers_ready);
        if st.workers_ready == self.inner.settings.workers && self.phase() == Phase::Loading {
            self.set_phase(Phase::Ready);
            tracing::info!(workers = st.workers_ready, "models loaded and warmed up: ready");
        }
        self.inner.work.notify_all();
    }

    fn worker_failed(&self, message: String) {
        tracing::error!(error = %message, "a worker cannot load its models");
        self.inner.fatal.send_replace(Some(message));
    }

    /// Blocks until a job is available (and returns it, marked running) or the workers
    /// are told to stop or drain (`None`).
    fn next_job(&self) -> Option<Claim> {
        let mut st = self.lock();
        loop {
            match self.phase() {
                Phase::Draining | Phase::Stopped => return None,
                Phase::Loading | Phase::Ready => {}
            }
            if self.phase() == Phase::Ready {
                if let Some(id) = st.queue.pop() {
                    self.update_depth(&st);
                    let now = now_ms();
                    let st_ref = &mut *st;
                    let Some(entry) = st_ref.jobs.get_mut(&id) else { continue };
                    if entry.record.deadline_at_ms.is_some_and(|t| t <= now) {
                        // Back in place so that the common path below fails it properly.
                        st_ref.queue.push(entry.record.options.priority, entry.record.seq, id.clone());
                        if let Err(e) = self.fail_queued_past_deadline(st_ref, &id) {
                            tracing::error!(job_id = id.as_str(), error = %e, "cannot record a deadline failure");
                        }
                        continue;
                    }
                    let mut record = entry.record.clone();
                    record.state = JobState::Running;
                    record.attempts += 1;
                    record.started_at_ms = Some(now);
                    let (w, h) = (record.width as usize, record.height as usize);
                    let tiles = crate::engine::tile_grid(w, h, self.inner.settings.engine.tile).len() as u32;
                    record.progress = Progress { tiles_done: 0, tiles_total: tiles };
                    if let Err(e) = self.inner.store.put(&record) {
                        // The job still runs; a crash now would run it again, which is safe.
                        tracing::error!(job_id = id.as_str(), error = %e, "cannot persist the running state");
                    }
                    let queue_ms = (now - record.created_at_ms).max(0) as f64;
                    entry.record = record;
                    let r = &entry.record;
                    let claim = Claim {
                        id: id.clone(),
                        attempt: r.attempts,
                        input: self.inner.store.input_path(&id),
                        reference: r.has_reference.then(|| self.inner.store.reference_path(&id)),
                        variant: r.options.variant,
                        fireflies: r.options.fireflies(self.inner.settings.fireflies),
                        layers: r.options.layers.clone(),
                        deadline_at_ms: r.deadline_at_ms,
                        queue_ms,
                        cancel: entry.cancel.clone(),
                    };
                    let _ = entry.events.send(JobEvent::Started { attempt: r.attempts });
                    let _ = entry.events.send(JobEvent::Progress(r.progress));
                    st.running += 1;
                    self.inner.running.send_replace(st.running);
                    self.inner.telemetry.set_in_flight(st.running);
                    self.inner.telemetry.observe_stage("queue", queue_ms);
                    return Some(claim);
                }
            }
            st = self.inner.work.wait(st).unwrap_or_else(lock_poisoned);
        }
    }

    fn progress(&self, id: &str, progress: Progress) {
        let mut st = self.lock();
        if let Some(entry) = st.jobs.get_mut(id) {
            entry.record.progress = progress;
            let _ = entry.events.send(JobEvent::Progress(progress));
        }
        self.inner.telemetry.tile_done();
    }

    fn aborting(&self) -> bool {
        self.inner.abort.load(Ordering::SeqCst)
    }

    /// Records how a run ended. For a success, the result is written (summary, then the
    /// EXR, each atomically) before the record says `succeeded`.
    fn finish(&self, claim: Claim, outcome: Outcome) {
        let id = claim.id.as_str();
        let ttl = self.inner.settings.result_ttl.as_millis() as i64;
        // A success: prepare the final record and write the files outside the lock.
        let success = match outcome {
            Outcome::Succeeded(success) => success,
            other => {
                self.finish_other(&claim, other, ttl);
                return;
            }
        };
        let current = self.lock().jobs.get(id).map(|e| e.record.clone());
        // None: deleted while running; the files go below.
        let prepared = current.map(|record| self.write_result(record, *success));
        let mut st = self.lock();
        st.running -= 1;
        self.inner.running.send_replace(st.running);
        self.inner.telemetry.set_in_flight(st.running);
        let Some(entry) = st.jobs.get_mut(id) else {
            drop(st);
            // Deleted while running.
            self.inner.store.remove_files(id);
            return;
        };
        match prepared {
            None => {
                drop(st);
                self.inner.store.remove_files(id);
            }
            Some(Ok(record)) => {
                if let Err(e) = self.inner.store.put(&record) {
                    tracing::error!(job_id = id, error = %e, "cannot persist the success; the result stays on disk");
                }
                let run_ms = record.timings.map(|t| t.total).unwrap_or(0.0);
                entry.record = record;
                let status = JobStatus { record: entry.record.clone(), queue_position: 0 };
                let _ = entry.events.send(JobEvent::Succeeded(Box::new(status)));
                st.avg_run_ms = if st.avg_run_ms == 0.0 { run_ms } else { 0.8 * st.avg_run_ms + 0.2 * run_ms };
                self.inner.telemetry.job_finished("succeeded");
                drop(st);
                self.inner.store.remove_inputs(id);
                tracing::info!(job_id = id, ms = run_ms, "succeeded");
            }
            Some(Err(e)) => {
                drop(st);
                let error = JobError { code: JobErrorCode::Internal, message: format!("cannot write the result: {e}") };
                self.finish_other_locked(&claim, Outcome::Failed(error, None), ttl, false);
            }
        }
    }

    fn write_result(&self, mut record: JobRecord, s: Success) -> std::io::Result<JobRecord> {
        let id = record.id.clone();
        let t = std::time::Instant::now();
        let now_before = now_ms();
        record.state = JobState::Succeeded;
        record.variant = Some(s.variant);
        record.progress = s.progress;
        record.metrics = s.metrics;
        record.sanitized = Some(s.sanitized);
        record.fireflies = Some(s.fireflies);
        record.missing_variances = s.missing_variances;
        record.error = None;
        record.result_bytes = Some(s.result.len() as u64);
        record.finished_at_ms = Some(now_before);
        record.expires_at_ms = Some(now_before + self.inner.settings.result_ttl.as_millis() as i64);
        let mut timings = s.timings;
        // Estimated write time in the summary; the real one replaces it in the database.
        record.timings = Some(timings);
        let summary = serde_json::to_vec(&record).map_err(std::io::Error::other)?;
        store::write_durable(&self.inner.store.summary_path(&id), &summary)?;
        store::write_durable(&self.inner.store.result_path(&id), &s.result)?;
        let write_ms = t.elapsed().as_secs_f64() * 1e3;
        timings.encode += write_ms;
        timings.total = s.started.elapsed().as_secs_f64() * 1e3;
        record.timings = Some(timings);
        record.finished_at_ms = Some(now_ms());
        let tel = &self.inner.telemetry;
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
        tel.job_output(s.pixels, record.sanitized.as_ref().map_or(0, |c| c.total));
        tel.fireflies_handled(s.fireflies.handled);
        Ok(record)
    }

    fn finish_other(&self, claim: &Claim, outcome: Outcome, ttl: i64) {
        self.finish_other_locked(claim, outcome, ttl, true)
    }

    /// Failure, cancellation or interruption. `count_running` is false when the running
    /// count was already decremented.
    fn finish_other_locked(&self, claim: &Claim, outcome: Outcome, ttl: i64, count_running: bool) {
        let id = claim.id.as_str();
        let mut st = self.lock();
        if count_running {
            st.running -= 1;
            self.inner.running.send_replace(st.running);
            self.inner.telemetry.set_in_flight(st.running);
        }
        let st = &mut *st;
        let Some(entry) = st.jobs.get_mut(id) else {
            self.inner.store.remove_files(id);
            return;
        };
        let mut record = entry.record.clone();
        let now = now_ms();
        let (event_kind, outcome_name): (fn(Box<JobStatus>) -> JobEvent, &str) = match outcome {
            Outcome::Succeeded(_) => unreachable!("handled by finish"),
            Outcome::Failed(error, timings) => {
                tracing::warn!(job_id = id, code = error.code.name(), error = %error.message, "failed");
                record.state = JobState::Failed;
                record.error = Some(error);
                record.timings = timings;
                (JobEvent::Failed, "failed")
            }
            Outcome::Cancelled => {
                tracing::info!(job_id = id, "cancelled while running");
                record.state = JobState::Cancelled;
                (JobEvent::Cancelled, "cancelled")
            }
            Outcome::Interrupted => {
                tracing::info!(job_id = id, "interrupted by shutdown; queued for the next start");
                record.state = JobState::Queued;
                record.progress = Progress::default();
                if let Err(e) = self.inner.store.put(&record) {
                    tracing::error!(job_id = id, error = %e, "cannot persist the interrupted job");
                }
                st.queue.push(record.options.priority, record.seq, record.id.clone());
                entry.record = record;
                self.update_depth(st);
                self.inner.telemetry.job_interrupted();
                return;
            }
        };
        record.finished_at_ms = Some(now);
        record.expires_at_ms = Some(now + ttl);
        if let Err(e) = self.inner.store.put(&record) {
            tracing::error!(job_id = id, error = %e, "cannot persist the job's end");
        }
        entry.record = record;
        let status = JobStatus { record: entry.record.clone(), queue_position: 0 };
        let _ = entry.events.send(event_kind(Box::new(status)));
        self.inner.telemetry.job_finished(outcome_name);
        self.inner.store.remove_inputs(id);
    }
}

/// Filters of [`JobService::list`].
#[derive(Clone, Debug, Default)]
pub struct ListFilter {
    pub state: Option<JobState>,
    pub priority: Option<Priority>,
    pub label: Option<String>,
    pub limit: Option<usize>,
    pub after: Option<String>,
}

/// Which upload a [`Sink`] receives.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum UploadPart {
    Frame,
    Reference,
}

impl UploadPart {
    pub fn name(self) -> &'static str {
        match self {
            UploadPart::Frame => "frame",
            UploadPart::Reference => "reference",
        }
    }
}

/// An admitted submission whose frame is being uploaded. Dropping it without
/// [`Ticket::commit`] releases its place and removes what was written.
pub struct Ticket {
    service: JobService,
    id: String,
    options: JobOptions,
    transport: &'static str,
    received: u64,
    frame: Option<u64>,
    reference: Option<u64>,
    done: bool,
    client: ClientId,
}

fn release_upload(st: &mut State, client: &ClientId) {
    if let Some(n) = st.uploads.get_mut(client) {
        *n -= 1;
        if *n == 0 {
            st.uploads.remove(client);
        }
    }
}

impl Ticket {
    pub fn id(&self) -> &str {
        &self.id
    }

    pub fn options(&self) -> &JobOptions {
        &self.options
    }

    /// Bytes still allowed under the body limit.
    pub fn remaining(&self) -> u64 {
        self.service.inner.settings.max_body_bytes.saturating_sub(self.received)
    }

    /// Starts writing one part of the upload (each part at most once).
    pub async fn sink(&mut self, part: UploadPart) -> Result<Sink> {
        let already = match part {
            UploadPart::Frame => self.frame.is_some(),
            UploadPart::Reference => self.reference.is_some(),
        };
        if already {
            return Err(Error::BadRequest(format!("the {} was sent twice", part.name())));
        }
        let store = &self.service.inner.store;
        let path = match part {
            UploadPart::Frame => store.input_path(&self.id),
            UploadPart::Reference => store.reference_path(&self.id),
        };
        let dir = store.job_dir(&self.id);
        tokio::fs::create_dir_all(&dir).await.map_err(|e| Error::internal("cannot create the job directory", e))?;
        let tmp = store::part_path(&path);
        let file =
            tokio::fs::File::create(&tmp).await.map_err(|e| Error::internal("cannot create the upload file", e))?;
        Ok(Sink {
            file: tokio::io::BufWriter::with_capacity(1 << 20, file),
            tmp,
            path,
            part,
            written: 0,
            limit: self.remaining(),
            max_body: self.service.inner.settings.max_body_bytes,
            telemetry: self.service.inner.telemetry.clone(),
            transport: self.transport,
        })
    }

    /// Completes one part: flushes it to disk and moves it into place.
    pub async fn finish(&mut self, sink: Sink) -> Result<()> {
        let part = sink.part;
        let n = sink.finish().await?;
        self.received += n;
        match part {
            UploadPart::Frame => self.frame = Some(n),
            UploadPart::Reference => self.reference = Some(n),
        }
        Ok(())
    }

    /// Validates the uploaded headers and queues the job.
    pub async fn commit(mut self) -> Result<JobStatus> {
        if self.frame.is_none() {
            return Err(Error::BadRequest("no frame was uploaded".into()));
        }
        let store = &self.service.inner.store;
        let input = store.input_path(&self.id);
        let reference = self.reference.map(|_| store.reference_path(&self.id));
        let limits = self.service.inner.settings.limits;
        let info = tokio::task::spawn_blocking(move || -> Result<crate::frame::HeaderInfo> {
            let info = validate::check_frame(&input, &limits).map_err(|e| Error::frame("frame", e))?;
            if let Some(reference) = reference {
                let r = validate::check_reference(&reference, &limits).map_err(|e| Error::frame("reference", e))?;
                if (r.width, r.height) != (info.width, info.height) {
                    return Err(Error::InvalidFrame(format!(
                        "reference is {}x{} but the frame is {}x{}",
                        r.width, r.height, info.width, info.height
                    )));
                }
            }
            Ok(info)
        })
        .await
        .map_err(|e| Error::internal("header check", e))??;
        let service = self.service.clone();
        let (status, ticket) = tokio::task::spawn_blocking(move || {
            let status = service.enqueue(&self, info);
            if status.is_ok() {
                self.done = true;
            }
            (status, self)
        })
        .await
        .map_err(|e| Error::internal("enqueue", e))?;
        drop(ticket);
        let status = status?;
        tracing::info!(
            job_id = status.record.id.as_str(),
            priority = status.record.options.priority.name(),
            width = status.record.width,
            height = status.record.height,
            bytes = status.record.input_bytes,
            client = status.record.client.as_deref().unwrap_or(""),
            "queued"
        );
        Ok(status)
    }
}

impl Drop for Ticket {
    fn drop(&mut self) {
        if !self.done {
            self.service.release(self.options.idempotency_key.as_deref(), &self.client);
            let dir = self.service.inner.store.job_dir(&self.id);
            // Small and rare (refused uploads): removing inline is fine.
            let _ = std::fs::remove_dir_all(dir);
        }
    }
}

/// Receives one uploaded file, enforcing the body limit as bytes arrive.
pub struct Sink {
    file: tokio::io::BufWriter<tokio::fs::File>,
    tmp: PathBuf,
    path: PathBuf,
    part: UploadPart,
    written: u64,
    limit: u64,
    max_body: u64,
    telemetry: Arc<Telemetry>,
    transport: &'static str,
}

impl Sink {
    pub fn written(&self) -> u64 {
        self.written
    }

    pub async fn write(&mut self, data: &[u8]) -> Result<()> {
        self.written += data.len() as u64;
        self.telemetry.bytes_received(self.transport, data.len() as u64);
        if self.written > self.limit {
            return Err(Error::TooLarge(format!("the upload is over the limit of {} bytes", self.max_body)));
        }
        self.file.write_all(data).await.map_err(|e| Error::internal("cannot write the upload", e))
    }

    async fn finish(mut self) -> Result<u64> {
        self.file.flush().await.map_err(|e| Error::internal("cannot write the upload", e))?;
        let file = self.file.into_inner();
        file.sync_all().await.map_err(|e| Error::internal("cannot sync the upload", e))?;
        drop(file);
        tokio::fs::rename(&self.tmp, &self.path).await.map_err(|e| Error::internal("cannot move the upload", e))?;
        Ok(self.written)
    }
}

/// Rebuilds the in-memory state from the store (see [`JobService::start`]).
fn recover(store: &Store, settings: &Settings, telemetry: &Telemetry) -> Result<State> {
    let mut st = State::default();
    let now = now_ms();
    let mut expired = Vec::new();
    let mut records = store.load_all()?;
    records.sort_by_key(|r| r.seq);
    let (mut requeued, mut kept, mut completed) = (0, 0, 0);
    for mut r in records {
        st.next_seq = st.next_seq.max(r.seq + 1);
        match r.state {
            JobState::Succeeded | JobState::Failed | JobState::Cancelled => {
                if r.expires_at_ms.is_some_and(|t| t <= now) {
                    expired.push(r.id.clone());
                    continue;
                }
                if r.state == JobState::Succeeded && !store.result_path(&r.id).is_file() {
                    r.state = JobState::Failed;
                    r.error =
                        Some(JobError { code: JobErrorCode::Internal, message: "the result file is missing".into() });
                    store.put(&r)?;
                }
                kept += 1;
            }
            JobState::Queued | JobState::Running => {
                let summary = store.summary_path(&r.id);
                let adopted = if store.result_path(&r.id).is_file() && summary.is_file() {
                    std::fs::read(&summary).ok().and_then(|b| serde_json::from_slice::<JobRecord>(&b).ok())
                } else {
                    None
                };
                if let Some(done) = adopted {
                    // Finished just before the process stopped: keep that result.
                    r = done;
                    store.put(&r)?;
                    store.remove_inputs(&r.id);
                    completed += 1;
                } else if !store.input_path(&r.id).is_file() {
                    r.state = JobState::Failed;
                    r.error = Some(JobError {
                        code: JobErrorCode::Internal,
                        message: "the uploaded frame is missing".into(),
                    });
                    r.finished_at_ms = Some(now);
                    r.expires_at_ms = Some(now + settings.result_ttl.as_millis() as i64);
                    store.put(&r)?;
                } else {
                    if r.state == JobState::Running {
                        telemetry.job_interrupted();
                        tracing::info!(job_id = r.id.as_str(), attempts = r.attempts, "interrupted run: queued again");
                    }
                    r.state = JobState::Queued;
                    r.progress = Progress::default();
                    r.cancel_requested = false;
                    store.put(&r)?;
                    st.queue.push(r.options.priority, r.seq, r.id.clone());
                    requeued += 1;
                }
            }
        }
        if let Some(key) = &r.options.idempotency_key {
            st.keys.insert(key.clone(), r.id.clone());
        }
        st.jobs.insert(r.id.clone(), Entry::new(r));
    }
    if !expired.is_empty() {
        let ids: Vec<&str> = expired.iter().map(String::as_str).collect();
        store.remove(&ids)?;
    }
    // Files of jobs without a record: uploads cut short, expired or deleted jobs.
    if let Ok(dir) = std::fs::read_dir(store.jobs_dir()) {
        for entry in dir.flatten() {
            let name = entry.file_name().to_string_lossy().to_string();
            if !st.jobs.contains_key(&name) {
                store.remove_files(&name);
            } else {
                for leftover in ["input.exr.part", "reference.exr.part", "result.exr.part", "result.json.part"] {
                    let _ = std::fs::remove_file(entry.path().join(leftover));
                }
            }
        }
    }
    if requeued + kept + completed + expired.len() > 0 {
        tracing::info!(requeued, kept, completed, expired = expired.len(), "recovered the job store");
    }
    Ok(st)
}
