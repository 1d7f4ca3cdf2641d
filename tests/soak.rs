//! Faults and load against the daemon binary: SIGKILL at random points of job processing
//! (crash safety), a burst of ten times the queue capacity (overload), and SIGTERM while
//! busy (drain). Each test prints a JSON line of figures; `make reliability` runs them with
//! larger settings and docs/reliability.md records the results.
//!
//! Knobs (environment): `MCDENOISE_SOAK_KILLS` (restarts after SIGKILL, default 6),
//! `MCDENOISE_SOAK_SEED` (default 1), `MCDENOISE_BURST_FACTOR` (burst size over the queue
//! capacity, default 10), `MCDENOISE_BURST_MODELS` (models of the burst's daemon, default the
//! tiny test models), `MCDENOISE_BURST_FRAME` (side of the burst's square frames, default
//! 48), `MCDENOISE_RELIABILITY_OUT` (a directory for the JSON figures).

use crate::common;
use crate::daemon_common;

use std::collections::{BTreeMap, HashMap};
use std::time::{Duration, Instant};

use bytes::Bytes;
use futures_util::StreamExt;
use hyper::{Method, StatusCode};
use serde_json::{json, Value};

use daemon_common::*;
use mcdenoise::client::{body_bytes, HttpClient};

fn knob(name: &str, default: u64) -> u64 {
    std::env::var(name).ok().and_then(|v| v.parse().ok()).unwrap_or(default)
}

/// Writes the figures where `make reliability` collects them, and prints them.
fn report(name: &str, figures: &Value) {
    println!("{name}: {figures}");
    if let Ok(dir) = std::env::var("MCDENOISE_RELIABILITY_OUT") {
        std::fs::create_dir_all(&dir).unwrap();
        std::fs::write(format!("{dir}/{name}.json"), serde_json::to_string_pretty(figures).unwrap()).unwrap();
    }
}

/// xorshift64*: reproducible choices from a seed.
struct Rng(u64);

impl Rng {
    fn below(&mut self, n: u64) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        (self.0.wrapping_mul(0x2545_f491_4f6c_dd1d) >> 32) % n.max(1)
    }
}

/// Submits `exr` in `pieces` parts `gap` apart (so a kill can land mid-upload). `Some(id)`
/// when the daemon answered 202.
async fn slow_submit(http: HttpClient, exr: Vec<u8>, label: String, pieces: usize, gap: Duration) -> Option<String> {
    let (tx, rx) = tokio::sync::mpsc::channel::<Bytes>(pieces.max(1));
    let stream =
        tokio_stream::wrappers::ReceiverStream::new(rx).map(|b| Ok::<_, std::io::Error>(hyper::body::Frame::data(b)));
    let body = http_body_util::BodyExt::boxed(http_body_util::StreamBody::new(stream));
    let path = format!("/v1/jobs?label={label}");
    let request =
        tokio::spawn(async move { http.json(Method::POST, &path, &[("content-type", "image/x-exr")], body).await });
    let size = exr.len().div_ceil(pieces.max(1));
    for piece in exr.chunks(size) {
        if tx.send(Bytes::copy_from_slice(piece)).await.is_err() {
            break;
        }
        tokio::time::sleep(gap).await;
    }
    drop(tx);
    match request.await.ok()?.ok()? {
        (StatusCode::ACCEPTED, job) => job["id"].as_str().map(str::to_owned),
        _ => None,
    }
}

/// The decoded `R,G,B` of a result, or why it is not a complete EXR.
fn pixels(exr: &[u8]) -> Result<Vec<f32>, String> {
    let frame =
        mcdenoise::frame::Frame::reference_from_exr_bytes(exr, &Default::default()).map_err(|e| e.to_string())?;
    Ok(frame.color().concat())
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sigkill_at_random_points_loses_no_accepted_job_and_serves_no_partial_result() {
    let kills = knob("MCDENOISE_SOAK_KILLS", 6);
    let seed = knob("MCDENOISE_SOAK_SEED", 1);
    let mut rng = Rng(seed.wrapping_mul(0x9e37_79b9_7f4a_7c15) | 1);
    let dir = tempfile::tempdir().unwrap();
    let slow = ["--tile", "16", "--debug-tile-delay", "15ms", "--shutdown-timeout", "0s"];
    let sizes = [(32usize, 32usize), (48, 32), (64, 48)];
    let frames: Vec<Vec<u8>> = sizes.iter().map(|&(w, h)| frame(w, h)).collect();

    // What an uninterrupted run gives for each frame.
    let mut expected = Vec::new();
    {
        let reference_dir = tempfile::tempdir().unwrap();
        let d = start(reference_dir.path(), &["--tile", "16"]).await;
        d.ready().await;
        for f in &frames {
            let id = d.submit_ok(f, "").await;
            d.wait_state(&id, "succeeded").await;
            expected.push(pixels(&d.result(&id).await.1).unwrap());
        }
        d.stop().await;
    }

    // label -> (frame index, job id once accepted)
    let mut submitted: BTreeMap<String, (usize, Option<String>)> = BTreeMap::new();
    let mut served: HashMap<String, Vec<f32>> = HashMap::new();
    let mut in_flight_at_kill: BTreeMap<&str, u64> = BTreeMap::new();
    let mut results_checked = 0;
    for round in 0..=kills {
        let mut p = spawn_daemon(dir.path(), &slow);
        let http = HttpClient::new(&p.http, None);
        wait_ready(&http).await;
        // Results served now must be complete and what an uninterrupted run gives.
        for (label, (which, id)) in &submitted {
            let Some(id) = id else { continue };
            let resp = http.get(&format!("/v1/jobs/{id}/result")).await.unwrap();
            if resp.status() == StatusCode::OK {
                use http_body_util::BodyExt;
                let bytes = resp.into_body().collect().await.unwrap().to_bytes();
                match pixels(&bytes) {
                    Ok(px) => {
                        assert_eq!(px, expected[*which], "{label}: the result differs from an uninterrupted run");
                        served.insert(id.clone(), px);
                        results_checked += 1;
                    }
                    Err(e) => panic!("{label}: a partial result was served: {e}"),
                }
            }
        }
        if round == kills {
            // The last start: no kill; everything must finish.
            let t = Instant::now();
            for (label, (_, id)) in &submitted {
                let Some(id) = id else { continue };
                let limit = Duration::from_secs(120).saturating_sub(t.elapsed());
                eprintln!("{label}: waiting for {id}");
                wait_succeeded(&http, id, limit).await;
            }
            assert!(p.terminate().success());
            break;
        }
        // Work for this round: a few jobs, some uploaded slowly; the kill comes at a random
        // moment while they upload, wait or run.
        let mut uploads = Vec::new();
        for j in 0..3 + rng.below(3) as usize {
            let which = rng.below(frames.len() as u64) as usize;
            let label = format!("r{round}-j{j}");
            let pieces = 1 + rng.below(6) as usize;
            let gap = Duration::from_millis(rng.below(150));
            submitted.insert(label.clone(), (which, None));
            uploads.push(tokio::spawn({
                let (http, exr, label) = (http.clone(), frames[which].clone(), label.clone());
                async move { (label.clone(), slow_submit(http, exr, label, pieces, gap).await) }
            }));
        }
        tokio::time::sleep(Duration::from_millis(rng.below(700))).await;
        // What is in flight as the kill lands (read just before it).
        if let Some((_, list)) = get_json(&http, "/v1/jobs?limit=1000").await {
            for job in list["jobs"].as_array().unwrap() {
                match job["state"].as_str() {
                    Some("running") => *in_flight_at_kill.entry("running").or_default() += 1,
                    Some("queued") => *in_flight_at_kill.entry("queued").or_default() += 1,
                    _ => {}
                }
            }
        }
        let unanswered = uploads.iter().filter(|u| !u.is_finished()).count();
        *in_flight_at_kill.entry("uploading").or_default() += unanswered as u64;
        p.kill();
        for u in uploads {
            let (label, id) = u.await.unwrap();
            submitted.get_mut(&label).unwrap().1 = id;
        }
    }

    // Each accepted job is there exactly once, succeeded, with the right result; uploads
    // cut by a kill left either nothing or one complete job.
    let d = start(dir.path(), &["--tile", "16"]).await;
    d.ready().await;
    let (_, list) = d.get_json("/v1/jobs?limit=1000").await;
    let jobs = list["jobs"].as_array().unwrap();
    let mut by_label: HashMap<&str, Vec<&Value>> = HashMap::new();
    for job in jobs {
        by_label.entry(job["label"].as_str().unwrap()).or_default().push(job);
    }
    let mut accepted = 0;
    for (label, (which, id)) in &submitted {
        let found = by_label.get(label.as_str()).map(Vec::as_slice).unwrap_or(&[]);
        assert!(found.len() <= 1, "{label}: {} jobs for one submission", found.len());
        if let Some(id) = id {
            accepted += 1;
            assert_eq!(found.len(), 1, "{label}: accepted job {id} lost");
            assert_eq!(found[0]["id"].as_str(), Some(id.as_str()));
        }
        if let Some(job) = found.first() {
            assert_eq!(job["state"], "succeeded", "{label}: {job}");
            let id = job["id"].as_str().unwrap();
            let px = pixels(&d.result(id).await.1).unwrap();
            assert_eq!(px, expected[*which], "{label}: wrong result");
            if let Some(before) = served.get(id) {
                assert_eq!(&px, before, "{label}: the result changed after it was served");
            }
        }
    }
    d.stop().await;
    let leftovers: Vec<_> =
        walk(dir.path()).into_iter().filter(|p| p.extension().is_some_and(|e| e == "part")).collect();
    assert!(leftovers.is_empty(), "partial files left: {leftovers:?}");
    assert!(accepted > 0);
    report(
        "kill-soak",
        &json!({
            "kills": kills,
            "seed": seed,
            "submissions": submitted.len(),
            "accepted": accepted,
            "jobs_lost": 0,
            "jobs_duplicated": 0,
            "results_served_and_checked": results_checked,
            "partial_results_served": 0,
            "in_flight_at_kills": in_flight_at_kill,
        }),
    );
}

fn percentile(sorted_ms: &[f64], q: f64) -> f64 {
    if sorted_ms.is_empty() {
        return f64::NAN;
    }
    sorted_ms[((sorted_ms.len() - 1) as f64 * q).round() as usize]
}

fn summary(mut ms: Vec<f64>) -> Value {
    ms.sort_by(f64::total_cmp);
    json!({ "count": ms.len(), "p50_ms": percentile(&ms, 0.5), "p99_ms": percentile(&ms, 0.99), "max_ms": ms.last() })
}

/// Peak resident memory of a process (VmHWM), in MB.
fn peak_rss_mb(pid: u32) -> f64 {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap();
    let kb: f64 = status
        .lines()
        .find_map(|l| l.strip_prefix("VmHWM:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse().ok())
        .unwrap();
    kb / 1024.0
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_burst_of_ten_times_the_queue_is_shed_at_once_and_the_daemon_recovers() {
    let factor = knob("MCDENOISE_BURST_FACTOR", 10) as usize;
    let side = knob("MCDENOISE_BURST_FRAME", 48) as usize;
    let models =
        std::env::var("MCDENOISE_BURST_MODELS").unwrap_or_else(|_| common::tiny_models().display().to_string());
    let capacity = 8usize;
    let nodes: Vec<String> = (0..16).map(|i| format!("node-{i}")).collect();
    let dir = tempfile::tempdir().unwrap();
    let cap = capacity.to_string();
    let tokens = nodes.join(",");
    // With the tiny models each tile is slowed down so that the burst meets busy workers.
    let (tile, delay) = if models.contains("fixtures") { ("16", "10ms") } else { ("256", "0s") };
    let p = spawn_daemon(
        dir.path(),
        &[
            "--queue-capacity",
            &cap,
            "--auth-token",
            &tokens,
            "--operator-token",
            "farm-ops",
            "--models",
            &models,
            "--tile",
            tile,
            "--debug-tile-delay",
            delay,
            "--threads-per-worker",
            "2",
        ],
    );
    let clients: Vec<HttpClient> = nodes.iter().map(|t| HttpClient::new(&p.http, Some(t))).collect();
    // The farm manager: an operator token sees every node's jobs.
    let ops = HttpClient::new(&p.http, Some("farm-ops"));
    wait_ready(&clients[0]).await;
    let rss_idle = peak_rss_mb(p.child.id());
    let exr = frame(side, side);

    // A job to poll while the burst is served.
    let (_, probe) = clients[0]
        .json(Method::POST, "/v1/jobs", &[("content-type", "image/x-exr")], body_bytes(exr.clone()))
        .await
        .unwrap();
    let probe = probe["id"].as_str().unwrap().to_string();
    let stop = tokio_util::sync::CancellationToken::new();
    let poller = tokio::spawn({
        let (http, stop, path) = (ops.clone(), stop.clone(), format!("/v1/jobs/{probe}"));
        async move {
            let mut ms = Vec::new();
            while !stop.is_cancelled() {
                let t = Instant::now();
                let (status, _) = get_json(&http, &path).await.unwrap();
                assert_eq!(status, StatusCode::OK);
                ms.push(t.elapsed().as_secs_f64() * 1e3);
                tokio::time::sleep(Duration::from_millis(5)).await;
            }
            ms
        }
    });

    let burst = capacity * factor;
    let t_burst = Instant::now();
    let answers = futures_util::future::join_all((0..burst).map(|i| {
        let (http, exr) = (clients[i % clients.len()].clone(), exr.clone());
        async move {
            let t = Instant::now();
            let resp =
                http.send(Method::POST, "/v1/jobs", &[("content-type", "image/x-exr")], body_bytes(exr)).await.unwrap();
            let retry_after = resp.headers().get("retry-after").map(|v| v.to_str().unwrap().to_string());
            let (status, body) = mcdenoise::client::read_json(resp).await.unwrap();
            (status, body, retry_after, t.elapsed().as_secs_f64() * 1e3)
        }
    }))
    .await;
    let burst_s = t_burst.elapsed().as_secs_f64();
    let (mut accepted, mut rejected_ms, mut accepted_ms) = (Vec::new(), Vec::new(), Vec::new());
    for (status, body, retry_after, ms) in answers {
        match status {
            StatusCode::ACCEPTED => {
                accepted.push(body["id"].as_str().unwrap().to_string());
                accepted_ms.push(ms);
            }
            StatusCode::TOO_MANY_REQUESTS => {
                assert_eq!(body["error"]["code"], "queue_full", "{body}");
                let secs: u64 = retry_after.expect("429 carries Retry-After").parse().unwrap();
                assert!((1..=600).contains(&secs));
                rejected_ms.push(ms);
            }
            other => panic!("{other}: {body}"),
        }
    }
    assert!(accepted.len() >= capacity - 1 && accepted.len() < burst, "{} accepted", accepted.len());
    assert_eq!(accepted.len() + rejected_ms.len(), burst);

    // Everything accepted completes.
    let t = Instant::now();
    for id in accepted.iter().chain([&probe]) {
        wait_succeeded(&ops, id, Duration::from_secs(120).saturating_sub(t.elapsed())).await;
    }
    let drained_s = t.elapsed().as_secs_f64();
    stop.cancel();
    let status_ms = poller.await.unwrap();
    let rss_peak = peak_rss_mb(p.child.id());
    assert!(rss_peak < 1024.0, "peak RSS {rss_peak:.0} MB");

    // Recovered without a restart: a new job is accepted and completes.
    let (status, job) = clients[3]
        .json(Method::POST, "/v1/jobs", &[("content-type", "image/x-exr")], body_bytes(exr.clone()))
        .await
        .unwrap();
    assert_eq!(status, StatusCode::ACCEPTED, "{job}");
    let id = job["id"].as_str().unwrap();
    loop {
        let (_, job) = get_json(&clients[3], &format!("/v1/jobs/{id}")).await.unwrap();
        if job["state"] == "succeeded" {
            break;
        }
        assert!(t.elapsed() < Duration::from_secs(120), "{job}");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    report(
        if models.contains("fixtures") { "overload" } else { "overload-shipped-models" },
        &json!({
            "queue_capacity": capacity,
            "models": models,
            "frame": format!("{side}x{side}"),
            "clients": nodes.len(),
            "burst": burst,
            "accepted": accepted.len(),
            "rejected_429": rejected_ms.len(),
            "burst_answered_s": burst_s,
            "rejection_latency": summary(rejected_ms),
            "acceptance_latency": summary(accepted_ms),
            "status_query_latency_while_saturated": summary(status_ms),
            "accepted_work_completed_s": drained_s,
            "peak_rss_mb": rss_peak,
            "idle_rss_mb": rss_idle,
            "recovered_without_restart": true,
        }),
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sigterm_while_busy_flips_readiness_first_drains_and_loses_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let slow = ["--tile", "16", "--debug-tile-delay", "40ms", "--shutdown-timeout", "10s"];
    let mut p = spawn_daemon(dir.path(), &slow);
    let http = HttpClient::new(&p.http, None);
    wait_ready(&http).await;
    let mut ids = Vec::new();
    for _ in 0..3 {
        let (status, job) = http
            .json(Method::POST, "/v1/jobs", &[("content-type", "image/x-exr")], body_bytes(frame(64, 48)))
            .await
            .unwrap();
        assert_eq!(status, StatusCode::ACCEPTED, "{job}");
        ids.push(job["id"].as_str().unwrap().to_string());
    }
    let t = Instant::now();
    loop {
        let (_, job) = get_json(&http, &format!("/v1/jobs/{}", ids[0])).await.unwrap();
        if job["state"] == "running" {
            break;
        }
        assert!(t.elapsed() < Duration::from_secs(30), "{job}");
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    // Probe readiness as fast as possible from the SIGTERM until the listener closes.
    let prober = tokio::spawn({
        let http = http.clone();
        async move {
            let mut seen = Vec::new();
            loop {
                match http.get("/readyz").await {
                    Ok(resp) => {
                        let s = resp.status().as_u16();
                        if seen.last() != Some(&s) {
                            seen.push(s);
                        }
                    }
                    Err(_) => {
                        seen.push(0);
                        return seen;
                    }
                }
                tokio::time::sleep(Duration::from_millis(2)).await;
            }
        }
    });
    tokio::time::sleep(Duration::from_millis(50)).await;
    let t_term = Instant::now();
    let status = tokio::task::spawn_blocking(move || {
        let status = p.terminate();
        (status, p)
    })
    .await
    .unwrap();
    let (exit, _p) = status;
    let drain_s = t_term.elapsed().as_secs_f64();
    assert!(exit.success(), "{exit:?}");
    assert!(drain_s < 10.0 + 5.0, "the drain took {drain_s:.1} s, beyond the 10 s deadline");
    let seen = prober.await.unwrap();
    // 200 while serving, then 503 (draining) while the listener is still open, then closed.
    assert_eq!(seen, vec![200, 503, 0], "readiness answers in order: {seen:?}");

    // Nothing lost: the running job finished during the drain, the queued ones run after a
    // restart.
    let p = spawn_daemon(dir.path(), &[]);
    let http = HttpClient::new(&p.http, None);
    wait_ready(&http).await;
    let (_, first) = get_json(&http, &format!("/v1/jobs/{}", ids[0])).await.unwrap();
    assert_eq!(first["state"], "succeeded", "the running job completed in the drain: {first}");
    assert_eq!(first["attempts"], 1, "{first}");
    let t = Instant::now();
    for id in &ids[1..] {
        loop {
            let (status, job) = get_json(&http, &format!("/v1/jobs/{id}")).await.unwrap();
            assert_eq!(status, StatusCode::OK, "{job}");
            if job["state"] == "succeeded" {
                break;
            }
            assert!(t.elapsed() < Duration::from_secs(60), "{job}");
            tokio::time::sleep(Duration::from_millis(20)).await;
        }
    }
    report("sigterm-drain", &json!({ "drain_s": drain_s, "readiness_sequence": seen, "jobs_lost": 0 }));
}
