//! OpenVINO's runtime driven directly, for the contract-v2 networks on CPUs whose vendor
//! OpenVINO's ONNX Runtime plugin does not serve.
//!
//! The plugin (`onnxruntime-ep-openvino`, [`super::runtime::register_openvino`]) offers
//! only Intel hardware to ONNX Runtime: on an AMD CPU it registers and offers no device.
//! OpenVINO's CPU runtime itself runs on any x86-64 CPU, and in bfloat16 on those with
//! AVX512-BF16 (AMD EPYC since Zen 4), where it ran the default network about 1.5× as fast
//! as ONNX Runtime's float32 CPU provider (docs/results/speed-work.md). There `--device
//! openvino` compiles each contract-v2 graph with OpenVINO's C API (the `openvino` crate,
//! linked at run time like ONNX Runtime) after ONNX Runtime has checked it against the
//! contract; the other networks (contract v1, the paper's) stay on ONNX Runtime's CPU
//! provider. The runtime is the plugin's own (the same `libopenvino.so` in the same
//! directory), with OpenVINO's C library (`libopenvino_c.so`) beside it, which
//! `scripts/install-ort` takes from the `openvino` wheel of the same build.

use std::path::{Path, PathBuf};
use std::sync::{Mutex, OnceLock};

use openvino::{CompiledModel, Core, DeviceType, ElementType, InferRequest, RwPropertyKey, Shape, Tensor};

/// OpenVINO's library version suffix (2026.4.1), as the plugin's libraries carry it.
pub const OPENVINO_SO_VERSION: &str = "2641";

/// One OpenVINO core for the process: compiling takes it (the CPU properties are the
/// core's), running does not.
static CORE: OnceLock<Result<Mutex<Core>, String>> = OnceLock::new();

/// The directory the runtime was loaded from, once it has.
static LOADED: OnceLock<PathBuf> = OnceLock::new();

/// Loads OpenVINO's runtime and C library from `dir` (once per process; later calls return
/// the first call's outcome) and checks that it offers the CPU.
pub fn load(dir: &Path) -> Result<&'static Path, String> {
    let core = CORE.get_or_init(|| {
        let runtime = dir.join(format!("libopenvino.so.{OPENVINO_SO_VERSION}"));
        let c_api = dir.join(format!("libopenvino_c.so.{OPENVINO_SO_VERSION}"));
        for file in [&runtime, &c_api] {
            if !file.is_file() {
                return Err(format!(
                    "{} not found; `scripts/install-ort` installs OpenVINO's runtime and C library there",
                    file.display()
                ));
            }
        }
        // The C library names the runtime by its soname without a path: loaded first from
        // its own path, the runtime satisfies that. It stays loaded for the process.
        // SAFETY: loading a library runs its initialisers; OpenVINO's have no preconditions.
        let library = unsafe { libloading::Library::new(&runtime) }
            .map_err(|e| format!("cannot load {}: {e}", runtime.display()))?;
        std::mem::forget(library);
        openvino_sys::library::load_from(&c_api).map_err(|e| format!("cannot load {}: {e}", c_api.display()))?;
        let core = Core::new().map_err(|e| format!("OpenVINO's core: {e}"))?;
        let devices = core.available_devices().map_err(|e| format!("OpenVINO's devices: {e}"))?;
        if !devices.iter().any(|d| d.as_ref() == "CPU") {
            return Err(format!("OpenVINO in {} offers no CPU device", dir.display()));
        }
        let _ = LOADED.set(dir.to_path_buf());
        Ok(Mutex::new(core))
    });
    core.as_ref().map(|_| LOADED.get().expect("set with the core").as_path()).map_err(Clone::clone)
}

/// A contract-v2 graph compiled by OpenVINO for the CPU, with its request and the input
/// tensors of the last region shape (reused while the shape repeats). The fields drop in
/// order: the tensors, then the request, then the compiled model.
pub struct Compiled {
    inputs: Option<([usize; 3], [Tensor; 3])>,
    request: InferRequest,
    outputs: Vec<String>,
    _model: CompiledModel,
}

/// The graph's inputs, in the order [`Compiled::run`] takes their data.
const INPUTS: [&str; 3] = ["diffuse", "specular", "features"];

impl Compiled {
    /// Compiles `path` for the CPU with `properties` (OpenVINO CPU properties, name and
    /// value), through the core [`load`] made; `outputs` are the graph's output names.
    pub fn new(path: &Path, properties: &[(String, String)], outputs: Vec<String>) -> Result<Compiled, String> {
        let core = CORE.get().and_then(|c| c.as_ref().ok()).ok_or("OpenVINO's runtime is not loaded")?;
        let mut core = core.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
        let file = path.to_str().ok_or_else(|| format!("{} is not UTF-8", path.display()))?;
        let model = core.read_model_from_file(file, "").map_err(|e| format!("OpenVINO cannot read it: {e}"))?;
        for (key, value) in properties {
            core.set_property(&DeviceType::CPU, &RwPropertyKey::Other(key.clone().into()), value)
                .map_err(|e| format!("OpenVINO's CPU property {key} = {value}: {e}"))?;
        }
        let mut compiled =
            core.compile_model(&model, DeviceType::CPU).map_err(|e| format!("OpenVINO cannot compile it: {e}"))?;
        let request = compiled.create_infer_request().map_err(|e| format!("OpenVINO's request: {e}"))?;
        Ok(Compiled { inputs: None, request, outputs, _model: compiled })
    }

    /// Runs one region: `data` are the inputs' values (`[10, h, w]`, `[10, h, w]`, `dims` =
    /// `[C, h, w]`), copied into the request's tensors; returns every output by name.
    pub fn run(&mut self, data: [&[f32]; 3], dims: [usize; 3]) -> Result<Outputs, String> {
        let [c, h, w] = dims;
        if self.inputs.as_ref().is_none_or(|(d, _)| *d != dims) {
            self.inputs = None;
            let tensor = |channels: usize| {
                let shape = Shape::new(&[1, channels as i64, h as i64, w as i64]).map_err(|e| e.to_string())?;
                Tensor::new(ElementType::F32, &shape).map_err(|e| e.to_string())
            };
            let tensors =
                [tensor(super::contract::COLOR_CHANNELS)?, tensor(super::contract::COLOR_CHANNELS)?, tensor(c)?];
            for (name, tensor) in INPUTS.iter().zip(&tensors) {
                self.request.set_tensor(name, tensor).map_err(|e| format!("input `{name}`: {e}"))?;
            }
            self.inputs = Some((dims, tensors));
        }
        let (_, tensors) = self.inputs.as_mut().expect("made above");
        for ((name, tensor), src) in INPUTS.iter().zip(tensors.iter_mut()).zip(data) {
            let dst = tensor.get_data_mut::<f32>().map_err(|e| format!("input `{name}`: {e}"))?;
            if dst.len() != src.len() {
                return Err(format!("input `{name}`: {} values for a tensor of {}", src.len(), dst.len()));
            }
            dst.copy_from_slice(src);
        }
        self.request.infer().map_err(|e| format!("OpenVINO's inference: {e}"))?;
        let tensors = self
            .outputs
            .iter()
            .map(|name| {
                let tensor = self.request.get_tensor(name).map_err(|e| format!("output `{name}`: {e}"))?;
                Ok((name.clone(), tensor))
            })
            .collect::<Result<Vec<_>, String>>()?;
        Ok(Outputs(tensors))
    }
}

/// A region's outputs from [`Compiled::run`], by name.
pub struct Outputs(Vec<(String, Tensor)>);

impl Outputs {
    /// Output `name`'s shape and values.
    pub fn get(&self, name: &str) -> Result<(Vec<i64>, &[f32]), String> {
        let (_, tensor) =
            self.0.iter().find(|(n, _)| n == name).ok_or_else(|| format!("OpenVINO has no output `{name}`"))?;
        let shape = tensor.get_shape().map_err(|e| format!("output `{name}`: {e}"))?;
        let data = tensor.get_data::<f32>().map_err(|e| format!("output `{name}`: {e}"))?;
        Ok((shape.get_dimensions().to_vec(), data))
    }
}
