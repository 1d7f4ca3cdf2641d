//! Loading contract-v1 models into ONNX Runtime sessions and running them.

use std::path::{Path, PathBuf};

use ort::session::{builder::GraphOptimizationLevel, Session};
use ort::value::{TensorRef, ValueType};
use serde::Serialize;
use sha2::Digest;

use super::contract::{self, keys, Component, Variant, COLOR_CHANNELS, TAPS};
use super::EngineError;

/// A loaded network: what its file declares about itself, and the file's digest. The one
/// description of a model, reported by `/v1/models`, `ListModels` and the metrics.
#[derive(Clone, Debug, Serialize)]
pub struct ModelInfo {
    pub variant: Variant,
    pub component: Component,
    #[serde(rename = "file")]
    pub path: PathBuf,
    /// The model contract version the file declares (checked at load).
    pub contract: String,
    pub receptive_radius: usize,
    pub flops_per_pixel: f64,
    pub architecture: String,
    /// SHA-256 of the file, hex.
    pub sha256: String,
}

/// One network (a component of a variant) in its own session.
pub struct Network {
    session: Session,
    pub info: ModelInfo,
}

fn model_error(path: &Path, reason: impl Into<String>) -> EngineError {
    EngineError::Model { path: path.to_path_buf(), reason: reason.into() }
}

/// Session options: `threads` intra-op threads, no spinning (the engine is idle between
/// jobs), all graph optimizations. A helper returning `ort::Result` because builder errors
/// carry the builder and are not `Send`.
pub fn build_session(env: &ort::environment::Environment, path: &Path, threads: usize) -> ort::Result<Session> {
    Session::builder(env)?
        .with_optimization_level(GraphOptimizationLevel::All)?
        .with_intra_threads(threads)?
        .with_inter_threads(1)?
        .with_intra_op_spinning(false)?
        .commit_from_file(path)
}

impl Network {
    /// Loads `path` and checks it against contract v1 for `variant` and `component`.
    pub fn load(
        env: &ort::environment::Environment,
        path: &Path,
        variant: Variant,
        component: Component,
        threads: usize,
    ) -> Result<Network, EngineError> {
        if !path.is_file() {
            return Err(model_error(path, "file not found"));
        }
        let session =
            build_session(env, path, threads.max(1)).map_err(|e| model_error(path, format!("cannot load: {e}")))?;
        let meta = session.metadata().map_err(|e| model_error(path, format!("cannot read metadata: {e}")))?;
        let get = |key: &str| -> Result<String, EngineError> {
            meta.custom(key)
                .ok_or_else(|| model_error(path, format!("metadata `{key}` is missing (not a contract-v1 model?)")))
        };
        let expect = |key: &str, want: &str| -> Result<(), EngineError> {
            let got = get(key)?;
            if got == want {
                Ok(())
            } else {
                Err(model_error(path, format!("metadata `{key}` is `{got}`, expected `{want}`")))
            }
        };
        expect(keys::CONTRACT, contract::CONTRACT_VERSION)?;
        expect(keys::COMPONENT, component.name())?;
        expect(keys::VARIANT, variant.name())?;
        expect(keys::KERNEL_SIZE, &contract::KERNEL_SIZE.to_string())?;
        expect(keys::FEATURES, &variant.features().join(","))?;
        let receptive_radius = get(keys::RECEPTIVE_RADIUS)?
            .parse::<usize>()
            .map_err(|e| model_error(path, format!("metadata `{}` is not a number: {e}", keys::RECEPTIVE_RADIUS)))?;
        let flops_per_pixel = get(keys::FLOPS_PER_PIXEL)?
            .parse::<f64>()
            .map_err(|e| model_error(path, format!("metadata `{}` is not a number: {e}", keys::FLOPS_PER_PIXEL)))?;
        let architecture = meta.custom(keys::ARCHITECTURE).unwrap_or_default();
        drop(meta);

        check_outlet(path, session.inputs(), "color", COLOR_CHANNELS)?;
        check_outlet(path, session.inputs(), "features", variant.feature_channels())?;
        check_outlet(path, session.outputs(), "kernel", TAPS)?;

        let sha256 = std::fs::read(path)
            .map(|b| sha2::Sha256::digest(&b).iter().map(|x| format!("{x:02x}")).collect())
            .map_err(|e| model_error(path, format!("cannot read: {e}")))?;
        let info = ModelInfo {
            variant,
            component,
            path: path.to_path_buf(),
            contract: contract::CONTRACT_VERSION.to_string(),
            receptive_radius,
            flops_per_pixel,
            architecture,
            sha256,
        };
        Ok(Network { session, info })
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
            EngineError::Inference(format!("{} {}: {e}", self.info.variant.name(), self.info.component.name()))
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

/// The two networks of one variant.
pub struct ModelPair {
    pub variant: Variant,
    pub diffuse: Network,
    pub specular: Network,
}

impl ModelPair {
    /// Context a tile needs around it: the larger receptive radius of the two networks.
    pub fn receptive_radius(&self) -> usize {
        self.diffuse.info.receptive_radius.max(self.specular.info.receptive_radius)
    }

    pub fn flops_per_pixel(&self) -> f64 {
        self.diffuse.info.flops_per_pixel + self.specular.info.flops_per_pixel
    }

    pub fn network(&mut self, component: Component) -> &mut Network {
        match component {
            Component::Diffuse => &mut self.diffuse,
            Component::Specular => &mut self.specular,
        }
    }
}

/// Loads the variants found under `dir` (`dir/full`, `dir/nocov`).
pub fn load_models(
    env: &ort::environment::Environment,
    dir: &Path,
    threads: usize,
) -> Result<Vec<ModelPair>, EngineError> {
    let mut pairs = Vec::new();
    for variant in Variant::ALL {
        let vdir = dir.join(variant.name());
        if !vdir.is_dir() {
            continue;
        }
        let load = |component: Component| {
            Network::load(env, &vdir.join(format!("{}.onnx", component.name())), variant, component, threads)
        };
        pairs.push(ModelPair { variant, diffuse: load(Component::Diffuse)?, specular: load(Component::Specular)? });
    }
    if pairs.is_empty() {
        return Err(model_error(
            dir,
            "no model variants found (expected full/ or nocov/ holding diffuse.onnx and specular.onnx)",
        ));
    }
    Ok(pairs)
}
