//! Speed benchmark (`make bench`, or `cargo bench --bench speed -- [--models DIR] [--threads N]
//! [--tile N] [--tile-v2 N] [--runs N] [--out FILE] [--work DIR] [--quick] [--engine-only]
//! [--int8-models DIR] [--device D]`). Every figure is measured in the same run
//! so that the ratios between them hold even on a machine with other load:
//!
//! 1. the machine's ceiling: FP32 GEMM through ONNX Runtime's MatMul (benches/matmul.onnx)
//!    on all engine threads;
//! 2. the inference floor: ONNX Runtime alone running the models on the tiles of a 1280×720
//!    frame ([`Engine::inference_only`]);
//! 3. the engine on that frame: decode, preprocess, inference, reconstruction, encode;
//! 4. the daemon end to end (upload, queue, engine, result download) with 1, 2 and 8
//!    concurrent HTTP clients, against the engine alone on the same frames;
//! 5. peak resident memory of `mcdenoise run` at 720p, 1080p and 4K;
//! 6. with `--int8-models DIR` (int8 copies of the models, `mcdenoise_train.quantize`): the
//!    int8 GEMM ceiling (u8 × s8 MatMulInteger, benches/matmul-int8.onnx) and stages 2–3
//!    again with those models, against FP32 in the same run; and whether the CPU has bf16
//!    instructions.
//!
//! Writes one JSON document (`--out`, default `target/bench/speed.json`) and leaves the 720p
//! frame it used in `--work` (default `target/bench/frame-1280x720.exr`) for the OIDN
//! comparison in benches/oidn_speed.py.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

use anyhow::{bail, Context, Result};
use bytes::Bytes;
use exr::prelude::*;
use hyper::{Method, StatusCode};
use serde_json::{json, Value};

use mcdenoise::client::{body_bytes, read_json, HttpClient};
use mcdenoise::config::parse_serve_args;
use mcdenoise::engine::{model, runtime, synthetic_planes, Engine, EngineConfig};
use mcdenoise::frame::{self, write_planes, Frame, Limits, OutputLayer, SampleType};
use mcdenoise::server::Server;

struct Args {
    models: PathBuf,
    threads: usize,
    tile: usize,
    /// Tile side for contract-v2 models.
    tile_v2: usize,
    runs: usize,
    out: PathBuf,
    work: PathBuf,
    quick: bool,
    /// Only the ceilings and the engine (for iterating on the engine's speed).
    engine_only: bool,
    /// Int8 copies of the models, measured against FP32.
    int8_models: Option<PathBuf>,
    /// `--device` of the engine, the daemon and `mcdenoise run` (default `auto`, theirs).
    device: String,
}

fn parse_args() -> Result<Args> {
    let mut a = Args {
        models: PathBuf::from("models"),
        threads: std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1),
        tile: 256,
        tile_v2: mcdenoise::engine::DEFAULT_TILE_V2,
        runs: 3,
        out: PathBuf::from("target/bench/speed.json"),
        work: PathBuf::from("target/bench"),
        quick: false,
        engine_only: false,
        int8_models: None,
        device: "auto".to_string(),
    };
    let mut it = std::env::args().skip(1);
    while let Some(flag) = it.next() {
        let mut value = || it.next().with_context(|| format!("{flag} needs a value"));
        match flag.as_str() {
            "--bench" => {}
            "--models" => a.models = value()?.into(),
            "--threads" => a.threads = value()?.parse()?,
            "--tile" => a.tile = value()?.parse()?,
            "--tile-v2" => a.tile_v2 = value()?.parse()?,
            "--runs" => a.runs = value()?.parse()?,
            "--out" => a.out = value()?.into(),
            "--work" => a.work = value()?.into(),
            "--quick" => a.quick = true,
            "--engine-only" => a.engine_only = true,
            "--int8-models" => a.int8_models = Some(value()?.into()),
            "--device" => a.device = value()?,
            other => bail!("unknown argument `{other}`"),
        }
    }
    Ok(a)
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    let n = v.len();
    if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    }
}

fn percentile(mut v: Vec<f64>, p: f64) -> f64 {
    v.sort_by(f64::total_cmp);
    v[((p * (v.len() - 1) as f64).round() as usize).min(v.len() - 1)]
}

/// A synthetic frame with every channel (covariance included) as an EXR file, float32.
fn frame_exr(w: usize, h: usize) -> Vec<u8> {
    let planes = synthetic_planes(w, h, true);
    let named = planes.iter().map(|(n, p)| (n.as_str(), p.as_slice()));
    write_planes(w, h, named, SampleType::F32, Encoding::FAST_LOSSLESS).expect("encode synthetic frame")
}

fn engine(a: &Args, models: &Path) -> Result<Engine> {
    let mut config = EngineConfig::new(models);
    config.threads = a.threads;
    config.tile = a.tile;
    config.tile_v2 = a.tile_v2;
    config.device = a.device.parse().map_err(anyhow::Error::msg)?;
    let mut e = Engine::load(&config)?;
    e.warm_up()?;
    Ok(e)
}

/// A GEMM's throughput through ONNX Runtime (MLAS): G(FL)OP/s of an n×n×n product of `a`
/// and `b` by the two-input model `file` under benches/, best of `runs`.
fn gemm_ceiling<A, B>(file: &str, a: &[A], b: &[B], n: usize, threads: usize, runs: usize) -> Result<f64>
where
    A: ort::value::PrimitiveTensorElementType + Clone + std::fmt::Debug + 'static,
    B: ort::value::PrimitiveTensorElementType + Clone + std::fmt::Debug + 'static,
{
    use ort::value::TensorRef;
    let env = runtime::environment(None).map_err(anyhow::Error::msg)?;
    let model = Path::new(env!("CARGO_MANIFEST_DIR")).join("benches").join(file);
    // The engine's own session settings.
    let mut session =
        model::build_session(env, &model, model::Placement::cpu(threads)).map_err(|e| anyhow::anyhow!("{e}"))?;
    let mut best = f64::INFINITY;
    for _ in 0..runs + 1 {
        let ta = TensorRef::from_array_view(([n, n], a))?;
        let tb = TensorRef::from_array_view(([n, n], b))?;
        let t = Instant::now();
        let out = session.run(ort::inputs!["A" => ta, "B" => tb])?;
        best = best.min(t.elapsed().as_secs_f64());
        drop(out);
    }
    Ok(2.0 * (n * n * n) as f64 / best / 1e9)
}

/// Runs per GEMM ceiling: the best of several, since on a shared virtual machine a single
/// 1536³ product varies by a quarter from run to run.
fn gemm_runs(a: &Args) -> usize {
    if a.quick {
        a.runs
    } else {
        a.runs.max(8)
    }
}

/// FP32 GEMM (benches/matmul.onnx): GFLOP/s.
fn gemm_f32(n: usize, threads: usize, runs: usize) -> Result<f64> {
    let a: Vec<f32> = (0..n * n).map(|i| ((i % 97) as f32) * 0.01).collect();
    let b: Vec<f32> = (0..n * n).map(|i| ((i % 89) as f32) * 0.01).collect();
    gemm_ceiling("matmul.onnx", &a, &b, n, threads, runs)
}

/// Int8 GEMM, u8 × s8 into int32 as the int8 convolutions take it (benches/matmul-int8.onnx):
/// GOP/s, a multiply and an add counted as two operations like FP32's.
fn gemm_int8(n: usize, threads: usize, runs: usize) -> Result<f64> {
    let a: Vec<u8> = (0..n * n).map(|i| (i % 251) as u8).collect();
    let b: Vec<i8> = (0..n * n).map(|i| ((i % 241) as i32 - 120) as i8).collect();
    gemm_ceiling("matmul-int8.onnx", &a, &b, n, threads, runs)
}

/// The CPU's bf16 instructions, from /proc/cpuinfo's flags.
fn bf16_flags() -> Vec<String> {
    let flags = std::fs::read_to_string("/proc/cpuinfo").unwrap_or_default();
    let line = flags.lines().find(|l| l.starts_with("flags")).unwrap_or("");
    line.split_whitespace().filter(|f| f.contains("bf16")).map(str::to_string).collect()
}

struct EngineRun {
    decode: f64,
    preprocess: f64,
    inference: f64,
    reconstruction: f64,
    encode: f64,
    /// Wall time of `Engine::denoise` (frame in memory to denoised planes).
    denoise: f64,
    /// Wall time from EXR bytes to EXR bytes.
    total: f64,
}

/// One frame through the engine as `mcdenoise run` does it, from EXR bytes to EXR bytes.
fn engine_run(e: &mut Engine, exr: &[u8]) -> Result<EngineRun> {
    let start = Instant::now();
    let t = Instant::now();
    let f = Frame::from_exr_bytes(exr, &Limits::default())?;
    let decode = t.elapsed().as_secs_f64();
    let t = Instant::now();
    let out = e.denoise(&f, None, &mut |_| true)?;
    let denoise = t.elapsed().as_secs_f64();
    let t = Instant::now();
    let layers = [OutputLayer { prefix: "", planes: [&out.color[0], &out.color[1], &out.color[2]] }];
    let bytes = frame::write_exr(out.width, out.height, &layers)?;
    std::hint::black_box(bytes);
    Ok(EngineRun {
        decode,
        preprocess: out.timings.preprocess.as_secs_f64(),
        inference: out.timings.inference.as_secs_f64(),
        reconstruction: out.timings.reconstruction.as_secs_f64(),
        encode: t.elapsed().as_secs_f64(),
        denoise,
        total: start.elapsed().as_secs_f64(),
    })
}

fn engine_section(a: &Args, e: &mut Engine, exr: &[u8], w: usize, h: usize, gemm: f64) -> Result<Value> {
    let f = Frame::from_exr_bytes(exr, &Limits::default())?;
    let variant = e.select(&f)?;
    let flops = e.flops_per_pixel(variant).context("variant loaded")? * (w * h) as f64;
    // One run first, so that neither measurement pays ONNX Runtime's first run on these tile shapes.
    engine_run(e, exr)?;
    let mut floor = Vec::new();
    let mut runs = Vec::new();
    for _ in 0..a.runs {
        floor.push(e.inference_only(&f, variant)?.as_secs_f64());
        runs.push(engine_run(e, exr)?);
    }
    let m = |g: &dyn Fn(&EngineRun) -> f64| median(runs.iter().map(g).collect());
    let (floor_s, denoise, total) = (median(floor), m(&|r| r.denoise), m(&|r| r.total));
    eprintln!(
        "engine {w}x{h}: ORT alone {floor_s:.2} s, engine {denoise:.2} s ({:.0} %), with EXR decode and encode \
         {total:.2} s ({:.0} %)",
        100.0 * floor_s / denoise,
        100.0 * floor_s / total
    );
    Ok(json!({
        "width": w, "height": h, "variant": variant, "tile": a.tile, "tile_v2": a.tile_v2, "threads": a.threads, "runs": a.runs,
        "device": e.device().to_string(),
        // How OpenVINO was reached (`plugin` or `runtime`, src/engine/runtime.rs), where it runs.
        "openvino_via": mcdenoise::engine::runtime::openvino_route().map(|r| r.name()),
        "flops_per_frame": flops,
        "ort_alone_s": floor_s,
        "ort_alone_gflops": flops / floor_s / 1e9,
        "engine_stages_s": {
            "decode": m(&|r| r.decode), "preprocess": m(&|r| r.preprocess), "inference": m(&|r| r.inference),
            "reconstruction": m(&|r| r.reconstruction), "encode": m(&|r| r.encode),
        },
        "engine_s": denoise,
        "engine_gflops": flops / denoise / 1e9,
        "engine_vs_ort_alone": floor_s / denoise,
        "engine_vs_gemm_ceiling": flops / denoise / 1e9 / gemm,
        "engine_with_io_s": total,
        "engine_with_io_vs_ort_alone": floor_s / total,
        "ort_alone_vs_gemm_ceiling": flops / floor_s / 1e9 / gemm,
    }))
}

/// The int8 models on the same frame as the FP32 ones (`fp32`: the engine section), with the
/// int8 GEMM ceiling measured beside the FP32 one.
fn int8_section(a: &Args, models: &Path, exr: &[u8], w: usize, h: usize, n: usize, fp32: &Value) -> Result<Value> {
    let ceiling = gemm_int8(n, a.threads, gemm_runs(a))?;
    let ceiling1 = gemm_int8(n, 1, gemm_runs(a))?;
    eprintln!("int8 GEMM ceiling {n}³: {ceiling:.1} GOP/s on {} threads, {ceiling1:.1} on 1", a.threads);
    let mut e = engine(a, models)?;
    let int8 = engine_section(a, &mut e, exr, w, h, ceiling)?;
    let ratio = |key: &str| int8[key].as_f64().unwrap_or(f64::NAN) / fp32[key].as_f64().unwrap_or(f64::NAN);
    eprintln!(
        "int8 {w}x{h}: ORT alone {:.2}x FP32's time, engine {:.2}x, with EXR I/O {:.2}x",
        ratio("ort_alone_s"),
        ratio("engine_s"),
        ratio("engine_with_io_s")
    );
    Ok(json!({
        "models": models,
        "gemm_ceiling": { "n": n, "gops": ceiling, "gops_1_thread": ceiling1, "threads": a.threads },
        "engine": int8,
        "time_vs_fp32": {
            "ort_alone": ratio("ort_alone_s"), "engine": ratio("engine_s"), "engine_with_io": ratio("engine_with_io_s"),
        },
    }))
}

/// Submits `jobs` frames from `clients` concurrent clients; each client uploads, waits for
/// the job and downloads the result. Returns the wall seconds and, per job, the latency and
/// the worker's own time on it (the job's `timings`: decode, denoise, encode and the durable
/// write of the result).
async fn daemon_load(http: &HttpClient, exr: Bytes, clients: usize, jobs: usize) -> Result<(f64, Vec<(f64, f64)>)> {
    let next = std::sync::Arc::new(std::sync::atomic::AtomicUsize::new(0));
    let t0 = Instant::now();
    let mut tasks = Vec::new();
    for _ in 0..clients {
        let (http, exr, next) = (http.clone(), exr.clone(), next.clone());
        tasks.push(tokio::spawn(async move {
            let mut lat = Vec::new();
            while next.fetch_add(1, std::sync::atomic::Ordering::SeqCst) < jobs {
                let t = Instant::now();
                let h = [("content-type", "image/x-exr")];
                let (status, job) = http.json(Method::POST, "/v1/jobs", &h, body_bytes(exr.clone())).await?;
                if status != StatusCode::ACCEPTED {
                    bail!("submit: {status} {job}");
                }
                let id = job["id"].as_str().context("job id")?.to_string();
                let worker_s = loop {
                    let (_, j) =
                        http.json(Method::GET, &format!("/v1/jobs/{id}"), &[], body_bytes(Bytes::new())).await?;
                    match j["state"].as_str() {
                        Some("succeeded") => break j["timings_ms"]["total"].as_f64().context("job timings")? / 1e3,
                        Some("failed") | Some("cancelled") | Some("expired") => bail!("job {id}: {j}"),
                        _ => tokio::time::sleep(Duration::from_millis(20)).await,
                    }
                };
                let resp = http.get(&format!("/v1/jobs/{id}/result")).await?;
                if resp.status() != StatusCode::OK {
                    bail!("result: {:?}", read_json(resp).await?);
                }
                use http_body_util::BodyExt;
                let body = resp.into_body().collect().await?.to_bytes();
                std::hint::black_box(body);
                lat.push((t.elapsed().as_secs_f64(), worker_s));
            }
            Ok(lat)
        }));
    }
    let mut lat = Vec::new();
    for t in tasks {
        lat.extend(t.await??);
    }
    Ok((t0.elapsed().as_secs_f64(), lat))
}

fn daemon_section(a: &Args, e: &mut Engine) -> Result<Value> {
    let (w, h, jobs) = if a.quick { (160, 96, 4) } else { (640, 360, 16) };
    let exr = Bytes::from(frame_exr(w, h));
    let engine_s = median((0..a.runs).map(|_| engine_run(e, &exr).map(|r| r.total)).collect::<Result<Vec<_>>>()?);
    let engine_fph = 3600.0 / engine_s;
    let data = tempfile::tempdir()?;
    let rt = tokio::runtime::Builder::new_multi_thread().worker_threads(2).enable_all().build()?;
    let models = a.models.display().to_string();
    let threads = a.threads.to_string();
    let tile = a.tile.to_string();
    let tile_v2 = a.tile_v2.to_string();
    let args: Vec<String> = [
        "serve",
        "--http",
        "127.0.0.1:0",
        "--grpc",
        "127.0.0.1:0",
        "--workers",
        "1",
        "--threads-per-worker",
        &threads,
        "--tile",
        &tile,
        "--tile-v2",
        &tile_v2,
        "--models",
        &models,
        "--device",
        &a.device,
        "--log",
        "warn",
        "--data-dir",
    ]
    .iter()
    .map(|s| s.to_string())
    .chain([data.path().display().to_string()])
    .collect();
    rt.block_on(async {
        let server = Server::start(parse_serve_args(args)?).await?;
        let http = HttpClient::new(&format!("http://{}", server.http_addr), None);
        let t = Instant::now();
        while http.get("/readyz").await?.status() != StatusCode::OK {
            if t.elapsed() > Duration::from_secs(120) {
                bail!("the daemon did not become ready");
            }
            tokio::time::sleep(Duration::from_millis(50)).await;
        }
        let mut rows = Vec::new();
        for clients in [1usize, 2, 8] {
            let (wall, per_job) = daemon_load(&http, exr.clone(), clients, jobs).await?;
            let fph = 3600.0 * jobs as f64 / wall;
            let lat: Vec<f64> = per_job.iter().map(|j| j.0).collect();
            let worker_s = per_job.iter().map(|j| j.1).sum::<f64>() / jobs as f64;
            eprintln!("daemon {clients} clients: {fph:.0} frames/h (engine alone {engine_fph:.0})");
            rows.push(json!({
                "clients": clients, "jobs": jobs, "wall_s": wall, "frames_per_hour": fph,
                "vs_engine_alone": fph / engine_fph,
                "latency_p50_s": percentile(lat.clone(), 0.5), "latency_p99_s": percentile(lat, 0.99),
                // Where a frame's wall time goes: the worker's own time on it, and the rest
                // (the worker waiting for the next upload, HTTP work competing for the cores).
                "wall_per_frame_s": wall / jobs as f64,
                "worker_per_frame_s": worker_s,
            }));
        }
        server.shutdown();
        server.wait().await?;
        Ok(json!({
            "width": w, "height": h, "workers": 1, "threads_per_worker": a.threads,
            "engine_alone_s_per_frame": engine_s, "engine_alone_frames_per_hour": engine_fph, "clients": rows,
        }))
    })
}

/// Peak RSS (kB) of `mcdenoise run` on a synthetic frame, through GNU time.
fn memory_section(a: &Args, dir: &Path) -> Result<Value> {
    let sizes: &[(usize, usize, &str)] =
        if a.quick { &[(320, 180, "180p")] } else { &[(1280, 720, "720p"), (1920, 1080, "1080p"), (3840, 2160, "4K")] };
    let mut rows = Vec::new();
    for &(w, h, name) in sizes {
        let input = dir.join(format!("mem-{name}.exr"));
        std::fs::write(&input, frame_exr(w, h))?;
        let output = dir.join(format!("mem-{name}-out.exr"));
        let res = Command::new("/usr/bin/time")
            .args(["-f", "%M"])
            .arg(env!("CARGO_BIN_EXE_mcdenoise"))
            .arg("run")
            .arg(&input)
            .arg("-o")
            .arg(&output)
            .args(["--models", &a.models.display().to_string()])
            .args(["--threads", &a.threads.to_string(), "--tile", &a.tile.to_string()])
            .args(["--tile-v2", &a.tile_v2.to_string(), "--device", &a.device])
            .output()
            .context("cannot run /usr/bin/time")?;
        if !res.status.success() {
            bail!("mcdenoise run {name}: {}", String::from_utf8_lossy(&res.stderr));
        }
        let stderr = String::from_utf8_lossy(&res.stderr);
        let kb: f64 = stderr.lines().last().context("no time output")?.trim().parse()?;
        let report: Value = serde_json::from_slice(&res.stdout)?;
        // What the frame itself must occupy: every decoded plane plus the output planes.
        let planes = synthetic_planes(1, 1, true).len() + 3 * 3 * 2;
        let frame_mb = (planes * w * h * 4) as f64 / 1e6;
        eprintln!("memory {name}: peak RSS {:.0} MB", kb / 1e3);
        rows.push(json!({
            "frame": name, "width": w, "height": h, "peak_rss_mb": kb / 1e3, "frame_buffers_mb": frame_mb,
            "rss_beyond_frame_mb": kb / 1e3 - frame_mb, "total_s": report["timings_ms"]["total"].as_f64().unwrap_or(0.0) / 1e3,
        }));
        std::fs::remove_file(&input).ok();
        std::fs::remove_file(&output).ok();
    }
    Ok(Value::Array(rows))
}

fn cpu_model() -> String {
    std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("model name"))
                .map(|l| l.split(':').nth(1).unwrap_or("").trim().to_string())
        })
        .unwrap_or_default()
}

/// The 1-minute load average, to tell from the report whether other work shared the cores.
fn loadavg() -> f64 {
    std::fs::read_to_string("/proc/loadavg")
        .ok()
        .and_then(|s| s.split_whitespace().next().and_then(|v| v.parse().ok()))
        .unwrap_or(f64::NAN)
}

fn main() -> Result<()> {
    // The process as `mcdenoise` runs it: glibc's thresholds and huge pages (src/memory.rs).
    mcdenoise::memory::configure();
    let a = parse_args()?;
    let load_start = loadavg();
    let dir = a.work.clone();
    std::fs::create_dir_all(&dir)?;
    if let Some(parent) = a.out.parent() {
        std::fs::create_dir_all(parent)?;
    }
    let n = if a.quick { 256 } else { 1536 };
    let gemm = gemm_f32(n, a.threads, gemm_runs(&a))?;
    let gemm1 = gemm_f32(n, 1, gemm_runs(&a))?;
    eprintln!("GEMM ceiling {n}³: {gemm:.1} GFLOP/s on {} threads, {gemm1:.1} on 1", a.threads);

    let (w, h) = if a.quick { (320, 180) } else { (1280, 720) };
    let exr = frame_exr(w, h);
    std::fs::write(dir.join(format!("frame-{w}x{h}.exr")), &exr)?;
    let mut e = engine(&a, &a.models)?;
    let engine_json = engine_section(&a, &mut e, &exr, w, h, gemm)?;
    let daemon_json = if a.engine_only { Value::Null } else { daemon_section(&a, &mut e)? };
    drop(e);
    let memory_json = if a.engine_only { Value::Null } else { memory_section(&a, &dir)? };
    let int8_json = match &a.int8_models {
        Some(models) => int8_section(&a, models, &exr, w, h, n, &engine_json)?,
        None => Value::Null,
    };

    let report = json!({
        "machine": {
            "cpu": cpu_model(), "threads": a.threads, "ort_version": runtime::ORT_VERSION, "device": a.device,
            "loadavg_start": load_start, "loadavg_end": loadavg(),
        },
        "models": a.models,
        "gemm_ceiling": { "n": n, "gflops": gemm, "gflops_1_thread": gemm1, "threads": a.threads },
        "engine": engine_json,
        "daemon": daemon_json,
        "memory": memory_json,
        "int8": int8_json,
        "bf16": { "cpu_flags": bf16_flags() },
    });
    std::fs::write(&a.out, serde_json::to_string_pretty(&report)? + "\n")?;
    eprintln!("wrote {}", a.out.display());
    Ok(())
}
