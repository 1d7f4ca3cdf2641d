//! The daemon's clients: `mcdenoise submit` ([`submit`]), and small HTTP and gRPC clients
//! for scripts and tests.

use std::path::Path;

use anyhow::{anyhow, bail, Context, Result};
use bytes::Bytes;
use futures_util::{stream, StreamExt, TryStreamExt};
use http_body_util::{combinators::BoxBody, BodyExt, Full, StreamBody};
use hyper::body::{Frame, Incoming};
use hyper::{Method, Request, Response, StatusCode};
use hyper_util::client::legacy::{connect::HttpConnector, Client};
use hyper_util::rt::TokioExecutor;
use serde_json::Value;

use crate::atomic::AsyncFile;
use crate::grpc::pb;
use crate::wire::JobView;

mod submit;

pub use submit::{submit, submit_async, FrameSpec, SubmitArgs};

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
        self.send_raw(method, path, headers, body)
            .await?
            .map_err(|e| anyhow!("request to {}{path} failed: {e}", self.base))
    }

    /// [`HttpClient::send`] with the transport's own error, which tells a refused
    /// connection (`is_connect`) from one lost mid-request.
    pub async fn send_raw(
        &self,
        method: Method,
        path: &str,
        headers: &[(&str, &str)],
        body: Body,
    ) -> Result<std::result::Result<Response<Incoming>, hyper_util::client::legacy::Error>> {
        let mut req = Request::builder().method(method).uri(format!("{}{path}", self.base));
        if let Some(t) = &self.token {
            req = req.header("authorization", format!("Bearer {t}"));
        }
        for (k, v) in headers {
            req = req.header(*k, *v);
        }
        Ok(self.client.request(req.body(body)?).await)
    }

    pub fn base(&self) -> &str {
        &self.base
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

pub(crate) fn api_error(status: StatusCode, body: &Value) -> anyhow::Error {
    let message = body["error"]["message"].as_str().map(str::to_owned).unwrap_or_else(|| body.to_string());
    anyhow!("{status}: {message}")
}

/// One Server-Sent Event.
#[derive(Clone, Debug, PartialEq)]
pub struct SseEvent {
    pub event: String,
    /// The `id:` field, when the daemon sent one.
    pub id: Option<String>,
    pub data: Value,
}

/// Reads `text/event-stream` events from a response, calling `on_event` for each until it
/// returns false or the stream ends.
pub async fn read_sse(resp: Response<Incoming>, mut on_event: impl FnMut(SseEvent) -> bool) -> Result<()> {
    let mut events = SseReader::new(resp);
    while let Some(ev) = events.next().await? {
        if !on_event(ev) {
            break;
        }
    }
    Ok(())
}

/// The events of a `text/event-stream` response, one at a time.
pub struct SseReader {
    body: Incoming,
    buffer: String,
}

impl SseReader {
    pub fn new(resp: Response<Incoming>) -> SseReader {
        SseReader { body: resp.into_body(), buffer: String::new() }
    }

    /// The next event; `None` at the end of the stream.
    pub async fn next(&mut self) -> Result<Option<SseEvent>> {
        loop {
            while let Some(end) = self.buffer.find("\n\n") {
                let block: String = self.buffer.drain(..end + 2).collect();
                let mut event = String::from("message");
                let mut id = None;
                let mut payload = String::new();
                for line in block.lines() {
                    if let Some(v) = line.strip_prefix("event:") {
                        event = v.trim().to_string();
                    } else if let Some(v) = line.strip_prefix("id:") {
                        id = Some(v.trim().to_string());
                    } else if let Some(v) = line.strip_prefix("data:") {
                        payload.push_str(v.strip_prefix(' ').unwrap_or(v));
                    }
                }
                if payload.is_empty() {
                    continue; // keep-alive comment
                }
                let data = serde_json::from_str(&payload).unwrap_or(Value::String(payload));
                return Ok(Some(SseEvent { event, id, data }));
            }
            match self.body.frame().await {
                None => return Ok(None),
                Some(frame) => {
                    if let Some(data) = frame?.data_ref() {
                        self.buffer.push_str(&String::from_utf8_lossy(data));
                    }
                }
            }
        }
    }
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
    grpc_client(channel, token)
}

/// A client on `channel` with the bearer token attached and the daemon's message limits.
pub fn grpc_client(channel: tonic::transport::Channel, token: Option<&str>) -> Result<GrpcClient> {
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

pub(crate) fn grpc_error(s: tonic::Status) -> anyhow::Error {
    anyhow!("{:?}: {}", s.code(), s.message())
}

/// A gRPC job in the HTTP API's form.
pub(crate) fn job_from_pb(job: pb::Job) -> Result<JobView> {
    JobView::try_from(job).map_err(|e| anyhow!("the daemon's job is not valid: {e}"))
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
