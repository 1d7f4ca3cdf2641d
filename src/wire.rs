//! The job's wire forms, typed, in one place: the HTTP/JSON view ([`JobView`], the `Job`
//! schema of `src/http/openapi.json`, checked by a test), the HTTP query-string form of the
//! options ([`OptionsQuery`]), and the conversions to and from the protobuf messages.
//!
//! The server serialises [`JobView`]; the Rust client (`mcdenoise submit`) decodes HTTP
//! answers into it and converts gRPC answers into it, so the two cannot drift apart. A
//! new job option is one edit here (query form and protobuf) besides [`JobOptions`] itself
//! and the proto file.

use serde::{Deserialize, Serialize};

use crate::engine::{FireflyMode, FireflyReport, Variant};
use crate::grpc::pb;
use crate::jobs::{
    rfc3339, FireflyCounts, JobError, JobMetrics, JobOptions, JobState, JobStatus, Layer, Priority, Progress,
    QualityMetrics, SanitizedCounts, Timings,
};

/// A job as the HTTP API shows it (`Job` in the OpenAPI document).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct JobView {
    pub id: String,
    pub state: JobState,
    pub priority: Priority,
    pub label: Option<String>,
    pub idempotency_key: Option<String>,
    /// Who submitted it (`token:<digest prefix>` or `ip:<address>`; `None` for records
    /// older than owners): what the `client` filter of a listing matches.
    #[serde(default)]
    pub client: Option<String>,
    /// 1-based, while queued.
    pub queue_position: Option<u64>,
    pub progress: Progress,
    pub width: u32,
    pub height: u32,
    pub input_bytes: u64,
    pub has_reference: bool,
    pub layers: Vec<Layer>,
    /// The variant asked for; `None` is `auto`.
    pub requested_variant: Option<Variant>,
    /// The variant that ran.
    pub variant: Option<Variant>,
    /// The firefly handling asked for; `None` is the daemon's default.
    pub requested_fireflies: Option<FireflyMode>,
    pub requested_firefly_strength: Option<f32>,
    /// The channel map asked for (a name or an inline map); `None` is `auto`.
    #[serde(default)]
    pub channel_map: Option<String>,
    /// The firefly handling the run used, and what it clamped.
    pub fireflies: Option<FireflyCounts>,
    pub attempts: u32,
    pub cancel_requested: bool,
    pub timings_ms: Option<Timings>,
    pub metrics: Option<JobMetrics>,
    pub sanitized: Option<SanitizedCounts>,
    #[serde(default)]
    pub missing_variances: Vec<String>,
    /// What the frame's renderer passes could only approximate.
    #[serde(default)]
    pub warnings: Vec<String>,
    pub error: Option<JobError>,
    pub result_bytes: Option<u64>,
    /// RFC 3339 times.
    pub created_at: String,
    pub started_at: Option<String>,
    pub finished_at: Option<String>,
    pub deadline_at: Option<String>,
    pub expires_at: Option<String>,
    pub urls: JobUrls,
}

/// A page of `GET /v1/jobs`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct JobList {
    pub jobs: Vec<JobView>,
    /// Pass as `page_token` for the next page; `None` on the last page.
    pub next_page_token: Option<String>,
}

/// Where to find a job's resources.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct JobUrls {
    #[serde(rename = "self")]
    pub this: String,
    pub events: String,
    pub result: String,
    pub cancel: String,
}

impl JobUrls {
    pub fn of(id: &str) -> JobUrls {
        let base = format!("/v1/jobs/{id}");
        JobUrls {
            events: format!("{base}/events"),
            result: format!("{base}/result"),
            cancel: format!("{base}/cancel"),
            this: base,
        }
    }
}

impl From<&JobStatus> for JobView {
    fn from(s: &JobStatus) -> JobView {
        let r = &s.record;
        JobView {
            id: r.id.clone(),
            state: r.state,
            priority: r.options.priority,
            label: r.options.label.clone(),
            idempotency_key: r.options.idempotency_key.clone(),
            client: r.client.clone(),
            queue_position: (r.state == JobState::Queued).then_some(s.queue_position),
            progress: r.progress,
            width: r.width,
            height: r.height,
            input_bytes: r.input_bytes,
            has_reference: r.has_reference,
            layers: r.options.layers.clone(),
            requested_variant: r.options.variant,
            variant: r.variant,
            requested_fireflies: r.options.fireflies,
            requested_firefly_strength: r.options.firefly_strength,
            channel_map: r.options.channel_map.clone(),
            fireflies: r.fireflies,
            attempts: r.attempts,
            cancel_requested: r.cancel_requested,
            timings_ms: r.timings,
            metrics: r.metrics,
            sanitized: r.sanitized.clone(),
            missing_variances: r.missing_variances.clone(),
            warnings: r.warnings.clone(),
            error: r.error.clone(),
            result_bytes: r.result_bytes,
            created_at: rfc3339(r.created_at_ms),
            started_at: r.started_at_ms.map(rfc3339),
            finished_at: r.finished_at_ms.map(rfc3339),
            deadline_at: r.deadline_at_ms.map(rfc3339),
            expires_at: r.expires_at_ms.map(rfc3339),
            urls: JobUrls::of(&r.id),
        }
    }
}

// --- HTTP query string ---------------------------------------------------------------------

/// The options of a raw-body `POST /v1/jobs`, from the query string.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct OptionsQuery {
    pub priority: Option<String>,
    /// Comma-separated.
    pub layers: Option<String>,
    pub label: Option<String>,
    /// `auto`, or the name of a loaded variant.
    pub variant: Option<String>,
    pub deadline_seconds: Option<u64>,
    pub idempotency_key: Option<String>,
    /// `auto` or `off`.
    pub fireflies: Option<String>,
    pub firefly_strength: Option<f32>,
    /// `auto`, a channel map's name, or `key=AOVs` pairs separated by `;`.
    pub channel_map: Option<String>,
}

impl OptionsQuery {
    /// The options; the message names the value that is wrong.
    pub fn parse(self) -> Result<JobOptions, String> {
        let priority = match self.priority.as_deref() {
            None | Some("") => Priority::default(),
            Some(p) => p.parse()?,
        };
        let layers = self
            .layers
            .as_deref()
            .unwrap_or("")
            .split(',')
            .map(str::trim)
            .filter(|l| !l.is_empty())
            .map(str::parse)
            .collect::<Result<Vec<Layer>, String>>()?;
        Ok(JobOptions {
            priority,
            layers,
            idempotency_key: self.idempotency_key,
            label: self.label,
            variant: Variant::parse_choice(self.variant.as_deref().unwrap_or(""))?,
            deadline_seconds: self.deadline_seconds,
            fireflies: match self.fireflies.as_deref() {
                None | Some("") => None,
                Some(f) => Some(f.parse()?),
            },
            firefly_strength: self.firefly_strength,
            channel_map: self.channel_map,
        })
    }

    /// The query string (percent-encoded, without `?`).
    pub fn encode(&self) -> String {
        let mut q = Vec::new();
        let mut push = |k: &str, v: Option<String>| {
            if let Some(v) = v {
                q.push(format!("{k}={}", percent_encode(&v)));
            }
        };
        push("priority", self.priority.clone());
        push("layers", self.layers.clone());
        push("label", self.label.clone());
        push("variant", self.variant.clone());
        push("deadline_seconds", self.deadline_seconds.map(|d| d.to_string()));
        push("idempotency_key", self.idempotency_key.clone());
        push("fireflies", self.fireflies.clone());
        push("firefly_strength", self.firefly_strength.map(|s| s.to_string()));
        push("channel_map", self.channel_map.clone());
        q.join("&")
    }
}

impl From<&JobOptions> for OptionsQuery {
    fn from(o: &JobOptions) -> OptionsQuery {
        OptionsQuery {
            priority: Some(o.priority.name().to_string()),
            layers: (!o.layers.is_empty()).then(|| o.layers.iter().map(|l| l.name()).collect::<Vec<_>>().join(",")),
            label: o.label.clone(),
            variant: o.variant.map(|v| v.name().to_string()),
            deadline_seconds: o.deadline_seconds,
            idempotency_key: o.idempotency_key.clone(),
            fireflies: o.fireflies.map(|f| f.name().to_string()),
            firefly_strength: o.firefly_strength,
            channel_map: o.channel_map.clone(),
        }
    }
}

/// Percent-encodes everything but RFC 3986's unreserved characters.
pub fn percent_encode(s: &str) -> String {
    s.bytes()
        .map(|b| match b {
            b'A'..=b'Z' | b'a'..=b'z' | b'0'..=b'9' | b'-' | b'_' | b'.' | b'~' => (b as char).to_string(),
            _ => format!("%{b:02X}"),
        })
        .collect()
}

// --- Protobuf ------------------------------------------------------------------------------

impl From<JobState> for pb::JobState {
    fn from(s: JobState) -> pb::JobState {
        match s {
            JobState::Queued => pb::JobState::Queued,
            JobState::Running => pb::JobState::Running,
            JobState::Succeeded => pb::JobState::Succeeded,
            JobState::Failed => pb::JobState::Failed,
            JobState::Cancelled => pb::JobState::Cancelled,
        }
    }
}

/// A state from its protobuf value; `Ok(None)` for `UNSPECIFIED`.
pub fn state_from_pb(v: i32) -> Result<Option<JobState>, String> {
    Ok(match pb::JobState::try_from(v).map_err(|_| format!("unknown job state {v}"))? {
        pb::JobState::Unspecified => None,
        pb::JobState::Queued => Some(JobState::Queued),
        pb::JobState::Running => Some(JobState::Running),
        pb::JobState::Succeeded => Some(JobState::Succeeded),
        pb::JobState::Failed => Some(JobState::Failed),
        pb::JobState::Cancelled => Some(JobState::Cancelled),
    })
}

impl From<Priority> for pb::Priority {
    fn from(p: Priority) -> pb::Priority {
        match p {
            Priority::Low => pb::Priority::Low,
            Priority::Normal => pb::Priority::Normal,
            Priority::High => pb::Priority::High,
        }
    }
}

/// A priority from its protobuf value; `Ok(None)` for `UNSPECIFIED`.
pub fn priority_from_pb(v: i32) -> Result<Option<Priority>, String> {
    Ok(match pb::Priority::try_from(v).map_err(|_| format!("unknown priority {v}"))? {
        pb::Priority::Unspecified => None,
        pb::Priority::Low => Some(Priority::Low),
        pb::Priority::Normal => Some(Priority::Normal),
        pb::Priority::High => Some(Priority::High),
    })
}

impl TryFrom<pb::JobOptions> for JobOptions {
    type Error = String;

    fn try_from(o: pb::JobOptions) -> Result<JobOptions, String> {
        let variant = match pb::Variant::try_from(o.variant).map_err(|_| format!("unknown variant {}", o.variant))? {
            pb::Variant::Unspecified => None,
            pb::Variant::Full => Some(Variant::Full),
            pb::Variant::Nocov => Some(Variant::Nocov),
        };
        // `variant_name` (any loaded variant) takes precedence over the enum.
        let variant = match o.variant_name.as_str() {
            "" => variant,
            name => Some(name.parse()?),
        };
        let fireflies = match pb::FireflyMode::try_from(o.fireflies)
            .map_err(|_| format!("unknown fireflies mode {}", o.fireflies))?
        {
            pb::FireflyMode::Unspecified => None,
            pb::FireflyMode::Auto => Some(FireflyMode::Auto),
            pb::FireflyMode::Off => Some(FireflyMode::Off),
        };
        Ok(JobOptions {
            priority: priority_from_pb(o.priority)?.unwrap_or_default(),
            layers: o.layers.iter().map(|l| l.parse()).collect::<Result<_, String>>()?,
            idempotency_key: Some(o.idempotency_key).filter(|s| !s.is_empty()),
            label: Some(o.label).filter(|s| !s.is_empty()),
            variant,
            deadline_seconds: Some(o.deadline_seconds).filter(|s| *s > 0),
            fireflies,
            firefly_strength: Some(o.firefly_strength).filter(|s| *s != 0.0),
            channel_map: Some(o.channel_map).filter(|s| !s.is_empty()),
        })
    }
}

impl From<&JobOptions> for pb::JobOptions {
    fn from(o: &JobOptions) -> pb::JobOptions {
        // The enum for the two standard variants (older daemons know only those), the name
        // for any other.
        let (variant, variant_name) = match o.variant {
            None => (pb::Variant::Unspecified, String::new()),
            Some(v) if v == Variant::Full => (pb::Variant::Full, String::new()),
            Some(v) if v == Variant::Nocov => (pb::Variant::Nocov, String::new()),
            Some(v) => (pb::Variant::Unspecified, v.name().to_string()),
        };
        let fireflies = match o.fireflies {
            None => pb::FireflyMode::Unspecified,
            Some(FireflyMode::Auto) => pb::FireflyMode::Auto,
            Some(FireflyMode::Off) => pb::FireflyMode::Off,
        };
        pb::JobOptions {
            priority: pb::Priority::from(o.priority) as i32,
            layers: o.layers.iter().map(|l| l.name().to_string()).collect(),
            idempotency_key: o.idempotency_key.clone().unwrap_or_default(),
            label: o.label.clone().unwrap_or_default(),
            variant: variant as i32,
            deadline_seconds: o.deadline_seconds.unwrap_or(0),
            variant_name,
            fireflies: fireflies as i32,
            firefly_strength: o.firefly_strength.unwrap_or(0.0),
            channel_map: o.channel_map.clone().unwrap_or_default(),
        }
    }
}

impl From<QualityMetrics> for pb::QualityMetrics {
    fn from(q: QualityMetrics) -> pb::QualityMetrics {
        pb::QualityMetrics { relmse: q.relmse, dssim: q.dssim, psnr: q.psnr, smape: q.smape }
    }
}

impl From<pb::QualityMetrics> for QualityMetrics {
    fn from(q: pb::QualityMetrics) -> QualityMetrics {
        QualityMetrics { relmse: q.relmse, dssim: q.dssim, psnr: q.psnr, smape: q.smape }
    }
}

impl From<Timings> for pb::StageTimings {
    fn from(t: Timings) -> pb::StageTimings {
        pb::StageTimings {
            queue: t.queue,
            decode: t.decode,
            preprocess: t.preprocess,
            inference: t.inference,
            reconstruction: t.reconstruction,
            encode: t.encode,
            total: t.total,
        }
    }
}

impl From<pb::StageTimings> for Timings {
    fn from(t: pb::StageTimings) -> Timings {
        Timings {
            queue: t.queue,
            decode: t.decode,
            preprocess: t.preprocess,
            inference: t.inference,
            reconstruction: t.reconstruction,
            encode: t.encode,
            total: t.total,
        }
    }
}

impl From<Progress> for pb::Progress {
    fn from(p: Progress) -> pb::Progress {
        pb::Progress { tiles_done: p.tiles_done, tiles_total: p.tiles_total }
    }
}

impl From<&JobStatus> for pb::Job {
    fn from(s: &JobStatus) -> pb::Job {
        let r = &s.record;
        pb::Job {
            id: r.id.clone(),
            state: pb::JobState::from(r.state) as i32,
            priority: pb::Priority::from(r.options.priority) as i32,
            label: r.options.label.clone().unwrap_or_default(),
            idempotency_key: r.options.idempotency_key.clone().unwrap_or_default(),
            client: r.client.clone().unwrap_or_default(),
            queue_position: s.queue_position,
            progress: Some(r.progress.into()),
            timings: r.timings.map(Into::into),
            error: r
                .error
                .as_ref()
                .map(|e| pb::JobError { code: e.code.name().to_string(), message: e.message.clone() }),
            missing_variances: r.missing_variances.clone(),
            warnings: r.warnings.clone(),
            channel_map: r.options.channel_map.clone().unwrap_or_default(),
            fireflies: r.fireflies.map(|f| pb::Fireflies {
                mode: f.mode.name().to_string(),
                strength: f.strength,
                handled: f.handled,
                diffuse: f.by_component.diffuse,
                specular: f.by_component.specular,
            }),
            metrics: r.metrics.map(|m| pb::JobMetrics { input: Some(m.input.into()), output: Some(m.output.into()) }),
            sanitized: r
                .sanitized
                .as_ref()
                .map(|c| pb::Sanitized { total: c.total, by_buffer: c.by_buffer.clone().into_iter().collect() }),
            width: r.width,
            height: r.height,
            variant: r.variant.map(|v| v.name().to_string()).unwrap_or_default(),
            layers: r.options.layers.iter().map(|l| l.name().to_string()).collect(),
            attempts: r.attempts,
            cancel_requested: r.cancel_requested,
            has_reference: r.has_reference,
            input_bytes: r.input_bytes,
            result_bytes: r.result_bytes.unwrap_or(0),
            created_at_ms: r.created_at_ms,
            started_at_ms: r.started_at_ms.unwrap_or(0),
            finished_at_ms: r.finished_at_ms.unwrap_or(0),
            expires_at_ms: r.expires_at_ms.unwrap_or(0),
            deadline_at_ms: r.deadline_at_ms.unwrap_or(0),
        }
    }
}

/// A gRPC job as the HTTP API would show it. The protobuf form does not carry the
/// requested variant and firefly handling: `requested_*` are `None`.
impl TryFrom<pb::Job> for JobView {
    type Error = String;

    fn try_from(j: pb::Job) -> Result<JobView, String> {
        let state = state_from_pb(j.state)?.ok_or("the job has no state")?;
        let time = |ms: i64| (ms != 0).then(|| rfc3339(ms));
        let error = match j.error {
            None => None,
            Some(e) => Some(JobError { code: e.code.parse()?, message: e.message }),
        };
        let metrics = match j.metrics {
            Some(pb::JobMetrics { input: Some(input), output: Some(output) }) => {
                Some(JobMetrics { input: input.into(), output: output.into() })
            }
            _ => None,
        };
        Ok(JobView {
            urls: JobUrls::of(&j.id),
            id: j.id,
            state,
            priority: priority_from_pb(j.priority)?.unwrap_or_default(),
            label: Some(j.label).filter(|s| !s.is_empty()),
            idempotency_key: Some(j.idempotency_key).filter(|s| !s.is_empty()),
            client: Some(j.client).filter(|s| !s.is_empty()),
            queue_position: (state == JobState::Queued).then_some(j.queue_position),
            progress: j
                .progress
                .map(|p| Progress { tiles_done: p.tiles_done, tiles_total: p.tiles_total })
                .unwrap_or_default(),
            width: j.width,
            height: j.height,
            input_bytes: j.input_bytes,
            has_reference: j.has_reference,
            layers: j.layers.iter().map(|l| l.parse()).collect::<Result<_, String>>()?,
            requested_variant: None,
            variant: Some(j.variant).filter(|v| !v.is_empty()).map(|v| v.parse()).transpose()?,
            requested_fireflies: None,
            requested_firefly_strength: None,
            channel_map: Some(j.channel_map).filter(|m| !m.is_empty()),
            fireflies: match j.fireflies {
                None => None,
                Some(f) => Some(FireflyCounts {
                    mode: f.mode.parse()?,
                    strength: f.strength,
                    handled: f.handled,
                    by_component: FireflyReport { diffuse: f.diffuse, specular: f.specular },
                }),
            },
            attempts: j.attempts,
            cancel_requested: j.cancel_requested,
            timings_ms: j.timings.map(Into::into),
            metrics,
            sanitized: j
                .sanitized
                .map(|s| SanitizedCounts { total: s.total, by_buffer: s.by_buffer.into_iter().collect() }),
            missing_variances: j.missing_variances,
            warnings: j.warnings,
            error,
            result_bytes: (j.result_bytes > 0 || state == JobState::Succeeded).then_some(j.result_bytes),
            created_at: rfc3339(j.created_at_ms),
            started_at: time(j.started_at_ms),
            finished_at: time(j.finished_at_ms),
            deadline_at: time(j.deadline_at_ms),
            expires_at: time(j.expires_at_ms),
        })
    }
}

#[cfg(test)]
mod tests {
    use serde_json::Value;

    use super::*;
    use crate::jobs::{JobErrorCode, JobRecord};

    fn full_status() -> JobStatus {
        let q = QualityMetrics { relmse: 0.1, dssim: 0.2, psnr: f64::INFINITY, smape: 0.3 };
        let record = JobRecord {
            id: "j1".into(),
            seq: 7,
            state: JobState::Failed,
            options: JobOptions {
                priority: Priority::High,
                layers: vec![Layer::Diffuse, Layer::Specular, Layer::All],
                idempotency_key: Some("k".into()),
                label: Some("shot".into()),
                variant: Some(Variant::parse("lin2020").unwrap()),
                deadline_seconds: Some(60),
                fireflies: Some(FireflyMode::Off),
                firefly_strength: Some(2.5),
                channel_map: Some("arnold".into()),
            },
            width: 64,
            height: 32,
            input_bytes: 1000,
            has_reference: true,
            created_at_ms: 1_700_000_000_000,
            started_at_ms: Some(1_700_000_001_000),
            finished_at_ms: Some(1_700_000_002_000),
            deadline_at_ms: Some(1_700_000_060_000),
            expires_at_ms: Some(1_700_086_402_000),
            attempts: 2,
            cancel_requested: true,
            variant: Some(Variant::Full),
            progress: Progress { tiles_done: 2, tiles_total: 2 },
            timings: Some(Timings {
                queue: 1.0,
                decode: 2.0,
                preprocess: 3.0,
                inference: 4.0,
                reconstruction: 5.0,
                encode: 6.0,
                total: 21.0,
            }),
            metrics: Some(JobMetrics { input: q, output: q }),
            sanitized: Some(SanitizedCounts { total: 3, by_buffer: [("albedo".to_string(), 3)].into() }),
            fireflies: Some(FireflyCounts {
                mode: FireflyMode::Off,
                strength: 2.5,
                handled: 5,
                by_component: FireflyReport { diffuse: 2, specular: 3 },
            }),
            missing_variances: vec!["depthVariance".into()],
            warnings: vec!["a warning".into()],
            error: Some(JobError { code: JobErrorCode::Internal, message: "disk full".into() }),
            result_bytes: Some(123),
            client: Some("token:abc".into()),
            storage_failures: 0,
            trace_parent: None,
            rev: 0,
        };
        JobStatus { record, queue_position: 0 }
    }

    fn sparse_status() -> JobStatus {
        let mut s = full_status();
        let r = &mut s.record;
        r.state = JobState::Queued;
        r.options = JobOptions::default();
        (r.started_at_ms, r.finished_at_ms, r.deadline_at_ms, r.expires_at_ms) = (None, None, None, None);
        (r.variant, r.timings, r.metrics, r.sanitized, r.error, r.result_bytes) = (None, None, None, None, None, None);
        r.fireflies = None;
        r.missing_variances.clear();
        s.queue_position = 4;
        s
    }

    /// Resolves `$ref`s of the OpenAPI document.
    fn resolve<'a>(doc: &'a Value, schema: &'a Value) -> &'a Value {
        match schema["$ref"].as_str() {
            Some(r) => {
                let path = r.trim_start_matches("#/").split('/');
                path.fold(doc, |v, k| &v[k])
            }
            None => schema,
        }
    }

    /// Checks `value` against `schema` (types, enums, properties, required, items), at `at`.
    fn conforms(doc: &Value, schema: &Value, value: &Value, at: &str) -> Result<(), String> {
        let schema = resolve(doc, schema);
        if let Some(alternatives) = schema["oneOf"].as_array() {
            let matching = alternatives.iter().filter(|a| conforms(doc, a, value, at).is_ok()).count();
            return match matching {
                1 => Ok(()),
                n => Err(format!("{at}: {value} matches {n} of the `oneOf` alternatives, not one")),
            };
        }
        if let (Some(_), Value::Object(fields)) = (schema["additionalProperties"].as_object(), value) {
            for (k, v) in fields {
                conforms(doc, &schema["additionalProperties"], v, &format!("{at}.{k}"))?;
            }
        }
        let types: Vec<&str> = match &schema["type"] {
            Value::String(t) => vec![t.as_str()],
            Value::Array(ts) => ts.iter().filter_map(Value::as_str).collect(),
            _ => vec![],
        };
        let actual = match value {
            Value::Null => "null",
            Value::Bool(_) => "boolean",
            Value::Number(n) if n.is_u64() || n.is_i64() => "integer",
            Value::Number(_) => "number",
            Value::String(_) => "string",
            Value::Array(_) => "array",
            Value::Object(_) => "object",
        };
        let type_ok = types.is_empty() || types.contains(&actual) || (actual == "integer" && types.contains(&"number"));
        if !type_ok {
            return Err(format!("{at}: {value} is {actual}, the schema says {types:?}"));
        }
        if let Some(options) = schema["enum"].as_array() {
            if !options.contains(value) {
                return Err(format!("{at}: {value} is not one of {options:?}"));
            }
        }
        if let (Some(properties), Value::Object(fields)) = (schema["properties"].as_object(), value) {
            for (k, v) in fields {
                let Some(s) = properties.get(k) else { return Err(format!("{at}: `{k}` is not in the schema")) };
                conforms(doc, s, v, &format!("{at}.{k}"))?;
            }
            for k in properties.keys() {
                if !fields.contains_key(k) {
                    return Err(format!("{at}: the schema's `{k}` is never sent"));
                }
            }
        }
        if let (Some(required), Value::Object(fields)) = (schema["required"].as_array(), value) {
            for k in required.iter().filter_map(Value::as_str) {
                if !fields.contains_key(k) {
                    return Err(format!("{at}: required `{k}` is missing"));
                }
            }
        }
        if let (Value::Array(items), false) = (value, schema["items"].is_null()) {
            for (i, v) in items.iter().enumerate() {
                conforms(doc, &schema["items"], v, &format!("{at}[{i}]"))?;
            }
        }
        Ok(())
    }

    #[test]
    fn the_job_view_is_the_openapi_documents_job() {
        let doc: Value = serde_json::from_str(crate::http::OPENAPI).unwrap();
        let schema = &doc["components"]["schemas"]["Job"];
        for status in [full_status(), sparse_status()] {
            let json = serde_json::to_value(JobView::from(&status)).unwrap();
            conforms(&doc, schema, &json, "Job").unwrap();
        }
        // And the checker catches a field the document lacks.
        let mut json = serde_json::to_value(JobView::from(&full_status())).unwrap();
        json["colour"] = "red".into();
        assert!(conforms(&doc, schema, &json, "Job").is_err());
    }

    #[test]
    fn the_view_round_trips_through_json_and_through_protobuf() {
        for status in [full_status(), sparse_status()] {
            let view = JobView::from(&status);
            let json = serde_json::to_string(&view).unwrap();
            assert_eq!(serde_json::from_str::<JobView>(&json).unwrap(), view);
            let from_pb = JobView::try_from(pb::Job::from(&status)).unwrap();
            let unsent = JobView {
                requested_variant: None,
                requested_fireflies: None,
                requested_firefly_strength: None,
                ..view
            };
            assert_eq!(from_pb, unsent);
        }
    }

    #[test]
    fn options_round_trip_through_the_query_string_and_protobuf() {
        let options = full_status().record.options;
        assert_eq!(OptionsQuery::from(&options).parse().unwrap(), options);
        assert_eq!(JobOptions::try_from(pb::JobOptions::from(&options)).unwrap(), options);
        assert_eq!(JobOptions::try_from(pb::JobOptions::from(&JobOptions::default())).unwrap(), JobOptions::default());
        let bad = OptionsQuery { layers: Some("diffuse,albedo".into()), ..Default::default() };
        assert_eq!(bad.parse().unwrap_err(), "unknown layer `albedo` (expected diffuse, specular or all)");
        let encoded = OptionsQuery { label: Some("a b&c".into()), ..Default::default() }.encode();
        assert_eq!(encoded, "label=a%20b%26c");
    }
}
