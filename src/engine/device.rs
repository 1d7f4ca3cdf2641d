//! Where inference runs: `cpu`, `cuda[:N]` (ONNX Runtime's CUDA execution provider on GPU
//! N), or `auto` (CUDA when the ONNX Runtime library has its provider and a device is
//! visible, else the CPU).
//!
//! The CUDA execution provider lives in the GPU build of ONNX Runtime (`onnxruntime-gpu`,
//! the GPU image; docs/deploy.md). The CPU build the default setup installs has none:
//! asking it for `cuda` is an error that says so, at start-up, before any job is taken.

use std::fmt;
use std::str::FromStr;

use ort::ep::{ExecutionProvider, CUDA};

/// The device the networks run on.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Device {
    /// ONNX Runtime's CPU execution provider.
    #[default]
    Cpu,
    /// ONNX Runtime's CUDA execution provider on this GPU.
    Cuda(u32),
    /// CUDA (GPU 0) where available, else the CPU.
    Auto,
}

impl FromStr for Device {
    type Err = String;

    fn from_str(s: &str) -> Result<Device, String> {
        match s.trim() {
            "cpu" => Ok(Device::Cpu),
            "auto" => Ok(Device::Auto),
            "cuda" => Ok(Device::Cuda(0)),
            other => match other.strip_prefix("cuda:").map(str::parse::<u32>) {
                Some(Ok(n)) => Ok(Device::Cuda(n)),
                _ => {
                    Err(format!("unknown device `{other}` (expected `auto`, `cpu`, `cuda` or `cuda:N`, N a GPU index)"))
                }
            },
        }
    }
}

impl fmt::Display for Device {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Device::Cpu => f.write_str("cpu"),
            Device::Cuda(n) => write!(f, "cuda:{n}"),
            Device::Auto => f.write_str("auto"),
        }
    }
}

/// Whether the loaded ONNX Runtime library has the CUDA execution provider.
pub fn cuda_provider_available() -> bool {
    CUDA::is_available().unwrap_or(false)
}

impl Device {
    /// The device sessions are built for once the library is loaded: `auto` becomes
    /// `cuda:0` or `cpu`; `cuda` on a library without the CUDA provider is an error naming
    /// the library.
    pub fn resolve(self, library: &str) -> Result<Device, String> {
        let available = cuda_provider_available();
        match self {
            Device::Auto => Ok(if available { Device::Cuda(0) } else { Device::Cpu }),
            Device::Cuda(n) if !available => Err(format!(
                "--device cuda:{n}: the ONNX Runtime library {library} has no CUDA execution provider \
                 (it is the CPU build); use the GPU image, or point ORT_DYLIB_PATH at the library of \
                 onnxruntime-gpu {} (docs/deploy.md), or choose --device cpu",
                super::runtime::ORT_VERSION
            )),
            d => Ok(d),
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
}
