//! Shared by the daemon tests: a daemon on ephemeral ports with the tiny test models (in
//! process, or the binary), waiting for readiness and for job states over HTTP, synthetic
//! frames. Every daemon test file uses these instead of its own polling loops.
#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use bytes::Bytes;
use hyper::{Method, StatusCode};
use serde_json::Value;

use mcdenoise::client::{body_bytes, read_json, read_sse, HttpClient, SseEvent};
use mcdenoise::config::parse_serve_args;
use mcdenoise::server::Server;

use crate::common::{exr_single, named_planes, tiny_models, Sample};

/// Polls `probe` every 20 ms until it gives `Some`, for at most `limit`; then fails,
/// naming `what` and the last value seen.
pub async fn poll<T, V: std::fmt::Debug, F, Fut>(what: &str, limit: Duration, mut probe: F) -> T
where
    F: FnMut() -> Fut,
    Fut: std::future::Future<Output = Result<T, V>>,
{
    let t = Instant::now();
    loop {
        match probe().await {
            Ok(v) => return v,
            Err(last) => assert!(t.elapsed() < limit, "{what}: not after {limit:?} (last: {last:?})"),
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

/// A GET with a JSON answer; `None` if the daemon cannot be reached.
pub async fn get_json(http: &HttpClient, path: &str) -> Option<(StatusCode, Value)> {
    http.json(Method::GET, path, &[], body_bytes(Bytes::new())).await.ok()
}

/// Waits until `/readyz` answers 200 (60 s at most).
pub async fn wait_ready(http: &HttpClient) {
    poll("the daemon becoming ready", Duration::from_secs(60), || async {
        match get_json(http, "/readyz").await {
            Some((StatusCode::OK, _)) => Ok(()),
            other => Err(other),
        }
    })
    .await
}

/// Polls the job until `pred` holds (60 s at most); its JSON.
pub async fn wait_job(http: &HttpClient, id: &str, what: &str, pred: impl Fn(&Value) -> bool) -> Value {
    poll(&format!("job {id} becoming {what}"), Duration::from_secs(60), || async {
        match get_json(http, &format!("/v1/jobs/{id}")).await {
            Some((StatusCode::OK, job)) if pred(&job) => Ok(job),
            other => Err(other),
        }
    })
    .await
}

pub fn is_finished(job: &Value) -> bool {
    matches!(job["state"].as_str(), Some("succeeded" | "failed" | "cancelled"))
}

/// Waits until the job has finished, whichever way.
pub async fn wait_finished(http: &HttpClient, id: &str) -> Value {
    wait_job(http, id, "finished", is_finished).await
}

/// Waits until the job has succeeded; fails at once if it ends any other way or is lost.
pub async fn wait_succeeded(http: &HttpClient, id: &str, limit: Duration) -> Value {
    poll(&format!("job {id} succeeding"), limit, || async {
        let (status, job) = get_json(http, &format!("/v1/jobs/{id}")).await.expect("the daemon answers");
        assert_eq!(status, StatusCode::OK, "the accepted job {id} was lost: {job}");
        match job["state"].as_str() {
            Some("succeeded") => Ok(job),
            Some("queued" | "running") => Err(job),
            _ => panic!("the job {id} ended other than succeeded: {job}"),
        }
    })
    .await
}

/// A daemon under test.
pub struct Daemon {
    pub server: Server,
    pub http: HttpClient,
    pub base: String,
    pub grpc: String,
}

/// The arguments of a test daemon: loopback ephemeral ports, tiny models, one worker with
/// one thread, 32-pixel tiles; `extra` overrides.
pub fn args(data_dir: &Path, extra: &[&str]) -> Vec<String> {
    let mut a: Vec<String> = [
        "serve",
        "--http",
        "127.0.0.1:0",
        "--grpc",
        "127.0.0.1:0",
        "--workers",
        "1",
        "--threads-per-worker",
        "1",
        "--tile",
        "32",
        "--log",
        "warn",
    ]
    .iter()
    .map(|s| s.to_string())
    .collect();
    a.push("--data-dir".into());
    a.push(data_dir.display().to_string());
    a.push("--models".into());
    a.push(tiny_models().display().to_string());
    // ONNX Runtime's CPU provider, whatever `auto` would choose here: these daemons run in
    // the test process, and once OpenVINO's plugin has run in a process the CPU provider's
    // results there differ (engine_v2's graph-against-engine comparisons by 5e-4); the
    // `openvino` device is tested in processes of its own (tests/cli.rs).
    if !extra.contains(&"--device") {
        a.extend(["--device".into(), "cpu".into()]);
    }
    // `scripts/test-shared`: the same tests with the daemon in shared mode, each daemon on
    // a prefix of its own so that tests do not see each other's jobs.
    if let Ok(store) = std::env::var("MCDENOISE_TEST_STORE") {
        if !extra.contains(&"--store") {
            static DAEMONS: std::sync::atomic::AtomicUsize = std::sync::atomic::AtomicUsize::new(0);
            let n = DAEMONS.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
            a.extend(["--store".into(), store, "--nats-prefix".into(), format!("t{}_{n}", std::process::id())]);
        }
    }
    a.extend(extra.iter().map(|s| s.to_string()));
    a
}

pub async fn start(data_dir: &Path, extra: &[&str]) -> Daemon {
    start_with_token(data_dir, extra, None).await
}

pub async fn start_with_token(data_dir: &Path, extra: &[&str], token: Option<&str>) -> Daemon {
    let args = parse_serve_args(args(data_dir, extra)).expect("valid test arguments");
    let server = Server::start(args).await.expect("the daemon starts");
    let base = format!("http://{}", server.http_addr);
    let grpc = server.grpc_addr.to_string();
    Daemon { http: HttpClient::new(&base, token), base, grpc, server }
}

impl Daemon {
    /// Waits until the core is ready, then until /readyz says so.
    pub async fn ready(&self) {
        self.server.service.wait_ready(Duration::from_secs(30)).await.expect("the daemon becomes ready");
        wait_ready(&self.http).await;
    }

    pub async fn stop(self) {
        self.server.shutdown();
        self.server.wait().await.expect("clean shutdown");
    }

    pub async fn get_json(&self, path: &str) -> (StatusCode, Value) {
        self.http.json(Method::GET, path, &[], body_bytes(Bytes::new())).await.expect("request")
    }

    pub async fn post_json(&self, path: &str) -> (StatusCode, Value) {
        self.http.json(Method::POST, path, &[], body_bytes(Bytes::new())).await.expect("request")
    }

    /// Submits a raw EXR body; `query` without the `?`.
    pub async fn submit(&self, exr: &[u8], query: &str, headers: &[(&str, &str)]) -> (StatusCode, Value) {
        let mut h: Vec<(&str, &str)> = headers.to_vec();
        if !headers.iter().any(|(k, _)| k.eq_ignore_ascii_case("content-type")) {
            h.push(("content-type", "image/x-exr"));
        }
        self.http.json(Method::POST, &format!("/v1/jobs?{query}"), &h, body_bytes(exr.to_vec())).await.expect("submit")
    }

    /// Submits and expects 202; returns the job id.
    pub async fn submit_ok(&self, exr: &[u8], query: &str) -> String {
        let (status, job) = self.submit(exr, query, &[]).await;
        assert_eq!(status, StatusCode::ACCEPTED, "{job}");
        job["id"].as_str().unwrap().to_string()
    }

    pub async fn job(&self, id: &str) -> Value {
        let (status, job) = self.get_json(&format!("/v1/jobs/{id}")).await;
        assert_eq!(status, StatusCode::OK, "{job}");
        job
    }

    /// Polls the job until `pred` holds.
    pub async fn wait_job(&self, id: &str, what: &str, pred: impl Fn(&Value) -> bool) -> Value {
        wait_job(&self.http, id, what, pred).await
    }

    pub async fn wait_finished(&self, id: &str) -> Value {
        wait_finished(&self.http, id).await
    }

    pub async fn wait_state(&self, id: &str, state: &str) -> Value {
        self.wait_job(id, state, |j| j["state"] == state).await
    }

    /// Waits until the job runs and has done at least one tile.
    pub async fn wait_running(&self, id: &str) -> Value {
        self.wait_job(id, "running", |j| j["state"] == "running" && j["progress"]["tiles_done"].as_u64() >= Some(1))
            .await
    }

    /// Every SSE event of a job until the stream ends.
    pub async fn events(&self, id: &str) -> Vec<SseEvent> {
        let resp = self.http.get(&format!("/v1/jobs/{id}/events")).await.expect("events");
        assert_eq!(resp.status(), StatusCode::OK);
        let mut out = Vec::new();
        read_sse(resp, |e| {
            out.push(e);
            true
        })
        .await
        .expect("event stream");
        out
    }

    pub async fn result(&self, id: &str) -> (StatusCode, Vec<u8>) {
        use http_body_util::BodyExt;
        let resp = self.http.get(&format!("/v1/jobs/{id}/result")).await.expect("result");
        let status = resp.status();
        if status != StatusCode::OK {
            let (s, v) = read_json(resp).await.unwrap();
            return (s, v.to_string().into_bytes());
        }
        (status, resp.into_body().collect().await.unwrap().to_bytes().to_vec())
    }
}

/// A complete frame (no covariance) of `w`×`h` as EXR bytes.
pub fn frame(w: usize, h: usize) -> Vec<u8> {
    exr_single(w, h, &named_planes(w, h, false), Sample::F32)
}

/// A frame with one buffer's channels left out.
pub fn frame_without(w: usize, h: usize, prefix: &str) -> Vec<u8> {
    let planes: Vec<_> = named_planes(w, h, false).into_iter().filter(|(n, _)| !n.starts_with(prefix)).collect();
    exr_single(w, h, &planes, Sample::F32)
}

/// A reference (`R,G,B`) for [`frame`]: diffuse + specular, slightly changed.
pub fn reference(w: usize, h: usize) -> Vec<u8> {
    let planes = named_planes(w, h, false);
    let get = |n: &str| planes.iter().find(|(k, _)| k == n).unwrap().1.clone();
    let rgb: Vec<(String, Vec<f32>)> = ["R", "G", "B"]
        .iter()
        .map(|c| {
            let d = get(&format!("diffuse.{c}"));
            let s = get(&format!("specular.{c}"));
            (c.to_string(), d.iter().zip(&s).map(|(a, b)| 0.95 * (a + b)).collect())
        })
        .collect();
    exr_single(w, h, &rgb, Sample::F32)
}

pub fn write(dir: &Path, name: &str, bytes: &[u8]) -> PathBuf {
    let p = dir.join(name);
    std::fs::write(&p, bytes).unwrap();
    p
}

pub fn multipart(options: &str, parts: &[(&str, &[u8])]) -> (String, Vec<u8>) {
    let boundary = "test-boundary-7MA4YWxkTrZu0gW";
    let mut body = Vec::new();
    body.extend_from_slice(
        format!("--{boundary}\r\nContent-Disposition: form-data; name=\"options\"\r\nContent-Type: application/json\r\n\r\n{options}\r\n")
            .as_bytes(),
    );
    for (name, data) in parts {
        body.extend_from_slice(
            format!("--{boundary}\r\nContent-Disposition: form-data; name=\"{name}\"; filename=\"{name}.exr\"\r\nContent-Type: image/x-exr\r\n\r\n")
                .as_bytes(),
        );
        body.extend_from_slice(data);
        body.extend_from_slice(b"\r\n");
    }
    body.extend_from_slice(format!("--{boundary}--\r\n").as_bytes());
    (format!("multipart/form-data; boundary={boundary}"), body)
}

/// The binary, started as `mcdenoise serve` with JSON logs; its addresses read from the
/// "listening" log line. Every log line is kept in `logs`.
pub struct Process {
    pub child: std::process::Child,
    pub http: String,
    pub grpc: String,
    pub logs: std::sync::Arc<std::sync::Mutex<Vec<String>>>,
    reader: Option<std::thread::JoinHandle<()>>,
}

/// Starts the daemon binary at log level `info` (a `--log` in `extra` wins).
pub fn spawn_daemon(data_dir: &Path, extra: &[&str]) -> Process {
    spawn_daemon_with(data_dir, extra, |_| {})
}

/// [`spawn_daemon`] with the command adjusted by `adjust` before it starts.
pub fn spawn_daemon_with(data_dir: &Path, extra: &[&str], adjust: impl FnOnce(&mut std::process::Command)) -> Process {
    use std::io::BufRead;
    let mut argv = args(data_dir, &["--log-format", "json", "--log", "info"]);
    argv.extend(extra.iter().map(|s| s.to_string()));
    let mut command = std::process::Command::new(env!("CARGO_BIN_EXE_mcdenoise"));
    adjust(&mut command);
    let mut child = command
        .args(&argv)
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .expect("the binary starts");
    let stderr = child.stderr.take().unwrap();
    let logs = std::sync::Arc::new(std::sync::Mutex::new(Vec::new()));
    let (tx, rx) = std::sync::mpsc::channel();
    let kept = logs.clone();
    let reader = std::thread::spawn(move || {
        for line in std::io::BufReader::new(stderr).lines().map_while(Result::ok) {
            // Kept before the addresses are passed on: the listening line is in `logs` by
            // the time `spawn_daemon` returns.
            kept.lock().unwrap().push(line.clone());
            if let Ok(v) = serde_json::from_str::<Value>(&line) {
                if v["message"] == "listening" {
                    let _ = tx.send((v["http"].as_str().unwrap().to_string(), v["grpc"].as_str().unwrap().to_string()));
                }
            }
        }
    });
    let (http, grpc) = rx.recv_timeout(Duration::from_secs(30)).expect("the daemon logs its addresses");
    Process { child, http: format!("http://{http}"), grpc, logs, reader: Some(reader) }
}

impl Process {
    /// Sends SIGTERM and waits for the exit; `logs` is then complete.
    pub fn terminate(&mut self) -> std::process::ExitStatus {
        let pid = self.child.id().to_string();
        assert!(std::process::Command::new("kill").args(["-TERM", &pid]).status().unwrap().success());
        let status = self.child.wait().unwrap();
        self.join_logs();
        status
    }

    /// SIGKILL.
    pub fn kill(&mut self) {
        self.child.kill().expect("SIGKILL");
        self.child.wait().unwrap();
        self.join_logs();
    }

    fn join_logs(&mut self) {
        if let Some(reader) = self.reader.take() {
            let _ = reader.join();
        }
    }
}

impl Drop for Process {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Every file under `dir`.
pub fn walk(dir: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    for entry in std::fs::read_dir(dir).unwrap().flatten() {
        let path = entry.path();
        if path.is_dir() {
            out.extend(walk(&path));
        } else {
            out.push(path);
        }
    }
    out
}

/// A self-signed certificate for `localhost`, written as PEM files; returns the
/// certificate's PEM.
/// A self-signed certificate in `dir` and the daemon flags that serve it: (CA PEM, flags).
pub fn tls_flags(dir: &std::path::Path) -> (String, Vec<String>) {
    let ca = self_signed(dir);
    let file = |name: &str| dir.join(name).display().to_string();
    (ca, vec!["--tls-cert".into(), file("cert.pem"), "--tls-key".into(), file("key.pem")])
}

pub fn self_signed(dir: &std::path::Path) -> String {
    let key = rcgen::generate_simple_self_signed(vec!["localhost".to_string()]).unwrap();
    std::fs::write(dir.join("cert.pem"), key.cert.pem()).unwrap();
    std::fs::write(dir.join("key.pem"), key.signing_key.serialize_pem()).unwrap();
    key.cert.pem()
}

/// `GET path` over TLS, trusting only `ca_pem`; the status line.
pub async fn https_get(addr: std::net::SocketAddr, ca_pem: &str, path: &str) -> anyhow::Result<String> {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    use tokio_rustls::rustls::{self, pki_types::pem::PemObject, pki_types::CertificateDer};
    let mut roots = rustls::RootCertStore::empty();
    roots.add(CertificateDer::from_pem_slice(ca_pem.as_bytes())?)?;
    let config =
        rustls::ClientConfig::builder_with_provider(std::sync::Arc::new(rustls::crypto::ring::default_provider()))
            .with_safe_default_protocol_versions()?
            .with_root_certificates(roots)
            .with_no_client_auth();
    let connector = tokio_rustls::TlsConnector::from(std::sync::Arc::new(config));
    let tcp = tokio::net::TcpStream::connect(addr).await?;
    let mut tls = connector.connect("localhost".try_into()?, tcp).await?;
    tls.write_all(format!("GET {path} HTTP/1.1\r\nhost: localhost\r\nconnection: close\r\n\r\n").as_bytes()).await?;
    let mut answer = String::new();
    tls.read_to_string(&mut answer).await?;
    Ok(answer.lines().next().unwrap_or("").to_string())
}
