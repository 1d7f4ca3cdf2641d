//! The gRPC transport (tonic): `mcdenoise.v1.Denoiser` (proto/mcdenoise/v1/denoise.proto),
//! the standard `grpc.health.v1.Health` service and server reflection (v1 and v1alpha),
//! over the same [`JobService`] as the HTTP API.

use std::sync::Arc;

use futures_util::stream::{BoxStream, StreamExt};
use tokio_util::sync::CancellationToken;
use tonic::metadata::MetadataValue;
use tonic::service::interceptor::InterceptedService;
use tonic::transport::server::TcpConnectInfo;
use tonic::{Request, Response, Status, Streaming};

use crate::conn::Protocols;

use crate::auth::{Caller, ClientId, Tokens};
use crate::error::Error;
use crate::jobs::{Admission, JobEvent, JobOptions, JobService, ListFilter, Phase, UploadPart};
use crate::wire::{priority_from_pb, state_from_pb};

/// Generated from `proto/mcdenoise/v1/denoise.proto` at build time.
#[allow(clippy::all, missing_docs)]
pub mod pb {
    tonic::include_proto!("mcdenoise.v1");

    /// Encoded descriptors of the proto, served by reflection.
    pub const FILE_DESCRIPTOR_SET: &[u8] = include_bytes!(concat!(env!("OUT_DIR"), "/mcdenoise_v1_descriptor.bin"));
}

use pb::denoiser_server::{Denoiser, DenoiserServer};
use tonic::Code;
use tonic_types::{ErrorDetails, StatusExt};

/// Largest gRPC message accepted or sent: chunks of up to 4 MiB plus framing.
pub const MAX_MESSAGE_BYTES: usize = 4 * 1024 * 1024 + 64 * 1024;
/// Size of the chunks of `FetchResult`.
pub const RESULT_CHUNK_BYTES: usize = 1024 * 1024;

/// The gRPC status of each error (exhaustive: a new variant must be mapped here). Every
/// status carries a `google.rpc.ErrorInfo` detail (`grpc-status-details-bin`) whose reason
/// is the error's code in capitals (`QUEUE_FULL`, as `queue_full` in HTTP answers), domain
/// `mcdenoise`, metadata `code` (the HTTP code) and, for refusals to retry later,
/// `retry_after_s`; those also carry a `retry-after` metadata entry in seconds.
pub fn status(e: &Error) -> Status {
    let message = e.to_string();
    let (code, retry_after_s) = match e {
        Error::BadRequest(_) | Error::InvalidFrame(_) | Error::TooLarge(_) => (Code::InvalidArgument, None),
        Error::Timeout(_) => (Code::DeadlineExceeded, None),
        Error::Unauthenticated(_) => (Code::Unauthenticated, None),
        Error::Forbidden(_) => (Code::PermissionDenied, None),
        Error::NotFound(_) => (Code::NotFound, None),
        Error::Conflict(_) => (Code::FailedPrecondition, None),
        Error::InProgress(_) => (Code::Aborted, None),
        Error::QueueFull { retry_after_s, .. } | Error::ClientLimit { retry_after_s, .. } => {
            (Code::ResourceExhausted, Some(*retry_after_s))
        }
        Error::Unavailable(_) => (Code::Unavailable, None),
        Error::Storage { .. } => (Code::Unavailable, Some(5)),
        Error::Internal(_) => {
            tracing::error!(error = %message, "grpc call failed");
            (Code::Internal, None)
        }
    };
    let mut metadata = tonic::metadata::MetadataMap::new();
    let mut info = std::collections::HashMap::from([("code".to_string(), e.code().to_string())]);
    if let Some(s) = retry_after_s {
        metadata.insert("retry-after", MetadataValue::from(s));
        info.insert("retry_after_s".into(), s.to_string());
    }
    if matches!(e, Error::Storage { .. }) {
        metadata.insert("error-code", MetadataValue::from_static(e.code()));
    }
    let details = ErrorDetails::with_error_info(e.code().to_ascii_uppercase(), ERROR_DOMAIN, info);
    Status::with_error_details_and_metadata(code, message, details, metadata)
}

/// The `domain` of the daemon's `google.rpc.ErrorInfo` details.
pub const ERROR_DOMAIN: &str = "mcdenoise";

fn invalid(message: impl Into<String>) -> Status {
    status(&Error::BadRequest(message.into()))
}

// --- Conversions (the job's and its options' live in `crate::wire`) ---------------------

impl From<&crate::engine::ModelInfo> for pb::ModelInfo {
    fn from(m: &crate::engine::ModelInfo) -> pb::ModelInfo {
        pb::ModelInfo {
            variant: m.variant.name().to_string(),
            component: m.component_name().to_string(),
            file: m.path.display().to_string(),
            receptive_radius: m.receptive_radius as u32,
            flops_per_pixel: m.flops_per_pixel,
            architecture: m.architecture.clone(),
            sha256: m.sha256.clone(),
            contract: m.contract.to_string(),
        }
    }
}

/// The protobuf form of an event.
pub fn event_pb(job_id: &str, ev: &JobEvent) -> pb::JobEvent {
    let mut out = pb::JobEvent { job_id: job_id.to_string(), ..Default::default() };
    let kind = match ev {
        JobEvent::Queued { status } => {
            out.queue_position = status.queue_position;
            out.job = Some(pb::Job::from(&**status));
            pb::EventType::Queued
        }
        JobEvent::Started { attempt } => {
            out.attempt = *attempt;
            pb::EventType::Started
        }
        JobEvent::Progress(p) => {
            out.progress = Some(pb::Progress { tiles_done: p.tiles_done, tiles_total: p.tiles_total });
            pb::EventType::Progress
        }
        JobEvent::Succeeded(s) => {
            out.job = Some(pb::Job::from(&**s));
            pb::EventType::Succeeded
        }
        JobEvent::Failed(s) => {
            out.job = Some(pb::Job::from(&**s));
            pb::EventType::Failed
        }
        JobEvent::Cancelled(s) => {
            out.job = Some(pb::Job::from(&**s));
            pb::EventType::Cancelled
        }
        JobEvent::Deleted => pb::EventType::Deleted,
    };
    out.r#type = kind as i32;
    out
}

// --- The service ---------------------------------------------------------------------------

/// `mcdenoise.v1.Denoiser` over a [`JobService`].
#[derive(Clone)]
pub struct Api {
    service: JobService,
    shutdown: CancellationToken,
}

impl Api {
    pub fn new(service: JobService, shutdown: CancellationToken) -> Api {
        Api { service, shutdown }
    }

    fn observe<T>(&self, method: &str, result: Result<T, Status>) -> Result<T, Status> {
        let code = match &result {
            Ok(_) => "OK".to_string(),
            Err(s) => format!("{:?}", s.code()),
        };
        self.service.telemetry().grpc_request(method, &code);
        result
    }
}

type EventStream = BoxStream<'static, Result<pb::JobEvent, Status>>;
type ChunkStream = BoxStream<'static, Result<pb::ResultChunk, Status>>;

#[tonic::async_trait]
impl Denoiser for Api {
    async fn submit_job(&self, request: Request<Streaming<pb::SubmitJobRequest>>) -> Result<Response<pb::Job>, Status> {
        let client = caller_of(&request).id;
        let result = submit_upload(&self.service, &client, request.into_inner()).await;
        if let Err(e) = &result {
            if let Error::Timeout(m) = e {
                tracing::warn!(client = client.as_str(), transport = "grpc", "upload timed out: {m}");
            }
            self.service.note_rejection(e);
        }
        self.observe("SubmitJob", result.map(Response::new).map_err(|e| status(&e)))
    }

    async fn get_job(&self, request: Request<pb::GetJobRequest>) -> Result<Response<pb::Job>, Status> {
        let caller = caller_of(&request);
        let id = request.into_inner().id;
        let result = self.service.find(&id, &caller).await.map(|s| Response::new(pb::Job::from(&s)));
        self.observe("GetJob", result.map_err(|e| status(&e)))
    }

    async fn list_jobs(&self, request: Request<pb::ListJobsRequest>) -> Result<Response<pb::ListJobsResponse>, Status> {
        let caller = caller_of(&request);
        let r = request.into_inner();
        let result = (|| {
            let filter = ListFilter {
                state: state_from_pb(r.state).map_err(invalid)?,
                priority: priority_from_pb(r.priority).map_err(invalid)?,
                label: Some(r.label).filter(|s| !s.is_empty()),
                limit: (r.page_size > 0).then_some(r.page_size as usize),
                after: Some(r.page_token).filter(|s| !s.is_empty()),
                owner: caller.owner_filter(),
                client: Some(r.client).filter(|s| !s.is_empty()),
                newest_first: r.newest_first,
            };
            let (jobs, next) = self.service.list(&filter).map_err(|e| status(&e))?;
            Ok(Response::new(pb::ListJobsResponse {
                jobs: jobs.iter().map(pb::Job::from).collect(),
                next_page_token: next.unwrap_or_default(),
            }))
        })();
        self.observe("ListJobs", result)
    }

    async fn cancel_job(&self, request: Request<pb::CancelJobRequest>) -> Result<Response<pb::Job>, Status> {
        let caller = caller_of(&request);
        let id = request.into_inner().id;
        let result =
            self.service.cancel(&id, &caller).await.map(|s| Response::new(pb::Job::from(&s))).map_err(|e| status(&e));
        self.observe("CancelJob", result)
    }

    async fn delete_job(
        &self,
        request: Request<pb::DeleteJobRequest>,
    ) -> Result<Response<pb::DeleteJobResponse>, Status> {
        let caller = caller_of(&request);
        let id = request.into_inner().id;
        let result = self
            .service
            .delete(&id, &caller)
            .await
            .map(|()| Response::new(pb::DeleteJobResponse {}))
            .map_err(|e| status(&e));
        self.observe("DeleteJob", result)
    }

    type WatchJobStream = EventStream;

    async fn watch_job(&self, request: Request<pb::WatchJobRequest>) -> Result<Response<EventStream>, Status> {
        let caller = caller_of(&request);
        let id = request.into_inner().id;
        let result = self.service.follow(&id, &caller).await.map_err(|e| status(&e)).map(|events| {
            let stream =
                crate::conn::until_shutdown(events.map(move |ev| Ok(event_pb(&id, &ev))), self.shutdown.clone())
                    .boxed();
            Response::new(stream)
        });
        self.observe("WatchJob", result)
    }

    type FetchResultStream = ChunkStream;

    async fn fetch_result(&self, request: Request<pb::FetchResultRequest>) -> Result<Response<ChunkStream>, Status> {
        let caller = caller_of(&request);
        let id = request.into_inner().id;
        let result = self.service.open_result(&id, &caller).await.map_err(|e| status(&e)).map(|(file, len)| {
            let telemetry = self.service.telemetry().clone();
            let mut first = true;
            let stream = tokio_util::io::ReaderStream::with_capacity(file, RESULT_CHUNK_BYTES)
                .map(move |chunk| match chunk {
                    Ok(data) => {
                        telemetry.bytes_sent("grpc", data.len() as u64);
                        let total_size = if std::mem::take(&mut first) { len } else { 0 };
                        Ok(pb::ResultChunk { data: data.to_vec(), total_size })
                    }
                    Err(e) => Err(status(&Error::internal("reading the result", e))),
                })
                .boxed();
            Response::new(stream)
        });
        self.observe("FetchResult", result)
    }

    async fn list_models(&self, _: Request<pb::ListModelsRequest>) -> Result<Response<pb::ListModelsResponse>, Status> {
        let result = match self.service.models() {
            None => Err(status(&Error::Unavailable("the models are still loading".into()))),
            Some(models) => {
                let s = self.service.settings();
                Ok(Response::new(pb::ListModelsResponse {
                    models: models.iter().map(pb::ModelInfo::from).collect(),
                    tile: s.engine.tile as u32,
                    workers: s.workers as u32,
                    threads_per_worker: s.engine.threads as u32,
                }))
            }
        };
        self.observe("ListModels", result)
    }
}

/// Reassembles a `SubmitJob` upload (header, then the frame's chunks, then the
/// reference's) and queues the job. Separate from the service so that it can be driven by
/// any stream (the fuzz target `grpc_chunks` does).
pub async fn submit_upload<S>(service: &JobService, client: &ClientId, mut stream: S) -> Result<pb::Job, Error>
where
    S: futures_util::Stream<Item = Result<pb::SubmitJobRequest, Status>> + Unpin,
{
    use pb::submit_job_request::Message;
    let gap = service.settings().upload_timeout;
    let first = next_message(&mut stream, gap).await?;
    let header = match first.and_then(|m| m.message) {
        Some(Message::Header(h)) => h,
        Some(Message::Chunk(_)) => {
            return Err(Error::BadRequest("the first message must be a `header`, not a `chunk`".into()))
        }
        None => return Err(Error::BadRequest("empty upload: the first message must be a `header`".into())),
    };
    let options = JobOptions::try_from(header.options.unwrap_or_default()).map_err(Error::BadRequest)?;
    if header.frame_size == 0 {
        return Err(Error::BadRequest("header.frame_size must be the frame's size in bytes".into()));
    }
    let max = service.settings().max_body_bytes;
    let declared = header.frame_size.saturating_add(header.reference_size);
    if declared > max {
        return Err(Error::TooLarge(format!("the upload declares {declared} bytes, over the limit of {max}")));
    }
    let mut ticket = match service.admit(options, "grpc", client)? {
        Admission::Existing(status) => return Ok(pb::Job::from(&status)),
        Admission::New(t) => t,
    };
    let sizes = [(UploadPart::Frame, header.frame_size), (UploadPart::Reference, header.reference_size)];
    let mut current = 0usize;
    let mut sink = Some(ticket.sink(UploadPart::Frame).await?);
    loop {
        let msg = next_message(&mut stream, gap).await?;
        let Some(msg) = msg else { break };
        let chunk = match msg.message {
            Some(Message::Chunk(c)) => c,
            Some(Message::Header(_)) => return Err(Error::BadRequest("the header was sent twice".into())),
            None => return Err(Error::BadRequest("a message with neither header nor chunk".into())),
        };
        let part = match pb::Part::try_from(chunk.part) {
            Ok(pb::Part::Frame) => UploadPart::Frame,
            Ok(pb::Part::Reference) => UploadPart::Reference,
            Ok(pb::Part::Unspecified) | Err(_) => {
                return Err(Error::BadRequest("every chunk must name its part (FRAME or REFERENCE)".into()))
            }
        };
        // Move on to the reference once the frame is complete.
        let (expected_part, expected_size) = sizes[current];
        let done = sink.as_ref().map_or(0, |s| s.written());
        if part != expected_part {
            if expected_part == UploadPart::Frame && part == UploadPart::Reference {
                return Err(Error::BadRequest(format!(
                    "a reference chunk arrived after {done} of the frame's {expected_size} bytes; send the frame first"
                )));
            }
            return Err(Error::BadRequest("frame chunks must all come before the reference's".into()));
        }
        if done + chunk.data.len() as u64 > expected_size {
            return Err(Error::BadRequest(format!(
                "the {} is larger than the {expected_size} bytes declared in the header",
                part.name()
            )));
        }
        let s = sink.as_mut().expect("a sink is open while data is expected");
        s.write(&chunk.data).await?;
        if s.written() == expected_size {
            ticket.finish(sink.take().expect("open")).await?;
            current += 1;
            if current < sizes.len() && sizes[current].1 > 0 {
                sink = Some(ticket.sink(sizes[current].0).await?);
            } else {
                // Everything declared has arrived; anything more is an error below.
                current = sizes.len();
                break;
            }
        }
    }
    if current < sizes.len() {
        let (part, size) = sizes[current];
        let got = sink.as_ref().map_or(0, |s| s.written());
        return Err(Error::BadRequest(format!(
            "the upload ended after {got} of the {size} bytes declared for the {}",
            part.name()
        )));
    }
    if let Some(extra) = next_message(&mut stream, gap).await? {
        if extra.message.is_some() {
            return Err(Error::BadRequest("more data than the sizes declared in the header".into()));
        }
    }
    let status = ticket.commit().await?;
    Ok(pb::Job::from(&status))
}

/// The next message of an upload; one that takes longer than `gap` (`--upload-timeout`)
/// to come fails the upload.
async fn next_message<S>(stream: &mut S, gap: std::time::Duration) -> Result<Option<pb::SubmitJobRequest>, Error>
where
    S: futures_util::Stream<Item = Result<pb::SubmitJobRequest, Status>> + Unpin,
{
    match tokio::time::timeout(gap, stream.next()).await {
        Err(_) => Err(Error::Timeout(format!(
            "no upload message arrived for {} (--upload-timeout); the upload was dropped",
            humantime::format_duration(gap)
        ))),
        Ok(m) => m.transpose().map_err(|s| Error::BadRequest(format!("upload stream: {}", s.message()))),
    }
}

/// tonic answers a request message that is not valid protobuf with INTERNAL; it is the
/// client's error, so it becomes INVALID_ARGUMENT (the message is kept).
fn decode_errors_are_invalid_argument(
    mut response: axum::http::Response<tonic::body::Body>,
) -> axum::http::Response<tonic::body::Body> {
    if let Some(status) = Status::from_header_map(response.headers()) {
        if status.code() == tonic::Code::Internal && status.message().starts_with("failed to decode Protobuf message") {
            let _ = Status::invalid_argument(status.message().to_string()).add_header(response.headers_mut());
        }
    }
    response
}

/// Who is calling: set by [`Auth`] on every API request (a request that did not pass it
/// is named by its address and may see nothing but its own jobs).
fn caller_of<T>(request: &Request<T>) -> Caller {
    request.extensions().get::<Caller>().cloned().unwrap_or_else(|| Caller {
        id: ClientId::peer(request.remote_addr()),
        scope: crate::auth::Scope::Submit,
        metrics: false,
    })
}

/// Checks `authorization: Bearer <token>` metadata and records who is calling (a
/// [`Caller`] extension).
/// A refused caller is logged and, on `SubmitJob`, counted as a rejected job.
#[derive(Clone)]
pub struct Auth {
    tokens: Arc<Tokens>,
    service: JobService,
}

/// The path of a gRPC request (`/package.Service/Method`), an extension set before the
/// interceptors run (they see no URI).
#[derive(Clone)]
struct MethodPath(String);

const SUBMIT_PATH: &str = "/mcdenoise.v1.Denoiser/SubmitJob";

impl tonic::service::Interceptor for Auth {
    fn call(&mut self, mut request: Request<()>) -> Result<Request<()>, Status> {
        let authorization = request.metadata().get("authorization").and_then(|v| v.to_str().ok());
        match self.tokens.authenticate(authorization, request.remote_addr(), "metadata authorization") {
            Ok(caller) => {
                request.extensions_mut().insert(caller);
                Ok(request)
            }
            Err(e) => {
                let path = request.extensions().get::<MethodPath>().map_or("", |p| p.0.as_str());
                self.service.note_refused_caller(&e, "grpc", path, request.remote_addr(), path == SUBMIT_PATH);
                Err(status(&e))
            }
        }
    }
}

/// Serves gRPC on `listener` until `shutdown` is cancelled.
pub async fn serve(
    listener: tokio::net::TcpListener,
    service: JobService,
    tokens: Arc<Tokens>,
    tls: Option<crate::tls::Tls>,
    timeouts: crate::conn::Timeouts,
    admission: Arc<crate::conn::Admission>,
    shutdown: CancellationToken,
) -> anyhow::Result<()> {
    let auth = Auth { tokens, service: service.clone() };
    let api = DenoiserServer::new(Api::new(service.clone(), shutdown.clone()))
        .max_decoding_message_size(MAX_MESSAGE_BYTES)
        .max_encoding_message_size(MAX_MESSAGE_BYTES);
    let (reporter, health) = tonic_health::server::health_reporter();
    let reflection_v1 = tonic_reflection::server::Builder::configure()
        .register_encoded_file_descriptor_set(pb::FILE_DESCRIPTOR_SET)
        .register_encoded_file_descriptor_set(tonic_health::pb::FILE_DESCRIPTOR_SET)
        .build_v1()?;
    let reflection_v1alpha = tonic_reflection::server::Builder::configure()
        .register_encoded_file_descriptor_set(pb::FILE_DESCRIPTOR_SET)
        .register_encoded_file_descriptor_set(tonic_health::pb::FILE_DESCRIPTOR_SET)
        .build_v1alpha()?;

    // Health follows readiness: SERVING only when models are loaded, not draining, and the
    // data directory can take writes.
    let mut phase = service.subscribe_phase();
    let mut storage = service.subscribe_storage();
    let health_task = tokio::spawn(async move {
        loop {
            let serving = *phase.borrow_and_update() == Phase::Ready && storage.borrow_and_update().is_none();
            let status =
                if serving { tonic_health::ServingStatus::Serving } else { tonic_health::ServingStatus::NotServing };
            reporter.set_service_status("", status).await;
            reporter.set_service_status("mcdenoise.v1.Denoiser", status).await;
            let changed = tokio::select! {
                r = phase.changed() => r,
                r = storage.changed() => r,
            };
            if changed.is_err() {
                break;
            }
        }
    });

    let routes = tonic::service::Routes::new(health)
        .add_service(InterceptedService::new(reflection_v1, auth.clone()))
        .add_service(InterceptedService::new(reflection_v1alpha, auth.clone()))
        .add_service(InterceptedService::new(api, auth))
        .prepare();
    let routes = tower::ServiceExt::<axum::http::Request<hyper::body::Incoming>>::map_request(
        routes,
        |mut request: axum::http::Request<hyper::body::Incoming>| {
            let path = MethodPath(request.uri().path().to_owned());
            request.extensions_mut().insert(path);
            request
        },
    );
    let routes = tower::ServiceExt::<axum::http::Request<hyper::body::Incoming>>::map_response(
        routes,
        decode_errors_are_invalid_argument as fn(axum::http::Response<tonic::body::Body>) -> _,
    );
    let local = listener.local_addr().ok();
    // What tonic's own server would record: `Request::remote_addr` reads it.
    let per_peer = move |peer| {
        let info = TcpConnectInfo { local_addr: local, remote_addr: Some(peer) };
        crate::conn::WithExtension::new(routes.clone(), info)
    };
    let tls = tls.map(|t| t.grpc);
    let result = crate::conn::serve(listener, tls, Protocols::Http2, timeouts, admission, per_peer, shutdown).await;
    health_task.abort();
    result.map_err(Into::into)
}
