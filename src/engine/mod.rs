//! The denoising engine: preprocessing, tiled ONNX inference, kernel reconstruction and the
//! inverse transforms. Synchronous and transport-free; the CLI and the daemon drive it.
//!
//! Before tiling, [`fireflies`] finds and clamps isolated outliers on the whole frame (its
//! own stage, independent of the networks). A frame is cut into square tiles. Each tile is
//! preprocessed and run through the networks
//! together with a halo of context at least as wide as the networks' receptive radius (and
//! what the reconstruction reads), so the tiled result equals the whole-frame result while
//! memory follows the tile size. A variant is either two contract-v1 graphs (one per
//! component, one 21×21 kernel: [`reconstruct`]) or one contract-v2 graph (both components,
//! kernels at several scales: [`multiscale`]); for the latter, tiles and halos are aligned to
//! its pooling grid and regions padded to it, so that tiles see the frame's grid.

pub mod albedo;
mod compress;
pub mod contract;
pub mod device;
pub mod exposure;
pub mod fireflies;
pub mod model;
pub mod multiscale;
pub mod openvino;
pub mod preprocess;
pub mod reconstruct;
pub mod runtime;
pub mod stages;
pub mod variance;

use std::path::PathBuf;
use std::time::{Duration, Instant};

use serde::Serialize;

pub use albedo::AlbedoPrefilter;
pub use contract::{
    Component, FeatureSet, InputCompression, Outputs, Precision, Reconstruction, SpecularPyramid, Variant,
};
pub use device::{Device, IoBinding};
pub use fireflies::{Fireflies, FireflyMode};
pub use model::{ModelInfo, VariantModel};
pub use preprocess::{depth_scale, FrameStats, Rect, EPS};

use crate::frame::{Buffer, Frame, FrameKind, Plane, PlaneRef};

/// Why the engine could not denoise.
#[derive(Debug, thiserror::Error)]
pub enum EngineError {
    /// The ONNX Runtime library is missing or unusable.
    #[error("{0}")]
    Runtime(String),
    #[error("model {}: {reason}", path.display())]
    Model { path: PathBuf, reason: String },
    /// No loaded variant fits the frame's channels.
    #[error("{0}")]
    NoModel(String),
    #[error("inference failed: {0}")]
    Inference(String),
    #[error("cancelled")]
    Cancelled,
}

/// How the engine is set up.
#[derive(Clone, Debug)]
pub struct EngineConfig {
    /// Directory holding the variants (`full/`, `nocov/`, ...; docs/model-contract.md).
    pub models_dir: PathBuf,
    /// Side of a tile's core in pixels for contract-v1 models; 0 runs the whole frame at
    /// once.
    pub tile: usize,
    /// The same for contract-v2 models (rounded up to the model's size multiple): their
    /// halo is wider, so their tiles are larger.
    pub tile_v2: usize,
    /// Largest region (a core with its halo) the networks run on, in pixels: the frame is
    /// cut into more, smaller cores where a region would be larger. It bounds the
    /// runtime's working memory, which follows the region's pixels. `None`: the device's
    /// default ([`default_region_pixels`]).
    pub region_pixels: Option<usize>,
    /// Threads for ONNX Runtime and for pre/post-processing.
    pub threads: usize,
    /// Explicit path of libonnxruntime; otherwise it is searched for (see [`runtime`]).
    pub ort_library: Option<PathBuf>,
    /// Where the networks run ([`Device`]; `cpu` unless asked).
    pub device: Device,
    /// Where contract-v2 kernels are applied ([`Reconstruction`]; `auto`: in the graph on a
    /// GPU where the variant has `model-recon.onnx`).
    pub reconstruction: Reconstruction,
    /// The contract-v2 networks' precision ([`Precision`]; `auto`: half on a GPU where the
    /// variant has `model-recon-fp16.onnx`).
    pub precision: Precision,
    /// Whether contract-v2 networks run through ONNX Runtime's I/O binding ([`IoBinding`];
    /// `auto`: off).
    pub io_binding: IoBinding,
    /// Whether the albedo is prefiltered by its variance ([`albedo`]; `on` unless turned off).
    pub albedo_prefilter: AlbedoPrefilter,
    /// When the variants' networks are loaded ([`ModelLoading`]; `eager` unless asked).
    pub loading: ModelLoading,
    /// Whether a contract-v2 variant with stage files runs in stages where the frame allows
    /// ([`stages`]; on unless turned off: off, the whole graph per region, which the tests
    /// compare with).
    pub stages: bool,
}

/// When [`Engine::load`] loads the variants' networks.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum ModelLoading {
    /// All of them at once, so that a broken model stops the load and every variant is
    /// ready for the first job (the daemon).
    #[default]
    Eager,
    /// Each when a frame first needs it: the variants are found (and their directories
    /// checked) at load, their networks created on first use. A one-frame run then pays for
    /// the sessions of the variant it uses only.
    OnDemand,
}

impl EngineConfig {
    pub fn new(models_dir: impl Into<PathBuf>) -> Self {
        EngineConfig {
            models_dir: models_dir.into(),
            tile: 256,
            tile_v2: DEFAULT_TILE_V2,
            region_pixels: None,
            threads: std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1),
            ort_library: None,
            device: Device::Cpu,
            reconstruction: Reconstruction::Auto,
            precision: Precision::Auto,
            io_binding: IoBinding::Auto,
            albedo_prefilter: AlbedoPrefilter::On,
            stages: true,
            loading: ModelLoading::Eager,
        }
    }
}

/// Default tile side for contract-v2 models. Measured with the default msnet (receptive
/// radius 117, halo 128) on a 1280×720 frame, `mcdenoise run` on 2 cores: 768 gives two
/// tiles, 7.1–7.3 s and 0.79–0.80 GB peak; 512 8.1 s and 0.76 GB; 1024 7.2 s and 0.99 GB;
/// the whole frame 4.8–8.9 s and 1.07–1.27 GB (docs/model-contract.md).
pub const DEFAULT_TILE_V2: usize = 768;

/// Default [`EngineConfig::region_pixels`]: 896 × 768. Measured with the default msnet
/// (`mcdenoise run`, 2 threads, a 3840×2160 float frame of 20 planes): peak RSS grows by
/// about 1.3 GB per million region pixels (ONNX Runtime's activations and outputs, the
/// region's inputs); 768² cores (regions of 1024 × 976 inside a 4K frame) peaked at
/// 1.92 GB, 512² (768²) at 1.40 GB but 33 % slower. Frames up to 1920×1080 never need
/// more than 768² cores in a balanced grid (their regions stay under 0.62 M pixels), so
/// the bound applies to larger frames only (docs/results/speed-work.md).
pub const DEFAULT_REGION_PIXELS: usize = 896 * 768;

/// The same with OpenVINO through its ONNX Runtime plugin (`--device openvino` on an Intel
/// CPU): 540,000. Its working memory for a region is larger than ONNX Runtime's CPU
/// provider's (`mcdenoise run`, 2 threads, Intel Xeon with AMX, the bench frame tiled into
/// 3840×2160: peak 1.58–1.59 GB with 896 × 768 regions, 1.38–1.39 GB with this bound's 40,
/// at the same speed; 1920×1080 1.12 → 0.97 GB in 8 regions). A 1280×720 frame runs as
/// four regions of 768 × 488 instead of two of 768 × 720: peak 1.0 → 0.70 GB, and a
/// one-frame process faster (median 1.84 → 1.09 s over six alternated runs), its fresh
/// memory fewer pages for the kernel to fault in (docs/results/speed-work.md). Any bound
/// from 506,368 (4K's regions) up to 552,959 cuts these three sizes alike.
pub const OPENVINO_REGION_PIXELS: usize = 540_000;

/// The same with OpenVINO's runtime driven directly (`--device openvino` on other CPUs,
/// [`runtime::OpenVino::Runtime`]): 576,000, which keeps 1280×720 in two regions of
/// 768 × 720 and cuts 1080p and 4K as [`OPENVINO_REGION_PIXELS`] does. On an AMD EPYC
/// (Zen 4, 2 threads) four regions made a one-frame process slower, not faster: medians
/// over eight alternated runs 1.75 s against 1.54 s for two (each region shape's first run
/// costs OpenVINO 0.15–0.25 s more than the next, and four regions compute 1.47 M pixels
/// against 1.11 M); 4K peaked at 1.37 GB in 40 regions and 1.55 GB in 28
/// (docs/results/speed-work.md).
pub const OPENVINO_RUNTIME_REGION_PIXELS: usize = 576_000;

/// The region bound where none is given: [`OPENVINO_REGION_PIXELS`] or
/// [`OPENVINO_RUNTIME_REGION_PIXELS`] with OpenVINO, as it is reached, else
/// [`DEFAULT_REGION_PIXELS`].
pub fn default_region_pixels(device: Device) -> usize {
    match device {
        Device::OpenVino if runtime::openvino_route() == Some(runtime::OpenVino::Runtime) => {
            OPENVINO_RUNTIME_REGION_PIXELS
        }
        Device::OpenVino => OPENVINO_REGION_PIXELS,
        Device::Cpu | Device::Cuda(_) | Device::Auto => DEFAULT_REGION_PIXELS,
    }
}

/// Time spent per stage.
#[derive(Clone, Copy, Debug, Default, Serialize)]
pub struct StageTimings {
    /// Firefly detection and clamping ([`fireflies`]).
    #[serde(serialize_with = "as_ms")]
    pub fireflies: Duration,
    #[serde(serialize_with = "as_ms")]
    pub preprocess: Duration,
    #[serde(serialize_with = "as_ms")]
    pub inference: Duration,
    #[serde(serialize_with = "as_ms")]
    pub reconstruction: Duration,
}

pub(crate) fn as_ms<S: serde::Serializer>(d: &Duration, s: S) -> Result<S::Ok, S::Error> {
    s.serialize_f64(d.as_secs_f64() * 1e3)
}

/// Progress after a tile.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Progress {
    pub tiles_done: usize,
    pub tiles_total: usize,
}

/// What one denoising is asked for besides the frame.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Options {
    /// The variant, or `None` for the one [`Engine::select`] picks.
    pub variant: Option<Variant>,
    /// The outlier handling before the networks.
    pub fireflies: Fireflies,
    /// Return the denoised diffuse and specular besides the color ([`Denoised::components`]).
    /// Without them the color is assembled tile by tile and the frame-sized planes of the
    /// two components are never allocated (at 4K, 200 MB).
    pub components: bool,
}

/// The denoised diffuse and specular components of a frame (their sum is the color).
#[derive(Clone, Debug)]
pub struct Components {
    pub diffuse: [Plane; 3],
    pub specular: [Plane; 3],
}

/// A denoised frame.
#[derive(Debug)]
pub struct Denoised {
    pub width: usize,
    pub height: usize,
    pub variant: Variant,
    pub color: [Plane; 3],
    /// The components, where [`Options::components`] asked for them.
    pub components: Option<Components>,
    pub tiles: usize,
    pub timings: StageTimings,
    /// What the firefly handling did.
    pub fireflies: FireflyReport,
    /// The factor the frame's radiance was scaled by before the networks (and the results by
    /// its inverse after): 1 unless its level was outside the training range ([`exposure`]).
    pub exposure: f32,
    /// Whether the network ran in stages ([`stages`]).
    pub staged: bool,
}

/// Samples (pixel × component) the firefly handling clamped, per component.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, serde::Deserialize)]
pub struct FireflyReport {
    pub diffuse: u64,
    pub specular: u64,
}

impl FireflyReport {
    /// Samples handled, all components together.
    pub fn total(&self) -> u64 {
        self.diffuse + self.specular
    }
}

/// Loaded models plus the tiling and threading settings.
pub struct Engine {
    models: Vec<VariantModel>,
    /// Variants found but not loaded yet ([`ModelLoading::OnDemand`]).
    unloaded: Vec<model::VariantDir>,
    /// Time spent loading variants on first use.
    loaded_on_demand: Duration,
    env: &'static ort::environment::Environment,
    placement: model::Placement,
    tile: usize,
    tile_v2: usize,
    region_pixels: usize,
    pool: rayon::ThreadPool,
    device: Device,
    albedo_prefilter: AlbedoPrefilter,
    stages: bool,
}

impl Engine {
    /// Loads the ONNX Runtime library and every variant under `config.models_dir` (or finds
    /// them, to be loaded on first use: [`ModelLoading`]).
    pub fn load(config: &EngineConfig) -> Result<Engine, EngineError> {
        let env = runtime::environment(config.ort_library.as_deref()).map_err(EngineError::Runtime)?;
        let threads = config.threads.max(1);
        let library = runtime::library().map_or_else(|| "loaded".to_string(), |p| p.display().to_string());
        let device = config.device.resolve(env, &library).map_err(EngineError::Runtime)?;
        let via = runtime::openvino_route().filter(|_| device == Device::OpenVino).map(runtime::OpenVino::name);
        tracing::info!(asked = %config.device, device = %device, openvino_via = via, "the networks run on {device}");
        let placement = model::Placement {
            threads,
            device,
            reconstruction: config.reconstruction,
            precision: config.precision,
            io_binding: config.io_binding,
        };
        let (models, unloaded) = match config.loading {
            ModelLoading::Eager => (model::load_models(env, &config.models_dir, placement)?, Vec::new()),
            ModelLoading::OnDemand => (Vec::new(), model::find_variants(&config.models_dir)?),
        };
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .thread_name(|i| format!("mcdenoise-engine-{i}"))
            .build()
            .map_err(|e| EngineError::Runtime(format!("cannot start the engine's thread pool: {e}")))?;
        Ok(Engine {
            models,
            unloaded,
            loaded_on_demand: Duration::ZERO,
            env,
            placement,
            tile: config.tile,
            tile_v2: config.tile_v2,
            region_pixels: config.region_pixels.unwrap_or_else(|| default_region_pixels(device)),
            pool,
            device,
            albedo_prefilter: config.albedo_prefilter,
            stages: config.stages,
        })
    }

    /// Where the networks run: `cpu` or `cuda:N` (`auto` resolved at load).
    pub fn device(&self) -> Device {
        self.device
    }

    /// What each loaded network declares.
    pub fn models(&self) -> Vec<&ModelInfo> {
        self.models.iter().flat_map(VariantModel::infos).collect()
    }

    /// The variants the engine serves (loaded or to be loaded on first use), in name order.
    pub fn variants(&self) -> Vec<Variant> {
        let mut all: Vec<Variant> =
            self.models.iter().map(|m| m.variant).chain(self.unloaded.iter().map(|u| u.variant)).collect();
        all.sort_by(|a, b| a.name().cmp(b.name()));
        all
    }

    /// Whether `variant` is loaded or found to be loaded on first use.
    fn serves(&self, variant: Variant) -> bool {
        self.models.iter().any(|m| m.variant == variant) || self.unloaded.iter().any(|u| u.variant == variant)
    }

    /// Loads `variant`'s networks if it is one found but not loaded yet; an error naming the
    /// variants there are if it is neither.
    fn ensure_loaded(&mut self, variant: Variant) -> Result<(), EngineError> {
        if self.models.iter().any(|m| m.variant == variant) {
            return Ok(());
        }
        let Some(i) = self.unloaded.iter().position(|u| u.variant == variant) else {
            return Err(EngineError::NoModel(format!(
                "no `{variant}` model is loaded (loaded: {})",
                self.loaded_names()
            )));
        };
        // A variant that fails to load stays unloaded: asked for again, it names its error again.
        let t = Instant::now();
        let model = model::load_variant(self.env, &self.unloaded[i], self.placement)?;
        self.unloaded.remove(i);
        self.models.push(model);
        self.loaded_on_demand += t.elapsed();
        Ok(())
    }

    /// Time spent so far loading variants on first use ([`ModelLoading::OnDemand`]).
    pub fn loaded_on_demand(&self) -> Duration {
        self.loaded_on_demand
    }

    /// FLOPs per pixel of a variant's networks (both components).
    pub fn flops_per_pixel(&self, variant: Variant) -> Option<f64> {
        self.models.iter().find(|m| m.variant == variant).map(VariantModel::flops_per_pixel)
    }

    /// The variant for a frame: `beauty` when it has no diffuse/specular split
    /// ([`Frame::beauty_only`]) and `beauty` is loaded, `full` when it has covariance and
    /// `full` is loaded, else `nocov`.
    pub fn select(&self, frame: &Frame) -> Result<Variant, EngineError> {
        let kind = frame.kind();
        let variant = self.select_kind(kind)?;
        if variant == Variant::Nocov && kind.covariance {
            tracing::warn!("frame has covariance but no `full` model is loaded; using `nocov`");
        }
        Ok(variant)
    }

    /// [`Engine::select`] for a frame of `kind`.
    fn select_kind(&self, kind: FrameKind) -> Result<Variant, EngineError> {
        let has = |v: Variant| self.serves(v);
        if kind.beauty_only && has(Variant::Beauty) {
            Ok(Variant::Beauty)
        } else if kind.covariance && has(Variant::Full) {
            Ok(Variant::Full)
        } else if has(Variant::Nocov) {
            Ok(Variant::Nocov)
        } else {
            let lacks = if kind.covariance {
                "no `full` or `nocov` model is loaded"
            } else {
                "the frame has no `covariance` channel and no `nocov` model is loaded"
            };
            Err(EngineError::NoModel(format!("{lacks} (loaded: {}); name a variant", self.loaded_names())))
        }
    }

    fn loaded_names(&self) -> String {
        self.variants().iter().map(|v| v.name()).collect::<Vec<_>>().join(", ")
    }

    /// Runs each loaded variant once on a small frame, so that the first real job does not
    /// pay ONNX Runtime's first-run cost.
    pub fn warm_up(&mut self) -> Result<(), EngineError> {
        for (variant, features) in self.models.iter().map(|m| (m.variant, m.features)).collect::<Vec<_>>() {
            let frame = synthetic_frame(32, 32, features.uses_covariance());
            self.denoise(&frame, Some(variant), &mut |_| true)?;
        }
        Ok(())
    }

    /// Denoises `frame` with `variant` (or the one [`Engine::select`] picks) and the default
    /// firefly handling (`auto`), with its components. `on_tile` is called after each tile;
    /// returning `false` cancels between tiles.
    pub fn denoise(
        &mut self,
        frame: &Frame,
        variant: Option<Variant>,
        on_tile: &mut dyn FnMut(Progress) -> bool,
    ) -> Result<Denoised, EngineError> {
        self.denoise_with(frame, Options { variant, components: true, ..Options::default() }, on_tile)
    }

    /// [`Engine::denoise`] as `options` ask.
    pub fn denoise_with(
        &mut self,
        frame: &Frame,
        options: Options,
        on_tile: &mut dyn FnMut(Progress) -> bool,
    ) -> Result<Denoised, EngineError> {
        let variant = match options.variant {
            Some(v) => v,
            None => self.select(frame)?,
        };
        let mut timings = StageTimings::default();
        let t = Instant::now();
        let exposure = exposure::scale_for(self.pool.install(|| exposure::level(frame)));
        let exposed = self.pool.install(|| exposure::apply(frame, exposure));
        let frame = exposed.as_ref().unwrap_or(frame);
        timings.preprocess += t.elapsed();
        let t = Instant::now();
        let fields = firefly_fields(variant);
        let (handled, report) = self.pool.install(|| handle_fireflies(frame, options.fireflies, fields));
        let frame = handled.as_ref().unwrap_or(frame);
        timings.fireflies = t.elapsed();
        let t = Instant::now();
        let mode = self.albedo_prefilter;
        let prepared = self.pool.install(|| prepare(frame, mode, variant == Variant::Beauty));
        let frame = prepared.as_ref().unwrap_or(frame);
        timings.preprocess += t.elapsed();

        self.ensure_loaded(variant)?;
        let (model, plan) = plan(&mut self.models, [self.tile, self.tile_v2], self.region_pixels, variant, frame)?;
        let stats = FrameStats::of(frame);
        let tiles = plan.cores(frame.width, frame.height);
        let (w, h) = (frame.width, frame.height);
        let planes = || -> [Plane; 3] { std::array::from_fn(|_| vec![0f32; w * h]) };
        let mut color = planes();
        let mut components = options.components.then(|| Components { diffuse: planes(), specular: planes() });
        let albedo = frame.planes(Buffer::Albedo);
        let mut scratch = Scratch::default();
        let staged = match staged_network(model, self.stages, w, h, self.region_pixels) {
            Some(net) => Some(stage_frame(net, &self.pool, frame, &stats, &tiles, &mut scratch, &mut timings)?),
            None => None,
        };

        for (index, core) in tiles.iter().enumerate() {
            let [mut diffuse, mut specular] =
                match (&staged, staged_network(model, self.stages, w, h, self.region_pixels)) {
                    (Some(staged), Some(net)) => finish_staged(net, &self.pool, staged, index, &mut timings)?,
                    _ => run_region(
                        model,
                        &self.pool,
                        frame,
                        &stats,
                        Placement { region: expand(*core, plan.halo, w, h), core: *core, multiple: plan.multiple },
                        &mut scratch,
                        &mut timings,
                        true,
                    )?,
                };
            let t = Instant::now();
            self.pool.install(|| finish_core(&mut diffuse, &mut specular, &albedo, *core, w));
            if exposure != 1.0 {
                // Saturated as the colour is: a frame of huge values back up may exceed f32.
                let back = 1.0 / exposure;
                diffuse.iter_mut().chain(specular.iter_mut()).for_each(|v| *v = saturate(*v * back));
            }
            if let Some(c) = &mut components {
                scatter(&diffuse, *core, w, &mut c.diffuse);
                scatter(&specular, *core, w, &mut c.specular);
            }
            for (d, s) in diffuse.iter_mut().zip(&specular) {
                *d = saturate(*d + s);
            }
            scatter(&diffuse, *core, w, &mut color);
            timings.reconstruction += t.elapsed();
            if !on_tile(Progress { tiles_done: index + 1, tiles_total: tiles.len() }) && index + 1 < tiles.len() {
                return Err(EngineError::Cancelled);
            }
        }
        Ok(Denoised {
            width: w,
            height: h,
            variant,
            color,
            components,
            tiles: tiles.len(),
            timings,
            fireflies: report,
            exposure,
            staged: staged.is_some(),
        })
    }

    /// Time spent in ONNX Runtime alone on the regions [`Engine::denoise`] would run for
    /// `frame` (preprocessing done beforehand and not counted, logits not consumed; in
    /// stages, the stages [`Engine::denoise`] would run, with the reconstruction between
    /// them not counted): the inference floor the speed benchmark compares the engine with.
    pub fn inference_only(&mut self, frame: &Frame, variant: Variant) -> Result<Duration, EngineError> {
        self.ensure_loaded(variant)?;
        let (model, plan) = plan(&mut self.models, [self.tile, self.tile_v2], self.region_pixels, variant, frame)?;
        let stats = FrameStats::of(frame);
        let mut timings = StageTimings::default();
        let mut scratch = Scratch::default();
        let cores = plan.cores(frame.width, frame.height);
        if let Some(net) = staged_network(model, self.stages, frame.width, frame.height, self.region_pixels) {
            let staged = stage_frame(net, &self.pool, frame, &stats, &cores, &mut scratch, &mut timings)?;
            for index in 0..cores.len() {
                finish_staged(net, &self.pool, &staged, index, &mut timings)?;
            }
            return Ok(timings.inference);
        }
        for core in cores {
            let region = expand(core, plan.halo, frame.width, frame.height);
            let at = Placement { region, core, multiple: plan.multiple };
            run_region(model, &self.pool, frame, &stats, at, &mut scratch, &mut timings, false)?;
        }
        Ok(timings.inference)
    }
}

/// What the daemon's workers and `mcdenoise run` need of a denoiser. [`Engine`] is the real
/// one (ONNX Runtime); the job service's unit tests drive the whole job lifecycle with a fake
/// that needs no model.
pub trait Denoiser {
    /// The loaded networks.
    fn models(&self) -> Vec<ModelInfo>;

    /// Where the networks run (`auto` resolved), where the denoiser knows.
    fn device(&self) -> Option<Device> {
        None
    }

    /// Denoises `frame` (see [`Engine::denoise_with`]): `on_tile` is called after each tile,
    /// and returning `false` stops between tiles with [`EngineError::Cancelled`].
    fn denoise(
        &mut self,
        frame: &Frame,
        options: Options,
        on_tile: &mut dyn FnMut(Progress) -> bool,
    ) -> Result<Denoised, EngineError>;

    /// Whether [`Denoiser::prepare`] may have work to do: some variant is loaded only on
    /// first use ([`ModelLoading::OnDemand`]).
    fn loads_on_demand(&self) -> bool {
        false
    }

    /// Loads what a frame of `kind` denoised with `variant` (`None`: the one chosen for the
    /// frame) will need, while the frame is still being decoded. A failure is left for
    /// [`Denoiser::denoise`] to report.
    fn prepare(&mut self, _variant: Option<Variant>, _kind: FrameKind) {}
}

impl Denoiser for Engine {
    fn models(&self) -> Vec<ModelInfo> {
        Engine::models(self).into_iter().cloned().collect()
    }

    fn device(&self) -> Option<Device> {
        Some(self.device)
    }

    fn denoise(
        &mut self,
        frame: &Frame,
        options: Options,
        on_tile: &mut dyn FnMut(Progress) -> bool,
    ) -> Result<Denoised, EngineError> {
        Engine::denoise_with(self, frame, options, on_tile)
    }

    fn loads_on_demand(&self) -> bool {
        !self.unloaded.is_empty()
    }

    fn prepare(&mut self, variant: Option<Variant>, kind: FrameKind) {
        let loaded = variant.map_or_else(|| self.select_kind(kind), Ok).and_then(|v| self.ensure_loaded(v));
        if let Err(e) = loaded {
            tracing::debug!("not loaded ahead of the frame: {e}");
        }
    }
}

/// Makes the denoiser of one worker. Called on the worker's own thread, which then owns
/// the denoiser (its ONNX Runtime sessions and thread pool) until it exits.
pub type DenoiserFactory = std::sync::Arc<dyn Fn() -> Result<Box<dyn Denoiser>, EngineError> + Send + Sync>;

impl Engine {
    /// A factory of engines loaded from `config` and warmed up.
    pub fn factory(config: EngineConfig) -> DenoiserFactory {
        std::sync::Arc::new(move || {
            let mut engine = Engine::load(&config)?;
            engine.warm_up()?;
            Ok(Box::new(engine) as Box<dyn Denoiser>)
        })
    }
}

/// `x` with ±∞ replaced by ±`f32::MAX` and NaN by 0.
fn saturate(x: f32) -> f32 {
    preprocess::saturate(x, f32::MAX)
}

/// The frame as the networks see it once its fireflies are handled: the albedo prefiltered
/// ([`albedo::prefilter`] with `mode`), then, for the `beauty` variant, the beauty-only
/// view ([`Frame::to_beauty`]). `None` when neither changes it. `Engine::denoise` and
/// `mcdenoise preprocess` (training's inputs) both go through here, so they agree.
pub fn prepare(frame: &Frame, mode: AlbedoPrefilter, beauty: bool) -> Option<Frame> {
    let prefiltered = albedo::prefilter(frame, mode);
    if beauty {
        Some(prefiltered.as_ref().unwrap_or(frame).to_beauty())
    } else {
        prefiltered
    }
}

/// Whether `variant`'s inputs keep fields of bright samples (rule 4 of [`fireflies`]): the
/// `full` and `nocov` networks, which spread them and lost RelMSE and DSSIM when they were
/// clamped. The `beauty` and `lin2020` networks lost RelMSE with the rule on held-out
/// frames (docs/fireflies.md, "Sparse signals are not outliers"), so theirs, and any other
/// variant's, are clamped as before.
pub fn firefly_fields(variant: Variant) -> bool {
    variant == Variant::Full || variant == Variant::Nocov
}

/// Runs the firefly handling on every color buffer the networks read (diffuse, divided by
/// albedo as the network sees it, and specular). Returns the changed frame (`None` when
/// nothing was changed: the frame is only copied when it has outliers) and the counts.
/// `fields`: whether fields of bright samples are left to the network (rule 4 of
/// [`fireflies`]; [`firefly_fields`]).
pub fn handle_fireflies(frame: &Frame, settings: Fireflies, fields: bool) -> (Option<Frame>, FireflyReport) {
    use fireflies::Layer;
    let mut report = FireflyReport::default();
    if !settings.enabled() {
        return (None, report);
    }
    let (w, h) = (frame.width, frame.height);
    let albedo = frame.rgb(Buffer::Albedo);
    let layer = |color: Buffer, variance: Buffer, albedo: Option<[PlaneRef<'_>; 3]>| -> Vec<fireflies::Fix> {
        let c = frame.f32_planes(color);
        // Variances filled in as zeros for a missing buffer say nothing.
        let known = frame.has(variance) && !frame.missing_variances.iter().any(|m| m == variance.name());
        let layer =
            Layer { color: [&c[0], &c[1], &c[2]], variance: known.then(|| frame.rgb(variance)), albedo, fields };
        fireflies::detect(layer, w, h, settings)
    };
    let diffuse = layer(Buffer::Diffuse, Buffer::DiffuseVariance, Some(albedo));
    let specular = layer(Buffer::Specular, Buffer::SpecularVariance, None);
    report.diffuse = diffuse.len() as u64;
    report.specular = specular.len() as u64;
    if report.total() == 0 {
        return (None, report);
    }
    let mut out = frame.clone();
    fireflies::apply(&diffuse, out.planes_mut(Buffer::Diffuse));
    fireflies::apply(&specular, out.planes_mut(Buffer::Specular));
    (Some(out), report)
}

/// The loaded model of `variant` ([`Engine::ensure_loaded`]), checked against the frame's
/// channels, and its tiling for tiles of side `tiles[0]` (contract v1) or `tiles[1]`
/// (contract v2), regions of at most `region_pixels`.
fn plan<'a>(
    models: &'a mut [VariantModel],
    tiles: [usize; 2],
    region_pixels: usize,
    variant: Variant,
    frame: &Frame,
) -> Result<(&'a mut VariantModel, Tiling), EngineError> {
    let model = models
        .iter_mut()
        .find(|m| m.variant == variant)
        .ok_or_else(|| EngineError::NoModel(format!("no `{variant}` model is loaded")))?;
    if model.features.uses_covariance() && !frame.has(Buffer::Covariance) {
        return Err(EngineError::NoModel(format!("the `{variant}` model needs a `covariance` channel")));
    }
    let plan = Tiling::for_model(&model.infos(), tiles, region_pixels);
    Ok((model, plan))
}

/// How a frame is cut for one model: the largest core side, the context around each core,
/// what both (and each region's sides) must be multiples of, and the largest region.
#[derive(Clone, Copy, Debug)]
pub struct Tiling {
    /// Largest core side (0: the whole frame as one core).
    pub tile: usize,
    pub halo: usize,
    pub multiple: usize,
    /// Largest region (core and halo, inside the frame) in pixels.
    pub region_pixels: usize,
}

impl Tiling {
    /// How frames are cut for the variant whose graphs `infos` describes (contract 1: a
    /// pair; contract 2: one multi-scale graph): cores of at most `tiles[0]` (contract 1) or
    /// `tiles[1]` (contract 2) a side, a halo of the receptive radius (at least what the
    /// reconstruction reads), sides multiples of 2^(levels − 1) for contract 2, regions of
    /// at most `region_pixels`. The engine cuts frames with it, and the daemon counts a
    /// claimed job's tiles with it before the worker reports.
    pub fn for_model(infos: &[&ModelInfo], tiles: [usize; 2], region_pixels: usize) -> Tiling {
        let declared = infos.iter().map(|i| i.receptive_radius).max().unwrap_or(0);
        let (tile, multiple, reads) = match infos.iter().find(|i| i.contract >= 2) {
            Some(i) => (tiles[1], 1usize << i.levels.saturating_sub(1), multiscale::reach(i.kernel_size, i.levels)),
            None => (tiles[0], 1, contract::KERNEL_RADIUS),
        };
        Tiling {
            tile: tile.next_multiple_of(multiple),
            halo: declared.max(reads).next_multiple_of(multiple),
            multiple,
            region_pixels,
        }
    }

    /// Square cores of side `tile` without halo: what a job's tile count is estimated from
    /// when its variant's model is not loaded.
    pub fn plain(tile: usize) -> Tiling {
        Tiling { tile, halo: 0, multiple: 1, region_pixels: usize::MAX }
    }

    /// Cores covering a `w`×`h` frame, row-major: a balanced grid of `nx` × `ny` cores of
    /// one size (the last column and row smaller), sides multiples of `multiple`; `nx` and
    /// `ny` are the fewest that keep every side within `tile` and every region within
    /// `region_pixels` (cores are split further, the longer side first, until the largest
    /// region fits or cores are down to `multiple`). One core for `tile == 0`.
    ///
    /// Balanced rather than `tile`-sided: a 1280-wide frame is two cores of 640, not 768
    /// and 512, so the largest region (what sets the peak memory) is smaller for the same
    /// halo work.
    pub fn cores(&self, w: usize, h: usize) -> Vec<Rect> {
        if self.tile == 0 {
            return vec![Rect { x: 0, y: 0, w, h }];
        }
        let m = self.multiple.max(1);
        let side = |len: usize, n: usize| len.div_ceil(n).next_multiple_of(m).min(len.next_multiple_of(m));
        // The largest extent of a region along a side of `len` cut into cores of `c`: an
        // inner core has a halo on both sides, the two outer ones on one.
        let extent = |len: usize, c: usize| match len.div_ceil(c) {
            1 => len,
            2 => (c + self.halo).min(len),
            _ => (c + 2 * self.halo).min(len),
        };
        let (mut nx, mut ny) = (w.div_ceil(self.tile), h.div_ceil(self.tile));
        loop {
            let (cw, ch) = (side(w, nx), side(h, ny));
            let (rw, rh) = (extent(w, cw), extent(h, ch));
            if rw * rh <= self.region_pixels || (cw <= m && ch <= m) {
                let mut out = Vec::new();
                for y in (0..h).step_by(ch) {
                    for x in (0..w).step_by(cw) {
                        out.push(Rect { x, y, w: cw.min(w - x), h: ch.min(h - y) });
                    }
                }
                return out;
            }
            if (cw >= ch && cw > m) || ch <= m {
                nx += 1;
            } else {
                ny += 1;
            }
        }
    }
}

/// Where a region lies: the pixels the network runs on (`region`, the core with its halo)
/// and those it delivers (`core`). `region`'s origin must be a multiple of `multiple`; its
/// sides are padded to one by replicating the last row and column.
#[derive(Clone, Copy)]
struct Placement {
    region: Rect,
    core: Rect,
    multiple: usize,
}

/// Buffers a frame's regions reuse one after the other: the network inputs and the kept
/// color. Fresh buffers would each be mapped and faulted in page by page, some 150 MB per
/// region: at 3840×2160 (28 regions) 0.8 million page faults and 2.6 s of kernel time more
/// (docs/results/speed-work.md).
#[derive(Default)]
struct Scratch {
    inputs: preprocess::Inputs,
    colors: [Vec<f32>; 2],
}

/// Preprocesses the placement's region and runs `model` on it; returns the filtered diffuse
/// and specular color of its core (each `[3][core.h][core.w]`), or nothing when
/// `reconstruct` is false (the logits are then not consumed).
#[allow(clippy::too_many_arguments)]
fn run_region(
    model: &mut VariantModel,
    pool: &rayon::ThreadPool,
    frame: &Frame,
    stats: &FrameStats,
    Placement { region, core, multiple }: Placement,
    scratch: &mut Scratch,
    timings: &mut StageTimings,
    reconstruct: bool,
) -> Result<[Vec<f32>; 2], EngineError> {
    let t = Instant::now();
    let mut inputs = std::mem::take(&mut scratch.inputs);
    pool.install(|| preprocess::preprocess_into(frame, stats, model.features, region, &mut inputs));
    timings.preprocess += t.elapsed();
    let mut out = [vec![0f32; 3 * core.pixels()], vec![0f32; 3 * core.pixels()]];
    if !reconstruct {
        out = [Vec::new(), Vec::new()];
    }
    match &mut model.networks {
        model::Networks::Pair { diffuse, specular } => {
            for (slot, (net, color)) in
                [(diffuse, &inputs.diffuse), (specular, &inputs.specular)].into_iter().enumerate()
            {
                let t = Instant::now();
                let mut recon_time = Duration::ZERO;
                let core_out = &mut out[slot];
                net.run(color, &inputs.features, region.h, region.w, |logits| {
                    if reconstruct {
                        let t = Instant::now();
                        pool.install(|| {
                            reconstruct::apply_kernels(logits, &color[..3 * region.pixels()], region, core, core_out)
                        });
                        recon_time = t.elapsed();
                    }
                })?;
                timings.inference += t.elapsed() - recon_time;
                timings.reconstruction += recon_time;
            }
            scratch.inputs = inputs;
        }
        model::Networks::MultiScale(net) => {
            let t = Instant::now();
            let (pw, ph) = (region.w.next_multiple_of(multiple), region.h.next_multiple_of(multiple));
            let mut diffuse = pad_planes(inputs.diffuse, region.w, region.h, pw, ph);
            let mut specular = pad_planes(inputs.specular, region.w, region.h, pw, ph);
            let mut features = pad_planes(inputs.features, region.w, region.h, pw, ph);
            // The kernels filter the uncompressed color (channels 0–2 of each tensor): keep
            // it aside when the engine compresses the inputs.
            let color_len = 3 * pw * ph;
            let engine_compresses = net.info.input_compression == InputCompression::Engine;
            if engine_compresses {
                for (kept, tensor) in scratch.colors.iter_mut().zip([&diffuse, &specular]) {
                    kept.clear();
                    kept.extend_from_slice(&tensor[..color_len]);
                }
                pool.install(|| {
                    for tensor in [&mut diffuse, &mut specular, &mut features] {
                        compress::symlog_in_place(tensor);
                    }
                });
            }
            timings.preprocess += t.elapsed();
            let t = Instant::now();
            let mut recon_time = Duration::ZERO;
            let local = Rect { x: core.x - region.x, y: core.y - region.y, w: core.w, h: core.h };
            let ran = if net.info.outputs == Outputs::Filtered {
                // The graph reconstructs: only the core's pixels are taken.
                net.run_filtered(&diffuse, &specular, &features, ph, pw, |filtered| {
                    if reconstruct {
                        for (out, plane) in out.iter_mut().zip(filtered) {
                            crop(plane, pw, ph, local, out);
                        }
                    }
                })
            } else {
                net.run(&diffuse, &specular, &features, ph, pw, |pyramids| {
                    if reconstruct {
                        let (cd, cs) = if engine_compresses {
                            (scratch.colors[0].as_slice(), scratch.colors[1].as_slice())
                        } else {
                            (&diffuse[..color_len], &specular[..color_len])
                        };
                        let t = Instant::now();
                        pool.install(|| {
                            let [od, os] = &mut out;
                            rayon::join(
                                || multiscale::reconstruct(&pyramids[0], cd, pw, ph, local, od),
                                || multiscale::reconstruct(&pyramids[1], cs, pw, ph, local, os),
                            )
                        });
                        recon_time = t.elapsed();
                    }
                })
            };
            scratch.inputs = preprocess::Inputs { rect: region, diffuse, specular, features };
            ran?;
            timings.inference += t.elapsed() - recon_time;
            timings.reconstruction += recon_time;
        }
    }
    Ok(out)
}

/// The multi-scale network of `model` when it runs a `w`×`h` frame in stages: it has stage
/// files, `enabled`, and the frame's pooled level-0 features (half its padded size) fit in
/// one region of `region_pixels` for the middle stage.
fn staged_network(
    model: &mut VariantModel,
    enabled: bool,
    w: usize,
    h: usize,
    region_pixels: usize,
) -> Option<&mut model::MultiScaleNetwork> {
    match &mut model.networks {
        model::Networks::MultiScale(net) if enabled && net.stages.is_some() => {
            let m = net.size_multiple;
            let fits = (w.next_multiple_of(m) / 2) * (h.next_multiple_of(m) / 2) <= region_pixels;
            fits.then_some(net)
        }
        _ => None,
    }
}

/// A frame's work in stages up to its cores' level 0 ([`stages`]): per core, its region (the
/// core and [`stages::MARGIN`] around it, inside the frame; padded to the size multiple) with
/// the level-0 features and the preprocessed color `front` and the preprocessing gave there;
/// for the frame (padded), decoder level 1's output and each component's `o_1`.
struct StagedFrame {
    regions: Vec<StagedRegion>,
    /// The padded frame's size.
    width: usize,
    height: usize,
    /// `[1][c1][height/2][width/2]`, as `middle` gave it.
    decoder1: ort::value::DynValue,
    /// The diffuse's and the specular's `o_1` ([`multiscale::coarse_levels`]), `[3][height/2][width/2]`.
    coarse: [Vec<f32>; 2],
}

struct StagedRegion {
    region: Rect,
    core: Rect,
    /// The padded region's size.
    pw: usize,
    ph: usize,
    /// `[1][c][ph][pw]`, as `front` gave it (ONNX Runtime's memory).
    level0: ort::value::DynValue,
    /// The uncompressed diffuse and specular color, `[3][ph][pw]` each.
    colors: [Vec<f32>; 2],
}

/// `rect` of the padded region a core's results cover in the padded frame: the core, and to
/// the padded frame's edge where the core reaches the frame's.
fn padded_core(core: Rect, region: Rect, pw: usize, ph: usize, w: usize, h: usize) -> Rect {
    let x1 = if core.x + core.w == w { region.x + pw } else { core.x + core.w };
    let y1 = if core.y + core.h == h { region.y + ph } else { core.y + core.h };
    Rect { x: core.x, y: core.y, w: x1 - core.x, h: y1 - core.y }
}

/// Copies `rect` (frame coordinates) of `src`, the `[c][at.h][at.w]` planes of the area
/// `at` of the frame, into the `[c][dh][dw]` planes `dst` of the whole frame.
fn paste(src: &[f32], at: Rect, rect: Rect, dst: &mut [f32], dw: usize, dh: usize) {
    let channels = src.len() / at.pixels();
    for c in 0..channels {
        for row in 0..rect.h {
            let y = rect.y + row;
            let from = &src[c * at.pixels() + (y - at.y) * at.w + rect.x - at.x..][..rect.w];
            dst[c * dw * dh + y * dw + rect.x..][..rect.w].copy_from_slice(from);
        }
    }
}

/// The first two stages over `frame`: `front` per core, then `middle` over the frame's pooled
/// features, and the coarse levels of the reconstruction over the frame.
fn stage_frame(
    net: &mut model::MultiScaleNetwork,
    pool: &rayon::ThreadPool,
    frame: &Frame,
    stats: &FrameStats,
    cores: &[Rect],
    scratch: &mut Scratch,
    timings: &mut StageTimings,
) -> Result<StagedFrame, EngineError> {
    let (w, h, m) = (frame.width, frame.height, net.size_multiple);
    let (fw, fh) = (w.next_multiple_of(m), h.next_multiple_of(m));
    let stages = net.stages.as_mut().expect("a staged network");
    let c0 = stages.level0_channels;
    let mut pooled = vec![0f32; c0 * (fw / 2) * (fh / 2)];
    let mut color = [vec![0f32; 3 * fw * fh], vec![0f32; 3 * fw * fh]];
    let mut regions = Vec::with_capacity(cores.len());
    let engine_compresses = net.info.input_compression == InputCompression::Engine;
    for &core in cores {
        let t = Instant::now();
        let region = expand(core, stages::MARGIN, w, h);
        let mut inputs = std::mem::take(&mut scratch.inputs);
        pool.install(|| preprocess::preprocess_into(frame, stats, net.info.features, region, &mut inputs));
        let (pw, ph) = (region.w.next_multiple_of(m), region.h.next_multiple_of(m));
        let mut diffuse = pad_planes(std::mem::take(&mut inputs.diffuse), region.w, region.h, pw, ph);
        let mut specular = pad_planes(std::mem::take(&mut inputs.specular), region.w, region.h, pw, ph);
        let mut features = pad_planes(std::mem::take(&mut inputs.features), region.w, region.h, pw, ph);
        let colors = [diffuse[..3 * pw * ph].to_vec(), specular[..3 * pw * ph].to_vec()];
        let target = padded_core(core, region, pw, ph, w, h);
        let at = Rect { x: region.x, y: region.y, w: pw, h: ph };
        for (whole, part) in color.iter_mut().zip(&colors) {
            paste(part, at, target, whole, fw, fh);
        }
        if engine_compresses {
            pool.install(|| {
                for tensor in [&mut diffuse, &mut specular, &mut features] {
                    compress::symlog_in_place(tensor);
                }
            });
        }
        timings.preprocess += t.elapsed();
        let t = Instant::now();
        let mut out = stages.front(&diffuse, &specular, &features, ph, pw)?;
        let level0 = out.take("level0", [c0, ph, pw])?;
        let half = |r: Rect| Rect { x: r.x / 2, y: r.y / 2, w: r.w / 2, h: r.h / 2 };
        let part = out.get("pooled", [c0, ph / 2, pw / 2])?;
        paste(part, half(at), half(target), &mut pooled, fw / 2, fh / 2);
        drop(out);
        timings.inference += t.elapsed();
        scratch.inputs = preprocess::Inputs { rect: region, diffuse, specular, features };
        regions.push(StagedRegion { region, core, pw, ph, level0, colors });
    }
    let t = Instant::now();
    let (k, levels, linear) =
        (net.info.kernel_size, net.info.levels, net.info.specular_pyramid == SpecularPyramid::Linear);
    let detail_gains = net.info.detail_gains;
    let c1 = stages.decoder1_channels;
    let mut out = stages.middle(&pooled, fh / 2, fw / 2)?;
    let decoder1 = out.take("decoder1", [c1, fh / 2, fw / 2])?;
    let inference = t.elapsed();
    let t = Instant::now();
    let mut pyramids = [false, linear].map(|linear_means| multiscale::Pyramid {
        kernel_size: k,
        kernels: vec![&[][..]],
        blends: vec![&[][..]],
        gains: if detail_gains { vec![&[][..]] } else { Vec::new() },
        linear_means,
    });
    fn halves(data: &[f32]) -> [&[f32]; 2] {
        let (d, s) = data.split_at(data.len() / 2);
        [d, s]
    }
    for l in 1..levels {
        let (lw, lh) = (fw >> l, fh >> l);
        for (p, half) in pyramids.iter_mut().zip(halves(out.get(&format!("kernel_{l}"), [2 * k * k, lh, lw])?)) {
            p.kernels.push(half);
        }
        if l + 1 < levels {
            for (p, half) in pyramids.iter_mut().zip(halves(out.get(&format!("blend_{l}"), [2, lh, lw])?)) {
                p.blends.push(half);
            }
            if detail_gains {
                for (p, half) in pyramids.iter_mut().zip(halves(out.get(&format!("gain_{l}"), [2, lh, lw])?)) {
                    p.gains.push(half);
                }
            }
        }
    }
    let [cd, cs] = &color;
    let coarse = pool.install(|| {
        rayon::join(
            || multiscale::coarse_levels(&pyramids[0], cd, fw, fh),
            || multiscale::coarse_levels(&pyramids[1], cs, fw, fh),
        )
    });
    drop(out);
    timings.reconstruction += t.elapsed();
    timings.inference += inference;
    Ok(StagedFrame { regions, width: fw, height: fh, decoder1, coarse: [coarse.0, coarse.1] })
}

/// The last stage for core `index` of a [`StagedFrame`]: `back` over its region, then level 0
/// of the reconstruction over the core; the filtered diffuse and specular, `[3][core.h][core.w]` each.
fn finish_staged(
    net: &mut model::MultiScaleNetwork,
    pool: &rayon::ThreadPool,
    staged: &StagedFrame,
    index: usize,
    timings: &mut StageTimings,
) -> Result<[Vec<f32>; 2], EngineError> {
    let StagedRegion { region, core, pw, ph, level0, colors } = &staged.regions[index];
    let (region, core, pw, ph) = (*region, *core, *pw, *ph);
    let (fw, fh) = (staged.width, staged.height);
    let half = Rect { x: region.x / 2, y: region.y / 2, w: pw / 2, h: ph / 2 };
    let (k, detail_gains) = (net.info.kernel_size, net.info.detail_gains);
    let stages = net.stages.as_mut().expect("a staged network");
    let c1 = stages.decoder1_channels;
    let t = Instant::now();
    let mut decoder1 = vec![0f32; c1 * half.pixels()];
    let whole = stages::tensor(&staged.decoder1, "middle", "decoder1", [c1, fh / 2, fw / 2])?;
    crop(whole, fw / 2, fh / 2, half, &mut decoder1);
    let out = stages.back(&decoder1, level0, ph, pw)?;
    let kernel = out.get("kernel_0", [2 * k * k, ph, pw])?;
    let blend = out.get("blend_0", [2, ph, pw])?;
    let gain = if detail_gains { Some(out.get("gain_0", [2, ph, pw])?) } else { None };
    timings.inference += t.elapsed();
    let t = Instant::now();
    let local = Rect { x: core.x - region.x, y: core.y - region.y, w: core.w, h: core.h };
    let coarse = staged.coarse.each_ref().map(|c| {
        let mut part = vec![0f32; 3 * half.pixels()];
        crop(c, fw / 2, fh / 2, half, &mut part);
        part
    });
    let (kd, ks) = kernel.split_at(kernel.len() / 2);
    let (bd, bs) = blend.split_at(blend.len() / 2);
    let (gd, gs) = match gain {
        Some(g) => {
            let (d, s) = g.split_at(g.len() / 2);
            (Some(d), Some(s))
        }
        None => (None, None),
    };
    let mut out_planes = [vec![0f32; 3 * core.pixels()], vec![0f32; 3 * core.pixels()]];
    let [od, os] = &mut out_planes;
    pool.install(|| {
        rayon::join(
            || multiscale::finest(kd, bd, gd, k, &colors[0], pw, ph, &coarse[0], local, od),
            || multiscale::finest(ks, bs, gs, k, &colors[1], pw, ph, &coarse[1], local, os),
        )
    });
    timings.reconstruction += t.elapsed();
    Ok(out_planes)
}

/// Copies `rect` of the `[c][h][w]` planes `src` into `[c][rect.h][rect.w]` `dst`.
fn crop(src: &[f32], w: usize, h: usize, rect: Rect, dst: &mut [f32]) {
    let channels = src.len() / (w * h);
    for c in 0..channels {
        for y in 0..rect.h {
            let row = &src[c * w * h + (rect.y + y) * w + rect.x..][..rect.w];
            dst[(c * rect.h + y) * rect.w..][..rect.w].copy_from_slice(row);
        }
    }
}

/// Planar `[c][h][w]` planes padded to `[c][ph][pw]` by replicating the last column and row
/// (returned as they are when no padding is needed).
fn pad_planes(src: Vec<f32>, w: usize, h: usize, pw: usize, ph: usize) -> Vec<f32> {
    if (pw, ph) == (w, h) {
        return src;
    }
    let channels = src.len() / (w * h);
    let mut dst = vec![0f32; channels * pw * ph];
    for c in 0..channels {
        for y in 0..ph {
            let row = &src[c * w * h + y.min(h - 1) * w..][..w];
            let out = &mut dst[c * pw * ph + y * pw..][..pw];
            out[..w].copy_from_slice(row);
            out[w..].fill(row[w - 1]);
        }
    }
    dst
}

/// Cores of at most `tile` a side covering a `w`×`h` frame in a balanced grid, row-major
/// ([`Tiling::cores`] without halo); one core for `tile == 0`.
pub fn tile_grid(w: usize, h: usize, tile: usize) -> Vec<Rect> {
    Tiling::plain(tile).cores(w, h)
}

/// `core` grown by `halo` on every side, clamped to the frame.
pub fn expand(core: Rect, halo: usize, w: usize, h: usize) -> Rect {
    let x = core.x.saturating_sub(halo);
    let y = core.y.saturating_sub(halo);
    Rect { x, y, w: (core.x + core.w + halo).min(w) - x, h: (core.y + core.h + halo).min(h) - y }
}

/// The inverse transforms of a core's filtered `[3][core.h][core.w]` diffuse and specular,
/// in place: the diffuse times the albedo (`max(a, 0) + EPS`, read from the frame's rows
/// of the core), the specular `exp(x) − 1`, both saturated: a finite input never gives a
/// non-finite output (a filtered diffuse value times an albedo near the float maximum
/// would overflow).
fn finish_core(diffuse: &mut [f32], specular: &mut [f32], albedo: &[PlaneRef<'_>], core: Rect, w: usize) {
    use rayon::prelude::*;
    let cn = core.pixels();
    diffuse.par_chunks_mut(core.w).enumerate().for_each_init(
        || vec![0f32; core.w],
        |a, (i, row)| {
            let (c, y) = (i / core.h, i % core.h);
            albedo[c].read((core.y + y) * w + core.x, a);
            for (d, a) in row.iter_mut().zip(a.iter()) {
                *d = saturate(*d * (a.max(0.0) + EPS));
            }
        },
    );
    debug_assert_eq!(diffuse.len(), 3 * cn);
    specular.par_chunks_mut(core.w).for_each(|row| {
        compress::expm1_row(row);
        for s in row {
            *s = saturate(*s);
        }
    });
}

/// Copies a core's `[3][core.h][core.w]` into frame-sized `[3][h][w]` planes.
fn scatter(core_out: &[f32], core: Rect, w: usize, dst: &mut [Plane; 3]) {
    let cn = core.pixels();
    for (c, plane) in dst.iter_mut().enumerate() {
        for row in 0..core.h {
            plane[(core.y + row) * w + core.x..][..core.w]
                .copy_from_slice(&core_out[c * cn + row * core.w..][..core.w]);
        }
    }
}

/// The named planes of [`synthetic_frame`] (canonical channel names), e.g. to write it as an
/// EXR file.
pub fn synthetic_planes(w: usize, h: usize, with_covariance: bool) -> Vec<(String, Plane)> {
    let plane = |f: &dyn Fn(f32, f32) -> f32| -> Plane {
        (0..w * h).map(|i| f((i % w) as f32 / w as f32, (i / w) as f32 / h as f32)).collect()
    };
    let mut planes: Vec<(String, Plane)> = Vec::new();
    for (c, ch) in ["R", "G", "B"].into_iter().enumerate() {
        let k = c as f32;
        planes.push((format!("diffuse.{ch}"), plane(&|x, y| 0.5 + 0.4 * (6.0 * x + k).sin() * (4.0 * y).cos())));
        planes.push((format!("specular.{ch}"), plane(&|x, y| 0.2 * (1.0 + (9.0 * x * y + k).sin()))));
        planes.push((format!("albedo.{ch}"), plane(&|x, y| 0.3 + 0.2 * (x + y + k * 0.1))));
        planes.push((format!("normal.{ch}"), plane(&|x, y| [x - 0.5, y - 0.5, 0.7][c])));
    }
    planes.push(("depth.Z".into(), plane(&|x, y| 2.0 + x + 0.5 * y)));
    for v in ["diffuseVariance", "specularVariance", "albedoVariance", "normalVariance", "depthVariance"] {
        planes.push((format!("{v}.Z"), plane(&|x, y| 0.01 * (1.0 + x * y))));
    }
    if with_covariance {
        planes.push(("covariance".into(), plane(&|x, y| (x * 3.0).fract() * y)));
        planes.push(("covarianceVariance.Z".into(), plane(&|x, _| 0.001 * x)));
    }
    planes
}

/// A smooth synthetic frame with every channel, for warm-up, tests and benchmarks.
pub fn synthetic_frame(w: usize, h: usize, with_covariance: bool) -> Frame {
    let maps = crate::frame::ChannelMaps::default();
    Frame::from_planes(w, h, synthetic_planes(w, h, with_covariance), crate::frame::layout::REQUIRED, &maps)
        .expect("synthetic frame is complete")
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The shipped network's tiling: 768-px cores at most, halo 128, multiple 16.
    fn default_tiling() -> Tiling {
        Tiling { tile: DEFAULT_TILE_V2, halo: 128, multiple: 16, region_pixels: DEFAULT_REGION_PIXELS }
    }

    fn info(contract: u32, kernel_size: usize, levels: usize, receptive_radius: usize) -> ModelInfo {
        ModelInfo {
            variant: Variant::Full,
            component: None,
            contract,
            features: FeatureSet::Full,
            path: "m.onnx".into(),
            receptive_radius,
            flops_per_pixel: 1.0,
            architecture: "test".into(),
            sha256: String::new(),
            kernel_size,
            levels,
            input_compression: InputCompression::Engine,
            outputs: Outputs::Kernels,
            precision: Precision::Fp32,
            specular_pyramid: contract::SpecularPyramid::Log,
            detail_gains: false,
        }
    }

    #[test]
    fn a_models_tiling_follows_its_contract() {
        // The shipped network's metadata (5 levels of 5×5 kernels, radius 117) gives the
        // tiling above, and a 4K frame its 28 cores, as the daemon counts them at claim time.
        let v2 = info(2, 5, 5, 117);
        let t = Tiling::for_model(&[&v2], [256, DEFAULT_TILE_V2], DEFAULT_REGION_PIXELS);
        let d = default_tiling();
        assert_eq!((t.tile, t.halo, t.multiple, t.region_pixels), (d.tile, d.halo, d.multiple, d.region_pixels));
        assert_eq!(t.cores(3840, 2160).len(), 28);
        // A declared radius below what the reconstruction reads is raised to it.
        let t = Tiling::for_model(&[&info(2, 5, 5, 0)], [256, 500], usize::MAX);
        assert_eq!((t.tile, t.halo, t.multiple), (512, multiscale::reach(5, 5).next_multiple_of(16), 16));
        // Contract 1, a pair: its own tile size, no alignment, at least the kernel's radius.
        let (d1, s1) = (info(1, 21, 1, 13), info(1, 21, 1, 22));
        let t = Tiling::for_model(&[&d1, &s1], [300, 768], usize::MAX);
        assert_eq!((t.tile, t.halo, t.multiple), (300, 22, 1));
        let t = Tiling::for_model(&[&info(1, 21, 1, 3)], [300, 768], usize::MAX);
        assert_eq!(t.halo, contract::KERNEL_RADIUS);
    }

    /// Checks that `cores` cover the frame once, start on the grid and stay within the
    /// tiling's bounds; returns the largest region's pixels.
    fn check(t: &Tiling, w: usize, h: usize, cores: &[Rect]) -> usize {
        let mut covered = vec![0u8; w * h];
        let mut largest = 0;
        for c in cores {
            assert!(c.x % t.multiple == 0 && c.y % t.multiple == 0, "{c:?} starts off the grid");
            assert!(c.w <= t.tile && c.h <= t.tile, "{c:?} is larger than {}", t.tile);
            for y in c.y..c.y + c.h {
                for x in c.x..c.x + c.w {
                    covered[y * w + x] += 1;
                }
            }
            largest = largest.max(expand(*c, t.halo, w, h).pixels());
        }
        assert!(covered.iter().all(|n| *n == 1), "{w}×{h}: the cores do not cover the frame once");
        largest
    }

    #[test]
    fn frames_up_to_1080p_are_balanced_and_larger_ones_split_to_the_region_bound() {
        let t = default_tiling();
        // (frame, cores across × down, core size)
        for ((w, h), (nx, ny), (cw, ch)) in [
            ((1280, 720), (2, 1), (640, 720)),
            ((1920, 1080), (3, 2), (640, 544)),
            // 5 × 3 cores of 768 × 720 would make regions of 1024 × 976.
            ((3840, 2160), (7, 4), (560, 544)),
        ] {
            let cores = t.cores(w, h);
            assert_eq!(cores.len(), nx * ny, "{w}×{h}");
            assert_eq!((cores[0].w, cores[0].h), (cw, ch), "{w}×{h}");
            assert!(check(&t, w, h, &cores) <= t.region_pixels, "{w}×{h}");
        }
        let unbounded = Tiling { region_pixels: usize::MAX, ..t };
        assert_eq!(unbounded.cores(3840, 2160).len(), 15);
    }

    #[test]
    fn openvinos_bound_cuts_720p_in_four_and_larger_frames_as_measured() {
        // OPENVINO_REGION_PIXELS's doc: 720p in 2 × 2 regions (not 2 × 1), 1080p in 8,
        // 4K in 40, for any bound of its stated range.
        for region_pixels in [506_368, OPENVINO_REGION_PIXELS, 552_959] {
            let t = Tiling { region_pixels, ..default_tiling() };
            for ((w, h), n) in [((1280, 720), 4), ((1920, 1080), 8), ((3840, 2160), 40)] {
                let cores = t.cores(w, h);
                assert_eq!(cores.len(), n, "{w}×{h} with {region_pixels}");
                assert!(check(&t, w, h, &cores) <= region_pixels);
            }
        }
        let above = Tiling { region_pixels: 552_960, ..default_tiling() };
        assert_eq!(above.cores(1280, 720).len(), 2);
        let below = Tiling { region_pixels: 506_367, ..default_tiling() };
        assert!(below.cores(3840, 2160).len() > 40);
    }

    #[test]
    fn openvinos_runtime_bound_keeps_720p_in_two_and_cuts_larger_frames_alike() {
        // OPENVINO_RUNTIME_REGION_PIXELS's doc: 720p in 2 regions, 1080p and 4K as with the
        // plugin's bound.
        for region_pixels in [552_960, OPENVINO_RUNTIME_REGION_PIXELS] {
            let t = Tiling { region_pixels, ..default_tiling() };
            for ((w, h), n) in [((1280, 720), 2), ((1920, 1080), 8), ((3840, 2160), 40)] {
                let cores = t.cores(w, h);
                assert_eq!(cores.len(), n, "{w}×{h} with {region_pixels}");
                assert!(check(&t, w, h, &cores) <= region_pixels);
            }
        }
    }

    #[test]
    fn any_frame_is_covered_within_the_bounds() {
        for (tile, halo, multiple, region) in
            [(768, 128, 16, DEFAULT_REGION_PIXELS), (20, 8, 4, 30 * 30), (7, 0, 1, 49)]
        {
            let t = Tiling { tile, halo, multiple, region_pixels: region };
            for (w, h) in [(1, 1), (5, 3), (37, 91), (100, 100), (1000, 17), (2049, 1531)] {
                let largest = check(&t, w, h, &t.cores(w, h));
                // Only cores already at the grid's size may leave a region over the bound.
                let min_region =
                    expand(Rect { x: 2 * multiple, y: 2 * multiple, w: multiple, h: multiple }, halo, w, h);
                assert!(largest <= region.max(min_region.pixels()), "{w}×{h}, tile {tile}: region {largest}");
            }
        }
        assert_eq!(Tiling::plain(0).cores(30, 20), vec![Rect { x: 0, y: 0, w: 30, h: 20 }]);
    }
}
