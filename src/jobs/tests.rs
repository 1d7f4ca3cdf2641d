//! The job lifecycle with a fake denoiser and tokio's paused clock: admission, priorities,
//! cancel while queued and while running, deadlines, retention, recovery after a crash.
//! No model and no ONNX Runtime: each test runs in milliseconds.
//!
//! The fake denoiser takes one permit from a [`Gate`] per tile, so a test decides when a
//! running job moves on. Time moves only with `tokio::time::advance`; the core reads it
//! through its clock (deadlines, retention), the workers' threads included.

use std::sync::{Arc, Condvar, Mutex};
use std::thread::JoinHandle;
use std::time::Duration;

use futures_util::StreamExt;

use super::store::{Store, RECORD_FILE};
use super::*;
use crate::engine::{Component, Denoised, Denoiser, EngineError, ModelInfo, Progress as TileProgress, Variant};
use crate::frame::{Frame, SampleType};

/// Permits for tiles: the fake denoiser waits for one before each tile.
#[derive(Default)]
struct Gate {
    /// `None`: open, no waiting.
    permits: Mutex<Option<u64>>,
    changed: Condvar,
}

impl Gate {
    fn closed() -> Arc<Gate> {
        Arc::new(Gate { permits: Mutex::new(Some(0)), changed: Condvar::new() })
    }

    fn release(&self, n: u64) {
        if let Some(p) = self.permits.lock().unwrap().as_mut() {
            *p += n;
        }
        self.changed.notify_all();
    }

    fn open(&self) {
        *self.permits.lock().unwrap() = None;
        self.changed.notify_all();
    }

    fn take(&self) {
        let mut permits = self.permits.lock().unwrap();
        loop {
            match permits.as_mut() {
                None => return,
                Some(p) if *p > 0 => {
                    *p -= 1;
                    return;
                }
                Some(_) => permits = self.changed.wait(permits).unwrap(),
            }
        }
    }
}

/// Denoises by copying the frame's diffuse + specular, tile by tile through the gate, and
/// notes the width of every frame it is given (tests tell jobs apart by width).
struct FakeDenoiser {
    gate: Arc<Gate>,
    tile: usize,
    seen: Arc<Mutex<Vec<usize>>>,
}

impl Denoiser for FakeDenoiser {
    fn models(&self) -> Vec<ModelInfo> {
        vec![ModelInfo {
            variant: Variant::Nocov,
            component: Some(Component::Diffuse),
            contract: 1,
            features: crate::engine::FeatureSet::Nocov,
            path: "fake.onnx".into(),
            kernel_size: 21,
            levels: 1,
            receptive_radius: 0,
            flops_per_pixel: 1.0,
            architecture: "fake".into(),
            sha256: String::new(),
            input_compression: crate::engine::InputCompression::Graph,
            outputs: crate::engine::Outputs::Kernels,
            precision: crate::engine::Precision::Fp32,
            specular_pyramid: crate::engine::SpecularPyramid::Log,
            detail_gains: false,
        }]
    }

    fn denoise(
        &mut self,
        frame: &Frame,
        options: crate::engine::Options,
        on_tile: &mut dyn FnMut(TileProgress) -> bool,
    ) -> Result<Denoised, EngineError> {
        self.seen.lock().unwrap().push(frame.width);
        let tiles = crate::engine::tile_grid(frame.width, frame.height, self.tile).len();
        for done in 1..=tiles {
            self.gate.take();
            if !on_tile(TileProgress { tiles_done: done, tiles_total: tiles }) && done < tiles {
                return Err(EngineError::Cancelled);
            }
        }
        let color = frame.diffuse_plus_specular();
        Ok(Denoised {
            width: frame.width,
            height: frame.height,
            variant: options.variant.unwrap_or(Variant::Nocov),
            components: options
                .components
                .then(|| crate::engine::Components { diffuse: color.clone(), specular: color.clone() }),
            color,
            tiles,
            timings: Default::default(),
            fireflies: Default::default(),
            exposure: 1.0,
            staged: false,
        })
    }
}

const TILE: usize = 32;

fn settings(capacity: usize) -> Settings {
    let mut engine = EngineConfig::new("fake-models");
    engine.tile = TILE;
    Settings {
        capacity,
        result_ttl: Duration::from_secs(60),
        default_deadline: None,
        limits: Limits::default(),
        max_body_bytes: 1 << 20,
        upload_timeout: Duration::from_secs(30),
        max_uploads_per_client: 16,
        max_jobs_per_client: usize::MAX,
        workers: 1,
        engine,
        fireflies: Default::default(),
        variance_check: Default::default(),
        min_free_bytes: 0,
        channel_maps: Default::default(),
    }
}

/// Unix milliseconds that follow tokio's (paused) clock, read from any thread.
fn paused_clock() -> Clock {
    let handle = tokio::runtime::Handle::current();
    let (start_ms, start) = (now_ms(), tokio::time::Instant::now());
    Arc::new(move || {
        let _runtime = handle.enter();
        start_ms + (tokio::time::Instant::now() - start).as_millis() as i64
    })
}

struct Harness {
    service: JobService,
    workers: Vec<JoinHandle<()>>,
    gate: Arc<Gate>,
    seen: Arc<Mutex<Vec<usize>>>,
    dir: tempfile::TempDir,
}

impl Harness {
    async fn start(settings: Settings, gate: Arc<Gate>) -> Harness {
        Harness::start_in(tempfile::tempdir().unwrap(), settings, gate).await
    }

    async fn start_in(dir: tempfile::TempDir, settings: Settings, gate: Arc<Gate>) -> Harness {
        let seen = Arc::new(Mutex::new(Vec::new()));
        let (g, s) = (gate.clone(), seen.clone());
        let denoisers: DenoiserFactory = Arc::new(move || {
            Ok(Box::new(FakeDenoiser { gate: g.clone(), tile: TILE, seen: s.clone() }) as Box<dyn Denoiser>)
        });
        let (service, workers) = JobService::start_with_clock(
            dir.path(),
            settings,
            Arc::new(Telemetry::new()),
            denoisers,
            Backend::Embedded,
            paused_clock(),
        )
        .unwrap();
        // No timeout here: under the paused clock it would fire at once.
        service.subscribe_phase().wait_for(|p| *p == Phase::Ready).await.unwrap();
        Harness { service, workers, gate, seen, dir }
    }

    /// Uploads a synthetic frame `width` pixels wide and commits it.
    async fn submit(&self, width: usize, options: JobOptions) -> Result<Admitted> {
        self.submit_as(&ops().id, width, options).await
    }

    async fn submit_as(&self, client: &ClientId, width: usize, options: JobOptions) -> Result<Admitted> {
        let mut ticket = match self.service.admit(options, "test", client)? {
            Admission::Existing(status) => return Ok(Admitted::Existing(status)),
            Admission::New(t) => t,
        };
        let mut sink = ticket.sink(UploadPart::Frame).await?;
        sink.write(&frame_bytes(width, 16)).await?;
        ticket.finish(sink).await?;
        Ok(Admitted::New(ticket.commit().await?))
    }

    async fn submit_new(&self, width: usize, options: JobOptions) -> String {
        match self.submit(width, options).await.unwrap() {
            Admitted::New(s) => s.record.id,
            Admitted::Existing(s) => panic!("expected a new job, got {}", s.record.id),
        }
    }

    /// Waits (on the job's events, not on time) until `pred` holds for its status.
    async fn until(&self, id: &str, what: &str, pred: impl Fn(&JobStatus) -> bool) -> JobStatus {
        let mut events = self.service.events(id, &ops()).unwrap();
        loop {
            let status = self.service.get(id, &ops()).unwrap();
            if pred(&status) {
                return status;
            }
            assert!(events.next().await.is_some(), "job {id} ended its events before it was {what}: {status:?}");
        }
    }

    async fn until_state(&self, id: &str, state: JobState) -> JobStatus {
        self.until(id, state.name(), |s| s.record.state == state).await
    }

    fn stop(self) {
        self.gate.open();
        self.service.begin_drain();
        self.service.stop_workers();
        for w in self.workers {
            w.join().unwrap();
        }
    }
}

#[derive(Debug)]
enum Admitted {
    New(JobStatus),
    Existing(JobStatus),
}

fn frame_bytes(w: usize, h: usize) -> Vec<u8> {
    let planes = crate::engine::synthetic_planes(w, h, false);
    let named = planes.iter().map(|(n, p)| (n.as_str(), p.as_slice()));
    crate::frame::write_planes(w, h, named, SampleType::F32, exr::prelude::Encoding::FAST_LOSSLESS).unwrap()
}

/// The caller the tests act as: an operator, allowed every job.
fn ops() -> Caller {
    Caller::operator(ClientId("test".into()))
}

fn options(priority: Priority) -> JobOptions {
    JobOptions { priority, ..Default::default() }
}

#[tokio::test(start_paused = true)]
async fn admission_refuses_over_capacity_replays_keys_and_runs_by_priority() {
    let h = Harness::start(settings(3), Gate::closed()).await;
    // 40 px wide: runs first and holds the worker.
    let first = h.submit_new(40, options(Priority::Normal)).await;
    h.until_state(&first, JobState::Running).await;
    let low = h.submit_new(41, options(Priority::Low)).await;
    let keyed = JobOptions { idempotency_key: Some("shot-1".into()), ..options(Priority::High) };
    let high = h.submit_new(42, keyed.clone()).await;
    match h.submit(99, keyed).await.unwrap() {
        Admitted::Existing(s) => assert_eq!(s.record.id, high, "a retried key returns the same job"),
        Admitted::New(s) => panic!("a retried key made a second job {}", s.record.id),
    }
    let normal = h.submit_new(43, options(Priority::Normal)).await;
    let positions: Vec<u64> =
        [&high, &normal, &low].iter().map(|id| h.service.get(id, &ops()).unwrap().queue_position).collect();
    assert_eq!(positions, [1, 2, 3]);
    match h.submit(44, options(Priority::High)).await {
        Err(Error::QueueFull { capacity: 3, retry_after_s }) => assert!(retry_after_s >= 1),
        other => panic!("expected a full queue, got {other:?}"),
    }
    h.gate.open();
    for id in [&first, &high, &normal, &low] {
        let s = h.until_state(id, JobState::Succeeded).await;
        assert_eq!(s.record.attempts, 1);
        assert!(h.dir.path().join("jobs").join(id).join("result.exr").is_file());
    }
    assert_eq!(*h.seen.lock().unwrap(), [40, 42, 43, 41], "high, then normal, then low; FIFO within a class");
    h.stop();
}

#[tokio::test(start_paused = true)]
async fn cancel_ends_a_queued_job_at_once_and_a_running_one_at_its_next_tile() {
    let h = Harness::start(settings(8), Gate::closed()).await;
    let running = h.submit_new(64, options(Priority::Normal)).await;
    h.until_state(&running, JobState::Running).await;
    let queued = h.submit_new(32, options(Priority::Normal)).await;

    let s = h.service.cancel(&queued, &ops()).await.unwrap();
    assert_eq!(s.record.state, JobState::Cancelled);
    assert!(s.record.cancel_requested && s.record.finished_at_ms.is_some());
    assert!(!h.dir.path().join("jobs").join(&queued).join("input.exr").exists(), "inputs removed");
    assert!(matches!(h.service.cancel(&queued, &ops()).await, Err(Error::Conflict(_))));

    let s = h.service.cancel(&running, &ops()).await.unwrap();
    assert_eq!((s.record.state, s.record.cancel_requested), (JobState::Running, true));
    h.gate.release(1);
    let s = h.until_state(&running, JobState::Cancelled).await;
    assert_eq!(s.record.progress.tiles_done, 1, "stopped after its first of two tiles");
    assert!(matches!(h.service.open_result(&running, &ops()).await, Err(Error::Conflict(_))));
    h.stop();
}

/// A shared-mode claim whose write fails puts back the record it read, but never over a
/// later revision the watch applied meanwhile (another replica ran the job while the write
/// was timing out: the stale record would show it queued for good).
#[tokio::test(start_paused = true)]
async fn a_failed_claim_puts_back_the_read_record_but_not_over_a_later_one() {
    let h = Harness::start(settings(8), Gate::closed()).await;
    let running = h.submit_new(64, options(Priority::Normal)).await;
    h.until_state(&running, JobState::Running).await;
    let id = h.submit_new(32, options(Priority::Normal)).await;
    let read = h.service.lock().jobs[&id].record.clone();
    let mut later = read.clone();
    later.rev = read.rev + 1;
    later.state = JobState::Succeeded;
    h.service.lock().jobs.get_mut(&id).unwrap().record = later;
    h.service.restore(read.clone());
    let held = h.service.lock().jobs[&id].record.clone();
    assert_eq!((held.rev, held.state), (read.rev + 1, JobState::Succeeded), "the later revision stays");

    // Nothing newer arrived: the read record comes back (the claim's changes undone).
    h.service.lock().jobs.get_mut(&id).unwrap().record.rev = read.rev;
    h.service.restore(read.clone());
    let held = h.service.lock().jobs[&id].record.clone();
    assert_eq!((held.rev, held.state), (read.rev, JobState::Queued));
    h.stop();
}

#[tokio::test(start_paused = true)]
async fn deadlines_fail_queued_jobs_in_the_sweep_and_running_jobs_between_tiles() {
    let h = Harness::start(settings(8), Gate::closed()).await;
    let running = h.submit_new(64, JobOptions { deadline_seconds: Some(10), ..Default::default() }).await;
    h.until_state(&running, JobState::Running).await;
    let queued = h.submit_new(32, JobOptions { deadline_seconds: Some(5), ..Default::default() }).await;

    tokio::time::advance(Duration::from_secs(4)).await;
    h.service.sweep().await.unwrap();
    assert_eq!(h.service.get(&queued, &ops()).unwrap().record.state, JobState::Queued);
    tokio::time::advance(Duration::from_secs(2)).await;
    h.service.sweep().await.unwrap();
    let s = h.service.get(&queued, &ops()).unwrap();
    assert_eq!(s.record.state, JobState::Failed);
    let error = s.record.error.unwrap();
    assert_eq!(error.code, JobErrorCode::DeadlineExceeded);
    assert!(error.message.contains("while it was queued"), "{}", error.message);

    tokio::time::advance(Duration::from_secs(5)).await;
    h.gate.release(1);
    let s = h.until_state(&running, JobState::Failed).await;
    let error = s.record.error.unwrap();
    assert_eq!(error.code, JobErrorCode::DeadlineExceeded);
    assert!(error.message.contains("while it ran"), "{}", error.message);
    h.stop();
}

#[tokio::test(start_paused = true)]
async fn a_job_is_seen_and_changed_only_by_its_owner_or_an_operator() {
    let h = Harness::start(settings(8), Gate::closed()).await;
    let node = |name: &str| Caller { id: ClientId(name.into()), scope: crate::auth::Scope::Submit, metrics: false };
    let (a, b) = (node("token:aaaa"), node("token:bbbb"));
    let mine = match h.submit_as(&a.id, 32, options(Priority::Normal)).await.unwrap() {
        Admitted::New(s) => s.record.id,
        Admitted::Existing(s) => panic!("new job expected, got {}", s.record.id),
    };
    // Another client's job answers exactly like a missing one, for every operation.
    assert!(matches!(h.service.get(&mine, &b), Err(Error::NotFound(_))));
    assert!(matches!(h.service.events(&mine, &b), Err(Error::NotFound(_))));
    assert!(matches!(h.service.open_result(&mine, &b).await, Err(Error::NotFound(_))));
    assert!(matches!(h.service.cancel(&mine, &b).await, Err(Error::NotFound(_))));
    assert!(matches!(h.service.delete(&mine, &b).await, Err(Error::NotFound(_))));
    let owned = |c: &Caller| ListFilter { owner: c.owner_filter(), ..Default::default() };
    assert!(h.service.list(&owned(&b)).unwrap().0.is_empty());
    assert_eq!(h.service.list(&owned(&a)).unwrap().0.len(), 1);
    assert_eq!(h.service.list(&owned(&ops())).unwrap().0.len(), 1, "operators list every job");
    // The owner and operators may.
    assert_eq!(h.service.get(&mine, &a).unwrap().record.client.as_deref(), Some("token:aaaa"));
    assert_eq!(h.service.get(&mine, &ops()).unwrap().record.id, mine);
    h.service.cancel(&mine, &a).await.unwrap();
    h.service.delete(&mine, &ops()).await.unwrap();
    h.stop();
}

#[tokio::test(start_paused = true)]
async fn finished_jobs_are_kept_for_the_retention_time_then_removed() {
    let gate = Gate::closed();
    gate.open();
    let h = Harness::start(settings(8), gate).await;
    let id = h.submit_new(32, JobOptions { label: Some("kept".into()), ..Default::default() }).await;
    let s = h.until_state(&id, JobState::Succeeded).await;
    assert_eq!(s.record.expires_at_ms.unwrap() - s.record.finished_at_ms.unwrap(), 60_000);
    let (_file, len) = h.service.open_result(&id, &ops()).await.unwrap();
    assert_eq!(Some(len), s.record.result_bytes);

    tokio::time::advance(Duration::from_secs(59)).await;
    assert_eq!(h.service.sweep().await.unwrap(), 0);
    tokio::time::advance(Duration::from_secs(2)).await;
    assert_eq!(h.service.sweep().await.unwrap(), 1);
    assert!(matches!(h.service.get(&id, &ops()), Err(Error::NotFound(_))));
    assert!(!h.dir.path().join("jobs").join(&id).exists(), "its files go too");
    h.stop();
}

fn record(id: &str, seq: u64, state: JobState) -> JobRecord {
    JobRecord {
        id: id.into(),
        seq,
        state,
        options: JobOptions::default(),
        width: 32,
        height: 16,
        input_bytes: 1,
        has_reference: false,
        created_at_ms: now_ms(),
        started_at_ms: None,
        finished_at_ms: None,
        deadline_at_ms: None,
        expires_at_ms: None,
        attempts: u32::from(state != JobState::Queued),
        cancel_requested: false,
        variant: None,
        progress: Progress::default(),
        timings: None,
        metrics: None,
        sanitized: None,
        fireflies: None,
        missing_variances: Vec::new(),
        warnings: Vec::new(),
        error: None,
        result_bytes: None,
        client: None,
        storage_failures: 0,
        trace_parent: None,
        rev: 0,
    }
}

/// Writes `record` as a daemon would: into its job directory and the database.
fn put(store: &Store, record: &JobRecord) {
    std::fs::create_dir_all(store.job_dir(&record.id)).unwrap();
    store.put(record).unwrap();
}

fn write_file(store: &Store, id: &str, name: &str, bytes: &[u8]) {
    std::fs::create_dir_all(store.job_dir(id)).unwrap();
    std::fs::write(store.job_dir(id).join(name), bytes).unwrap();
}

#[tokio::test(start_paused = true)]
async fn recovery_after_a_crash_requeues_adopts_fails_and_forgets_as_documented() {
    let dir = tempfile::tempdir().unwrap();
    {
        // The store as a killed daemon leaves it.
        let store = Store::open(dir.path()).unwrap();
        let write = |id: &str, name: &str, bytes: &[u8]| write_file(&store, id, name, bytes);
        // Interrupted while running: queued again, with a half-written result to clean up.
        put(&store, &record("interrupted", 1, JobState::Running));
        write("interrupted", "input.exr", &frame_bytes(32, 16));
        write("interrupted", "result.exr.part", b"half");
        // Finished just before the crash: its summary and result are adopted.
        let mut done = record("finished", 2, JobState::Succeeded);
        done.result_bytes = Some(4);
        put(&store, &record("finished", 2, JobState::Running));
        write("finished", "result.json", &serde_json::to_vec(&done).unwrap());
        write("finished", "result.exr", b"done");
        write("finished", "input.exr", &frame_bytes(32, 16));
        // Queued, but its upload (its whole directory) is gone.
        put(&store, &record("lost", 3, JobState::Queued));
        std::fs::remove_dir_all(store.job_dir("lost")).unwrap();
        // Expired while the daemon was down.
        let mut old = record("expired", 4, JobState::Failed);
        old.expires_at_ms = Some(now_ms() - 1);
        put(&store, &old);
        write("expired", "result.json", b"{}");
        // An upload cut short: a directory with only a temporary file.
        write("orphan", "input.exr.part", b"partial");
    }
    let gate = Gate::closed();
    gate.open();
    let h = Harness::start_in(dir, settings(8), gate).await;

    let s = h.until_state("interrupted", JobState::Succeeded).await;
    assert_eq!(s.record.attempts, 2, "ran again after the interrupted attempt");
    let s = h.service.get("finished", &ops()).unwrap();
    assert_eq!((s.record.state, s.record.result_bytes), (JobState::Succeeded, Some(4)));
    assert_eq!(h.seen.lock().unwrap().len(), 1, "the adopted job did not run again");
    let s = h.service.get("lost", &ops()).unwrap();
    assert_eq!(s.record.state, JobState::Failed);
    assert!(s.record.error.unwrap().message.contains("uploaded frame is missing"));
    assert!(matches!(h.service.get("expired", &ops()), Err(Error::NotFound(_))));
    let jobs = h.dir.path().join("jobs");
    assert!(!jobs.join("expired").exists() && !jobs.join("orphan").exists());
    assert!(!jobs.join("interrupted").join("result.exr.part").exists());
    assert!(!h.dir.path().join("quarantine").exists(), "nothing to quarantine");
    h.stop();
}

#[tokio::test(start_paused = true)]
async fn a_lost_or_rolled_back_database_is_rebuilt_from_the_job_directories() {
    let dir = tempfile::tempdir().unwrap();
    {
        let store = Store::open(dir.path()).unwrap();
        put(&store, &record("queued", 1, JobState::Queued));
        write_file(&store, "queued", "input.exr", &frame_bytes(32, 16));
        let mut done = record("done", 2, JobState::Succeeded);
        done.expires_at_ms = Some(now_ms() + 3_600_000);
        put(&store, &done);
        write_file(&store, "done", "result.exr", b"done");
        // A later state that only the directory's copy has (the database rolled back).
        put(&store, &record("cancelled", 3, JobState::Queued));
        write_file(&store, "cancelled", "input.exr", &frame_bytes(32, 16));
        let mut later = record("cancelled", 3, JobState::Cancelled);
        later.rev = 1_000;
        later.expires_at_ms = Some(now_ms() + 3_600_000);
        std::fs::write(store.record_path("cancelled"), serde_json::to_vec(&later).unwrap()).unwrap();
    }
    std::fs::remove_file(dir.path().join("jobs.redb")).unwrap();
    let gate = Gate::closed();
    gate.open();
    let h = Harness::start_in(dir, settings(8), gate).await;
    h.until_state("queued", JobState::Succeeded).await;
    assert_eq!(h.service.get("done", &ops()).unwrap().record.state, JobState::Succeeded);
    assert_eq!(
        h.service.get("cancelled", &ops()).unwrap().record.state,
        JobState::Cancelled,
        "no terminal state reversed"
    );
    assert_eq!(h.seen.lock().unwrap().len(), 1, "only the queued job ran");
    h.stop();
}

#[tokio::test(start_paused = true)]
async fn what_no_record_accounts_for_is_quarantined_not_deleted() {
    let dir = tempfile::tempdir().unwrap();
    {
        let store = Store::open(dir.path()).unwrap();
        // Files with no record anywhere.
        write_file(&store, "stray", "input.exr", b"frame");
        // A record in neither copy that can be read.
        write_file(&store, "garbled", "input.exr", b"frame");
        write_file(&store, "garbled", RECORD_FILE, b"{ not json");
    }
    let h = Harness::start_in(dir, settings(8), Gate::closed()).await;
    let quarantine: Vec<String> = std::fs::read_dir(h.dir.path().join("quarantine"))
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().to_string())
        .collect();
    assert_eq!(quarantine.len(), 2, "{quarantine:?}");
    for name in ["stray.", "garbled."] {
        let kept = quarantine.iter().find(|q| q.starts_with(name)).unwrap();
        assert!(h.dir.path().join("quarantine").join(kept).join("input.exr").is_file());
    }
    assert!(h.service.telemetry().render().contains("mcdenoise_storage_quarantined_total 2"));
    h.stop();
}

#[tokio::test(start_paused = true)]
async fn deleting_a_running_job_removes_it_and_its_files_when_the_run_ends() {
    let h = Harness::start(settings(8), Gate::closed()).await;
    let id = h.submit_new(64, options(Priority::Normal)).await;
    let mut events = h.service.events(&id, &ops()).unwrap();
    h.until_state(&id, JobState::Running).await;
    h.service.delete(&id, &ops()).await.unwrap();
    assert!(matches!(h.service.get(&id, &ops()), Err(Error::NotFound(_))));
    while events.next().await.is_some() {}
    h.gate.release(2);
    // The worker notices at its next tile; then nothing of the job is left.
    let next = h.submit_new(32, options(Priority::Normal)).await;
    h.gate.open();
    h.until_state(&next, JobState::Succeeded).await;
    assert!(!h.dir.path().join("jobs").join(&id).exists());
    assert_eq!(h.service.storage_problem(), None, "a deleted job's missing directory is not a storage fault");
    h.stop();
}

/// The size and the 8-bit RGB pixels of a PNG.
fn decode_png(bytes: &[u8]) -> ((u32, u32), Vec<u8>) {
    let mut reader = png::Decoder::new(std::io::Cursor::new(bytes)).read_info().unwrap();
    let mut buf = vec![0; reader.output_buffer_size().unwrap()];
    let info = reader.next_frame(&mut buf).unwrap();
    buf.truncate(info.buffer_size());
    ((info.width, info.height), buf)
}

#[tokio::test(start_paused = true)]
async fn previews_come_from_the_uploads_then_from_what_a_succeeded_job_keeps() {
    use crate::preview::{Region, Spec};
    let h = Harness::start(settings(8), Gate::closed()).await;
    let spec = Spec::default();
    let preview = |id: &str, caller: &Caller, image: PreviewImage, spec: Spec| {
        let (service, id, caller) = (h.service.clone(), id.to_string(), caller.clone());
        async move { service.preview(&id, &caller, image, spec).await }
    };
    let running = h.submit_new(64, options(Priority::Normal)).await;
    h.until_state(&running, JobState::Running).await;
    let queued = h.submit_new(40, options(Priority::Normal)).await;

    // Unfinished: the input from its upload; no result yet; no reference was sent.
    let png = preview(&queued, &ops(), PreviewImage::Input, spec).await.unwrap();
    assert_eq!(decode_png(&png).0, (40, 16));
    let e = preview(&running, &ops(), PreviewImage::Result, spec).await.unwrap_err();
    assert!(matches!(&e, Error::Conflict(m) if m.contains("once it has succeeded")), "{e:?}");
    let e = preview(&running, &ops(), PreviewImage::Reference, spec).await.unwrap_err();
    assert!(matches!(&e, Error::NotFound(m) if m.contains("without a reference")), "{e:?}");
    // Another client's job answers like a missing one.
    let other = Caller { id: ClientId("token:other".into()), scope: crate::auth::Scope::Submit, metrics: false };
    let e = preview(&queued, &other, PreviewImage::Input, spec).await.unwrap_err();
    assert!(matches!(&e, Error::NotFound(m) if m == &format!("no job {queued}")), "{e:?}");
    // A cancelled job keeps nothing of its upload.
    h.service.cancel(&queued, &ops()).await.unwrap();
    let e = preview(&queued, &ops(), PreviewImage::Input, spec).await.unwrap_err();
    assert!(matches!(&e, Error::NotFound(m) if m.contains("only a succeeded job keeps it")), "{e:?}");

    // Succeeded: the colour the worker decoded is kept for the input's previews.
    h.gate.open();
    h.until_state(&running, JobState::Succeeded).await;
    let dir = h.dir.path().join("jobs").join(&running);
    // (The upload itself is removed just after the terminal event.)
    assert!(dir.join("preview-input.exr").is_file());
    assert!(!dir.join("preview-reference.exr").exists());
    let (size, before) = decode_png(&preview(&running, &ops(), PreviewImage::Input, spec).await.unwrap());
    let (size_after, after) = decode_png(&preview(&running, &ops(), PreviewImage::Result, spec).await.unwrap());
    assert_eq!((size, size_after), ((64, 16), (64, 16)));
    // The fake denoiser returns the input's colour: the two agree up to the kept copy's
    // half floats.
    assert!(before.iter().zip(&after).all(|(a, b)| a.abs_diff(*b) <= 1));
    assert!(before.iter().any(|v| *v > 0), "not a black picture");
    // Brighter with exposure; a region at full resolution; a smaller size.
    let (_, bright) =
        decode_png(&preview(&running, &ops(), PreviewImage::Result, Spec { exposure: 2.0, ..spec }).await.unwrap());
    assert!(bright.iter().zip(&after).all(|(b, a)| b >= a) && bright != after);
    let region = Spec { region: Some(Region { x: 8, y: 4, width: 10, height: 6 }), ..spec };
    let (size, cut) = decode_png(&preview(&running, &ops(), PreviewImage::Result, region).await.unwrap());
    assert_eq!(size, (10, 6));
    assert_eq!(&cut[..30], &after[(4 * 64 + 8) * 3..(4 * 64 + 18) * 3], "the region's first row, unscaled");
    let small = preview(&running, &ops(), PreviewImage::Result, Spec { max_size: 16, ..spec }).await.unwrap();
    assert_eq!(decode_png(&small).0, (16, 4));
    let outside = Spec { region: Some(Region { x: 60, y: 0, width: 10, height: 6 }), ..spec };
    let e = preview(&running, &ops(), PreviewImage::Result, outside).await.unwrap_err();
    assert!(matches!(&e, Error::BadRequest(m) if m.contains("not inside the 64x16 frame")), "{e:?}");
    // Answered again from the cache, the same bytes.
    let again = preview(&running, &ops(), PreviewImage::Result, Spec { max_size: 16, ..spec }).await.unwrap();
    assert!(Arc::ptr_eq(&small, &again));
    h.stop();
}

#[tokio::test(start_paused = true)]
async fn stats_count_every_state_and_the_last_hours_throughput() {
    let h = Harness::start(settings(8), Gate::closed()).await;
    let a = ClientId("token:aaaa".into());
    let done = h.submit_new(64, options(Priority::Normal)).await;
    h.until_state(&done, JobState::Running).await;
    let high = match h.submit_as(&a, 32, options(Priority::High)).await.unwrap() {
        Admitted::New(s) => s.record.id,
        Admitted::Existing(s) => panic!("new job expected, got {}", s.record.id),
    };
    let low = h.submit_new(32, options(Priority::Low)).await;
    let stats = h.service.stats(None);
    assert_eq!((stats.jobs, stats.by_state["queued"], stats.by_state["running"]), (3, 2, 1));
    assert_eq!((stats.queued_by_priority["high"], stats.queued_by_priority["low"]), (1, 1));
    assert_eq!(stats.last_hour.frames_per_hour, 0);
    assert_eq!(stats.last_hour.mean_seconds_per_megapixel, None);
    h.service.cancel(&low, &ops()).await.unwrap();
    h.gate.open();
    h.until_state(&done, JobState::Succeeded).await;
    h.until_state(&high, JobState::Succeeded).await;
    let stats = h.service.stats(None);
    let hour = &stats.last_hour;
    assert_eq!((hour.succeeded, hour.cancelled, hour.frames_per_hour), (2, 1, 2));
    assert!((hour.megapixels - (64.0 * 16.0 + 32.0 * 16.0) / 1e6).abs() < 1e-12);
    assert!(hour.mean_seconds_per_megapixel.is_some());
    assert_eq!(stats.by_state["succeeded"], 2);
    // A submit token's totals count its own jobs only.
    let own = h.service.stats(Some("token:aaaa"));
    assert_eq!((own.jobs, own.last_hour.frames_per_hour), (1, 1));
    // Listing: newest first, and by client.
    let newest = ListFilter { newest_first: true, limit: Some(2), ..Default::default() };
    let (page, next) = h.service.list(&newest).unwrap();
    assert_eq!(page.iter().map(|s| s.record.id.as_str()).collect::<Vec<_>>(), [low.as_str(), high.as_str()]);
    let (rest, _) = h.service.list(&ListFilter { after: next, ..newest }).unwrap();
    assert_eq!(rest.iter().map(|s| s.record.id.as_str()).collect::<Vec<_>>(), [done.as_str()]);
    let mine = ListFilter { client: Some("token:aaaa".into()), ..Default::default() };
    assert_eq!(h.service.list(&mine).unwrap().0.len(), 1);
    // An hour later nothing finished in the window; the totals stay.
    tokio::time::advance(Duration::from_secs(3601)).await;
    let stats = h.service.stats(None);
    assert_eq!((stats.jobs, stats.last_hour.frames_per_hour, stats.last_hour.cancelled), (3, 0, 0));
    h.stop();
}

/// The dashboard with 10,000 jobs in the store: the calls its queue view makes on every
/// refresh (the totals, one page of 50 jobs, newest first, with or without filters), made
/// through the HTTP router, stay paginated and answer quickly. The jobs are put straight
/// into the core's state (writing 10,000 records durably takes minutes); the one worker is
/// held by a running job so that none of them is claimed.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn ten_thousand_jobs_answer_the_dashboards_calls_in_pages_and_quickly() {
    use axum::body::Body;
    use http_body_util::BodyExt;
    use tower::ServiceExt;

    const JOBS: u64 = 10_000;
    let h = Harness::start(settings(JOBS as usize + 8), Gate::closed()).await;
    let held = h.submit_new(64, options(Priority::Normal)).await;
    h.until_state(&held, JobState::Running).await;
    let now = now_ms();
    {
        let mut st = h.service.lock();
        for i in 0..JOBS {
            let state = JobState::ALL[(i % 5) as usize];
            let mut r = record(&format!("job-{i:05}"), 100 + i, state);
            r.options.priority = Priority::ALL[(i % 3) as usize];
            r.options.label = Some(format!("shot{:03}", i % 100));
            r.client = Some(format!("token:{:012x}", i % 7));
            if state.is_terminal() {
                r.finished_at_ms = Some(now - i as i64 * 1000);
            }
            if state == JobState::Succeeded {
                r.timings = Some(Timings { total: 250.0, ..Default::default() });
            }
            if state == JobState::Queued {
                st.queue.push(r.options.priority, r.seq, r.id.clone());
            }
            st.jobs.insert(r.id.clone(), Entry::new(r));
        }
        st.next_seq = 100 + JOBS;
    }
    let router = crate::http::router(crate::http::AppState {
        service: h.service.clone(),
        tokens: Arc::new(crate::auth::Tokens::default()),
        shutdown: tokio_util::sync::CancellationToken::new(),
        info: Arc::new(crate::http::Info::new(serde_json::Value::Null)),
    });
    let get = |uri: String| {
        let router = router.clone();
        async move {
            let t = std::time::Instant::now();
            let request = axum::http::Request::get(&uri).body(Body::empty()).unwrap();
            let response = router.oneshot(request).await.unwrap();
            assert_eq!(response.status(), 200, "{uri}");
            let body = response.into_body().collect().await.unwrap().to_bytes();
            (serde_json::from_slice::<serde_json::Value>(&body).unwrap(), t.elapsed())
        }
    };
    let mut slowest = Duration::ZERO;
    let (stats, took) = get("/v1/stats".into()).await;
    slowest = slowest.max(took);
    assert_eq!(stats["jobs"], JOBS + 1);
    assert_eq!(stats["by_state"]["failed"], JOBS / 5);
    // Finished within the hour: one a second, the newest 3,600 of them.
    let in_window = (0..3600).filter(|i| i % 5 == 2).count();
    assert_eq!(stats["last_hour"]["succeeded"], in_window);

    // Newest first, page by page, as the queue view walks them.
    let mut token = String::new();
    let mut seen = std::collections::HashSet::new();
    for page in 0..5 {
        let (list, took) = get(format!("/v1/jobs?limit=50&order=newest&page_token={token}")).await;
        slowest = slowest.max(took);
        let jobs = list["jobs"].as_array().unwrap();
        assert_eq!(jobs.len(), 50, "page {page}");
        if page == 0 {
            assert_eq!(jobs[0]["id"], format!("job-{:05}", JOBS - 1), "the newest first");
        }
        assert!(jobs.iter().all(|j| seen.insert(j["id"].as_str().unwrap().to_string())), "no job twice");
        token = list["next_page_token"].as_str().unwrap().to_string();
    }
    // Filtered: the queued high-priority jobs of one shot and one client.
    let (list, took) = get("/v1/jobs?limit=50&order=newest&state=queued&priority=high&label=shot000".into()).await;
    slowest = slowest.max(took);
    let jobs = list["jobs"].as_array().unwrap();
    assert!(!jobs.is_empty() && jobs.iter().all(|j| j["state"] == "queued" && j["label"] == "shot000"));
    assert!(jobs.iter().all(|j| j["queue_position"].as_u64().is_some_and(|p| p >= 1)));
    let (list, took) = get("/v1/jobs?limit=50&client=token:000000000003".into()).await;
    slowest = slowest.max(took);
    assert!(list["jobs"].as_array().unwrap().iter().all(|j| j["client"] == "token:000000000003"));
    assert!(list["next_page_token"].is_string(), "more than a page of that client's jobs");
    println!("slowest dashboard call over {JOBS} jobs: {slowest:?}");
    assert!(slowest < Duration::from_millis(250), "a dashboard call took {slowest:?}");
    h.stop();
}
