//! The daemon's gRPC API against a real daemon on ephemeral ports: chunked upload, watch,
//! chunked download, the chunk protocol, cancellation, health and reflection.

use crate::daemon_common;

use std::time::Duration;

use futures_util::stream;
use mcdenoise::client::{fetch_grpc, grpc_connect, upload_stream};
use mcdenoise::frame::Frame;
use mcdenoise::grpc::pb;
use pb::submit_job_request::Message;
use tonic::Code;

use daemon_common::*;

fn header(frame_size: u64, reference_size: u64) -> pb::SubmitJobRequest {
    pb::SubmitJobRequest {
        message: Some(Message::Header(pb::SubmitHeader { options: None, frame_size, reference_size })),
    }
}

fn chunk(part: pb::Part, data: &[u8]) -> pb::SubmitJobRequest {
    pb::SubmitJobRequest { message: Some(Message::Chunk(pb::Chunk { part: part as i32, data: data.to_vec() })) }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn grpc_round_trip_uploads_in_chunks_watches_and_downloads() {
    let dir = tempfile::tempdir().unwrap();
    let d = start(dir.path(), &[]).await;
    d.ready().await;
    let (w, h) = (48, 40);
    let frame_path = write(dir.path(), "frame.exr", &frame(w, h));
    let reference_path = write(dir.path(), "reference.exr", &reference(w, h));
    let mut client = grpc_connect(&d.grpc, None).await.unwrap();

    let options = pb::JobOptions {
        priority: pb::Priority::High as i32,
        layers: vec!["specular".into()],
        label: "grpc-shot".into(),
        ..Default::default()
    };
    // Small chunks: many messages per file.
    let upload = upload_stream(options, &frame_path, Some(&reference_path), 7000).await.unwrap();
    let job = client.submit_job(upload).await.unwrap().into_inner();
    assert_eq!(job.priority, pb::Priority::High as i32);
    assert!(job.has_reference);
    assert_eq!((job.width, job.height), (48, 40));

    let mut events = client.watch_job(pb::WatchJobRequest { id: job.id.clone() }).await.unwrap().into_inner();
    let mut kinds = Vec::new();
    let mut last = None;
    while let Some(ev) = events.message().await.unwrap() {
        assert_eq!(ev.job_id, job.id);
        kinds.push(pb::EventType::try_from(ev.r#type).unwrap());
        last = Some(ev);
    }
    assert_eq!(kinds.last(), Some(&pb::EventType::Succeeded), "{kinds:?}");
    assert!(kinds.contains(&pb::EventType::Progress), "{kinds:?}");
    let done = last.unwrap().job.unwrap();
    assert_eq!(done.state, pb::JobState::Succeeded as i32);
    let metrics = done.metrics.expect("metrics with a reference");
    assert!(metrics.output.unwrap().relmse >= 0.0 && metrics.input.unwrap().psnr > 0.0);
    let timings = done.timings.unwrap();
    assert!(timings.inference > 0.0 && timings.total >= timings.inference);
    assert_eq!(done.progress.unwrap().tiles_done, 4);

    let out = dir.path().join("out.exr");
    let n = fetch_grpc(&mut client, &job.id, &out).await.unwrap();
    assert_eq!(n, done.result_bytes);
    let result = Frame::reference_from_exr_bytes(&std::fs::read(&out).unwrap(), &Default::default()).unwrap();
    assert_eq!((result.width, result.height), (w, h));
    // The same bytes over HTTP.
    let (_, http_bytes) = d.result(&job.id).await;
    assert_eq!(http_bytes, std::fs::read(&out).unwrap());

    let got = client.get_job(pb::GetJobRequest { id: job.id.clone() }).await.unwrap().into_inner();
    assert_eq!(got.state, pb::JobState::Succeeded as i32);
    let list = client
        .list_jobs(pb::ListJobsRequest { label: "grpc-shot".into(), ..Default::default() })
        .await
        .unwrap()
        .into_inner();
    assert_eq!(list.jobs.len(), 1);
    let models = client.list_models(pb::ListModelsRequest {}).await.unwrap().into_inner();
    assert_eq!(models.models.len(), 4);
    assert_eq!(client.get_job(pb::GetJobRequest { id: "nope".into() }).await.unwrap_err().code(), Code::NotFound);
    client.delete_job(pb::DeleteJobRequest { id: job.id.clone() }).await.unwrap();
    assert_eq!(client.get_job(pb::GetJobRequest { id: job.id }).await.unwrap_err().code(), Code::NotFound);
    d.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_chunk_protocol_is_enforced_and_refusals_leak_no_capacity() {
    let dir = tempfile::tempdir().unwrap();
    // Capacity 1: a refused upload that kept its reservation would block the last submit.
    let d = start(dir.path(), &["--queue-capacity", "1", "--max-body-bytes", "1000000"]).await;
    d.ready().await;
    let mut client = grpc_connect(&d.grpc, None).await.unwrap();
    let exr = frame(32, 32);
    let n = exr.len() as u64;
    let half = exr.len() / 2;
    let cases: Vec<(&str, Vec<pb::SubmitJobRequest>, &str)> = vec![
        ("empty stream", vec![], "the first message must be a `header`"),
        ("chunk first", vec![chunk(pb::Part::Frame, &exr)], "not a `chunk`"),
        ("no frame size", vec![header(0, 0)], "frame_size"),
        ("over the limit", vec![header(2_000_000, 0)], "over the limit"),
        ("missing bytes", vec![header(n, 0), chunk(pb::Part::Frame, &exr[..half])], "ended after"),
        ("more than declared", vec![header(n - 10, 0), chunk(pb::Part::Frame, &exr)], "larger than the"),
        (
            "reference before the frame is complete",
            vec![header(n, 100), chunk(pb::Part::Frame, &exr[..half]), chunk(pb::Part::Reference, &[0; 100])],
            "send the frame first",
        ),
        ("part missing", vec![header(n, 0), chunk(pb::Part::Unspecified, &exr)], "must name its part"),
        ("header twice", vec![header(n, 0), header(n, 0)], "header was sent twice"),
        (
            "trailing data",
            vec![header(n, 0), chunk(pb::Part::Frame, &exr), chunk(pb::Part::Frame, &[1, 2, 3])],
            "more data than",
        ),
        ("not an EXR", vec![header(4, 0), chunk(pb::Part::Frame, b"EXR?")], "frame: "),
    ];
    for (name, messages, expected) in cases {
        let status = client.submit_job(stream::iter(messages)).await.unwrap_err();
        assert_eq!(status.code(), Code::InvalidArgument, "{name}: {status:?}");
        assert!(status.message().contains(expected), "{name}: {}", status.message());
    }
    // A correct upload, in two frame chunks.
    let ok = vec![header(n, 0), chunk(pb::Part::Frame, &exr[..half]), chunk(pb::Part::Frame, &exr[half..])];
    let job = client.submit_job(stream::iter(ok)).await.unwrap().into_inner();
    d.wait_state(&job.id, "succeeded").await;
    let list = client.list_jobs(pb::ListJobsRequest::default()).await.unwrap().into_inner();
    assert_eq!(list.jobs.len(), 1);
    d.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn grpc_cancels_a_running_job_and_the_watch_ends_with_cancelled() {
    let dir = tempfile::tempdir().unwrap();
    let d = start(dir.path(), &["--tile", "16", "--debug-tile-delay", "100ms"]).await;
    d.ready().await;
    let mut client = grpc_connect(&d.grpc, None).await.unwrap();
    let path = write(dir.path(), "f.exr", &frame(64, 64));
    let job = client.submit_job(upload_stream(Default::default(), &path, None, 1 << 20).await.unwrap()).await.unwrap();
    let id = job.into_inner().id;
    let mut events = client.watch_job(pb::WatchJobRequest { id: id.clone() }).await.unwrap().into_inner();
    let mut cancelled = false;
    let mut kinds = Vec::new();
    while let Some(ev) = events.message().await.unwrap() {
        let kind = pb::EventType::try_from(ev.r#type).unwrap();
        kinds.push(kind);
        if kind == pb::EventType::Progress && ev.progress.unwrap().tiles_done >= 2 && !cancelled {
            let j = client.cancel_job(pb::CancelJobRequest { id: id.clone() }).await.unwrap().into_inner();
            assert!(j.cancel_requested);
            cancelled = true;
        }
    }
    assert_eq!(kinds.last(), Some(&pb::EventType::Cancelled), "{kinds:?}");
    let status = client.cancel_job(pb::CancelJobRequest { id: id.clone() }).await.unwrap_err();
    assert_eq!(status.code(), Code::FailedPrecondition);
    let status = client.fetch_result(pb::FetchResultRequest { id }).await.unwrap_err();
    assert_eq!(status.code(), Code::FailedPrecondition);
    d.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn health_and_reflection_are_served() {
    use tonic_reflection::pb::v1::server_reflection_client::ServerReflectionClient;
    use tonic_reflection::pb::v1::server_reflection_request::MessageRequest;
    use tonic_reflection::pb::v1::server_reflection_response::MessageResponse;
    use tonic_reflection::pb::v1::ServerReflectionRequest;

    let dir = tempfile::tempdir().unwrap();
    let d = start(dir.path(), &[]).await;
    d.ready().await;
    let channel =
        tonic::transport::Endpoint::from_shared(format!("http://{}", d.grpc)).unwrap().connect().await.unwrap();
    let mut health = tonic_health::pb::health_client::HealthClient::new(channel.clone());
    let serving = tonic_health::pb::health_check_response::ServingStatus::Serving as i32;
    // Health follows readiness through a watch: it may lag `/readyz` by a moment.
    for service in ["", "mcdenoise.v1.Denoiser"] {
        let t = std::time::Instant::now();
        loop {
            let request = tonic_health::pb::HealthCheckRequest { service: service.into() };
            let status = health.check(request).await.unwrap().into_inner().status;
            if status == serving {
                break;
            }
            assert!(t.elapsed() < Duration::from_secs(5), "{service}: not serving 5 s after /readyz said ready");
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    }
    let mut reflection = ServerReflectionClient::new(channel);
    let request = ServerReflectionRequest {
        host: String::new(),
        message_request: Some(MessageRequest::ListServices(String::new())),
    };
    let mut replies = reflection.server_reflection_info(stream::iter([request])).await.unwrap().into_inner();
    let reply = replies.message().await.unwrap().unwrap();
    let Some(MessageResponse::ListServicesResponse(list)) = reply.message_response else { panic!("{reply:?}") };
    let names: Vec<String> = list.service.into_iter().map(|s| s.name).collect();
    for expected in ["mcdenoise.v1.Denoiser", "grpc.health.v1.Health"] {
        assert!(names.iter().any(|n| n == expected), "{names:?}");
    }
    d.stop().await;
}
