//! A contract-v2 network in three stages (docs/model-contract.md, "Stages"): `front.onnx`
//! (the inputs to the level-0 features and their 2×2 max-pool), `middle.onnx` (the pooled
//! features to decoder level 1 and the logits of levels 1 … L−1) and `back.onnx` (decoder
//! level 1 and the level-0 features to the logits of level 0), cut from `model.onnx` by
//! `python -m mcdenoise_train.stages` (their weights are read from `model.onnx` itself, as
//! ONNX external data). The full-resolution stages reach a few pixels, so the
//! engine runs them per core with [`MARGIN`] pixels around it and the middle one once over
//! the frame, at half resolution, instead of the whole graph over each core and a halo of
//! its receptive radius ([`super::Engine::denoise`]).

use std::path::Path;

use ort::session::{Session, SessionOutputs};
use ort::value::{DynValue, TensorRef};

use super::contract::keys;
use super::model::{self, ModelInfo, Opened, Placement, SessionUse};
use super::EngineError;

/// The stage files, in the order they run.
pub const FILES: [&str; 3] = ["front.onnx", "middle.onnx", "back.onnx"];

/// Pixels around a core that the full-resolution stages run on: the level-0 features are
/// exact 3 pixels in from a region's cut edge (the extractors' three 3×3 convolutions), the
/// level-0 logits 2 further in (decoder level 0's two), and the reconstruction of level 0
/// reads them 3 beyond the core; a multiple of 16 keeps every pyramid level aligned.
pub const MARGIN: usize = 16;

/// The three stages' sessions, with the channels of the level-0 features and of decoder
/// level 1's output as `back.onnx`'s inputs declare them.
pub struct Stages {
    front: Session,
    middle: Session,
    back: Session,
    /// Channels of `level0` and `pooled`.
    pub level0_channels: usize,
    /// Channels of `decoder1`.
    pub decoder1_channels: usize,
}

/// A stage's outputs.
pub struct Outputs<'s> {
    outputs: SessionOutputs<'s>,
    stage: &'static str,
}

impl Outputs<'_> {
    /// Output `name`, checked to be `[1, c, h, w]` with `dims` = `[c, h, w]`.
    pub fn get(&self, name: &str, dims: [usize; 3]) -> Result<&[f32], EngineError> {
        tensor(&self.outputs[name], self.stage, name, dims)
    }

    /// Output `name` taken out as ONNX Runtime's own value, checked as [`Outputs::get`]
    /// does: kept for a later stage without copying it.
    pub fn take(&mut self, name: &str, dims: [usize; 3]) -> Result<DynValue, EngineError> {
        let value = self
            .outputs
            .remove(name)
            .ok_or_else(|| EngineError::Inference(format!("{} stage: no output `{name}`", self.stage)))?;
        tensor(&value, self.stage, name, dims)?;
        Ok(value)
    }
}

/// The data of a stage's output `name`, checked to be float32 `[1, c, h, w]` with `dims` =
/// `[c, h, w]`.
pub fn tensor<'v>(value: &'v DynValue, stage: &str, name: &str, dims: [usize; 3]) -> Result<&'v [f32], EngineError> {
    let (shape, data) = value
        .try_extract_tensor::<f32>()
        .map_err(|e| EngineError::Inference(format!("{stage} stage: output `{name}`: {e}")))?;
    let want = [1, dims[0] as i64, dims[1] as i64, dims[2] as i64];
    if shape.iter().copied().ne(want) {
        return Err(EngineError::Inference(format!(
            "{stage} stage: output `{name}` has shape {:?}, expected {want:?}",
            shape.iter().collect::<Vec<_>>()
        )));
    }
    Ok(data)
}

impl Stages {
    /// The stages beside `info.path` (`model.onnx`), when all three are there and were cut
    /// from that file; `Ok(None)` when there are none. A stage cut from another file, or
    /// whose inputs and outputs are not the contract's, is an error naming it.
    pub fn load(
        env: &ort::environment::Environment,
        info: &ModelInfo,
        placement: Placement,
    ) -> Result<Option<Stages>, EngineError> {
        let dir = info.path.parent().unwrap_or(Path::new("."));
        let paths = FILES.map(|f| dir.join(f));
        if !paths.iter().any(|p| p.exists()) {
            return Ok(None);
        }
        if let Some(missing) = paths.iter().find(|p| !p.exists()) {
            return Err(model::model_error(
                missing,
                format!(
                    "file not found: a staged network needs {} beside model.onnx (`python -m \
                     mcdenoise_train.stages DIR` writes them)",
                    FILES.join(", ")
                ),
            ));
        }
        // A stage reads its weights from model.onnx (ONNX external data): one cut from another
        // file may fail to load, or load and fail the check of `stage_of` below.
        let again = format!("cut them again with `python -m mcdenoise_train.stages {}`", dir.display());
        let open = |p: &Path| {
            Opened::open(env, p, placement, SessionUse::Run).map_err(|e| match e {
                EngineError::Model { path, reason } => EngineError::Model {
                    path,
                    reason: format!(
                        "{reason} (a stage file reads its weights from the model.onnx it was cut from: {again})"
                    ),
                },
                other => other,
            })
        };
        let [front, middle, back] = paths.map(|p| open(&p));
        let (front, middle, back) = (front?, middle?, back?);
        for (opened, stage) in [(&front, "front"), (&middle, "middle"), (&back, "back")] {
            opened.expect(keys::STAGE, stage, "")?;
            if opened.get(keys::STAGE_OF)? != info.sha256 {
                return Err(model::model_error(
                    &opened.path,
                    format!(
                        "cut from another model.onnx (metadata `{}` is not the SHA-256 of {}): {again}",
                        keys::STAGE_OF,
                        info.path.display()
                    ),
                ));
            }
        }
        let channels = |opened: &Opened, name: &str| -> Result<usize, EngineError> {
            let input = opened
                .session
                .inputs()
                .iter()
                .find(|i| i.name() == name)
                .ok_or_else(|| model::model_error(&opened.path, format!("no input `{name}`")))?;
            model::outlet_channels(&opened.path, input)
        };
        let level0_channels = channels(&back, "level0")?;
        let decoder1_channels = channels(&back, "decoder1")?;
        let pooled = channels(&middle, "pooled")?;
        if pooled != level0_channels {
            return Err(model::model_error(
                &middle.path,
                format!("input `pooled` has {pooled} channels, back.onnx's `level0` {level0_channels}"),
            ));
        }
        Ok(Some(Stages {
            front: front.session,
            middle: middle.session,
            back: back.session,
            level0_channels,
            decoder1_channels,
        }))
    }

    /// `front` on a region's inputs (`[10, h, w]`, `[10, h, w]`, `[C, h, w]`): `level0`
    /// (`[c, h, w]`) and `pooled` (`[c, h/2, w/2]`).
    pub fn front(
        &mut self,
        diffuse: &[f32],
        specular: &[f32],
        features: &[f32],
        h: usize,
        w: usize,
    ) -> Result<Outputs<'_>, EngineError> {
        let fail = |e: ort::Error| EngineError::Inference(format!("front stage: {e}"));
        let c = features.len() / (h * w);
        let t = |ch: usize, data| TensorRef::from_array_view(([1usize, ch, h, w], data)).map_err(fail);
        let (d, s, f) = (t(diffuse.len() / (h * w), diffuse)?, t(specular.len() / (h * w), specular)?, t(c, features)?);
        let outputs = self.front.run(ort::inputs!["diffuse" => d, "specular" => s, "features" => f]).map_err(fail)?;
        Ok(Outputs { outputs, stage: "front" })
    }

    /// `middle` on a frame's pooled features (`[c, h, w]`, half resolution): `decoder1` and
    /// the logits of levels 1 … L−1.
    pub fn middle(&mut self, pooled: &[f32], h: usize, w: usize) -> Result<Outputs<'_>, EngineError> {
        let fail = |e: ort::Error| EngineError::Inference(format!("middle stage: {e}"));
        let p = TensorRef::from_array_view(([1usize, self.level0_channels, h, w], pooled)).map_err(fail)?;
        let outputs = self.middle.run(ort::inputs!["pooled" => p]).map_err(fail)?;
        Ok(Outputs { outputs, stage: "middle" })
    }

    /// `back` on a region's `decoder1` (`[c1, h/2, w/2]`) and `level0` (`[1, c, h, w]`, as
    /// `front` gave it): the logits of level 0.
    pub fn back(
        &mut self,
        decoder1: &[f32],
        level0: &DynValue,
        h: usize,
        w: usize,
    ) -> Result<Outputs<'_>, EngineError> {
        let fail = |e: ort::Error| EngineError::Inference(format!("back stage: {e}"));
        let d = TensorRef::from_array_view(([1usize, self.decoder1_channels, h / 2, w / 2], decoder1)).map_err(fail)?;
        let outputs = self.back.run(ort::inputs!["decoder1" => d, "level0" => level0]).map_err(fail)?;
        Ok(Outputs { outputs, stage: "back" })
    }
}
