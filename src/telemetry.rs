//! Logs (tracing, text or JSON) and Prometheus metrics.
//!
//! Every metric family is registered, and every bounded label value initialised, when the
//! daemon starts: a scrape before the first job already shows queue depth 0 per priority,
//! 0 jobs per outcome and empty stage histograms. Beside the `mcdenoise_*` families: the
//! standard `process_*` metrics (CPU, memory, file descriptors, threads, start time) read
//! from /proc at each scrape, and `mcdenoise_build_info`.

use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Mutex;

use prometheus_client::encoding::text::encode;
use prometheus_client::metrics::counter::Counter;
use prometheus_client::metrics::family::Family;
use prometheus_client::metrics::gauge::Gauge;
use prometheus_client::metrics::histogram::{exponential_buckets, Histogram};
use prometheus_client::registry::Registry;
use tracing_subscriber::filter::{EnvFilter, LevelFilter, Targets};
use tracing_subscriber::layer::SubscriberExt;
use tracing_subscriber::util::SubscriberInitExt;
use tracing_subscriber::Layer;

use crate::jobs::record::Priority;

/// Log line format.
#[derive(clap::ValueEnum, Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum LogFormat {
    /// Human-readable lines.
    #[default]
    Text,
    /// One JSON object per line, with the span fields (e.g. `job_id`).
    Json,
}

/// Installs the global tracing subscriber, writing to stderr. `filter` uses the
/// `RUST_LOG` syntax (e.g. `info,mcdenoise=debug`). With a `tracer`, the daemon's own
/// spans (info level and above, whatever the log filter) are also exported as
/// OpenTelemetry spans ([`crate::otlp`]). Calling it twice is harmless.
pub fn init_logging(format: LogFormat, filter: &str, tracer: Option<opentelemetry_sdk::trace::Tracer>) {
    let filter = EnvFilter::try_new(filter).unwrap_or_else(|_| EnvFilter::new("info"));
    let ansi = std::io::IsTerminal::is_terminal(&std::io::stderr());
    let fmt = tracing_subscriber::fmt::layer().with_writer(std::io::stderr).with_ansi(ansi);
    let fmt = match format {
        LogFormat::Text => fmt.boxed(),
        LogFormat::Json => fmt.json().flatten_event(true).with_current_span(true).with_span_list(false).boxed(),
    };
    let spans = tracer.map(|tracer| {
        let ours = Targets::new().with_target("mcdenoise", LevelFilter::INFO);
        tracing_opentelemetry::layer().with_tracer(tracer).with_filter(ours)
    });
    let _ = tracing_subscriber::registry().with(fmt.with_filter(filter)).with(spans).try_init();
}

type Labels = Vec<(String, String)>;

fn labels(pairs: &[(&str, &str)]) -> Labels {
    pairs.iter().map(|(k, v)| (k.to_string(), v.to_string())).collect()
}

/// Stages timed per job (`mcdenoise_stage_duration_seconds{stage}`).
pub const STAGES: [&str; 7] = ["queue", "decode", "preprocess", "inference", "reconstruction", "encode", "total"];
/// Terminal outcomes (`mcdenoise_jobs_finished_total{outcome}`).
pub const OUTCOMES: [&str; 3] = ["succeeded", "failed", "cancelled"];
/// Why a submission was refused (`mcdenoise_jobs_rejected_total{reason}`).
pub const REJECTIONS: [&str; 10] = [
    "queue_full",
    "client_limit",
    "invalid",
    "too_large",
    "timeout",
    "unavailable",
    "storage_full",
    "storage_unavailable",
    "unauthenticated",
    "other",
];
pub const TRANSPORTS: [&str; 2] = ["http", "grpc"];

/// The daemon's Prometheus metrics.
pub struct Telemetry {
    registry: Mutex<Registry>,
    queue_depth: Family<Labels, Gauge>,
    jobs_submitted: Family<Labels, Counter>,
    jobs_finished: Family<Labels, Counter>,
    jobs_rejected: Family<Labels, Counter>,
    jobs_interrupted: Counter,
    jobs_in_flight: Gauge,
    uploads_in_progress: Gauge,
    connections: Family<Labels, Gauge>,
    connections_refused: Family<Labels, Counter>,
    stage_seconds: Family<Labels, Histogram, fn() -> Histogram>,
    bytes_received: Family<Labels, Counter>,
    bytes_sent: Family<Labels, Counter>,
    http_requests: Family<Labels, Counter>,
    grpc_requests: Family<Labels, Counter>,
    model_info: Family<Labels, Gauge>,
    ready: Gauge,
    workers_ready: Gauge,
    workers: Gauge,
    queue_capacity: Gauge,
    shared_queue_messages: Gauge,
    nats_connected: Gauge,
    tiles: Counter,
    sanitized: Counter,
    fireflies: Counter,
    pixels: Counter,
    storage_free_bytes: Gauge,
    storage_healthy: Gauge,
    storage_errors: Family<Labels, Counter>,
    storage_quarantined: Counter,
    storage_retries: Counter,
    last_scrape_len: AtomicU64,
}

/// Kinds of storage errors (`mcdenoise_storage_errors_total{kind}`).
const STORAGE_ERRORS: [&str; 3] = ["full", "unavailable", "moved"];

fn stage_histogram() -> Histogram {
    // 1 ms to ~33 min.
    Histogram::new(exponential_buckets(0.001, 2.0, 22))
}

impl Default for Telemetry {
    fn default() -> Self {
        Self::new()
    }
}

impl Telemetry {
    pub fn new() -> Telemetry {
        let mut root = Registry::default();
        let registry = root.sub_registry_with_prefix("mcdenoise");
        let t = Telemetry {
            registry: Mutex::new(Registry::default()),
            queue_depth: Family::default(),
            jobs_submitted: Family::default(),
            jobs_finished: Family::default(),
            jobs_rejected: Family::default(),
            jobs_interrupted: Counter::default(),
            jobs_in_flight: Gauge::default(),
            uploads_in_progress: Gauge::default(),
            connections: Family::default(),
            connections_refused: Family::default(),
            stage_seconds: Family::new_with_constructor(stage_histogram),
            bytes_received: Family::default(),
            bytes_sent: Family::default(),
            http_requests: Family::default(),
            grpc_requests: Family::default(),
            model_info: Family::default(),
            ready: Gauge::default(),
            workers_ready: Gauge::default(),
            workers: Gauge::default(),
            queue_capacity: Gauge::default(),
            shared_queue_messages: Gauge::default(),
            nats_connected: Gauge::default(),
            tiles: Counter::default(),
            sanitized: Counter::default(),
            fireflies: Counter::default(),
            pixels: Counter::default(),
            storage_free_bytes: Gauge::default(),
            storage_healthy: Gauge::default(),
            storage_errors: Family::default(),
            storage_quarantined: Counter::default(),
            storage_retries: Counter::default(),
            last_scrape_len: AtomicU64::new(0),
        };
        registry.register("queue_depth", "Jobs waiting in the queue, by priority class", t.queue_depth.clone());
        registry.register("queue_capacity", "Largest number of queued jobs admitted", t.queue_capacity.clone());
        registry.register(
            "shared_queue_messages",
            "Shared mode: job messages in the JetStream work queue (waiting or running), read from JetStream; \
             the same on every replica (0 in embedded mode)",
            t.shared_queue_messages.clone(),
        );
        registry.register(
            "nats_connected",
            "Shared mode: 1 while this replica is connected to NATS (0 in embedded mode)",
            t.nats_connected.clone(),
        );
        registry.register("jobs_submitted", "Jobs accepted, by transport", t.jobs_submitted.clone());
        registry.register("jobs_finished", "Jobs that reached a terminal state, by outcome", t.jobs_finished.clone());
        registry.register("jobs_rejected", "Submissions refused, by reason", t.jobs_rejected.clone());
        registry.register(
            "jobs_interrupted",
            "Running jobs put back in the queue (shutdown deadline or restart after a crash)",
            t.jobs_interrupted.clone(),
        );
        registry.register("jobs_in_flight", "Jobs being denoised now", t.jobs_in_flight.clone());
        registry.register(
            "uploads_in_progress",
            "Submissions whose frame is being received (each holds a place in the queue capacity)",
            t.uploads_in_progress.clone(),
        );
        registry.register(
            "connections",
            "Open connections on the API listeners (HTTP and gRPC)",
            t.connections.clone(),
        );
        registry.register(
            "connections_refused",
            "Connections closed at once because too many were open, by listener and cap (total, per_peer)",
            t.connections_refused.clone(),
        );
        registry.register(
            "stage_duration_seconds",
            "Time per job and stage (queue wait, decode, preprocess, inference, reconstruction, encode, total)",
            t.stage_seconds.clone(),
        );
        registry.register("received_bytes", "Bytes of frames received, by transport", t.bytes_received.clone());
        registry.register("sent_bytes", "Bytes of results sent, by transport", t.bytes_sent.clone());
        registry.register("http_requests", "HTTP requests, by route and status", t.http_requests.clone());
        registry.register("grpc_requests", "gRPC calls, by method and code", t.grpc_requests.clone());
        registry.register(
            "model_info",
            "Loaded networks (value 1): variant, component, architecture, sha256",
            t.model_info.clone(),
        );
        registry.register(
            "ready",
            "1 when models are loaded and warmed up and the daemon is not draining",
            t.ready.clone(),
        );
        registry.register("workers", "Configured workers", t.workers.clone());
        registry.register("workers_ready", "Workers with loaded, warmed-up models", t.workers_ready.clone());
        registry.register("tiles", "Tiles denoised", t.tiles.clone());
        registry.register("pixels", "Pixels of succeeded jobs", t.pixels.clone());
        registry.register("sanitized_samples", "Non-finite input samples replaced by 0", t.sanitized.clone());
        registry.register(
            "firefly_samples",
            "Input samples (pixel x component) clamped by the firefly handling",
            t.fireflies.clone(),
        );

        registry.register(
            "storage_free_bytes",
            "Bytes available to the daemon on the data directory's file system",
            t.storage_free_bytes.clone(),
        );
        registry.register(
            "storage_healthy",
            "1 while the data directory is the one opened, writable and above the free-space floor",
            t.storage_healthy.clone(),
        );
        registry.register(
            "storage_errors",
            "Storage faults seen by the health check or by a write, by kind (full, unavailable, moved)",
            t.storage_errors.clone(),
        );
        registry.register(
            "storage_quarantined",
            "Job directories and records that recovery could not account for, moved to quarantine/",
            t.storage_quarantined.clone(),
        );
        registry.register(
            "storage_retries",
            "Runs put back in the queue because their input or result could not be read or written",
            t.storage_retries.clone(),
        );
        for k in STORAGE_ERRORS {
            let _ = t.storage_errors.get_or_create(&labels(&[("kind", k)]));
        }

        let build = Family::<Labels, Gauge>::default();
        build
            .get_or_create(&labels(&[
                ("version", env!("CARGO_PKG_VERSION")),
                ("onnxruntime", crate::engine::runtime::ORT_VERSION),
                ("target", std::env::consts::ARCH),
            ]))
            .set(1);
        registry.register("build_info", "The daemon's version and the ONNX Runtime it is built for", build);
        root.register_collector(Box::new(ProcessCollector::new()));

        for p in Priority::ALL {
            t.queue_depth.get_or_create(&labels(&[("priority", p.name())])).set(0);
        }
        for o in OUTCOMES {
            let _ = t.jobs_finished.get_or_create(&labels(&[("outcome", o)]));
        }
        for r in REJECTIONS {
            let _ = t.jobs_rejected.get_or_create(&labels(&[("reason", r)]));
        }
        for tr in TRANSPORTS {
            let _ = t.jobs_submitted.get_or_create(&labels(&[("transport", tr)]));
            let _ = t.bytes_received.get_or_create(&labels(&[("transport", tr)]));
            let _ = t.bytes_sent.get_or_create(&labels(&[("transport", tr)]));
        }
        for s in STAGES {
            let _ = t.stage_seconds.get_or_create(&labels(&[("stage", s)]));
        }
        for l in ["api", "probe"] {
            t.connections.get_or_create(&labels(&[("listener", l)])).set(0);
            for r in ["total", "per_peer"] {
                let _ = t.connections_refused.get_or_create(&labels(&[("listener", l), ("reason", r)]));
            }
        }
        *t.registry.lock().unwrap() = root;
        t
    }

    /// The Prometheus text exposition (OpenMetrics text format).
    pub fn render(&self) -> String {
        let mut out = String::with_capacity(self.last_scrape_len.load(Ordering::Relaxed) as usize + 1024);
        encode(&mut out, &self.registry.lock().expect("metrics registry lock")).expect("writing to a String");
        self.last_scrape_len.store(out.len() as u64, Ordering::Relaxed);
        out
    }

    pub fn set_queue_depth(&self, priority: Priority, depth: usize) {
        self.queue_depth.get_or_create(&labels(&[("priority", priority.name())])).set(depth as i64);
    }

    pub fn set_shared_queue(&self, messages: u64, connected: bool) {
        self.shared_queue_messages.set(messages as i64);
        self.nats_connected.set(connected as i64);
    }

    pub fn set_queue_capacity(&self, capacity: usize) {
        self.queue_capacity.set(capacity as i64);
    }

    pub fn job_submitted(&self, transport: &str) {
        self.jobs_submitted.get_or_create(&labels(&[("transport", transport)])).inc();
    }

    pub fn job_finished(&self, outcome: &str) {
        self.jobs_finished.get_or_create(&labels(&[("outcome", outcome)])).inc();
    }

    pub fn job_rejected(&self, reason: &str) {
        self.jobs_rejected.get_or_create(&labels(&[("reason", reason)])).inc();
    }

    pub fn storage_error(&self, kind: &str) {
        self.storage_errors.get_or_create(&labels(&[("kind", kind)])).inc();
    }

    pub fn storage_quarantined(&self) {
        self.storage_quarantined.inc();
    }

    pub fn storage_retry(&self) {
        self.storage_retries.inc();
    }

    pub fn set_storage(&self, healthy: bool, free_bytes: Option<u64>) {
        self.storage_healthy.set(i64::from(healthy));
        if let Some(b) = free_bytes {
            self.storage_free_bytes.set(b.min(i64::MAX as u64) as i64);
        }
    }

    pub fn job_interrupted(&self) {
        self.jobs_interrupted.inc();
    }

    pub fn set_in_flight(&self, n: usize) {
        self.jobs_in_flight.set(n as i64);
    }

    pub fn set_uploads(&self, n: usize) {
        self.uploads_in_progress.set(n as i64);
    }

    pub fn set_connections(&self, listener: &str, n: usize) {
        self.connections.get_or_create(&labels(&[("listener", listener)])).set(n as i64);
    }

    pub fn connection_refused(&self, listener: &str, reason: &str) {
        self.connections_refused.get_or_create(&labels(&[("listener", listener), ("reason", reason)])).inc();
    }

    pub fn observe_stage(&self, stage: &str, ms: f64) {
        self.stage_seconds.get_or_create(&labels(&[("stage", stage)])).observe(ms / 1e3);
    }

    pub fn bytes_received(&self, transport: &str, n: u64) {
        self.bytes_received.get_or_create(&labels(&[("transport", transport)])).inc_by(n);
    }

    pub fn bytes_sent(&self, transport: &str, n: u64) {
        self.bytes_sent.get_or_create(&labels(&[("transport", transport)])).inc_by(n);
    }

    /// `route` must be a matched route template (bounded cardinality), never a raw path.
    pub fn http_request(&self, route: &str, status: u16) {
        self.http_requests.get_or_create(&labels(&[("route", route), ("status", &status.to_string())])).inc();
    }

    pub fn grpc_request(&self, method: &str, code: &str) {
        self.grpc_requests.get_or_create(&labels(&[("method", method), ("code", code)])).inc();
    }

    pub fn model_loaded(&self, variant: &str, component: &str, architecture: &str, sha256: &str) {
        self.model_info
            .get_or_create(&labels(&[
                ("variant", variant),
                ("component", component),
                ("architecture", architecture),
                ("sha256", sha256),
            ]))
            .set(1);
    }

    pub fn set_ready(&self, ready: bool) {
        self.ready.set(i64::from(ready));
    }

    pub fn set_workers(&self, configured: usize, ready: usize) {
        self.workers.set(configured as i64);
        self.workers_ready.set(ready as i64);
    }

    pub fn tile_done(&self) {
        self.tiles.inc();
    }

    pub fn job_output(&self, pixels: u64, sanitized: u64) {
        self.pixels.inc_by(pixels);
        self.sanitized.inc_by(sanitized);
    }

    pub fn fireflies_handled(&self, samples: u64) {
        self.fireflies.inc_by(samples);
    }
}

/// The standard `process_*` metrics of this process, read from /proc at each scrape
/// (Linux; elsewhere only the start time). Written here rather than taken from a crate:
/// the reading is a few lines, and the crates that do it bring a /proc parser of their own.
#[derive(Debug)]
struct ProcessCollector {
    start_time: f64,
}

impl ProcessCollector {
    fn new() -> ProcessCollector {
        let now = std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).unwrap_or_default();
        ProcessCollector { start_time: now.as_secs_f64() }
    }
}

/// From /proc/self/stat: CPU seconds (user + system), threads, virtual and resident bytes.
fn proc_stat() -> Option<(f64, i64, i64, i64)> {
    let text = std::fs::read_to_string("/proc/self/stat").ok()?;
    // The fields after the command name (which may hold spaces), from field 3 (`state`).
    let fields: Vec<&str> = text.get(text.rfind(')')? + 1..)?.split_whitespace().collect();
    let field = |n: usize| fields.get(n - 3)?.parse::<i64>().ok();
    let ticks = rustix::param::clock_ticks_per_second() as f64;
    let cpu = (field(14)? + field(15)?) as f64 / ticks;
    let page = rustix::param::page_size() as i64;
    Some((cpu, field(20)?, field(23)?, field(24)? * page))
}

impl prometheus_client::collector::Collector for ProcessCollector {
    fn encode(&self, mut encoder: prometheus_client::encoding::DescriptorEncoder) -> std::fmt::Result {
        use prometheus_client::encoding::EncodeMetric;
        use prometheus_client::metrics::counter::ConstCounter;
        use prometheus_client::metrics::gauge::ConstGauge;
        use prometheus_client::registry::Unit;

        fn gauge<T: prometheus_client::encoding::EncodeGaugeValue + Copy>(
            encoder: &mut prometheus_client::encoding::DescriptorEncoder,
            name: &str,
            help: &str,
            unit: Option<&Unit>,
            value: T,
        ) -> std::fmt::Result {
            let g = ConstGauge::new(value);
            g.encode(encoder.encode_descriptor(name, help, unit, g.metric_type())?)
        }
        gauge(
            &mut encoder,
            "process_start_time",
            "Start time since the Unix epoch",
            Some(&Unit::Seconds),
            self.start_time,
        )?;
        if let Some((cpu, threads, virt, rss)) = proc_stat() {
            let c = ConstCounter::new(cpu);
            c.encode(encoder.encode_descriptor(
                "process_cpu",
                "User and system CPU time spent",
                Some(&Unit::Seconds),
                c.metric_type(),
            )?)?;
            gauge(&mut encoder, "process_threads", "OS threads", None, threads)?;
            gauge(&mut encoder, "process_virtual_memory", "Virtual memory size", Some(&Unit::Bytes), virt)?;
            gauge(&mut encoder, "process_resident_memory", "Resident memory size", Some(&Unit::Bytes), rss)?;
        }
        if let Ok(dir) = std::fs::read_dir("/proc/self/fd") {
            gauge(&mut encoder, "process_open_fds", "Open file descriptors", None, dir.count() as i64)?;
        }
        if let Ok(limit) = rustix::process::getrlimit(rustix::process::Resource::Nofile).current.ok_or(()) {
            gauge(&mut encoder, "process_max_fds", "Open file descriptor limit", None, limit as i64)?;
        }
        Ok(())
    }
}
