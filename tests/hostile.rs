//! Slow, stalled and hostile clients against the daemon binary on loopback (issue 23):
//! bodies that try to make the daemon buffer them, uploads that count against the limits
//! however they are sent.

use crate::daemon_common;

use std::time::Duration;

use hyper::{Method, StatusCode};
use serde_json::Value;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

use daemon_common::*;
use mcdenoise::client::{body_bytes, HttpClient};

const BOUNDARY: &str = "hostile-boundary-1234";

/// `VmHWM` (peak resident memory) of a process, in bytes.
fn peak_rss(pid: u32) -> u64 {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap();
    let line = status.lines().find(|l| l.starts_with("VmHWM:")).expect("VmHWM in /proc/<pid>/status");
    let kib: u64 = line.split_whitespace().nth(1).unwrap().parse().unwrap();
    kib * 1024
}

/// The `host:port` of a `http://host:port` base.
fn authority(base: &str) -> &str {
    base.trim_start_matches("http://")
}

/// Reads an HTTP/1.1 answer (status and JSON body, sized by Content-Length).
async fn read_answer(stream: &mut (impl AsyncReadExt + Unpin)) -> (u16, Value) {
    let mut buf = Vec::new();
    let mut chunk = [0u8; 4096];
    let head_end = loop {
        let n = stream.read(&mut chunk).await.expect("the answer");
        assert!(n > 0, "the connection closed without an answer: {}", String::from_utf8_lossy(&buf));
        buf.extend_from_slice(&chunk[..n]);
        if let Some(at) = buf.windows(4).position(|w| w == b"\r\n\r\n") {
            break at + 4;
        }
    };
    let head = String::from_utf8_lossy(&buf[..head_end]).to_string();
    let status: u16 = head.split_whitespace().nth(1).unwrap().parse().unwrap();
    let length: usize = head
        .lines()
        .find_map(|l| l.to_ascii_lowercase().strip_prefix("content-length:").map(|v| v.trim().parse().unwrap()))
        .unwrap_or(0);
    while buf.len() < head_end + length {
        let n = stream.read(&mut chunk).await.unwrap();
        assert!(n > 0, "the answer was cut short");
        buf.extend_from_slice(&chunk[..n]);
    }
    (status, serde_json::from_slice(&buf[head_end..head_end + length]).unwrap_or(Value::Null))
}

/// Sends `prefix`, then `filler` bytes (in 1 MiB writes) as fast as the daemon takes them,
/// as one multipart `POST /v1/jobs` declaring `total` bytes; returns the answer, read
/// while the body is still being sent.
async fn flood(authority: &str, prefix: &[u8], filler: u8, total: u64) -> (u16, Value) {
    let stream = TcpStream::connect(authority).await.unwrap();
    let (mut rd, mut wr) = stream.into_split();
    let head = format!(
        "POST /v1/jobs HTTP/1.1\r\nhost: x\r\ncontent-type: multipart/form-data; boundary={BOUNDARY}\r\n\
         content-length: {total}\r\n\r\n"
    );
    let prefix = prefix.to_vec();
    let writer = tokio::spawn(async move {
        wr.write_all(head.as_bytes()).await?;
        wr.write_all(&prefix).await?;
        let block = vec![filler; 1 << 20];
        let mut sent = prefix.len() as u64;
        while sent < total {
            let n = block.len().min((total - sent) as usize);
            wr.write_all(&block[..n]).await?;
            sent += n as u64;
        }
        Ok::<u64, std::io::Error>(sent)
    });
    let answer = tokio::time::timeout(Duration::from_secs(60), read_answer(&mut rd)).await.expect("an answer");
    let sent = writer.is_finished();
    writer.abort();
    assert!(!sent, "the whole body was sent before the answer: it was read, not refused early");
    answer
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn huge_multipart_preambles_headers_and_options_are_refused_without_buffering_them() {
    let dir = tempfile::tempdir().unwrap();
    let p = spawn_daemon(dir.path(), &[]);
    let http = HttpClient::new(&p.http, None);
    wait_ready(&http).await;
    let before = peak_rss(p.child.id());
    const HUGE: u64 = 300 << 20;

    // An `options` part of 300 MiB: refused once past 64 KiB.
    let options = format!(
        "--{BOUNDARY}\r\nContent-Disposition: form-data; name=\"options\"\r\nContent-Type: application/json\r\n\r\n"
    );
    let (status, err) = flood(authority(&p.http), options.as_bytes(), b' ', HUGE).await;
    assert_eq!(status, 413, "{err}");
    assert_eq!(err["error"]["code"], "too_large", "{err}");
    assert_eq!(err["error"]["message"], "the `options` part is over its limit of 65536 bytes", "{err}");

    // A preamble of 300 MiB (no delimiter ever comes).
    let (status, err) = flood(authority(&p.http), b"", b'p', HUGE).await;
    assert_eq!(status, 413, "{err}");
    assert!(err["error"]["message"].as_str().unwrap().contains("preamble"), "{err}");

    // Part headers of 300 MiB.
    let headers = format!("--{BOUNDARY}\r\nContent-Disposition: form-data; name=\"frame\"\r\nX-Pad: ");
    let (status, err) = flood(authority(&p.http), headers.as_bytes(), b'h', HUGE).await;
    assert_eq!(status, 413, "{err}");
    assert!(err["error"]["message"].as_str().unwrap().contains("headers of multipart part 1"), "{err}");

    let after = peak_rss(p.child.id());
    let growth = after.saturating_sub(before);
    eprintln!("peak resident memory: {} MiB before, {} MiB after (+{} MiB)", before >> 20, after >> 20, growth >> 20);
    assert!(growth < 128 << 20, "resident memory grew by {} MiB", growth >> 20);

    // The daemon still serves a job.
    let (status, job) = http
        .json(Method::POST, "/v1/jobs", &[("content-type", "image/x-exr")], body_bytes(frame(16, 16)))
        .await
        .unwrap();
    assert_eq!(status, StatusCode::ACCEPTED, "{job}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_multipart_upload_holds_its_client_slot_from_its_first_byte() {
    let dir = tempfile::tempdir().unwrap();
    let p = spawn_daemon(dir.path(), &["--max-uploads-per-client", "1"]);
    let http = HttpClient::new(&p.http, None);
    wait_ready(&http).await;

    // A multipart upload that stops inside its `options` part: it is in flight.
    let mut stalled = TcpStream::connect(authority(&p.http)).await.unwrap();
    let body = format!("--{BOUNDARY}\r\nContent-Disposition: form-data; name=\"options\"\r\n\r\n{{\"prior");
    let head = format!(
        "POST /v1/jobs HTTP/1.1\r\nhost: x\r\ncontent-type: multipart/form-data; boundary={BOUNDARY}\r\n\
         content-length: 100000\r\n\r\n{body}"
    );
    stalled.write_all(head.as_bytes()).await.unwrap();
    wait_metric(&http, "mcdenoise_uploads_in_progress", 1.0).await;

    // The same client (authentication is off: its address) gets 429 for a second upload.
    let (content_type, form) = multipart("{}", &[("frame", &frame(16, 16))]);
    let submit = || async {
        http.json(Method::POST, "/v1/jobs", &[("content-type", content_type.as_str())], body_bytes(form.clone()))
            .await
            .unwrap()
    };
    let (status, err) = poll("the stalled upload holding the slot", Duration::from_secs(10), || async {
        match submit().await {
            (StatusCode::TOO_MANY_REQUESTS, err) => Ok((StatusCode::TOO_MANY_REQUESTS, err)),
            other => Err(other),
        }
    })
    .await;
    assert_eq!(status, StatusCode::TOO_MANY_REQUESTS);
    assert_eq!(err["error"]["code"], "client_limit", "{err}");

    // Gone, it gives the slot back.
    drop(stalled);
    let job = poll("the slot coming back", Duration::from_secs(10), || async {
        match submit().await {
            (StatusCode::ACCEPTED, job) => Ok(job),
            other => Err(other),
        }
    })
    .await;
    assert_eq!(job["state"], "queued", "{job}");
}

/// Reads until the other end closes the connection (data is ignored); how long that took.
async fn wait_closed(stream: &mut TcpStream, limit: Duration) -> Duration {
    let t = std::time::Instant::now();
    let mut buf = [0u8; 4096];
    loop {
        match tokio::time::timeout(limit.saturating_sub(t.elapsed()), stream.read(&mut buf)).await {
            Err(_) => panic!("the connection is still open after {limit:?}"),
            Ok(Ok(0)) | Ok(Err(_)) => return t.elapsed(),
            Ok(Ok(_)) => {}
        }
    }
}

/// Polls `/metrics` (through `http`) until `sample` reads `want`.
async fn wait_metric(http: &HttpClient, sample: &str, want: f64) {
    poll(&format!("{sample} at {want}"), Duration::from_secs(10), || async {
        let (_, metrics) = get_json(http, "/metrics").await.unwrap();
        match metric(metrics.as_str().unwrap(), sample) {
            v if v == want => Ok(()),
            v => Err(v),
        }
    })
    .await
}

/// The value of a sample in the Prometheus text.
fn metric(text: &str, sample: &str) -> f64 {
    text.lines()
        .find_map(|l| l.strip_prefix(sample).and_then(|v| v.trim().parse().ok()))
        .unwrap_or_else(|| panic!("no {sample} in the metrics"))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn half_headers_idle_connections_and_stalled_uploads_are_closed_within_their_timeouts() {
    let dir = tempfile::tempdir().unwrap();
    let timeouts = [
        "--header-timeout",
        "2s",
        "--upload-timeout",
        "2s",
        "--idle-timeout",
        "3s",
        "--keepalive-interval",
        "1s",
        "--keepalive-timeout",
        "1s",
        "--max-uploads-per-client",
        "1",
    ];
    let p = spawn_daemon(dir.path(), &timeouts);
    let http = HttpClient::new(&p.http, None);
    wait_ready(&http).await;
    // Generous: what matters is that they close at all, near their configured time.
    let limit = Duration::from_secs(15);

    // Half a request head.
    let mut half = TcpStream::connect(authority(&p.http)).await.unwrap();
    half.write_all(b"GET /readyz HTTP/1.1\r\nhost: x\r\n").await.unwrap();
    // A connection that sends nothing at all.
    let mut idle = TcpStream::connect(authority(&p.http)).await.unwrap();
    // A gRPC connection that sends only the HTTP/2 preface and an empty SETTINGS frame.
    let mut preface = TcpStream::connect(&p.grpc).await.unwrap();
    preface.write_all(b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n\x00\x00\x00\x04\x00\x00\x00\x00\x00").await.unwrap();
    // An upload with an idempotency key that stops after 1 KiB.
    let mut stalled = TcpStream::connect(authority(&p.http)).await.unwrap();
    stalled
        .write_all(
            b"POST /v1/jobs HTTP/1.1\r\nhost: x\r\ncontent-type: image/x-exr\r\nidempotency-key: shot-7\r\n\
              content-length: 100000\r\n\r\n",
        )
        .await
        .unwrap();
    stalled.write_all(&frame(16, 16)[..1024]).await.unwrap();

    let t = std::time::Instant::now();
    let (status, err) = tokio::time::timeout(limit, read_answer(&mut stalled)).await.expect("an answer");
    let answered = t.elapsed();
    assert_eq!(status, 408, "{err}");
    assert_eq!(err["error"]["code"], "timeout", "{err}");
    assert!(err["error"]["message"].as_str().unwrap().contains("--upload-timeout"), "{err}");
    for (what, conn) in
        [("half a header", &mut half), ("an idle connection", &mut idle), ("a gRPC preface", &mut preface)]
    {
        wait_closed(conn, limit).await;
        eprintln!("{what}: closed after {:?}", t.elapsed());
    }
    eprintln!("stalled upload: 408 after {answered:?}");

    // Its slot and its key are free again: the same client, the same key, accepted.
    let (status, job) = http
        .json(
            Method::POST,
            "/v1/jobs",
            &[("content-type", "image/x-exr"), ("idempotency-key", "shot-7")],
            body_bytes(frame(16, 16)),
        )
        .await
        .unwrap();
    assert_eq!(status, StatusCode::ACCEPTED, "{job}");
    let (status, metrics) = get_json(&http, "/metrics").await.unwrap();
    assert_eq!(status, StatusCode::OK);
    let metrics = metrics.as_str().unwrap();
    assert_eq!(metric(metrics, "mcdenoise_jobs_rejected_total{reason=\"timeout\"}"), 1.0);
    let logs = p.logs.lock().unwrap().join("\n");
    assert!(logs.contains("upload timed out"), "the timeout is logged");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_stalled_grpc_upload_gets_deadline_exceeded_and_frees_its_slot() {
    use mcdenoise::grpc::pb;
    let dir = tempfile::tempdir().unwrap();
    let d = start(dir.path(), &["--upload-timeout", "1s", "--max-uploads-per-client", "1"]).await;
    d.ready().await;
    let mut api = mcdenoise::client::grpc_connect(&d.grpc, None).await.unwrap();
    let exr = frame(16, 16);
    let header = pb::SubmitJobRequest {
        message: Some(pb::submit_job_request::Message::Header(pb::SubmitHeader {
            frame_size: exr.len() as u64,
            ..Default::default()
        })),
    };
    let (tx, rx) = tokio::sync::mpsc::channel(4);
    tx.send(header).await.unwrap();
    let status =
        tokio::time::timeout(Duration::from_secs(15), api.submit_job(tokio_stream::wrappers::ReceiverStream::new(rx)))
            .await
            .expect("an answer")
            .unwrap_err();
    assert_eq!(status.code(), tonic::Code::DeadlineExceeded, "{status:?}");
    drop(tx);
    d.submit_ok(&exr, "").await;
    d.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn stalled_tls_handshakes_leave_https_readyz_answering() {
    let dir = tempfile::tempdir().unwrap();
    let (ca, mut flags) = tls_flags(dir.path());
    // One peer (loopback) makes all 300: its per-address cap is raised above that here;
    // `connection_caps_close_floods_and_the_probe_port_keeps_answering` tests the cap.
    flags.extend(["--tls-handshake-timeout", "3s", "--max-connections-per-peer", "400"].map(String::from));
    let flags: Vec<&str> = flags.iter().map(String::as_str).collect();
    let p = spawn_daemon(&dir.path().join("data"), &flags);
    let addr: std::net::SocketAddr = authority(&p.http).parse().unwrap();
    poll("HTTPS /readyz answering 200", Duration::from_secs(60), || async {
        match https_get(addr, &ca, "/readyz").await {
            Ok(line) if line == "HTTP/1.1 200 OK" => Ok(()),
            other => Err(format!("{other:?}")),
        }
    })
    .await;

    // 300 connections that never send a ClientHello (no token needed), and one to gRPC.
    let mut stalled = Vec::new();
    for _ in 0..300 {
        stalled.push(TcpStream::connect(addr).await.unwrap());
    }
    let mut grpc = TcpStream::connect(&p.grpc).await.unwrap();
    let mut slowest = Duration::ZERO;
    for _ in 0..5 {
        let t = std::time::Instant::now();
        assert_eq!(https_get(addr, &ca, "/readyz").await.unwrap(), "HTTP/1.1 200 OK");
        slowest = slowest.max(t.elapsed());
    }
    eprintln!("HTTPS /readyz behind 300 stalled handshakes: slowest of 5 in {slowest:?}");
    assert!(slowest < Duration::from_secs(1), "{slowest:?}");
    // The stalled handshakes are dropped at their timeout, on both listeners.
    let took = wait_closed(&mut grpc, Duration::from_secs(15)).await;
    eprintln!("stalled gRPC handshake closed after {took:?}");
    let took = wait_closed(&mut stalled[0], Duration::from_secs(15)).await;
    eprintln!("stalled HTTPS handshake closed after {took:?}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_http_error_has_the_json_shape() {
    let dir = tempfile::tempdir().unwrap();
    let d = start(dir.path(), &[]).await;
    d.ready().await;
    let long_id = "x".repeat(60_000);
    let cases: Vec<(Method, String, u16, &str)> = vec![
        // The router's own answers: no route, wrong method, a path that is not UTF-8.
        (Method::GET, "/no/such/route".into(), 404, "not_found"),
        (Method::PUT, "/v1/jobs".into(), 405, "method_not_allowed"),
        (Method::POST, "/livez".into(), 405, "method_not_allowed"),
        (Method::GET, "/v1/jobs/%FF%FE".into(), 400, "bad_request"),
        // Query strings: not a number, over the documented maximum, an unknown key.
        (Method::GET, "/v1/jobs?limit=abc".into(), 400, "bad_request"),
        (Method::GET, "/v1/jobs?limit=1001".into(), 400, "bad_request"),
        (Method::GET, "/v1/jobs?limit=0".into(), 400, "bad_request"),
        (Method::GET, "/v1/jobs?colour=red".into(), 400, "bad_request"),
        // A very long id is not echoed whole.
        (Method::GET, format!("/v1/jobs/{long_id}"), 404, "not_found"),
    ];
    for (method, path, status, code) in cases {
        let resp = d.http.send(method.clone(), &path, &[], body_bytes(bytes::Bytes::new())).await.unwrap();
        let short = &path[..path.len().min(40)];
        assert_eq!(resp.status().as_u16(), status, "{method} {short}");
        let content_type = resp.headers().get("content-type").map(|v| v.to_str().unwrap().to_string());
        assert_eq!(content_type.as_deref(), Some("application/json"), "{method} {short}");
        if status == 405 {
            assert!(resp.headers().contains_key("allow"), "{method} {short}: 405 keeps its Allow header");
        }
        let (_, body) = mcdenoise::client::read_json(resp).await.unwrap();
        assert_eq!(body["error"]["code"], code, "{method} {short}: {body}");
        let message = body["error"]["message"].as_str().unwrap();
        assert!(!message.is_empty() && message.len() < 300, "{method} {short}: {message}");
    }
    // In range, `limit` is accepted.
    let (status, _) = d.get_json("/v1/jobs?limit=1000").await;
    assert_eq!(status, StatusCode::OK);
    d.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn grpc_refuses_malformed_messages_as_invalid_argument_and_truncates_long_ids() {
    use mcdenoise::grpc::pb;
    let dir = tempfile::tempdir().unwrap();
    let d = start(dir.path(), &[]).await;
    d.ready().await;
    // A GetJob whose body is not a protobuf message (field 1 declared 100 bytes long, 1 sent).
    let channel =
        tonic::transport::Endpoint::from_shared(format!("http://{}", d.grpc)).unwrap().connect().await.unwrap();
    let status = raw_grpc_call(&channel, &d.grpc, "/mcdenoise.v1.Denoiser/GetJob", &[0x0a, 100, b'x']).await;
    assert_eq!(status.code(), tonic::Code::InvalidArgument, "{status:?}");
    // A 100 kB id: NOT_FOUND, with the id cut in the message.
    let mut api = mcdenoise::client::grpc_connect(&d.grpc, None).await.unwrap();
    let status = api.get_job(pb::GetJobRequest { id: "y".repeat(100_000) }).await.unwrap_err();
    assert_eq!(status.code(), tonic::Code::NotFound, "{status:?}");
    assert!(status.message().len() < 300, "{} bytes", status.message().len());
    assert!(status.message().contains('…'), "{}", status.message());
    // page_size above the documented 1000.
    let status = api.list_jobs(pb::ListJobsRequest { page_size: 1001, ..Default::default() }).await.unwrap_err();
    assert_eq!(status.code(), tonic::Code::InvalidArgument, "{status:?}");
    d.stop().await;
}

/// Calls `path` with `message` as the (framed) request body; the status of the answer.
async fn raw_grpc_call(
    channel: &tonic::transport::Channel,
    authority: &str,
    path: &str,
    message: &[u8],
) -> tonic::Status {
    use http_body_util::BodyExt;
    use tower::{Service, ServiceExt};
    let mut framed = vec![0u8];
    framed.extend_from_slice(&(message.len() as u32).to_be_bytes());
    framed.extend_from_slice(message);
    let request = hyper::Request::post(format!("http://{authority}{path}"))
        .header("content-type", "application/grpc")
        .header("te", "trailers")
        .body(tonic::body::Body::new(http_body_util::Full::new(bytes::Bytes::from(framed))))
        .unwrap();
    let mut channel = channel.clone();
    let response = channel.ready().await.unwrap().call(request).await.unwrap();
    if let Some(status) = tonic::Status::from_header_map(response.headers()) {
        return status;
    }
    let collected = response.into_body().collect().await.unwrap();
    let trailers = collected.trailers().cloned().unwrap_or_default();
    tonic::Status::from_header_map(&trailers).expect("a grpc-status")
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_second_client_reusing_a_key_gets_its_own_job() {
    let dir = tempfile::tempdir().unwrap();
    let d = start_with_token(dir.path(), &["--auth-token", "farm-a,farm-b"], Some("farm-a")).await;
    d.ready().await;
    let b = HttpClient::new(&d.base, Some("farm-b"));
    let submit = |client: &HttpClient, exr: Vec<u8>| {
        let client = client.clone();
        async move {
            let headers = [("content-type", "image/x-exr"), ("idempotency-key", "f0001")];
            let resp = client.send(Method::POST, "/v1/jobs", &headers, body_bytes(exr)).await.unwrap();
            let replayed = resp.headers().contains_key("idempotent-replayed");
            let (status, job) = mcdenoise::client::read_json(resp).await.unwrap();
            assert_eq!(status, StatusCode::ACCEPTED, "{job}");
            (job["id"].as_str().unwrap().to_string(), job["width"].as_u64().unwrap(), replayed)
        }
    };
    // Two shots both name their frame f0001.
    let (a_id, a_width, replayed) = submit(&d.http, frame(16, 16)).await;
    assert!(!replayed);
    let (b_id, b_width, replayed) = submit(&b, frame(32, 16)).await;
    assert!(!replayed, "the second client's frame was answered with the first client's job");
    assert_ne!(a_id, b_id);
    assert_eq!((a_width, b_width), (16, 32), "each job holds its own client's frame");
    // Within one client, the key still replays.
    let (again, _, replayed) = submit(&d.http, frame(16, 16)).await;
    assert_eq!(again, a_id);
    assert!(replayed);
    // And after a restart.
    d.stop().await;
    let d = start_with_token(dir.path(), &["--auth-token", "farm-a,farm-b"], Some("farm-a")).await;
    d.ready().await;
    let b = HttpClient::new(&d.base, Some("farm-b"));
    let (again, _, replayed) = submit(&b, frame(32, 16)).await;
    assert_eq!((again.as_str(), replayed), (b_id.as_str(), true));
    d.stop().await;
}

/// The `listening` log line of a spawned daemon.
fn listening(p: &Process) -> Value {
    let logs = p.logs.lock().unwrap();
    logs.iter()
        .filter_map(|l| serde_json::from_str::<Value>(l).ok())
        .find(|v| v["message"] == "listening")
        .expect("a listening line")
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn connection_caps_close_floods_and_the_probe_port_keeps_answering() {
    let dir = tempfile::tempdir().unwrap();
    let p = spawn_daemon(
        dir.path(),
        &["--max-connections", "6", "--max-connections-per-peer", "4", "--probe-http", "127.0.0.1:0"],
    );
    let probe = HttpClient::new(&format!("http://{}", listening(&p)["probe"].as_str().unwrap()), None);
    // Ready through the probe port: a pooled client connection to the API would take a
    // place of its own.
    wait_ready(&probe).await;
    let api: std::net::SocketAddr = authority(&p.http).parse().unwrap();
    let from = |ip: &str| {
        let ip: std::net::IpAddr = ip.parse().unwrap();
        async move {
            let socket = tokio::net::TcpSocket::new_v4().unwrap();
            socket.bind((ip, 0).into()).unwrap();
            socket.connect(api).await.unwrap()
        }
    };
    let open_api = "mcdenoise_connections{listener=\"api\"}";

    // Four idle connections from 127.0.0.1 fill its share: a fifth is closed at once.
    let mut held = Vec::new();
    for _ in 0..4 {
        held.push(from("127.0.0.1").await);
    }
    wait_metric(&probe, open_api, 4.0).await;
    let mut fifth = from("127.0.0.1").await;
    wait_closed(&mut fifth, Duration::from_secs(5)).await;
    // Another address still gets in, up to the total of 6; the seventh is closed.
    held.push(from("127.0.0.2").await);
    held.push(from("127.0.0.2").await);
    wait_metric(&probe, open_api, 6.0).await;
    let mut seventh = from("127.0.0.2").await;
    wait_closed(&mut seventh, Duration::from_secs(5)).await;

    // The probe port answers throughout, and counts the refusals.
    let (status, ready) = get_json(&probe, "/readyz").await.unwrap();
    assert_eq!(status, StatusCode::OK, "{ready}");
    let (_, m) = get_json(&probe, "/metrics").await.unwrap();
    let m = m.as_str().unwrap();
    assert_eq!(metric(m, "mcdenoise_connections_refused_total{listener=\"api\",reason=\"per_peer\"}"), 1.0);
    assert_eq!(metric(m, "mcdenoise_connections_refused_total{listener=\"api\",reason=\"total\"}"), 1.0);
    let (status, _) = get_json(&probe, "/v1/jobs").await.unwrap();
    assert_eq!(status, StatusCode::NOT_FOUND, "the probe port serves probes only");

    // Closed, they give their places back.
    drop(held);
    let http = HttpClient::new(&p.http, None);
    poll("the API answering again", Duration::from_secs(10), || async {
        match get_json(&http, "/readyz").await {
            Some((StatusCode::OK, _)) => Ok(()),
            other => Err(format!("{other:?}")),
        }
    })
    .await;
}

#[test]
fn the_file_limit_is_raised_and_the_connection_cap_kept_below_it() {
    use std::os::unix::process::CommandExt;
    let dir = tempfile::tempdir().unwrap();
    // Soft limit 300 under a hard limit of 1024: raised to 1024 at start, and the cap of
    // 100000 connections lowered to 1024 - 256.
    let p = spawn_daemon_with(dir.path(), &["--max-connections", "100000"], |c| unsafe {
        c.pre_exec(|| {
            let limit = rustix::process::Rlimit { current: Some(300), maximum: Some(1024) };
            rustix::process::setrlimit(rustix::process::Resource::Nofile, limit).map_err(std::io::Error::from)
        });
    });
    let line = listening(&p);
    assert_eq!(line["file_limit"], 1024, "{line}");
    assert_eq!(line["max_connections"], 1024 - 256, "{line}");
}
