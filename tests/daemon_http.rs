//! The daemon's HTTP API against a real daemon on ephemeral ports, with the real engine
//! and the tiny test models: round trips, idempotency, cancellation, admission limits,
//! input errors, authentication, metrics.

use crate::common;
use crate::daemon_common;

use std::time::Duration;

use hyper::{Method, StatusCode};
use mcdenoise::client::{body_bytes, read_json};
use mcdenoise::frame::Frame;

use common::{
    channel_names, check_carried, engine, frame_of, max_rel_diff, overscan_frame, parts, samples_of, Placement,
    EXTRA_CHANNELS,
};
use daemon_common::*;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn http_round_trip_streams_progress_then_result_and_metrics() {
    let dir = tempfile::tempdir().unwrap();
    let d = start(dir.path(), &[]).await;
    d.ready().await;
    let (w, h) = (64, 48);
    let input = frame(w, h);
    let (content_type, body) = multipart(
        r#"{"priority": "high", "layers": ["diffuse"], "label": "shot-010"}"#,
        &[("frame", &input), ("reference", &reference(w, h))],
    );
    let resp = d
        .http
        .send(Method::POST, "/v1/jobs", &[("content-type", content_type.as_str())], body_bytes(body))
        .await
        .unwrap();
    let location = resp.headers().get("location").map(|v| v.to_str().unwrap().to_string());
    let (status, job) = read_json(resp).await.unwrap();
    assert_eq!(status, StatusCode::ACCEPTED, "{job}");
    let id = job["id"].as_str().unwrap().to_string();
    assert_eq!(location.as_deref(), Some(format!("/v1/jobs/{id}").as_str()));
    assert_eq!(job["urls"]["events"], format!("/v1/jobs/{id}/events"));
    assert_eq!(job["priority"], "high");
    assert_eq!((job["width"].as_u64(), job["height"].as_u64()), (Some(64), Some(48)));

    // Progress as Server-Sent Events, ending with the metrics.
    let events = d.events(&id).await;
    let names: Vec<&str> = events.iter().map(|e| e.event.as_str()).collect();
    assert_eq!(names.last(), Some(&"succeeded"), "{names:?}");
    let tiles: Vec<u64> = events
        .iter()
        .filter(|e| e.event == "progress")
        .map(|e| {
            assert_eq!(e.data["tiles_total"], 4, "64x48 in 32-pixel tiles");
            e.data["tiles_done"].as_u64().unwrap()
        })
        .collect();
    assert!(tiles.windows(2).all(|p| p[0] <= p[1]), "{tiles:?}");
    let done = &events.last().unwrap().data;
    assert_eq!(done["state"], "succeeded");
    assert_eq!(done["progress"]["tiles_done"], 4);
    for m in ["input", "output"] {
        for k in ["relmse", "dssim", "psnr", "smape"] {
            assert!(done["metrics"][m][k].is_number(), "{m}.{k}: {done}");
        }
    }
    for stage in ["queue", "decode", "preprocess", "inference", "reconstruction", "encode", "total"] {
        assert!(done["timings_ms"][stage].as_f64().unwrap() >= 0.0, "{stage}");
    }
    assert_eq!(done["sanitized"]["total"], 0);
    assert_eq!(done["variant"], "nocov");

    // The result is the engine's output for this frame, with the requested layer.
    let (status, exr) = d.result(&id).await;
    assert_eq!(status, StatusCode::OK);
    assert_eq!(done["result_bytes"].as_u64(), Some(exr.len() as u64));
    let out = Frame::reference_from_exr_bytes(&exr, &Default::default()).unwrap();
    assert_eq!((out.width, out.height), (w, h));
    let expected = engine(32).denoise(&frame_of(&input), None, &mut |_| true).unwrap();
    let got = out.color();
    for (c, (got, want)) in got.iter().zip(&expected.color).enumerate() {
        assert!(max_rel_diff(got, want) < 1e-4, "channel {c}");
    }
    let meta = exr::meta::MetaData::read_from_buffered(std::io::Cursor::new(&exr), false).unwrap();
    let names: Vec<String> = meta.headers[0].channels.list.iter().map(|c| c.name.to_string()).collect();
    assert!(names.contains(&"diffuse.R".to_string()), "{names:?}");

    // Listing and filtering, then deletion.
    let (_, list) = d.get_json("/v1/jobs?label=shot-010&state=succeeded").await;
    assert_eq!(list["jobs"].as_array().unwrap().len(), 1);
    let (_, list) = d.get_json("/v1/jobs?state=queued").await;
    assert_eq!(list["jobs"].as_array().unwrap().len(), 0);
    let (status, _) = d.get_json("/v1/jobs?state=bogus").await;
    assert_eq!(status, StatusCode::BAD_REQUEST);
    let (status, _) = d.http.json(Method::DELETE, &format!("/v1/jobs/{id}"), &[], body_bytes(vec![])).await.unwrap();
    assert_eq!(status, StatusCode::NO_CONTENT);
    let (status, err) = d.get_json(&format!("/v1/jobs/{id}")).await;
    assert_eq!(status, StatusCode::NOT_FOUND);
    assert_eq!(err["error"]["code"], "not_found");
    assert!(!dir.path().join("jobs").join(&id).exists(), "files removed with the job");
    d.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_overscan_frame_comes_back_in_place_with_its_attributes_alpha_and_aovs() {
    // Data window −8..263 in a 256×256 display window, every AOV asked back beside the
    // denoised diffuse.
    let dir = tempfile::tempdir().unwrap();
    let d = start(dir.path(), &[]).await;
    d.ready().await;
    let display = exr::prelude::IntegerBounds::from_dimensions((256, 256));
    let placement = Placement { origin: (-8, -8), display, pixel_aspect: 1.5, ..Placement::plain(272, 272) };
    let input = overscan_frame(-8, -8, 272, 272, &placement);
    let id = d.submit_ok(&input, "layers=all,diffuse").await;
    let job = wait_succeeded(&d.http, &id, Duration::from_secs(120)).await;
    assert_eq!(job["layers"], serde_json::json!(["all", "diffuse"]));
    assert_eq!((job["width"].as_u64(), job["height"].as_u64()), (Some(272), Some(272)));

    let (status, exr) = d.result(&id).await;
    assert_eq!(status, StatusCode::OK);
    let result = check_carried(&input, &exr, &["diffuse.R", "diffuse.G", "diffuse.B"]);
    assert_eq!(result.layer_data[0].attributes.layer_position, exr::prelude::Vec2(-8, -8));
    assert_eq!(result.attributes.display_window, display);
    let names = channel_names(&result);
    assert!(EXTRA_CHANNELS.iter().all(|c| names.contains(&c.to_string())), "{names:?}");
    // The pixels are the engine's output for this frame, where they were.
    let expected = engine(32).denoise(&frame_of(&input), None, &mut |_| true).unwrap();
    for (c, want) in ["R", "G", "B"].iter().zip(&expected.color) {
        assert!(max_rel_diff(&samples_of(&result, c), want) < 1e-4, "{c}");
    }
    for (c, want) in ["diffuse.R", "diffuse.G", "diffuse.B"].iter().zip(&parts(&expected).diffuse) {
        assert!(max_rel_diff(&samples_of(&result, c), want) < 1e-4, "{c}");
    }
    d.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_retried_submission_with_the_same_key_returns_the_same_job() {
    let dir = tempfile::tempdir().unwrap();
    let d = start(dir.path(), &[]).await;
    d.ready().await;
    let input = frame(32, 32);
    let (s1, j1) = d.submit(&input, "", &[("idempotency-key", "render-42-frame-7")]).await;
    let (s2, j2) = d.submit(&input, "", &[("idempotency-key", "render-42-frame-7")]).await;
    assert_eq!((s1, s2), (StatusCode::ACCEPTED, StatusCode::ACCEPTED));
    assert_eq!(j1["id"], j2["id"]);
    // The key also works as a query parameter and across transports.
    let (_, j3) = d.submit(&input, "idempotency_key=render-42-frame-7", &[]).await;
    assert_eq!(j1["id"], j3["id"]);
    let mut grpc = mcdenoise::client::grpc_connect(&d.grpc, None).await.unwrap();
    let path = write(dir.path(), "f.exr", &input);
    let options = mcdenoise::grpc::pb::JobOptions { idempotency_key: "render-42-frame-7".into(), ..Default::default() };
    let upload = mcdenoise::client::upload_stream(options, &path, None, 4096).await.unwrap();
    let j4 = grpc.submit_job(upload).await.unwrap().into_inner();
    assert_eq!(j1["id"].as_str(), Some(j4.id.as_str()));
    // A different key is a different job.
    let (_, j5) = d.submit(&input, "", &[("idempotency-key", "render-42-frame-8")]).await;
    assert_ne!(j1["id"], j5["id"]);
    let (_, list) = d.get_json("/v1/jobs").await;
    assert_eq!(list["jobs"].as_array().unwrap().len(), 2, "{list}");
    d.wait_state(j1["id"].as_str().unwrap(), "succeeded").await;
    // After completion, the key still answers with the finished job.
    let (_, j6) = d.submit(&input, "", &[("idempotency-key", "render-42-frame-7")]).await;
    assert_eq!(j6["id"], j1["id"]);
    assert_eq!(j6["state"], "succeeded");
    d.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn cancels_a_queued_job_at_once_and_a_running_one_between_tiles() {
    let dir = tempfile::tempdir().unwrap();
    // 64x64 in 16-pixel tiles = 16 tiles of at least 100 ms.
    let d = start(dir.path(), &["--tile", "16", "--debug-tile-delay", "100ms"]).await;
    d.ready().await;
    let running = d.submit_ok(&frame(64, 64), "").await;
    d.wait_running(&running).await;
    let queued = d.submit_ok(&frame(64, 64), "priority=low").await;
    let job = d.job(&queued).await;
    assert_eq!((job["state"].as_str(), job["queue_position"].as_u64()), (Some("queued"), Some(1)));

    let (status, job) = d.post_json(&format!("/v1/jobs/{queued}/cancel")).await;
    assert_eq!(status, StatusCode::OK, "{job}");
    assert_eq!(job["state"], "cancelled");

    let (status, job) = d.post_json(&format!("/v1/jobs/{running}/cancel")).await;
    assert_eq!(status, StatusCode::ACCEPTED, "{job}");
    assert_eq!(job["cancel_requested"], true);
    let events = d.events(&running).await;
    assert_eq!(events.last().unwrap().event, "cancelled");
    let job = d.job(&running).await;
    assert_eq!(job["state"], "cancelled");
    let done = job["progress"]["tiles_done"].as_u64().unwrap();
    assert!(done < 16, "stopped between tiles, not at the end: {done}");

    // Finished jobs cannot be cancelled again, and have no result.
    let (status, err) = d.post_json(&format!("/v1/jobs/{running}/cancel")).await;
    assert_eq!(status, StatusCode::CONFLICT, "{err}");
    let (status, _) = d.result(&running).await;
    assert_eq!(status, StatusCode::CONFLICT);
    d.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_full_queue_answers_429_with_retry_after_and_grpc_resource_exhausted() {
    let dir = tempfile::tempdir().unwrap();
    let d = start(dir.path(), &["--queue-capacity", "1", "--tile", "16", "--debug-tile-delay", "100ms"]).await;
    d.ready().await;
    let a = d.submit_ok(&frame(64, 64), "").await;
    d.wait_running(&a).await;
    let b = d.submit_ok(&frame(32, 32), "").await;

    let resp = d
        .http
        .send(Method::POST, "/v1/jobs", &[("content-type", "image/x-exr")], body_bytes(frame(32, 32)))
        .await
        .unwrap();
    let retry_after = resp.headers().get("retry-after").map(|v| v.to_str().unwrap().parse::<u64>().unwrap());
    let (status, err) = read_json(resp).await.unwrap();
    assert_eq!(status, StatusCode::TOO_MANY_REQUESTS, "{err}");
    assert_eq!(err["error"]["code"], "queue_full");
    assert!(retry_after.is_some_and(|s| s >= 1), "{retry_after:?}");

    let mut grpc = mcdenoise::client::grpc_connect(&d.grpc, None).await.unwrap();
    let path = write(dir.path(), "f.exr", &frame(32, 32));
    let upload = mcdenoise::client::upload_stream(Default::default(), &path, None, 4096).await.unwrap();
    let status = grpc.submit_job(upload).await.unwrap_err();
    assert_eq!(status.code(), tonic::Code::ResourceExhausted, "{status:?}");
    assert!(status.metadata().get("retry-after").is_some());
    // A machine-readable reason: google.rpc.ErrorInfo, as the HTTP code in capitals.
    use tonic_types::StatusExt;
    let info = status.get_details_error_info().expect("an ErrorInfo detail");
    assert_eq!((info.reason.as_str(), info.domain.as_str()), ("QUEUE_FULL", "mcdenoise"));
    assert_eq!(info.metadata.get("code").map(String::as_str), Some("queue_full"));
    assert!(info.metadata.get("retry_after_s").is_some_and(|s| s.parse::<u64>().unwrap() >= 1), "{info:?}");
    let missing = grpc.get_job(mcdenoise::grpc::pb::GetJobRequest { id: "nope".into() }).await.unwrap_err();
    assert_eq!(missing.get_details_error_info().map(|i| i.reason), Some("NOT_FOUND".to_string()));

    let (_, metrics) = d.get_json("/metrics").await;
    let metrics = metrics.as_str().unwrap().to_string();
    assert!(metrics.contains("mcdenoise_jobs_rejected_total{reason=\"queue_full\"} 2"), "{metrics}");
    assert!(metrics.contains("mcdenoise_queue_depth{priority=\"normal\"} 1"), "{metrics}");

    // Capacity frees up once the queued job leaves the queue.
    d.post_json(&format!("/v1/jobs/{b}/cancel")).await;
    let c = d.submit_ok(&frame(32, 32), "").await;
    d.post_json(&format!("/v1/jobs/{a}/cancel")).await;
    d.wait_state(&c, "succeeded").await;
    d.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn each_bad_input_gets_its_own_error_while_other_jobs_complete() {
    let dir = tempfile::tempdir().unwrap();
    let d = start(dir.path(), &["--max-pixels", "5000", "--max-body-bytes", "2000000"]).await;
    d.ready().await;
    let good = d.submit_ok(&frame(64, 64), "").await;

    // Not an EXR at all.
    let (status, err) = d.submit(b"this is not an EXR file", "", &[]).await;
    assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY, "{err}");
    assert_eq!(err["error"]["code"], "invalid_frame");
    assert!(err["error"]["message"].as_str().unwrap().starts_with("frame: "), "{err}");

    // A required channel missing: named in the answer.
    let (status, err) = d.submit(&frame_without(32, 32, "depth"), "", &[]).await;
    assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY, "{err}");
    let message = err["error"]["message"].as_str().unwrap();
    assert!(message.contains("missing channels: depth.Z"), "{message}");

    // Over the pixel limit (from the header).
    let (status, err) = d.submit(&frame(100, 60), "", &[]).await;
    assert_eq!(status, StatusCode::PAYLOAD_TOO_LARGE, "{err}");
    assert!(err["error"]["message"].as_str().unwrap().contains("over the limit of 5000"), "{err}");

    // Over the body limit: the daemon answers 413 at once and reads the rest of the body in
    // the background (up to 64 MiB), so the client reads the answer, not a reset.
    let over = vec![0u8; 2_500_000];
    let (status, err) =
        d.http.json(Method::POST, "/v1/jobs", &[("content-type", "image/x-exr")], body_bytes(over)).await.unwrap();
    assert_eq!(status, StatusCode::PAYLOAD_TOO_LARGE, "{err}");
    assert_eq!(err["error"]["code"], "too_large");

    // Bad options.
    let (status, err) = d.submit(&frame(32, 32), "priority=urgent", &[]).await;
    assert_eq!(status, StatusCode::BAD_REQUEST, "{err}");
    assert!(err["error"]["message"].as_str().unwrap().contains("urgent"));
    let (status, err) = d.submit(&frame(32, 32), "layers=albedo", &[]).await;
    assert_eq!(status, StatusCode::BAD_REQUEST, "{err}");
    let (ct, body) = multipart(r#"{"priority": "high", "colour": 1}"#, &[("frame", &frame(32, 32))]);
    let (status, err) =
        d.http.json(Method::POST, "/v1/jobs", &[("content-type", &ct)], body_bytes(body)).await.unwrap();
    assert_eq!(status, StatusCode::BAD_REQUEST, "{err}");
    assert!(err["error"]["message"].as_str().unwrap().contains("colour"), "{err}");
    let (status, _) = d.submit(&frame(32, 32), "", &[("content-type", "text/plain")]).await;
    assert_eq!(status, StatusCode::BAD_REQUEST);

    // A reference of another size.
    let (ct, body) = multipart("{}", &[("frame", &frame(32, 32)), ("reference", &reference(32, 16))]);
    let (status, err) =
        d.http.json(Method::POST, "/v1/jobs", &[("content-type", &ct)], body_bytes(body)).await.unwrap();
    assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY, "{err}");
    assert!(err["error"]["message"].as_str().unwrap().contains("reference is 32x16"), "{err}");

    // A valid header with truncated pixel data: accepted, then the job fails with the reason.
    let whole = frame(64, 64);
    let truncated = d.submit_ok(&whole[..whole.len() * 2 / 3], "").await;
    let job = d.wait_state(&truncated, "failed").await;
    assert_eq!(job["error"]["code"], "invalid_frame", "{job}");
    assert!(job["error"]["message"].as_str().unwrap().starts_with("frame: "), "{job}");

    // gRPC names the missing channel too.
    let mut grpc = mcdenoise::client::grpc_connect(&d.grpc, None).await.unwrap();
    let path = write(dir.path(), "nodepth.exr", &frame_without(32, 32, "depth"));
    let upload = mcdenoise::client::upload_stream(Default::default(), &path, None, 4096).await.unwrap();
    let status = grpc.submit_job(upload).await.unwrap_err();
    assert_eq!(status.code(), tonic::Code::InvalidArgument);
    assert!(status.message().contains("depth.Z"), "{}", status.message());

    // Unknown jobs and unfinished results.
    let (status, _) = d.get_json("/v1/jobs/no-such-job").await;
    assert_eq!(status, StatusCode::NOT_FOUND);
    let (status, _) = d.get_json("/v1/nothing-here").await;
    assert_eq!(status, StatusCode::NOT_FOUND);

    // Meanwhile the good job and a later one complete.
    d.wait_state(&good, "succeeded").await;
    let later = d.submit_ok(&frame(32, 32), "").await;
    d.wait_state(&later, "succeeded").await;
    let (_, list) = d.get_json("/v1/jobs").await;
    assert_eq!(list["jobs"].as_array().unwrap().len(), 3, "refused uploads leave no job: {list}");
    d.stop().await;
    // Job directories only: the storage health check's probe file may be mid-write in jobs/.
    let leftovers: Vec<_> = std::fs::read_dir(dir.path().join("jobs"))
        .unwrap()
        .flatten()
        .filter(|e| !e.file_name().to_string_lossy().starts_with(mcdenoise::jobs::HEALTH_PROBE))
        .map(|e| e.file_name())
        .collect();
    assert_eq!(leftovers.len(), 3, "refused uploads leave no files: {leftovers:?}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bearer_tokens_guard_everything_but_health() {
    let dir = tempfile::tempdir().unwrap();
    let d = start_with_token(dir.path(), &["--auth-token", "s3cret,other"], None).await;
    d.ready().await;
    for open in ["/livez", "/readyz"] {
        assert_eq!(d.http.get(open).await.unwrap().status(), StatusCode::OK, "{open}");
    }
    for guarded in ["/v1/jobs", "/metrics", "/v1/models", "/v1/openapi.json"] {
        let resp = d.http.get(guarded).await.unwrap();
        assert_eq!(resp.status(), StatusCode::UNAUTHORIZED, "{guarded}");
        assert!(resp.headers().get("www-authenticate").is_some());
    }
    let (status, _) = d.submit(&frame(32, 32), "", &[]).await;
    assert_eq!(status, StatusCode::UNAUTHORIZED);
    let (status, _) = d.submit(&frame(32, 32), "", &[("authorization", "Bearer wrong")]).await;
    assert_eq!(status, StatusCode::UNAUTHORIZED);
    let (status, job) = d.submit(&frame(32, 32), "", &[("authorization", "Bearer other")]).await;
    assert_eq!(status, StatusCode::ACCEPTED, "{job}");
    let authed = mcdenoise::client::HttpClient::new(&d.base, Some("s3cret"));
    let (status, _) = authed.json(Method::GET, "/v1/jobs", &[], body_bytes(vec![])).await.unwrap();
    assert_eq!(status, StatusCode::OK);

    // gRPC: the API needs the token, health does not.
    let mut anonymous = mcdenoise::client::grpc_connect(&d.grpc, None).await.unwrap();
    let err = anonymous.list_jobs(mcdenoise::grpc::pb::ListJobsRequest::default()).await.unwrap_err();
    assert_eq!(err.code(), tonic::Code::Unauthenticated);
    // Each submit token lists only its own jobs.
    let mut owner = mcdenoise::client::grpc_connect(&d.grpc, Some("other")).await.unwrap();
    let jobs = owner.list_jobs(mcdenoise::grpc::pb::ListJobsRequest::default()).await.unwrap().into_inner();
    assert_eq!(jobs.jobs.len(), 1);
    let mut client = mcdenoise::client::grpc_connect(&d.grpc, Some("s3cret")).await.unwrap();
    let jobs = client.list_jobs(mcdenoise::grpc::pb::ListJobsRequest::default()).await.unwrap().into_inner();
    assert_eq!(jobs.jobs.len(), 0);
    let channel =
        tonic::transport::Endpoint::from_shared(format!("http://{}", d.grpc)).unwrap().connect().await.unwrap();
    let mut health = tonic_health::pb::health_client::HealthClient::new(channel);
    let reply = health.check(tonic_health::pb::HealthCheckRequest { service: String::new() }).await.unwrap();
    assert_eq!(reply.into_inner().status, tonic_health::pb::health_check_response::ServingStatus::Serving as i32);
    d.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn metrics_models_and_openapi_are_served_from_the_start() {
    let dir = tempfile::tempdir().unwrap();
    let d = start(dir.path(), &[]).await;
    d.ready().await;
    let resp = d.http.get("/metrics").await.unwrap();
    assert!(resp.headers()["content-type"].to_str().unwrap().starts_with("application/openmetrics-text"));
    let (_, text) = read_json(resp).await.unwrap();
    let text = text.as_str().unwrap().to_string();
    for line in [
        "mcdenoise_queue_depth{priority=\"high\"} 0",
        "mcdenoise_queue_depth{priority=\"low\"} 0",
        "mcdenoise_jobs_finished_total{outcome=\"succeeded\"} 0",
        "mcdenoise_jobs_finished_total{outcome=\"failed\"} 0",
        "mcdenoise_jobs_in_flight 0",
        "mcdenoise_stage_duration_seconds_count{stage=\"inference\"} 0",
        "mcdenoise_received_bytes_total{transport=\"grpc\"} 0",
        "mcdenoise_ready 1",
        "mcdenoise_model_info{variant=\"nocov\",component=\"diffuse\"",
        &format!("mcdenoise_build_info{{version=\"{}\",onnxruntime=\"1.31.1\"", env!("CARGO_PKG_VERSION")),
        "process_cpu_seconds_total ",
        "process_resident_memory_bytes ",
        "process_open_fds ",
        "process_max_fds ",
        "process_threads ",
        "process_start_time_seconds ",
    ] {
        assert!(text.contains(line), "missing `{line}` in:\n{text}");
    }
    let rss: f64 =
        text.lines().find_map(|l| l.strip_prefix("process_resident_memory_bytes ")).unwrap().parse().unwrap();
    assert!(rss > 1e6, "{rss}");

    let (status, info) = d.get_json("/v1/info").await;
    assert_eq!(status, StatusCode::OK);
    assert_eq!(info["version"], env!("CARGO_PKG_VERSION"));
    assert_eq!((info["phase"].as_str(), info["ready"].as_bool()), (Some("ready"), Some(true)));
    // The device as asked, and where it resolved (`auto` would name what it chose).
    assert_eq!((info["device"]["kind"].as_str(), info["device"]["runs_on"].as_str()), (Some("cpu"), Some("cpu")));
    assert_eq!(info["device"]["workers"], 1);
    assert_eq!(info["models"].as_array().map(Vec::len), Some(4), "{info}");
    assert_eq!(info["settings"]["queue_capacity"], 256, "{info}");
    assert!(info["settings"]["data_dir"].as_str().unwrap().contains(dir.path().to_str().unwrap()));

    let (status, models) = d.get_json("/v1/models").await;
    assert_eq!(status, StatusCode::OK);
    let list = models["models"].as_array().unwrap();
    assert_eq!(list.len(), 4, "{models}");
    for m in list {
        assert_eq!(m["sha256"].as_str().unwrap().len(), 64);
        assert!(m["flops_per_pixel"].as_f64().unwrap() > 0.0);
        assert_eq!(m["contract"], "1");
    }

    let (status, api) = d.get_json("/v1/openapi.json").await;
    assert_eq!(status, StatusCode::OK);
    assert_eq!(api["openapi"], "3.1.0");
    for path in
        ["/v1/jobs", "/v1/jobs/{id}", "/v1/jobs/{id}/events", "/v1/jobs/{id}/result", "/v1/info", "/readyz", "/metrics"]
    {
        assert!(api["paths"][path].is_object(), "{path}");
    }

    // After a job: counters and histograms move.
    let id = d.submit_ok(&frame(32, 32), "").await;
    d.wait_state(&id, "succeeded").await;
    tokio::time::sleep(Duration::from_millis(50)).await;
    let (_, text) = d.get_json("/metrics").await;
    let text = text.as_str().unwrap().to_string();
    assert!(text.contains("mcdenoise_jobs_finished_total{outcome=\"succeeded\"} 1"), "{text}");
    assert!(text.contains("mcdenoise_stage_duration_seconds_count{stage=\"inference\"} 1"), "{text}");
    assert!(text.contains("mcdenoise_jobs_submitted_total{transport=\"http\"} 1"), "{text}");
    d.stop().await;
}

/// Firefly handling per job: the handled-sample count in the job's JSON (and its gRPC form)
/// and in `mcdenoise_firefly_samples_total`; `off` per job; a bad strength refused.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn fireflies_are_counted_per_job_and_on_metrics() {
    let dir = tempfile::tempdir().unwrap();
    let d = start(dir.path(), &[]).await;
    d.ready().await;
    let (w, h) = (40, 32);
    // Three isolated outliers in the diffuse buffer, with variance raised to match.
    let mut planes = common::named_planes(w, h, false);
    let outliers = [5 * w + 7, 16 * w + 20, 25 * w + 33];
    for (name, plane) in planes.iter_mut() {
        for &i in &outliers {
            if name.starts_with("diffuse.") {
                plane[i] = 5e3;
            } else if name == "diffuseVariance.Z" {
                plane[i] = 2.5e7;
            }
        }
    }
    let exr = common::exr_single(w, h, &planes, common::Sample::F32);

    let auto = d.submit_ok(&exr, "fireflies=auto&firefly_strength=1.5").await;
    let off = d.submit_ok(&exr, "fireflies=off").await;
    let default = d.submit_ok(&exr, "").await;
    let auto = d.wait_state(&auto, "succeeded").await;
    let off = d.wait_state(&off, "succeeded").await;
    let default = d.wait_state(&default, "succeeded").await;
    assert_eq!(auto["requested_fireflies"], "auto");
    assert_eq!(auto["fireflies"]["mode"], "auto");
    assert_eq!(auto["fireflies"]["strength"], 1.5);
    assert_eq!(auto["fireflies"]["handled"], 3, "{auto}");
    assert_eq!(auto["fireflies"]["by_component"]["diffuse"], 3);
    assert_eq!(auto["fireflies"]["by_component"]["specular"], 0);
    assert_eq!(off["fireflies"]["mode"], "off");
    assert_eq!(off["fireflies"]["handled"], 0);
    assert_eq!(default["requested_fireflies"], serde_json::Value::Null);
    assert_eq!(
        (default["fireflies"]["mode"].as_str(), default["fireflies"]["strength"].as_f64()),
        (Some("auto"), Some(1.0))
    );
    assert_eq!(default["fireflies"]["handled"], 3);

    let (_, metrics) = d.get_json("/metrics").await;
    let metrics = metrics.as_str().unwrap().to_string();
    assert!(metrics.contains("mcdenoise_firefly_samples_total 6\n"), "{metrics}");

    // The gRPC form of the same job.
    let id = auto["id"].as_str().unwrap().to_string();
    let mut client = mcdenoise::client::grpc_connect(&d.grpc, None).await.unwrap();
    let job = client.get_job(mcdenoise::grpc::pb::GetJobRequest { id }).await.unwrap().into_inner();
    let pb = job.fireflies.unwrap();
    assert_eq!((pb.mode.as_str(), pb.strength, pb.handled, pb.diffuse), ("auto", 1.5, 3, 3));

    // Options over gRPC: `off` per job; the job reports it.
    use mcdenoise::grpc::pb;
    let path = write(dir.path(), "outliers.exr", &exr);
    let options = pb::JobOptions { fireflies: pb::FireflyMode::Off as i32, ..Default::default() };
    let upload = mcdenoise::client::upload_stream(options, &path, None, 1 << 20).await.unwrap();
    let job = client.submit_job(upload).await.unwrap().into_inner();
    let done = d.wait_state(&job.id, "succeeded").await;
    assert_eq!((done["fireflies"]["mode"].as_str(), done["fireflies"]["handled"].as_u64()), (Some("off"), Some(0)));
    let options = pb::JobOptions { firefly_strength: 20.0, ..Default::default() };
    let upload = mcdenoise::client::upload_stream(options, &path, None, 1 << 20).await.unwrap();
    let err = client.submit_job(upload).await.unwrap_err();
    assert_eq!(err.code(), tonic::Code::InvalidArgument, "{err:?}");

    for bad in ["firefly_strength=50", "firefly_strength=0", "fireflies=sometimes"] {
        let (status, err) = d.submit(&exr, bad, &[]).await;
        assert_eq!(status, StatusCode::BAD_REQUEST, "{bad}: {err}");
    }
    d.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_wrong_token_on_a_large_upload_is_answered_401_counted_and_logged() {
    let dir = tempfile::tempdir().unwrap();
    let d = start_with_token(dir.path(), &["--auth-token", "tok", "--operator-token", "ops"], Some("wrong")).await;
    d.ready().await;
    // 8 MiB the daemon must not keep: the client still reads the 401, not a reset.
    let big = vec![0u8; 8 << 20];
    for _ in 0..3 {
        let len = big.len().to_string();
        let headers = [("content-type", "image/x-exr"), ("content-length", len.as_str())];
        let (status, err) = d.http.json(Method::POST, "/v1/jobs", &headers, body_bytes(big.clone())).await.unwrap();
        assert_eq!(status, StatusCode::UNAUTHORIZED, "{err}");
        assert_eq!(err["error"]["code"], "unauthenticated");
    }
    // gRPC: a refused SubmitJob is counted too; other refused calls are not submissions.
    let mut grpc = mcdenoise::client::grpc_connect(&d.grpc, Some("wrong")).await.unwrap();
    let upload = futures_util::stream::iter([mcdenoise::grpc::pb::SubmitJobRequest::default()]);
    assert_eq!(grpc.submit_job(upload).await.unwrap_err().code(), tonic::Code::Unauthenticated);
    let err = grpc.list_jobs(mcdenoise::grpc::pb::ListJobsRequest::default()).await.unwrap_err();
    assert_eq!(err.code(), tonic::Code::Unauthenticated);
    assert_eq!(d.http.get("/v1/jobs").await.unwrap().status(), StatusCode::UNAUTHORIZED);
    let submitter = mcdenoise::client::HttpClient::new(&d.base, Some("tok"));
    let (status, info) = submitter.json(Method::GET, "/v1/info", &[], body_bytes(vec![])).await.unwrap();
    assert_eq!(status, StatusCode::OK);
    assert_eq!((info["caller"]["scope"].as_str(), info["settings"].is_null()), (Some("submit"), true), "{info}");
    let ops = mcdenoise::client::HttpClient::new(&d.base, Some("ops"));
    let (_, info) = ops.json(Method::GET, "/v1/info", &[], body_bytes(vec![])).await.unwrap();
    assert_eq!(info["caller"]["scope"], "operator");
    assert_eq!(info["settings"]["auth"], "1 submit token(s), 1 operator token(s)", "{info}");
    assert!(!info.to_string().contains("\"tok\"") && !info.to_string().contains("\"ops\""), "{info}");
    let (status, text) = ops.json(Method::GET, "/metrics", &[], body_bytes(vec![])).await.unwrap();
    assert_eq!(status, StatusCode::OK);
    let text = text.as_str().unwrap();
    assert!(text.contains("mcdenoise_jobs_rejected_total{reason=\"unauthenticated\"} 4"), "{text}");
    d.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn events_have_ids_resume_after_last_event_id_and_end_with_deleted() {
    let dir = tempfile::tempdir().unwrap();
    let d = start(dir.path(), &["--tile", "16", "--debug-tile-delay", "150ms"]).await;
    d.ready().await;
    let running = d.submit_ok(&frame(64, 64), "").await;
    let queued = d.submit_ok(&frame(32, 32), "").await;
    // Read the running job's events up to tile 2, then reconnect from there.
    let resp = d.http.get(&format!("/v1/jobs/{running}/events")).await.unwrap();
    let mut events = mcdenoise::client::SseReader::new(resp);
    let mut seen = Vec::new();
    while let Some(ev) = events.next().await.unwrap() {
        let id = ev.id.clone().expect("every event has an id");
        seen.push((ev.event.clone(), id.clone()));
        if id == "1.2" {
            break;
        }
    }
    assert!(seen.iter().any(|(e, id)| e == "started" && id == "1.started"), "{seen:?}");
    drop(events);
    let resp = d
        .http
        .send(Method::GET, &format!("/v1/jobs/{running}/events"), &[("last-event-id", "1.2")], body_bytes(vec![]))
        .await
        .unwrap();
    let mut events = mcdenoise::client::SseReader::new(resp);
    let first = events.next().await.unwrap().expect("an event");
    assert_eq!(first.event, "progress", "{first:?}");
    assert!(first.data["tiles_done"].as_u64().unwrap() > 2, "{first:?}");
    assert_eq!(first.id.as_deref(), Some(format!("1.{}", first.data["tiles_done"]).as_str()));
    // A job deleted while watched ends its stream with `deleted`.
    let watcher = {
        let http = d.http.clone();
        let path = format!("/v1/jobs/{queued}/events");
        tokio::spawn(async move {
            let mut out = Vec::new();
            let resp = http.get(&path).await.unwrap();
            mcdenoise::client::read_sse(resp, |e| {
                out.push(e);
                true
            })
            .await
            .unwrap();
            out
        })
    };
    tokio::time::sleep(Duration::from_millis(300)).await;
    let resp = d.http.send(Method::DELETE, &format!("/v1/jobs/{queued}"), &[], body_bytes(vec![])).await.unwrap();
    assert!(resp.status().is_success(), "{}", resp.status());
    let got = tokio::time::timeout(Duration::from_secs(10), watcher).await.expect("the stream ends").unwrap();
    let names: Vec<&str> = got.iter().map(|e| e.event.as_str()).collect();
    assert_eq!(names, ["queued", "deleted"], "{got:?}");
    assert_eq!(got[1].data["id"], queued.as_str());
    d.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_cycles_frame_without_the_diffuse_passes_is_denoised_with_a_warning() {
    let dir = tempfile::tempdir().unwrap();
    let d = start(dir.path(), &[]).await;
    d.ready().await;
    let (bytes, _) = common::cycles_frame(32, 24, |p| !p.starts_with("Diffuse"));
    let id = d.submit_ok(&bytes, "").await;
    let job = d.wait_state(&id, "succeeded").await;
    let warnings = job["warnings"].as_array().unwrap();
    assert_eq!(warnings.len(), 1, "{job}");
    assert!(warnings[0].as_str().unwrap().contains("Diffuse Direct, Indirect and Color passes"), "{job}");
    let mut grpc = mcdenoise::client::grpc_connect(&d.grpc, None).await.unwrap();
    let pb = grpc.get_job(mcdenoise::grpc::pb::GetJobRequest { id: id.clone() }).await.unwrap().into_inner();
    assert_eq!(pb.warnings.len(), 1);
    let (bytes, _) = common::cycles_frame(32, 24, |_| true);
    let id = d.submit_ok(&bytes, "").await;
    assert_eq!(d.wait_state(&id, "succeeded").await["warnings"], serde_json::json!([]));
    d.stop().await;
}

/// A frame's diffuse, specular, albedo, normal and depth planes under their canonical names
/// (no variances), the twin that renderer-named frames are compared with.
fn canonical_buffers(w: usize, h: usize) -> Vec<(String, Vec<f32>)> {
    common::named_planes(w, h, false)
        .into_iter()
        .filter(|(n, _)| ["diffuse.", "specular.", "albedo.", "normal.", "depth."].iter().any(|p| n.starts_with(p)))
        .collect()
}

/// An Arnold-named frame (beauty R,G,B,A, diffuse_direct/indirect, denoise_albedo, N, Z) is
/// denoised through the Arnold preset, as its canonical twin is; one without its depth AOV
/// is refused naming the AOVs Arnold must write.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_arnold_named_frame_is_denoised_through_its_preset() {
    let (w, h) = (40, 24);
    let canonical = canonical_buffers(w, h);
    let get = |n: &str| canonical.iter().find(|(k, _)| k == n).unwrap().1.clone();
    let mut arnold: Vec<(String, Vec<f32>)> = Vec::new();
    for (c, axis) in ["R", "G", "B"].into_iter().zip(["X", "Y", "Z"]) {
        let (d, s) = (get(&format!("diffuse.{c}")), get(&format!("specular.{c}")));
        arnold.push((c.into(), d.iter().zip(&s).map(|(a, b)| a + b).collect()));
        arnold.push((format!("diffuse_direct.{c}"), d.iter().map(|v| 0.75 * v).collect()));
        arnold.push((format!("diffuse_indirect.{c}"), d.iter().map(|v| 0.25 * v).collect()));
        arnold.push((format!("denoise_albedo.{c}"), get(&format!("albedo.{c}"))));
        arnold.push((format!("N.{axis}"), get(&format!("normal.{c}"))));
    }
    arnold.push(("A".into(), vec![1.0; w * h]));
    arnold.push(("Z".into(), get("depth.Z")));
    let exr = |planes: &[(String, Vec<f32>)]| common::exr_single(w, h, planes, common::Sample::F32);

    let dir = tempfile::tempdir().unwrap();
    let d = start(dir.path(), &[]).await;
    d.ready().await;
    let twin = d.submit_ok(&exr(&canonical), "").await;
    let id = d.submit_ok(&exr(&arnold), "").await;
    let job = d.wait_state(&id, "succeeded").await;
    assert_eq!(job["variant"], "nocov", "{job}");
    d.wait_state(&twin, "succeeded").await;
    let read = |bytes: Vec<u8>| Frame::reference_from_exr_bytes(&bytes, &Default::default()).unwrap();
    let (a, b) = (read(d.result(&id).await.1), read(d.result(&twin).await.1));
    for c in 0..3 {
        let diff = max_rel_diff(&a.color()[c], &b.color()[c]);
        assert!(diff < 1e-3, "channel {c}: {diff}");
    }
    let without_depth: Vec<_> = arnold.iter().filter(|(n, _)| n != "Z").cloned().collect();
    let (status, err) = d.submit(&exr(&without_depth), "", &[]).await;
    assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY, "{err}");
    let message = err["error"]["message"].as_str().unwrap();
    assert!(message.contains("this looks like Arnold output") && message.contains("depth: Z"), "{message}");
    d.stop().await;
}

/// A studio's own AOV names, mapped by a `[channel_maps.studio]` table of the config file
/// (tried before the shipped presets, and selectable by name), or by the job's own inline
/// map; a job that names a map is told what that map lacks, one that names no known map
/// is told which exist.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn channel_maps_from_the_config_file_and_the_job_read_a_studio_s_names() {
    let (w, h) = (40, 24);
    let canonical = canonical_buffers(w, h);
    let get = |n: &str| canonical.iter().find(|(k, _)| k == n).unwrap().1.clone();
    let mut studio: Vec<(String, Vec<f32>)> = vec![("dist".into(), get("depth.Z"))];
    for (c, axis) in ["R", "G", "B"].into_iter().zip(["X", "Y", "Z"]) {
        let (d, s) = (get(&format!("diffuse.{c}")), get(&format!("specular.{c}")));
        studio.push((c.into(), d.iter().zip(&s).map(|(a, b)| a + b).collect()));
        studio.push((format!("diff.{c}"), d));
        studio.push((format!("spec.{c}"), s));
        studio.push((format!("alb.{c}"), get(&format!("albedo.{c}"))));
        studio.push((format!("nrm.{axis}"), get(&format!("normal.{c}"))));
    }
    let exr = |planes: &[(String, Vec<f32>)]| common::exr_single(w, h, planes, common::Sample::F32);

    let dir = tempfile::tempdir().unwrap();
    let config = dir.path().join("serve.toml");
    std::fs::write(
        &config,
        "[channel_maps.studio]\nrenderer = \"Studio renderer\"\ndiffuse = \"diff\"\nspecular = \"spec\"\n\
         albedo = \"alb\"\nnormal = \"nrm\"\ndepth = \"dist\"\n",
    )
    .unwrap();
    let d = start(&dir.path().join("data"), &["--config", config.to_str().unwrap()]).await;
    d.ready().await;
    let (_, info) = d.get_json("/v1/info").await;
    assert_eq!(info["channel_maps"][0], serde_json::json!({ "name": "studio", "renderer": "Studio renderer" }));

    let query =
        |map: &str| mcdenoise::wire::OptionsQuery { channel_map: Some(map.into()), ..Default::default() }.encode();
    let twin = d.submit_ok(&exr(&canonical), "").await;
    let auto = d.submit_ok(&exr(&studio), "").await;
    let named = d.submit_ok(&exr(&studio), &query("studio")).await;
    let inline =
        d.submit_ok(&exr(&studio), &query("diffuse=diff; specular=spec; albedo=alb; normal=nrm; depth=dist")).await;
    d.wait_state(&twin, "succeeded").await;
    let read = |bytes: Vec<u8>| Frame::reference_from_exr_bytes(&bytes, &Default::default()).unwrap();
    let expected = read(d.result(&twin).await.1);
    for id in [&auto, &named, &inline] {
        let job = d.wait_state(id, "succeeded").await;
        let got = read(d.result(id).await.1);
        for c in 0..3 {
            let diff = max_rel_diff(&got.color()[c], &expected.color()[c]);
            assert!(diff < 1e-3, "{job}: channel {c}: {diff}");
        }
    }
    assert_eq!(d.job(&named).await["channel_map"], "studio");
    assert_eq!(d.job(&auto).await["channel_map"], serde_json::Value::Null);

    // Read through Arnold's map, the frame lacks Arnold's AOVs: named in that map's terms.
    let (status, err) = d.submit(&exr(&studio), &query("arnold"), &[]).await;
    assert_eq!(status, StatusCode::UNPROCESSABLE_ENTITY, "{err}");
    let message = err["error"]["message"].as_str().unwrap();
    assert!(message.contains("channel map `arnold` (Arnold)") && message.contains("depth: Z"), "{message}");
    // An unknown map is refused before the upload is read, listing the maps there are.
    let (status, err) = d.submit(&exr(&studio), &query("maya"), &[]).await;
    assert_eq!(status, StatusCode::BAD_REQUEST, "{err}");
    let message = err["error"]["message"].as_str().unwrap();
    assert!(message.contains("unknown channel map `maya`") && message.contains("studio, arnold"), "{message}");
    let (status, err) = d.submit(&exr(&studio), &query("diffuse=diff;colour=c"), &[]).await;
    assert_eq!(status, StatusCode::BAD_REQUEST, "{err}");
    assert!(err["error"]["message"].as_str().unwrap().contains("unknown key `colour`"), "{err}");
    d.stop().await;
}
