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
