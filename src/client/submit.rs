//! `mcdenoise submit`: one frame, or a numbered sequence (`shot.####.exr --frames 1-240`),
//! to a daemon over HTTP or gRPC, with the progress on stderr and the results written by a
//! pattern.
//!
//! Refusals that pass (429 queue full or client limit, 503 loading or draining) are retried
//! after the daemon's `Retry-After`, and refused or lost connections after a backoff, until
//! `--retry-timeout`; a refused token (401, 403) never is. Every submission carries an
//! idempotency key (the caller's, or a random one per frame), so a retry cannot make a
//! second job. An upload cut off mid-way is checked against the token before it is retried,
//! so that a wrong token is reported as the daemon's 401 rather than as a broken connection.

use std::io::{IsTerminal, Write};
use std::path::{Path, PathBuf};
use std::str::FromStr;
use std::time::{Duration, Instant};

use anyhow::{anyhow, bail, Context, Result};
use bytes::Bytes;
use clap::Args;
use futures_util::StreamExt;
use hyper::{Method, StatusCode};
use serde_json::{json, Value};

use super::{
    api_error, body_bytes, body_file, fetch_grpc, grpc_client, grpc_error, job_from_pb, multipart_body, read_json,
    save_body, upload_stream, GrpcClient, HttpClient, SseReader,
};
use crate::config::Secret;
use crate::engine::Variant;
use crate::grpc::pb;
use crate::jobs::{JobOptions, JobState, Layer};
use crate::wire::{JobView, OptionsQuery};

#[derive(Args, Debug, Clone)]
pub struct SubmitArgs {
    /// Noisy frame (multi-layer OpenEXR, see docs/frame-layout.md); with --frames, a pattern
    /// whose run of `#` is the zero-padded frame number (`shot.####.exr`).
    pub frame: PathBuf,
    /// Daemon URL: `http://HOST:PORT` for the HTTP API, `grpc://HOST:PORT` for gRPC.
    #[arg(long, env = "MCDENOISE_SERVER", default_value = "http://127.0.0.1:8080")]
    pub server: String,
    /// Reference frame: the job reports RelMSE, DSSIM, PSNR and SMAPE of input and output
    /// (with --frames, a pattern like FRAME).
    #[arg(long)]
    pub reference: Option<PathBuf>,
    /// Wait until the job finishes, showing its progress on stderr.
    #[arg(long)]
    pub wait: bool,
    /// Write the denoised EXR here (implies --wait). With --frames, a pattern with `#`
    /// (default: FRAME with `denoised` before the frame number, `shot.denoised.####.exr`).
    #[arg(short, long)]
    pub output: Option<PathBuf>,
    /// Frame numbers of a sequence: `1-240`, `1-240x2` (every second), `1,5,9-12`. The frames
    /// are submitted --concurrency at a time, each result written as soon as it is done.
    #[arg(long, value_parser = FrameSpec::from_str)]
    pub frames: Option<FrameSpec>,
    /// Frames in flight at once with --frames (submitted, queued or running).
    #[arg(long, default_value_t = 8, value_parser = clap::value_parser!(u32).range(1..=1024))]
    pub concurrency: u32,
    /// How long refusals that pass (429, 503) and refused or lost connections are retried.
    #[arg(long, default_value = "10m", value_parser = humantime::parse_duration)]
    pub retry_timeout: Duration,
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
    /// Makes retries safe across runs: a second submission with the same key returns the
    /// same job (with --frames, `KEY-<frame>` per frame). Default: a random key per frame.
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
    /// How the renderer's AOV names are read: auto, a channel map's name (arnold,
    /// renderman, karma, vray, redshift, or one of the daemon's config), or `key=AOVs`
    /// pairs separated by `;` (docs/frame-layout.md).
    #[arg(long)]
    pub channel_map: Option<String>,
    /// Bearer token, when the daemon requires one.
    #[arg(long, env = "MCDENOISE_TOKEN", hide_env_values = true)]
    pub token: Option<Secret>,
    /// No progress on stderr.
    #[arg(short, long)]
    pub quiet: bool,
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
            channel_map: self.channel_map.clone(),
        })
    }
}

/// Most frames one `--frames` may name.
const MAX_FRAMES: usize = 1_000_000;

/// The frame numbers of `--frames`, in the order given.
#[derive(Clone, Debug, PartialEq)]
pub struct FrameSpec(pub Vec<u64>);

impl FromStr for FrameSpec {
    type Err = String;

    fn from_str(s: &str) -> std::result::Result<FrameSpec, String> {
        let number = |t: &str| {
            t.trim().parse::<u64>().map_err(|_| format!("{t:?} in --frames {s:?} is not a frame number (0 or more)"))
        };
        let mut frames = Vec::new();
        for part in s.split(',') {
            let (range, step) = match part.split_once('x') {
                Some((r, step)) => (r, number(step)?),
                None => (part, 1),
            };
            if step == 0 {
                return Err(format!("the step of {part:?} in --frames must be at least 1"));
            }
            let (first, last) = match range.split_once('-') {
                Some((a, b)) => (number(a)?, number(b)?),
                None => (number(range)?, number(range)?),
            };
            if last < first {
                return Err(format!("{part:?} in --frames ends before it starts"));
            }
            if (last - first) / step >= MAX_FRAMES as u64
                || frames.len() + ((last - first) / step) as usize >= MAX_FRAMES
            {
                return Err(format!("--frames {s:?} names more than {MAX_FRAMES} frames"));
            }
            frames.extend((first..=last).step_by(step as usize));
        }
        Ok(FrameSpec(frames))
    }
}

/// `pattern` with its last run of `#` replaced by `n`, zero-padded to the run's length;
/// `None` when it has no `#`.
pub fn frame_name(pattern: &str, n: u64) -> Option<String> {
    let (head, run, tail) = split_pattern(pattern)?;
    Some(format!("{head}{n:0w$}{tail}", w = run.len()))
}

fn split_pattern(pattern: &str) -> Option<(&str, &str, &str)> {
    let end = pattern.rfind('#')? + 1;
    let start = pattern[..end].trim_end_matches('#').len();
    Some((&pattern[..start], &pattern[start..end], &pattern[end..]))
}

/// The default output pattern of a sequence: `denoised` before the frame number
/// (`shot.####.exr` -> `shot.denoised.####.exr`, `shot_####.exr` -> `shot_denoised_####.exr`).
pub fn default_output_pattern(pattern: &str) -> Option<String> {
    let (head, run, tail) = split_pattern(pattern)?;
    Some(match head.chars().last() {
        Some(c @ ('.' | '_' | '-')) => format!("{head}denoised{c}{run}{tail}"),
        None | Some('/') => format!("{head}denoised.{run}{tail}"),
        Some(_) => format!("{head}.denoised.{run}{tail}"),
    })
}

/// Progress of one job on stderr: rewritten in place on a terminal, a line per 10 %
/// otherwise; percentage, elapsed time and an estimate of the time left.
struct ProgressLine {
    quiet: bool,
    tty: bool,
    last_decile: Option<u64>,
    in_place: bool,
    started: Option<Instant>,
    position: Option<u64>,
}

impl ProgressLine {
    fn new(quiet: bool) -> Self {
        ProgressLine {
            quiet,
            tty: std::io::stderr().is_terminal(),
            last_decile: None,
            in_place: false,
            started: None,
            position: None,
        }
    }

    fn say(&mut self, line: &str) {
        if self.quiet {
            return;
        }
        if std::mem::take(&mut self.in_place) {
            eprintln!();
        }
        eprintln!("{line}");
    }

    /// A queue position, said when it changes.
    fn queued(&mut self, position: Option<u64>) {
        if position.is_some() && position != self.position {
            self.position = position;
            self.say(&format!("queued at position {}", position.unwrap_or(0)));
        }
    }

    fn started(&mut self, attempt: u64) {
        self.started = Some(Instant::now());
        self.last_decile = None;
        self.say(&format!("started (attempt {attempt})"));
    }

    fn tiles(&mut self, done: u64, total: u64) {
        if self.quiet || total == 0 {
            return;
        }
        let done = done.min(total);
        let elapsed = self.started.get_or_insert_with(Instant::now).elapsed().as_secs_f64();
        let eta = if done > 0 {
            format!("ETA {:.1} s", elapsed * (total - done) as f64 / done as f64)
        } else {
            "ETA unknown".into()
        };
        let text = format!("{:3}% (tile {done}/{total}), {elapsed:.1} s elapsed, {eta}", done * 100 / total);
        if self.tty {
            eprint!("\r{text}   ");
            let _ = std::io::stderr().flush();
            self.in_place = true;
        } else {
            let decile = done * 10 / total;
            if self.last_decile != Some(decile) {
                eprintln!("{text}");
                self.last_decile = Some(decile);
            }
        }
    }
}

/// One frame to denoise.
#[derive(Clone, Debug)]
struct FrameJob {
    frame: PathBuf,
    reference: Option<PathBuf>,
    output: Option<PathBuf>,
    key: String,
}

/// What every frame of one `mcdenoise submit` shares.
struct Submitter {
    transport: Transport,
    options: JobOptions,
    retry_timeout: Duration,
    quiet: bool,
}

enum Transport {
    Http(HttpClient),
    Grpc(GrpcClient),
}

/// Longest single wait between retries.
const MAX_RETRY_WAIT: Duration = Duration::from_secs(60);
/// How often the queue position of a queued job is asked for.
const QUEUE_POLL: Duration = Duration::from_secs(2);

impl Submitter {
    fn new(args: &SubmitArgs) -> Result<Submitter> {
        let token = args.token.as_ref().map(|t| t.0.as_str());
        let transport = if let Some(rest) = args.server.strip_prefix("grpc://") {
            Transport::Grpc(grpc_lazy(rest, token)?)
        } else if args.server.starts_with("http://") {
            Transport::Http(HttpClient::new(&args.server, token))
        } else {
            bail!("--server must start with http:// or grpc:// (got {})", args.server)
        };
        Ok(Submitter { transport, options: args.options()?, retry_timeout: args.retry_timeout, quiet: args.quiet })
    }

    /// Waits `wait` before another attempt, or gives up with `reason` when the retry time
    /// is spent.
    async fn retry(&self, who: &str, reason: String, wait: Duration, deadline: Instant) -> Result<()> {
        let wait = wait.min(MAX_RETRY_WAIT);
        if Instant::now() + wait > deadline {
            bail!("{reason} (gave up after --retry-timeout {})", humantime::format_duration(self.retry_timeout));
        }
        if !self.quiet {
            eprintln!("{who}{reason}; retrying in {:.1} s", wait.as_secs_f64());
        }
        tokio::time::sleep(wait).await;
        Ok(())
    }

    /// Submits, and with `wait` follows the job to its end and writes its result.
    async fn run(&self, f: &FrameJob, who: &str, line: &mut ProgressLine, wait: bool) -> Result<JobView> {
        match &self.transport {
            Transport::Http(client) => self.run_http(client, f, who, line, wait).await,
            Transport::Grpc(client) => self.run_grpc(client.clone(), f, who, line, wait).await,
        }
    }

    async fn run_http(
        &self,
        client: &HttpClient,
        f: &FrameJob,
        who: &str,
        line: &mut ProgressLine,
        wait: bool,
    ) -> Result<JobView> {
        let job = self.post_http(client, f, who).await?;
        let id = job.id.clone();
        line.say(&format!("{who}submitted job {id}"));
        if !wait {
            return Ok(job);
        }
        let last = watch_http(client, &id, line).await?;
        if let (Some(out), JobState::Succeeded) = (&f.output, last.state) {
            let resp = client.get(&format!("/v1/jobs/{id}/result")).await?;
            if !resp.status().is_success() {
                let (s, v) = read_json(resp).await?;
                return Err(api_error(s, &v));
            }
            let n = save_body(resp, out).await?;
            line.say(&format!("{who}wrote {} ({n} bytes)", out.display()));
        }
        Ok(last)
    }

    /// `POST /v1/jobs`, retried as the module documentation says.
    async fn post_http(&self, client: &HttpClient, f: &FrameJob, who: &str) -> Result<JobView> {
        let deadline = Instant::now() + self.retry_timeout;
        let options = JobOptions { idempotency_key: Some(f.key.clone()), ..self.options.clone() };
        let mut attempt = 0;
        loop {
            attempt += 1;
            let (path, content_type, len, body) = match &f.reference {
                None => {
                    let (body, len) = body_file(&f.frame).await?;
                    // The key goes in its header.
                    let query = OptionsQuery { idempotency_key: None, ..OptionsQuery::from(&options) };
                    (format!("/v1/jobs?{}", query.encode()), "image/x-exr".to_string(), len, body)
                }
                Some(reference) => {
                    let json = serde_json::to_value(&options)?;
                    let (body, content_type, len) =
                        multipart_body(&json, &[("frame", &f.frame), ("reference", reference)]).await?;
                    ("/v1/jobs".to_string(), content_type, len, body)
                }
            };
            let len = len.to_string();
            let headers =
                [("content-type", content_type.as_str()), ("content-length", &len), ("idempotency-key", &f.key)];
            let (reason, wait) = match client.send_raw(Method::POST, &path, &headers, body).await? {
                Ok(resp) => {
                    let status = resp.status();
                    let retry_after = resp
                        .headers()
                        .get("retry-after")
                        .and_then(|v| v.to_str().ok())
                        .and_then(|v| v.trim().parse::<u64>().ok())
                        .map(Duration::from_secs);
                    let (_, body) = read_json(resp).await?;
                    if status.is_success() {
                        return serde_json::from_value(body).context("the daemon's answer is not a job");
                    }
                    if status != StatusCode::TOO_MANY_REQUESTS && status != StatusCode::SERVICE_UNAVAILABLE {
                        return Err(api_error(status, &body));
                    }
                    (api_error(status, &body).to_string(), retry_after.unwrap_or(Duration::from_secs(1)))
                }
                Err(e) if e.is_connect() => (format!("cannot connect to {}: {e}", client.base()), backoff(attempt)),
                Err(e) => {
                    if let Some(refusal) = refused_token(client).await {
                        return Err(refusal);
                    }
                    (format!("the upload to {} was cut off: {e}", client.base()), backoff(attempt))
                }
            };
            self.retry(who, reason, wait, deadline).await?;
        }
    }

    async fn run_grpc(
        &self,
        mut client: GrpcClient,
        f: &FrameJob,
        who: &str,
        line: &mut ProgressLine,
        wait: bool,
    ) -> Result<JobView> {
        let deadline = Instant::now() + self.retry_timeout;
        let options = JobOptions { idempotency_key: Some(f.key.clone()), ..self.options.clone() };
        let mut attempt = 0;
        let job = loop {
            attempt += 1;
            let upload = upload_stream((&options).into(), &f.frame, f.reference.as_deref(), 1 << 20).await?;
            match client.submit_job(upload).await {
                Ok(job) => break job.into_inner(),
                Err(s) if matches!(s.code(), tonic::Code::ResourceExhausted | tonic::Code::Unavailable) => {
                    let retry_after = s
                        .metadata()
                        .get("retry-after")
                        .and_then(|v| v.to_str().ok())
                        .and_then(|v| v.parse::<u64>().ok())
                        .map(Duration::from_secs);
                    let wait = retry_after.unwrap_or_else(|| backoff(attempt));
                    self.retry(who, grpc_error(s).to_string(), wait, deadline).await?;
                }
                Err(s) => return Err(grpc_error(s)),
            }
        };
        line.say(&format!("{who}submitted job {}", job.id));
        if !wait {
            return job_from_pb(job);
        }
        let mut events =
            client.watch_job(pb::WatchJobRequest { id: job.id.clone() }).await.map_err(grpc_error)?.into_inner();
        let mut last = job.clone();
        while let Some(ev) = events.message().await.map_err(grpc_error)? {
            match pb::EventType::try_from(ev.r#type).unwrap_or(pb::EventType::Unspecified) {
                pb::EventType::Queued => line.queued(Some(ev.queue_position)),
                pb::EventType::Started => line.started(ev.attempt as u64),
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
                pb::EventType::Deleted => bail!("job {} was deleted before it finished", job.id),
                pb::EventType::Unspecified => {}
            }
        }
        if !matches!(
            pb::JobState::try_from(last.state),
            Ok(pb::JobState::Succeeded | pb::JobState::Failed | pb::JobState::Cancelled)
        ) {
            last = client.get_job(pb::GetJobRequest { id: job.id.clone() }).await.map_err(grpc_error)?.into_inner();
        }
        if let (Some(out), Ok(pb::JobState::Succeeded)) = (&f.output, pb::JobState::try_from(last.state)) {
            let n = fetch_grpc(&mut client, &job.id, out).await?;
            line.say(&format!("{who}wrote {} ({n} bytes)", out.display()));
        }
        job_from_pb(last)
    }
}

/// A gRPC client that connects on first use (so a daemon not up yet is retried like a
/// refused connection).
fn grpc_lazy(host_port: &str, token: Option<&str>) -> Result<GrpcClient> {
    let channel = tonic::transport::Endpoint::from_shared(format!("http://{host_port}"))
        .with_context(|| format!("grpc://{host_port} is not a valid address"))?
        .connect_lazy();
    grpc_client(channel, token)
}

fn backoff(attempt: u32) -> Duration {
    Duration::from_millis((250u64 << attempt.min(6)).min(10_000))
}

/// After an upload was cut off: the daemon's 401 or 403 when it refuses this client's
/// token (it may answer before reading the body, and close), else `None`.
async fn refused_token(client: &HttpClient) -> Option<anyhow::Error> {
    let resp = client.get("/v1/jobs?limit=1").await.ok()?;
    let status = resp.status();
    if status != StatusCode::UNAUTHORIZED && status != StatusCode::FORBIDDEN {
        return None;
    }
    let (status, body) = read_json(resp).await.ok()?;
    Some(api_error(status, &body))
}

/// Follows a job's events to its end: the terminal job.
async fn watch_http(client: &HttpClient, id: &str, line: &mut ProgressLine) -> Result<JobView> {
    let resp = client.get(&format!("/v1/jobs/{id}/events")).await?;
    if !resp.status().is_success() {
        let (s, v) = read_json(resp).await?;
        return Err(api_error(s, &v));
    }
    let mut events = SseReader::new(resp);
    let mut queued = false;
    let mut poll = tokio::time::interval(QUEUE_POLL);
    poll.reset();
    loop {
        tokio::select! {
            ev = events.next() => {
                let Some(ev) = ev? else { break };
                match ev.event.as_str() {
                    "queued" => {
                        queued = true;
                        line.queued(ev.data["queue_position"].as_u64());
                    }
                    "started" => {
                        queued = false;
                        line.started(ev.data["attempt"].as_u64().unwrap_or(1));
                    }
                    "progress" => line.tiles(
                        ev.data["tiles_done"].as_u64().unwrap_or(0),
                        ev.data["tiles_total"].as_u64().unwrap_or(0),
                    ),
                    "succeeded" | "failed" | "cancelled" => {
                        line.say(&ev.event);
                        return serde_json::from_value(ev.data).context("the daemon's event is not a job");
                    }
                    "deleted" => bail!("job {id} was deleted before it finished"),
                    _ => {}
                }
            }
            _ = poll.tick(), if queued => {
                let job = client.json(Method::GET, &format!("/v1/jobs/{id}"), &[], body_bytes(Bytes::new())).await;
                if let Ok((StatusCode::OK, job)) = job {
                    if job["state"] == "queued" {
                        line.queued(job["queue_position"].as_u64());
                    }
                }
            }
        }
    }
    // The stream ended early (daemon shutting down): report the latest state.
    let (s, v) = client.json(Method::GET, &format!("/v1/jobs/{id}"), &[], body_bytes(Bytes::new())).await?;
    if !s.is_success() {
        return Err(api_error(s, &v));
    }
    serde_json::from_value(v).context("the daemon's answer is not a job")
}

fn random_key() -> String {
    format!("mcdenoise-submit-{}", uuid::Uuid::now_v7().simple())
}

/// `mcdenoise submit`.
pub fn submit(args: SubmitArgs) -> Result<()> {
    let runtime = tokio::runtime::Builder::new_current_thread().enable_all().build()?;
    if let Some(frames) = args.frames.clone() {
        let (done, failed) = runtime.block_on(submit_sequence(&args, &frames))?;
        if !failed.is_empty() {
            let list: Vec<String> = failed.iter().map(u64::to_string).collect();
            bail!("{} of {} frames failed: {}", failed.len(), done + failed.len(), list.join(", "));
        }
        return Ok(());
    }
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

/// Submits one frame, optionally waits and downloads; returns the job.
pub async fn submit_async(args: SubmitArgs) -> Result<JobView> {
    let cx = Submitter::new(&args)?;
    let wait = args.wait || args.output.is_some();
    let f = FrameJob {
        frame: args.frame.clone(),
        reference: args.reference.clone(),
        output: args.output.clone(),
        key: args.idempotency_key.clone().unwrap_or_else(random_key),
    };
    cx.run(&f, "", &mut ProgressLine::new(args.quiet), wait).await
}

/// Denoises the frames of `--frames`, `--concurrency` at a time: a line per frame on stderr,
/// a JSON object per frame on stdout (`frame`, `input`, `output`, and `job` or `error`).
/// Returns how many succeeded and the numbers of those that did not.
async fn submit_sequence(args: &SubmitArgs, frames: &FrameSpec) -> Result<(usize, Vec<u64>)> {
    let text = |p: &Path| p.to_str().map(str::to_owned).ok_or_else(|| anyhow!("{} is not UTF-8", p.display()));
    let input = text(&args.frame)?;
    if !input.contains('#') {
        bail!("--frames needs FRAME to be a pattern with # for the frame number, like shot.####.exr (got {input})");
    }
    let output = match &args.output {
        Some(o) => text(o)?,
        None => default_output_pattern(&input).expect("the pattern has a #"),
    };
    if !output.contains('#') {
        bail!("with --frames, --output must be a pattern with # for the frame number (got {output})");
    }
    let reference = args.reference.as_deref().map(text).transpose()?;
    if reference.as_ref().is_some_and(|r| !r.contains('#')) {
        bail!("with --frames, --reference must be a pattern with # for the frame number");
    }
    let cx = Submitter::new(args)?;
    let name = |p: &str, n| PathBuf::from(frame_name(p, n).expect("the pattern has a #"));
    let jobs = frames.0.iter().map(|&n| {
        let f = FrameJob {
            frame: name(&input, n),
            reference: reference.as_deref().map(|r| name(r, n)),
            output: Some(name(&output, n)),
            key: args.idempotency_key.as_ref().map_or_else(random_key, |k| format!("{k}-{n}")),
        };
        let cx = &cx;
        async move {
            let t = Instant::now();
            let result = cx.run(&f, &format!("frame {n}: "), &mut ProgressLine::new(true), true).await;
            (n, f, result, t.elapsed())
        }
    });
    let mut results = futures_util::stream::iter(jobs).buffer_unordered(args.concurrency as usize);
    let (mut done, mut failed) = (0, Vec::new());
    let total = frames.0.len();
    while let Some((n, f, result, took)) = results.next().await {
        let output = f.output.as_deref().unwrap_or(Path::new("")).display().to_string();
        let mut row = json!({ "frame": n, "input": f.frame.display().to_string(), "output": output });
        let outcome = match result {
            Ok(job) if job.state == JobState::Succeeded => {
                done += 1;
                row["job"] = serde_json::to_value(&job)?;
                format!("succeeded in {:.1} s -> {output}", took.as_secs_f64())
            }
            Ok(job) => {
                failed.push(n);
                let why = job.error.as_ref().map(|e| format!(": {}", e.message)).unwrap_or_default();
                row["job"] = serde_json::to_value(&job)?;
                format!("{}{why}", job.state.name())
            }
            Err(e) => {
                failed.push(n);
                row["error"] = Value::String(format!("{e:#}"));
                format!("failed: {e:#}")
            }
        };
        println!("{row}");
        if !args.quiet {
            eprintln!("frame {n}: {outcome} [{}/{total}]", done + failed.len());
        }
    }
    failed.sort_unstable();
    Ok((done, failed))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frame_specs_list_their_frames_in_order_and_refuse_nonsense() {
        assert_eq!(FrameSpec::from_str("1-4").unwrap().0, vec![1, 2, 3, 4]);
        assert_eq!(FrameSpec::from_str("1-9x4").unwrap().0, vec![1, 5, 9]);
        assert_eq!(FrameSpec::from_str("7,1,3-4").unwrap().0, vec![7, 1, 3, 4]);
        for bad in ["", "a-3", "5-1", "1-3x0", "-2", "1-2000000"] {
            assert!(FrameSpec::from_str(bad).is_err(), "{bad:?}");
        }
    }

    #[test]
    fn patterns_pad_the_last_run_of_hashes() {
        assert_eq!(frame_name("sh/beauty.####.exr", 12).unwrap(), "sh/beauty.0012.exr");
        assert_eq!(frame_name("v#/b_##.exr", 123).unwrap(), "v#/b_123.exr");
        assert_eq!(frame_name("plain.exr", 1), None);
        assert_eq!(default_output_pattern("sh/beauty.####.exr").unwrap(), "sh/beauty.denoised.####.exr");
        assert_eq!(default_output_pattern("b_####.exr").unwrap(), "b_denoised_####.exr");
        assert_eq!(default_output_pattern("sh/####.exr").unwrap(), "sh/denoised.####.exr");
        assert_eq!(default_output_pattern("b####.exr").unwrap(), "b.denoised.####.exr");
    }
}
