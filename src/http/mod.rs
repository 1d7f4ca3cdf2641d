//! The HTTP transport (axum): JSON under `/v1`, Server-Sent Events for progress, the
//! EXR result as a download, PNG previews, health probes and Prometheus metrics, and the
//! web dashboard ([`dashboard`]). Every handler is a thin translation onto [`JobService`];
//! the reference is `docs/api.md` and the OpenAPI document served at `/v1/openapi.json`.

pub mod dashboard;
mod error;
pub mod multipart;

use std::convert::Infallible;
use std::future::Future;
use std::pin::Pin;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

use axum::body::Body;
use axum::extract::{ConnectInfo, DefaultBodyLimit, Extension, MatchedPath, Path, Query, Request, State};
use axum::http::{header, HeaderMap, HeaderValue, StatusCode};
use axum::middleware::{self, Next};
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use axum::{Json, Router};
use futures_util::{Stream, StreamExt};
use serde::Deserialize;
use serde_json::{json, Value};
use tokio_util::sync::CancellationToken;

pub use error::ApiError;
use multipart::{FormData, FormError};

use crate::auth::{Caller, ClientId, Tokens};
use crate::error::Error;
use crate::jobs::{
    Admission, JobEvent, JobOptions, JobService, JobState, JobStatus, ListFilter, PreviewImage, UploadPart,
};
use crate::wire::{JobList, JobView, OptionsQuery};

/// The OpenAPI 3.1 description of this API.
pub const OPENAPI: &str = include_str!("openapi.json");

/// Shared by every handler.
#[derive(Clone)]
pub struct AppState {
    pub service: JobService,
    /// Accepted bearer tokens; none disables authentication.
    pub tokens: Arc<Tokens>,
    /// Cancelled when the server stops: open event streams end.
    pub shutdown: CancellationToken,
    /// What `/v1/info` says of the process.
    pub info: Arc<Info>,
}

/// The process's identity for `/v1/info`: when it started and its settings (without
/// secrets: [`crate::config::ServeArgs::summary`]).
pub struct Info {
    started: std::time::SystemTime,
    settings: Value,
}

impl Info {
    pub fn new(settings: Value) -> Info {
        Info { started: std::time::SystemTime::now(), settings }
    }
}

/// Every route that needs a bearer token (when tokens are configured), as
/// `(method, path template)`. The router is built from this table, and a test calls each
/// entry without a token and checks the OpenAPI document lists exactly these plus
/// [`OPEN_ROUTES`].
pub const PROTECTED_ROUTES: &[(&str, &str)] = &[
    ("POST", "/v1/jobs"),
    ("GET", "/v1/jobs"),
    ("GET", "/v1/jobs/{id}"),
    ("DELETE", "/v1/jobs/{id}"),
    ("POST", "/v1/jobs/{id}/cancel"),
    ("GET", "/v1/jobs/{id}/events"),
    ("GET", "/v1/jobs/{id}/result"),
    ("GET", "/v1/jobs/{id}/preview"),
    ("GET", "/v1/stats"),
    ("GET", "/v1/models"),
    ("GET", "/v1/info"),
    ("GET", "/v1/openapi.json"),
    ("GET", "/metrics"),
];

/// The probes, open to anyone (Kubernetes calls them without credentials).
pub const OPEN_ROUTES: &[(&str, &str)] = &[("GET", "/livez"), ("GET", "/readyz")];

fn handler(method: &str, path: &str) -> axum::routing::MethodRouter<AppState> {
    match (method, path) {
        ("POST", "/v1/jobs") => post(submit),
        ("GET", "/v1/jobs") => get(list),
        ("GET", "/v1/jobs/{id}") => get(get_job),
        ("DELETE", "/v1/jobs/{id}") => axum::routing::delete(delete_job),
        ("POST", "/v1/jobs/{id}/cancel") => post(cancel),
        ("GET", "/v1/jobs/{id}/events") => get(events),
        ("GET", "/v1/jobs/{id}/result") => get(result),
        ("GET", "/v1/jobs/{id}/preview") => get(preview),
        ("GET", "/v1/stats") => get(stats),
        ("GET", "/v1/models") => get(models),
        ("GET", "/v1/info") => get(info),
        ("GET", "/v1/openapi.json") => get(openapi),
        ("GET", "/metrics") => get(metrics),
        ("GET", "/livez") => get(livez),
        ("GET", "/readyz") => get(readyz),
        other => unreachable!("no handler for {other:?}"),
    }
}

fn routes(table: &[(&str, &str)]) -> Router<AppState> {
    let mut router = Router::new();
    for (method, path) in table {
        router = router.route(path, handler(method, path));
    }
    router
}

/// The whole HTTP API and the dashboard. Serve it through [`per_peer`]: without
/// authentication, clients are told apart by their address.
pub fn router(state: AppState) -> Router {
    open_and_protected(&state, PROTECTED_ROUTES, "no such route")
        .merge(dashboard::routes())
        // Uploads are streamed to disk and limited by `--max-body-bytes` as they arrive.
        .layer(DefaultBodyLimit::disable())
        .layer(middleware::from_fn_with_state(state.clone(), observe))
        .with_state(state)
}

/// The probe listener's routes (`--probe-http`): the open probes and `/metrics` (which
/// needs a token as on the API port).
pub fn probe_router(state: AppState) -> Router {
    let not_found = "no such route (the probe port serves /livez, /readyz and /metrics)";
    open_and_protected(&state, &[("GET", "/metrics")], not_found).with_state(state)
}

/// [`OPEN_ROUTES`] and the `protected` ones behind the token check, JSON errors for every
/// answer, `not_found` for any other path.
fn open_and_protected(state: &AppState, protected: &[(&str, &str)], not_found: &'static str) -> Router<AppState> {
    let protected = routes(protected).route_layer(middleware::from_fn_with_state(state.clone(), authenticate));
    routes(OPEN_ROUTES)
        .merge(protected)
        .fallback(move || async move { ApiError::from(Error::NotFound(not_found.into())) })
        .layer(middleware::from_fn(json_errors))
}

/// Gives every error answer the JSON shape of [`ApiError`], including those the router
/// and axum's extractors write as plain text (405, a path that is not UTF-8, a bad query):
/// their status and headers (`Allow`) are kept, their text becomes the message.
async fn json_errors(request: Request, next: Next) -> Response {
    let (method, path) = (request.method().clone(), request.uri().path().to_owned());
    let response = next.run(request).await;
    let status = response.status();
    let is_json =
        response.headers().get(header::CONTENT_TYPE).is_some_and(|v| v.as_bytes().starts_with(b"application/json"));
    if status.as_u16() < 400 || is_json {
        return response;
    }
    let (mut parts, body) = response.into_parts();
    let text = axum::body::to_bytes(body, 4096).await.map(|b| String::from_utf8_lossy(&b).trim().to_string());
    let path = crate::error::truncate(&path, crate::error::ECHO_CHARS);
    let (code, message) = match status {
        StatusCode::METHOD_NOT_ALLOWED => {
            let allowed = parts.headers.get(header::ALLOW).and_then(|v| v.to_str().ok()).unwrap_or("");
            ("method_not_allowed", format!("{method} is not allowed on {path} (allowed: {allowed})"))
        }
        StatusCode::NOT_FOUND => ("not_found", format!("no route {method} {path}")),
        _ => {
            let code = if status.is_client_error() { "bad_request" } else { "internal" };
            let text = text.ok().filter(|t| !t.is_empty());
            let text = text.unwrap_or_else(|| status.canonical_reason().unwrap_or("error").to_string());
            (code, crate::error::truncate(&text, 256).into_owned())
        }
    };
    let body = serde_json::to_vec(&json!({ "error": { "code": code, "message": message } })).unwrap_or_default();
    parts.headers.insert(header::CONTENT_TYPE, HeaderValue::from_static("application/json"));
    parts.headers.remove(header::CONTENT_LENGTH);
    Response::from_parts(parts, Body::from(body))
}

/// Logs each request, counts it by route template and status, and runs it in an
/// `http.request` span (exported with `--otlp-endpoint`: [`crate::otlp`]) that carries the
/// job id of a job's route or of a submission, and continues a client's `traceparent`.
async fn observe(State(app): State<AppState>, request: Request, next: Next) -> Response {
    let route = request.extensions().get::<MatchedPath>().map(|p| p.as_str().to_owned());
    let method = request.method().clone();
    let t = std::time::Instant::now();
    let span = {
        let route = route.as_deref().unwrap_or("unmatched");
        let job_id = route.starts_with("/v1/jobs/{id}").then(|| request.uri().path().split('/').nth(3)).flatten();
        let span = tracing::info_span!(
            "http.request",
            otel.name = %format!("{method} {route}"),
            otel.kind = "server",
            http.request.method = %method,
            http.route = route,
            http.response.status_code = tracing::field::Empty,
            job_id = job_id,
        );
        let header = |name: &str| request.headers().get(name).and_then(|v| v.to_str().ok());
        crate::otlp::continue_trace(&span, header("traceparent"), header("tracestate"));
        span
    };
    let response = tracing::Instrument::instrument(next.run(request), span.clone()).await;
    let route = route.as_deref().unwrap_or("unmatched");
    let status = response.status();
    span.record("http.response.status_code", status.as_u16());
    app.service.telemetry().http_request(route, status.as_u16());
    let ms = t.elapsed().as_secs_f64() * 1e3;
    // 503 is an expected answer (loading, draining): not an error of the daemon.
    if status.is_server_error() && status != StatusCode::SERVICE_UNAVAILABLE {
        tracing::error!(%method, route, status = status.as_u16(), ms, "http request");
    } else if route != "/livez" && route != "/readyz" && route != "/metrics" {
        tracing::debug!(%method, route, status = status.as_u16(), ms, "http request");
    }
    response
}

/// The address of the other end of a connection, plain or TLS: a `ConnectInfo<Peer>`
/// extension on every request (see [`per_peer`]).
#[derive(Clone, Copy, Debug)]
pub struct Peer(pub std::net::SocketAddr);

/// The router as the service of one connection from `peer` (for [`crate::conn::serve`]).
pub fn per_peer(
    router: Router,
) -> impl Fn(std::net::SocketAddr) -> crate::conn::WithExtension<Router, ConnectInfo<Peer>> {
    move |peer| crate::conn::WithExtension::new(router.clone(), ConnectInfo(Peer(peer)))
}

/// Checks the bearer token and records who is calling (a [`Caller`] extension). A refused
/// request is logged and, for a submission, counted as a rejection; the body it was
/// sending is read and discarded (as far as [`DrainOnDrop`] goes), so that a client in the
/// middle of an upload reads the 401 instead of a reset connection.
async fn authenticate(State(app): State<AppState>, mut request: Request, next: Next) -> Response {
    let peer = request.extensions().get::<ConnectInfo<Peer>>().map(|c| c.0 .0);
    let authorization = request.headers().get(header::AUTHORIZATION).and_then(|v| v.to_str().ok());
    match app.tokens.authenticate(authorization, peer, "header Authorization") {
        Ok(caller) => {
            request.extensions_mut().insert(caller);
            next.run(request).await
        }
        Err(e) => {
            let route = request.extensions().get::<MatchedPath>().map_or("unmatched", |p| p.as_str()).to_owned();
            let submission = request.method() == axum::http::Method::POST && route == "/v1/jobs";
            app.service.note_refused_caller(&e, "http", &route, peer, submission);
            drop(DrainOnDrop(Some(request.into_body())));
            ApiError::from(e).into_response()
        }
    }
}

// --- Health, metrics, models ---------------------------------------------------------------

async fn livez() -> Json<Value> {
    Json(json!({ "status": "alive" }))
}

async fn readyz(State(app): State<AppState>) -> Response {
    let phase = app.service.phase();
    let storage = app.service.storage_problem();
    let ready = app.service.is_ready();
    let code = if ready { StatusCode::OK } else { StatusCode::SERVICE_UNAVAILABLE };
    let storage = match storage {
        None => json!({ "ok": true }),
        Some(p) => json!({ "ok": false, "kind": p.kind, "reason": p.reason }),
    };
    (code, Json(json!({ "ready": ready, "phase": phase, "storage": storage }))).into_response()
}

async fn metrics(State(app): State<AppState>, Extension(caller): Extension<Caller>) -> Response {
    if !caller.metrics {
        return ApiError::from(Error::Forbidden("the metrics need a token with the operator scope".into()))
            .into_response();
    }
    (
        [(header::CONTENT_TYPE, "application/openmetrics-text; version=1.0.0; charset=utf-8")],
        app.service.telemetry().render(),
    )
        .into_response()
}

async fn models(State(app): State<AppState>) -> Result<Json<Value>, ApiError> {
    let models = app.service.models().ok_or_else(|| Error::Unavailable("the models are still loading".into()))?;
    let s = app.service.settings();
    Ok(Json(json!({
        "contract": crate::engine::contract::CONTRACT_VERSION,
        "tile": s.engine.tile,
        "workers": s.workers,
        "threads_per_worker": s.engine.threads,
        "models": models,
    })))
}

/// `GET /v1/info`: version, device, phase, the loaded models (null while loading), uptime,
/// and for callers allowed the metrics the settings.
async fn info(State(app): State<AppState>, Extension(caller): Extension<Caller>) -> Json<Value> {
    let s = app.service.settings();
    let started = app.info.started;
    let uptime = started.elapsed().unwrap_or_default().as_secs_f64();
    let started_ms = started.duration_since(std::time::UNIX_EPOCH).unwrap_or_default().as_millis() as i64;
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    Json(json!({
        "version": env!("CARGO_PKG_VERSION"),
        "onnxruntime": crate::engine::runtime::ORT_VERSION,
        "started_at": crate::jobs::record::rfc3339(started_ms),
        "uptime_seconds": (uptime * 1e3).round() / 1e3,
        "phase": app.service.phase(),
        "ready": app.service.is_ready(),
        "device": {
            "kind": s.engine.device.to_string(),
            "runs_on": app.service.device().map(|d| d.to_string()),
            "cores": cores,
            "workers": s.workers,
            "threads_per_worker": s.engine.threads,
        },
        "models": app.service.models(),
        "channel_maps": s.channel_maps.iter().map(|m| json!({ "name": m.name, "renderer": m.renderer })).collect::<Vec<_>>(),
        "caller": { "scope": caller.scope.name() },
        "settings": if caller.metrics { app.info.settings.clone() } else { Value::Null },
    }))
}

async fn openapi() -> Response {
    ([(header::CONTENT_TYPE, "application/json")], OPENAPI).into_response()
}

// --- Jobs ----------------------------------------------------------------------------------

/// The options of a raw-body submission: the query string, and the `Idempotency-Key`
/// header unless the query names a key.
fn options_from_query(q: OptionsQuery, headers: &HeaderMap) -> Result<JobOptions, Error> {
    let mut options = q.parse().map_err(Error::BadRequest)?;
    if options.idempotency_key.is_none() {
        options.idempotency_key = idempotency_header(headers)?;
    }
    Ok(options)
}

/// The `Idempotency-Key` header; one that is not visible ASCII is refused rather than
/// ignored (ignoring it would turn a retry into a second job).
fn idempotency_header(headers: &HeaderMap) -> Result<Option<String>, Error> {
    match headers.get("idempotency-key") {
        None => Ok(None),
        Some(v) => v.to_str().map(|s| Some(s.to_owned())).map_err(|_| {
            Error::BadRequest("the Idempotency-Key header must be visible ASCII (letters, digits, punctuation)".into())
        }),
    }
}

fn accepted(status: &JobStatus, replayed: bool) -> Response {
    tracing::Span::current().record("job_id", status.record.id.as_str());
    let mut response = (StatusCode::ACCEPTED, Json(JobView::from(status))).into_response();
    let h = response.headers_mut();
    if let Ok(v) = HeaderValue::from_str(&format!("/v1/jobs/{}", status.record.id)) {
        h.insert(header::LOCATION, v);
    }
    if replayed {
        h.insert("idempotent-replayed", HeaderValue::from_static("true"));
    }
    response
}

/// `POST /v1/jobs`: a raw EXR body (options in the query string) or multipart
/// (`options` JSON part first, then `frame`, then optionally `reference`).
async fn submit(
    State(app): State<AppState>,
    Extension(caller): Extension<Caller>,
    request: Request,
) -> Result<Response, ApiError> {
    let client = caller.id;
    let gap = app.service.settings().upload_timeout;
    let stalled = Arc::new(AtomicBool::new(false));
    let request = request.map(|body| Body::new(Progress::new(DrainOnDrop(Some(body)), gap, stalled.clone())));
    let service = app.service.clone();
    let mut result = submit_inner(app, client.clone(), request).await;
    if result.is_err() && stalled.load(Ordering::Acquire) {
        let message = format!(
            "no upload bytes arrived for {} (--upload-timeout); the upload was dropped",
            humantime::format_duration(gap)
        );
        tracing::warn!(client = client.as_str(), transport = "http", "upload timed out: {message}");
        result = Err(Error::Timeout(message).into());
    }
    if let Err(e) = &result {
        service.note_rejection(&e.0);
    }
    result
}

/// An upload body that fails when no byte arrives for `gap` (`--upload-timeout`), setting
/// `stalled`; its handler then answers 408 and drops the upload, releasing its slot.
struct Progress {
    inner: DrainOnDrop,
    gap: Duration,
    deadline: Pin<Box<tokio::time::Sleep>>,
    stalled: Arc<AtomicBool>,
}

impl Progress {
    fn new(inner: DrainOnDrop, gap: Duration, stalled: Arc<AtomicBool>) -> Progress {
        Progress { inner, gap, deadline: Box::pin(tokio::time::sleep(gap)), stalled }
    }
}

impl http_body::Body for Progress {
    type Data = bytes::Bytes;
    type Error = axum::Error;

    fn poll_frame(
        mut self: Pin<&mut Self>,
        cx: &mut std::task::Context<'_>,
    ) -> std::task::Poll<Option<Result<http_body::Frame<bytes::Bytes>, axum::Error>>> {
        let this = &mut *self;
        match Pin::new(&mut this.inner).poll_frame(cx) {
            std::task::Poll::Pending => {
                if this.deadline.as_mut().poll(cx).is_ready() {
                    this.stalled.store(true, Ordering::Release);
                    return std::task::Poll::Ready(Some(Err(axum::Error::new("the upload stalled"))));
                }
                std::task::Poll::Pending
            }
            ready => {
                let next = tokio::time::Instant::now() + this.gap;
                this.deadline.as_mut().reset(next);
                ready
            }
        }
    }

    fn is_end_stream(&self) -> bool {
        self.inner.is_end_stream()
    }

    fn size_hint(&self) -> http_body::SizeHint {
        self.inner.size_hint()
    }
}

async fn submit_inner(app: AppState, client: ClientId, request: Request) -> Result<Response, ApiError> {
    let max = app.service.settings().max_body_bytes;
    let declared =
        request.headers().get(header::CONTENT_LENGTH).and_then(|v| v.to_str().ok()).and_then(|v| v.parse::<u64>().ok());
    if declared.is_some_and(|n| n > max) {
        return Err(Error::TooLarge(format!("the upload is over the limit of {max} bytes")).into());
    }
    let query = match request.uri().query() {
        None => OptionsQuery::default(),
        Some(q) => serde_urlencoded_query(q)?,
    };
    let options = options_from_query(query, request.headers())?;
    let content_type =
        request.headers().get(header::CONTENT_TYPE).and_then(|v| v.to_str().ok()).unwrap_or("").to_ascii_lowercase();
    if content_type.starts_with("multipart/form-data") {
        return submit_multipart(app, client, options, request).await;
    }
    if !(content_type.is_empty()
        || content_type.starts_with("image/x-exr")
        || content_type.starts_with("application/octet-stream"))
    {
        return Err(Error::BadRequest(format!(
            "unsupported content type `{content_type}`: send the frame as image/x-exr or multipart/form-data"
        ))
        .into());
    }
    let mut ticket = match app.service.admit(options, "http", &client)? {
        Admission::Existing(status) => return Ok(accepted(&status, true)),
        Admission::New(t) => t,
    };
    let mut sink = ticket.sink(UploadPart::Frame).await?;
    let mut body = request.into_body().into_data_stream();
    while let Some(chunk) = body.next().await {
        let chunk = chunk.map_err(|e| Error::BadRequest(format!("the upload was interrupted: {e}")))?;
        sink.write(&chunk).await?;
    }
    if sink.written() == 0 {
        return Err(Error::BadRequest("the request body is empty: send the EXR frame as the body".into()).into());
    }
    ticket.finish(sink).await?;
    let status = ticket.commit().await?;
    Ok(accepted(&status, false))
}

/// Unread upload bytes discarded after an early answer, at most (beyond: the connection
/// is closed).
const DRAIN_BYTES: u64 = 64 << 20;
/// Time given to a client to finish sending after an early answer.
const DRAIN_TIME: Duration = Duration::from_secs(10);

/// The body of an upload. Dropped before its end (a refusal such as 429, or an error
/// mid-upload), the rest is read and discarded in the background, up to [`DRAIN_BYTES`] and
/// [`DRAIN_TIME`]: the answer goes out at once, and a client still sending reads it instead
/// of a reset connection.
struct DrainOnDrop(Option<Body>);

impl http_body::Body for DrainOnDrop {
    type Data = bytes::Bytes;
    type Error = axum::Error;

    fn poll_frame(
        self: std::pin::Pin<&mut Self>,
        cx: &mut std::task::Context<'_>,
    ) -> std::task::Poll<Option<Result<http_body::Frame<bytes::Bytes>, axum::Error>>> {
        match self.get_mut().0.as_mut() {
            Some(body) => std::pin::Pin::new(body).poll_frame(cx),
            None => std::task::Poll::Ready(None),
        }
    }

    fn is_end_stream(&self) -> bool {
        self.0.as_ref().is_none_or(http_body::Body::is_end_stream)
    }

    fn size_hint(&self) -> http_body::SizeHint {
        self.0.as_ref().map(http_body::Body::size_hint).unwrap_or_default()
    }
}

impl Drop for DrainOnDrop {
    fn drop(&mut self) {
        let Some(body) = self.0.take() else { return };
        if http_body::Body::is_end_stream(&body) {
            return;
        }
        let Ok(runtime) = tokio::runtime::Handle::try_current() else { return };
        runtime.spawn(async move {
            let mut stream = body.into_data_stream();
            let mut read = 0u64;
            let _ = tokio::time::timeout(DRAIN_TIME, async {
                while let Some(Ok(chunk)) = stream.next().await {
                    read += chunk.len() as u64;
                    if read > DRAIN_BYTES {
                        break;
                    }
                }
            })
            .await;
        });
    }
}

fn serde_urlencoded_query(q: &str) -> Result<OptionsQuery, Error> {
    Query::<OptionsQuery>::try_from_uri(&format!("/?{q}").parse().map_err(|_| Error::BadRequest("bad query".into()))?)
        .map(|Query(q)| q)
        .map_err(bad_query)
}

/// A query string the handler's query type refuses, as the API's error.
fn bad_query(e: axum::extract::rejection::QueryRejection) -> Error {
    Error::BadRequest(format!("bad query string: {}", e.body_text()))
}

/// Largest `options` part of a multipart body, in bytes.
const OPTIONS_LIMIT: usize = 64 * 1024;

fn form_error(e: FormError) -> Error {
    match e {
        FormError::TooLarge { .. } => Error::TooLarge(e.to_string()),
        FormError::Malformed(_) | FormError::Body(_) => Error::BadRequest(e.to_string()),
    }
}

/// A multipart body: its slot is taken before any of it is read, and nothing of it is
/// held in memory beyond the limits of [`multipart`] and the `options` part's.
async fn submit_multipart(
    app: AppState,
    client: ClientId,
    mut options: JobOptions,
    request: Request,
) -> Result<Response, ApiError> {
    let header_key = idempotency_header(request.headers())?;
    let content_type = request.headers().get(header::CONTENT_TYPE).and_then(|v| v.to_str().ok()).unwrap_or("");
    let boundary = multipart::boundary(content_type)
        .ok_or_else(|| Error::BadRequest("bad multipart body: the Content-Type names no boundary".into()))?;
    let mut slot = Some(app.service.reserve(&client)?);
    let body = request.into_body().into_data_stream();
    let mut form = FormData::new(body, &boundary, multipart::Limits::default());
    let mut ticket = None;
    let mut options_seen = false;
    while let Some(head) = form.next_part().await.map_err(form_error)? {
        let name = head.name.unwrap_or_default();
        match name.as_str() {
            "options" => {
                if ticket.is_some() {
                    return Err(Error::BadRequest("the `options` part must come before `frame`".into()).into());
                }
                if std::mem::replace(&mut options_seen, true) {
                    return Err(Error::BadRequest("the `options` part was sent twice".into()).into());
                }
                let text = form.read_to_limit("the `options` part", OPTIONS_LIMIT).await.map_err(form_error)?;
                options = serde_json::from_slice::<JobOptions>(&text)
                    .map_err(|e| Error::BadRequest(format!("bad `options` JSON: {e}")))?;
                if options.idempotency_key.is_none() {
                    options.idempotency_key = header_key.clone();
                }
            }
            "frame" | "reference" => {
                let part = if name == "frame" { UploadPart::Frame } else { UploadPart::Reference };
                if ticket.is_none() {
                    let slot = slot.take().expect("reserved above, taken once");
                    match app.service.admit_reserved(slot, options.clone(), "http")? {
                        Admission::Existing(status) => return Ok(accepted(&status, true)),
                        Admission::New(t) => ticket = Some(t),
                    }
                }
                let t = ticket.as_mut().expect("admitted above");
                let mut sink = t.sink(part).await?;
                while let Some(chunk) = form.chunk().await.map_err(form_error)? {
                    sink.write(&chunk).await?;
                }
                if sink.written() == 0 {
                    return Err(Error::BadRequest(format!("the `{name}` part is empty")).into());
                }
                t.finish(sink).await?;
            }
            other => {
                return Err(Error::BadRequest(format!(
                    "unknown multipart part `{}` (expected options, frame, reference)",
                    crate::error::truncate(other, crate::error::ECHO_CHARS)
                ))
                .into())
            }
        }
    }
    let ticket = ticket.ok_or_else(|| Error::BadRequest("no `frame` part".into()))?;
    let status = ticket.commit().await?;
    Ok(accepted(&status, false))
}

async fn get_job(
    State(app): State<AppState>,
    Extension(caller): Extension<Caller>,
    Path(id): Path<String>,
) -> Result<Json<JobView>, ApiError> {
    Ok(Json(JobView::from(&app.service.find(&id, &caller).await?)))
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct ListQuery {
    state: Option<String>,
    priority: Option<String>,
    label: Option<String>,
    client: Option<String>,
    order: Option<String>,
    limit: Option<usize>,
    page_token: Option<String>,
}

async fn list(
    State(app): State<AppState>,
    Extension(caller): Extension<Caller>,
    query: Result<Query<ListQuery>, axum::extract::rejection::QueryRejection>,
) -> Result<Json<JobList>, ApiError> {
    let Query(q) = query.map_err(bad_query)?;
    let state = q.state.as_deref().map(str::parse).transpose().map_err(Error::BadRequest)?;
    let priority = q.priority.as_deref().map(str::parse).transpose().map_err(Error::BadRequest)?;
    let newest_first = match q.order.as_deref() {
        None | Some("oldest") => false,
        Some("newest") => true,
        Some(other) => {
            return Err(Error::BadRequest(format!(
                "unknown order `{}` (expected oldest or newest)",
                crate::error::truncate(other, crate::error::ECHO_CHARS)
            ))
            .into())
        }
    };
    let filter = ListFilter {
        state,
        priority,
        label: q.label,
        limit: q.limit,
        after: q.page_token,
        owner: caller.owner_filter(),
        client: q.client.filter(|c| !c.is_empty()),
        newest_first,
    };
    let (jobs, next) = app.service.list(&filter)?;
    Ok(Json(JobList { jobs: jobs.iter().map(JobView::from).collect(), next_page_token: next }))
}

async fn cancel(
    State(app): State<AppState>,
    Extension(caller): Extension<Caller>,
    Path(id): Path<String>,
) -> Result<Response, ApiError> {
    let status = app.service.cancel(&id, &caller).await?;
    let code = if status.record.state == JobState::Cancelled { StatusCode::OK } else { StatusCode::ACCEPTED };
    Ok((code, Json(JobView::from(&status))).into_response())
}

async fn delete_job(
    State(app): State<AppState>,
    Extension(caller): Extension<Caller>,
    Path(id): Path<String>,
) -> Result<StatusCode, ApiError> {
    app.service.delete(&id, &caller).await?;
    Ok(StatusCode::NO_CONTENT)
}

async fn result(
    State(app): State<AppState>,
    Extension(caller): Extension<Caller>,
    Path(id): Path<String>,
) -> Result<Response, ApiError> {
    let (file, len) = app.service.open_result(&id, &caller).await?;
    let telemetry = app.service.telemetry().clone();
    let stream = tokio_util::io::ReaderStream::with_capacity(file, 256 * 1024).inspect(move |chunk| {
        if let Ok(c) = chunk {
            telemetry.bytes_sent("http", c.len() as u64);
        }
    });
    Ok((
        [
            (header::CONTENT_TYPE, "image/x-exr".to_string()),
            (header::CONTENT_LENGTH, len.to_string()),
            (header::CONTENT_DISPOSITION, format!("attachment; filename=\"{id}.exr\"")),
        ],
        Body::from_stream(stream),
    )
        .into_response())
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct PreviewQuery {
    image: Option<String>,
    exposure: Option<f32>,
    view: Option<String>,
    max_size: Option<usize>,
    region: Option<String>,
}

/// `GET /v1/jobs/{id}/preview`: a PNG of the job's input, result or reference, tone
/// mapped by the daemon ([`crate::preview`]) and cached ([`JobService::preview`]).
async fn preview(
    State(app): State<AppState>,
    Extension(caller): Extension<Caller>,
    Path(id): Path<String>,
    query: Result<Query<PreviewQuery>, axum::extract::rejection::QueryRejection>,
) -> Result<Response, ApiError> {
    let Query(q) = query.map_err(bad_query)?;
    let image: PreviewImage = q
        .image
        .as_deref()
        .ok_or_else(|| Error::BadRequest("name the image: image=input, result or reference".into()))?
        .parse()
        .map_err(Error::BadRequest)?;
    let spec = crate::preview::Spec {
        exposure: q.exposure.unwrap_or(0.0),
        view: q.view.as_deref().map(str::parse).transpose().map_err(Error::BadRequest)?.unwrap_or_default(),
        max_size: q.max_size.unwrap_or(crate::preview::DEFAULT_MAX_SIZE),
        region: q.region.as_deref().map(str::parse).transpose().map_err(Error::BadRequest)?,
    };
    let png = app.service.preview(&id, &caller, image, spec).await?;
    Ok((
        [(header::CONTENT_TYPE, "image/png"), (header::CACHE_CONTROL, "private, max-age=3600")],
        Body::from(png.to_vec()),
    )
        .into_response())
}

/// `GET /v1/stats`: totals by state and priority and the last hour's throughput over the
/// jobs the caller may see, with the queue's capacity and the workers.
async fn stats(State(app): State<AppState>, Extension(caller): Extension<Caller>) -> Json<Value> {
    let stats = app.service.stats(caller.owner_filter().as_deref());
    let s = app.service.settings();
    Json(json!({
        "jobs": stats.jobs,
        "by_state": stats.by_state,
        "queued_by_priority": stats.queued_by_priority,
        "last_hour": stats.last_hour,
        "queue_capacity": s.capacity,
        "workers": s.workers,
    }))
}

/// The JSON data of an SSE event.
pub fn event_json(job_id: &str, ev: &JobEvent) -> Value {
    match ev {
        JobEvent::Queued { status } => json!(JobView::from(&**status)),
        JobEvent::Started { attempt } => json!({ "id": job_id, "attempt": attempt }),
        JobEvent::Progress(p) => {
            json!({ "id": job_id, "tiles_done": p.tiles_done, "tiles_total": p.tiles_total })
        }
        JobEvent::Succeeded(s) | JobEvent::Failed(s) | JobEvent::Cancelled(s) => json!(JobView::from(&**s)),
        JobEvent::Deleted => json!({ "id": job_id }),
    }
}

/// The `id:` of an event: where it stands in the job's life, so that a client that
/// reconnects with `Last-Event-ID` is not sent again what it has seen (`queued`;
/// `<attempt>.started`, `<attempt>.<tiles done>`; the terminal event's name).
fn event_id(ev: &JobEvent, attempt: u32) -> String {
    match ev {
        JobEvent::Queued { .. } => "queued".into(),
        JobEvent::Started { attempt } => format!("{attempt}.started"),
        JobEvent::Progress(p) => format!("{attempt}.{}", p.tiles_done),
        terminal => terminal.name().into(),
    }
}

/// `GET /v1/jobs/{id}/events`: Server-Sent Events with ids, ending after the terminal
/// event. With `Last-Event-ID` (a reconnection), the events of the job's current state that
/// the client saw already are not sent again.
async fn events(
    State(app): State<AppState>,
    Extension(caller): Extension<Caller>,
    Path(id): Path<String>,
    headers: HeaderMap,
) -> Result<Sse<impl Stream<Item = Result<Event, Infallible>>>, ApiError> {
    let seen = headers.get("last-event-id").and_then(|v| v.to_str().ok()).map(str::to_owned);
    let stream = app.service.follow(&id, &caller).await?;
    let mut attempt = 0;
    let mut resuming = seen.is_some();
    let stream = stream.filter_map(move |ev| {
        if let JobEvent::Started { attempt: a } = ev {
            attempt = a;
        }
        let event_id = event_id(&ev, attempt);
        // The current state comes first; skip what the client has, up to the first news.
        let known = resuming
            && seen.as_deref().is_some_and(|s| {
                s == event_id || (matches!(ev, JobEvent::Started { .. }) && s.starts_with(&format!("{attempt}.")))
            });
        resuming &= known;
        let event = Event::default().event(ev.name()).id(event_id).data(event_json(&id, &ev).to_string());
        std::future::ready((!known).then_some(Ok(event)))
    });
    let stream = crate::conn::until_shutdown(stream, app.shutdown.clone());
    Ok(Sse::new(stream).keep_alive(KeepAlive::default()))
}
