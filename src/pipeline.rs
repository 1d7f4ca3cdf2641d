//! One frame through a [`Denoiser`]: decode → denoise → encode → quality metrics.
//!
//! `mcdenoise run` and the daemon's workers both run this; it is synchronous and owns no
//! thread. Callers decide what to do with the result (write it, report it) and how a
//! [`Failure`] reaches their users.

use std::path::Path;
use std::time::Instant;

use crate::engine::{Denoiser, EngineError, Fireflies, FireflyReport, Progress, Variant};
use crate::frame::{write_exr, Frame, FrameError, Limits, OutputLayer, Sanitized};
use crate::jobs::{Layer, Timings};
use crate::quality::Comparison;

/// What to denoise.
pub struct Request<'a> {
    pub frame: &'a Path,
    /// A reference frame: the output carries the quality metrics of input and output.
    pub reference: Option<&'a Path>,
    /// `None` lets the denoiser pick (`full` when the frame has covariance).
    pub variant: Option<Variant>,
    /// Firefly handling before the networks (docs/fireflies.md).
    pub fireflies: Fireflies,
    /// Extra layers of the result besides `R,G,B`.
    pub layers: &'a [Layer],
    pub limits: Limits,
}

/// A denoised frame, encoded.
pub struct Output {
    pub width: usize,
    pub height: usize,
    pub variant: Variant,
    pub tiles: usize,
    /// The result as an OpenEXR file.
    pub encoded: Vec<u8>,
    pub metrics: Option<Comparison>,
    pub sanitized: Sanitized,
    /// Variance buffers the frame lacked, taken as 0.
    pub missing_variances: Vec<String>,
    /// What the frame's passes could only approximate.
    pub warnings: Vec<String>,
    /// Samples the firefly handling clamped.
    pub fireflies: FireflyReport,
    /// Milliseconds per stage; `queue` is 0 (the pipeline does not know about queues), and
    /// `preprocess` includes the firefly handling (also given alone in `fireflies_ms`).
    pub timings: Timings,
    pub fireflies_ms: f64,
}

/// Which input a failure concerns.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Input {
    Frame,
    Reference,
}

impl Input {
    pub fn name(self) -> &'static str {
        match self {
            Input::Frame => "frame",
            Input::Reference => "reference",
        }
    }
}

/// A reference whose size differs from the frame's.
#[derive(Clone, Copy, Debug, PartialEq, Eq, thiserror::Error)]
#[error("reference is {}x{} but the frame is {}x{}", reference.0, reference.1, frame.0, frame.1)]
pub struct SizeMismatch {
    pub frame: (usize, usize),
    pub reference: (usize, usize),
}

/// Checks that a reference has the frame's size (`(width, height)` each).
pub fn check_same_size(frame: (usize, usize), reference: (usize, usize)) -> Result<(), SizeMismatch> {
    if frame == reference {
        Ok(())
    } else {
        Err(SizeMismatch { frame, reference })
    }
}

/// Why a frame could not be denoised.
#[derive(Debug, thiserror::Error)]
pub enum Failure {
    #[error("cannot read the {}: {error}", which.name())]
    Read { which: Input, error: std::io::Error },
    #[error("{}: {error}", which.name())]
    Invalid { which: Input, error: FrameError },
    #[error(transparent)]
    SizeMismatch(#[from] SizeMismatch),
    #[error(transparent)]
    Engine(#[from] EngineError),
    #[error("cannot encode the result: {0}")]
    Encode(String),
}

fn ms(t: Instant) -> f64 {
    t.elapsed().as_secs_f64() * 1e3
}

/// Reads and decodes one input.
pub fn decode(path: &Path, which: Input, limits: &Limits) -> Result<Frame, Failure> {
    let bytes = std::fs::read(path).map_err(|error| Failure::Read { which, error })?;
    let frame = match which {
        Input::Frame => Frame::from_exr_bytes(&bytes, limits),
        Input::Reference => Frame::reference_from_exr_bytes(&bytes, limits),
    };
    frame.map_err(|error| Failure::Invalid { which, error })
}

/// Runs the pipeline. `on_tile` is called after each tile; returning `false` stops the
/// denoiser between tiles ([`EngineError::Cancelled`]).
pub fn run(
    denoiser: &mut dyn Denoiser,
    request: &Request<'_>,
    on_tile: &mut dyn FnMut(Progress) -> bool,
) -> Result<Output, Failure> {
    let started = Instant::now();
    let t = Instant::now();
    let frame = decode(request.frame, Input::Frame, &request.limits)?;
    let reference = request.reference.map(|p| decode(p, Input::Reference, &request.limits)).transpose()?;
    if let Some(r) = &reference {
        check_same_size((frame.width, frame.height), (r.width, r.height))?;
    }
    let decode_ms = ms(t);
    if frame.sanitized.total > 0 {
        tracing::warn!(samples = frame.sanitized.total, "non-finite samples replaced by 0");
    }
    if !frame.missing_variances.is_empty() {
        tracing::info!(buffers = ?frame.missing_variances, "variance buffers missing; taken as 0");
    }

    let out = denoiser.denoise(&frame, request.variant, request.fireflies, on_tile)?;

    let t = Instant::now();
    let mut layers = vec![OutputLayer { prefix: "", planes: [&out.color[0], &out.color[1], &out.color[2]] }];
    for layer in request.layers {
        let planes = match layer {
            Layer::Diffuse => &out.diffuse,
            Layer::Specular => &out.specular,
        };
        layers.push(OutputLayer { prefix: layer.name(), planes: [&planes[0], &planes[1], &planes[2]] });
    }
    let encoded = write_exr(out.width, out.height, &layers).map_err(|e| Failure::Encode(e.to_string()))?;
    let encode_ms = ms(t);

    let metrics = reference.as_ref().map(|r| {
        let (rc, noisy) = (r.color(), frame.color());
        Comparison::of(
            [&noisy[0], &noisy[1], &noisy[2]],
            [&out.color[0], &out.color[1], &out.color[2]],
            [&rc[0], &rc[1], &rc[2]],
            frame.width,
            frame.height,
        )
    });
    let timings = Timings {
        queue: 0.0,
        decode: decode_ms,
        preprocess: (out.timings.fireflies + out.timings.preprocess).as_secs_f64() * 1e3,
        inference: out.timings.inference.as_secs_f64() * 1e3,
        reconstruction: out.timings.reconstruction.as_secs_f64() * 1e3,
        encode: encode_ms,
        total: ms(started),
    };
    Ok(Output {
        width: out.width,
        height: out.height,
        variant: out.variant,
        tiles: out.tiles,
        encoded,
        metrics,
        sanitized: frame.sanitized,
        missing_variances: frame.missing_variances,
        warnings: frame.warnings,
        fireflies: out.fireflies,
        timings,
        fireflies_ms: out.timings.fireflies.as_secs_f64() * 1e3,
    })
}
