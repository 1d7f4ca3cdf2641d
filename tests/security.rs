//! Security of both transports: every route but the probes needs the token (enumerated
//! from the router's table, the OpenAPI document and the gRPC descriptors), tokens never
//! reach the logs or the job store, jobs belong to the client that submitted them,
//! per-client limits, and TLS on both listeners.

use crate::daemon_common;

use std::collections::BTreeSet;
use std::time::Duration;

use bytes::Bytes;
use futures_util::StreamExt;
use http_body_util::BodyExt;
use hyper::{Method, StatusCode};
use prost::Message;
use serde_json::Value;

use daemon_common::*;
use mcdenoise::client::{body_bytes, HttpClient};
use mcdenoise::http::dashboard::{asset, asset_names, CONTENT_SECURITY_POLICY, DASHBOARD_ROUTES};
use mcdenoise::http::{OPEN_ROUTES, PROTECTED_ROUTES};

/// `(method, path)` pairs of the OpenAPI document.
fn openapi_routes() -> BTreeSet<(String, String)> {
    let doc: Value = serde_json::from_str(mcdenoise::http::OPENAPI).unwrap();
    let mut out = BTreeSet::new();
    for (path, item) in doc["paths"].as_object().unwrap() {
        for method in item.as_object().unwrap().keys() {
            if ["get", "post", "put", "delete", "patch"].contains(&method.as_str()) {
                out.insert((method.to_uppercase(), path.clone()));
            }
        }
    }
    out
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_http_route_but_the_probes_needs_the_token() {
    let table: BTreeSet<(String, String)> =
        PROTECTED_ROUTES.iter().chain(OPEN_ROUTES).map(|(m, p)| (m.to_string(), p.to_string())).collect();
    assert_eq!(table, openapi_routes(), "the router's table and the OpenAPI document list the same routes");

    let dir = tempfile::tempdir().unwrap();
    let d = start_with_token(dir.path(), &["--auth-token", "s3cret"], None).await;
    d.ready().await;
    let wrong = HttpClient::new(&d.base, Some("s3cret-not"));
    for (method, path) in PROTECTED_ROUTES {
        let path = path.replace("{id}", "0190a0b0-0000-7000-8000-000000000000");
        let method: Method = method.parse().unwrap();
        for (who, client) in [("no token", &d.http), ("a wrong token", &wrong)] {
            let resp = client.send(method.clone(), &path, &[], body_bytes(Bytes::new())).await.unwrap();
            assert_eq!(resp.status(), StatusCode::UNAUTHORIZED, "{method} {path} with {who}");
            assert!(resp.headers().contains_key("www-authenticate"), "{method} {path}");
        }
    }
    for (method, path) in OPEN_ROUTES {
        let resp = d.http.send(method.parse().unwrap(), path, &[], body_bytes(Bytes::new())).await.unwrap();
        assert_eq!(resp.status(), StatusCode::OK, "{method} {path} is open");
    }
    d.stop().await;
}

/// The dashboard's shell is open, holds no data and loads nothing from elsewhere: every
/// file is served without a token under the strict policy, names no other origin, has no
/// inline script or style; the API calls it makes still need the token.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_dashboard_shell_is_open_and_loads_nothing_from_outside() {
    assert_eq!(DASHBOARD_ROUTES, &[("GET", "/"), ("GET", "/ui/{file}")]);
    for (method, path) in DASHBOARD_ROUTES {
        assert!(!openapi_routes().contains(&(method.to_string(), path.to_string())), "{path} is not an API operation");
    }
    assert!(CONTENT_SECURITY_POLICY.contains("default-src 'none'"));
    for directive in ["script-src 'self'", "style-src 'self'", "connect-src 'self'", "img-src 'self' blob:"] {
        assert!(CONTENT_SECURITY_POLICY.contains(directive), "{directive}");
    }
    assert!(!CONTENT_SECURITY_POLICY.contains("unsafe-"), "no inline script or style is allowed");

    let dir = tempfile::tempdir().unwrap();
    let d = start_with_token(dir.path(), &["--auth-token", "s3cret"], None).await;
    d.ready().await;
    for name in asset_names() {
        let path = if name == "index.html" { "/".to_string() } else { format!("/ui/{name}") };
        let resp = d.http.send(Method::GET, &path, &[], body_bytes(Bytes::new())).await.unwrap();
        assert_eq!(resp.status(), StatusCode::OK, "{path} needs no token");
        let h = resp.headers().clone();
        assert_eq!(h["content-security-policy"], CONTENT_SECURITY_POLICY, "{path}");
        assert_eq!(h["x-content-type-options"], "nosniff", "{path}");
        let etag = h["etag"].to_str().unwrap().to_string();
        let body = resp.into_body().collect().await.unwrap().to_bytes();
        assert_eq!(&body[..], asset(name).unwrap(), "{path} serves the embedded file");
        let text = std::str::from_utf8(&body).unwrap().replace("http://www.w3.org/2000/svg", "");
        for outside in ["http://", "https://", "//cdn", "@import", "url("] {
            assert!(!text.contains(outside), "{name} names `{outside}`");
        }
        if name == "index.html" {
            assert_eq!(text.matches("<script").count(), text.matches("<script src=\"/ui/").count(), "no inline script");
            assert!(!text.contains(" style=") && !text.contains("<style"), "no inline style");
            let handler = text.split(" on").skip(1).any(|rest| {
                rest.split_once('=')
                    .is_some_and(|(name, _)| !name.is_empty() && name.bytes().all(|b| b.is_ascii_lowercase()))
            });
            assert!(!handler, "no inline event handler");
        }
        // Unchanged: 304.
        let again =
            d.http.send(Method::GET, &path, &[("if-none-match", &etag)], body_bytes(Bytes::new())).await.unwrap();
        assert_eq!(again.status(), StatusCode::NOT_MODIFIED, "{path}");
    }
    let (status, body) = d.get_json("/ui/secrets.json").await;
    assert_eq!((status, body["error"]["code"].as_str()), (StatusCode::NOT_FOUND, Some("not_found")));
    for path in ["/v1/stats", "/v1/jobs?order=newest&limit=50", "/v1/jobs/x/preview?image=result"] {
        let resp = d.http.send(Method::GET, path, &[], body_bytes(Bytes::new())).await.unwrap();
        assert_eq!(resp.status(), StatusCode::UNAUTHORIZED, "{path}: the page's data calls need the token");
    }
    d.stop().await;
}

/// Every method of every service in `descriptor_sets`, as `/package.Service/Method`.
fn grpc_methods(descriptor_sets: &[&[u8]]) -> Vec<String> {
    let mut out = Vec::new();
    for set in descriptor_sets {
        let set = prost_types::FileDescriptorSet::decode(*set).unwrap();
        for file in set.file {
            for service in &file.service {
                for method in &service.method {
                    out.push(format!("/{}.{}/{}", file.package(), service.name(), method.name()));
                }
            }
        }
    }
    out
}

/// Calls `path` with an empty message and no credentials; the `grpc-status` of the
/// answer's headers (present when the call is refused before it runs).
async fn raw_grpc_status(channel: &tonic::transport::Channel, authority: &str, path: &str) -> Option<String> {
    use tower::{Service, ServiceExt};
    let request = hyper::Request::post(format!("http://{authority}{path}"))
        .header("content-type", "application/grpc")
        .header("te", "trailers")
        .body(tonic::body::Body::new(http_body_util::Full::new(Bytes::from_static(&[0, 0, 0, 0, 0]))))
        .unwrap();
    let mut channel = channel.clone();
    let response = channel.ready().await.unwrap().call(request).await.unwrap();
    response.headers().get("grpc-status").map(|v| v.to_str().unwrap().to_string())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_grpc_method_but_health_needs_the_token() {
    let dir = tempfile::tempdir().unwrap();
    let d = start_with_token(dir.path(), &["--auth-token", "s3cret"], None).await;
    d.ready().await;
    let channel =
        tonic::transport::Endpoint::from_shared(format!("http://{}", d.grpc)).unwrap().connect().await.unwrap();
    let methods = grpc_methods(&[
        mcdenoise::grpc::pb::FILE_DESCRIPTOR_SET,
        tonic_reflection::pb::v1::FILE_DESCRIPTOR_SET,
        tonic_reflection::pb::v1alpha::FILE_DESCRIPTOR_SET,
        tonic_health::pb::FILE_DESCRIPTOR_SET,
    ]);
    assert!(methods.len() >= 12, "{methods:?}");
    let unauthenticated = (tonic::Code::Unauthenticated as i32).to_string();
    let mut guarded = 0;
    for path in &methods {
        let status = raw_grpc_status(&channel, &d.grpc, path).await;
        if path.starts_with("/grpc.health.v1.Health/") {
            assert_ne!(status.as_deref(), Some(unauthenticated.as_str()), "{path} is open to probes");
        } else {
            assert_eq!(status.as_deref(), Some(unauthenticated.as_str()), "{path} needs the token");
            guarded += 1;
        }
    }
    assert!(guarded >= 10, "{guarded} guarded methods");
    d.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn tokens_never_reach_the_logs_or_the_job_store() {
    const GOOD: &str = "canary-good-7f3a9c";
    const BAD: &str = "canary-bad-51e0d2";
    let dir = tempfile::tempdir().unwrap();
    let mut p = spawn_daemon(dir.path(), &["--auth-token", GOOD, "--log", "trace"]);
    let authed = HttpClient::new(&p.http, Some(GOOD));
    let wrong = HttpClient::new(&p.http, Some(BAD));
    wait_ready(&authed).await;
    let (status, job) = authed
        .json(Method::POST, "/v1/jobs", &[("content-type", "image/x-exr")], body_bytes(frame(32, 16)))
        .await
        .unwrap();
    assert_eq!(status, StatusCode::ACCEPTED, "{job}");
    let (status, _) = wrong.json(Method::GET, "/v1/jobs", &[], body_bytes(Bytes::new())).await.unwrap();
    assert_eq!(status, StatusCode::UNAUTHORIZED);
    for token in [GOOD, BAD] {
        let mut client = mcdenoise::client::grpc_connect(&p.grpc, Some(token)).await.unwrap();
        let _ = client.list_jobs(mcdenoise::grpc::pb::ListJobsRequest::default()).await;
    }
    let id = job["id"].as_str().unwrap();
    wait_succeeded(&authed, id, Duration::from_secs(60)).await;
    assert!(p.terminate().success());
    let logs = p.logs.lock().unwrap().join("\n");
    assert!(logs.lines().count() > 20, "trace logging was on: {logs}");
    assert!(logs.contains("token:"), "the client is named by its token's digest");
    for token in [GOOD, BAD] {
        assert!(!logs.contains(token), "a token was logged");
        for entry in walk(dir.path()) {
            let bytes = std::fs::read(&entry).unwrap();
            assert!(!bytes.windows(token.len()).any(|w| w == token.as_bytes()), "{} holds a token", entry.display());
        }
    }
}

/// A request whose body never ends until the returned sender is dropped.
fn stalled_upload(
    client: &HttpClient,
) -> (tokio::sync::mpsc::Sender<Bytes>, tokio::task::JoinHandle<anyhow::Result<(StatusCode, Value)>>) {
    let (tx, rx) = tokio::sync::mpsc::channel::<Bytes>(4);
    let stream =
        tokio_stream::wrappers::ReceiverStream::new(rx).map(|b| Ok::<_, std::io::Error>(hyper::body::Frame::data(b)));
    let body = BodyExt::boxed(http_body_util::StreamBody::new(stream));
    let client = client.clone();
    let task =
        tokio::spawn(
            async move { client.json(Method::POST, "/v1/jobs", &[("content-type", "image/x-exr")], body).await },
        );
    (tx, task)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn each_client_has_its_own_limits_on_uploads_and_unfinished_jobs() {
    let dir = tempfile::tempdir().unwrap();
    let d = start_with_token(
        dir.path(),
        &[
            "--auth-token",
            "farm-a,farm-b",
            "--max-uploads-per-client",
            "1",
            "--max-jobs-per-client",
            "2",
            "--tile",
            "16",
            "--debug-tile-delay",
            "40ms",
        ],
        Some("farm-a"),
    )
    .await;
    d.ready().await;
    let b = HttpClient::new(&d.base, Some("farm-b"));

    // Uploads: one in flight per client. Probes with an empty body are admitted and then
    // refused (400), so they leave no jobs behind; one may take the slot just before the
    // stalled upload does, which is then refused itself and started again.
    let t = std::time::Instant::now();
    let (tx, stalled, err) = 'probe: loop {
        let (tx, stalled) = stalled_upload(&d.http);
        tx.send(Bytes::from_static(b"\x76\x2f\x31\x01")).await.unwrap();
        while !stalled.is_finished() {
            let (status, err) = d.submit(&[], "", &[]).await;
            if status == StatusCode::TOO_MANY_REQUESTS {
                break 'probe (tx, stalled, err);
            }
            assert_eq!(status, StatusCode::BAD_REQUEST, "{err}");
            assert!(t.elapsed() < Duration::from_secs(10));
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    };
    assert_eq!(err["error"]["code"], "client_limit", "{err}");
    assert!(err["error"]["message"].as_str().unwrap().contains("uploads in progress"), "{err}");
    assert!(err["error"]["message"].as_str().unwrap().starts_with("token:"), "{err}");
    // Another client is not held up by it.
    let (status, other) =
        b.json(Method::POST, "/v1/jobs", &[("content-type", "image/x-exr")], body_bytes(frame(16, 16))).await.unwrap();
    assert_eq!(status, StatusCode::ACCEPTED, "{other}");
    // The stalled upload ends (a truncated frame): its place is released.
    drop(tx);
    let (status, _) = stalled.await.unwrap().unwrap();
    assert!(status.is_client_error(), "{status}");

    // Unfinished jobs: two per client, counted across both transports.
    let (mut accepted, mut refused) = (Vec::new(), None);
    for _ in 0..4 {
        let (status, j) = d.submit(&frame(64, 64), "", &[]).await;
        match status {
            StatusCode::ACCEPTED => accepted.push(j["id"].as_str().unwrap().to_string()),
            StatusCode::TOO_MANY_REQUESTS => {
                refused = Some(j);
                break;
            }
            other => panic!("{other}: {j}"),
        }
    }
    let refused = refused.expect("the client limit was reached");
    assert!(accepted.len() <= 2, "{accepted:?}");
    assert!(refused["error"]["message"].as_str().unwrap().contains("unfinished jobs"), "{refused}");
    let mut grpc = mcdenoise::client::grpc_connect(&d.grpc, Some("farm-a")).await.unwrap();
    let path = write(dir.path(), "f.exr", &frame(16, 16));
    let upload = mcdenoise::client::upload_stream(Default::default(), &path, None, 4096).await.unwrap();
    let status = grpc.submit_job(upload).await.unwrap_err();
    assert_eq!(status.code(), tonic::Code::ResourceExhausted, "{status:?}");
    assert!(status.metadata().get("retry-after").is_some());
    // Once they finish, the client may submit again.
    for id in &accepted {
        d.wait_state(id, "succeeded").await;
    }
    d.submit_ok(&frame(16, 16), "").await;
    d.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn jobs_belong_to_their_client_and_operators_see_every_job() {
    let dir = tempfile::tempdir().unwrap();
    let d = start_with_token(dir.path(), &["--auth-token", "farm-a,farm-b", "--operator-token", "ops"], Some("farm-a"))
        .await;
    d.ready().await;
    let (b, ops) = (HttpClient::new(&d.base, Some("farm-b")), HttpClient::new(&d.base, Some("ops")));
    let call = |c: &HttpClient, method: Method, path: String| {
        let c = c.clone();
        async move { c.json(method, &path, &[], body_bytes(Bytes::new())).await.unwrap() }
    };
    let id = d.submit_ok(&frame(16, 16), "label=shot-1").await;
    d.wait_state(&id, "succeeded").await;

    // farm-b: the job does not exist for it, whatever it asks.
    for (method, path) in [
        (Method::GET, format!("/v1/jobs/{id}")),
        (Method::GET, format!("/v1/jobs/{id}/result")),
        (Method::GET, format!("/v1/jobs/{id}/events")),
        (Method::POST, format!("/v1/jobs/{id}/cancel")),
        (Method::DELETE, format!("/v1/jobs/{id}")),
    ] {
        let (status, err) = call(&b, method.clone(), path.clone()).await;
        assert_eq!(
            (status, err["error"]["code"].as_str()),
            (StatusCode::NOT_FOUND, Some("not_found")),
            "{method} {path}"
        );
    }
    let (_, list) = call(&b, Method::GET, "/v1/jobs".into()).await;
    assert_eq!(list["jobs"], serde_json::json!([]), "{list}");
    let mut grpc_b = mcdenoise::client::grpc_connect(&d.grpc, Some("farm-b")).await.unwrap();
    let status = grpc_b.get_job(mcdenoise::grpc::pb::GetJobRequest { id: id.clone() }).await.unwrap_err();
    assert_eq!(status.code(), tonic::Code::NotFound, "{status:?}");
    // A submit token does not read the metrics once operator tokens exist.
    let (status, err) = call(&b, Method::GET, "/metrics".into()).await;
    assert_eq!((status, err["error"]["code"].as_str()), (StatusCode::FORBIDDEN, Some("forbidden")), "{err}");

    // The operator sees and lists it, and reads the metrics; the owner downloads it.
    let (status, job) = call(&ops, Method::GET, format!("/v1/jobs/{id}")).await;
    assert_eq!((status, job["label"].as_str()), (StatusCode::OK, Some("shot-1")), "{job}");
    let (_, list) = call(&ops, Method::GET, "/v1/jobs".into()).await;
    assert_eq!(list["jobs"].as_array().map(Vec::len), Some(1), "{list}");
    assert_eq!(ops.get("/metrics").await.unwrap().status(), StatusCode::OK);
    assert_eq!(d.result(&id).await.0, StatusCode::OK);
    let mut grpc_ops = mcdenoise::client::grpc_connect(&d.grpc, Some("ops")).await.unwrap();
    grpc_ops.delete_job(mcdenoise::grpc::pb::DeleteJobRequest { id: id.clone() }).await.unwrap();
    assert_eq!(d.get_json(&format!("/v1/jobs/{id}")).await.0, StatusCode::NOT_FOUND);
    d.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn both_listeners_speak_tls_when_given_a_certificate() {
    let dir = tempfile::tempdir().unwrap();
    let ca = self_signed(dir.path());
    let cert = dir.path().join("cert.pem").display().to_string();
    let key = dir.path().join("key.pem").display().to_string();
    let data = dir.path().join("data");
    let d = start(&data, &["--tls-cert", &cert, "--tls-key", &key]).await;
    let http_addr = d.server.http_addr;

    // HTTPS answers; plain HTTP on the same port gets no answer.
    let t = std::time::Instant::now();
    while https_get(http_addr, &ca, "/readyz").await.unwrap() != "HTTP/1.1 200 OK" {
        assert!(t.elapsed() < Duration::from_secs(30));
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    assert!(d.http.get("/livez").await.is_err(), "plain HTTP is refused");
    // A client that opens connections and never starts its handshake holds up no other.
    let mut stalled = Vec::new();
    for _ in 0..8 {
        stalled.push(tokio::net::TcpStream::connect(http_addr).await.unwrap());
    }
    assert_eq!(https_get(http_addr, &ca, "/livez").await.unwrap(), "HTTP/1.1 200 OK");
    drop(stalled);
    let other_ca = rcgen::generate_simple_self_signed(vec!["localhost".to_string()]).unwrap().cert.pem();
    assert!(https_get(http_addr, &other_ca, "/livez").await.is_err(), "the client checks the certificate");

    // gRPC over TLS: health and a whole job.
    let tls = tonic::transport::ClientTlsConfig::new()
        .ca_certificate(tonic::transport::Certificate::from_pem(&ca))
        .domain_name("localhost");
    let channel = tonic::transport::Endpoint::from_shared(format!("https://{}", d.grpc))
        .unwrap()
        .tls_config(tls)
        .unwrap()
        .connect()
        .await
        .unwrap();
    let mut health = tonic_health::pb::health_client::HealthClient::new(channel.clone());
    let reply = health.check(tonic_health::pb::HealthCheckRequest { service: String::new() }).await.unwrap();
    assert_eq!(reply.into_inner().status, tonic_health::pb::health_check_response::ServingStatus::Serving as i32);
    let mut api = mcdenoise::grpc::pb::denoiser_client::DenoiserClient::new(channel);
    let path = write(dir.path(), "f.exr", &frame(32, 16));
    let upload = mcdenoise::client::upload_stream(Default::default(), &path, None, 4096).await.unwrap();
    let job = api.submit_job(upload).await.unwrap().into_inner();
    poll("the gRPC job succeeding", Duration::from_secs(60), || {
        let mut api = api.clone();
        let id = job.id.clone();
        async move {
            let j = api.get_job(mcdenoise::grpc::pb::GetJobRequest { id }).await.unwrap().into_inner();
            if j.state == mcdenoise::grpc::pb::JobState::Succeeded as i32 {
                Ok(())
            } else {
                Err(j)
            }
        }
    })
    .await;
    let plain = tonic::transport::Endpoint::from_shared(format!("http://{}", d.grpc)).unwrap().connect().await;
    if let Ok(channel) = plain {
        let mut health = tonic_health::pb::health_client::HealthClient::new(channel);
        assert!(health.check(tonic_health::pb::HealthCheckRequest { service: String::new() }).await.is_err());
    }
    d.stop().await;

    // A key that does not go with the certificate is refused at startup, naming the files.
    let other = rcgen::generate_simple_self_signed(vec!["localhost".to_string()]).unwrap();
    std::fs::write(dir.path().join("other-key.pem"), other.signing_key.serialize_pem()).unwrap();
    let other_key = dir.path().join("other-key.pem").display().to_string();
    let args =
        mcdenoise::config::parse_serve_args(args(&data, &["--tls-cert", &cert, "--tls-key", &other_key])).unwrap();
    let err = match mcdenoise::server::Server::start(args).await {
        Ok(_) => panic!("a mismatched key was accepted"),
        Err(e) => format!("{e:#}"),
    };
    assert!(err.contains("other-key.pem"), "{err}");
}
