//! The daemon's life: readiness while loading and draining, restarts (graceful and after
//! SIGKILL) without losing or repeating work, deadlines, retention, and the
//! `mcdenoise submit` client against a live daemon.

use crate::daemon_common;

use std::process::Command;
use std::time::Duration;

use hyper::StatusCode;
use serde_json::Value;

use daemon_common::*;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn readiness_is_false_until_models_load_and_while_draining() {
    let dir = tempfile::tempdir().unwrap();
    let d = start(dir.path(), &["--debug-startup-delay", "800ms", "--tile", "16", "--debug-tile-delay", "60ms"]).await;
    // Loading: alive, not ready, submissions refused, gRPC health NOT_SERVING.
    assert_eq!(d.http.get("/livez").await.unwrap().status(), StatusCode::OK);
    let (status, body) = d.get_json("/readyz").await;
    assert_eq!(status, StatusCode::SERVICE_UNAVAILABLE);
    assert_eq!(body["phase"], "loading");
    let (status, err) = d.submit(&frame(32, 32), "", &[]).await;
    assert_eq!(status, StatusCode::SERVICE_UNAVAILABLE, "{err}");
    let channel =
        tonic::transport::Endpoint::from_shared(format!("http://{}", d.grpc)).unwrap().connect().await.unwrap();
    let mut health = tonic_health::pb::health_client::HealthClient::new(channel);
    let check = || tonic_health::pb::HealthCheckRequest { service: String::new() };
    let not_serving = tonic_health::pb::health_check_response::ServingStatus::NotServing as i32;
    assert_eq!(health.check(check()).await.unwrap().into_inner().status, not_serving);
    let (status, _) = d.get_json("/v1/models").await;
    assert_eq!(status, StatusCode::SERVICE_UNAVAILABLE);

    d.ready().await;
    let (_, body) = d.get_json("/readyz").await;
    assert_eq!(body["phase"], "ready");

    // Draining: a running job finishes, nothing new is admitted, readiness is false.
    let running = d.submit_ok(&frame(64, 64), "").await;
    d.wait_running(&running).await;
    let queued = d.submit_ok(&frame(32, 32), "").await;
    d.server.shutdown();
    let body = poll("readiness turning false", Duration::from_secs(5), || async {
        match d.get_json("/readyz").await {
            (StatusCode::SERVICE_UNAVAILABLE, body) => Ok(body),
            other => Err(other),
        }
    })
    .await;
    assert_eq!(body["phase"], "draining");
    assert_eq!(health.check(check()).await.unwrap().into_inner().status, not_serving);
    let (status, err) = d.submit(&frame(32, 32), "", &[]).await;
    assert_eq!(status, StatusCode::SERVICE_UNAVAILABLE, "{err}");
    assert!(err["error"]["message"].as_str().unwrap().contains("shutting down"));
    assert_eq!(d.job(&queued).await["state"], "queued", "queued work waits for the next start");
    // The running job completes during the drain (its event stream, opened while draining,
    // ends with success); then the listeners close. That its result and the queued job
    // survive the restart is `a_restart_keeps_finished_results_and_runs_queued_and_interrupted_jobs`.
    let events = d.events(&running).await;
    assert_eq!(events.last().unwrap().event, "succeeded");
    d.server.wait().await.unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_restart_keeps_finished_results_and_runs_queued_and_interrupted_jobs() {
    let dir = tempfile::tempdir().unwrap();
    let slow = ["--tile", "16", "--debug-tile-delay", "80ms", "--shutdown-timeout", "0s"];
    let d = start(dir.path(), &slow).await;
    d.ready().await;
    let finished = d.submit_ok(&frame(32, 16), "").await;
    d.wait_state(&finished, "succeeded").await;
    let (_, result_before) = d.result(&finished).await;
    let interrupted = d.submit_ok(&frame(64, 64), "").await;
    d.wait_running(&interrupted).await;
    let queued = d.submit_ok(&frame(32, 32), "idempotency_key=shot-3").await;
    // Shutdown timeout 0: the running job is stopped at its next tile and requeued.
    d.stop().await;

    let d = start(dir.path(), &[]).await;
    d.ready().await;
    let job = d.job(&finished).await;
    assert_eq!((job["state"].as_str(), job["attempts"].as_u64()), (Some("succeeded"), Some(1)), "{job}");
    assert_eq!(d.result(&finished).await.1, result_before, "the finished result is served unchanged");
    let job = d.wait_state(&interrupted, "succeeded").await;
    assert_eq!(job["attempts"], 2, "interrupted once, then completed: {job}");
    let job = d.wait_state(&queued, "succeeded").await;
    assert_eq!(job["attempts"], 1, "{job}");
    // The idempotency key survives the restart.
    let (_, again) = d.submit(&frame(32, 32), "idempotency_key=shot-3", &[]).await;
    assert_eq!(again["id"].as_str(), Some(queued.as_str()));
    let (_, list) = d.get_json("/v1/jobs").await;
    assert_eq!(list["jobs"].as_array().unwrap().len(), 3, "{list}");
    let (_, metrics) = d.get_json("/metrics").await;
    assert!(metrics.as_str().unwrap().contains("mcdenoise_jobs_finished_total{outcome=\"succeeded\"} 2"));
    d.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_killed_daemon_loses_nothing_and_completes_nothing_twice() {
    use hyper::Method;
    use mcdenoise::client::{body_bytes, HttpClient};
    let dir = tempfile::tempdir().unwrap();
    let mut p = spawn_daemon(dir.path(), &["--tile", "16", "--debug-tile-delay", "80ms"]);
    let http = HttpClient::new(&p.http, None);
    let submit = |http: HttpClient, exr: Vec<u8>| async move {
        let (s, j) =
            http.json(Method::POST, "/v1/jobs", &[("content-type", "image/x-exr")], body_bytes(exr)).await.unwrap();
        assert_eq!(s, StatusCode::ACCEPTED, "{j}");
        j["id"].as_str().unwrap().to_string()
    };
    wait_ready(&http).await;
    let done = submit(http.clone(), frame(32, 16)).await;
    wait_job(&http, &done, "succeeded", |j| j["state"] == "succeeded").await;
    let (_, before) = get_json(&http, &format!("/v1/jobs/{done}")).await.unwrap();
    let running = submit(http.clone(), frame(64, 64)).await;
    wait_job(&http, &running, "in the expected state", |j| {
        j["state"] == "running" && j["progress"]["tiles_done"].as_u64() >= Some(2)
    })
    .await;
    let queued = submit(http.clone(), frame(32, 32)).await;

    p.kill();

    let mut p = spawn_daemon(dir.path(), &[]);
    let http = HttpClient::new(&p.http, None);
    let (_, after) = get_json(&http, &format!("/v1/jobs/{done}")).await.unwrap();
    assert_eq!(after["state"], "succeeded");
    assert_eq!(after["attempts"], 1, "not run again");
    assert_eq!(after["result_bytes"], before["result_bytes"]);
    let j = wait_job(&http, &running, "in the expected state", |j| j["state"] == "succeeded").await;
    assert_eq!(j["attempts"], 2, "the interrupted run started again: {j}");
    let j = wait_job(&http, &queued, "in the expected state", |j| j["state"] == "succeeded").await;
    assert_eq!(j["attempts"], 1);
    let resp = http.get(&format!("/v1/jobs/{done}/result")).await.unwrap();
    assert_eq!(resp.status(), StatusCode::OK);
    let mut grpc = mcdenoise::client::grpc_connect(&p.grpc, None).await.unwrap();
    let job = grpc.get_job(mcdenoise::grpc::pb::GetJobRequest { id: done.clone() }).await.unwrap().into_inner();
    assert_eq!(job.state, mcdenoise::grpc::pb::JobState::Succeeded as i32);

    // SIGTERM: a graceful exit with status 0.
    let status = p.terminate();
    assert!(status.success(), "{status:?}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn deadlines_fail_slow_jobs_and_expired_jobs_are_removed() {
    let dir = tempfile::tempdir().unwrap();
    let d = start(
        dir.path(),
        &["--tile", "16", "--debug-tile-delay", "100ms", "--result-ttl", "1500ms", "--janitor-interval", "100ms"],
    )
    .await;
    d.ready().await;
    // The slow job (32 tiles of 100 ms) fails at its deadline, 2 s; the job queued behind it
    // has a deadline a second earlier, so it has expired, by a margin no scheduling delay
    // eats, before the worker is free to start it.
    let slow = d.submit_ok(&frame(128, 64), "deadline_seconds=2").await;
    let queued_behind = d.submit_ok(&frame(64, 64), "deadline_seconds=1").await;
    let job = d.wait_state(&slow, "failed").await;
    assert_eq!(job["error"]["code"], "deadline_exceeded", "{job}");
    let job = d.wait_state(&queued_behind, "failed").await;
    assert_eq!(job["error"]["code"], "deadline_exceeded", "{job}");
    assert_eq!(job["attempts"], 0, "failed while queued, never started: {job}");

    let quick = d.submit_ok(&frame(16, 16), "").await;
    d.wait_state(&quick, "succeeded").await;
    assert!(dir.path().join("jobs").join(&quick).join("result.exr").is_file());
    // Removed after the retention time: from the API, then (just after) from the disk.
    let job_dir = dir.path().join("jobs").join(&quick);
    poll("the job's removal", Duration::from_secs(10), || async {
        match d.get_json(&format!("/v1/jobs/{quick}")).await {
            (StatusCode::NOT_FOUND, _) if !job_dir.exists() => Ok(()),
            other => Err((other, job_dir.exists())),
        }
    })
    .await;
    d.stop().await;
}

async fn run(mut cmd: Command) -> std::process::Output {
    tokio::task::spawn_blocking(move || cmd.output().unwrap()).await.unwrap()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_submit_command_waits_and_writes_the_result_over_http_and_grpc() {
    let dir = tempfile::tempdir().unwrap();
    let d = start(dir.path(), &["--auth-token", "tok"]).await;
    d.ready().await;
    let frame_path = write(dir.path(), "frame.exr", &frame(40, 24));
    let reference_path = write(dir.path(), "ref.exr", &reference(40, 24));
    for server in [d.base.clone(), format!("grpc://{}", d.grpc)] {
        let out = dir.path().join(format!("out-{}.exr", server.len()));
        let mut cmd = Command::new(env!("CARGO_BIN_EXE_mcdenoise"));
        cmd.args(["submit", frame_path.to_str().unwrap(), "--server", &server, "--wait", "-o"])
            .arg(&out)
            .args(["--reference", reference_path.to_str().unwrap(), "--layers", "diffuse", "--label", "cli"])
            .env("MCDENOISE_TOKEN", "tok");
        let output = run(cmd).await;
        let stderr = String::from_utf8_lossy(&output.stderr);
        assert!(output.status.success(), "{server}: {stderr}");
        let job: Value = serde_json::from_slice(&output.stdout).unwrap();
        assert_eq!(job["state"], "succeeded", "{server}: {job}");
        assert!(job["metrics"]["output"]["relmse"].is_number(), "{server}: {job}");
        assert!(stderr.contains("submitted job") && stderr.contains("succeeded"), "{stderr}");
        let result =
            mcdenoise::frame::Frame::reference_from_exr_bytes(&std::fs::read(&out).unwrap(), &Default::default());
        assert_eq!(result.unwrap().width, 40);
    }
    // Without the token: refused, with a non-zero exit status and the reason.
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_mcdenoise"));
    cmd.args(["submit", frame_path.to_str().unwrap(), "--server", &d.base]).env_remove("MCDENOISE_TOKEN");
    let output = run(cmd).await;
    assert!(!output.status.success());
    assert!(String::from_utf8_lossy(&output.stderr).contains("401"), "{}", String::from_utf8_lossy(&output.stderr));
    d.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_submit_command_denoises_a_frame_range_retrying_a_full_queue() {
    let dir = tempfile::tempdir().unwrap();
    let d = start(dir.path(), &["--queue-capacity", "1", "--tile", "16", "--debug-tile-delay", "20ms"]).await;
    d.ready().await;
    for n in 1..=4 {
        write(dir.path(), &format!("shot.{n:04}.exr"), &frame(40, 24));
    }
    // Frames 1-4 at once against a queue of one: refused with 429 and retried; frame 5 is missing.
    let pattern = dir.path().join("shot.####.exr");
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_mcdenoise"));
    cmd.args(["submit", pattern.to_str().unwrap(), "--server", &d.base, "--frames", "1-5", "--concurrency", "4"]);
    let output = run(cmd).await;
    let stderr = String::from_utf8_lossy(&output.stderr);
    assert!(!output.status.success(), "{stderr}");
    assert!(stderr.contains("1 of 5 frames failed: 5"), "{stderr}");
    assert!(stderr.contains("429") && stderr.contains("retrying in"), "{stderr}");
    let rows: Vec<Value> =
        String::from_utf8_lossy(&output.stdout).lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    assert_eq!(rows.len(), 5);
    for n in 1..=4u64 {
        let row = rows.iter().find(|r| r["frame"] == n).unwrap();
        assert_eq!(row["job"]["state"], "succeeded", "{row}");
        let out = dir.path().join(format!("shot.denoised.{n:04}.exr"));
        assert_eq!(row["output"], out.to_str().unwrap());
        assert!(out.is_file(), "{}", out.display());
    }
    assert!(rows.iter().find(|r| r["frame"] == 5).unwrap()["error"].as_str().unwrap().contains("shot.0005.exr"));
    d.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_submit_command_reports_a_wrong_token_on_a_large_upload_as_401_at_once() {
    let dir = tempfile::tempdir().unwrap();
    let d = start(dir.path(), &["--auth-token", "tok"]).await;
    d.ready().await;
    // Larger than the daemon reads from a refused client: the connection is closed on it.
    let big = write(dir.path(), "big.exr", &vec![0u8; 80 << 20]);
    for server in [d.base.clone(), format!("grpc://{}", d.grpc)] {
        let mut cmd = Command::new(env!("CARGO_BIN_EXE_mcdenoise"));
        cmd.args(["submit", big.to_str().unwrap(), "--server", &server, "--token", "wrong"]);
        let t = std::time::Instant::now();
        let output = run(cmd).await;
        let stderr = String::from_utf8_lossy(&output.stderr);
        assert!(!output.status.success(), "{stderr}");
        assert!(stderr.contains("401") || stderr.contains("Unauthenticated"), "{server}: {stderr}");
        assert!(stderr.contains("invalid bearer token") && !stderr.contains("retrying"), "{server}: {stderr}");
        assert!(t.elapsed() < Duration::from_secs(30), "{server}: took {:?}", t.elapsed());
    }
    d.stop().await;
}

#[test]
fn a_second_daemon_on_a_data_directory_in_use_exits_with_a_clear_error() {
    let dir = tempfile::tempdir().unwrap();
    let mut first = spawn_daemon(dir.path(), &[]);
    let second = Command::new(env!("CARGO_BIN_EXE_mcdenoise")).args(args(dir.path(), &[])).output().unwrap();
    assert_eq!(second.status.code(), Some(1));
    let err = String::from_utf8_lossy(&second.stderr);
    assert!(
        err.contains(&format!("the data directory {} is in use by another mcdenoise daemon", dir.path().display())),
        "{err}"
    );
    assert!(first.terminate().success());
}

/// An OpenTelemetry collector on loopback that keeps every span it is sent.
#[derive(Clone, Default)]
struct Collector(std::sync::Arc<std::sync::Mutex<Vec<opentelemetry_proto::tonic::trace::v1::Span>>>);

#[tonic::async_trait]
impl opentelemetry_proto::tonic::collector::trace::v1::trace_service_server::TraceService for Collector {
    async fn export(
        &self,
        request: tonic::Request<opentelemetry_proto::tonic::collector::trace::v1::ExportTraceServiceRequest>,
    ) -> Result<
        tonic::Response<opentelemetry_proto::tonic::collector::trace::v1::ExportTraceServiceResponse>,
        tonic::Status,
    > {
        let mut spans = self.0.lock().unwrap();
        for resource in request.into_inner().resource_spans {
            let service = resource
                .resource
                .iter()
                .flat_map(|r| &r.attributes)
                .any(|a| a.key == "service.name" && format!("{:?}", a.value).contains("\"farm-denoiser\""));
            assert!(service, "spans come with the configured service.name");
            spans.extend(resource.scope_spans.into_iter().flat_map(|s| s.spans));
        }
        Ok(tonic::Response::new(Default::default()))
    }
}

/// With `--otlp-endpoint` the daemon sends its spans to an OpenTelemetry collector: the
/// submission's HTTP span continues the client's `traceparent` and carries the job id, and
/// the job's run (on a worker, later) is that span's child, with its stages as children.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn traces_reach_an_otlp_collector_with_the_job_id() {
    use opentelemetry_proto::tonic::collector::trace::v1::trace_service_server::TraceServiceServer;
    use opentelemetry_proto::tonic::common::v1::any_value::Value as Any;
    let collector = Collector::default();
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let endpoint = format!("http://{}", listener.local_addr().unwrap());
    tokio::spawn(
        tonic::transport::Server::builder()
            .add_service(TraceServiceServer::new(collector.clone()))
            .serve_with_incoming(tokio_stream::wrappers::TcpListenerStream::new(listener)),
    );
    let dir = tempfile::tempdir().unwrap();
    let mut p = spawn_daemon(dir.path(), &["--otlp-endpoint", &endpoint, "--otlp-service-name", "farm-denoiser"]);
    let http = mcdenoise::client::HttpClient::new(&p.http, None);
    wait_ready(&http).await;
    let (trace_id, client_span) = ("4bf92f3577b34da6a3ce929d0e0e4736", "00f067aa0ba902b7");
    let traceparent = format!("00-{trace_id}-{client_span}-01");
    let headers = [("content-type", "image/x-exr"), ("traceparent", traceparent.as_str())];
    let (status, job) = http
        .json(hyper::Method::POST, "/v1/jobs", &headers, mcdenoise::client::body_bytes(frame(32, 24)))
        .await
        .unwrap();
    assert_eq!(status, StatusCode::ACCEPTED, "{job}");
    let id = job["id"].as_str().unwrap().to_string();
    wait_succeeded(&http, &id, Duration::from_secs(60)).await;
    let exit = p.terminate();
    assert!(exit.success(), "{exit}: {}", p.logs.lock().unwrap().join("\n"));

    let spans = collector.0.lock().unwrap().clone();
    let hex = |b: &[u8]| b.iter().map(|x| format!("{x:02x}")).collect::<String>();
    let attr = |s: &opentelemetry_proto::tonic::trace::v1::Span, key: &str| {
        s.attributes.iter().find(|a| a.key == key).and_then(|a| a.value.clone()?.value).map(|v| match v {
            Any::StringValue(s) => s,
            Any::IntValue(i) => i.to_string(),
            other => format!("{other:?}"),
        })
    };
    let names: Vec<&str> = spans.iter().map(|s| s.name.as_str()).collect();
    let find =
        |name: &str| spans.iter().find(|s| s.name == name).unwrap_or_else(|| panic!("no `{name}` span in {names:?}"));
    let submit = find("POST /v1/jobs");
    assert_eq!((hex(&submit.trace_id), hex(&submit.parent_span_id)), (trace_id.to_string(), client_span.to_string()));
    assert_eq!(attr(submit, "job_id").as_deref(), Some(id.as_str()));
    assert_eq!(attr(submit, "http.response.status_code").as_deref(), Some("202"));
    let run = find("job");
    assert_eq!(attr(run, "job_id").as_deref(), Some(id.as_str()));
    assert_eq!(attr(run, "outcome").as_deref(), Some("succeeded"));
    assert_eq!((hex(&run.trace_id), hex(&run.parent_span_id)), (trace_id.to_string(), hex(&submit.span_id)));
    for stage in ["decode", "denoise", "encode"] {
        let s = find(stage);
        assert_eq!((hex(&s.trace_id), hex(&s.parent_span_id)), (trace_id.to_string(), hex(&run.span_id)), "{stage}");
    }
    // A job's routes carry its id too.
    assert!(spans.iter().any(|s| s.name == "GET /v1/jobs/{id}" && attr(s, "job_id").as_deref() == Some(id.as_str())));
}

#[test]
fn a_sigterm_as_soon_as_the_daemon_listens_is_a_graceful_exit() {
    // The signal listeners exist before the "listening" line (server::shutdown_signal):
    // a SIGTERM at once drains and exits with status 0 instead of ending the process.
    for _ in 0..5 {
        let dir = tempfile::tempdir().unwrap();
        let mut p = spawn_daemon(dir.path(), &[]);
        let status = p.terminate();
        assert!(status.success(), "{status:?}");
        assert!(p.logs.lock().unwrap().iter().any(|l| l.contains("SIGTERM received")));
    }
}

/// `GLIBC_TUNABLES` of a daemon started with `adjust`, read from /proc once it listens
/// (after it has started itself again, if it does: src/memory.rs).
#[cfg(all(target_os = "linux", target_env = "gnu"))]
fn daemon_tunables(adjust: impl FnOnce(&mut Command)) -> Option<String> {
    let dir = tempfile::tempdir().unwrap();
    let mut p = spawn_daemon_with(dir.path(), &[], adjust);
    let environ = std::fs::read(format!("/proc/{}/environ", p.child.id())).unwrap();
    let status = p.terminate();
    assert!(status.success(), "{status:?}: {:?}", p.logs.lock().unwrap());
    // glibc parses the variable in place, each `:` becoming a NUL in the process's original
    // environment, which /proc shows: the tunables are the segments after the name.
    let mut parts = environ.split(|b| *b == 0).skip_while(|v| !v.starts_with(b"GLIBC_TUNABLES="));
    let first = parts.next()?.strip_prefix(b"GLIBC_TUNABLES=").unwrap();
    let rest = parts.take_while(|v| v.starts_with(b"glibc."));
    Some(std::iter::once(first).chain(rest).map(String::from_utf8_lossy).collect::<Vec<_>>().join(":"))
}

#[test]
#[cfg(all(target_os = "linux", target_env = "gnu"))]
fn the_daemon_asks_for_huge_pages_when_told_to_where_the_kernel_gives_them_on_request() {
    let mode = std::fs::read_to_string("/sys/kernel/mm/transparent_hugepage/enabled").unwrap_or_default();
    let on_request = mode.contains("[madvise]");
    // By default the process starts as it is.
    let default = daemon_tunables(|c| {
        c.env_remove("GLIBC_TUNABLES").env_remove("MCDENOISE_HUGE_PAGES");
    });
    assert_eq!(default, None);
    let plain = daemon_tunables(|c| {
        c.env_remove("GLIBC_TUNABLES").env("MCDENOISE_HUGE_PAGES", "on");
    });
    let others = daemon_tunables(|c| {
        c.env("GLIBC_TUNABLES", "glibc.malloc.arena_max=4").env("MCDENOISE_HUGE_PAGES", "on");
    });
    if on_request {
        assert_eq!(plain.as_deref(), Some("glibc.malloc.hugetlb=1"));
        assert_eq!(others.as_deref(), Some("glibc.malloc.arena_max=4:glibc.malloc.hugetlb=1"));
    } else {
        eprintln!("transparent huge pages `{}`: the daemon starts as it is", mode.trim());
        assert_eq!(plain, None);
        assert_eq!(others.as_deref(), Some("glibc.malloc.arena_max=4"));
    }
    // The operator's own choice, and the switch, are left as they are.
    let chosen = daemon_tunables(|c| {
        c.env("GLIBC_TUNABLES", "glibc.malloc.hugetlb=0").env("MCDENOISE_HUGE_PAGES", "on");
    });
    assert_eq!(chosen.as_deref(), Some("glibc.malloc.hugetlb=0"));
    let off = daemon_tunables(|c| {
        c.env_remove("GLIBC_TUNABLES").env("MCDENOISE_HUGE_PAGES", "off");
    });
    assert_eq!(off, None);
}
