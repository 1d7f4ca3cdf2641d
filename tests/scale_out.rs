//! Shared mode (`--store nats://…`): three daemon processes on one real `nats-server` with
//! JetStream (Debian's package, started here on a loopback port), jobs submitted round-robin.
//! Any replica answers for any job; idempotency keys and admission limits hold across
//! replicas; a replica SIGKILLed mid-job has its job finished by another, with the same
//! result, nothing lost or finished twice; a NATS restart loses no accepted job; the
//! retention sweep removes each job once.

use crate::common;
use crate::daemon_common;

use std::collections::HashMap;
use std::net::TcpListener;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use http_body_util::BodyExt;
use hyper::{Method, StatusCode};
use serde_json::Value;

use daemon_common::{frame, get_json, poll, spawn_daemon, wait_ready, Process};
use mcdenoise::client::{body_bytes, read_sse, HttpClient};

/// `nats-server`, from PATH or where Debian puts it.
fn nats_binary() -> PathBuf {
    let on_path = std::env::var_os("PATH")
        .and_then(|p| std::env::split_paths(&p).map(|d| d.join("nats-server")).find(|p| p.is_file()));
    on_path
        .or_else(|| Some(PathBuf::from("/usr/sbin/nats-server")).filter(|p| p.is_file()))
        .expect("nats-server is needed for the shared-mode tests: `bash scripts/setup test` installs Debian's package")
}

fn free_port() -> u16 {
    TcpListener::bind("127.0.0.1:0").unwrap().local_addr().unwrap().port()
}

/// A JetStream server on a loopback port, its data in `dir` (kept across restarts).
struct Nats {
    child: Option<Child>,
    port: u16,
    dir: PathBuf,
}

impl Nats {
    fn start(dir: &Path) -> Nats {
        let mut nats = Nats { child: None, port: free_port(), dir: dir.to_path_buf() };
        nats.restart();
        nats
    }

    fn url(&self) -> String {
        format!("nats://127.0.0.1:{}", self.port)
    }

    /// Starts the server (again, on the same port and data) and waits until it listens.
    fn restart(&mut self) {
        let child = Command::new(nats_binary())
            .args(["-js", "-a", "127.0.0.1", "-p", &self.port.to_string(), "-sd"])
            .arg(&self.dir)
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("nats-server starts");
        self.child = Some(child);
        let deadline = Instant::now() + Duration::from_secs(20);
        while std::net::TcpStream::connect(("127.0.0.1", self.port)).is_err() {
            assert!(Instant::now() < deadline, "nats-server does not listen on {}", self.port);
            std::thread::sleep(Duration::from_millis(50));
        }
    }

    fn kill(&mut self) {
        if let Some(mut child) = self.child.take() {
            let _ = child.kill();
            let _ = child.wait();
        }
    }
}

impl Drop for Nats {
    fn drop(&mut self) {
        self.kill();
    }
}

/// A daemon of the shared fleet: one worker, 16-pixel tiles that take at least `delay`.
struct Fleet {
    root: PathBuf,
    url: String,
    extra: Vec<String>,
    replicas: Vec<Process>,
    /// Processes killed so far (their logs are read at the end).
    killed: Vec<Process>,
}

impl Fleet {
    fn start(root: &Path, nats: &Nats, n: usize, extra: &[&str]) -> Fleet {
        let mut fleet = Fleet {
            root: root.to_path_buf(),
            url: nats.url(),
            extra: extra.iter().map(|s| s.to_string()).collect(),
            replicas: Vec::new(),
            killed: Vec::new(),
        };
        for i in 0..n {
            let p = fleet.spawn(i);
            fleet.replicas.push(p);
        }
        fleet
    }

    fn spawn(&self, i: usize) -> Process {
        let mut args: Vec<&str> = vec!["--store", &self.url, "--tile", "16", "--storage-check-interval", "200ms"];
        args.extend(self.extra.iter().map(String::as_str));
        spawn_daemon(&self.root.join(format!("replica-{i}")), &args)
    }

    fn http(&self, i: usize) -> HttpClient {
        HttpClient::new(&self.replicas[i % self.replicas.len()].http, None)
    }

    async fn ready(&self) {
        for i in 0..self.replicas.len() {
            wait_ready(&self.http(i)).await;
        }
    }

    /// SIGKILLs replica `i` and starts a new process in its place.
    fn kill_and_replace(&mut self, i: usize) {
        self.replicas[i].kill();
        let mut p = self.spawn(i);
        std::mem::swap(&mut p, &mut self.replicas[i]);
        self.killed.push(p);
    }

    /// Every log line of every process so far, parsed.
    fn logs(&self) -> Vec<Value> {
        self.replicas
            .iter()
            .chain(&self.killed)
            .flat_map(|p| p.logs.lock().unwrap().clone())
            .filter_map(|l| serde_json::from_str::<Value>(&l).ok())
            .collect()
    }
}

impl Drop for Fleet {
    /// A failed test leaves every replica's log next to the replicas' directories, kept.
    fn drop(&mut self) {
        if std::thread::panicking() {
            let kept = std::env::temp_dir().join(format!("scale-out-{}.log", std::process::id()));
            let lines: Vec<String> = self
                .replicas
                .iter()
                .chain(&self.killed)
                .enumerate()
                .flat_map(|(i, p)| p.logs.lock().unwrap().iter().map(|l| format!("[{i}] {l}")).collect::<Vec<_>>())
                .collect();
            let _ = std::fs::write(&kept, lines.join("\n"));
            eprintln!("replica logs: {}", kept.display());
        }
    }
}

/// How many log lines say `message` about each job (a replica's line may reach its log a
/// moment after its answer: wait for them first).
fn count_by_job(logs: &[Value], message: &str) -> HashMap<String, usize> {
    let mut counts = HashMap::new();
    for l in logs {
        let fields = if l.get("fields").is_some() { &l["fields"] } else { l };
        if fields["message"] == message {
            if let Some(id) = fields["job_id"].as_str().or_else(|| l["span"]["job_id"].as_str()) {
                *counts.entry(id.to_string()).or_default() += 1;
            }
        }
    }
    counts
}

async fn submit(http: &HttpClient, exr: &[u8], query: &str) -> (StatusCode, Value) {
    http.json(Method::POST, &format!("/v1/jobs?{query}"), &[("content-type", "image/x-exr")], body_bytes(exr.to_vec()))
        .await
        .expect("submit")
}

async fn submit_ok(http: &HttpClient, exr: &[u8], query: &str) -> String {
    let (status, job) = submit(http, exr, query).await;
    assert_eq!(status, StatusCode::ACCEPTED, "{job}");
    job["id"].as_str().unwrap().to_string()
}

async fn job(http: &HttpClient, id: &str) -> Value {
    let (status, job) = get_json(http, &format!("/v1/jobs/{id}")).await.expect("a job answer");
    assert_eq!(status, StatusCode::OK, "{job}");
    job
}

async fn wait_state(http: &HttpClient, id: &str, state: &str, limit: Duration) -> Value {
    poll(&format!("job {id} {state}"), limit, || async {
        let j = get_json(http, &format!("/v1/jobs/{id}")).await.map(|(_, j)| j);
        match j {
            Some(j) if j["state"] == state => Ok(j),
            other => Err(other.map(|j| j["state"].clone())),
        }
    })
    .await
}

async fn result_pixels(http: &HttpClient, id: &str) -> Vec<(String, Vec<u32>)> {
    let resp = http.get(&format!("/v1/jobs/{id}/result")).await.unwrap();
    assert_eq!(resp.status(), StatusCode::OK);
    let bytes = resp.into_body().collect().await.unwrap().to_bytes();
    let image = common::read_exr(&bytes);
    let mut channels: Vec<(String, Vec<u32>)> = image
        .layer_data
        .iter()
        .flat_map(|l| l.channel_data.list.iter().map(|c| (c.name.to_string(), common::bits(&c.sample_data).1)))
        .collect();
    channels.sort();
    channels
}

async fn metric(http: &HttpClient, name: &str) -> Option<f64> {
    let resp = http.get("/metrics").await.ok()?;
    let text = String::from_utf8(resp.into_body().collect().await.ok()?.to_bytes().to_vec()).ok()?;
    text.lines().find_map(|l| l.strip_prefix(name).and_then(|v| v.trim().parse().ok()))
}

/// A job is found through every replica the moment it is accepted, as a client behind a
/// load balancer needs, even where a replica's watch lags (`--debug-watch-delay`, what load
/// does): a read by id that misses the mirror reads the shared record.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_job_is_found_through_any_replica_at_once() {
    let dir = tempfile::tempdir().unwrap();
    let nats = Nats::start(&dir.path().join("nats"));
    let fleet = Fleet::start(dir.path(), &nats, 2, &["--debug-watch-delay", "2s", "--debug-tile-delay", "200ms"]);
    fleet.ready().await;
    let exr = frame(48, 48);
    let status_of = |id: &str| format!("/v1/jobs/{id}");
    let id = submit_ok(&fleet.http(0), &exr, "").await;
    let (status, job) = get_json(&fleet.http(1), &status_of(&id)).await.unwrap();
    assert_eq!(status, StatusCode::OK, "the other replica, asked at once: {job}");
    let resp = fleet.http(1).get(&format!("/v1/jobs/{id}/events")).await.unwrap();
    assert_eq!(resp.status(), StatusCode::OK, "its events on the other replica");
    drop(resp);
    let mut grpc = mcdenoise::client::grpc_connect(&fleet.replicas[1].grpc, None).await.unwrap();
    let got = grpc.get_job(mcdenoise::grpc::pb::GetJobRequest { id: id.clone() }).await;
    assert!(got.is_ok(), "GetJob on the other replica: {got:?}");
    // A cancellation through the other replica reaches it too: at once if the job is still
    // queued (200), or at its next tile if a replica has started it meanwhile (202; the
    // first job's tiles take 1.8 s, but a loaded machine may run the second as soon).
    let other = submit_ok(&fleet.http(0), &exr, "").await;
    let (status, body) = fleet
        .http(1)
        .json(Method::POST, &format!("/v1/jobs/{other}/cancel"), &[], body_bytes(Vec::new()))
        .await
        .unwrap();
    assert!(
        status == StatusCode::OK || status == StatusCode::ACCEPTED,
        "cancel through the other replica: {status} {body}"
    );
    wait_state(&fleet.http(0), &other, "cancelled", Duration::from_secs(30)).await;
    // What is not a job stays unknown, without a read of the store.
    let (status, _) = get_json(&fleet.http(1), &status_of("not-a-job")).await.unwrap();
    assert_eq!(status, StatusCode::NOT_FOUND);
    let (status, _) = get_json(&fleet.http(1), &status_of(&uuid::Uuid::now_v7().to_string())).await.unwrap();
    assert_eq!(status, StatusCode::NOT_FOUND);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn three_replicas_share_one_queue_and_answer_for_every_job() {
    let dir = tempfile::tempdir().unwrap();
    let nats = Nats::start(&dir.path().join("nats"));
    let fleet = Fleet::start(dir.path(), &nats, 3, &["--debug-tile-delay", "10ms"]);
    fleet.ready().await;
    let exr = frame(48, 48);

    let mut ids = Vec::new();
    for i in 0..12 {
        ids.push(submit_ok(&fleet.http(i), &exr, "").await);
    }
    let mut reference = None;
    for (i, id) in ids.iter().enumerate() {
        // Asked of a replica other than the one that took it.
        let done = wait_state(&fleet.http(i + 1), id, "succeeded", Duration::from_secs(60)).await;
        assert_eq!(done["attempts"], 1, "{done}");
        for r in 0..3 {
            // Each replica learns of the end through its watch, within moments.
            let seen = wait_state(&fleet.http(r), id, "succeeded", Duration::from_secs(5)).await;
            assert_eq!(
                (&seen["attempts"], &seen["result_bytes"]),
                (&done["attempts"], &done["result_bytes"]),
                "replica {r}"
            );
        }
        let pixels = result_pixels(&fleet.http(i + 2), id).await;
        match &reference {
            None => reference = Some(pixels),
            Some(first) => assert!(first == &pixels, "job {id}: another result for the same frame"),
        }
    }
    tokio::time::sleep(Duration::from_millis(500)).await;
    let logs = fleet.logs();
    let claimed = count_by_job(&logs, "claimed from the shared queue");
    let finished = count_by_job(&logs, "finished");
    for id in &ids {
        assert_eq!(claimed.get(id), Some(&1), "job {id} claimed once");
        assert_eq!(finished.get(id), Some(&1), "job {id} finished once");
    }
    let per_replica: Vec<usize> = fleet
        .replicas
        .iter()
        .map(|p| p.logs.lock().unwrap().iter().filter(|l| l.contains("claimed from the shared queue")).count())
        .collect();
    assert!(per_replica.iter().filter(|n| **n > 0).count() >= 2, "the work is shared: {per_replica:?}");

    // Lists: every replica lists every job.
    for r in 0..3 {
        let (_, list) = get_json(&fleet.http(r), "/v1/jobs?limit=100").await.unwrap();
        assert_eq!(list["jobs"].as_array().unwrap().len(), ids.len(), "replica {r}: {list}");
    }

    // Idempotency keys are global: the same key on two replicas is one job.
    let first = submit_ok(&fleet.http(0), &exr, "idempotency_key=shot-7-f0001").await;
    let (status, again) = submit(&fleet.http(1), &exr, "idempotency_key=shot-7-f0001").await;
    assert!(status.is_success(), "{status} {again}");
    assert_eq!(again["id"], first.as_str());
    wait_state(&fleet.http(2), &first, "succeeded", Duration::from_secs(60)).await;

    // Events of a job run anywhere, watched on another replica, to the end.
    let slow = submit_ok(&fleet.http(0), &frame(96, 96), "").await;
    let resp = fleet.http(1).get(&format!("/v1/jobs/{slow}/events")).await.unwrap();
    assert_eq!(resp.status(), StatusCode::OK, "events of {slow} on another replica");
    let mut events = Vec::new();
    read_sse(resp, |ev| {
        events.push(ev.event.clone());
        ev.event != "succeeded"
    })
    .await
    .unwrap();
    assert!(matches!(events.first().map(String::as_str), Some("queued" | "started")), "{events:?}");
    assert!(events.iter().any(|e| e == "progress"), "{events:?}");
    assert_eq!(events.last().map(String::as_str), Some("succeeded"), "{events:?}");

    // Cancel on one replica reaches the replica running the job.
    let long = submit_ok(&fleet.http(0), &frame(160, 160), "").await;
    wait_state(&fleet.http(0), &long, "running", Duration::from_secs(30)).await;
    let (status, j) = fleet
        .http(2)
        .json(Method::POST, &format!("/v1/jobs/{long}/cancel"), &[], body_bytes(Vec::new()))
        .await
        .unwrap();
    assert!(status.is_success(), "{status} {j}");
    let j = wait_state(&fleet.http(1), &long, "cancelled", Duration::from_secs(30)).await;
    assert!(j["progress"]["tiles_done"].as_u64() < j["progress"]["tiles_total"].as_u64(), "stopped early: {j}");

    // Delete on one replica: gone everywhere.
    let (status, body) =
        fleet.http(1).json(Method::DELETE, &format!("/v1/jobs/{}", ids[0]), &[], body_bytes(Vec::new())).await.unwrap();
    assert!(status.is_success(), "{status} {body}");
    for r in 0..3 {
        poll("the deleted job is gone", Duration::from_secs(10), || async {
            match get_json(&fleet.http(r), &format!("/v1/jobs/{}", ids[0])).await {
                Some((StatusCode::NOT_FOUND, _)) => Ok(()),
                other => Err(other.map(|(s, _)| s)),
            }
        })
        .await;
    }

    // Metrics: the shared queue as JetStream counts it, and the connection.
    assert_eq!(metric(&fleet.http(0), "mcdenoise_nats_connected").await, Some(1.0));
    assert!(metric(&fleet.http(0), "mcdenoise_shared_queue_messages").await.is_some());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn admission_limits_and_the_retention_sweep_hold_across_replicas() {
    let dir = tempfile::tempdir().unwrap();
    let nats = Nats::start(&dir.path().join("nats"));
    let fleet = Fleet::start(
        dir.path(),
        &nats,
        3,
        &[
            "--debug-tile-delay",
            "80ms",
            "--queue-capacity",
            "2",
            "--max-jobs-per-client",
            "6",
            "--result-ttl",
            "2s",
            "--janitor-interval",
            "100ms",
        ],
    );
    fleet.ready().await;
    // 64 tiles of at least 80 ms: none ends while the queue is filled and tried.
    let exr = frame(128, 128);
    // Three run (one per replica), two wait: the shared queue is full for every replica.
    let mut ids = Vec::new();
    for i in 0..3 {
        let id = submit_ok(&fleet.http(i), &exr, "").await;
        wait_state(&fleet.http(i), &id, "running", Duration::from_secs(30)).await;
        ids.push(id);
    }
    for i in 0..2 {
        ids.push(submit_ok(&fleet.http(i), &exr, "").await);
    }
    tokio::time::sleep(Duration::from_millis(300)).await;
    for r in 0..3 {
        let (status, body) = submit(&fleet.http(r), &exr, "").await;
        assert_eq!(status, StatusCode::TOO_MANY_REQUESTS, "replica {r}: {body}");
        assert_eq!(body["error"]["code"], "queue_full", "{body}");
    }
    for id in &ids {
        wait_state(&fleet.http(0), id, "succeeded", Duration::from_secs(60)).await;
    }
    // Expired after 2 s: removed everywhere, each by one replica only.
    for id in &ids {
        poll(&format!("expired job {id} gone from replica 1"), Duration::from_secs(20), || async {
            match get_json(&fleet.http(1), &format!("/v1/jobs/{id}")).await {
                Some((StatusCode::NOT_FOUND, _)) => Ok(()),
                other => Err(other.map(|(s, _)| s)),
            }
        })
        .await;
    }
    tokio::time::sleep(Duration::from_millis(500)).await;
    let swept = count_by_job(&fleet.logs(), "expired and removed");
    for id in &ids {
        assert_eq!(swept.get(id), Some(&1), "job {id} swept once: {swept:?}");
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn killed_replicas_lose_nothing_and_finish_nothing_twice() {
    const KILLS: usize = 20;
    let dir = tempfile::tempdir().unwrap();
    let nats = Nats::start(&dir.path().join("nats"));
    let mut fleet = Fleet::start(dir.path(), &nats, 3, &["--debug-tile-delay", "25ms", "--nats-ack-wait", "2s"]);
    fleet.ready().await;
    let exr = frame(64, 64);
    let mut ids = Vec::new();
    for i in 0..6 {
        ids.push(submit_ok(&fleet.http(i), &exr, "").await);
    }
    let mut kills = 0;
    let mut victim = 0;
    let started = Instant::now();
    while kills < KILLS {
        assert!(started.elapsed() < Duration::from_secs(300), "only {kills} kills mid-job in 5 minutes");
        // Keep the queue from running dry, through a replica that is not about to die.
        if ids.len() < 6 + 2 * kills + 2 {
            ids.push(submit_ok(&fleet.http(victim + 1), &exr, "").await);
        }
        let busy = metric(&fleet.http(victim), "mcdenoise_jobs_in_flight").await == Some(1.0);
        let tiles = metric(&fleet.http(victim), "mcdenoise_tiles_total").await.unwrap_or(0.0);
        if !busy || tiles < 1.0 {
            tokio::time::sleep(Duration::from_millis(50)).await;
            continue;
        }
        fleet.kill_and_replace(victim);
        kills += 1;
        wait_ready(&fleet.http(victim)).await;
        victim = (victim + 1) % 3;
    }
    let mut reference = None;
    let mut reruns = 0;
    let mut ended = Vec::new();
    for id in &ids {
        let j = wait_state(&fleet.http(0), id, "succeeded", Duration::from_secs(120)).await;
        reruns += j["attempts"].as_u64().unwrap() - 1;
        ended.push(j.clone());
        let pixels = result_pixels(&fleet.http(1), id).await;
        match &reference {
            None => reference = Some(pixels),
            Some(first) => assert!(first == &pixels, "job {id} (attempts {}): another result", j["attempts"]),
        }
    }
    // Finished once: no replica wrote another end afterwards (a replica killed between
    // writing the end and logging it leaves no line, hence at most one).
    tokio::time::sleep(Duration::from_secs(3)).await;
    for (id, first) in ids.iter().zip(&ended) {
        let now = job(&fleet.http(2), id).await;
        assert_eq!(now, *first, "job {id} changed after it ended");
    }
    let finished = count_by_job(&fleet.logs(), "finished");
    for id in &ids {
        assert!(finished.get(id).copied().unwrap_or(0) <= 1, "job {id} finished once");
    }
    eprintln!("{kills} kills mid-job; {} jobs, all succeeded once; {reruns} runs cut short and run again", ids.len());
    // Each kill hit a replica with a job in flight: (nearly) every one is run again elsewhere.
    assert!(reruns as usize >= KILLS * 3 / 4, "{reruns} reruns after {kills} kills");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_nats_restart_loses_no_accepted_job() {
    let dir = tempfile::tempdir().unwrap();
    let mut nats = Nats::start(&dir.path().join("nats"));
    let fleet = Fleet::start(dir.path(), &nats, 2, &["--debug-tile-delay", "20ms", "--nats-ack-wait", "2s"]);
    fleet.ready().await;
    let exr = frame(64, 64);
    let mut ids = Vec::new();
    for i in 0..8 {
        ids.push(submit_ok(&fleet.http(i), &exr, "").await);
    }
    wait_state(&fleet.http(0), &ids[0], "succeeded", Duration::from_secs(60)).await;

    nats.kill();
    // Not ready while NATS is away; submissions are refused, not lost.
    for r in 0..2 {
        poll("not ready without NATS", Duration::from_secs(10), || async {
            match get_json(&fleet.http(r), "/readyz").await {
                Some((StatusCode::SERVICE_UNAVAILABLE, body)) => Ok(body),
                other => Err(other),
            }
        })
        .await;
    }
    let (status, body) = submit(&fleet.http(0), &exr, "").await;
    assert_eq!(status, StatusCode::SERVICE_UNAVAILABLE, "{body}");
    tokio::time::sleep(Duration::from_secs(1)).await;
    nats.restart();

    fleet.ready().await;
    ids.push(submit_ok(&fleet.http(1), &exr, "").await);
    let mut ended = Vec::new();
    for id in &ids {
        ended.push(wait_state(&fleet.http(1), id, "succeeded", Duration::from_secs(120)).await);
    }
    // Ended once: an end written just as NATS went away is found by the next run, which
    // only acknowledges it; nothing ends twice. The other replica shows the same ended
    // record once its mirror has caught up (a replica whose requests are still timing out
    // after the restart shows the job as it last saw it for a few seconds).
    tokio::time::sleep(Duration::from_secs(1)).await;
    let finished = count_by_job(&fleet.logs(), "finished");
    for (id, first) in ids.iter().zip(&ended) {
        assert!(finished.get(id).copied().unwrap_or(0) <= 1, "job {id} finished once");
        let there = wait_state(&fleet.http(0), id, "succeeded", Duration::from_secs(30)).await;
        assert_eq!(there, *first, "job {id} changed after it ended");
    }
}

/// Replicas of a new deployment start together: each creates the stream, buckets, object
/// store and consumers that do not exist yet, and one replica's creation racing another's
/// must not stop either (the server answers the loser with "already in use" or "subjects
/// overlap").
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn replicas_starting_together_all_open_the_store() {
    use mcdenoise::jobs::shared::Shared;
    use mcdenoise::jobs::SharedConfig;
    let dir = tempfile::tempdir().unwrap();
    let nats = Nats::start(&dir.path().join("nats"));
    for round in 0..30 {
        let config = SharedConfig {
            servers: nats.url(),
            replicas: 1,
            ack_wait: Duration::from_secs(5),
            prefix: format!("race{round}"),
        };
        let opened = futures_util::future::join_all((0..6).map(|_| {
            let config = config.clone();
            tokio::spawn(async move { Shared::connect(&config, Duration::from_secs(10)).await.map(|_| ()) })
        }))
        .await;
        for (i, r) in opened.into_iter().enumerate() {
            if let Err(e) = r.unwrap() {
                panic!("round {round}, replica {i}: {e}");
            }
        }
    }
}
