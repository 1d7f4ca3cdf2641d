//! `mcdenoise submit`: sends a frame to a daemon over HTTP or gRPC, shows the progress,
//! and writes the result. Also a small HTTP client for scripts and tests.

use std::io::{IsTerminal, Write};
use std::path::{Path, PathBuf};

use anyhow::{anyhow, bail, Context, Result};
use bytes::Bytes;
use clap::Args;
use futures_util::{stream, StreamExt, TryStreamExt};
use http_body_util::{combinators::BoxBody, BodyExt, Full, StreamBody};
use hyper::body::{Frame, Incoming};
use hyper::{Method, Request, Response, StatusCode};
use hyper_util::client::legacy::{connect::HttpConnector, Client};
use hyper_util::rt::TokioExecutor;
use serde_json::Value;

use crate::atomic::AsyncFile;
use crate::config::Secret;
use crate::engine::Variant;
use crate::grpc::pb;
use crate::jobs::{JobOptions, JobState, Layer};
use crate::wire::{JobView, OptionsQuery};

#[derive(Args, Debug, Clone)]
pub struct SubmitArgs {
    /// Noisy frame (multi-layer OpenEXR, see docs/frame-layout.md).
    pub frame: PathBuf,
    /// Daemon URL: `http://HOST:PORT` for the HTTP API, `grpc://HOST:PORT` for gRPC.
    #[arg(long, env = "MCDENOISE_SERVER", default_value = "http://127.0.0.1:8080")]
    pub server: String,
    /// Reference frame: the job reports RelMSE, DSSIM, PSNR and SMAPE of input and output.
    #[arg(long)]
    pub reference: Option<PathBuf>,
    /// Wait until the job finishes, showing its progress on stderr.
    #[arg(long)]
    pub wait: bool,
    /// Write the denoised EXR here (implies --wait).
    #[arg(short, long)]
    pub output: Option<PathBuf>,
    /// Priority class: high, normal or low.
    #[arg(long, default_value = "normal")]
    pub priority: String,
    /// Extra layers of the result besides R,G,B (and the input's alpha, always kept):
    /// diffuse, specular (the denoised components), all (every other channel of the input,
    /// unchanged); comma-separated, combinable.
    #[arg(long, value_delimiter = ',')]
    pub layers: Vec<String>,
    /// Free-text label (shown in listings, usable as a filter).
    #[arg(long)]
    pub label: Option<String>,
    /// Makes retries safe: a second submission with the same key returns the same job.
    #[arg(long)]
    pub idempotency_key: Option<String>,
    /// Model variant: auto, or the name of a variant the daemon has loaded (full, nocov, ...).
    #[arg(long, default_value = "auto")]
    pub variant: String,
    /// Seconds after which the job fails (default: the daemon's).
    #[arg(long)]
    pub deadline_seconds: Option<u64>,
    /// Firefly handling: auto or off (default: the daemon's; docs/fireflies.md).
    #[arg(long)]
    pub fireflies: Option<String>,
    /// Strength of the firefly handling, 0.1 to 10 (default: the daemon's).
    #[arg(long)]
    pub firefly_strength: Option<f32>,
    /// Bearer token, when the daemon requires one.
    #[arg(long, env = "MCDENOISE_TOKEN", hide_env_values = true)]
    pub token: Option<Secret>,
    /// No progress on stderr.
    #[arg(short, long)]
    pub quiet: bool,
}

/// Progress output on stderr: rewritten in place on a terminal, a line per 10 % otherwise.
struct ProgressLine {
    quiet: bool,
    tty: bool,
    last_decile: Option<u32>,
}

impl ProgressLine {
    fn new(quiet: bool) -> Self {
        ProgressLine { quiet, tty: std::io::stderr().is_terminal(), last_decile: None }
    }

    fn say(&mut self, line: &str) {
        if self.quiet {
            return;
        }
        if self.tty && self.last_decile.is_some() {
            eprintln!();
        }
        self.last_decile = None;
        eprintln!("{line}");
    }

    fn tiles(&mut self, done: u64, total: u64) {
        if self.quiet || total == 0 {
            return;
        }
        if self.tty {
            eprint!("\rtile {done}/{total}");
            let _ = std::io::stderr().flush();
            self.last_decile = Some(0);
        } else {
            let decile = (done * 10 / total) as u32;
            if self.last_decile != Some(decile) {
                eprintln!("tile {done}/{total}");
                self.last_decile = Some(decile);
            }
        }
    }
}

/// `mcdenoise submit`.
pub fn submit(args: SubmitArgs) -> Result<()> {
    let runtime = tokio::runtime::Builder::new_current_thread().enable_all().build()?;
    let job = runtime.block_on(submit_async(args))?;
    println!("{}", serde_json::to_string_pretty(&job)?);
    match job.state {
        JobState::Failed => {
            bail!("the job failed: {}", job.error.map(|e| e.message).unwrap_or_else(|| "unknown reason".into()))
        }
        JobState::Cancelled => bail!("the job was cancelled"),
        JobState::Queued | JobState::Running | JobState::Succeeded => Ok(()),
    }
}

impl SubmitArgs {
    /// The job's options, each value checked (with the daemon's messages).
    pub fn options(&self) -> Result<JobOptions> {
        let layers = self.layers.iter().map(|l| l.parse()).collect::<Result<Vec<Layer>, String>>();
        Ok(JobOptions {
            priority: self.priority.parse().map_err(anyhow::Error::msg)?,
            layers: layers.map_err(anyhow::Error::msg)?,
            idempotency_key: self.idempotency_key.clone(),
            label: self.label.clone(),
            variant: Variant::parse_choice(&self.variant).map_err(anyhow::Error::msg)?,
            deadline_seconds: self.deadline_seconds,
            fireflies: self.fireflies.as_deref().map(str::parse).transpose().map_err(anyhow::Error::msg)?,
            firefly_strength: self.firefly_strength,
        })
    }
}

/// Submits, optionally waits and downloads; returns the job.
pub async fn submit_async(args: SubmitArgs) -> Result<JobView> {
    let wait = args.wait || args.output.is_some();
    let options = args.options()?;
    if let Some(rest) = args.server.strip_prefix("grpc://") {
        submit_grpc(&args, &options, rest, wait).await
    } else if args.server.starts_with("http://") {
        submit_http(&args, &options, wait).await
    } else {
        bail!("--server must start with http:// or grpc:// (got {})", args.server)
    }
}

/// A job from an answer's JSON.
fn job_view(v: Value) -> Result<JobView> {
    serde_json::from_value(v).context("the daemon's answer is not a job")
}

// --- HTTP ----------------------------------------------------------------------------------

type Body = BoxBody<Bytes, std::io::Error>;

/// A minimal HTTP/1.1 client for the daemon's API.
#[derive(Clone)]
pub struct HttpClient {
    client: Client<HttpConnector, Body>,
    base: String,
    token: Option<String>,
}

/// A body from bytes.
pub fn body_bytes(b: impl Into<Bytes>) -> Body {
    Full::new(b.into()).map_err(|never| match never {}).boxed()
}

/// A body streamed from a file.
pub async fn body_file(path: &Path) -> Result<(Body, u64)> {
    let file = tokio::fs::File::open(path).await.with_context(|| format!("cannot open {}", path.display()))?;
    let len = file.metadata().await?.len();
    let stream = tokio_util::io::ReaderStream::with_capacity(file, 1 << 20).map_ok(Frame::data);
    Ok((BodyExt::boxed(StreamBody::new(stream)), len))
}

impl HttpClient {
    /// `base` is like `http://127.0.0.1:8080`.
    pub fn new(base: &str, token: Option<&str>) -> HttpClient {
        let client = Client::builder(TokioExecutor::new()).build_http();
        HttpClient { client, base: base.trim_end_matches('/').to_string(), token: token.map(str::to_owned) }
    }

    /// Sends a request; `headers` are extra `(name, value)` pairs.
    pub async fn send(
        &self,
        method: Method,
        path: &str,
        headers: &[(&str, &str)],
        body: Body,
    ) -> Result<Response<Incoming>> {
        let mut req = Request::builder().method(method).uri(format!("{}{path}", self.base));
        if let Some(t) = &self.token {
            req = req.header("authorization", format!("Bearer {t}"));
        }
        for (k, v) in headers {
            req = req.header(*k, *v);
        }
        let req = req.body(body)?;
        self.client.request(req).await.map_err(|e| anyhow!("request to {}{path} failed: {e}", self.base))
    }

    pub async fn get(&self, path: &str) -> Result<Response<Incoming>> {
        self.send(Method::GET, path, &[], body_bytes(Bytes::new())).await
    }

    /// Sends and reads a JSON answer: `(status, body)`; a non-JSON body becomes a string.
    pub async fn json(
        &self,
        method: Method,
        path: &str,
        headers: &[(&str, &str)],
        body: Body,
    ) -> Result<(StatusCode, Value)> {
        let resp = self.send(method, path, headers, body).await?;
        read_json(resp).await
    }
}

/// Reads a whole response as JSON (or a JSON string if it is not JSON).
pub async fn read_json(resp: Response<Incoming>) -> Result<(StatusCode, Value)> {
    let status = resp.status();
    let bytes = resp.into_body().collect().await?.to_bytes();
    let value =
        serde_json::from_slice(&bytes).unwrap_or_else(|_| Value::String(String::from_utf8_lossy(&bytes).into()));
    Ok((status, value))
}

fn api_error(status: StatusCode, body: &Value) -> anyhow::Error {
    let message = body["error"]["message"].as_str().map(str::to_owned).unwrap_or_else(|| body.to_string());
    anyhow!("{status}: {message}")
}

/// One Server-Sent Event.
#[derive(Clone, Debug, PartialEq)]
pub struct SseEvent {
    pub event: String,
    pub data: Value,
}

/// Reads `text/event-stream` events from a response, calling `on_event` for each until it
/// returns false or the stream ends.
pub async fn read_sse(resp: Response<Incoming>, mut on_event: impl FnMut(SseEvent) -> bool) -> Result<()> {
    let mut body = resp.into_body();
    let mut buffer = String::new();
    while let Some(frame) = body.frame().await {
        let frame = frame?;
        let Some(data) = frame.data_ref() else { continue };
        buffer.push_str(&String::from_utf8_lossy(data));
        while let Some(end) = buffer.find("\n\n") {
            let block: String = buffer.drain(..end + 2).collect();
            let mut event = String::from("message");
            let mut payload = String::new();
            for line in block.lines() {
                if let Some(v) = line.strip_prefix("event:") {
                    event = v.trim().to_string();
                } else if let Some(v) = line.strip_prefix("data:") {
                    payload.push_str(v.strip_prefix(' ').unwrap_or(v));
                }
            }
            if payload.is_empty() {
                continue; // keep-alive comment
            }
            let data = serde_json::from_str(&payload).unwrap_or(Value::String(payload));
            if !on_event(SseEvent { event, data }) {
                return Ok(());
            }
        }
    }
    Ok(())
}

/// Streams a response body into `path` atomically (`.part`, fsync, rename).
pub async fn save_body(resp: Response<Incoming>, path: &Path) -> Result<u64> {
    let mut file = AsyncFile::create(path).await.with_context(|| format!("cannot create {}", path.display()))?;
    let mut body = resp.into_body();
    let mut n = 0u64;
    while let Some(frame) = body.frame().await {
        if let Some(data) = frame?.data_ref() {
            file.write_all(data).await?;
            n += data.len() as u64;
        }
    }
    file.commit().await.with_context(|| format!("cannot write {}", path.display()))?;
    Ok(n)
}

/// Percent-encodes everything but RFC 3986's unreserved characters.
pub use crate::wire::percent_encode;

/// A multipart body: an `options` JSON part and file parts, streamed; returns its
/// content type and length.
pub async fn multipart_body(options: &Value, files: &[(&str, &Path)]) -> Result<(Body, String, u64)> {
    let boundary = format!("mcdenoise-{}", uuid::Uuid::now_v7().simple());
    let mut pieces: Vec<Body> = Vec::new();
    let mut len = 0u64;
    let push_bytes = |pieces: &mut Vec<Body>, len: &mut u64, b: String| {
        *len += b.len() as u64;
        pieces.push(body_bytes(b));
    };
    push_bytes(
        &mut pieces,
        &mut len,
        format!(
            "--{boundary}\r\nContent-Disposition: form-data; name=\"options\"\r\nContent-Type: application/json\r\n\r\n{options}\r\n"
        ),
    );
    for (name, path) in files {
        push_bytes(
            &mut pieces,
            &mut len,
            format!(
                "--{boundary}\r\nContent-Disposition: form-data; name=\"{name}\"; filename=\"{name}.exr\"\r\nContent-Type: image/x-exr\r\n\r\n"
            ),
        );
        let (body, n) = body_file(path).await?;
        len += n;
        pieces.push(body);
        push_bytes(&mut pieces, &mut len, "\r\n".to_string());
    }
    push_bytes(&mut pieces, &mut len, format!("--{boundary}--\r\n"));
    let stream = stream::iter(pieces).flat_map(|b| b.into_data_stream()).map_ok(Frame::data);
    Ok((BodyExt::boxed(StreamBody::new(stream)), format!("multipart/form-data; boundary={boundary}"), len))
}

async fn submit_http(args: &SubmitArgs, options: &JobOptions, wait: bool) -> Result<JobView> {
    let client = HttpClient::new(&args.server, args.token.as_ref().map(|t| t.0.as_str()));
    let mut line = ProgressLine::new(args.quiet);
    let (status, job) = match &args.reference {
        None => {
            let (body, len) = body_file(&args.frame).await?;
            let len = len.to_string();
            let mut headers = vec![("content-type", "image/x-exr"), ("content-length", len.as_str())];
            if let Some(k) = &args.idempotency_key {
                headers.push(("idempotency-key", k.as_str()));
            }
            // The key goes in its header.
            let query = OptionsQuery { idempotency_key: None, ..OptionsQuery::from(options) };
            client.json(Method::POST, &format!("/v1/jobs?{}", query.encode()), &headers, body).await?
        }
        Some(reference) => {
            let options = serde_json::to_value(options)?;
            let (body, content_type, len) =
                multipart_body(&options, &[("frame", &args.frame), ("reference", reference)]).await?;
            let len = len.to_string();
            client
                .json(Method::POST, "/v1/jobs", &[("content-type", &content_type), ("content-length", &len)], body)
                .await?
        }
    };
    if !status.is_success() {
        return Err(api_error(status, &job));
    }
    let job = job_view(job)?;
    let id = job.id.clone();
    line.say(&format!("submitted job {id}"));
    if !wait {
        return Ok(job);
    }
    let resp = client.get(&format!("/v1/jobs/{id}/events")).await?;
    if !resp.status().is_success() {
        let (s, v) = read_json(resp).await?;
        return Err(api_error(s, &v));
    }
    let mut last_event = None;
    read_sse(resp, |ev| {
        match ev.event.as_str() {
            "queued" => line.say(&format!("queued at position {}", ev.data["queue_position"])),
            "started" => line.say(&format!("started (attempt {})", ev.data["attempt"])),
            "progress" => {
                line.tiles(ev.data["tiles_done"].as_u64().unwrap_or(0), ev.data["tiles_total"].as_u64().unwrap_or(0))
            }
            "succeeded" | "failed" | "cancelled" => {
                line.say(&ev.event);
                last_event = Some(ev.data);
                return false;
            }
            _ => {}
        }
        true
    })
    .await?;
    let last = match last_event {
        Some(data) => job_view(data)?,
        None => {
            // The stream ended early (daemon shutting down): report the latest state.
            let (s, v) = client.json(Method::GET, &format!("/v1/jobs/{id}"), &[], body_bytes(Bytes::new())).await?;
            if !s.is_success() {
                return Err(api_error(s, &v));
            }
            job_view(v)?
        }
    };
    if let (Some(out), JobState::Succeeded) = (&args.output, last.state) {
        let resp = client.get(&format!("/v1/jobs/{id}/result")).await?;
        if !resp.status().is_success() {
            let (s, v) = read_json(resp).await?;
            return Err(api_error(s, &v));
        }
        let n = save_body(resp, out).await?;
        line.say(&format!("wrote {} ({n} bytes)", out.display()));
    }
    Ok(last)
}

// --- gRPC ------------------------------------------------------------------------------------

/// A gRPC client with the bearer token attached, if any.
pub type GrpcClient = pb::denoiser_client::DenoiserClient<
    tonic::service::interceptor::InterceptedService<tonic::transport::Channel, TokenInterceptor>,
>;

#[derive(Clone)]
pub struct TokenInterceptor(Option<tonic::metadata::MetadataValue<tonic::metadata::Ascii>>);

impl tonic::service::Interceptor for TokenInterceptor {
    fn call(&mut self, mut req: tonic::Request<()>) -> Result<tonic::Request<()>, tonic::Status> {
        if let Some(v) = &self.0 {
            req.metadata_mut().insert("authorization", v.clone());
        }
        Ok(req)
    }
}

/// Connects to `host:port`.
pub async fn grpc_connect(host_port: &str, token: Option<&str>) -> Result<GrpcClient> {
    let channel = tonic::transport::Endpoint::from_shared(format!("http://{host_port}"))?
        .connect()
        .await
        .with_context(|| format!("cannot connect to grpc://{host_port}"))?;
    let token = token.map(|t| format!("Bearer {t}").parse()).transpose().context("the token is not valid ASCII")?;
    Ok(pb::denoiser_client::DenoiserClient::with_interceptor(channel, TokenInterceptor(token))
        .max_decoding_message_size(crate::grpc::MAX_MESSAGE_BYTES)
        .max_encoding_message_size(crate::grpc::MAX_MESSAGE_BYTES))
}

/// The upload stream of `SubmitJob`: header, then the files in chunks of `chunk` bytes.
pub async fn upload_stream(
    options: pb::JobOptions,
    frame: &Path,
    reference: Option<&Path>,
    chunk: usize,
) -> Result<impl futures_util::Stream<Item = pb::SubmitJobRequest> + Send + 'static> {
    use pb::submit_job_request::Message;
    let open = |p: &Path| {
        let p = p.to_path_buf();
        async move { tokio::fs::File::open(&p).await.with_context(|| format!("cannot open {}", p.display())) }
    };
    let frame_file = open(frame).await?;
    let frame_size = frame_file.metadata().await?.len();
    let (reference_file, reference_size) = match reference {
        Some(r) => {
            let f = open(r).await?;
            let n = f.metadata().await?.len();
            (Some(f), n)
        }
        None => (None, 0),
    };
    let header = pb::SubmitJobRequest {
        message: Some(Message::Header(pb::SubmitHeader { options: Some(options), frame_size, reference_size })),
    };
    let chunks = move |file: tokio::fs::File, part: pb::Part| {
        // A read error ends the stream; the daemon then reports the missing bytes.
        tokio_util::io::ReaderStream::with_capacity(file, chunk).filter_map(move |r| {
            std::future::ready(match r {
                Ok(data) => Some(pb::SubmitJobRequest {
                    message: Some(Message::Chunk(pb::Chunk { part: part as i32, data: data.to_vec() })),
                }),
                Err(e) => {
                    tracing::error!(error = %e, "reading the upload failed");
                    None
                }
            })
        })
    };
    let reference_chunks = stream::iter(reference_file).flat_map(move |f| chunks(f, pb::Part::Reference));
    Ok(stream::once(async move { header }).chain(chunks(frame_file, pb::Part::Frame)).chain(reference_chunks))
}

fn grpc_error(s: tonic::Status) -> anyhow::Error {
    anyhow!("{:?}: {}", s.code(), s.message())
}

/// A gRPC job in the HTTP API's form.
fn job_from_pb(job: pb::Job) -> Result<JobView> {
    JobView::try_from(job).map_err(|e| anyhow!("the daemon's job is not valid: {e}"))
}

async fn submit_grpc(args: &SubmitArgs, options: &JobOptions, host_port: &str, wait: bool) -> Result<JobView> {
    let mut client = grpc_connect(host_port, args.token.as_ref().map(|t| t.0.as_str())).await?;
    let mut line = ProgressLine::new(args.quiet);
    let upload = upload_stream(options.into(), &args.frame, args.reference.as_deref(), 1 << 20).await?;
    let job = client.submit_job(upload).await.map_err(grpc_error)?.into_inner();
    line.say(&format!("submitted job {}", job.id));
    if !wait {
        return job_from_pb(job);
    }
    let mut events =
        client.watch_job(pb::WatchJobRequest { id: job.id.clone() }).await.map_err(grpc_error)?.into_inner();
    let mut last = job.clone();
    while let Some(ev) = events.message().await.map_err(grpc_error)? {
        match pb::EventType::try_from(ev.r#type).unwrap_or(pb::EventType::Unspecified) {
            pb::EventType::Queued => line.say(&format!("queued at position {}", ev.queue_position)),
            pb::EventType::Started => line.say(&format!("started (attempt {})", ev.attempt)),
            pb::EventType::Progress => {
                if let Some(p) = ev.progress {
                    line.tiles(p.tiles_done as u64, p.tiles_total as u64);
                }
            }
            t @ (pb::EventType::Succeeded | pb::EventType::Failed | pb::EventType::Cancelled) => {
                line.say(t.as_str_name().trim_start_matches("EVENT_TYPE_").to_ascii_lowercase().as_str());
                if let Some(j) = ev.job {
                    last = j;
                }
                break;
            }
            pb::EventType::Unspecified => {}
        }
    }
    if !matches!(
        pb::JobState::try_from(last.state),
        Ok(pb::JobState::Succeeded | pb::JobState::Failed | pb::JobState::Cancelled)
    ) {
        last = client.get_job(pb::GetJobRequest { id: job.id.clone() }).await.map_err(grpc_error)?.into_inner();
    }
    if let (Some(out), Ok(pb::JobState::Succeeded)) = (&args.output, pb::JobState::try_from(last.state)) {
        let n = fetch_grpc(&mut client, &job.id, out).await?;
        line.say(&format!("wrote {} ({n} bytes)", out.display()));
    }
    job_from_pb(last)
}

/// Downloads a result over gRPC into `path` atomically.
pub async fn fetch_grpc(client: &mut GrpcClient, id: &str, path: &Path) -> Result<u64> {
    let mut chunks =
        client.fetch_result(pb::FetchResultRequest { id: id.to_string() }).await.map_err(grpc_error)?.into_inner();
    let mut file = AsyncFile::create(path).await.with_context(|| format!("cannot create {}", path.display()))?;
    let mut n = 0u64;
    let mut total = None;
    while let Some(c) = chunks.message().await.map_err(grpc_error)? {
        if total.is_none() {
            total = Some(c.total_size);
        }
        file.write_all(&c.data).await?;
        n += c.data.len() as u64;
    }
    if total.is_some_and(|t| t != n) {
        bail!("the result stream ended after {n} of {} bytes", total.unwrap_or(0));
    }
    file.commit().await.with_context(|| format!("cannot write {}", path.display()))?;
    Ok(n)
}
