//! The denoising engine: preprocessing, tiled ONNX inference, kernel reconstruction and the
//! inverse transforms. Synchronous and transport-free; the CLI and the daemon drive it.
//!
//! A frame is cut into square tiles. Each tile is preprocessed and run through both networks
//! together with a halo of context at least as wide as the networks' receptive radius (and
//! the kernel radius), so the tiled result equals the whole-frame result while memory
//! follows the tile size.

pub mod contract;
pub mod model;
pub mod preprocess;
pub mod reconstruct;
pub mod runtime;

use std::path::PathBuf;
use std::time::{Duration, Instant};

use serde::Serialize;

pub use contract::{Component, Variant};
pub use model::{ModelInfo, ModelPair};
pub use preprocess::{FrameStats, Rect, EPS};

use crate::frame::{Buffer, Frame, Plane};

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
    /// Directory holding `full/` and/or `nocov/`.
    pub models_dir: PathBuf,
    /// Side of a tile's core in pixels; 0 runs the whole frame at once.
    pub tile: usize,
    /// Threads for ONNX Runtime and for pre/post-processing.
    pub threads: usize,
    /// Explicit path of libonnxruntime; otherwise it is searched for (see [`runtime`]).
    pub ort_library: Option<PathBuf>,
}

impl EngineConfig {
    pub fn new(models_dir: impl Into<PathBuf>) -> Self {
        EngineConfig {
            models_dir: models_dir.into(),
            tile: 256,
            threads: std::thread::available_parallelism().map(|n| n.get()).unwrap_or(1),
            ort_library: None,
        }
    }
}

/// Time spent per stage.
#[derive(Clone, Copy, Debug, Default, Serialize)]
pub struct StageTimings {
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

/// A denoised frame.
pub struct Denoised {
    pub width: usize,
    pub height: usize,
    pub variant: Variant,
    pub color: [Plane; 3],
    pub diffuse: [Plane; 3],
    pub specular: [Plane; 3],
    pub tiles: usize,
    pub timings: StageTimings,
}

/// Loaded models plus the tiling and threading settings.
pub struct Engine {
    pairs: Vec<ModelPair>,
    tile: usize,
    pool: rayon::ThreadPool,
}

impl Engine {
    /// Loads the ONNX Runtime library and every variant under `config.models_dir`.
    pub fn load(config: &EngineConfig) -> Result<Engine, EngineError> {
        let env = runtime::environment(config.ort_library.as_deref()).map_err(EngineError::Runtime)?;
        let threads = config.threads.max(1);
        let pairs = model::load_models(env, &config.models_dir, threads)?;
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .thread_name(|i| format!("mcdenoise-engine-{i}"))
            .build()
            .map_err(|e| EngineError::Runtime(format!("cannot start the engine's thread pool: {e}")))?;
        Ok(Engine { pairs, tile: config.tile, pool })
    }

    /// What each loaded network declares.
    pub fn models(&self) -> Vec<&ModelInfo> {
        self.pairs.iter().flat_map(|p| [&p.diffuse.info, &p.specular.info]).collect()
    }

    pub fn variants(&self) -> Vec<Variant> {
        self.pairs.iter().map(|p| p.variant).collect()
    }

    /// FLOPs per pixel of a variant's two networks.
    pub fn flops_per_pixel(&self, variant: Variant) -> Option<f64> {
        self.pairs.iter().find(|p| p.variant == variant).map(ModelPair::flops_per_pixel)
    }

    /// The variant for a frame: `full` when it has covariance and `full` is loaded, else
    /// `nocov`.
    pub fn select(&self, frame: &Frame) -> Result<Variant, EngineError> {
        let has = |v: Variant| self.pairs.iter().any(|p| p.variant == v);
        if frame.has(Buffer::Covariance) && has(Variant::Full) {
            Ok(Variant::Full)
        } else if has(Variant::Nocov) {
            if frame.has(Buffer::Covariance) {
                tracing::warn!("frame has covariance but no `full` model is loaded; using `nocov`");
            }
            Ok(Variant::Nocov)
        } else {
            Err(EngineError::NoModel("the frame has no `covariance` channel and no `nocov` model is loaded".into()))
        }
    }

    /// Runs each loaded variant once on a small frame, so that the first real job does not
    /// pay ONNX Runtime's first-run cost.
    pub fn warm_up(&mut self) -> Result<(), EngineError> {
        for variant in self.variants() {
            let frame = synthetic_frame(32, 32, variant == Variant::Full);
            self.denoise(&frame, Some(variant), &mut |_| true)?;
        }
        Ok(())
    }

    /// Denoises `frame` with `variant` (or the one [`Engine::select`] picks). `on_tile` is
    /// called after each tile; returning `false` cancels between tiles.
    pub fn denoise(
        &mut self,
        frame: &Frame,
        variant: Option<Variant>,
        on_tile: &mut dyn FnMut(Progress) -> bool,
    ) -> Result<Denoised, EngineError> {
        let variant = match variant {
            Some(v) => v,
            None => self.select(frame)?,
        };
        let (pair, halo) = pair_for(&mut self.pairs, variant, frame)?;
        let stats = FrameStats::of(frame);
        let tiles = tile_grid(frame.width, frame.height, self.tile);
        let (w, h) = (frame.width, frame.height);
        let mut filtered = [vec![0f32; 3 * w * h], vec![0f32; 3 * w * h]];
        let mut timings = StageTimings::default();

        for (index, core) in tiles.iter().enumerate() {
            let region = expand(*core, halo, w, h);
            let t = Instant::now();
            let inputs = self.pool.install(|| preprocess::preprocess(frame, &stats, variant, region));
            timings.preprocess += t.elapsed();
            for (slot, component) in Component::ALL.into_iter().enumerate() {
                let color = match component {
                    Component::Diffuse => &inputs.diffuse,
                    Component::Specular => &inputs.specular,
                };
                let t = Instant::now();
                let mut core_out = vec![0f32; 3 * core.pixels()];
                let pool = &self.pool;
                let mut recon_time = Duration::ZERO;
                pair.network(component).run(color, &inputs.features, region.h, region.w, |logits| {
                    let t = Instant::now();
                    pool.install(|| {
                        reconstruct::apply_kernels(logits, &color[..3 * region.pixels()], region, *core, &mut core_out)
                    });
                    recon_time = t.elapsed();
                })?;
                timings.inference += t.elapsed() - recon_time;
                timings.reconstruction += recon_time;
                scatter(&core_out, *core, w, h, &mut filtered[slot]);
            }
            if !on_tile(Progress { tiles_done: index + 1, tiles_total: tiles.len() }) && index + 1 < tiles.len() {
                return Err(EngineError::Cancelled);
            }
        }

        let t = Instant::now();
        let n = w * h;
        let albedo = frame.planes(Buffer::Albedo);
        let diffuse: [Plane; 3] = std::array::from_fn(|c| {
            filtered[0][c * n..][..n].iter().zip(&albedo[c]).map(|(d, a)| d * (a.max(0.0) + EPS)).collect()
        });
        let specular: [Plane; 3] =
            std::array::from_fn(|c| filtered[1][c * n..][..n].iter().map(|s| s.exp_m1()).collect());
        let color: [Plane; 3] =
            std::array::from_fn(|c| diffuse[c].iter().zip(&specular[c]).map(|(d, s)| d + s).collect());
        timings.reconstruction += t.elapsed();
        Ok(Denoised { width: w, height: h, variant, color, diffuse, specular, tiles: tiles.len(), timings })
    }

    /// Time spent in ONNX Runtime alone on the regions [`Engine::denoise`] would run for
    /// `frame` (preprocessing done beforehand and not counted, logits not consumed): the
    /// inference floor the speed benchmark compares the engine with.
    pub fn inference_only(&mut self, frame: &Frame, variant: Variant) -> Result<Duration, EngineError> {
        let (pair, halo) = pair_for(&mut self.pairs, variant, frame)?;
        let stats = FrameStats::of(frame);
        let mut total = Duration::ZERO;
        for core in tile_grid(frame.width, frame.height, self.tile) {
            let region = expand(core, halo, frame.width, frame.height);
            let inputs = self.pool.install(|| preprocess::preprocess(frame, &stats, variant, region));
            for component in Component::ALL {
                let color = match component {
                    Component::Diffuse => &inputs.diffuse,
                    Component::Specular => &inputs.specular,
                };
                let t = Instant::now();
                pair.network(component).run(color, &inputs.features, region.h, region.w, |_| ())?;
                total += t.elapsed();
            }
        }
        Ok(total)
    }
}

/// What the daemon's workers and `mcdenoise run` need of a denoiser. [`Engine`] is the real
/// one (ONNX Runtime); the job service's unit tests drive the whole job lifecycle with a fake
/// that needs no model.
pub trait Denoiser {
    /// The loaded networks.
    fn models(&self) -> Vec<ModelInfo>;

    /// Denoises `frame` (see [`Engine::denoise`]): `on_tile` is called after each tile, and
    /// returning `false` stops between tiles with [`EngineError::Cancelled`].
    fn denoise(
        &mut self,
        frame: &Frame,
        variant: Option<Variant>,
        on_tile: &mut dyn FnMut(Progress) -> bool,
    ) -> Result<Denoised, EngineError>;
}

impl Denoiser for Engine {
    fn models(&self) -> Vec<ModelInfo> {
        Engine::models(self).into_iter().cloned().collect()
    }

    fn denoise(
        &mut self,
        frame: &Frame,
        variant: Option<Variant>,
        on_tile: &mut dyn FnMut(Progress) -> bool,
    ) -> Result<Denoised, EngineError> {
        Engine::denoise(self, frame, variant, on_tile)
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

/// The loaded pair of `variant`, checked against the frame's channels, and the halo its
/// tiles need: the networks' receptive radius, at least the kernel radius.
fn pair_for<'a>(
    pairs: &'a mut [ModelPair],
    variant: Variant,
    frame: &Frame,
) -> Result<(&'a mut ModelPair, usize), EngineError> {
    if variant.uses_covariance() && !frame.has(Buffer::Covariance) {
        return Err(EngineError::NoModel("the `full` model needs a `covariance` channel".into()));
    }
    let pair = pairs
        .iter_mut()
        .find(|p| p.variant == variant)
        .ok_or_else(|| EngineError::NoModel(format!("no `{}` model is loaded", variant.name())))?;
    let halo = pair.receptive_radius().max(contract::KERNEL_RADIUS);
    Ok((pair, halo))
}

/// Cores of side `tile` covering a `w`×`h` frame, row-major; one core for `tile == 0`.
pub fn tile_grid(w: usize, h: usize, tile: usize) -> Vec<Rect> {
    if tile == 0 {
        return vec![Rect { x: 0, y: 0, w, h }];
    }
    let mut out = Vec::new();
    for y in (0..h).step_by(tile) {
        for x in (0..w).step_by(tile) {
            out.push(Rect { x, y, w: tile.min(w - x), h: tile.min(h - y) });
        }
    }
    out
}

/// `core` grown by `halo` on every side, clamped to the frame.
pub fn expand(core: Rect, halo: usize, w: usize, h: usize) -> Rect {
    let x = core.x.saturating_sub(halo);
    let y = core.y.saturating_sub(halo);
    Rect { x, y, w: (core.x + core.w + halo).min(w) - x, h: (core.y + core.h + halo).min(h) - y }
}

/// Copies a core's `[3][core.h][core.w]` into frame-sized `[3][h][w]` planes.
fn scatter(core_out: &[f32], core: Rect, w: usize, h: usize, dst: &mut [f32]) {
    let (n, cn) = (w * h, core.pixels());
    for c in 0..3 {
        for row in 0..core.h {
            dst[c * n + (core.y + row) * w + core.x..][..core.w]
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
    Frame::from_planes(w, h, synthetic_planes(w, h, with_covariance), crate::frame::layout::REQUIRED)
        .expect("synthetic frame is complete")
}
