//! Where inference runs: `cpu`, `openvino` (the CPU through OpenVINO, in bfloat16 on CPUs
//! that compute it natively), `cuda[:N]` (ONNX Runtime's CUDA execution provider on GPU N),
//! or `auto` (CUDA when the ONNX Runtime library has its provider and a device is visible,
//! else OpenVINO where its bfloat16 is the faster (AMX, or AVX512-BF16 on AMD) and it is
//! installed, else the CPU).
//!
//! OpenVINO's execution provider is a plugin library (`onnxruntime-ep-openvino`, which
//! carries OpenVINO's runtime) that `scripts/install-ort` puts beside ONNX Runtime's
//! library and the engine registers with ONNX Runtime when it is asked for
//! ([`super::runtime::openvino`]); the plugin serves Intel CPUs only, so on others the
//! engine drives the same runtime directly for the contract-v2 networks
//! ([`super::openvino`]). On a CPU with native bfloat16 (AMX on Intel Xeon since Sapphire
//! Rapids, AVX512-BF16 on Intel Xeon since Cooper Lake and AMD EPYC since Zen 4) OpenVINO
//! runs the convolutions in bfloat16 (its default there); elsewhere in float32, where ONNX
//! Runtime's own CPU provider is faster (docs/results/speed-work.md). `auto` takes it only
//! where it was measured faster than the CPU provider ([`CpuBf16::openvino_pays`]): with
//! AMX, and with AVX512-BF16 on AMD, not with AVX512-BF16 alone on an Intel Xeon. A
//! process runs one device: once OpenVINO has run in a process, sessions of ONNX Runtime's
//! CPU provider in the same process gave results that differ by up to 5e-4 (relative) from
//! a process without it, so tests that compare the CPU provider's outputs keep OpenVINO out
//! of their process.
//!
//! The CUDA execution provider lives in the GPU build of ONNX Runtime (`onnxruntime-gpu`,
//! the GPU image; docs/deploy.md). The CPU build the default setup installs has none:
//! asking it for `cuda` is an error that says so, at start-up, before any job is taken.
//! The provider also needs the NVIDIA driver (`libcuda.so.1`) and a GPU: both are checked
//! through the driver's own API ([`cuda_devices`]) before a session is built, so that
//! `cuda` without them is an error naming what is missing and `auto` falls back to the CPU.

use std::fmt;
use std::str::FromStr;

use ort::ep::{ExecutionProvider, CUDA};

/// The device the networks run on.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Device {
    /// ONNX Runtime's CPU execution provider.
    #[default]
    Cpu,
    /// The CPU through OpenVINO's execution provider plugin.
    OpenVino,
    /// ONNX Runtime's CUDA execution provider on this GPU.
    Cuda(u32),
    /// CUDA (GPU 0) where available, else OpenVINO where its bfloat16 is the faster
    /// ([`CpuBf16::openvino_pays`]) and it is installed, else the CPU.
    Auto,
}

impl FromStr for Device {
    type Err = String;

    fn from_str(s: &str) -> Result<Device, String> {
        match s.trim() {
            "cpu" => Ok(Device::Cpu),
            "openvino" => Ok(Device::OpenVino),
            "auto" => Ok(Device::Auto),
            "cuda" => Ok(Device::Cuda(0)),
            other => match other.strip_prefix("cuda:").map(str::parse::<u32>) {
                Some(Ok(n)) => Ok(Device::Cuda(n)),
                _ => Err(format!(
                    "unknown device `{other}` (expected `auto`, `cpu`, `openvino`, `cuda` or `cuda:N`, N a GPU index)"
                )),
            },
        }
    }
}

impl fmt::Display for Device {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Device::Cpu => f.write_str("cpu"),
            Device::OpenVino => f.write_str("openvino"),
            Device::Cuda(n) => write!(f, "cuda:{n}"),
            Device::Auto => f.write_str("auto"),
        }
    }
}

/// Whether a contract-v2 network's tensors go through ONNX Runtime's I/O binding: the
/// region's inputs written into, and its outputs read from, buffers ONNX Runtime allocated
/// once per region shape (on a GPU page-locked host memory, which crosses PCIe by DMA
/// without the staging copy pageable memory needs), instead of tensors over the engine's
/// own buffers created for each run.
#[derive(clap::ValueEnum, Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum IoBinding {
    /// Off, for now, on a GPU as on the CPU (where ONNX Runtime reads the engine's buffers
    /// directly): on an H100 the binding failed with two workers (docs/results.md, "GPU"),
    /// and what it gains there is not yet measured in the daemon.
    #[default]
    Auto,
    On,
    Off,
}

impl IoBinding {
    /// Whether the binding is used, on any device.
    pub fn enabled(self) -> bool {
        self == IoBinding::On
    }
}

/// Whether the loaded ONNX Runtime library has the CUDA execution provider.
pub fn cuda_provider_available() -> bool {
    CUDA::is_available().unwrap_or(false)
}

/// The number of GPUs the NVIDIA driver reports (`cuInit`, `cuDeviceGetCount` of
/// `libcuda.so.1`), or why there is none: no driver library, or the driver's error.
///
/// Written against the driver API directly (two calls through `libloading`, which ONNX
/// Runtime's loader already brings) because the provider itself reports a missing driver
/// only when the first session is built, as a load error of a model file.
pub fn cuda_devices() -> Result<u32, String> {
    type CuInit = unsafe extern "C" fn(u32) -> i32;
    type CuDeviceGetCount = unsafe extern "C" fn(*mut i32) -> i32;
    // SAFETY: libcuda.so.1 is the NVIDIA driver library; loading it runs no code of ours, and
    // both symbols have these C signatures in every CUDA driver API version (cuda.h).
    unsafe {
        let lib = libloading::Library::new("libcuda.so.1").map_err(|e| {
            let why = std::error::Error::source(&e).map_or_else(|| e.to_string(), ToString::to_string);
            format!("the NVIDIA driver library libcuda.so.1 cannot be loaded ({why})")
        })?;
        let init: libloading::Symbol<CuInit> =
            lib.get(b"cuInit\0").map_err(|e| format!("libcuda.so.1 has no cuInit ({e})"))?;
        let count: libloading::Symbol<CuDeviceGetCount> =
            lib.get(b"cuDeviceGetCount\0").map_err(|e| format!("libcuda.so.1 has no cuDeviceGetCount ({e})"))?;
        match init(0) {
            0 => {}
            100 => return Ok(0), // CUDA_ERROR_NO_DEVICE
            code => return Err(format!("the NVIDIA driver failed to start (cuInit error {code})")),
        }
        let mut n = 0i32;
        match count(&mut n) {
            0 => Ok(n.max(0) as u32),
            code => Err(format!("the NVIDIA driver cannot count its GPUs (cuDeviceGetCount error {code})")),
        }
    }
}

/// What the CPU offers OpenVINO's bfloat16 convolutions ([`CpuBf16::detect`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct CpuBf16 {
    /// AMX tiles with bfloat16 (Intel Xeon since Sapphire Rapids, where the hypervisor
    /// passes them through).
    pub amx: bool,
    /// AVX512-BF16's bfloat16 dot products (Intel Xeon since Cooper Lake, AMD EPYC since
    /// Zen 4).
    pub avx512_bf16: bool,
    /// The vendor is Intel (`GenuineIntel`).
    pub intel: bool,
}

impl CpuBf16 {
    /// Reads CPUID: leaf 0's vendor, leaf 7 sub-leaf 0 EDX bit 22 (AMX-BF16) and bit 24
    /// (AMX-TILE), sub-leaf 1 EAX bit 5 (AVX512-BF16). The kernel's permission to use AMX
    /// tiles is OpenVINO's to ask for.
    #[cfg(target_arch = "x86_64")]
    pub fn detect() -> CpuBf16 {
        use std::arch::x86_64::{__cpuid, __cpuid_count};
        let leaf0 = __cpuid(0);
        // "GenuineIntel" in EBX, EDX, ECX.
        let intel = (leaf0.ebx, leaf0.edx, leaf0.ecx) == (0x756e_6547, 0x4965_6e69, 0x6c65_746e);
        // Leaf 7 exists where leaf 0 reports a maximum of at least 7, and its sub-leaf 1
        // where sub-leaf 0's EAX reports at least 1; both checked first.
        if leaf0.eax < 7 {
            return CpuBf16 { intel, ..CpuBf16::default() };
        }
        let leaf7 = __cpuid_count(7, 0);
        let amx = leaf7.edx & (1 << 22) != 0 && leaf7.edx & (1 << 24) != 0;
        let avx512_bf16 = leaf7.eax >= 1 && __cpuid_count(7, 1).eax & (1 << 5) != 0;
        CpuBf16 { amx, avx512_bf16, intel }
    }

    /// Off x86-64: none of them.
    #[cfg(not(target_arch = "x86_64"))]
    pub fn detect() -> CpuBf16 {
        CpuBf16::default()
    }

    /// Whether OpenVINO's bfloat16 runs the default network faster than ONNX Runtime's
    /// float32 CPU provider here, as measured (docs/results/speed-work.md): with AMX (an
    /// Intel Xeon, 2.5x), and with AVX512-BF16 on an AMD EPYC (Zen 4, about 1.5x). Not with
    /// AVX512-BF16 alone on an Intel Xeon: there OpenVINO was 1.5-1.8x slower (an Emerald
    /// Rapids virtual machine without AMX).
    pub fn openvino_pays(self) -> bool {
        self.amx || (self.avx512_bf16 && !self.intel)
    }
}

/// Whether `--device auto` runs the CPU networks through OpenVINO on this CPU
/// ([`CpuBf16::openvino_pays`]).
pub fn cpu_prefers_openvino() -> bool {
    CpuBf16::detect().openvino_pays()
}

/// What [`Device::resolve`] found on this machine.
struct Found {
    /// Whether the loaded ONNX Runtime library has the CUDA execution provider.
    cuda_provider: bool,
    /// What the NVIDIA driver said, asked only when the provider could use it.
    cuda_devices: Result<u32, String>,
    /// Whether OpenVINO's bfloat16 is the faster way to run the networks on this CPU
    /// ([`CpuBf16::openvino_pays`]).
    openvino_pays: bool,
}

impl Device {
    /// The device sessions are built for once the library is loaded: `auto` becomes
    /// `cuda:0` where the library has the CUDA provider and the driver reports a GPU, else
    /// `openvino` on a CPU where its bfloat16 is the faster and OpenVINO loads, else `cpu`;
    /// `cuda:N` without the provider, the driver or GPU N is an error naming what is
    /// missing, and so is `openvino` without OpenVINO. `openvino` registers the plugin with
    /// `env`, or loads OpenVINO's runtime where the plugin does not serve the CPU (once per
    /// process).
    pub fn resolve(self, env: &ort::environment::Environment, library: &str) -> Result<Device, String> {
        let cuda_provider = matches!(self, Device::Auto | Device::Cuda(_)) && cuda_provider_available();
        let found = Found {
            cuda_provider,
            // The driver is asked only when the provider could use it.
            cuda_devices: if cuda_provider { cuda_devices() } else { Ok(0) },
            openvino_pays: cpu_prefers_openvino(),
        };
        self.resolve_with(library, found, || super::runtime::openvino(env).map(|_| ()))
    }

    /// [`Device::resolve`] given what was found, with `openvino` registering the plugin
    /// (called only for `openvino`, and for `auto` on such a CPU and no GPU).
    fn resolve_with(
        self,
        library: &str,
        found: Found,
        openvino: impl FnOnce() -> Result<(), String>,
    ) -> Result<Device, String> {
        const INSTEAD: &str = "or choose --device cpu (or auto)";
        let Found { cuda_provider: provider, cuda_devices: devices, openvino_pays } = found;
        match self {
            Device::Auto if provider && matches!(devices, Ok(n) if n > 0) => Ok(Device::Cuda(0)),
            Device::Auto => {
                if provider {
                    let why = devices.map_or_else(|e| e, |_| "the NVIDIA driver reports no GPU".to_string());
                    tracing::warn!("--device auto: no GPU: {why}");
                }
                if !openvino_pays {
                    return Ok(Device::Cpu);
                }
                match openvino() {
                    Ok(()) => Ok(Device::OpenVino),
                    Err(e) => {
                        tracing::warn!(
                            "--device auto: OpenVINO's bfloat16 is the faster on this CPU, but OpenVINO is not \
                             available ({e}); running on ONNX Runtime's CPU provider"
                        );
                        Ok(Device::Cpu)
                    }
                }
            }
            Device::OpenVino => openvino().map(|()| self).map_err(|e| format!("--device openvino: {e}; {INSTEAD}")),
            Device::Cuda(n) if !provider => Err(format!(
                "--device cuda:{n}: the ONNX Runtime library {library} has no CUDA execution provider \
                 (it is the CPU build); use the GPU image, or point ORT_DYLIB_PATH at the library of \
                 onnxruntime-gpu {} (docs/deploy.md), {INSTEAD}",
                super::runtime::ORT_VERSION
            )),
            Device::Cuda(n) => match devices {
                Err(e) => Err(format!(
                    "--device cuda:{n}: {e}; on a GPU machine install the NVIDIA driver, in a container run \
                     the GPU image with the NVIDIA container toolkit (`docker run --gpus all`, or request \
                     nvidia.com/gpu on Kubernetes), {INSTEAD}"
                )),
                Ok(count) if n >= count => Err(format!(
                    "--device cuda:{n}: the NVIDIA driver reports {count} GPU(s){}; {INSTEAD}",
                    if count > 0 { format!(", numbered 0 to {}", count - 1) } else { String::new() }
                )),
                Ok(_) => Ok(self),
            },
            Device::Cpu => Ok(self),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn devices_parse_and_print() {
        for (s, d) in
            [("cpu", Device::Cpu), ("auto", Device::Auto), ("cuda", Device::Cuda(0)), ("cuda:3", Device::Cuda(3))]
        {
            assert_eq!(s.parse::<Device>(), Ok(d));
        }
        assert_eq!(Device::Cuda(2).to_string(), "cuda:2");
        for bad in ["gpu", "cuda:", "cuda:-1", "cuda:x", "CUDA"] {
            let err = bad.parse::<Device>().unwrap_err();
            assert!(err.contains(&format!("`{bad}`")) && err.contains("cuda:N"), "{err}");
        }
    }

    #[test]
    fn io_binding_is_on_only_when_asked_for() {
        use IoBinding::*;
        for (binding, enabled) in [(Auto, false), (On, true), (Off, false)] {
            assert_eq!(binding.enabled(), enabled, "{binding:?}");
        }
    }

    #[test]
    fn devices_resolve_from_the_provider_and_the_driver() {
        let lib = "/opt/lib/libonnxruntime.so.1.31.1";
        let no_driver = || Err("the NVIDIA driver library libcuda.so.1 cannot be loaded (not found)".to_string());
        let found = |cuda_provider, cuda_devices| Found { cuda_provider, cuda_devices, openvino_pays: false };
        let no_openvino = || -> Result<(), String> { panic!("OpenVINO asked for on a CPU where it does not pay") };
        // auto: CUDA only with the provider and a GPU.
        assert_eq!(Device::Auto.resolve_with(lib, found(true, Ok(2)), no_openvino), Ok(Device::Cuda(0)));
        for (provider, devices) in [(false, Ok(0)), (true, Ok(0)), (true, no_driver())] {
            assert_eq!(Device::Auto.resolve_with(lib, found(provider, devices), no_openvino), Ok(Device::Cpu));
        }
        assert_eq!(Device::Cpu.resolve_with(lib, found(true, no_driver()), no_openvino), Ok(Device::Cpu));
        assert_eq!(Device::Cuda(1).resolve_with(lib, found(true, Ok(2)), no_openvino), Ok(Device::Cuda(1)));
        // cuda: each missing part named.
        let err = Device::Cuda(0).resolve_with(lib, found(false, Ok(0)), no_openvino).unwrap_err();
        assert!(err.contains(lib) && err.contains("CPU build") && err.contains("--device cpu"), "{err}");
        let err = Device::Cuda(0).resolve_with(lib, found(true, no_driver()), no_openvino).unwrap_err();
        assert!(
            err.starts_with("--device cuda:0: the NVIDIA driver library libcuda.so.1") && err.contains("--gpus all"),
            "{err}"
        );
        let err = Device::Cuda(2).resolve_with(lib, found(true, Ok(2)), no_openvino).unwrap_err();
        assert!(err.contains("reports 2 GPU(s), numbered 0 to 1"), "{err}");
        let err = Device::Cuda(0).resolve_with(lib, found(true, Ok(0)), no_openvino).unwrap_err();
        assert!(err.contains("reports 0 GPU(s);"), "{err}");
    }

    #[test]
    fn openvino_pays_with_amx_and_with_avx512_bf16_on_amd_only() {
        let cpu = |amx, avx512_bf16, intel| CpuBf16 { amx, avx512_bf16, intel };
        // Intel Xeon with AMX (Sapphire Rapids on): OpenVINO measured 2.5x as fast.
        assert!(cpu(true, true, true).openvino_pays());
        // AMD EPYC Zen 4: AVX512-BF16, about 1.5x as fast.
        assert!(cpu(false, true, false).openvino_pays());
        // Intel Xeon with AVX512-BF16 and no AMX (Cooper Lake, or AMX hidden by a
        // hypervisor): 1.5-1.8x slower than the CPU provider.
        assert!(!cpu(false, true, true).openvino_pays());
        // Neither: float32 through OpenVINO, slower everywhere measured.
        assert!(!cpu(false, false, true).openvino_pays());
        assert!(!cpu(false, false, false).openvino_pays());
    }

    #[cfg(all(target_os = "linux", target_arch = "x86_64"))]
    #[test]
    fn cpuid_detection_agrees_with_the_kernel() {
        // The kernel's view of the first CPU.
        let info = std::fs::read_to_string("/proc/cpuinfo").expect("/proc/cpuinfo");
        let field = |name: &str| {
            info.lines()
                .find(|l| l.split(':').next().is_some_and(|k| k.trim() == name))
                .and_then(|l| l.split_once(':'))
                .map(|(_, v)| v.trim().to_string())
                .unwrap_or_default()
        };
        let flags = field("flags");
        let has = |flag: &str| flags.split_whitespace().any(|f| f == flag);
        let found = CpuBf16::detect();
        assert_eq!(found.intel, field("vendor_id") == "GenuineIntel", "{found:?}");
        assert_eq!(found.avx512_bf16, has("avx512_bf16"), "{found:?}");
        // A kernel too old to enable AMX lists no AMX flags where CPUID has them.
        assert!(found.amx || !(has("amx_bf16") && has("amx_tile")), "{found:?}");
        assert_eq!(cpu_prefers_openvino(), found.openvino_pays());
    }

    #[test]
    fn openvino_is_chosen_on_a_cpu_where_it_pays_and_loads() {
        let lib = "/opt/lib/libonnxruntime.so.1.31.1";
        let bf16 = |openvino_pays| Found { cuda_provider: false, cuda_devices: Ok(0), openvino_pays };
        let missing = || Err("OpenVINO's execution provider plugin not found (looked for /x/openvino)".to_string());
        // auto: OpenVINO where it pays and is installed; the CPU provider without either.
        assert_eq!(Device::Auto.resolve_with(lib, bf16(true), || Ok(())), Ok(Device::OpenVino));
        assert_eq!(Device::Auto.resolve_with(lib, bf16(true), missing), Ok(Device::Cpu));
        assert_eq!(Device::Auto.resolve_with(lib, bf16(false), || Ok(())), Ok(Device::Cpu));
        // A GPU comes first.
        let gpu = Found { cuda_provider: true, cuda_devices: Ok(1), openvino_pays: true };
        assert_eq!(Device::Auto.resolve_with(lib, gpu, || Ok(())), Ok(Device::Cuda(0)));
        // openvino asked for by name: on any CPU, an error naming what is missing without the plugin.
        assert_eq!(Device::OpenVino.resolve_with(lib, bf16(false), || Ok(())), Ok(Device::OpenVino));
        let err = Device::OpenVino.resolve_with(lib, bf16(true), missing).unwrap_err();
        assert!(err.starts_with("--device openvino: OpenVINO's execution provider plugin not found"), "{err}");
        assert!(err.contains("--device cpu"), "{err}");
        assert_eq!("openvino".parse::<Device>(), Ok(Device::OpenVino));
        assert_eq!(Device::OpenVino.to_string(), "openvino");
    }

    #[test]
    fn the_driver_probe_answers_without_a_driver() {
        // Here (CI has no GPU) either answer is fine, but the probe must not crash, and
        // without the library it must say which library is missing.
        match cuda_devices() {
            Ok(_) => {}
            Err(e) => assert!(e.contains("libcuda.so.1") || e.contains("NVIDIA driver"), "{e}"),
        }
    }
}
