//! The fuzz harnesses: structured inputs (via `arbitrary`) driven through the real code
//! paths, with the properties each must keep.
//!
//! - [`exr_frame`]: any bytes through the header check and the frame and reference readers
//!   (channel-layout resolution included): no panic, no frame over the pixel limit.
//! - [`http_submit`]: a `POST /v1/jobs` (raw body or multipart, query options, headers)
//!   through the whole axum router onto a live job service with the tiny test models: no
//!   panic, never a 500, and a 202 names a job.
//! - [`grpc_chunks`]: a `SubmitJob` message stream (headers, chunks of either part in any
//!   order and size) through the gRPC reassembly onto the same service: no panic, never an
//!   internal error.
//!
//! Inputs are built around real frames ([`FrameSpec`]: a synthetic frame of a fuzzed size,
//! with channels left out, bytes flipped and the tail cut), so the fuzzer reaches the pixel
//! readers instead of stopping at the magic number. Accepted jobs are deleted at once so the
//! store stays small however long a run lasts.
//!
//! Shared by the `cargo fuzz` targets (fuzz/fuzz_targets) and by the main crate's
//! `tests/fuzz_regressions.rs`, which replays the kept corpus on stable Rust.

use std::path::PathBuf;
use std::sync::{Arc, OnceLock};
use std::time::Duration;

use arbitrary::{Arbitrary, Unstructured};
use axum::body::Body;
use futures_util::StreamExt;
use http_body_util::BodyExt;
use tower::ServiceExt;

use mcdenoise::auth::{Caller, ClientId, Tokens};
use mcdenoise::client::percent_encode;
use mcdenoise::error::Error;
use mcdenoise::frame::{Frame, Limits, SampleType};
use mcdenoise::grpc::pb;
use mcdenoise::jobs::{JobService, Settings};

/// The pixel limit of the harnesses (a 64×64 frame).
pub const MAX_PIXELS: u64 = 64 * 64;

// --- Inputs ------------------------------------------------------------------------------

/// A synthetic frame, then damaged.
#[derive(Arbitrary, Debug)]
pub struct FrameSpec {
    width: u8,
    height: u8,
    covariance: bool,
    half: bool,
    /// Index of a channel to leave out.
    drop_channel: Option<u8>,
    /// `(position, xor)` pairs applied to the encoded bytes.
    flips: Vec<(u16, u8)>,
    /// Bytes cut from the end.
    truncate: Option<u16>,
}

impl FrameSpec {
    pub fn bytes(&self) -> Vec<u8> {
        let (w, h) = (1 + self.width as usize % 40, 1 + self.height as usize % 40);
        let mut planes = mcdenoise::engine::synthetic_planes(w, h, self.covariance);
        if let Some(i) = self.drop_channel {
            planes.remove(i as usize % planes.len());
        }
        let sample = if self.half { SampleType::F16 } else { SampleType::F32 };
        let named = planes.iter().map(|(n, p)| (n.as_str(), p.as_slice()));
        let mut bytes = mcdenoise::frame::write_planes(w, h, named, sample, exr::prelude::Encoding::FAST_LOSSLESS)
            .expect("a synthetic frame encodes");
        for (at, xor) in &self.flips {
            let n = bytes.len();
            bytes[*at as usize % n] ^= xor;
        }
        if let Some(cut) = self.truncate {
            let keep = bytes.len() - (cut as usize % bytes.len());
            bytes.truncate(keep);
        }
        bytes
    }
}

/// Bytes of an upload part.
#[derive(Arbitrary, Debug)]
pub enum Payload {
    Raw(Vec<u8>),
    Frame(FrameSpec),
    Json(Vec<(OptionKey, JsonValue)>),
}

impl Payload {
    pub fn bytes(&self) -> Vec<u8> {
        match self {
            Payload::Raw(b) => b.clone(),
            Payload::Frame(f) => f.bytes(),
            Payload::Json(fields) => {
                let map: serde_json::Map<String, serde_json::Value> =
                    fields.iter().map(|(k, v)| (k.name().to_string(), v.json())).collect();
                serde_json::Value::Object(map).to_string().into_bytes()
            }
        }
    }
}

#[derive(Arbitrary, Debug)]
pub enum OptionKey {
    Priority,
    Layers,
    Label,
    Variant,
    DeadlineSeconds,
    IdempotencyKey,
    Other(String),
}

impl OptionKey {
    fn name(&self) -> &str {
        match self {
            OptionKey::Priority => "priority",
            OptionKey::Layers => "layers",
            OptionKey::Label => "label",
            OptionKey::Variant => "variant",
            OptionKey::DeadlineSeconds => "deadline_seconds",
            OptionKey::IdempotencyKey => "idempotency_key",
            OptionKey::Other(s) => s,
        }
    }
}

#[derive(Arbitrary, Debug)]
pub enum JsonValue {
    Str(String),
    Known(u8),
    Int(i64),
    Bool(bool),
    Null,
    List(Vec<String>),
}

/// Values the daemon knows, so the fuzzer gets past option parsing.
const KNOWN: &[&str] = &["high", "normal", "low", "diffuse", "specular", "auto", "full", "nocov", "", "shot-1"];

impl JsonValue {
    fn json(&self) -> serde_json::Value {
        match self {
            JsonValue::Str(s) => s.clone().into(),
            JsonValue::Known(i) => KNOWN[*i as usize % KNOWN.len()].into(),
            JsonValue::Int(i) => (*i).into(),
            JsonValue::Bool(b) => (*b).into(),
            JsonValue::Null => serde_json::Value::Null,
            JsonValue::List(l) => l.clone().into(),
        }
    }

    fn text(&self) -> String {
        match self.json() {
            serde_json::Value::String(s) => s,
            other => other.to_string(),
        }
    }
}

#[derive(Arbitrary, Debug)]
pub enum ContentType {
    Exr,
    OctetStream,
    Missing,
    Multipart,
    MultipartWithoutBoundary,
    Other(String),
}

#[derive(Arbitrary, Debug)]
pub enum PartName {
    Options,
    Frame,
    Reference,
    Other(String),
}

#[derive(Arbitrary, Debug)]
pub enum HttpBody {
    Raw(Payload),
    Parts(Vec<(PartName, Payload)>),
}

/// A `POST /v1/jobs`.
#[derive(Arbitrary, Debug)]
pub struct HttpSubmit {
    content_type: ContentType,
    query: Vec<(OptionKey, JsonValue)>,
    idempotency_header: Option<String>,
    /// A `Content-Length` header that may disagree with the body.
    declared_length: Option<u64>,
    body: HttpBody,
}

const BOUNDARY: &str = "fuzz-boundary-4f1c";

impl HttpSubmit {
    fn request(&self) -> Option<axum::http::Request<Body>> {
        let query: Vec<String> = self
            .query
            .iter()
            .map(|(k, v)| format!("{}={}", percent_encode(k.name()), percent_encode(&v.text())))
            .collect();
        let mut builder = axum::http::Request::post(format!("/v1/jobs?{}", query.join("&")));
        let content_type = match &self.content_type {
            ContentType::Exr => Some("image/x-exr".to_string()),
            ContentType::OctetStream => Some("application/octet-stream".to_string()),
            ContentType::Missing => None,
            ContentType::Multipart => Some(format!("multipart/form-data; boundary={BOUNDARY}")),
            ContentType::MultipartWithoutBoundary => Some("multipart/form-data".to_string()),
            ContentType::Other(s) => Some(s.clone()),
        };
        if let Some(ct) = content_type {
            builder = builder.header("content-type", ct);
        }
        if let Some(key) = &self.idempotency_header {
            builder = builder.header("idempotency-key", key.as_str());
        }
        if let Some(n) = self.declared_length {
            builder = builder.header("content-length", n);
        }
        let body = match &self.body {
            HttpBody::Raw(p) => p.bytes(),
            HttpBody::Parts(parts) => {
                let mut body = Vec::new();
                for (name, payload) in parts {
                    let name = match name {
                        PartName::Options => "options",
                        PartName::Frame => "frame",
                        PartName::Reference => "reference",
                        PartName::Other(s) => s.as_str(),
                    };
                    body.extend_from_slice(
                        format!("--{BOUNDARY}\r\nContent-Disposition: form-data; name=\"{name}\"\r\n\r\n").as_bytes(),
                    );
                    body.extend_from_slice(&payload.bytes());
                    body.extend_from_slice(b"\r\n");
                }
                body.extend_from_slice(format!("--{BOUNDARY}--\r\n").as_bytes());
                body
            }
        };
        builder.body(Body::from(body)).ok()
    }
}

/// Sizes declared by a `SubmitJob` header.
#[derive(Arbitrary, Debug)]
pub enum Sizes {
    /// The sizes of the chunks that follow, off by the deltas.
    Matching {
        frame_delta: i8,
        reference_delta: i8,
    },
    Given {
        frame: u64,
        reference: u64,
    },
}

#[derive(Arbitrary, Debug)]
pub enum GrpcMessage {
    Header {
        sizes: Sizes,
        options: Option<Vec<(OptionKey, JsonValue)>>,
    },
    Chunk {
        part: i8,
        data: Payload,
    },
    /// A frame cut into chunks of `chunk` bytes (at least 1).
    SplitFrame {
        part: i8,
        frame: FrameSpec,
        chunk: u16,
    },
    Empty,
    /// The client's stream fails here.
    StreamError,
}

/// A `SubmitJob` client stream.
#[derive(Arbitrary, Debug)]
pub struct GrpcUpload {
    messages: Vec<GrpcMessage>,
}

fn options_pb(fields: &[(OptionKey, JsonValue)]) -> pb::JobOptions {
    let mut o = pb::JobOptions::default();
    for (k, v) in fields {
        let as_int = || match v {
            JsonValue::Int(i) => *i,
            JsonValue::Known(i) => *i as i64 % 5,
            _ => 0,
        };
        match k {
            OptionKey::Priority => o.priority = as_int() as i32,
            OptionKey::Layers => o.layers.push(v.text()),
            OptionKey::Label => o.label = v.text(),
            OptionKey::Variant => o.variant = as_int() as i32,
            OptionKey::DeadlineSeconds => o.deadline_seconds = as_int() as u64,
            OptionKey::IdempotencyKey => o.idempotency_key = v.text(),
            OptionKey::Other(_) => {}
        }
    }
    o
}

impl GrpcUpload {
    fn messages(&self) -> Vec<Result<pb::SubmitJobRequest, tonic::Status>> {
        use pb::submit_job_request::Message;
        let mut chunks: Vec<Result<pb::SubmitJobRequest, tonic::Status>> = Vec::new();
        let (mut frame_bytes, mut reference_bytes) = (0i64, 0i64);
        let mut headers = Vec::new();
        for m in &self.messages {
            let mut push = |part: i8, data: Vec<u8>| {
                match part.rem_euclid(3) {
                    1 => frame_bytes += data.len() as i64,
                    2 => reference_bytes += data.len() as i64,
                    _ => {}
                }
                chunks.push(Ok(pb::SubmitJobRequest {
                    message: Some(Message::Chunk(pb::Chunk { part: part.rem_euclid(4) as i32, data })),
                }));
            };
            match m {
                GrpcMessage::Header { sizes, options } => {
                    headers.push((chunks.len(), sizes, options.as_ref().map(|o| options_pb(o))));
                    chunks.push(Ok(pb::SubmitJobRequest { message: None }));
                }
                GrpcMessage::Chunk { part, data } => push(*part, data.bytes()),
                GrpcMessage::SplitFrame { part, frame, chunk } => {
                    for piece in frame.bytes().chunks((*chunk as usize).max(1)) {
                        push(*part, piece.to_vec());
                    }
                }
                GrpcMessage::Empty => chunks.push(Ok(pb::SubmitJobRequest { message: None })),
                GrpcMessage::StreamError => chunks.push(Err(tonic::Status::cancelled("client went away"))),
            }
        }
        // Headers are filled in last: "matching" sizes are those of all the chunks.
        for (at, sizes, options) in headers {
            let (frame_size, reference_size) = match sizes {
                Sizes::Matching { frame_delta, reference_delta } => (
                    (frame_bytes + *frame_delta as i64).max(0) as u64,
                    (reference_bytes + *reference_delta as i64).max(0) as u64,
                ),
                Sizes::Given { frame, reference } => (*frame, *reference),
            };
            chunks[at] = Ok(pb::SubmitJobRequest {
                message: Some(Message::Header(pb::SubmitHeader { options, frame_size, reference_size })),
            });
        }
        chunks
    }
}

// --- The service under test ---------------------------------------------------------------

struct Daemon {
    runtime: tokio::runtime::Runtime,
    service: JobService,
    router: axum::Router,
    _dir: tempfile::TempDir,
}

fn tiny_models() -> PathBuf {
    let here = PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    // The main crate (tests/fuzz_regressions.rs) or the fuzz crate beside it.
    [here.join("tests/fixtures/models/tiny"), here.join("../tests/fixtures/models/tiny")]
        .into_iter()
        .find(|p| p.is_dir())
        .expect("tests/fixtures/models/tiny")
}

fn daemon() -> &'static Daemon {
    static DAEMON: OnceLock<Daemon> = OnceLock::new();
    DAEMON.get_or_init(|| {
        let dir = tempfile::tempdir().expect("a temporary directory");
        let data = dir.path().display().to_string();
        let models = tiny_models().display().to_string();
        let pixels = MAX_PIXELS.to_string();
        let args = mcdenoise::config::parse_serve_args([
            "serve",
            "--data-dir",
            &data,
            "--models",
            &models,
            "--workers",
            "1",
            "--threads-per-worker",
            "1",
            "--tile",
            "32",
            "--max-pixels",
            &pixels,
            "--max-body-bytes",
            "262144",
            // ONNX Runtime's CPU provider whatever `auto` would choose: this service runs in
            // the fuzzer's (or the test's) process, which OpenVINO would share with the
            // CPU provider's sessions of other tests (src/engine/device.rs).
            "--device",
            "cpu",
        ])
        .expect("valid arguments");
        let runtime = tokio::runtime::Builder::new_multi_thread().worker_threads(1).enable_all().build().unwrap();
        let telemetry = Arc::new(mcdenoise::telemetry::Telemetry::new());
        let settings = Settings::from_args(&args);
        let engines = mcdenoise::engine::Engine::factory(settings.engine.clone());
        let (service, _workers) =
            JobService::start(dir.path(), settings, telemetry, engines, mcdenoise::jobs::Backend::Embedded)
                .expect("the job service starts");
        runtime
            .block_on(service.wait_ready(Duration::from_secs(60)))
            .expect("the tiny models load (is ORT_DYLIB_PATH set?)");
        let state = mcdenoise::http::AppState {
            service: service.clone(),
            tokens: Arc::new(Tokens::default()),
            shutdown: tokio_util::sync::CancellationToken::new(),
            info: Arc::new(mcdenoise::http::Info::new(serde_json::Value::Null)),
        };
        let router = mcdenoise::http::router(state);
        Daemon { runtime, service, router, _dir: dir }
    })
}

// --- Harnesses ------------------------------------------------------------------------------

/// The daemon catches panics at two boundaries (the EXR decoder, a job's run) and turns
/// them into that input's error. libFuzzer's panic hook aborts on any panic, caught or not;
/// this one only prints, so only a panic that escapes those boundaries (and reaches
/// libFuzzer's own `catch_unwind`) counts as a crash.
fn contained_panics_are_errors() {
    static ONCE: std::sync::Once = std::sync::Once::new();
    ONCE.call_once(|| std::panic::set_hook(Box::new(|info| eprintln!("contained: {info}"))));
}

/// Any bytes as a frame and as a reference; whether they made a valid frame.
pub fn exr_frame(data: &[u8]) -> bool {
    let limits = Limits { max_pixels: MAX_PIXELS };
    if let Ok(info) = mcdenoise::frame::read_header(std::io::Cursor::new(data), &limits) {
        assert!((info.width * info.height) as u64 <= MAX_PIXELS, "header over the pixel limit: {info:?}");
    }
    let frame = Frame::from_exr_bytes(data, &limits);
    for frame in [&frame, &Frame::reference_from_exr_bytes(data, &limits)].into_iter().flatten() {
        assert!(frame.pixels() as u64 <= MAX_PIXELS);
    }
    frame.is_ok()
}

pub fn exr_frame_bytes(data: &[u8]) -> bool {
    contained_panics_are_errors();
    // Inputs starting with a 0 byte describe a damaged synthetic frame; others are bytes.
    match data.split_first() {
        Some((0, rest)) => {
            FrameSpec::arbitrary_take_rest(Unstructured::new(rest)).is_ok_and(|spec| exr_frame(&spec.bytes()))
        }
        _ => exr_frame(data),
    }
}

/// Deletes an accepted job so the store does not grow.
fn forget(d: &Daemon, id: &str) {
    let _ = d.runtime.block_on(d.service.delete(id, &Caller::operator(ClientId("fuzz".into()))));
}

/// Whether the submission was accepted as a job.
pub fn http_submit(input: &HttpSubmit) -> bool {
    let Some(request) = input.request() else { return false };
    let d = daemon();
    let (status, body) = d.runtime.block_on(async {
        let response = d.router.clone().oneshot(request).await.expect("the router is infallible");
        let status = response.status();
        let body = response.into_body().collect().await.map(|b| b.to_bytes()).unwrap_or_default();
        (status, body)
    });
    let text = String::from_utf8_lossy(&body);
    assert!(!status.is_server_error() || status == 503, "{status}: {text}");
    if status == 202 {
        let job: serde_json::Value = serde_json::from_slice(&body).expect("a 202 carries the job");
        forget(d, job["id"].as_str().expect("the job has an id"));
    }
    status == 202
}

pub fn http_submit_bytes(data: &[u8]) -> bool {
    contained_panics_are_errors();
    HttpSubmit::arbitrary_take_rest(Unstructured::new(data)).is_ok_and(|input| http_submit(&input))
}

/// Whether the upload was accepted as a job.
pub fn grpc_chunks(input: &GrpcUpload) -> bool {
    let d = daemon();
    let messages = input.messages();
    let client = ClientId("fuzz".into());
    let result = d.runtime.block_on(mcdenoise::grpc::submit_upload(
        &d.service,
        &client,
        futures_util::stream::iter(messages).boxed(),
    ));
    match result {
        Ok(job) => {
            forget(d, &job.id);
            true
        }
        Err(Error::Internal(message)) => panic!("internal error from a client's stream: {message}"),
        Err(_) => false,
    }
}

pub fn grpc_chunks_bytes(data: &[u8]) -> bool {
    contained_panics_are_errors();
    GrpcUpload::arbitrary_take_rest(Unstructured::new(data)).is_ok_and(|input| grpc_chunks(&input))
}
