//! The `mcdenoise` binary end to end: run, preprocess, and its errors.

use crate::common;

use std::process::Command;

use common::*;
use mcdenoise::frame::{Buffer, Frame, Limits};

fn bin() -> Command {
    Command::new(env!("CARGO_BIN_EXE_mcdenoise"))
}

fn write_frame(dir: &std::path::Path, name: &str, w: usize, h: usize, cov: bool) -> std::path::PathBuf {
    let path = dir.join(name);
    std::fs::write(&path, exr_single(w, h, &named_planes(w, h, cov), Sample::F32)).unwrap();
    path
}

#[test]
fn run_writes_the_denoised_exr_and_a_json_report() {
    let tmp = tempfile::tempdir().unwrap();
    let input = write_frame(tmp.path(), "in.exr", 40, 24, true);
    let out = tmp.path().join("out.exr");
    let res = bin()
        .args(["run", input.to_str().unwrap(), "-o", out.to_str().unwrap(), "--reference", input.to_str().unwrap()])
        .args([
            "--models",
            tiny_models().to_str().unwrap(),
            "--tile",
            "16",
            "--threads",
            "1",
            "--layers",
            "diffuse,specular",
        ])
        .output()
        .unwrap();
    assert!(res.status.success(), "{}", String::from_utf8_lossy(&res.stderr));
    let report: serde_json::Value = serde_json::from_slice(&res.stdout).unwrap();
    assert_eq!(report["variant"], "full");
    assert_eq!(report["tiles"], 6);
    for stage in ["decode", "preprocess", "inference", "reconstruction", "encode", "total"] {
        assert!(report["timings_ms"][stage].as_f64().unwrap() >= 0.0, "{stage}");
    }
    // Against itself the input is perfect; the (random) network's output is not.
    assert_eq!(report["metrics"]["input"]["relmse"], 0.0);
    assert!(report["metrics"]["output"]["relmse"].as_f64().unwrap() > 0.0);

    let frame = Frame::reference_from_exr_bytes(&std::fs::read(&out).unwrap(), &Limits::default()).unwrap();
    assert_eq!((frame.width, frame.height), (40, 24));
    assert!(frame.has(Buffer::Color) && frame.has(Buffer::Diffuse) && frame.has(Buffer::Specular));
    let leftovers: Vec<_> = std::fs::read_dir(tmp.path())
        .unwrap()
        .filter_map(|e| e.ok())
        .filter(|e| e.file_name().to_string_lossy().ends_with(".part"))
        .collect();
    assert!(leftovers.is_empty(), "temporary files left: {leftovers:?}");
}

#[test]
fn preprocess_writes_the_documented_arrays() {
    let tmp = tempfile::tempdir().unwrap();
    let input = write_frame(tmp.path(), "in.exr", 12, 9, true);
    let out = tmp.path().join("x.npz");
    let res = bin()
        .args([
            "preprocess",
            input.to_str().unwrap(),
            "-o",
            out.to_str().unwrap(),
            "--reference",
            input.to_str().unwrap(),
        ])
        .output()
        .unwrap();
    assert!(res.status.success(), "{}", String::from_utf8_lossy(&res.stderr));
    let mut npz = ndarray_npy::NpzReader::new(std::fs::File::open(&out).unwrap()).unwrap();
    let shape = |npz: &mut ndarray_npy::NpzReader<std::fs::File>, k: &str| -> Vec<usize> {
        let a: ndarray::Array3<f32> = npz.by_name(k).unwrap();
        a.shape().to_vec()
    };
    assert_eq!(shape(&mut npz, "diffuse_color"), [10, 9, 12]);
    assert_eq!(shape(&mut npz, "specular_color"), [10, 9, 12]);
    assert_eq!(shape(&mut npz, "features"), [28, 9, 12]);
    for k in ["albedo", "noisy", "diffuse_target", "specular_target", "reference"] {
        assert_eq!(shape(&mut npz, k), [3, 9, 12], "{k}");
    }
    // With itself as reference, the diffuse target is the input's own d / (a + ε).
    let color: ndarray::Array3<f32> = npz.by_name("diffuse_color").unwrap();
    let target: ndarray::Array3<f32> = npz.by_name("diffuse_target").unwrap();
    assert_eq!(color.slice(ndarray::s![0..3, .., ..]), target);

    let res = bin()
        .args(["preprocess", input.to_str().unwrap(), "-o", out.to_str().unwrap(), "--variant", "nocov"])
        .output()
        .unwrap();
    assert!(res.status.success());
    let mut npz = ndarray_npy::NpzReader::new(std::fs::File::open(&out).unwrap()).unwrap();
    assert_eq!(shape(&mut npz, "features"), [24, 9, 12]);
}

#[test]
fn bad_input_is_reported_by_name() {
    let tmp = tempfile::tempdir().unwrap();
    let planes: Vec<_> = named_planes(8, 8, false).into_iter().filter(|(n, _)| n != "normal.G").collect();
    let input = tmp.path().join("bad.exr");
    std::fs::write(&input, exr_single(8, 8, &planes, Sample::F32)).unwrap();
    let res = bin()
        .args(["run", input.to_str().unwrap(), "-o", "/dev/null", "--models", tiny_models().to_str().unwrap()])
        .output()
        .unwrap();
    assert_eq!(res.status.code(), Some(1));
    let err = String::from_utf8_lossy(&res.stderr);
    assert!(err.contains("bad.exr: invalid frame: missing channels: normal.G (the file has: "), "{err}");
}

#[test]
fn a_missing_onnx_runtime_is_a_clear_error() {
    let tmp = tempfile::tempdir().unwrap();
    let input = write_frame(tmp.path(), "in.exr", 8, 8, true);
    let res = bin()
        .args(["run", input.to_str().unwrap(), "-o", tmp.path().join("o.exr").to_str().unwrap()])
        .args(["--models", tiny_models().to_str().unwrap()])
        .env("ORT_DYLIB_PATH", tmp.path().join("nowhere/libonnxruntime.so"))
        .env("MCDENOISE_HOME", tmp.path())
        .env("HOME", tmp.path())
        .output()
        .unwrap();
    assert_eq!(res.status.code(), Some(1));
    let err = String::from_utf8_lossy(&res.stderr);
    assert!(err.contains("ONNX Runtime library not found") && err.contains("scripts/setup"), "{err}");
    assert!(!err.contains("panicked"), "{err}");
}

#[test]
fn cuda_without_the_gpu_build_of_onnx_runtime_is_a_clear_error() {
    // Where the library is the GPU build, `cuda` would run (or fail for want of a GPU): this
    // test is about the CPU build, which CI and `scripts/setup` install.
    mcdenoise::engine::runtime::environment(None).expect("the ONNX Runtime library");
    if mcdenoise::engine::device::cuda_provider_available() {
        eprintln!("skipped: this ONNX Runtime library has the CUDA execution provider");
        return;
    }
    let tmp = tempfile::tempdir().unwrap();
    let input = write_frame(tmp.path(), "in.exr", 16, 16, true);
    let out = tmp.path().join("o.exr");
    let run = |device: &str| {
        bin()
            .args(["run", input.to_str().unwrap(), "-o", out.to_str().unwrap()])
            .args(["--models", tiny_models().to_str().unwrap(), "--threads", "1", "--device", device])
            .output()
            .unwrap()
    };
    let res = run("cuda:1");
    assert_eq!(res.status.code(), Some(1));
    let err = String::from_utf8_lossy(&res.stderr);
    for part in ["--device cuda:1", "has no CUDA execution provider", "onnxruntime-gpu", "--device cpu"] {
        assert!(err.contains(part), "{part}: {err}");
    }
    assert!(!err.contains("panicked") && !out.exists(), "{err}");
    // `auto` falls back to the CPU (through OpenVINO where it pays: AMX, or AVX512-BF16 on AMD) and the
    // report says where it ran.
    let res = run("auto");
    assert!(res.status.success(), "{}", String::from_utf8_lossy(&res.stderr));
    let report: serde_json::Value = serde_json::from_slice(&res.stdout).unwrap();
    let cpu = if mcdenoise::engine::device::cpu_prefers_openvino() { "openvino" } else { "cpu" };
    assert_eq!(report["device"], cpu);
    let res = run("gpu");
    assert_eq!(res.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&res.stderr).contains("unknown device `gpu`"));
    // The daemon stops at start-up with the same message, before it takes a job.
    let res = bin()
        .args(["serve", "--models", tiny_models().to_str().unwrap(), "--data-dir"])
        .arg(tmp.path().join("data"))
        .args(["--http", "127.0.0.1:0", "--grpc", "127.0.0.1:0", "--device", "cuda"])
        .output()
        .unwrap();
    assert_eq!(res.status.code(), Some(1));
    let err = String::from_utf8_lossy(&res.stderr);
    assert!(err.contains("--device cuda:0: the ONNX Runtime library") && err.contains("onnxruntime-gpu"), "{err}");
}

#[test]
fn openvino_runs_the_shipped_network_as_the_cpu_provider_does() {
    // `scripts/setup` installs OpenVINO's plugin and runtime beside the library; on a CPU
    // with native bfloat16 they compute in it, elsewhere in float32: either way the metrics
    // stay within 2 %, through the plugin (an Intel CPU) or the runtime directly (any CPU,
    // and what `MCDENOISE_OPENVINO_VIA=runtime` takes on an Intel one).
    let fixtures = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures/frames");
    let models = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("models");
    let tmp = tempfile::tempdir().unwrap();
    let run_via = |device: &str, plugin: Option<&str>, via: &str| {
        let mut cmd = bin();
        cmd.args(["run", fixtures.join("cornell-spp8.exr").to_str().unwrap()])
            .args(["-o", tmp.path().join(format!("{device}.exr")).to_str().unwrap()])
            .args(["--reference", fixtures.join("cornell-ref.exr").to_str().unwrap()])
            .args(["--models", models.to_str().unwrap(), "--threads", "2", "--device", device])
            .env("MCDENOISE_OPENVINO_VIA", via);
        if let Some(p) = plugin {
            cmd.env("MCDENOISE_OPENVINO_PLUGIN", p);
        }
        cmd.output().unwrap()
    };
    let run = |device: &str, plugin: Option<&str>| run_via(device, plugin, "auto");
    let report = |res: &std::process::Output| -> serde_json::Value {
        assert!(res.status.success(), "{}", String::from_utf8_lossy(&res.stderr));
        serde_json::from_slice(&res.stdout).unwrap()
    };
    let cpu = report(&run("cpu", None));
    for via in ["auto", "runtime"] {
        let openvino = report(&run_via("openvino", None, via));
        assert_eq!((cpu["device"].as_str(), openvino["device"].as_str()), (Some("cpu"), Some("openvino")));
        assert!(cpu["openvino_via"].is_null(), "{cpu}");
        // `auto` takes the plugin on an Intel CPU and the runtime elsewhere; `runtime` always.
        let taken = openvino["openvino_via"].as_str().unwrap_or_default();
        assert!(if via == "runtime" { taken == "runtime" } else { ["plugin", "runtime"].contains(&taken) }, "{taken}");
        for metric in ["relmse", "dssim"] {
            let (a, b) = (
                cpu["metrics"]["output"][metric].as_f64().unwrap(),
                openvino["metrics"]["output"][metric].as_f64().unwrap(),
            );
            assert!((b / a - 1.0).abs() < 0.02, "{via}, {metric}: cpu {a}, openvino {b}");
            assert!(b < 0.5 * openvino["metrics"]["input"][metric].as_f64().unwrap(), "{via}, {metric}: {b}");
        }
    }
    // A route that is not one is named.
    let res = run_via("openvino", None, "direct");
    assert_eq!(res.status.code(), Some(1));
    let err = String::from_utf8_lossy(&res.stderr);
    assert!(err.contains("MCDENOISE_OPENVINO_VIA is `direct`, expected `plugin`, `runtime` or `auto`"), "{err}");
    // Without the plugin: `openvino` is an error naming where it looked, `auto` the CPU provider.
    let missing = tmp.path().join("nowhere/libonnxruntime_providers_openvino_plugin.so");
    let res = run("openvino", missing.to_str());
    assert_eq!(res.status.code(), Some(1));
    let err = String::from_utf8_lossy(&res.stderr);
    for part in
        ["--device openvino: OpenVINO's execution provider plugin not found", missing.to_str().unwrap(), "--device cpu"]
    {
        assert!(err.contains(part), "{part}: {err}");
    }
    assert_eq!(report(&run("auto", missing.to_str()))["device"], "cpu");
    // With it, `auto` takes OpenVINO exactly where its bfloat16 pays on this CPU.
    let expected = if mcdenoise::engine::device::cpu_prefers_openvino() { "openvino" } else { "cpu" };
    assert_eq!(report(&run("auto", None))["device"], expected);
}

#[test]
fn a_models_directory_not_found_is_named_as_resolved() {
    let tmp = tempfile::tempdir().unwrap();
    let res = bin()
        .current_dir(tmp.path())
        .args(["serve", "--models", "nosuch", "--data-dir", "data", "--http", "127.0.0.1:0", "--grpc", "127.0.0.1:0"])
        .output()
        .unwrap();
    assert_eq!(res.status.code(), Some(1));
    let err = String::from_utf8_lossy(&res.stderr);
    let resolved = tmp.path().canonicalize().unwrap().join("nosuch");
    assert!(
        err.contains(&format!("no such directory ({} from the current directory)", resolved.display()))
            || err.contains(&format!(
                "no such directory ({} from the current directory)",
                tmp.path().join("nosuch").display()
            )),
        "{err}"
    );
    assert!(err.contains("models/"), "{err}");
}

#[test]
fn a_bad_config_value_is_reported_with_its_file_and_key_once() {
    let tmp = tempfile::tempdir().unwrap();
    let config = tmp.path().join("serve.toml");
    std::fs::write(&config, "queue-capacity = \"abc\"\n").unwrap();
    let res = bin().args(["serve", "--config", config.to_str().unwrap()]).output().unwrap();
    assert_ne!(res.status.code(), Some(0));
    let err = String::from_utf8_lossy(&res.stderr);
    assert!(
        err.contains(&format!("config file {}, key queue-capacity: invalid value 'abc'", config.display())),
        "{err}"
    );
    assert_eq!(err.matches("error:").count(), 1, "{err}");
}

#[test]
fn every_serve_option_is_documented_in_the_api_reference() {
    use clap::CommandFactory;
    let doc = std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/docs/api.md")).unwrap();
    let cmd = mcdenoise::config::ServeArgs::command();
    let mut checked = 0;
    for arg in cmd.get_arguments().filter(|a| !a.is_hide_set()) {
        let Some(long) = arg.get_long() else { continue };
        assert!(doc.contains(&format!("`--{long}")), "--{long} is missing from docs/api.md");
        if let Some(env) = arg.get_env() {
            let env = env.to_string_lossy();
            assert!(doc.contains(env.as_ref()), "{env} is missing from docs/api.md");
        }
        checked += 1;
    }
    assert!(checked >= 20, "{checked}");
}

/// `mcdenoise run INPUT -o OUTPUT` with the tiny models, 64-pixel tiles, one thread and
/// `extra`; fails the test unless it succeeds.
fn run_ok(input: &std::path::Path, output: &std::path::Path, extra: &[&str]) {
    let res = bin()
        .args(["run", input.to_str().unwrap(), "-o", output.to_str().unwrap()])
        .args(["--models", tiny_models().to_str().unwrap(), "--tile", "64", "--threads", "1"])
        .args(extra)
        .output()
        .unwrap();
    assert!(res.status.success(), "{}", String::from_utf8_lossy(&res.stderr));
}

#[test]
fn run_io_binding_is_reported_and_changes_no_pixel() {
    // The contract-v2 fixtures, in tiles of several shapes; `auto` leaves the binding off,
    // `on` uses ONNX Runtime's CPU memory for the bound tensors.
    let tmp = tempfile::tempdir().unwrap();
    let input = write_frame(tmp.path(), "in.exr", 70, 50, true);
    let v2 = tiny_models().with_file_name("tiny-v2");
    let run = |binding: &str| {
        let out = tmp.path().join(format!("out-{binding}.exr"));
        let res = bin()
            .args(["run", input.to_str().unwrap(), "-o", out.to_str().unwrap(), "--models", v2.to_str().unwrap()])
            .args(["--tile-v2", "32", "--threads", "1", "--io-binding", binding])
            .output()
            .unwrap();
        assert!(res.status.success(), "{}", String::from_utf8_lossy(&res.stderr));
        let report: serde_json::Value = serde_json::from_slice(&res.stdout).unwrap();
        let frame = Frame::reference_from_exr_bytes(&std::fs::read(out).unwrap(), &Limits::default()).unwrap();
        (report["io_binding"].as_bool().unwrap(), report["tiles"].as_u64().unwrap(), frame.color())
    };
    let (on, off, auto) = (run("on"), run("off"), run("auto"));
    assert_eq!((on.0, off.0, auto.0), (true, false, false));
    assert!(on.1 >= 4, "{} tiles", on.1);
    assert!(on.2 == off.2 && off.2 == auto.2, "the outputs differ");
    // Contract-v1 pairs run without it, whatever is asked.
    let out = tmp.path().join("out-v1.exr");
    let res = bin()
        .args([
            "run",
            input.to_str().unwrap(),
            "-o",
            out.to_str().unwrap(),
            "--models",
            tiny_models().to_str().unwrap(),
        ])
        .args(["--threads", "1", "--io-binding", "on"])
        .output()
        .unwrap();
    assert!(res.status.success(), "{}", String::from_utf8_lossy(&res.stderr));
    let report: serde_json::Value = serde_json::from_slice(&res.stdout).unwrap();
    assert_eq!((report["contract"].as_u64(), report["io_binding"].as_bool()), (Some(1), Some(false)));
    let res = bin().args(["run", "x.exr", "-o", "y.exr", "--io-binding", "gpu"]).output().unwrap();
    let stderr = String::from_utf8_lossy(&res.stderr);
    assert!(!res.status.success() && stderr.contains("--io-binding") && stderr.contains("on"), "{stderr}");
}

#[test]
fn run_keeps_overscan_attributes_alpha_and_with_all_every_aov() {
    // A 256×256 display window rendered with 8 pixels of overscan (data window −8..263),
    // anamorphic pixels; and the same image without the overscan.
    let tmp = tempfile::tempdir().unwrap();
    let display = exr::prelude::IntegerBounds::from_dimensions((256, 256));
    let overscan = Placement { origin: (-8, -8), display, pixel_aspect: 2.0, ..Placement::plain(272, 272) };
    let input = tmp.path().join("overscan.exr");
    std::fs::write(&input, overscan_frame(-8, -8, 272, 272, &overscan)).unwrap();
    let plain = tmp.path().join("plain.exr");
    std::fs::write(&plain, overscan_frame(0, 0, 256, 256, &Placement::plain(256, 256))).unwrap();
    let (out, plain_out) = (tmp.path().join("out.exr"), tmp.path().join("plain-out.exr"));
    run_ok(&input, &out, &["--layers", "all", "--fireflies", "off"]);
    run_ok(&plain, &plain_out, &["--fireflies", "off"]);

    let result = check_carried(&std::fs::read(&input).unwrap(), &std::fs::read(&out).unwrap(), &[]);
    assert_eq!(result.layer_data[0].attributes.layer_position, exr::prelude::Vec2(-8, -8));
    assert_eq!(result.attributes.display_window, display);
    // Without `all`, the alpha only; with it, the fixture's channels too.
    let plain_result = read_exr(&std::fs::read(&plain_out).unwrap());
    assert_eq!(channel_names(&plain_result), ["A", "B", "G", "R"]);
    let plain_input = read_exr(&std::fs::read(&plain).unwrap());
    let alpha = |image: &exr::prelude::Image<_>| bits(&channel_of(image, "A").sample_data);
    assert!(alpha(&plain_result) == alpha(&plain_input), "the alpha is carried bit for bit");
    let names = channel_names(&result);
    assert!(names.len() > 20 && EXTRA_CHANNELS.iter().all(|c| names.contains(&c.to_string())), "{names:?}");
    // The denoised image is in place: where the two overlap, away from the edges (which the
    // overscan moves), the display window's pixels match.
    for c in ["R", "G", "B"] {
        let (a, b) = (samples_of(&result, c), samples_of(&plain_result, c));
        let inner = |x: usize, y: usize| (24..232).contains(&x) && (24..232).contains(&y);
        let (got, want): (Vec<f32>, Vec<f32>) = (0..256 * 256)
            .filter(|i| inner(i % 256, i / 256))
            .map(|i| (a[(i / 256 + 8) * 272 + i % 256 + 8], b[i]))
            .unzip();
        assert!(max_rel_diff(&got, &want) < 1e-4, "{c}: {}", max_rel_diff(&got, &want));
    }
}

#[test]
fn run_gives_the_same_pixels_wherever_the_data_window_lies() {
    // Odd sizes and origins: the data window moves, the pixels do not change.
    let tmp = tempfile::tempdir().unwrap();
    let (w, h) = (97, 61);
    let placed = Placement {
        origin: (-3, 5),
        display: exr::prelude::IntegerBounds::new((-1, 0), (91, 70)),
        ..Placement::plain(w, h)
    };
    let mut outputs = Vec::new();
    for (name, placement) in [("placed", placed), ("origin", Placement::plain(w, h))] {
        let input = tmp.path().join(format!("{name}.exr"));
        std::fs::write(&input, overscan_frame(5, -2, w, h, &placement)).unwrap();
        let out = tmp.path().join(format!("{name}-out.exr"));
        run_ok(&input, &out, &["--layers", "diffuse,all"]);
        let result = check_carried(&std::fs::read(&input).unwrap(), &std::fs::read(&out).unwrap(), &DIFFUSE);
        assert_eq!(
            (result.layer_data[0].attributes.layer_position, result.attributes.display_window),
            (exr::prelude::Vec2(placement.origin.0, placement.origin.1), placement.display)
        );
        outputs.push(result);
    }
    for c in ["R", "G", "B", "diffuse.R", "diffuse.G", "diffuse.B"] {
        assert!(samples_of(&outputs[0], c) == samples_of(&outputs[1], c), "{c}");
    }
}

const DIFFUSE: [&str; 3] = ["diffuse.R", "diffuse.G", "diffuse.B"];

#[test]
fn run_reads_renderer_names_through_the_channel_map_given() {
    let tmp = tempfile::tempdir().unwrap();
    let (w, h) = (24, 16);
    // The canonical frame with every buffer renamed `my_<name>`: no preset knows it.
    let renamed: Vec<(String, Vec<f32>)> =
        named_planes(w, h, false).into_iter().map(|(n, p)| (format!("my_{n}"), p)).collect();
    let input = tmp.path().join("studio.exr");
    std::fs::write(&input, exr_single(w, h, &renamed, Sample::F32)).unwrap();
    let (canonical, twin) = (write_frame(tmp.path(), "twin.exr", w, h, false), tmp.path().join("twin.out.exr"));
    run_ok(&canonical, &twin, &[]);
    let out = tmp.path().join("studio.out.exr");
    let mut map =
        "diffuse=my_diffuse; specular=my_specular; albedo=my_albedo; normal=my_normal; depth=my_depth".to_string();
    for v in ["diffuse", "specular", "albedo", "normal", "depth"] {
        map.push_str(&format!("; variances.{v}Variance=my_{v}Variance"));
    }
    run_ok(&input, &out, &["--channel-map", &map]);
    let read =
        |p: &std::path::Path| Frame::reference_from_exr_bytes(&std::fs::read(p).unwrap(), &Limits::default()).unwrap();
    let (a, b) = (read(&out), read(&twin));
    for c in 0..3 {
        let diff = max_rel_diff(&a.color()[c], &b.color()[c]);
        assert!(diff < 1e-5, "channel {c}: {diff}");
    }

    for (map, says) in [
        ("auto", "missing channels"),
        ("vray", "channel map `vray` (V-Ray): write the AOVs it lacks"),
        ("houdini", "unknown channel map `houdini` (expected auto, arnold, renderman, karma, vray, redshift"),
    ] {
        let res = bin()
            .args(["run", input.to_str().unwrap(), "-o", "/dev/null", "--models", tiny_models().to_str().unwrap()])
            .args(["--channel-map", map])
            .output()
            .unwrap();
        assert_eq!(res.status.code(), Some(1), "{map}");
        let err = String::from_utf8_lossy(&res.stderr);
        assert!(err.contains(says), "{map}: {err}");
    }
}

#[test]
fn run_reports_variances_of_the_samples_and_with_auto_scales_them_back() {
    // The cornell fixture with every variance 64 times too large: the samples' variance at
    // 64 spp where the variance of the pixel's mean belongs.
    let cornell = fixture("cornell-spp8.exr");
    let size = (cornell.width, cornell.height);
    let planes: Vec<(String, Vec<f32>)> = cornell
        .planes
        .into_iter()
        .map(|(name, plane)| {
            let k = if name.contains("Variance") { 64.0 } else { 1.0 };
            (name, plane.into_iter().map(|v| v * k).collect())
        })
        .collect();
    assert!(planes.iter().filter(|(n, _)| n.contains("Variance")).count() >= 6);
    let tmp = tempfile::tempdir().unwrap();
    let input = tmp.path().join("in.exr");
    std::fs::write(&input, exr_single(size.0, size.1, &planes, Sample::F32)).unwrap();
    let models = concat!(env!("CARGO_MANIFEST_DIR"), "/models");
    let run = |check: &str| -> serde_json::Value {
        let out = tmp.path().join(format!("out-{check}.exr"));
        let res = bin()
            .args(["run", input.to_str().unwrap(), "-o", out.to_str().unwrap(), "--models", models])
            .args(["--threads", "1", "--variance-check", check])
            .output()
            .unwrap();
        assert!(res.status.success(), "{}", String::from_utf8_lossy(&res.stderr));
        serde_json::from_slice(&res.stdout).unwrap()
    };
    let (auto, warn, off) = (run("auto"), run("warn"), run("off"));
    assert_eq!((auto["variance_check"].as_str(), off["variance_check"].as_str()), (Some("auto"), Some("off")));
    let said = |report: &serde_json::Value, what: &str| {
        report["warnings"].as_array().unwrap().iter().any(|w| {
            let w = w.as_str().unwrap();
            w.contains("variance of the pixel's mean") && w.contains(what)
        })
    };
    assert!(said(&auto, "was scaled by"), "{auto}");
    assert!(said(&warn, "--variance-check auto scales them"), "{warn}");
    assert!(off["warnings"].as_array().unwrap().is_empty(), "{off}");
    let res = bin().args(["run", "x.exr", "-o", "y.exr", "--variance-check", "maybe"]).output().unwrap();
    let stderr = String::from_utf8_lossy(&res.stderr);
    assert!(!res.status.success() && stderr.contains("--variance-check") && stderr.contains("auto"), "{stderr}");
}
