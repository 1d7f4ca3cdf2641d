//! Locating and loading the ONNX Runtime shared library.
//!
//! The library is loaded at run time (ort's `load-dynamic`), so the binary builds without
//! it and a missing library is a clear error instead of a link failure or a panic.
//! `scripts/setup` installs it from the pinned `onnxruntime` wheel.

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use ort::environment::Environment;

/// The ONNX Runtime version the engine is built against (ort's `api-31`).
pub const ORT_VERSION: &str = "1.31.1";

static ENVIRONMENT: OnceLock<Result<Environment, String>> = OnceLock::new();
static LIBRARY: OnceLock<PathBuf> = OnceLock::new();
static OPENVINO: OnceLock<Result<OpenVino, String>> = OnceLock::new();

/// The file name of OpenVINO's execution provider plugin (`onnxruntime-ep-openvino`), which
/// `scripts/install-ort` puts, with the OpenVINO runtime it carries, in an `openvino`
/// directory beside ONNX Runtime's library.
pub const OPENVINO_PLUGIN: &str = "libonnxruntime_providers_openvino_plugin.so";

/// The name ONNX Runtime gives the plugin's execution provider.
pub const OPENVINO_EP: &str = "OpenVINOExecutionProvider";

/// The library [`environment`] loaded, once it has.
pub fn library() -> Option<&'static Path> {
    LIBRARY.get().map(PathBuf::as_path)
}

/// Where the library is looked for, in order: an explicit path, `$ORT_DYLIB_PATH`,
/// `$MCDENOISE_HOME/lib`, `~/.cache/mcdenoise/lib`, the executable's directory and its
/// `../lib`, `/usr/local/lib`, `/usr/lib`.
pub fn candidates(explicit: Option<&Path>) -> Vec<PathBuf> {
    let file = format!("libonnxruntime.so.{ORT_VERSION}");
    let mut out = Vec::new();
    if let Some(p) = explicit {
        out.push(p.to_path_buf());
    }
    if let Some(p) = std::env::var_os("ORT_DYLIB_PATH").filter(|p| !p.is_empty()) {
        out.push(PathBuf::from(p));
    }
    if let Some(home) = std::env::var_os("MCDENOISE_HOME").filter(|p| !p.is_empty()) {
        out.push(PathBuf::from(home).join("lib").join(&file));
    }
    if let Some(home) = std::env::var_os("HOME").filter(|p| !p.is_empty()) {
        out.push(PathBuf::from(home).join(".cache/mcdenoise/lib").join(&file));
    }
    if let Some(dir) = std::env::current_exe().ok().and_then(|e| e.parent().map(Path::to_path_buf)) {
        out.push(dir.join(&file));
        out.push(dir.join("../lib").join(&file));
    }
    for dir in ["/usr/local/lib", "/usr/lib"] {
        out.push(Path::new(dir).join(&file));
        out.push(Path::new(dir).join("libonnxruntime.so"));
    }
    out
}

/// Where OpenVINO's plugin is looked for: `$MCDENOISE_OPENVINO_PLUGIN` alone where it is
/// set, else the `openvino` directory beside the loaded ONNX Runtime library, then under
/// `$MCDENOISE_HOME/lib` and `~/.cache/mcdenoise/lib`.
pub fn openvino_candidates() -> Vec<PathBuf> {
    if let Some(p) = std::env::var_os("MCDENOISE_OPENVINO_PLUGIN").filter(|p| !p.is_empty()) {
        return vec![PathBuf::from(p)];
    }
    let mut out = Vec::new();
    if let Some(dir) = library().and_then(Path::parent) {
        out.push(dir.join("openvino").join(OPENVINO_PLUGIN));
    }
    if let Some(home) = std::env::var_os("MCDENOISE_HOME").filter(|p| !p.is_empty()) {
        out.push(PathBuf::from(home).join("lib/openvino").join(OPENVINO_PLUGIN));
    }
    if let Some(home) = std::env::var_os("HOME").filter(|p| !p.is_empty()) {
        out.push(PathBuf::from(home).join(".cache/mcdenoise/lib/openvino").join(OPENVINO_PLUGIN));
    }
    out
}

/// How `--device openvino` reaches OpenVINO in this process ([`openvino`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum OpenVino {
    /// Through ONNX Runtime's plugin, which offers the CPU (an Intel CPU): every network's
    /// session runs on it.
    Plugin,
    /// OpenVINO's runtime driven directly (a CPU the plugin does not serve): the
    /// contract-v2 networks are compiled by it, the others run on ONNX Runtime's CPU
    /// provider (`super::openvino`).
    Runtime,
}

impl OpenVino {
    /// The route's name in reports and logs: `plugin` or `runtime`.
    pub fn name(self) -> &'static str {
        match self {
            OpenVino::Plugin => "plugin",
            OpenVino::Runtime => "runtime",
        }
    }
}

/// Registers OpenVINO's execution provider plugin with `env` (once per process; later calls
/// return the first answer): [`OpenVino::Plugin`] where it offers the CPU, else OpenVINO's
/// runtime from the plugin's directory is loaded for [`OpenVino::Runtime`].
/// `$MCDENOISE_OPENVINO_VIA` (`plugin` or `runtime`) takes one of the two on any CPU.
pub fn openvino(env: &Environment) -> Result<OpenVino, String> {
    OPENVINO
        .get_or_init(|| {
            let via = std::env::var("MCDENOISE_OPENVINO_VIA").unwrap_or_default();
            let via = match via.trim() {
                "" | "auto" => None,
                "plugin" => Some(OpenVino::Plugin),
                "runtime" => Some(OpenVino::Runtime),
                other => {
                    return Err(format!("MCDENOISE_OPENVINO_VIA is `{other}`, expected `plugin`, `runtime` or `auto`"))
                }
            };
            let tried = openvino_candidates();
            let Some(path) = tried.iter().find(|p| p.is_file()) else {
                return Err(format!(
                    "OpenVINO's execution provider plugin not found (looked for {}). Install it with \
                     `scripts/install-ort` (part of `scripts/setup`), or point MCDENOISE_OPENVINO_PLUGIN at {OPENVINO_PLUGIN}",
                    tried.iter().map(|p| p.display().to_string()).collect::<Vec<_>>().join(", ")
                ));
            };
            let dir = path.parent().unwrap_or(Path::new("."));
            if via == Some(OpenVino::Runtime) {
                return super::openvino::load(dir).map(|_| OpenVino::Runtime);
            }
            env.register_ep_library("openvino", path)
                .map_err(|e| format!("cannot register OpenVINO's plugin {}: {e}", path.display()))?;
            if openvino_cpu(env).next().is_some() {
                return Ok(OpenVino::Plugin);
            }
            let no_cpu = format!("OpenVINO's plugin {} offers no CPU device (it serves Intel CPUs only)", path.display());
            if via == Some(OpenVino::Plugin) {
                return Err(no_cpu);
            }
            // OpenVINO's runtime beside the plugin serves the rest of the x86-64 CPUs.
            super::openvino::load(dir).map(|_| OpenVino::Runtime).map_err(|e| format!("{no_cpu}, and {e}"))
        })
        .clone()
}

/// How [`openvino`] reached OpenVINO, once it has.
pub fn openvino_route() -> Option<OpenVino> {
    OPENVINO.get().and_then(|r| r.as_ref().ok()).copied()
}

/// The CPU devices OpenVINO's plugin offers, once registered.
pub fn openvino_cpu(env: &Environment) -> impl Iterator<Item = ort::device::Device<'_>> {
    env.devices().filter(|d| {
        d.ep().is_ok_and(|ep| ep == OPENVINO_EP) && d.hardware_device().ty() == ort::memory::DeviceType::CPU
    })
}

/// Loads the library (once per process) and returns the shared environment.
///
/// The first call decides: later calls return the same environment or the same error,
/// whatever path they pass.
pub fn environment(explicit: Option<&Path>) -> Result<&'static Environment, String> {
    ENVIRONMENT
        .get_or_init(|| {
            let tried = candidates(explicit);
            let Some(path) = tried.iter().find(|p| p.is_file()) else {
                return Err(format!(
                    "ONNX Runtime library not found (looked for {}). Install it with `scripts/setup` \
                     (or `make setup`), or point ORT_DYLIB_PATH at libonnxruntime.so.{ORT_VERSION}",
                    tried.iter().map(|p| p.display().to_string()).collect::<Vec<_>>().join(", ")
                ));
            };
            let builder =
                ort::init_from(path).map_err(|e| format!("cannot load ONNX Runtime from {}: {e}", path.display()))?;
            let _ = LIBRARY.set(path.clone());
            let env = builder
                .with_name("mcdenoise")
                .with_telemetry(false)
                .build()
                .map_err(|e| format!("cannot create the ONNX Runtime environment: {e}"))?;
            register_shared_cpu_arena(&env)?;
            Ok(env)
        })
        .as_ref()
        .map_err(Clone::clone)
}

/// Registers one CPU arena allocator with the environment, which every session then uses
/// (`session.use_env_allocators`, [`super::model::build_session`]).
///
/// Each session otherwise keeps an arena of its own, grown to its largest region and never
/// given back: a daemon that had run one 1280×720 frame through each of the four shipped
/// variants held 3.26 GB, the sum of four arenas. Shared, the arena is as large as the
/// largest working set of the sessions that run at the same time (one per worker),
/// whichever variants they are. The arena's settings are ONNX Runtime's defaults, those of
/// the per-session arenas before: growing by what is asked instead of powers of two gave a
/// higher peak for a 1280×720 `mcdenoise run` (0.94 GB against 0.80 GB, three runs each).
fn register_shared_cpu_arena(env: &Environment) -> Result<(), String> {
    use ort::memory::{AllocationDevice, AllocatorType, MemoryInfo, MemoryType};
    use ort::AsPointer;
    let fail = |e: &dyn std::fmt::Display| format!("cannot register the shared CPU arena with ONNX Runtime: {e}");
    let info =
        MemoryInfo::new(AllocationDevice::CPU, 0, AllocatorType::Arena, MemoryType::Default).map_err(|e| fail(&e))?;
    // SAFETY: both pointers come from live ort objects of this API version; a null arena
    // configuration selects the defaults (documented in onnxruntime_c_api.h). The
    // environment keeps the allocator; `info` is copied by the call.
    unsafe {
        let status = (ort::api().CreateAndRegisterAllocator)(env.ptr().cast_mut(), info.ptr(), std::ptr::null());
        ort::Error::result_from_status(status).map_err(|e| fail(&e))
    }
}
