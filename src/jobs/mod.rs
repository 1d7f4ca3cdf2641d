//! The transport-free core of the daemon: admission, the persistent job store, the
//! priority queue, the workers, progress events, cancellation, deadlines and retention.
//!
//! [`JobService`] is a cheap `Clone` handle; the HTTP and gRPC transports both call it and
//! never choose a thread themselves: methods that touch the disk are `async` and move
//! their blocking work onto tokio's blocking pool; methods that only read or change memory
//! are plain functions that return at once.
//!
//! # Layout
//!
//! - `mod.rs` (this file): the handle, its settings and the one in-memory [`State`].
//! - [`record`]: job options, records, states and events (plain data).
//! - [`uploads`]: [`Ticket`] and [`Sink`], an admitted submission's files on their way in.
//! - `admission`: readiness, idempotency keys, capacity and per-client limits; queuing.
//! - `lifecycle`: the one `settle` of every final state, cancel, delete, the retention
//!   sweep, the shutdown steps.
//! - `claims`: the workers' side (`WorkerLink`): claims, progress, results.
//! - `queries`: reads: get, list, watch, events, results, totals.
//! - `previews`: tone-mapped PNG previews of a job's frames, cached (the dashboard).
//! - `recovery`: the state rebuilt from the store at startup (after a crash too).
//! - [`store`]: the redb database and the files of each job.
//! - [`shared`]: shared mode's store on NATS JetStream (records, queue, files), and
//!   `mirror`: the core's side of it (the state as a mirror of the shared records, claims
//!   through the JetStream queue). [`Backend`] chooses the mode at start.
//! - [`health`]: whether the data directory can take writes (readiness, admission).
//! - [`queue`]: priority classes, FIFO within a class.
//! - [`validate`]: the EXR header checks done at submission.
//! - `worker`: OS threads, each owning a [`Denoiser`](crate::engine::Denoiser), that run
//!   jobs through [`crate::pipeline`]. They reach the core only through `WorkerLink`.
//!
//! # Concurrency
//!
//! All job state lives in one `std::sync::Mutex<State>`, held for short sections only:
//! never across an `.await`, never while pixels are processed, never while the disk is
//! written. Workers wait on a `Condvar` for work.
//!
//! Durable record writes go through the *journal*, a second mutex that serialises them.
//! Lock order: journal, then state (never the other way). A change that must be durable
//! before anyone sees it (admission, a final state, a re-queue at shutdown) is made in
//! three steps: compute the new record from memory under the state lock, write it to the
//! store with only the journal held, then apply it in memory and send its event under the
//! state lock again. Because every writer holds the journal from the first step to the
//! last, no other durable change to the job can come in between, so the store never goes
//! back in time, and clients only ever learn of states that are on disk. Changes that need
//! not be durable first (a worker's claim, which recovery would redo anyway) are applied
//! in memory and then written from the latest in-memory record (`persist`), also under
//! the journal, so a later write always carries a later state and a deleted job is never
//! written back. Reads (get, list, events, progress) take only the state lock and never
//! wait for the disk.
//!
//! Events are sent under the same lock that a watcher's snapshot is taken under, so a
//! watcher sees every change after its snapshot exactly once.

mod admission;
mod claims;
mod health;
mod lifecycle;
mod mirror;
mod previews;
mod queries;
pub mod queue;
pub mod record;
mod recovery;
pub mod shared;
pub mod store;
mod uploads;
pub mod validate;
mod worker;

#[cfg(test)]
mod tests;

use std::collections::{HashMap, HashSet};
use std::sync::atomic::AtomicBool;
use std::sync::{Arc, Condvar, Mutex, MutexGuard, OnceLock, PoisonError};
use std::time::Duration;

use serde::Serialize;
use tokio::sync::{broadcast, watch};

use crate::auth::{Caller, ClientId};
use crate::config::ServeArgs;
use crate::engine::{DenoiserFactory, EngineConfig, Fireflies, ModelInfo};
use crate::error::{Error, Result};
use crate::frame::Limits;
use crate::telemetry::Telemetry;
pub use admission::{Admission, Slot};
pub use health::{StorageProblem, HEALTH_PROBE};
pub use previews::PreviewImage;
pub use queries::{ListFilter, Stats, Throughput, STATS_WINDOW_MS};
use queue::Queue;
pub use record::*;
pub use shared::SharedConfig;
use store::Store;
pub use uploads::{Sink, Ticket, UploadPart};

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

/// Settings the core needs, taken from [`ServeArgs`].
#[derive(Clone, Debug)]
pub struct Settings {
    pub capacity: usize,
    pub result_ttl: Duration,
    pub default_deadline: Option<Duration>,
    pub limits: Limits,
    pub max_body_bytes: u64,
    /// The longest gap between two pieces of an upload (`--upload-timeout`).
    pub upload_timeout: Duration,
    /// Uploads one client may have in flight at once.
    pub max_uploads_per_client: usize,
    /// Unfinished (uploading, queued or running) jobs one client may have.
    pub max_jobs_per_client: usize,
    pub workers: usize,
    /// How each worker's engine is set up (its tile size also counts a job's tiles).
    pub engine: EngineConfig,
    /// Firefly handling of jobs that do not choose their own.
    pub fireflies: Fireflies,
    /// Whether the variances' scale is checked (`--variance-check`).
    pub variance_check: crate::engine::variance::VarianceCheck,
    /// Free bytes the data directory must keep (see [`health`]).
    pub min_free_bytes: u64,
    /// How renderers' AOV names are read (the configured channel maps, then the shipped
    /// presets); a job may choose one.
    pub channel_maps: crate::frame::ChannelMaps,
}

impl Settings {
    pub fn from_args(args: &ServeArgs) -> Settings {
        let mut engine = EngineConfig::new(&args.models);
        engine.tile = args.tile;
        engine.tile_v2 = args.tile_v2;
        engine.region_pixels = args.region_pixels;
        engine.threads = args.threads_per_worker();
        engine.ort_library = args.ort_library.clone();
        engine.device = args.device;
        engine.reconstruction = args.reconstruction;
        engine.precision = args.precision;
        engine.io_binding = args.io_binding;
        engine.albedo_prefilter = args.albedo.albedo_prefilter;
        Settings {
            capacity: args.queue_capacity,
            result_ttl: args.result_ttl,
            default_deadline: Some(args.job_deadline).filter(|d| !d.is_zero()),
            limits: args.limits(),
            max_body_bytes: args.max_body_bytes,
            upload_timeout: args.upload_timeout,
            max_uploads_per_client: args.max_uploads_per_client,
            max_jobs_per_client: args.max_jobs_per_client(),
            workers: args.workers(),
            engine,
            fireflies: args.fireflies.settings(),
            variance_check: args.variances.variance_check,
            min_free_bytes: args.min_free_bytes,
            channel_maps: args.channel_maps(),
        }
    }

    fn ttl_ms(&self) -> i64 {
        self.result_ttl.as_millis() as i64
    }
}

/// Unix time in milliseconds, as the core reads it. Tests replace it with tokio's paused
/// clock.
pub(crate) type Clock = Arc<dyn Fn() -> i64 + Send + Sync>;

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

/// Everything the core knows about its jobs, in memory. The store holds the durable part
/// (the records); this is rebuilt from it at startup (`recovery`).
#[derive(Default)]
struct State {
    jobs: HashMap<String, Entry>,
    queue: Queue,
    /// Admissions whose upload is in progress; they count against the capacity.
    reserved: usize,
    /// Idempotency keys of committed jobs, each scoped to its client ([`scoped_key`]).
    keys: HashMap<String, String>,
    /// Idempotency keys of uploads in progress, scoped the same way.
    uploading: HashSet<String>,
    /// Uploads in progress per client.
    uploads: HashMap<ClientId, usize>,
    next_seq: u64,
    running: usize,
    workers_ready: usize,
    /// Moving average of the run time of recent jobs, for `Retry-After`.
    avg_run_ms: f64,
    /// Queued jobs waiting out a backoff after a storage failure: (due, Unix ms; id). They
    /// enter the queue when due.
    delayed: Vec<(i64, String)>,
    /// Shared mode: how far the watch has delivered the stored records' changes without a
    /// gap ([`mirror::WatchCursor`]).
    watched: mirror::WatchCursor,
}

struct Inner {
    state: Mutex<State>,
    /// Serialises durable record writes (see the module docs); taken before `state`.
    journal: Mutex<()>,
    /// Workers wait here for queued jobs (and for the stop signal).
    work: Condvar,
    store: Store,
    settings: Settings,
    telemetry: Arc<Telemetry>,
    clock: Clock,
    phase: watch::Sender<Phase>,
    running: watch::Sender<usize>,
    /// Set when a worker cannot load its models: the daemon exits with this message.
    fatal: watch::Sender<Option<String>>,
    /// Set at the shutdown deadline: running jobs stop at their next tile and are requeued.
    abort: AtomicBool,
    models: OnceLock<Vec<ModelInfo>>,
    /// Where the first worker's networks run (`--device auto` resolved).
    device: OnceLock<crate::engine::Device>,
    /// The data directory's problem, `None` while healthy (see [`health`]).
    storage: watch::Sender<Option<StorageProblem>>,
    /// Device and inode of the data directory when the store was opened.
    opened: (u64, u64),
    /// Encoded previews (see [`previews`]).
    previews: previews::PreviewCache,
    /// Shared mode: the records, queue and files on NATS JetStream ([`shared`]).
    shared: Option<shared::SharedRef>,
}

/// Where the jobs are kept.
pub enum Backend {
    /// The data directory: redb and the job files (the default).
    Embedded,
    /// NATS JetStream, shared with other replicas, and the records stored there when the
    /// daemon started (the data directory is a scratch cache).
    Shared(Arc<shared::Shared>, Vec<JobRecord>),
}

/// The core handle. Cheap to clone.
#[derive(Clone)]
pub struct JobService {
    inner: Arc<Inner>,
}

/// Proof that the journal is held (see the module docs).
struct Journal<'a>(#[allow(dead_code)] MutexGuard<'a, ()>);

fn lock_poisoned<T>(e: PoisonError<T>) -> T {
    e.into_inner()
}

/// An idempotency key as [`State`] holds it: scoped to the client that sent it, so one
/// client's key never answers for another's frame (two shots that both name a frame
/// `f0001`). Keys are visible ASCII and client ids have no space, so the space separates
/// them unambiguously.
fn scoped_key(client: Option<&str>, key: &str) -> String {
    format!("{} {key}", client.unwrap_or(""))
}

fn not_found(id: &str) -> Error {
    Error::NotFound(format!("no job {}", crate::error::truncate(id, crate::error::ECHO_CHARS)))
}

/// Job `id` if `caller` may see it; another client's job answers like a missing one, so
/// that job ids say nothing about other clients' work.
fn entry_for<'a>(st: &'a State, id: &str, caller: &Caller) -> Result<&'a Entry> {
    st.jobs.get(id).filter(|e| caller.may_access(e.record.client.as_deref())).ok_or_else(|| not_found(id))
}

impl JobService {
    /// Opens the store under `data_dir`, recovers its jobs (queued and interrupted ones
    /// are queued again, finished ones kept until they expire) and starts
    /// `settings.workers` workers, each with a denoiser from `denoisers`. Workers load
    /// their models in the background; the service is ready when all have.
    pub fn start(
        data_dir: &std::path::Path,
        settings: Settings,
        telemetry: Arc<Telemetry>,
        denoisers: DenoiserFactory,
        backend: Backend,
    ) -> Result<(JobService, Vec<std::thread::JoinHandle<()>>)> {
        JobService::start_with_clock(data_dir, settings, telemetry, denoisers, backend, Arc::new(now_ms))
    }

    pub(crate) fn start_with_clock(
        data_dir: &std::path::Path,
        settings: Settings,
        telemetry: Arc<Telemetry>,
        denoisers: DenoiserFactory,
        backend: Backend,
        clock: Clock,
    ) -> Result<(JobService, Vec<std::thread::JoinHandle<()>>)> {
        let store = Store::open(data_dir)?;
        let opened = health::identity(data_dir)
            .map_err(|e| Error::storage(&format!("data directory {}", data_dir.display()), &e))?;
        let (state, shared) = match backend {
            Backend::Embedded => (recovery::recover(&store, &settings, &telemetry, clock())?, None),
            Backend::Shared(shared, records) => {
                // The local files are a cache of the shared ones: start it empty.
                let jobs = store.jobs_dir();
                if let Err(e) = std::fs::remove_dir_all(&jobs).and_then(|()| std::fs::create_dir_all(&jobs)) {
                    return Err(Error::storage(&format!("cannot clear the scratch directory {}", jobs.display()), &e));
                }
                (mirror::initial_state(records), Some(shared))
            }
        };
        telemetry.set_queue_capacity(settings.capacity);
        telemetry.set_workers(settings.workers, 0);
        telemetry.set_ready(false);
        for p in Priority::ALL {
            telemetry.set_queue_depth(p, state.queue.depth(p));
        }
        let service = JobService {
            inner: Arc::new(Inner {
                state: Mutex::new(state),
                journal: Mutex::new(()),
                work: Condvar::new(),
                store,
                settings,
                telemetry,
                clock,
                phase: watch::channel(Phase::Loading).0,
                running: watch::channel(0).0,
                fatal: watch::channel(None).0,
                abort: AtomicBool::new(false),
                models: OnceLock::new(),
                device: OnceLock::new(),
                storage: watch::channel(None).0,
                opened,
                previews: previews::PreviewCache::new(previews::CACHE_BYTES),
                shared,
            }),
        };
        let workers = worker::spawn(claims::WorkerLink::new(service.clone()), denoisers, service.settings().workers)
            .map_err(|e| Error::internal("cannot start the workers", e))?;
        Ok((service, workers))
    }

    fn lock(&self) -> MutexGuard<'_, State> {
        self.inner.state.lock().unwrap_or_else(lock_poisoned)
    }

    fn journal(&self) -> Journal<'_> {
        Journal(self.inner.journal.lock().unwrap_or_else(lock_poisoned))
    }

    fn now(&self) -> i64 {
        (self.inner.clock)()
    }

    /// Runs `f` on the blocking pool: the core's boundary between async callers and the
    /// disk.
    async fn blocking<T: Send + 'static>(
        &self,
        f: impl FnOnce(&JobService) -> Result<T> + Send + 'static,
    ) -> Result<T> {
        let service = self.clone();
        tokio::task::spawn_blocking(move || f(&service)).await.map_err(|e| Error::internal("blocking task", e))?
    }

    pub fn settings(&self) -> &Settings {
        &self.inner.settings
    }

    /// Writes a record durably. Shared mode: only if the stored one is still the version
    /// `record` was made from (else [`Error::Conflict`]), and `record.rev` becomes the new
    /// version. Blocking.
    fn write_record(&self, record: &mut JobRecord) -> Result<()> {
        match &self.inner.shared {
            Some(shared) => shared.put(record),
            None => self.inner.store.put(record),
        }
    }

    /// Removes the records of `ids` durably (shared mode: with their idempotency keys and
    /// stored files). Blocking.
    fn remove_records(&self, ids: &[&str]) -> Result<()> {
        match &self.inner.shared {
            Some(shared) => {
                let jobs: Vec<(&str, Option<String>)> = {
                    let st = self.lock();
                    ids.iter()
                        .map(|id| {
                            let key = st.jobs.get(*id).and_then(|e| {
                                let r = &e.record;
                                r.options.idempotency_key.as_deref().map(|k| scoped_key(r.client.as_deref(), k))
                            });
                            (*id, key)
                        })
                        .collect()
                };
                shared.remove(&jobs)
            }
            None => self.inner.store.remove(ids),
        }
    }

    /// The channel maps a job's frame is read with (its own choice, else every map in
    /// turn); an unknown map is a bad request naming the known ones.
    pub fn channel_maps(&self, options: &JobOptions) -> Result<crate::frame::ChannelMaps> {
        let maps = &self.inner.settings.channel_maps;
        match &options.channel_map {
            None => Ok(maps.clone()),
            Some(choice) => maps.choose(choice).map_err(Error::BadRequest),
        }
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

    /// Waits until every worker has loaded its models (the service is ready), at most
    /// `timeout`. Fails with the worker's message if one could not load them.
    pub async fn wait_ready(&self, timeout: Duration) -> Result<()> {
        let mut phase = self.subscribe_phase();
        let mut fatal = self.subscribe_fatal();
        let ready = async {
            tokio::select! {
                r = phase.wait_for(|p| *p != Phase::Loading) => match r.map(|p| *p) {
                    Ok(Phase::Ready) => Ok(()),
                    _ => Err(Error::Unavailable("the service stopped before it was ready".into())),
                },
                f = fatal.wait_for(|f| f.is_some()) => Err(Error::Unavailable(
                    f.ok().and_then(|f| f.clone()).unwrap_or_else(|| "a worker failed".into()),
                )),
            }
        };
        tokio::time::timeout(timeout, ready)
            .await
            .map_err(|_| Error::Unavailable(format!("not ready after {timeout:?}: the models are still loading")))?
    }

    /// The loaded models; `None` until the first worker has loaded them.
    pub fn models(&self) -> Option<&[ModelInfo]> {
        self.inner.models.get().map(Vec::as_slice)
    }

    /// Where the networks run, once the first worker has loaded them.
    pub fn device(&self) -> Option<crate::engine::Device> {
        self.inner.device.get().copied()
    }

    /// Jobs running now.
    pub fn running(&self) -> usize {
        self.lock().running
    }

    fn set_phase(&self, phase: Phase) {
        self.inner.phase.send_replace(phase);
        self.inner.telemetry.set_ready(self.is_ready());
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
}
