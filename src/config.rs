//! Configuration of `mcdenoise serve`: flags, environment variables and an optional TOML
//! file.
//!
//! Precedence, highest first: command-line flag, environment variable (named on each
//! field), the file given by `--config` / `MCDENOISE_CONFIG`, the built-in default. The
//! file's keys are the long flag names (`queue-capacity = 64` or `queue_capacity = 64`);
//! unknown keys are an error.

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::time::Duration;

use anyhow::{bail, Context};
use clap::{Args, Command};

use crate::engine::variance::VarianceCheck;
use crate::engine::{AlbedoPrefilter, Fireflies, FireflyMode};
use crate::frame::presets::{ChannelMap, ChannelMapSpec};
use crate::frame::{ChannelMaps, Limits};
use crate::telemetry::LogFormat;

fn parse_duration(s: &str) -> Result<Duration, String> {
    humantime::parse_duration(s).map_err(|e| format!("{e} (examples: 30s, 5m, 24h)"))
}

fn parse_firefly_mode(s: &str) -> Result<FireflyMode, String> {
    s.parse()
}

fn parse_firefly_strength(s: &str) -> Result<f32, String> {
    let v: f32 = s.parse().map_err(|e| format!("{e} (a number, e.g. 1 or 0.5)"))?;
    Fireflies { mode: FireflyMode::Auto, strength: v }.validate().map(|f| f.strength)
}

fn parse_albedo_prefilter(s: &str) -> Result<AlbedoPrefilter, String> {
    s.parse()
}

/// Albedo prefiltering (src/engine/albedo.rs), shared by `run`, `preprocess` and `serve`.
#[derive(Args, Debug, Clone, Copy)]
pub struct AlbedoArgs {
    /// The albedo's noise before the networks: `on` (the default) averages it away where
    /// the frame's albedo variance says it is noise (non-local means), which the diffuse
    /// remodulation would otherwise put back into the output; `off` uses the albedo as the
    /// file gives it.
    #[arg(long, env = "MCDENOISE_ALBEDO_PREFILTER", default_value = "on", value_parser = parse_albedo_prefilter)]
    pub albedo_prefilter: AlbedoPrefilter,
}

fn parse_variance_check(s: &str) -> Result<VarianceCheck, String> {
    s.parse()
}

/// The variances' scale checked against the image's noise (src/engine/variance.rs), shared
/// by `run`, `preprocess` and `serve`.
#[derive(Args, Debug, Clone, Copy)]
pub struct VarianceArgs {
    /// The variances' scale, when they are far larger than the noise the image shows (a
    /// renderer that writes the samples' variance instead of the variance of the pixel's
    /// mean): `warn` (the default) says so in the result's warnings, `auto` also scales every
    /// variance buffer down to match, `off` does not measure.
    #[arg(long, env = "MCDENOISE_VARIANCE_CHECK", default_value = "warn", value_parser = parse_variance_check)]
    pub variance_check: VarianceCheck,
}

/// Firefly handling (docs/fireflies.md), shared by `run`, `preprocess` and `serve` (where
/// it is the default of jobs that do not set their own).
#[derive(Args, Debug, Clone, Copy)]
pub struct FireflyArgs {
    /// Outlier handling before the networks: `auto` clamps isolated, very bright samples
    /// (fireflies) to a bound from their neighbourhood; `off` leaves the frame as it is.
    #[arg(long, env = "MCDENOISE_FIREFLIES", default_value = "auto", value_parser = parse_firefly_mode)]
    pub fireflies: FireflyMode,
    /// Strength of the firefly handling, 0.1 to 10: the bound above the neighbourhood's
    /// median (in log units) is divided by it, so 2 clamps more and 0.5 less.
    #[arg(long, env = "MCDENOISE_FIREFLY_STRENGTH", default_value = "1", value_parser = parse_firefly_strength)]
    pub firefly_strength: f32,
}

impl FireflyArgs {
    pub fn settings(&self) -> Fireflies {
        Fireflies { mode: self.fireflies, strength: self.firefly_strength }
    }
}

/// A bearer token; `Debug` never prints it.
#[derive(Clone, PartialEq, Eq)]
pub struct Secret(pub String);

impl std::fmt::Debug for Secret {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("\"<redacted>\"")
    }
}

impl std::str::FromStr for Secret {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        if s.trim().is_empty() {
            return Err("an auth token cannot be empty".into());
        }
        Ok(Secret(s.to_string()))
    }
}

/// `mcdenoise serve`: the denoising daemon (HTTP and gRPC job API).
#[derive(clap::Parser, Debug, Clone)]
#[command(args_override_self = true)]
pub struct ServeArgs {
    /// TOML file with defaults for any of these options (keys are the long flag names).
    #[arg(long, env = "MCDENOISE_CONFIG")]
    pub config: Option<PathBuf>,

    // --- Listeners -----------------------------------------------------------------
    /// Address of the HTTP API (JSON under /v1, /livez, /readyz, /metrics).
    #[arg(long, env = "MCDENOISE_HTTP", default_value = "0.0.0.0:8080", help_heading = "Listeners")]
    pub http: SocketAddr,
    /// Address of the gRPC API (mcdenoise.v1.Denoiser, grpc.health.v1, reflection).
    #[arg(long, env = "MCDENOISE_GRPC", default_value = "0.0.0.0:50051", help_heading = "Listeners")]
    pub grpc: SocketAddr,
    /// Optional address of a probe listener: /livez, /readyz and /metrics only, plain
    /// HTTP, with connection caps of its own, so that probes keep answering while the API
    /// ports are flooded.
    #[arg(long, env = "MCDENOISE_PROBE_HTTP", help_heading = "Listeners")]
    pub probe_http: Option<SocketAddr>,

    // --- Storage -------------------------------------------------------------------
    /// Where jobs are kept: `embedded` (the data directory: one daemon) or
    /// `nats://HOST:PORT[,nats://HOST2:PORT...]` (NATS JetStream, shared by every replica
    /// given the same servers and --nats-prefix; docs/deploy.md, scale-out). Credentials may
    /// be in the URL (`nats://user:password@host:4222`).
    #[arg(long, env = "MCDENOISE_STORE", default_value = "embedded", help_heading = "Storage")]
    pub store: String,
    /// Shared mode: replicas of the JetStream stream, buckets and object store (the number
    /// of NATS servers in a cluster, usually 3).
    #[arg(long, env = "MCDENOISE_NATS_REPLICAS", default_value_t = 1, help_heading = "Storage")]
    pub nats_replicas: usize,
    /// Shared mode: how long a running job may go without a heartbeat (sent as its tiles
    /// progress) before JetStream gives it to another replica.
    #[arg(long, env = "MCDENOISE_NATS_ACK_WAIT", default_value = "30s", value_parser = parse_duration, help_heading = "Storage")]
    pub nats_ack_wait: Duration,
    /// Shared mode: prefix of the stream, bucket and subject names (replicas with the same
    /// prefix share their jobs).
    #[arg(long, env = "MCDENOISE_NATS_PREFIX", default_value = "mcdenoise", help_heading = "Storage")]
    pub nats_prefix: String,
    /// Directory of the job store (jobs.redb and the jobs' frames and results; in shared
    /// mode a scratch cache of the files). Created if missing; only one daemon may use it
    /// at a time.
    #[arg(long, env = "MCDENOISE_DATA_DIR", default_value = "mcdenoise-data", help_heading = "Storage")]
    pub data_dir: PathBuf,
    /// How long finished jobs (and their results) are kept before they are removed.
    #[arg(long, env = "MCDENOISE_RESULT_TTL", default_value = "24h", value_parser = parse_duration, help_heading = "Storage")]
    pub result_ttl: Duration,
    /// How often expired jobs are looked for.
    #[arg(long, env = "MCDENOISE_JANITOR_INTERVAL", default_value = "60s", value_parser = parse_duration, help_heading = "Storage")]
    pub janitor_interval: Duration,
    /// Free bytes the data directory's file system must keep: below it the daemon is not
    /// ready and refuses submissions with 503 `storage_full` (docs/reliability.md).
    #[arg(long, env = "MCDENOISE_MIN_FREE_BYTES", default_value_t = 256 << 20, help_heading = "Storage")]
    pub min_free_bytes: u64,
    /// How often the data directory is checked (still the one opened, writable, above
    /// --min-free-bytes).
    #[arg(long, env = "MCDENOISE_STORAGE_CHECK_INTERVAL", default_value = "2s", value_parser = parse_duration, help_heading = "Storage")]
    pub storage_check_interval: Duration,

    // --- Models and workers ----------------------------------------------------------
    /// Directory with the model variants (`full/`, `nocov/`, ...; docs/model-contract.md).
    #[arg(long, env = "MCDENOISE_MODELS", default_value = "models", help_heading = "Models and workers")]
    pub models: PathBuf,
    /// Path of libonnxruntime.so (default: searched for; see `scripts/setup`).
    #[arg(long, env = "ORT_DYLIB_PATH", help_heading = "Models and workers")]
    pub ort_library: Option<PathBuf>,
    /// Where the networks run: `cpu` (ONNX Runtime's CPU provider), `openvino` (the CPU
    /// through OpenVINO, in bfloat16 where the CPU has it: its ONNX Runtime plugin on Intel
    /// CPUs, its runtime directly on others), `cuda` or `cuda:N` (ONNX Runtime's CUDA
    /// execution provider on GPU N; needs the GPU build of ONNX Runtime, as in the GPU
    /// image), or `auto`: CUDA where available, else `openvino` on a CPU where its bfloat16
    /// is the faster (AMX, or AVX512-BF16 on AMD) and OpenVINO is installed, else `cpu`.
    /// Workers share the device: with a GPU, `--workers` is the number of jobs on it at once.
    #[arg(long, env = "MCDENOISE_DEVICE", default_value = "auto", value_parser = crate::cli::parse_device, help_heading = "Models and workers")]
    pub device: crate::engine::Device,
    /// Where contract-v2 kernels are applied: `engine` (the engine's own code, on the CPU),
    /// `graph` (inside the network's graph, `model-recon.onnx`, on the device the networks
    /// run on), or `auto` (`graph` on a GPU where the variant has that file, else `engine`).
    #[arg(long, env = "MCDENOISE_RECONSTRUCTION", default_value = "auto", value_parser = crate::cli::parse_reconstruction, help_heading = "Models and workers")]
    pub reconstruction: crate::engine::Reconstruction,
    /// What contract-v2 networks compute in: `fp32`, `fp16` (the network in half precision,
    /// `model-recon-fp16.onnx`, its reconstruction in the graph), or `auto` (`fp16` on a GPU
    /// where the variant has that file, else `fp32`).
    #[arg(long, env = "MCDENOISE_PRECISION", default_value = "auto", value_parser = crate::cli::parse_precision, help_heading = "Models and workers")]
    pub precision: crate::engine::Precision,
    /// ONNX Runtime's I/O binding for contract-v2 networks: `on` (the region's tensors in
    /// buffers ONNX Runtime allocated once per region shape, page-locked host memory on a
    /// GPU), `off`, or `auto` (`off` for now: with several workers on a GPU the binding failed).
    #[arg(long, env = "MCDENOISE_IO_BINDING", value_enum, default_value_t, help_heading = "Models and workers")]
    pub io_binding: crate::engine::IoBinding,
    /// Workers, each with its own ONNX Runtime sessions, denoising one job at a time
    /// (default: cores / threads-per-worker, at least 1).
    #[arg(long, env = "MCDENOISE_WORKERS", help_heading = "Models and workers")]
    pub workers: Option<usize>,
    /// Threads of each worker for inference and processing (default: min(cores, 8)).
    #[arg(long, env = "MCDENOISE_THREADS_PER_WORKER", help_heading = "Models and workers")]
    pub threads_per_worker: Option<usize>,
    /// Tile side in pixels (0: whole frame at once). Smaller tiles use less memory and
    /// make cancellation and progress finer; each tile adds a halo of context.
    #[arg(long, env = "MCDENOISE_TILE", default_value_t = 256, help_heading = "Models and workers")]
    pub tile: usize,
    /// Tile side for contract-v2 (multi-scale) models, whose halo is wider (0: whole frame).
    #[arg(long, env = "MCDENOISE_TILE_V2", default_value_t = crate::engine::DEFAULT_TILE_V2, help_heading = "Models and workers")]
    pub tile_v2: usize,
    /// Largest region (a tile with its halo) the networks run on, in pixels: larger frames
    /// are cut into more, smaller tiles. Bounds a worker's working memory (about 1.3 GB per
    /// million pixels with the default network) at some speed on frames above 1080p.
    /// Default: 688128 (896 × 768); with `--device openvino` 540000 through its plugin
    /// (Intel CPUs), 576000 through its runtime (others).
    #[arg(long, env = "MCDENOISE_REGION_PIXELS", help_heading = "Models and workers")]
    pub region_pixels: Option<usize>,
    /// Default firefly handling of jobs that do not set `fireflies` / `firefly_strength`.
    #[command(flatten)]
    pub fireflies: FireflyArgs,
    #[command(flatten)]
    pub albedo: AlbedoArgs,
    #[command(flatten)]
    pub variances: VarianceArgs,

    // --- Queue and limits --------------------------------------------------------------
    /// Largest number of queued jobs (running ones excluded); beyond it submissions get
    /// 429 / RESOURCE_EXHAUSTED.
    #[arg(long, env = "MCDENOISE_QUEUE_CAPACITY", default_value_t = 256, help_heading = "Queue and limits")]
    pub queue_capacity: usize,
    /// Default deadline of a job, counted from its submission (0s: none). A job still
    /// queued or running at its deadline fails with `deadline_exceeded`.
    #[arg(long, env = "MCDENOISE_JOB_DEADLINE", default_value = "1h", value_parser = parse_duration, help_heading = "Queue and limits")]
    pub job_deadline: Duration,
    /// Largest upload (frame plus reference) in bytes; larger ones get 413 /
    /// INVALID_ARGUMENT.
    #[arg(long, env = "MCDENOISE_MAX_BODY_BYTES", default_value_t = 1 << 30, help_heading = "Queue and limits")]
    pub max_body_bytes: u64,
    /// Largest accepted frame, in pixels (checked from the EXR header).
    #[arg(long, env = "MCDENOISE_MAX_PIXELS", default_value_t = Limits::default().max_pixels, help_heading = "Queue and limits")]
    pub max_pixels: u64,

    /// Uploads one client may have in flight at once (a client is a bearer token, or an
    /// address when authentication is off).
    #[arg(long, env = "MCDENOISE_MAX_UPLOADS_PER_CLIENT", default_value_t = 8, help_heading = "Queue and limits")]
    pub max_uploads_per_client: usize,
    /// Unfinished jobs (uploading, queued or running) one client may have (default: no
    /// limit beyond the queue's).
    #[arg(long, env = "MCDENOISE_MAX_JOBS_PER_CLIENT", help_heading = "Queue and limits")]
    pub max_jobs_per_client: Option<usize>,

    // --- Security ----------------------------------------------------------------------
    /// Bearer tokens accepted on every endpoint except /livez, /readyz and gRPC health
    /// (comma-separated in the environment), with the `submit` scope: each sees only the
    /// jobs it submitted. None (and no --operator-token): no authentication.
    #[arg(
        long = "auth-token",
        env = "MCDENOISE_AUTH_TOKENS",
        value_delimiter = ',',
        hide_env_values = true,
        help_heading = "Security"
    )]
    pub auth_tokens: Vec<Secret>,
    /// Bearer tokens with the `operator` scope: every client's jobs, and /metrics (which
    /// then needs one).
    #[arg(
        long = "operator-token",
        env = "MCDENOISE_OPERATOR_TOKENS",
        value_delimiter = ',',
        hide_env_values = true,
        help_heading = "Security"
    )]
    pub operator_tokens: Vec<Secret>,
    /// PEM certificate chain: with `--tls-key`, both listeners speak TLS only (HTTPS and
    /// gRPC over TLS).
    #[arg(long, env = "MCDENOISE_TLS_CERT", requires = "tls_key", help_heading = "Security")]
    pub tls_cert: Option<PathBuf>,
    /// PEM private key of `--tls-cert`.
    #[arg(long, env = "MCDENOISE_TLS_KEY", requires = "tls_cert", help_heading = "Security")]
    pub tls_key: Option<PathBuf>,

    // --- Connections -------------------------------------------------------------------
    /// Open connections on the HTTP and gRPC API listeners together; more are closed at
    /// once. Kept 256 below the open-file limit, which is raised to its hard maximum at
    /// start.
    #[arg(long, env = "MCDENOISE_MAX_CONNECTIONS", default_value_t = 4096, value_parser = clap::value_parser!(u32).range(1..), help_heading = "Connections")]
    pub max_connections: u32,
    /// Open connections from one address (behind a proxy or NAT all its clients share
    /// one: raise it there).
    #[arg(long, env = "MCDENOISE_MAX_CONNECTIONS_PER_PEER", default_value_t = 256, value_parser = clap::value_parser!(u32).range(1..), help_heading = "Connections")]
    pub max_connections_per_peer: u32,
    /// A TLS handshake not finished by then is dropped (each runs in its connection's own
    /// task: stalled handshakes hold up no one else).
    #[arg(long, env = "MCDENOISE_TLS_HANDSHAKE_TIMEOUT", default_value = "10s", value_parser = parse_duration, help_heading = "Connections")]
    pub tls_handshake_timeout: Duration,
    /// An HTTP/1 request head not complete by then closes the connection. Counted from
    /// when the connection is ready for a request, so it also closes idle HTTP/1
    /// keep-alive connections (a new connection that never sends a byte is closed by
    /// --idle-timeout).
    #[arg(long, env = "MCDENOISE_HEADER_TIMEOUT", default_value = "30s", value_parser = parse_duration, help_heading = "Connections")]
    pub header_timeout: Duration,
    /// A connection (HTTP/1, HTTP/2 or gRPC) that reads and writes nothing for this long
    /// is asked to close (requests in flight finish), and dropped after as long again.
    #[arg(long, env = "MCDENOISE_IDLE_TIMEOUT", default_value = "60s", value_parser = parse_duration, help_heading = "Connections")]
    pub idle_timeout: Duration,
    /// HTTP/2 and gRPC connections are sent a PING this often...
    #[arg(long, env = "MCDENOISE_KEEPALIVE_INTERVAL", default_value = "30s", value_parser = parse_duration, help_heading = "Connections")]
    pub keepalive_interval: Duration,
    /// ...and closed when it is not answered within this.
    #[arg(long, env = "MCDENOISE_KEEPALIVE_TIMEOUT", default_value = "20s", value_parser = parse_duration, help_heading = "Connections")]
    pub keepalive_timeout: Duration,
    /// An upload (HTTP body or gRPC stream) that sends no byte for this long is refused
    /// with 408 / DEADLINE_EXCEEDED (`timeout`): its client slot and idempotency key are
    /// released.
    #[arg(long, env = "MCDENOISE_UPLOAD_TIMEOUT", default_value = "30s", value_parser = parse_duration, help_heading = "Connections")]
    pub upload_timeout: Duration,

    // --- Operations --------------------------------------------------------------------
    /// Log format.
    #[arg(long, env = "MCDENOISE_LOG_FORMAT", value_enum, default_value_t, help_heading = "Operations")]
    pub log_format: LogFormat,
    /// Log filter (RUST_LOG syntax, e.g. `info,ort=warn` or `debug`). ONNX Runtime's own
    /// messages come under the `ort` target.
    #[arg(long, env = "MCDENOISE_LOG", default_value = "info,ort=warn", help_heading = "Operations")]
    pub log: String,
    /// OpenTelemetry collector to send traces to over OTLP/gRPC (e.g.
    /// `http://otel-collector:4317`): a span per HTTP request and per job run, with its
    /// stages, carrying the job id (docs/api.md). Default: no traces.
    #[arg(long, env = "MCDENOISE_OTLP_ENDPOINT", help_heading = "Operations")]
    pub otlp_endpoint: Option<String>,
    /// The `service.name` of the exported traces.
    #[arg(long, env = "MCDENOISE_OTLP_SERVICE_NAME", default_value = "mcdenoise", help_heading = "Operations")]
    pub otlp_service_name: String,
    /// On SIGTERM/SIGINT: how long running jobs may take to finish. Jobs still running
    /// then are stopped between two tiles and kept queued for the next start.
    #[arg(long, env = "MCDENOISE_SHUTDOWN_TIMEOUT", default_value = "30s", value_parser = parse_duration, help_heading = "Operations")]
    pub shutdown_timeout: Duration,

    /// Renderers' AOV names, from the config file's `[channel_maps.<name>]` tables
    /// (docs/frame-layout.md); tried before the shipped presets.
    #[arg(skip)]
    pub channel_maps: Vec<ChannelMap>,

    // --- Testing hooks (hidden) ------------------------------------------------------
    /// Sleeps this long after every tile (to make jobs slow in tests).
    #[arg(long, env = "MCDENOISE_DEBUG_TILE_DELAY", value_parser = parse_duration, default_value = "0s", hide = true)]
    pub debug_tile_delay: Duration,
    /// Sleeps this long before loading models (to observe readiness in tests).
    #[arg(long, env = "MCDENOISE_DEBUG_STARTUP_DELAY", value_parser = parse_duration, default_value = "0s", hide = true)]
    pub debug_startup_delay: Duration,
    /// Shared mode: sleeps this long before applying each change another replica made (a
    /// replica whose watch lags, as under load, in tests).
    #[arg(long, env = "MCDENOISE_DEBUG_WATCH_DELAY", value_parser = parse_duration, default_value = "0s", hide = true)]
    pub debug_watch_delay: Duration,
}

fn cores() -> usize {
    std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1)
}

impl ServeArgs {
    pub fn threads_per_worker(&self) -> usize {
        self.threads_per_worker.unwrap_or_else(|| cores().min(8)).max(1)
    }

    pub fn workers(&self) -> usize {
        self.workers.unwrap_or_else(|| (cores() / self.threads_per_worker()).max(1)).max(1)
    }

    pub fn max_jobs_per_client(&self) -> usize {
        self.max_jobs_per_client.unwrap_or(usize::MAX)
    }

    /// The time limits of both listeners' connections.
    pub fn timeouts(&self) -> crate::conn::Timeouts {
        crate::conn::Timeouts {
            tls_handshake: self.tls_handshake_timeout,
            header: self.header_timeout,
            idle: self.idle_timeout,
            keepalive_interval: self.keepalive_interval,
            keepalive_timeout: self.keepalive_timeout,
        }
    }

    pub fn limits(&self) -> Limits {
        Limits { max_pixels: self.max_pixels }
    }

    /// The channel maps frames are read with: the configured ones, then the shipped presets.
    pub fn channel_maps(&self) -> ChannelMaps {
        ChannelMaps::configured(self.channel_maps.clone())
    }

    /// Checks values that clap cannot.
    pub fn validate(&self) -> anyhow::Result<()> {
        if self.queue_capacity == 0 {
            bail!("--queue-capacity must be at least 1");
        }
        if self.store != "embedded" {
            for server in self.store.split(',') {
                let server = server.trim();
                if !(server.starts_with("nats://") || server.starts_with("tls://")) || server.len() <= "nats://".len() {
                    bail!(
                        "--store must be `embedded` or a list of NATS servers (nats://HOST:PORT,...), not `{}`",
                        crate::jobs::shared::redact(server)
                    );
                }
            }
            if !(1..=5).contains(&self.nats_replicas) {
                bail!("--nats-replicas must be 1 to 5 (JetStream's limit)");
            }
            if self.nats_ack_wait < Duration::from_secs(1) {
                bail!("--nats-ack-wait must be at least 1s");
            }
            if self.nats_prefix.is_empty()
                || !self.nats_prefix.chars().all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-')
            {
                bail!("--nats-prefix must be letters, digits, `_` or `-`, not `{}`", self.nats_prefix);
            }
        }
        if self.workers == Some(0) {
            bail!("--workers must be at least 1");
        }
        if self.max_uploads_per_client == 0 || self.max_jobs_per_client == Some(0) {
            bail!("--max-uploads-per-client and --max-jobs-per-client must be at least 1");
        }
        if self.janitor_interval.is_zero() {
            bail!("--janitor-interval must be positive");
        }
        if self.storage_check_interval.is_zero() {
            bail!("--storage-check-interval must be positive");
        }
        for (flag, d) in [
            ("--tls-handshake-timeout", self.tls_handshake_timeout),
            ("--header-timeout", self.header_timeout),
            ("--idle-timeout", self.idle_timeout),
            ("--keepalive-interval", self.keepalive_interval),
            ("--keepalive-timeout", self.keepalive_timeout),
            ("--upload-timeout", self.upload_timeout),
        ] {
            if d.is_zero() {
                bail!("{flag} must be positive");
            }
        }
        Ok(())
    }

    /// The settings as logged at startup (tokens redacted).
    /// The shared store's settings; `None` in embedded mode.
    pub fn shared_store(&self) -> Option<crate::jobs::SharedConfig> {
        (self.store != "embedded").then(|| crate::jobs::SharedConfig {
            servers: self.store.clone(),
            replicas: self.nats_replicas,
            ack_wait: self.nats_ack_wait,
            prefix: self.nats_prefix.clone(),
        })
    }

    pub fn summary(&self) -> serde_json::Value {
        serde_json::json!({
            "http": self.http.to_string(),
            "grpc": self.grpc.to_string(),
            "probe_http": self.probe_http.map(|a| a.to_string()),
            "max_connections": self.max_connections,
            "max_connections_per_peer": self.max_connections_per_peer,
            "data_dir": self.data_dir,
            "store": self.shared_store().map(|c| format!("jetstream {}", crate::jobs::shared::redact(&c.servers))).unwrap_or_else(|| "embedded".into()),
            "models": self.models,
            "device": self.device.to_string(),
            "reconstruction": self.reconstruction.to_string(),
            "precision": self.precision.name(),
            "io_binding": self.io_binding,
            "workers": self.workers(),
            "threads_per_worker": self.threads_per_worker(),
            "tile": self.tile,
            "tile_v2": self.tile_v2,
            "region_pixels": self.region_pixels,
            "fireflies": self.fireflies.settings(),
            "albedo_prefilter": self.albedo.albedo_prefilter,
            "variance_check": self.variances.variance_check,
            "queue_capacity": self.queue_capacity,
            "job_deadline": humantime::format_duration(self.job_deadline).to_string(),
            "result_ttl": humantime::format_duration(self.result_ttl).to_string(),
            "max_body_bytes": self.max_body_bytes,
            "min_free_bytes": self.min_free_bytes,
            "storage_check_interval": humantime::format_duration(self.storage_check_interval).to_string(),
            "max_pixels": self.max_pixels,
            "max_uploads_per_client": self.max_uploads_per_client,
            "max_jobs_per_client": self.max_jobs_per_client,
            "tls": self.tls_cert.is_some(),
            "timeouts": {
                "tls_handshake": humantime::format_duration(self.tls_handshake_timeout).to_string(),
                "header": humantime::format_duration(self.header_timeout).to_string(),
                "idle": humantime::format_duration(self.idle_timeout).to_string(),
                "keepalive_interval": humantime::format_duration(self.keepalive_interval).to_string(),
                "keepalive_timeout": humantime::format_duration(self.keepalive_timeout).to_string(),
                "upload": humantime::format_duration(self.upload_timeout).to_string(),
            },
            "auth": if self.auth_tokens.is_empty() && self.operator_tokens.is_empty() {
                "off".to_string()
            } else {
                format!("{} submit token(s), {} operator token(s)", self.auth_tokens.len(), self.operator_tokens.len())
            },
            "channel_maps": self.channel_maps().names(),
            "log_format": self.log_format,
            "otlp_endpoint": self.otlp_endpoint,
            "shutdown_timeout": humantime::format_duration(self.shutdown_timeout).to_string(),
        })
    }
}

/// The `[channel_maps.<name>]` tables of a config file; the message names the file and
/// the map.
fn channel_maps_of(value: toml::Value, path: &Path) -> anyhow::Result<Vec<ChannelMap>> {
    let toml::Value::Table(maps) = value else {
        bail!("config file {}, key channel_maps: a table of maps ([channel_maps.<name>])", path.display());
    };
    maps.into_iter()
        .map(|(name, spec)| {
            let map = spec
                .try_into()
                .map_err(|e: toml::de::Error| e.message().trim().to_string())
                .and_then(|spec: ChannelMapSpec| ChannelMap::new(&name, spec));
            map.map_err(|e| anyhow::anyhow!("config file {}, channel_maps.{name}: {e}", path.display()))
        })
        .collect()
}

/// Reads a TOML config file and sets its values as the defaults of `cmd`'s arguments (so
/// flags and environment variables still win). `cmd` is the `serve` command. Returns the
/// command and the file's channel maps.
pub fn apply_config_file(mut cmd: Command, path: &Path) -> anyhow::Result<(Command, Vec<ChannelMap>)> {
    let text = std::fs::read_to_string(path).with_context(|| format!("cannot read config file {}", path.display()))?;
    let mut table: toml::Table = text.parse().with_context(|| format!("{}: not valid TOML", path.display()))?;
    let maps = match table.remove("channel_maps").or_else(|| table.remove("channel-maps")) {
        Some(value) => channel_maps_of(value, path)?,
        None => Vec::new(),
    };
    let ids: Vec<String> = cmd.get_arguments().map(|a| a.get_id().to_string()).collect();
    let mut unknown = Vec::new();
    for (key, value) in table {
        let mut id = key.replace('-', "_");
        if id == "auth_token" || id == "operator_token" {
            id.push('s');
        }
        if !ids.contains(&id) || id == "config" {
            unknown.push(key);
            continue;
        }
        let values: Vec<String> = match value {
            toml::Value::Array(items) => items.iter().map(scalar).collect::<anyhow::Result<_>>(),
            other => scalar(&other).map(|v| vec![v]),
        }
        .with_context(|| format!("config file {}, key {key}", path.display()))?;
        // Each value is checked here, so that an error names the file and the key (clap
        // would report it as a bad default of the flag).
        let arg = cmd.get_arguments().find(|a| a.get_id() == id.as_str()).expect("a known argument");
        let long = arg.get_long().filter(|_| arg.get_action().takes_values());
        for v in values.iter().filter(|_| long.is_some()) {
            let flag = format!("--{}", long.unwrap_or_default());
            let check = Command::new("config").no_binary_name(true).arg(arg.clone().env(None::<&str>).required(false));
            if let Err(e) = check.try_get_matches_from([flag.as_str(), v.as_str()]) {
                let why = e.to_string();
                let why = why.lines().next().unwrap_or("").trim_start_matches("error: ").to_string();
                bail!("config file {}, key {key}: {why}", path.display());
            }
        }
        // clap keeps `&'static str` defaults; a config file is read once per process.
        let leaked: Vec<&'static str> = values.into_iter().map(|v| &*Box::leak(v.into_boxed_str())).collect();
        cmd = cmd.mut_arg(id.as_str(), |a| a.default_values(leaked));
    }
    if !unknown.is_empty() {
        bail!(
            "{}: unknown keys: {} (keys are the long flag names of `mcdenoise serve`, and channel_maps)",
            path.display(),
            unknown.join(", ")
        );
    }
    Ok((cmd, maps))
}

fn scalar(v: &toml::Value) -> anyhow::Result<String> {
    Ok(match v {
        toml::Value::String(s) => s.clone(),
        toml::Value::Integer(i) => i.to_string(),
        toml::Value::Float(f) => f.to_string(),
        toml::Value::Boolean(b) => b.to_string(),
        other => bail!("unsupported value `{other:?}` (a string, number or boolean, or an array of them)"),
    })
}

/// Parses `serve` arguments from `argv` (without the program or subcommand name in front:
/// `argv[0]` is taken as the command name), applying the config file if one is named.
pub fn parse_serve_args<I, T>(argv: I) -> anyhow::Result<ServeArgs>
where
    I: IntoIterator<Item = T>,
    T: Into<std::ffi::OsString> + Clone,
{
    use clap::{CommandFactory, FromArgMatches};
    let argv: Vec<std::ffi::OsString> = argv.into_iter().map(Into::into).collect();
    let first = ServeArgs::try_parse_from_args(&argv)?;
    let args = match &first.config {
        None => first,
        Some(path) => {
            let (cmd, maps) = apply_config_file(ServeArgs::command(), path)?;
            let matches = cmd.try_get_matches_from(&argv)?;
            ServeArgs { channel_maps: maps, ..ServeArgs::from_arg_matches(&matches)? }
        }
    };
    args.validate()?;
    Ok(args)
}

impl ServeArgs {
    fn try_parse_from_args(argv: &[std::ffi::OsString]) -> Result<ServeArgs, clap::Error> {
        <ServeArgs as clap::Parser>::try_parse_from(argv)
    }
}

/// Adds the `serve` options to a subcommand (used by the `mcdenoise` binary).
pub fn augment(cmd: Command) -> Command {
    <ServeArgs as Args>::augment_args(cmd)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_store_is_embedded_unless_nats_servers_are_given() {
        assert!(parse_serve_args(["serve"]).unwrap().shared_store().is_none());
        let a =
            parse_serve_args(["serve", "--store", "nats://u:pw@a:4222,nats://b:4222", "--nats-replicas", "3"]).unwrap();
        let c = a.shared_store().unwrap();
        assert_eq!(
            (c.servers.as_str(), c.replicas, c.prefix.as_str()),
            ("nats://u:pw@a:4222,nats://b:4222", 3, "mcdenoise")
        );
        assert_eq!(a.summary()["store"], "jetstream nats://***@a:4222,nats://b:4222", "no password in /v1/info");
        for (argv, names) in [
            (vec!["--store", "redis://x:6379"], "redis://x:6379"),
            (vec!["--store", "nats://a:4222", "--nats-replicas", "7"], "--nats-replicas"),
            (vec!["--store", "nats://a:4222", "--nats-prefix", "a.b"], "a.b"),
        ] {
            let e = parse_serve_args(["serve"].into_iter().chain(argv)).unwrap_err().to_string();
            assert!(e.contains(names), "{e}");
        }
        let e = parse_serve_args(["serve", "--store", "nats://u:secret@a:4222,bad"]).unwrap_err().to_string();
        assert!(e.contains("`bad`") && !e.contains("secret"), "{e}");
    }

    #[test]
    fn defaults_are_documented_values() {
        let a = parse_serve_args(["serve"]).unwrap();
        assert_eq!(a.http.to_string(), "0.0.0.0:8080");
        assert_eq!(a.grpc.to_string(), "0.0.0.0:50051");
        assert_eq!(a.queue_capacity, 256);
        assert_eq!(a.result_ttl, Duration::from_secs(86400));
        assert!(a.auth_tokens.is_empty());
        assert_eq!(a.fireflies.settings(), Fireflies::default());
        // Timeouts a farm can live with: none above a minute.
        for d in [a.tls_handshake_timeout, a.header_timeout, a.idle_timeout, a.keepalive_interval, a.upload_timeout] {
            assert!(!d.is_zero() && d <= Duration::from_secs(60), "{d:?}");
        }
    }

    #[test]
    fn the_example_config_file_is_valid_and_says_the_defaults() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("deploy/mcdenoise.example.toml");
        let a = parse_serve_args(["serve", "--config", path.to_str().unwrap()]).unwrap();
        let d = parse_serve_args(["serve"]).unwrap();
        assert_eq!((a.http, a.grpc, a.queue_capacity, a.result_ttl), (d.http, d.grpc, d.queue_capacity, d.result_ttl));
        assert_eq!(
            (a.tile, a.tile_v2, a.region_pixels, a.max_pixels, a.max_body_bytes),
            (d.tile, d.tile_v2, d.region_pixels, d.max_pixels, d.max_body_bytes)
        );
        assert_eq!(a.fireflies.settings(), d.fireflies.settings());
        assert_eq!(a.workers, Some(1));
        assert_eq!(a.channel_maps().names()[..2], ["studio", "arnold"]);
    }

    #[test]
    fn a_bad_config_value_names_the_file_and_the_key() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("serve.toml");
        for (text, expect) in [
            ("queue-capacity = \"abc\"\n", "key queue-capacity: invalid value 'abc' for '--queue-capacity"),
            ("workers = 1.5\n", "key workers: invalid value '1.5'"),
            ("tile = { a = 1 }\n", "key tile: unsupported value"),
        ] {
            std::fs::write(&path, text).unwrap();
            let err = format!("{:#}", parse_serve_args(["serve", "--config", path.to_str().unwrap()]).unwrap_err());
            assert!(err.contains(&format!("config file {}", path.display())) && err.contains(expect), "{err}");
            assert!(!err.contains("error:"), "{err}");
        }
    }

    #[test]
    fn fireflies_come_from_flags_and_the_config_file() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("serve.toml");
        std::fs::write(&path, "fireflies = \"off\"\nfirefly-strength = 2.5\n").unwrap();
        let p = path.to_str().unwrap();
        let a = parse_serve_args(["serve", "--config", p]).unwrap();
        assert_eq!(a.fireflies.settings(), Fireflies { mode: FireflyMode::Off, strength: 2.5 });
        let a = parse_serve_args(["serve", "--config", p, "--fireflies", "auto"]).unwrap();
        assert_eq!(a.fireflies.fireflies, FireflyMode::Auto);
        let err = parse_serve_args(["serve", "--firefly-strength", "0"]).unwrap_err();
        assert!(err.to_string().contains("0.1..=10"), "{err}");
        let err = parse_serve_args(["serve", "--fireflies", "maybe"]).unwrap_err();
        assert!(err.to_string().contains("expected auto or off"), "{err}");
    }

    #[test]
    fn config_file_sets_defaults_and_flags_win() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("serve.toml");
        std::fs::write(
            &path,
            "queue-capacity = 7\ntile = 64\nauth_token = [\"a\", \"b\"]\nresult_ttl = \"2h\"\nlog_format = \"json\"\n",
        )
        .unwrap();
        let p = path.to_str().unwrap();
        let a = parse_serve_args(["serve", "--config", p, "--tile", "32"]).unwrap();
        assert_eq!(a.queue_capacity, 7);
        assert_eq!(a.tile, 32);
        assert_eq!(a.auth_tokens, vec![Secret("a".into()), Secret("b".into())]);
        assert_eq!(a.result_ttl, Duration::from_secs(7200));
        assert_eq!(a.log_format, LogFormat::Json);
        assert!(!format!("{a:?}").contains("\"a\""), "tokens must not be printed");
    }

    #[test]
    fn channel_maps_come_from_the_config_file() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("serve.toml");
        let p = path.to_str().unwrap();
        std::fs::write(
            &path,
            "tile = 64\n[channel_maps.studio]\nrenderer = \"Studio\"\ndiffuse = \"diff\"\nalbedo = \"alb\"\n\
             normal = \"nrm\"\ndepth = \"z\"\n[channel_maps.arnold]\ndiffuse = \"diffuse\"\nalbedo = \"albedo\"\n\
             normal = \"N\"\ndepth = \"Z\"\n",
        )
        .unwrap();
        let a = parse_serve_args(["serve", "--config", p]).unwrap();
        assert_eq!(a.tile, 64);
        // Configured first; one named like a shipped preset replaces it.
        assert_eq!(a.channel_maps().names(), ["arnold", "studio", "renderman", "karma", "vray", "redshift"]);
        for (text, expect) in [
            ("[channel_maps.studio]\ndiffuse = \"d\"\n", "channel_maps.studio: channel map `studio` has no `albedo`"),
            ("[channel_maps.studio]\ndifuse = \"d\"\n", "channel_maps.studio: unknown field `difuse`"),
            ("channel_maps = 3\n", "key channel_maps: a table of maps"),
        ] {
            std::fs::write(&path, text).unwrap();
            let err = format!("{:#}", parse_serve_args(["serve", "--config", p]).unwrap_err());
            assert!(err.contains(&format!("config file {}", path.display())) && err.contains(expect), "{err}");
        }
    }

    #[test]
    fn unknown_config_keys_are_refused() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("serve.toml");
        std::fs::write(&path, "queue_capacty = 7\n").unwrap();
        let err = parse_serve_args(["serve", "--config", path.to_str().unwrap()]).unwrap_err();
        assert!(err.to_string().contains("queue_capacty"), "{err}");
    }
}
