//! The offline commands: denoise one file, or write the preprocessed tensors of one file
//! for training.

use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::{bail, Context, Result};
use clap::Args;
use ndarray::{Array0, Array3};
use serde_json::json;

use crate::config::{AlbedoArgs, FireflyArgs, VarianceArgs};
use crate::engine::{self, preprocess, Engine, EngineConfig, FeatureSet, ModelLoading, Rect, Variant, EPS};
use crate::frame::{Buffer, ChannelMaps, Frame, Limits, Plane, PlaneRef};
use crate::jobs::Layer;
use crate::pipeline::{self, Failure, Input};
use crate::quality::Metrics;

/// Options shared by the commands that read frames.
#[derive(Args, Debug, Clone)]
pub struct FrameArgs {
    /// Largest accepted frame, in pixels.
    #[arg(long, env = "MCDENOISE_MAX_PIXELS", default_value_t = Limits::default().max_pixels)]
    pub max_pixels: u64,
}

impl FrameArgs {
    fn limits(&self) -> Limits {
        Limits { max_pixels: self.max_pixels }
    }
}

/// Which model variant to use: `auto` (`beauty` for a frame without the diffuse/specular
/// split when `beauty` is loaded, `full` if the frame has covariance and `full` is loaded,
/// else `nocov`) or the name of a loaded variant (`full`, `nocov`, `beauty`, `lin2020`, ...).
#[derive(Clone, Copy, Debug, Default)]
pub struct VariantArg(Option<Variant>);

impl VariantArg {
    fn resolve(self) -> Option<Variant> {
        self.0
    }
}

impl std::str::FromStr for VariantArg {
    type Err = String;

    fn from_str(s: &str) -> Result<VariantArg, String> {
        if s == "auto" {
            return Ok(VariantArg(None));
        }
        Variant::parse(s).map(|v| VariantArg(Some(v))).ok_or_else(|| {
            format!(
                "`{s}` is not a variant name (auto, or a directory name of up to {} letters, digits, _, -, .)",
                Variant::MAX_LEN
            )
        })
    }
}

impl std::fmt::Display for VariantArg {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self.0 {
            None => f.write_str("auto"),
            Some(v) => f.write_str(v.name()),
        }
    }
}

#[derive(Args, Debug)]
pub struct RunArgs {
    /// Noisy frame (multi-layer OpenEXR, see docs/frame-layout.md).
    pub input: PathBuf,
    /// Where to write the denoised EXR.
    #[arg(short, long)]
    pub output: PathBuf,
    /// Reference frame: prints RelMSE, DSSIM, PSNR and SMAPE of input and output.
    #[arg(long)]
    pub reference: Option<PathBuf>,
    /// Directory with the model variants (`full/`, `nocov/`, ...). Every variant there is
    /// found, but only the networks of the one the frame is denoised with are loaded.
    #[arg(long, env = "MCDENOISE_MODELS", default_value = "models")]
    pub models: PathBuf,
    /// Tile side in pixels (0: whole frame at once).
    #[arg(long, env = "MCDENOISE_TILE", default_value_t = 256)]
    pub tile: usize,
    /// Tile side for contract-v2 (multi-scale) models, whose halo is wider (0: whole frame).
    #[arg(long, env = "MCDENOISE_TILE_V2", default_value_t = engine::DEFAULT_TILE_V2)]
    pub tile_v2: usize,
    /// Largest region (a tile with its halo) the networks run on, in pixels: larger frames
    /// are cut into more, smaller tiles, which bounds the working memory. Default: 688128
    /// (896 × 768); with `--device openvino` 540000 through its plugin (Intel CPUs),
    /// 576000 through its runtime (others).
    #[arg(long, env = "MCDENOISE_REGION_PIXELS")]
    pub region_pixels: Option<usize>,
    /// Threads for inference and processing (default: all cores).
    #[arg(long, env = "MCDENOISE_THREADS")]
    pub threads: Option<usize>,
    /// Extra layers to write besides R,G,B (and the input's alpha, always kept): `diffuse`,
    /// `specular` (the denoised components), `all` (every other channel of the input,
    /// unchanged); comma-separated, combinable.
    #[arg(long, value_delimiter = ',')]
    pub layers: Vec<String>,
    /// Model variant: `auto`, or the name of a loaded variant (`full`, `nocov`, `beauty`, `lin2020`, ...).
    #[arg(long, default_value_t)]
    pub variant: VariantArg,
    #[command(flatten)]
    pub fireflies: FireflyArgs,
    #[command(flatten)]
    pub albedo: AlbedoArgs,
    #[command(flatten)]
    pub variances: VarianceArgs,
    /// How the renderer's AOV names are read: `auto` (canonical names, Blender Cycles'
    /// passes, then every shipped preset), a preset's name (`arnold`, `renderman`,
    /// `karma`, `vray`, `redshift`), or the frame's own map as `key=AOVs` pairs separated
    /// by `;` (docs/frame-layout.md).
    #[arg(long, default_value = "auto")]
    pub channel_map: String,
    /// Path of libonnxruntime.so (default: searched for; see `scripts/setup`).
    #[arg(long, env = "ORT_DYLIB_PATH")]
    pub ort_library: Option<PathBuf>,
    /// Where the networks run: `cpu` (ONNX Runtime's CPU provider), `openvino` (the CPU
    /// through OpenVINO, in bfloat16 where the CPU has it: its ONNX Runtime plugin on Intel
    /// CPUs, its runtime directly on others), `cuda` or `cuda:N` (ONNX Runtime's CUDA
    /// execution provider, from the GPU build of ONNX Runtime), or `auto`: CUDA where
    /// available, else `openvino` on a CPU where its bfloat16 is the faster (AMX, or
    /// AVX512-BF16 on AMD), else `cpu`.
    #[arg(long, env = "MCDENOISE_DEVICE", default_value = "auto", value_parser = parse_device)]
    pub device: engine::Device,
    /// Where contract-v2 kernels are applied: `engine` (the engine's own code, on the CPU),
    /// `graph` (inside the network's graph, `model-recon.onnx`, on the device the networks
    /// run on), or `auto` (`graph` on a GPU where the variant has that file, else `engine`).
    #[arg(long, env = "MCDENOISE_RECONSTRUCTION", default_value = "auto", value_parser = parse_reconstruction)]
    pub reconstruction: engine::Reconstruction,
    /// What contract-v2 networks compute in: `fp32`, `fp16` (the network in half precision,
    /// `model-recon-fp16.onnx`, its reconstruction in the graph), or `auto` (`fp16` on a GPU
    /// where the variant has that file, else `fp32`).
    #[arg(long, env = "MCDENOISE_PRECISION", default_value = "auto", value_parser = parse_precision)]
    pub precision: engine::Precision,
    /// ONNX Runtime's I/O binding for contract-v2 networks: `on` (the region's tensors in
    /// buffers ONNX Runtime allocated once per region shape, page-locked host memory on a
    /// GPU), `off`, or `auto` (`off` for now: with several workers on a GPU the binding failed).
    #[arg(long, env = "MCDENOISE_IO_BINDING", value_enum, default_value_t)]
    pub io_binding: engine::IoBinding,
    #[command(flatten)]
    pub frame: FrameArgs,
}

/// clap's parser for `--device` ([`engine::Device`]).
pub fn parse_device(s: &str) -> std::result::Result<engine::Device, String> {
    s.parse()
}

/// clap's parser for `--reconstruction` ([`engine::Reconstruction`]).
pub fn parse_reconstruction(s: &str) -> std::result::Result<engine::Reconstruction, String> {
    s.parse()
}

/// clap's parser for `--precision` ([`engine::Precision`]).
pub fn parse_precision(s: &str) -> std::result::Result<engine::Precision, String> {
    s.parse()
}

#[derive(Args, Debug)]
pub struct PreprocessArgs {
    /// Noisy frame.
    pub input: PathBuf,
    /// Output `.npz` (float32 arrays; keys in docs/frame-layout.md).
    #[arg(short, long)]
    pub output: PathBuf,
    /// Reference frame: adds the training targets.
    #[arg(long)]
    pub reference: Option<PathBuf>,
    /// Feature set: `auto` (`full` if the frame has covariance, else `nocov`), `full`, `nocov` or `beauty` (the `nocov` inputs of the frame as the `beauty` variant takes it: the beauty in the diffuse slot, no variances).
    #[arg(long, default_value_t)]
    pub variant: VariantArg,
    /// The inputs are those `mcdenoise run` gives the networks, fireflies handled alike.
    #[command(flatten)]
    pub fireflies: FireflyArgs,
    /// And the albedo prefiltered alike.
    #[command(flatten)]
    pub albedo: AlbedoArgs,
    /// And the variances checked alike.
    #[command(flatten)]
    pub variances: VarianceArgs,
    #[command(flatten)]
    pub frame: FrameArgs,
}

fn read(path: &Path, limits: &Limits, reference: bool) -> Result<Frame> {
    let which = if reference { Input::Reference } else { Input::Frame };
    pipeline::decode(path, which, limits).map_err(|e| pipeline_error(e, path, Some(path)))
}

fn check_same_size(frame: &Frame, reference: &Frame) -> Result<()> {
    Ok(pipeline::check_same_size((frame.width, frame.height), (reference.width, reference.height))?)
}

fn ms(t: Instant) -> f64 {
    t.elapsed().as_secs_f64() * 1e3
}

/// Writes a file atomically ([`crate::atomic`]).
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    crate::atomic::write(path, bytes).with_context(|| format!("cannot write {}", path.display()))
}

/// `mcdenoise run`: denoise one frame, print a JSON report on stdout.
pub fn run(args: RunArgs) -> Result<()> {
    let total = Instant::now();
    let layers =
        args.layers.iter().map(|l| l.parse::<Layer>().map_err(anyhow::Error::msg)).collect::<Result<Vec<_>>>()?;
    let channel_maps = ChannelMaps::default().choose(&args.channel_map).map_err(anyhow::Error::msg)?;
    let mut config = EngineConfig::new(&args.models);
    config.tile = args.tile;
    config.tile_v2 = args.tile_v2;
    config.region_pixels = args.region_pixels;
    if let Some(t) = args.threads {
        config.threads = t;
    }
    config.ort_library = args.ort_library.clone();
    config.device = args.device;
    config.reconstruction = args.reconstruction;
    config.precision = args.precision;
    config.io_binding = args.io_binding;
    config.albedo_prefilter = args.albedo.albedo_prefilter;
    // One frame: only the variant it is denoised with is worth its sessions.
    config.loading = ModelLoading::OnDemand;

    let t = Instant::now();
    let mut engine = Engine::load(&config)?;
    let load_ms = ms(t);

    let fireflies = args.fireflies.settings();
    let request = pipeline::Request {
        frame: &args.input,
        reference: args.reference.as_deref(),
        variant: args.variant.resolve(),
        fireflies,
        variance_check: args.variances.variance_check,
        layers: &layers,
        limits: args.frame.limits(),
        channel_maps,
        keep_colors: false,
    };
    let out = pipeline::run(&mut engine, &request, &mut |p| {
        tracing::debug!(tile = p.tiles_done, of = p.tiles_total, "tile done");
        true
    })
    .map_err(|e| pipeline_error(e, &args.input, args.reference.as_deref()))?;

    let t = Instant::now();
    write_atomic(&args.output, &out.encoded)?;
    let mut timings = out.timings;
    timings.encode += ms(t);
    timings.total = ms(total);
    let flops = engine.flops_per_pixel(out.variant).unwrap_or(0.0);
    let used = engine.models().into_iter().find(|m| m.variant == out.variant);
    let contract = used.map_or(0, |m| m.contract);
    let reconstruction = match used.map(|m| m.outputs) {
        Some(engine::Outputs::Filtered) => engine::Reconstruction::Graph,
        _ => engine::Reconstruction::Engine,
    };
    eprintln!("denoised {} with variant `{}` (contract {contract})", args.input.display(), out.variant);
    let inference_s = (timings.inference / 1e3).max(1e-9);
    let report = json!({
        "input": args.input,
        "output": args.output,
        "width": out.width,
        "height": out.height,
        "variant": out.variant,
        "contract": contract,
        "tiles": out.tiles,
        // The network in three stages (front and back per core, middle over the frame).
        "stages": out.staged,
        "tile": if contract == 2 { args.tile_v2 } else { args.tile },
        "reconstruction": reconstruction.to_string(),
        "precision": used.map_or(engine::Precision::Fp32, |m| m.precision).name(),
        // Contract-v1 pairs run without it.
        "io_binding": contract == 2 && config.io_binding.enabled(),
        "threads": config.threads,
        "device": engine.device().to_string(),
        // With `openvino`, how OpenVINO was reached: `plugin` (ONNX Runtime's, Intel CPUs) or
        // `runtime` (OpenVINO's own, driven directly); null on other devices.
        "openvino_via": engine::runtime::openvino_route()
            .filter(|_| engine.device() == engine::Device::OpenVino)
            .map(|r| r.name()),
        "flops_per_pixel": flops,
        "sanitized": out.sanitized,
        "missing_variances": out.missing_variances,
        "warnings": out.warnings,
        "fireflies": {
            "mode": fireflies.mode,
            "strength": fireflies.strength,
            "handled": out.fireflies.total(),
            "by_component": out.fireflies,
        },
        "albedo_prefilter": config.albedo_prefilter,
        "variance_check": args.variances.variance_check,
        "timings_ms": {
            // Found at load, the used variant's networks created on first use.
            "load_models": load_ms + engine.loaded_on_demand().as_secs_f64() * 1e3,
            "decode": timings.decode,
            "fireflies": out.fireflies_ms,
            "preprocess": timings.preprocess - out.fireflies_ms,
            "inference": timings.inference,
            "reconstruction": timings.reconstruction,
            "encode": timings.encode,
            "total": timings.total,
        },
        "inference_gflops_per_s": flops * (out.width * out.height) as f64 / inference_s / 1e9,
        "metrics": out.metrics,
    });
    println!("{}", serde_json::to_string_pretty(&report)?);
    Ok(())
}

/// A pipeline failure as the command reports it: with the file it concerns.
fn pipeline_error(e: pipeline::Failure, input: &Path, reference: Option<&Path>) -> anyhow::Error {
    let path = |which: Input| match which {
        Input::Frame => input.display().to_string(),
        Input::Reference => reference.map(|p| p.display().to_string()).unwrap_or_default(),
    };
    match e {
        Failure::Read { which, error } => anyhow::Error::new(error).context(format!("cannot read {}", path(which))),
        Failure::Invalid { which, error } => {
            anyhow::Error::new(error).context(format!("{}: invalid frame", path(which)))
        }
        other => other.into(),
    }
}

/// `mcdenoise preprocess`: the network inputs (and training targets) of one frame as `.npz`.
pub fn preprocess(args: PreprocessArgs) -> Result<()> {
    let limits = args.frame.limits();
    let mut frame = read(&args.input, &limits, false)?;
    if let Some(scale) = engine::variance::check(&mut frame, args.variances.variance_check) {
        eprintln!("{}: {}", args.input.display(), scale.warning());
    }
    let reference = args.reference.as_deref().map(|p| read(p, &limits, true)).transpose()?;
    if let Some(r) = &reference {
        check_same_size(&frame, r)?;
    }
    let variant = args.variant.resolve();
    let set = match variant {
        Some(Variant::Full) if !frame.has(Buffer::Covariance) => {
            bail!("{}: --variant full needs a `covariance` channel", args.input.display())
        }
        Some(Variant::Full) => FeatureSet::Full,
        Some(Variant::Nocov) | Some(Variant::Beauty) => FeatureSet::Nocov,
        Some(v) => bail!(
            "--variant {v}: `preprocess` writes the `full`, `nocov` or `beauty` inputs (auto, full, nocov or beauty)"
        ),
        None if frame.has(Buffer::Covariance) => FeatureSet::Full,
        None => FeatureSet::Nocov,
    };
    if set == FeatureSet::Nocov {
        frame.remove(Buffer::Covariance);
    }
    let beauty = variant == Some(Variant::Beauty);
    let fields = variant.is_none_or(engine::firefly_fields);
    let (handled, report) = engine::handle_fireflies(&frame, args.fireflies.settings(), fields);
    if let Some(handled) = handled {
        frame = handled;
    }
    if let Some(prepared) = engine::prepare(&frame, args.albedo.albedo_prefilter, beauty) {
        frame = prepared;
    }
    let (w, h) = (frame.width, frame.height);
    let stats = engine::FrameStats::of(&frame);
    let inputs = preprocess::preprocess(&frame, &stats, set, Rect { x: 0, y: 0, w, h });

    let shaped = |v: Vec<f32>| -> Result<Array3<f32>> {
        let c = v.len() / (w * h);
        Ok(Array3::from_shape_vec((c, h, w), v)?)
    };
    let stack = |planes: [&[f32]; 3]| -> Vec<f32> { planes.concat() };
    let albedo: Vec<Plane> = frame.planes(Buffer::Albedo).iter().map(PlaneRef::to_vec).collect();
    let noisy = frame.diffuse_plus_specular();

    let file = crate::atomic::File::create(&args.output)
        .with_context(|| format!("cannot create {}", args.output.display()))?;
    let mut npz = ndarray_npy::NpzWriter::new(file);
    npz.add_array("diffuse_color", &shaped(inputs.diffuse)?)?;
    npz.add_array("specular_color", &shaped(inputs.specular)?)?;
    npz.add_array("features", &shaped(inputs.features)?)?;
    npz.add_array("albedo", &shaped(stack([&albedo[0], &albedo[1], &albedo[2]]))?)?;
    npz.add_array("noisy", &shaped(stack([&noisy[0], &noisy[1], &noisy[2]]))?)?;
    npz.add_array("variant", &Array0::from_elem((), i32::from(set == FeatureSet::Full)))?;
    if let Some(r) = &reference {
        if !(r.has(Buffer::Diffuse) && r.has(Buffer::Specular)) {
            bail!("the reference needs diffuse.* and specular.* channels for training targets");
        }
        let d_target: Vec<f32> = (0..3)
            .flat_map(|c| {
                r.f32_plane(Buffer::Diffuse, c).iter().zip(&albedo[c]).map(|(d, a)| d / (a + EPS)).collect::<Vec<_>>()
            })
            .collect();
        let s_target: Vec<f32> = (0..3)
            .flat_map(|c| r.f32_plane(Buffer::Specular, c).iter().map(|s| s.max(0.0).ln_1p()).collect::<Vec<_>>())
            .collect();
        let rc = r.color();
        npz.add_array("diffuse_target", &shaped(d_target)?)?;
        npz.add_array("specular_target", &shaped(s_target)?)?;
        npz.add_array("reference", &shaped(stack([&rc[0], &rc[1], &rc[2]]))?)?;
    }
    npz.finish()?.commit().with_context(|| format!("cannot write {}", args.output.display()))?;
    eprintln!(
        "wrote {} ({}x{}, variant {}, {} firefly samples handled)",
        args.output.display(),
        w,
        h,
        set.name(),
        report.total()
    );
    Ok(())
}

#[derive(Args, Debug)]
pub struct MetricsArgs {
    /// Image (`R,G,B`, or `diffuse.*` + `specular.*`).
    pub image: PathBuf,
    /// Reference image, same size.
    #[arg(long)]
    pub reference: PathBuf,
    #[command(flatten)]
    pub frame: FrameArgs,
}

/// `mcdenoise metrics`: the metrics of one image against a reference, as JSON on stdout.
pub fn metrics(args: MetricsArgs) -> Result<()> {
    let limits = args.frame.limits();
    let image = read(&args.image, &limits, true)?;
    let reference = read(&args.reference, &limits, true)?;
    check_same_size(&image, &reference)?;
    let (x, r) = (image.color(), reference.color());
    let m = Metrics::compute([&x[0], &x[1], &x[2]], [&r[0], &r[1], &r[2]], image.width, image.height);
    println!("{}", serde_json::to_string(&m)?);
    Ok(())
}
