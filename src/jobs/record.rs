//! What a job is: its options, its persisted record, and the events it emits.
//!
//! Locking: plain data; the core keeps the live copies inside its `State`.

use serde::{Deserialize, Serialize};

use crate::engine::{Fireflies, FireflyMode, FireflyReport, Variant};

/// Lifecycle: `queued → running → succeeded | failed | cancelled`. A running job that is
/// interrupted (shutdown deadline, crash) goes back to `queued` and runs again.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum JobState {
    Queued,
    Running,
    Succeeded,
    Failed,
    Cancelled,
}

impl JobState {
    pub const ALL: [JobState; 5] =
        [JobState::Queued, JobState::Running, JobState::Succeeded, JobState::Failed, JobState::Cancelled];

    pub fn name(self) -> &'static str {
        match self {
            JobState::Queued => "queued",
            JobState::Running => "running",
            JobState::Succeeded => "succeeded",
            JobState::Failed => "failed",
            JobState::Cancelled => "cancelled",
        }
    }

    pub fn parse(s: &str) -> Option<JobState> {
        JobState::ALL.into_iter().find(|v| v.name() == s)
    }

    pub fn is_terminal(self) -> bool {
        matches!(self, JobState::Succeeded | JobState::Failed | JobState::Cancelled)
    }
}

/// Priority class: higher classes are dequeued first, FIFO within a class.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Priority {
    Low,
    #[default]
    Normal,
    High,
}

impl Priority {
    pub const ALL: [Priority; 3] = [Priority::High, Priority::Normal, Priority::Low];

    pub fn name(self) -> &'static str {
        match self {
            Priority::Low => "low",
            Priority::Normal => "normal",
            Priority::High => "high",
        }
    }

    pub fn parse(s: &str) -> Option<Priority> {
        Priority::ALL.into_iter().find(|v| v.name() == s)
    }

    /// Sort key of the queue: 0 is served first.
    pub fn rank(self) -> u8 {
        match self {
            Priority::High => 0,
            Priority::Normal => 1,
            Priority::Low => 2,
        }
    }
}

impl std::str::FromStr for Priority {
    type Err = String;

    fn from_str(s: &str) -> Result<Priority, String> {
        Priority::parse(s).ok_or_else(|| format!("unknown priority `{s}` (expected high, normal or low)"))
    }
}

impl std::str::FromStr for JobState {
    type Err = String;

    fn from_str(s: &str) -> Result<JobState, String> {
        JobState::parse(s)
            .ok_or_else(|| format!("unknown state `{s}` (expected queued, running, succeeded, failed or cancelled)"))
    }
}

/// Extra layers of the result besides `R,G,B` (and the beauty's alpha, always carried).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Layer {
    /// The denoised diffuse component, `diffuse.R,G,B`.
    Diffuse,
    /// The denoised specular component, `specular.R,G,B`.
    Specular,
    /// Every other channel of the input (every AOV), unchanged; the denoised layers asked
    /// for beside it replace the input's channels of the same names.
    All,
}

impl Layer {
    pub fn name(self) -> &'static str {
        match self {
            Layer::Diffuse => "diffuse",
            Layer::Specular => "specular",
            Layer::All => "all",
        }
    }

    pub fn parse(s: &str) -> Option<Layer> {
        [Layer::Diffuse, Layer::Specular, Layer::All].into_iter().find(|v| v.name() == s)
    }
}

impl std::str::FromStr for Layer {
    type Err = String;

    fn from_str(s: &str) -> Result<Layer, String> {
        Layer::parse(s).ok_or_else(|| format!("unknown layer `{s}` (expected diffuse, specular or all)"))
    }
}

/// Largest accepted label and idempotency key, in bytes.
pub const MAX_LABEL_BYTES: usize = 256;
/// Longest accepted job deadline.
pub const MAX_DEADLINE_SECONDS: u64 = 30 * 24 * 3600;

/// What a client asks for when it submits a frame.
#[derive(Clone, Debug, Default, Serialize, Deserialize, PartialEq)]
#[serde(deny_unknown_fields, default)]
pub struct JobOptions {
    pub priority: Priority,
    pub layers: Vec<Layer>,
    pub idempotency_key: Option<String>,
    pub label: Option<String>,
    /// `None` picks `full` when the frame has covariance, else `nocov`.
    pub variant: Option<Variant>,
    /// Seconds from submission after which the job fails; `None` uses the daemon default.
    pub deadline_seconds: Option<u64>,
    /// Firefly handling (docs/fireflies.md); `None` uses the daemon default.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub fireflies: Option<FireflyMode>,
    /// Strength of the firefly handling, 0.1 to 10; `None` uses the daemon default.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub firefly_strength: Option<f32>,
    /// How renderers' AOV names are read: a channel map's name or an inline map
    /// ([`crate::frame::ChannelMaps::choose`]); `None`: every map in turn.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub channel_map: Option<String>,
}

impl JobOptions {
    /// Checks sizes and removes duplicate layers; empty strings count as absent.
    pub fn normalize(mut self) -> Result<JobOptions, String> {
        if self.channel_map.as_deref().is_some_and(|m| m.trim().is_empty() || m.trim().eq_ignore_ascii_case("auto")) {
            self.channel_map = None;
        }
        for (what, v) in [("label", &mut self.label), ("idempotency_key", &mut self.idempotency_key)] {
            if v.as_deref() == Some("") {
                *v = None;
            }
            if let Some(s) = v {
                if s.len() > MAX_LABEL_BYTES {
                    return Err(format!("{what} is {} bytes, at most {MAX_LABEL_BYTES} are accepted", s.len()));
                }
            }
        }
        let mut layers = Vec::new();
        for l in self.layers {
            if !layers.contains(&l) {
                layers.push(l);
            }
        }
        self.layers = layers;
        if self.deadline_seconds == Some(0) {
            self.deadline_seconds = None;
        }
        if let Some(s) = self.deadline_seconds.filter(|s| *s > MAX_DEADLINE_SECONDS) {
            return Err(format!("deadline_seconds is {s}, at most {MAX_DEADLINE_SECONDS} (30 days) is accepted"));
        }
        if let Some(strength) = self.firefly_strength {
            Fireflies { mode: FireflyMode::Auto, strength }.validate()?;
        }
        Ok(self)
    }

    /// The firefly handling of the job: its own options, else `default` (the daemon's).
    pub fn fireflies(&self, default: Fireflies) -> Fireflies {
        Fireflies {
            mode: self.fireflies.unwrap_or(default.mode),
            strength: self.firefly_strength.unwrap_or(default.strength),
        }
    }
}

/// Milliseconds per stage of the last run. `queue` is the wait before that run started.
#[derive(Clone, Copy, Debug, Default, Serialize, Deserialize, PartialEq)]
pub struct Timings {
    pub queue: f64,
    pub decode: f64,
    pub preprocess: f64,
    pub inference: f64,
    pub reconstruction: f64,
    pub encode: f64,
    pub total: f64,
}

/// RelMSE, DSSIM, PSNR and SMAPE of one image against the reference (see
/// [`crate::quality`]).
pub use crate::quality::Metrics as QualityMetrics;

/// Metrics of the noisy input and of the denoised output against the reference.
pub use crate::quality::Comparison as JobMetrics;

/// The firefly handling a job ran with and the samples (pixel × component) it clamped.
#[derive(Clone, Copy, Debug, Serialize, Deserialize, PartialEq)]
pub struct FireflyCounts {
    pub mode: FireflyMode,
    pub strength: f32,
    /// Samples handled, all components together.
    pub handled: u64,
    pub by_component: FireflyReport,
}

/// Non-finite samples replaced by 0 while decoding.
pub use crate::frame::Sanitized as SanitizedCounts;

/// Why a job failed. `code` is stable; `message` says what exactly.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct JobError {
    pub code: JobErrorCode,
    pub message: String,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum JobErrorCode {
    /// The frame could not be decoded or validated (names the channel or the defect).
    InvalidFrame,
    /// No loaded model fits the frame.
    NoModel,
    /// The job's deadline passed before it finished.
    DeadlineExceeded,
    /// ONNX Runtime failed.
    Inference,
    /// The job's input could not be read or its result written for a storage reason
    /// (full disk, read-only file system...) on [`MAX_STORAGE_FAILURES`] runs in a row.
    Storage,
    /// I/O or another failure on the daemon's side.
    Internal,
}

impl std::str::FromStr for JobErrorCode {
    type Err = String;

    fn from_str(s: &str) -> Result<JobErrorCode, String> {
        JobErrorCode::ALL.into_iter().find(|c| c.name() == s).ok_or_else(|| format!("unknown job error code `{s}`"))
    }
}

impl JobErrorCode {
    pub const ALL: [JobErrorCode; 6] = [
        JobErrorCode::InvalidFrame,
        JobErrorCode::NoModel,
        JobErrorCode::DeadlineExceeded,
        JobErrorCode::Inference,
        JobErrorCode::Storage,
        JobErrorCode::Internal,
    ];

    pub fn name(self) -> &'static str {
        match self {
            JobErrorCode::InvalidFrame => "invalid_frame",
            JobErrorCode::NoModel => "no_model",
            JobErrorCode::DeadlineExceeded => "deadline_exceeded",
            JobErrorCode::Inference => "inference",
            JobErrorCode::Storage => "storage",
            JobErrorCode::Internal => "internal",
        }
    }
}

/// Tiles done of the current run.
#[derive(Clone, Copy, Debug, Default, Serialize, Deserialize, PartialEq, Eq)]
pub struct Progress {
    pub tiles_done: u32,
    pub tiles_total: u32,
}

/// The persisted record of a job. Times are Unix milliseconds.
#[derive(Clone, Debug, Serialize, Deserialize, PartialEq)]
pub struct JobRecord {
    pub id: String,
    /// Admission order; FIFO within a priority class follows it, also across restarts.
    pub seq: u64,
    pub state: JobState,
    pub options: JobOptions,
    pub width: u32,
    pub height: u32,
    pub input_bytes: u64,
    pub has_reference: bool,
    pub created_at_ms: i64,
    pub started_at_ms: Option<i64>,
    pub finished_at_ms: Option<i64>,
    pub deadline_at_ms: Option<i64>,
    pub expires_at_ms: Option<i64>,
    /// Times the job was started; above 1 when a run was interrupted.
    pub attempts: u32,
    pub cancel_requested: bool,
    /// The variant that ran.
    pub variant: Option<Variant>,
    /// Progress of the run; the final value once finished.
    pub progress: Progress,
    pub timings: Option<Timings>,
    pub metrics: Option<JobMetrics>,
    pub sanitized: Option<SanitizedCounts>,
    /// Firefly handling of the run (docs/fireflies.md).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub fireflies: Option<FireflyCounts>,
    /// Variance buffers the frame lacked, taken as 0 (docs/frame-layout.md).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub missing_variances: Vec<String>,
    /// What the frame's renderer passes could only approximate (e.g. a Cycles frame without
    /// the Diffuse passes, or variances far larger than the image's noise), set
    /// once the job has run.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub warnings: Vec<String>,
    pub error: Option<JobError>,
    pub result_bytes: Option<u64>,
    /// Who submitted it (`token:<digest prefix>` or `ip:<address>`), for per-client limits.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub client: Option<String>,
    /// Runs whose input could not be read or whose result could not be written for a
    /// storage reason (full disk, read-only file system...); the job is queued again until
    /// a bound ([`MAX_STORAGE_FAILURES`]).
    #[serde(default, skip_serializing_if = "is_zero")]
    pub storage_failures: u32,
    /// The W3C `traceparent` of the submission's span, when traces are exported: the job's
    /// runs continue that trace ([`crate::otlp`]).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub trace_parent: Option<String>,
    /// Revision of the stored copy (set by the store at each write; see `jobs::store`).
    #[serde(default)]
    pub rev: u64,
}

/// Storage failures after which a job fails instead of being queued again.
pub const MAX_STORAGE_FAILURES: u32 = 5;

fn is_zero(n: &u32) -> bool {
    *n == 0
}

/// A job as clients see it: the record plus its live queue position.
#[derive(Clone, Debug, PartialEq)]
pub struct JobStatus {
    pub record: JobRecord,
    /// 1-based position among queued jobs, 0 when not queued.
    pub queue_position: u64,
}

/// What happens to a job, as streamed to watchers.
#[derive(Clone, Debug, PartialEq)]
pub enum JobEvent {
    /// Emitted first to every watcher of a queued job.
    Queued {
        status: Box<JobStatus>,
    },
    Started {
        attempt: u32,
    },
    Progress(Progress),
    /// Terminal events carry the final status (metrics, timings, error).
    Succeeded(Box<JobStatus>),
    Failed(Box<JobStatus>),
    Cancelled(Box<JobStatus>),
    /// The job was deleted while watched (it had not finished): nothing follows.
    Deleted,
}

impl JobEvent {
    pub fn name(&self) -> &'static str {
        match self {
            JobEvent::Queued { .. } => "queued",
            JobEvent::Started { .. } => "started",
            JobEvent::Progress(_) => "progress",
            JobEvent::Succeeded(_) => "succeeded",
            JobEvent::Failed(_) => "failed",
            JobEvent::Cancelled(_) => "cancelled",
            JobEvent::Deleted => "deleted",
        }
    }

    pub fn is_terminal(&self) -> bool {
        matches!(self, JobEvent::Succeeded(_) | JobEvent::Failed(_) | JobEvent::Cancelled(_) | JobEvent::Deleted)
    }

    /// The terminal event of a finished job.
    pub fn terminal(status: JobStatus) -> Option<JobEvent> {
        match status.record.state {
            JobState::Succeeded => Some(JobEvent::Succeeded(Box::new(status))),
            JobState::Failed => Some(JobEvent::Failed(Box::new(status))),
            JobState::Cancelled => Some(JobEvent::Cancelled(Box::new(status))),
            JobState::Queued | JobState::Running => None,
        }
    }
}

/// Unix time in milliseconds.
pub fn now_ms() -> i64 {
    std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map(|d| d.as_millis() as i64).unwrap_or(0)
}

/// RFC 3339 (UTC, milliseconds) of a Unix-milliseconds time.
pub fn rfc3339(ms: i64) -> String {
    let t = std::time::UNIX_EPOCH + std::time::Duration::from_millis(ms.max(0) as u64);
    humantime::format_rfc3339_millis(t).to_string()
}
