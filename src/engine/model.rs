//! Loading models (contract v1 or v2, docs/model-contract.md) into ONNX Runtime sessions and
//! running them.

use std::collections::HashSet;
use std::path::{Path, PathBuf};

use ort::memory::{AllocationDevice, Allocator, AllocatorType, MemoryInfo, MemoryType};
use ort::session::{builder::GraphOptimizationLevel, Session};
use ort::value::{Tensor, TensorRef, ValueType};
use serde::Serialize;
use sha2::Digest;

use super::contract::{
    self, keys, Component, FeatureSet, InputCompression, Outputs, Precision, Reconstruction, SpecularPyramid, Variant,
    COLOR_CHANNELS, TAPS,
};
use super::device::{Device, IoBinding};
use super::multiscale::Pyramid;
use super::EngineError;

/// A loaded network: what its file declares about itself, and the file's digest. The one
/// description of a model, reported by `/v1/models`, `ListModels` and the metrics.
#[derive(Clone, Debug, Serialize)]
pub struct ModelInfo {
    pub variant: Variant,
    /// The component the graph predicts; `None` for a contract-v2 graph, which predicts both
    /// (shown as `both`).
    #[serde(serialize_with = "component_or_both")]
    pub component: Option<Component>,
    /// Contract version (1 or 2; shown as a string, as the file's metadata has it).
    #[serde(serialize_with = "as_string")]
    pub contract: u32,
    /// The feature inputs (`mcdenoise.features`).
    pub features: FeatureSet,
    #[serde(rename = "file")]
    pub path: PathBuf,
    pub receptive_radius: usize,
    pub flops_per_pixel: f64,
    pub architecture: String,
    /// SHA-256 of the file, hex.
    pub sha256: String,
    /// Side of the predicted kernels.
    pub kernel_size: usize,
    /// Pyramid levels (1 for contract v1).
    pub levels: usize,
    /// Who compresses the inputs with symlog (`graph` for contract v1).
    pub input_compression: InputCompression,
    /// What the graph outputs (`kernels` for contract v1).
    pub outputs: Outputs,
    /// What the network computes in (`fp32` for contract v1).
    pub precision: Precision,
    /// How the reconstruction averages the specular's pyramid (`log` for contract v1, which
    /// has no pyramid).
    pub specular_pyramid: SpecularPyramid,
    /// Whether the graph outputs detail gains (`gain_<l>`, contract v2; false for v1).
    pub detail_gains: bool,
}

fn component_or_both<S: serde::Serializer>(c: &Option<Component>, s: S) -> Result<S::Ok, S::Error> {
    s.serialize_str(c.map_or("both", Component::name))
}

fn as_string<S: serde::Serializer>(v: &u32, s: S) -> Result<S::Ok, S::Error> {
    s.collect_str(v)
}

impl ModelInfo {
    /// `diffuse`, `specular`, or `both` for a contract-v2 graph.
    pub fn component_name(&self) -> &'static str {
        self.component.map_or("both", Component::name)
    }
}

/// One network (a component of a variant) in its own session.
pub struct Network {
    session: Session,
    pub info: ModelInfo,
}

pub(super) fn model_error(path: &Path, reason: impl Into<String>) -> EngineError {
    EngineError::Model { path: path.to_path_buf(), reason: reason.into() }
}

/// Where and with how many threads a network's session runs.
#[derive(Clone, Copy, Debug)]
pub struct Placement {
    /// Intra-op threads (CPU work, and the host side of a GPU session).
    pub threads: usize,
    /// Resolved: `cpu`, `openvino` or `cuda:N` ([`Device::resolve`]).
    pub device: Device,
    /// Where contract-v2 kernels are applied (which file of a v2 variant is loaded).
    pub reconstruction: Reconstruction,
    /// The contract-v2 network's precision (with `fp16`, the half-precision file).
    pub precision: Precision,
    /// Whether contract-v2 networks run through ONNX Runtime's I/O binding ([`IoBinding`]).
    pub io_binding: IoBinding,
}

impl Placement {
    pub fn cpu(threads: usize) -> Placement {
        Placement {
            threads,
            device: Device::Cpu,
            reconstruction: Reconstruction::Engine,
            precision: Precision::Fp32,
            io_binding: IoBinding::Off,
        }
    }
}

/// The file of a contract-v2 variant with the reconstruction in the graph.
pub const RECON_FILE: &str = "model-recon.onnx";

/// The same with the network in half precision (`mcdenoise.precision` `fp16`).
pub const RECON_FP16_FILE: &str = "model-recon-fp16.onnx";

/// Outputs of a graph with the reconstruction in it (`mcdenoise.outputs` `filtered`).
const FILTERED_OUTPUTS: [&str; 2] = ["diffuse_filtered", "specular_filtered"];

/// Session options: `threads` intra-op threads, no spinning (the engine is idle between
/// jobs), all graph optimizations; on `cuda:N` ONNX Runtime's CUDA execution provider on
/// that GPU, failing rather than falling back to the CPU. A helper returning `ort::Result`
/// because builder errors carry the builder and are not `Send`.
pub fn build_session(env: &ort::environment::Environment, path: &Path, placement: Placement) -> ort::Result<Session> {
    build_session_optimized(env, path, placement, GraphOptimizationLevel::All)
}

/// [`build_session`] at graph optimization `level`.
fn build_session_optimized(
    env: &ort::environment::Environment,
    path: &Path,
    placement: Placement,
    level: GraphOptimizationLevel,
) -> ort::Result<Session> {
    let threads = placement.threads.max(1);
    let builder = Session::builder(env)?;
    let builder = match placement.device {
        Device::Cuda(n) => builder.with_execution_providers([ort::ep::CUDA::default()
            .with_device_id(i32::try_from(n).unwrap_or(i32::MAX))
            .build()
            .error_on_failure()])?,
        // Where OpenVINO's plugin does not serve the CPU, the session is ONNX Runtime's CPU
        // provider's (a contract-v2 network is then compiled by OpenVINO directly).
        Device::OpenVino if super::runtime::openvino_route() == Some(super::runtime::OpenVino::Plugin) => {
            let cpu: serde_json::Map<String, serde_json::Value> = openvino_properties(threads)
                .map_err(ort::Error::new)?
                .into_iter()
                .map(|(k, v)| (k, serde_json::Value::String(v)))
                .collect();
            let config = serde_json::json!({ "CPU": cpu }).to_string();
            let options = [(format!("{}.load_config", super::runtime::OPENVINO_EP), config)];
            builder.with_devices(super::runtime::openvino_cpu(env), Some(&options))?
        }
        Device::OpenVino | Device::Cpu | Device::Auto => builder,
    };
    builder
        // Memory patterns are planned per input shape and kept: with tiles of several shapes
        // (edge tiles) they held 0.9 GB more at 4K for no speed (docs/results/speed-work.md).
        // The CPU arena stays: without it inference was 1.3-1.6x slower.
        .with_memory_pattern(false)?
        // The environment's CPU arena, shared by every session (runtime.rs).
        .with_env_allocators()?
        .with_optimization_level(level)?
        .with_intra_threads(threads)?
        .with_inter_threads(1)?
        .with_intra_op_spinning(false)?
        .commit_from_file(path)
}

/// OpenVINO's CPU properties for a network (the plugin's `load_config`, or the core's
/// before OpenVINO compiles it): its thread count (it runs its own pool), one stream for
/// one request at a time, and its default precision (bfloat16 where the CPU has it
/// natively, else float32); `$MCDENOISE_OPENVINO_CONFIG`, a JSON object of further CPU
/// properties (`{"INFERENCE_PRECISION_HINT": "f32"}`), is laid over them.
fn openvino_properties(threads: usize) -> Result<Vec<(String, String)>, String> {
    let mut cpu = vec![
        ("INFERENCE_NUM_THREADS".to_string(), threads.to_string()),
        ("NUM_STREAMS".to_string(), "1".to_string()),
        ("PERFORMANCE_HINT".to_string(), "LATENCY".to_string()),
    ];
    if let Some(extra) = std::env::var("MCDENOISE_OPENVINO_CONFIG").ok().filter(|v| !v.trim().is_empty()) {
        let bad = |why: &str| format!("MCDENOISE_OPENVINO_CONFIG: {why} (got `{extra}`)");
        let serde_json::Value::Object(extra) = serde_json::from_str(&extra).map_err(|e| bad(&e.to_string()))? else {
            return Err(bad("expected a JSON object of OpenVINO CPU properties"));
        };
        for (key, value) in extra {
            let value = match value {
                serde_json::Value::String(s) => s,
                other => other.to_string(),
            };
            cpu.retain(|(k, _)| *k != key);
            cpu.push((key, value));
        }
    }
    Ok(cpu)
}

/// A model file opened in a session, with its metadata read.
pub(super) struct Opened {
    pub(super) session: Session,
    pub(super) path: PathBuf,
    meta: std::collections::HashMap<String, String>,
    /// SHA-256 of the file, hex.
    sha256: String,
}

/// What an [`Opened`] session is for.
#[derive(Clone, Copy, PartialEq, Eq)]
pub(super) enum SessionUse {
    /// Running the network: every graph optimization.
    Run,
    /// Only its metadata and its inputs' and outputs' names and shapes (a network that
    /// OpenVINO compiles and runs): none, which saves the optimizer's time.
    Check,
}

impl Opened {
    pub(super) fn open(
        env: &ort::environment::Environment,
        path: &Path,
        placement: Placement,
        usage: SessionUse,
    ) -> Result<Opened, EngineError> {
        match std::fs::metadata(path) {
            Ok(m) if m.is_file() => {}
            Ok(_) => return Err(model_error(path, "not a file")),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Err(model_error(path, "file not found")),
            Err(e) if e.kind() == std::io::ErrorKind::PermissionDenied => {
                return Err(model_error(path, format!("permission denied: the daemon's user cannot read it ({e})")))
            }
            Err(e) => return Err(model_error(path, format!("cannot read: {e}"))),
        }
        let sha256 = std::fs::read(path)
            .map(|b| sha2::Sha256::digest(&b).iter().map(|x| format!("{x:02x}")).collect())
            .map_err(|e| match e.kind() {
                std::io::ErrorKind::PermissionDenied => {
                    model_error(path, format!("permission denied: the daemon's user cannot read it ({e})"))
                }
                _ => model_error(path, format!("cannot read: {e}")),
            })?;
        let level = match usage {
            SessionUse::Run => GraphOptimizationLevel::All,
            SessionUse::Check => GraphOptimizationLevel::Disable,
        };
        let session = build_session_optimized(env, path, placement, level)
            .map_err(|e| model_error(path, format!("cannot load: {e}")))?;
        let meta = {
            let fail = |e: ort::Error| model_error(path, format!("cannot read metadata: {e}"));
            let meta = session.metadata().map_err(fail)?;
            let keys = meta.custom_keys().map_err(fail)?;
            keys.into_iter().filter_map(|k| meta.custom(&k).map(|v| (k, v))).collect()
        };
        Ok(Opened { session, path: path.to_path_buf(), meta, sha256 })
    }

    pub(super) fn get(&self, key: &str) -> Result<&str, EngineError> {
        self.meta
            .get(key)
            .map(String::as_str)
            .ok_or_else(|| model_error(&self.path, format!("metadata `{key}` is missing")))
    }

    pub(super) fn expect(&self, key: &str, want: &str, hint: &str) -> Result<(), EngineError> {
        let got = self.get(key)?;
        if got == want {
            Ok(())
        } else {
            Err(model_error(&self.path, format!("metadata `{key}` is `{got}`, expected `{want}`{hint}")))
        }
    }

    /// An optional key's value through `parse` (which also gives the default for `None`);
    /// `expected` names the accepted values in the error.
    fn optional<T>(&self, key: &str, parse: fn(Option<&str>) -> Option<T>, expected: &str) -> Result<T, EngineError> {
        let value = self.meta.get(key).map(String::as_str);
        parse(value).ok_or_else(|| {
            model_error(&self.path, format!("metadata `{key}` is `{}`, expected {expected}", value.unwrap_or_default()))
        })
    }

    fn number<T: std::str::FromStr>(&self, key: &str) -> Result<T, EngineError>
    where
        T::Err: std::fmt::Display,
    {
        self.get(key)?
            .parse::<T>()
            .map_err(|e| model_error(&self.path, format!("metadata `{key}` is not a number: {e}")))
    }

    /// The contract version, then the fields common to both contracts.
    fn common(&self, contract: &str, hint: &str, variant: Variant) -> Result<Common, EngineError> {
        match self.meta.get(keys::CONTRACT) {
            None => {
                return Err(model_error(
                    &self.path,
                    format!("metadata `{}` is missing (not an mcdenoise model?)", keys::CONTRACT),
                ))
            }
            Some(_) => self.expect(keys::CONTRACT, contract, hint)?,
        }
        self.expect(keys::VARIANT, variant.name(), " (the name of its directory)")?;
        let list = self.get(keys::FEATURES)?;
        let features = FeatureSet::from_list(list).ok_or_else(|| {
            model_error(
                &self.path,
                format!(
                    "metadata `{}` is `{list}`, which is neither the `full` nor the `nocov` list of \
                     docs/model-contract.md",
                    keys::FEATURES
                ),
            )
        })?;
        let flops_per_pixel: f64 = self.number(keys::FLOPS_PER_PIXEL)?;
        if !(flops_per_pixel.is_finite() && flops_per_pixel >= 0.0) {
            return Err(model_error(&self.path, format!("metadata `{}` is {flops_per_pixel}", keys::FLOPS_PER_PIXEL)));
        }
        Ok(Common { features, receptive_radius: self.number(keys::RECEPTIVE_RADIUS)?, flops_per_pixel })
    }
}

struct Common {
    features: FeatureSet,
    receptive_radius: usize,
    flops_per_pixel: f64,
}

const V1_HINT: &str = " (a contract-2 model is one file, model.onnx)";
const V2_HINT: &str = " (a contract-1 model is two files, diffuse.onnx and specular.onnx)";

impl Network {
    /// Loads `path` and checks it against contract v1 for `variant` and `component`.
    pub fn load(
        env: &ort::environment::Environment,
        path: &Path,
        variant: Variant,
        component: Component,
        placement: Placement,
    ) -> Result<Network, EngineError> {
        let model = Opened::open(env, path, placement, SessionUse::Run)?;
        let common = model.common(contract::CONTRACT_VERSION, V1_HINT, variant)?;
        model.expect(keys::COMPONENT, component.name(), " (the file's name)")?;
        model.expect(keys::KERNEL_SIZE, &contract::KERNEL_SIZE.to_string(), "")?;
        let architecture = model.meta.get(keys::ARCHITECTURE).cloned().unwrap_or_default();

        check_outlet(path, model.session.inputs(), "color", COLOR_CHANNELS)?;
        check_outlet(path, model.session.inputs(), "features", common.features.feature_channels())?;
        check_outlet(path, model.session.outputs(), "kernel", TAPS)?;

        let info = ModelInfo {
            variant,
            component: Some(component),
            contract: 1,
            features: common.features,
            path: path.to_path_buf(),
            receptive_radius: common.receptive_radius,
            flops_per_pixel: common.flops_per_pixel,
            architecture,
            kernel_size: contract::KERNEL_SIZE,
            levels: 1,
            sha256: model.sha256.clone(),
            input_compression: InputCompression::Graph,
            precision: Precision::Fp32,
            outputs: Outputs::Kernels,
            specular_pyramid: SpecularPyramid::Log,
            detail_gains: false,
        };
        Ok(Network { session: model.session, info })
    }

    /// Runs the network on one region (`color` is `[10, h, w]`, `features` `[C, h, w]`) and
    /// hands the kernel logits `[441, h, w]` to `consume`, without copying them.
    pub fn run<R>(
        &mut self,
        color: &[f32],
        features: &[f32],
        h: usize,
        w: usize,
        consume: impl FnOnce(&[f32]) -> R,
    ) -> Result<R, EngineError> {
        let c = features.len() / (h * w);
        let fail = |e: ort::Error| {
            EngineError::Inference(format!("{} {}: {e}", self.info.variant.name(), self.info.component_name()))
        };
        let color = TensorRef::from_array_view(([1usize, COLOR_CHANNELS, h, w], color)).map_err(fail)?;
        let features = TensorRef::from_array_view(([1usize, c, h, w], features)).map_err(fail)?;
        let outputs = self.session.run(ort::inputs!["color" => color, "features" => features]).map_err(fail)?;
        let (shape, logits) = outputs["kernel"].try_extract_tensor::<f32>().map_err(fail)?;
        if shape.iter().copied().collect::<Vec<i64>>() != [1, TAPS as i64, h as i64, w as i64] {
            return Err(EngineError::Inference(format!(
                "kernel output has shape {shape:?}, expected [1, {TAPS}, {h}, {w}]"
            )));
        }
        Ok(consume(logits))
    }
}

/// A contract-v2 graph: both components, kernels at several scales, in one session.
pub struct MultiScaleNetwork {
    runner: Runner,
    pub info: ModelInfo,
    /// Region sides must be multiples of this (2^(levels − 1)).
    pub size_multiple: usize,
    /// The same network in three stages, where its directory has them and it runs on ONNX
    /// Runtime's CPU provider with the engine's reconstruction ([`super::stages`]).
    pub stages: Option<Box<super::stages::Stages>>,
}

/// What runs a [`MultiScaleNetwork`].
enum Runner {
    /// An ONNX Runtime session; with I/O binding ([`IoBinding`]), where the tensors are
    /// placed and those of the last region shape (`None` without).
    Ort { session: Session, binding: Option<Binding> },
    /// OpenVINO's runtime directly (`--device openvino` where its plugin does not serve
    /// the CPU: [`super::runtime::OpenVino::Runtime`]).
    OpenVino(super::openvino::Compiled),
}

/// One region's outputs, from either runner.
enum RegionOutputs<'a> {
    Ort(ort::session::SessionOutputs<'a>),
    OpenVino(super::openvino::Outputs),
}

/// The I/O binding of a [`MultiScaleNetwork`]: the memory its tensors live in (page-locked
/// host memory for a CUDA session, ONNX Runtime's CPU memory otherwise) and the tensors
/// bound for the last region shape, reused while the shape repeats (a frame's tiles have
/// at most four shapes, and the inner ones come in runs).
struct Binding {
    /// A CUDA session: its binding and run hold `BOUND_RUNS`.
    take_turns: bool,
    inputs_memory: MemoryInfo<'static>,
    outputs_memory: MemoryInfo<'static>,
    bound: Option<Bound>,
}

/// Input tensors `diffuse`, `specular`, `features` of one region shape, with the binding
/// that hands them (and every output, in `Binding::outputs_memory`) to the session.
struct Bound {
    /// `[channels of features, h, w]`.
    dims: [usize; 3],
    io: ort::session::IoBinding,
    inputs: [Tensor<f32>; 3],
}

impl Binding {
    /// Where a `device` session's bound tensors live.
    fn new(device: Device) -> ort::Result<Binding> {
        let (inputs_memory, outputs_memory) = match device {
            Device::Cuda(n) => {
                let id = i32::try_from(n).unwrap_or(i32::MAX);
                (
                    MemoryInfo::new(AllocationDevice::CUDA_PINNED, id, AllocatorType::Device, MemoryType::CPUInput)?,
                    MemoryInfo::new(AllocationDevice::CUDA_PINNED, id, AllocatorType::Device, MemoryType::CPUOutput)?,
                )
            }
            Device::Cpu | Device::OpenVino | Device::Auto => {
                let cpu = || MemoryInfo::new(AllocationDevice::CPU, 0, AllocatorType::Device, MemoryType::Default);
                (cpu()?, cpu()?)
            }
        };
        Ok(Binding { take_turns: matches!(device, Device::Cuda(_)), inputs_memory, outputs_memory, bound: None })
    }
}

/// Held by a CUDA session from the binding of its inputs to the end of its run. On an H100
/// (2026-11-27, docs/results.md "GPU") two workers binding at once failed: one worker's
/// `synchronize_inputs` (a `cudaDeviceSynchronize`) while the other's first run was in CUDA
/// stream capture (CUDA error 900). The GPU runs one network at a time anyway; the workers'
/// decoding, preprocessing and encoding still overlap.
static BOUND_RUNS: std::sync::Mutex<()> = std::sync::Mutex::new(());

/// Largest pyramid depth the engine accepts (a 2^15-pixel pooling grid).
const MAX_LEVELS: usize = 16;

impl MultiScaleNetwork {
    /// Loads `path` and checks it against contract v2 for `variant`.
    pub fn load(
        env: &ort::environment::Environment,
        path: &Path,
        variant: Variant,
        placement: Placement,
    ) -> Result<MultiScaleNetwork, EngineError> {
        // Where OpenVINO's runtime is driven directly, ONNX Runtime's session only checks the
        // graph against the contract.
        let direct = placement.device == Device::OpenVino
            && super::runtime::openvino_route() == Some(super::runtime::OpenVino::Runtime);
        let usage = if direct { SessionUse::Check } else { SessionUse::Run };
        let model = Opened::open(env, path, placement, usage)?;
        let common = model.common(contract::CONTRACT_V2, V2_HINT, variant)?;
        let kernel_size: usize = model.number(keys::KERNEL_SIZE)?;
        if kernel_size % 2 == 0 {
            return Err(model_error(
                path,
                format!("metadata `{}` is {kernel_size}, expected an odd number", keys::KERNEL_SIZE),
            ));
        }
        let levels: usize = model.number(keys::LEVELS)?;
        if !(1..=MAX_LEVELS).contains(&levels) {
            return Err(model_error(
                path,
                format!("metadata `{}` is {levels}, expected 1 to {MAX_LEVELS}", keys::LEVELS),
            ));
        }
        let size_multiple = 1usize << (levels - 1);
        model.expect(
            keys::SIZE_MULTIPLE,
            &size_multiple.to_string(),
            &format!(" (2^(levels − 1), levels = {levels})"),
        )?;
        let architecture = model.get(keys::ARCHITECTURE)?.to_string();
        let input_compression =
            model.optional(keys::INPUT_COMPRESSION, InputCompression::parse, "`graph` or `engine`")?;
        let outputs = model.optional(keys::OUTPUTS, Outputs::parse, "`kernels` or `filtered`")?;
        let precision =
            model.optional(keys::PRECISION, Precision::parse, "`fp32`, `fp16` or `int8` (then a description)")?;
        let specular_pyramid = model.optional(keys::SPECULAR_PYRAMID, SpecularPyramid::parse, "`log` or `linear`")?;
        if outputs == Outputs::Filtered && input_compression == InputCompression::Engine {
            return Err(model_error(
                path,
                format!(
                    "metadata `{}` is `filtered` but `{}` is `engine`: a graph that reconstructs needs its \
                     inputs uncompressed, so it must compress them itself (`graph`)",
                    keys::OUTPUTS,
                    keys::INPUT_COMPRESSION
                ),
            ));
        }

        let inputs = model.session.inputs();
        let expected_inputs = [
            ("diffuse", COLOR_CHANNELS),
            ("specular", COLOR_CHANNELS),
            ("features", common.features.feature_channels()),
        ];
        let mut expected_outputs = Vec::new();
        // Detail gains are optional outputs: a graph with `gain_0` has one per blend.
        let detail_gains =
            outputs == Outputs::Kernels && levels > 1 && model.session.outputs().iter().any(|o| o.name() == "gain_0");
        match outputs {
            Outputs::Kernels => {
                for l in 0..levels {
                    expected_outputs.push((format!("kernel_{l}"), 2 * kernel_size * kernel_size));
                    if l + 1 < levels {
                        expected_outputs.push((format!("blend_{l}"), 2));
                        if detail_gains {
                            expected_outputs.push((format!("gain_{l}"), 2));
                        }
                    }
                }
            }
            Outputs::Filtered => {
                expected_outputs.extend(FILTERED_OUTPUTS.map(|name| (name.to_string(), 3)));
            }
        }
        for (name, channels) in expected_inputs {
            check_outlet(path, inputs, name, channels)?;
        }
        for (name, channels) in &expected_outputs {
            check_outlet(path, model.session.outputs(), name, *channels).map_err(|e| with_levels_hint(e, levels))?;
        }
        check_no_extra(path, "input", inputs, expected_inputs.iter().map(|e| e.0))?;
        check_no_extra(path, "output", model.session.outputs(), expected_outputs.iter().map(|e| e.0.as_str()))
            .map_err(|e| with_levels_hint(e, levels))?;

        let info = ModelInfo {
            variant,
            component: None,
            contract: 2,
            features: common.features,
            path: path.to_path_buf(),
            receptive_radius: common.receptive_radius,
            flops_per_pixel: common.flops_per_pixel,
            architecture,
            kernel_size,
            levels,
            sha256: model.sha256.clone(),
            input_compression,
            outputs,
            precision,
            specular_pyramid,
            detail_gains,
        };
        let runner = if direct {
            // ONNX Runtime's session has checked the graph against the contract; OpenVINO
            // compiles the same file and runs it.
            let outputs = expected_outputs.into_iter().map(|(name, _)| name).collect();
            let properties = openvino_properties(placement.threads.max(1)).map_err(|e| model_error(path, e))?;
            let compiled = super::openvino::Compiled::new(path, &properties, outputs)
                .map_err(|e| model_error(path, format!("cannot load with OpenVINO: {e}")))?;
            Runner::OpenVino(compiled)
        } else if placement.io_binding.enabled() {
            let binding = Binding::new(placement.device)
                .map_err(|e| model_error(path, format!("cannot set up ONNX Runtime's I/O binding: {e}")))?;
            Runner::Ort { session: model.session, binding: Some(binding) }
        } else {
            Runner::Ort { session: model.session, binding: None }
        };
        Ok(MultiScaleNetwork { runner, info, size_multiple, stages: None })
    }

    /// Runs the graph on one region (sides multiples of `size_multiple`; `diffuse` and
    /// `specular` are `[10, h, w]`, `features` `[C, h, w]`) and hands the two components'
    /// pyramids of logits to `consume`, without copying them.
    pub fn run<R>(
        &mut self,
        diffuse: &[f32],
        specular: &[f32],
        features: &[f32],
        h: usize,
        w: usize,
        consume: impl FnOnce([Pyramid; 2]) -> R,
    ) -> Result<R, EngineError> {
        let (k, levels) = (self.info.kernel_size, self.info.levels);
        let name = self.info.variant;
        let linear = self.info.specular_pyramid == SpecularPyramid::Linear;
        let detail_gains = self.info.detail_gains;
        let outputs = self.infer(diffuse, specular, features, h, w)?;
        let tensor = |output: String, channels: usize, l: usize| {
            extract(&outputs, name, &output, [channels, h >> l, w >> l], (w, h))
        };
        let mut pyramids = [false, linear].map(|linear_means| Pyramid {
            kernel_size: k,
            kernels: Vec::new(),
            blends: Vec::new(),
            gains: Vec::new(),
            linear_means,
        });
        for l in 0..levels {
            let kernels = tensor(format!("kernel_{l}"), 2 * k * k, l)?;
            let (d, s) = kernels.split_at(kernels.len() / 2);
            pyramids[0].kernels.push(d);
            pyramids[1].kernels.push(s);
            if l + 1 < levels {
                let blends = tensor(format!("blend_{l}"), 2, l)?;
                let (d, s) = blends.split_at(blends.len() / 2);
                pyramids[0].blends.push(d);
                pyramids[1].blends.push(s);
                if detail_gains {
                    let gains = tensor(format!("gain_{l}"), 2, l)?;
                    let (d, s) = gains.split_at(gains.len() / 2);
                    pyramids[0].gains.push(d);
                    pyramids[1].gains.push(s);
                }
            }
        }
        Ok(consume(pyramids))
    }

    /// Runs a graph with the reconstruction in it (`mcdenoise.outputs` `filtered`) on one
    /// region and hands the filtered preprocessed color of the diffuse and the specular
    /// (each `[3, h, w]`) to `consume`.
    pub fn run_filtered<R>(
        &mut self,
        diffuse: &[f32],
        specular: &[f32],
        features: &[f32],
        h: usize,
        w: usize,
        consume: impl FnOnce([&[f32]; 2]) -> R,
    ) -> Result<R, EngineError> {
        let name = self.info.variant;
        let outputs = self.infer(diffuse, specular, features, h, w)?;
        let [d, s] = FILTERED_OUTPUTS;
        let planes = [extract(&outputs, name, d, [3, h, w], (w, h))?, extract(&outputs, name, s, [3, h, w], (w, h))?];
        Ok(consume(planes))
    }

    /// Runs the session on one region's inputs (`[10, h, w]`, `[10, h, w]`, `[C, h, w]`).
    fn infer(
        &mut self,
        diffuse: &[f32],
        specular: &[f32],
        features: &[f32],
        h: usize,
        w: usize,
    ) -> Result<RegionOutputs<'_>, EngineError> {
        let c = features.len() / (h * w);
        let name = self.info.variant;
        let fail = |e: ort::Error| EngineError::Inference(format!("{name}: {e}"));
        let (session, binding) = match &mut self.runner {
            Runner::Ort { session, binding } => (session, binding),
            Runner::OpenVino(compiled) => {
                return compiled
                    .run([diffuse, specular, features], [c, h, w])
                    .map(RegionOutputs::OpenVino)
                    .map_err(|e| EngineError::Inference(format!("{name}: {e}")))
            }
        };
        // Bound runs on a GPU take turns across the process's workers (see `BOUND_RUNS`).
        let _turn = binding
            .as_ref()
            .filter(|b| b.take_turns)
            .map(|_| BOUND_RUNS.lock().unwrap_or_else(std::sync::PoisonError::into_inner));
        if let Some(binding) = binding {
            bind(session, binding, [diffuse, specular, features], [c, h, w]).map_err(fail)?;
            let bound = binding.bound.as_ref().expect("bound by `bind`");
            return session.run_binding(&bound.io).map(RegionOutputs::Ort).map_err(fail);
        }
        let diffuse = TensorRef::from_array_view(([1usize, COLOR_CHANNELS, h, w], diffuse)).map_err(fail)?;
        let specular = TensorRef::from_array_view(([1usize, COLOR_CHANNELS, h, w], specular)).map_err(fail)?;
        let features = TensorRef::from_array_view(([1usize, c, h, w], features)).map_err(fail)?;
        session
            .run(ort::inputs!["diffuse" => diffuse, "specular" => specular, "features" => features])
            .map(RegionOutputs::Ort)
            .map_err(fail)
    }
}

/// Writes one region's inputs (`[diffuse, specular, features]`, features of `dims` =
/// `[channels, h, w]`) into the bound tensors, allocating and binding them first where the
/// shape changed, and binds them again: on a GPU that queues their copy to the device.
fn bind(session: &Session, binding: &mut Binding, data: [&[f32]; 3], dims: [usize; 3]) -> ort::Result<()> {
    let [c, h, w] = dims;
    if binding.bound.as_ref().is_none_or(|b| b.dims != dims) {
        // The previous shape's tensors are freed before the new ones are allocated.
        binding.bound = None;
        let allocator = Allocator::new(session, binding.inputs_memory.clone())?;
        let tensor = |channels: usize| Tensor::<f32>::new(&allocator, [1, channels, h, w]);
        let inputs = [tensor(COLOR_CHANNELS)?, tensor(COLOR_CHANNELS)?, tensor(c)?];
        binding.bound = Some(Bound { dims, io: session.create_binding()?, inputs });
    }
    let bound = binding.bound.as_mut().expect("bound above");
    // The outputs are bound again before every run: after a run the binding holds the
    // outputs it allocated, and a run handed those as its outputs failed on an H100
    // (ONNX Runtime's CopyTensorAsync with its source equal to its destination).
    for output in session.outputs() {
        bound.io.bind_output_to_device(output.name(), &binding.outputs_memory)?;
    }
    for ((name, tensor), src) in ["diffuse", "specular", "features"].into_iter().zip(&mut bound.inputs).zip(data) {
        tensor.extract_tensor_mut().1.copy_from_slice(src);
        bound.io.bind_input(name, tensor)?;
    }
    // The copies to the device are done before the run reads them (a no-op on the CPU).
    bound.io.synchronize_inputs()
}

/// The data of output `output`, checked to be `[1, channels, rows, columns]` (`dims`) for a
/// `region` = (w, h) region.
fn extract<'a>(
    outputs: &'a RegionOutputs<'_>,
    variant: Variant,
    output: &str,
    dims: [usize; 3],
    region: (usize, usize),
) -> Result<&'a [f32], EngineError> {
    let fail = |e: String| EngineError::Inference(format!("{variant}: {e}"));
    let (shape, data): (Vec<i64>, &[f32]) = match outputs {
        RegionOutputs::Ort(outputs) => {
            let (shape, data) = outputs[output].try_extract_tensor::<f32>().map_err(|e| fail(e.to_string()))?;
            (shape.iter().copied().collect(), data)
        }
        RegionOutputs::OpenVino(outputs) => outputs.get(output).map_err(fail)?,
    };
    let want = [1, dims[0] as i64, dims[1] as i64, dims[2] as i64];
    if shape != want {
        let (w, h) = region;
        return Err(EngineError::Inference(format!(
            "{variant}: output `{output}` has shape {shape:?}, expected {want:?} for a {w}x{h} region"
        )));
    }
    Ok(data)
}

fn with_levels_hint(e: EngineError, levels: usize) -> EngineError {
    match e {
        EngineError::Model { path, reason } => EngineError::Model {
            path,
            reason: format!(
                "{reason}; `{}` = {levels} expects outputs kernel_0 … kernel_{} and blend_0 … blend_{} \
                 (and, for detail gains, gain_0 … gain_{})",
                keys::LEVELS,
                levels - 1,
                levels as isize - 2,
                levels as isize - 2
            ),
        },
        other => other,
    }
}

/// Refuses graph inputs/outputs other than `expected`.
fn check_no_extra<'a>(
    path: &Path,
    kind: &str,
    outlets: &[ort::value::Outlet],
    expected: impl Iterator<Item = &'a str>,
) -> Result<(), EngineError> {
    let expected: HashSet<&str> = expected.collect();
    match outlets.iter().find(|o| !expected.contains(o.name())) {
        Some(extra) => Err(model_error(path, format!("graph has an unexpected {kind} `{}`", extra.name()))),
        None => Ok(()),
    }
}

/// The channel count of a float32 rank-4 graph input/output with a fixed channel dimension.
pub(super) fn outlet_channels(path: &Path, outlet: &ort::value::Outlet) -> Result<usize, EngineError> {
    let name = outlet.name();
    match outlet.dtype() {
        ValueType::Tensor { ty, shape, .. } if *ty == ort::value::TensorElementType::Float32 && shape.len() == 4 => {
            usize::try_from(shape[1])
                .map_err(|_| model_error(path, format!("`{name}` has no fixed channel count ({})", shape[1])))
        }
        other => Err(model_error(path, format!("`{name}` is {other:?}, expected a float32 tensor (N, C, H, W)"))),
    }
}

/// Checks that a graph input/output exists, is float32, rank 4, with `channels` channels
/// (or a dynamic channel dimension).
fn check_outlet(path: &Path, outlets: &[ort::value::Outlet], name: &str, channels: usize) -> Result<(), EngineError> {
    let Some(outlet) = outlets.iter().find(|o| o.name() == name) else {
        let names: Vec<&str> = outlets.iter().map(|o| o.name()).collect();
        return Err(model_error(path, format!("graph has no `{name}` (it has {})", names.join(", "))));
    };
    match outlet.dtype() {
        ValueType::Tensor { ty, shape, .. } => {
            if *ty != ort::value::TensorElementType::Float32 {
                return Err(model_error(path, format!("`{name}` is {ty:?}, expected float32")));
            }
            if shape.len() != 4 {
                return Err(model_error(path, format!("`{name}` has rank {}, expected 4 (N, C, H, W)", shape.len())));
            }
            if shape[1] != -1 && shape[1] != channels as i64 {
                return Err(model_error(path, format!("`{name}` has {} channels, expected {channels}", shape[1])));
            }
            Ok(())
        }
        other => Err(model_error(path, format!("`{name}` is {other:?}, expected a tensor"))),
    }
}

/// The networks of one variant: two contract-v1 graphs or one contract-v2 graph.
pub enum Networks {
    Pair { diffuse: Network, specular: Network },
    MultiScale(MultiScaleNetwork),
}

/// A loaded variant.
pub struct VariantModel {
    pub variant: Variant,
    /// The feature inputs its networks take.
    pub features: FeatureSet,
    pub networks: Networks,
}

impl VariantModel {
    pub fn infos(&self) -> Vec<&ModelInfo> {
        match &self.networks {
            Networks::Pair { diffuse, specular } => vec![&diffuse.info, &specular.info],
            Networks::MultiScale(net) => vec![&net.info],
        }
    }

    /// FLOPs per pixel of both components.
    pub fn flops_per_pixel(&self) -> f64 {
        self.infos().iter().map(|i| i.flops_per_pixel).sum()
    }
}

/// A subdirectory of the models directory that holds a variant's model files, found but
/// not loaded.
#[derive(Clone, Debug)]
pub struct VariantDir {
    pub variant: Variant,
    pub dir: PathBuf,
}

impl VariantDir {
    /// The variant in `dir`, if `dir` holds a model (`model.onnx`, or `diffuse.onnx` and
    /// `specular.onnx`); an error for a directory whose name is not a variant's, or that
    /// holds both contracts' files.
    fn find(dir: &Path) -> Result<Option<VariantDir>, EngineError> {
        let has_v2 = dir.join("model.onnx").exists();
        let has_v1 = Component::ALL.iter().any(|c| dir.join(format!("{}.onnx", c.name())).exists());
        if !has_v2 && !has_v1 {
            return Ok(None);
        }
        let name = dir.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
        let variant = Variant::parse(&name).ok_or_else(|| {
            model_error(
                dir,
                format!(
                    "`{name}` is not a valid variant name (at most {} ASCII letters, digits, `_`, `-`, `.`)",
                    Variant::MAX_LEN
                ),
            )
        })?;
        if has_v2 && has_v1 {
            return Err(model_error(
                dir,
                "holds both model.onnx (contract 2) and diffuse.onnx/specular.onnx (contract 1); keep one",
            ));
        }
        Ok(Some(VariantDir { variant, dir: dir.to_path_buf() }))
    }
}

/// Loads the model of a variant found by [`find_variants`].
pub fn load_variant(
    env: &ort::environment::Environment,
    found: &VariantDir,
    placement: Placement,
) -> Result<VariantModel, EngineError> {
    let (variant, dir) = (found.variant, found.dir.as_path());
    let v2 = dir.join("model.onnx");
    let v1 = Component::ALL.map(|c| dir.join(format!("{}.onnx", c.name())));
    if v2.exists() {
        let (recon, half) = (dir.join(RECON_FILE), dir.join(RECON_FP16_FILE));
        let on_gpu = matches!(placement.device, Device::Cuda(_));
        let fp16 = match placement.precision {
            Precision::Fp32 | Precision::Int8 => false,
            Precision::Fp16 if placement.reconstruction == Reconstruction::Engine => {
                return Err(model_error(
                    dir,
                    format!(
                        "--precision fp16 runs the half-precision network with its reconstruction in the graph \
                         ({RECON_FP16_FILE}); it needs --reconstruction graph or auto, not engine"
                    ),
                ))
            }
            Precision::Fp16 if !half.exists() => {
                return Err(model_error(
                    dir,
                    format!(
                        "--precision fp16 needs {RECON_FP16_FILE} beside model.onnx (the network in half precision \
                         with its reconstruction, `export_ms --recon --fp16`)"
                    ),
                ))
            }
            Precision::Fp16 => true,
            Precision::Auto => on_gpu && half.exists() && placement.reconstruction != Reconstruction::Engine,
        };
        let in_graph = fp16
            || match placement.reconstruction {
                Reconstruction::Engine => false,
                Reconstruction::Graph if !recon.exists() => {
                    return Err(model_error(
                        dir,
                        format!(
                            "--reconstruction graph needs {RECON_FILE} beside model.onnx (the same network with \
                             its reconstruction, `export_ms --recon`)"
                        ),
                    ))
                }
                Reconstruction::Graph => true,
                Reconstruction::Auto => recon.exists() && on_gpu,
            };
        if !in_graph && on_gpu {
            tracing::warn!(
                variant = %variant,
                "no {RECON_FILE}: the kernels are applied on the CPU after each GPU inference"
            );
        }
        let file = match (in_graph, fp16) {
            (true, true) => half,
            (true, false) => recon,
            (false, _) => v2,
        };
        let mut net = MultiScaleNetwork::load(env, &file, variant, placement)?;
        // The stages serve the CPU provider in float32 with the engine's reconstruction.
        if !in_graph && placement.device == Device::Cpu && !placement.io_binding.enabled() && levels_ok(&net) {
            net.stages = super::stages::Stages::load(env, &net.info, placement)?.map(Box::new);
        }
        if fp16 && net.info.precision != Precision::Fp16 {
            return Err(model_error(
                &file,
                format!(
                    "metadata `{}` is `{}`, expected `fp16` in this file",
                    keys::PRECISION,
                    net.info.precision.name()
                ),
            ));
        }
        let want = if in_graph { Outputs::Filtered } else { Outputs::Kernels };
        if net.info.outputs != want {
            return Err(model_error(
                &file,
                format!(
                    "metadata `{}` is `{}`, expected `{}` in this file",
                    keys::OUTPUTS,
                    net.info.outputs.name(),
                    want.name()
                ),
            ));
        }
        return Ok(VariantModel { variant, features: net.info.features, networks: Networks::MultiScale(net) });
    }
    let [d, s] = &v1;
    let diffuse = Network::load(env, d, variant, Component::Diffuse, placement)?;
    let specular = Network::load(env, s, variant, Component::Specular, placement)?;
    if diffuse.info.features != specular.info.features {
        return Err(model_error(
            dir,
            format!(
                "diffuse.onnx takes the `{}` features but specular.onnx the `{}` ones",
                diffuse.info.features.name(),
                specular.info.features.name()
            ),
        ));
    }
    Ok(VariantModel { variant, features: diffuse.info.features, networks: Networks::Pair { diffuse, specular } })
}

/// Whether a network has the levels the staged path reconstructs (at least two).
fn levels_ok(net: &MultiScaleNetwork) -> bool {
    net.info.levels >= 2 && net.info.outputs == Outputs::Kernels
}

/// Loads every variant under `dir` ([`find_variants`]), in name order.
pub fn load_models(
    env: &ort::environment::Environment,
    dir: &Path,
    placement: Placement,
) -> Result<Vec<VariantModel>, EngineError> {
    find_variants(dir)?.iter().map(|found| load_variant(env, found, placement)).collect()
}

/// The variants under `dir`: each subdirectory holding a model (`model.onnx`, or
/// `diffuse.onnx` and `specular.onnx`), in name order; an error naming what was expected
/// where there is none.
pub fn find_variants(dir: &Path) -> Result<Vec<VariantDir>, EngineError> {
    let mut dirs: Vec<PathBuf> = match std::fs::read_dir(dir) {
        Ok(entries) => entries
            .filter_map(Result::ok)
            .map(|e| e.path())
            .filter(|p| p.is_dir() && !p.file_name().is_some_and(|n| n.to_string_lossy().starts_with('.')))
            .collect(),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Vec::new(),
        Err(e) => return Err(model_error(dir, format!("cannot list the directory: {e}"))),
    };
    dirs.sort();
    let mut found = Vec::new();
    for d in dirs {
        found.extend(VariantDir::find(&d)?);
    }
    if found.is_empty() {
        // A relative path is resolved against the current directory: say which one.
        let resolved = match std::path::absolute(dir) {
            Ok(abs) if abs != dir => format!(" ({} from the current directory)", abs.display()),
            _ => String::new(),
        };
        let what = if dir.is_dir() { "no model variants found" } else { "no such directory" };
        return Err(model_error(
            dir,
            format!(
                "{what}{resolved}: expected subdirectories such as full/ or nocov/ holding model.onnx, or \
                 diffuse.onnx and specular.onnx (the shipped ones are in the repository's models/)"
            ),
        ));
    }
    Ok(found)
}
