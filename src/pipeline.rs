//! One frame through a [`Denoiser`]: decode → denoise → encode → quality metrics.
//!
//! `mcdenoise run` and the daemon's workers both run this; it is synchronous and owns no
//! thread. Callers decide what to do with the result (write it, report it) and how a
//! [`Failure`] reaches their users.

use std::path::Path;
use std::time::Instant;

use crate::engine::variance::{self, VarianceCheck};
use crate::engine::{Denoised, Denoiser, EngineError, Fireflies, FireflyReport, Options, Progress, Variant};
use crate::frame::{Carried, Carry, ChannelMaps, Frame, FrameError, FrameKind, Limits, Sanitized};
use crate::jobs::{Layer, Timings};
use crate::preview::Rgb;
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
    /// Whether variances far larger than the image's noise are scaled down
    /// ([`crate::engine::variance`]).
    pub variance_check: VarianceCheck,
    /// Extra layers of the result besides `R,G,B` and the beauty's alpha.
    pub layers: &'a [Layer],
    pub limits: Limits,
    /// How renderers' AOV names are read.
    pub channel_maps: ChannelMaps,
    /// Whether the output carries the decoded colour of the frame and the reference
    /// ([`Output::input_color`]): the daemon keeps it for its previews.
    pub keep_colors: bool,
}

/// A denoised frame, encoded: float32 `R,G,B`, the requested layers, and what
/// [`frame::Carried`] keeps of the input (windows, pixel aspect, attributes, alpha, and
/// every other channel with [`Layer::All`]), plus the denoiser's own attributes
/// ([`ATTRIBUTES`]).
pub struct Output {
    pub width: usize,
    pub height: usize,
    pub variant: Variant,
    pub tiles: usize,
    /// Whether the network ran in stages (engine::stages).
    pub staged: bool,
    /// The result as an OpenEXR file.
    pub encoded: Vec<u8>,
    pub metrics: Option<Comparison>,
    pub sanitized: Sanitized,
    /// Variance buffers the frame lacked, taken as 0.
    pub missing_variances: Vec<String>,
    /// What the frame's passes could only approximate, and what the variance check found.
    pub warnings: Vec<String>,
    /// Samples the firefly handling clamped.
    pub fireflies: FireflyReport,
    /// Milliseconds per stage; `queue` is 0 (the pipeline does not know about queues), and
    /// `preprocess` includes the firefly handling (also given alone in `fireflies_ms`).
    pub timings: Timings,
    pub fireflies_ms: f64,
    /// With [`Request::keep_colors`]: the frame's colour as decoded (`Frame::color`) and
    /// the reference's.
    pub input_color: Option<Rgb>,
    pub reference_color: Option<Rgb>,
}

/// What the result says when the frame's radiance was scaled into the networks' range.
fn exposure_warning(scale: f32) -> String {
    let top = crate::engine::exposure::LEVEL_MAX;
    format!(
        "the frame is brighter than any the networks trained on (exposure level above {top}): its radiance was \
         scaled by {scale:.4} before the networks and the result back by its inverse (docs/frame-layout.md, \
         \"Exposure\")"
    )
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

/// Opens an input file to be decoded a block at a time rather than read whole: the file's
/// bytes would sit beside the decoded planes (the decode's peak memory).
fn open(path: &Path, which: Input) -> Result<std::io::BufReader<std::fs::File>, Failure> {
    let file = std::fs::File::open(path).map_err(|error| Failure::Read { which, error })?;
    Ok(std::io::BufReader::with_capacity(1 << 20, file))
}

/// Reads and decodes one input.
pub fn decode(path: &Path, which: Input, limits: &Limits) -> Result<Frame, Failure> {
    let input = open(path, which)?;
    let frame = match which {
        Input::Frame => Frame::from_exr_reader_carrying(input, limits, &Carry::default(), &ChannelMaps::default())
            .map(|(frame, _)| frame),
        Input::Reference => Frame::reference_from_exr_reader(input, limits),
    };
    frame.map_err(|error| Failure::Invalid { which, error })
}

/// Reads and decodes the frame to denoise, with what its output carries.
fn decode_carrying(request: &Request<'_>, carry: &Carry) -> Result<(Frame, Carried), Failure> {
    let which = Input::Frame;
    Frame::from_exr_reader_carrying(open(request.frame, which)?, &request.limits, carry, &request.channel_maps)
        .map_err(|error| Failure::Invalid { which, error })
}

/// The kind of the frame to denoise as its header tells it, or `None` where the header
/// cannot be read (the decode then says why).
fn header_kind(request: &Request<'_>) -> Option<FrameKind> {
    let file = std::fs::File::open(request.frame).ok()?;
    let info = crate::frame::read_header(std::io::BufReader::new(file), &request.limits).ok()?;
    let names: Vec<&str> = info.channels.iter().map(String::as_str).collect();
    Some(FrameKind::of_channels(&names, &request.channel_maps))
}

/// The header attributes the denoiser adds to its results: the model variant, the networks
/// (architecture and SHA-256 of each graph) and the software version.
pub const ATTRIBUTES: [&str; 4] =
    ["mcdenoise/variant", "mcdenoise/model", "mcdenoise/model_sha256", "mcdenoise/version"];

/// The values of [`ATTRIBUTES`] for a result of `variant`.
fn attributes(denoiser: &dyn Denoiser, variant: Variant) -> [(&'static str, String); 4] {
    let models: Vec<_> = denoiser.models().into_iter().filter(|m| m.variant == variant).collect();
    let mut architectures: Vec<&str> = models.iter().map(|m| m.architecture.as_str()).collect();
    architectures.dedup();
    let hashes: Vec<String> =
        models.iter().map(|m| format!("{}:{}", m.component.map_or("both", |c| c.name()), m.sha256)).collect();
    [
        (ATTRIBUTES[0], variant.name().to_string()),
        (ATTRIBUTES[1], architectures.join(", ")),
        (ATTRIBUTES[2], hashes.join(", ")),
        (ATTRIBUTES[3], env!("CARGO_PKG_VERSION").to_string()),
    ]
}

/// The names of the channels of a denoised color layer: `R,G,B` for `""`, else
/// `<prefix>.R`, ...
fn rgb_names(prefix: &str) -> [String; 3] {
    ["R", "G", "B"].map(|c| if prefix.is_empty() { c.to_string() } else { format!("{prefix}.{c}") })
}

/// The names of the denoised channels of a result with `layers`.
fn written(layers: &[Layer]) -> Vec<String> {
    let components = layers.iter().filter(|l| **l != Layer::All).map(|l| l.name());
    std::iter::once("").chain(components).flat_map(rgb_names).collect()
}

/// Runs the pipeline. `on_tile` is called after each tile; returning `false` stops the
/// denoiser between tiles ([`EngineError::Cancelled`]).
pub fn run(
    denoiser: &mut dyn Denoiser,
    request: &Request<'_>,
    on_tile: &mut dyn FnMut(Progress) -> bool,
) -> Result<Output, Failure> {
    let started = Instant::now();
    let carry = Carry { all: request.layers.contains(&Layer::All), written: written(request.layers) };
    let decoding = || {
        let t = Instant::now();
        let decoded = tracing::info_span!("decode").in_scope(|| {
            let (frame, carried) = decode_carrying(request, &carry)?;
            let reference = request.reference.map(|p| decode(p, Input::Reference, &request.limits)).transpose()?;
            if let Some(r) = &reference {
                check_same_size((frame.width, frame.height), (r.width, r.height))?;
            }
            Ok::<_, Failure>((frame, carried, reference))
        });
        (decoded, ms(t))
    };
    let (decoded, decode_ms) = if denoiser.loads_on_demand() {
        // A denoiser that loads its networks on first use (`mcdenoise run`) loads them while
        // the frame decodes: its header says which variant the frame needs.
        let kind = header_kind(request);
        std::thread::scope(|scope| {
            let decoding = scope.spawn(decoding);
            if let Some(kind) = kind {
                denoiser.prepare(request.variant, kind);
            }
            decoding.join().unwrap_or_else(|panic| std::panic::resume_unwind(panic))
        })
    } else {
        decoding()
    };
    let (mut frame, mut carried, reference) = decoded?;
    if frame.sanitized.total > 0 {
        tracing::warn!(samples = frame.sanitized.total, "non-finite samples replaced by 0");
    }
    if !frame.missing_variances.is_empty() {
        tracing::info!(buffers = ?frame.missing_variances, "variance buffers missing; taken as 0");
    }
    let rescaled = variance::check(&mut frame, request.variance_check);
    if let Some(scale) = &rescaled {
        tracing::warn!(
            measure = scale.measured,
            factor = scale.factor,
            applied = scale.applied,
            "variances far larger than the image's noise"
        );
    }

    let span =
        tracing::info_span!("denoise", width = frame.width, height = frame.height, tiles = tracing::field::Empty);
    // The components are assembled only for a result that writes them.
    let components = request.layers.iter().any(|l| matches!(l, Layer::Diffuse | Layer::Specular));
    let options = Options { variant: request.variant, fireflies: request.fireflies, components };
    let out = span.in_scope(|| denoiser.denoise(&frame, options, on_tile))?;
    span.record("tiles", out.tiles);
    drop(span);
    let colors = |f: &Frame| request.keep_colors.then(|| Rgb::new(f.width, f.height, f.color()));
    let (input_color, reference_color) = (colors(&frame), reference.as_ref().and_then(colors));

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
    drop(reference);

    // The frame and the denoised planes are moved into the result, not copied.
    let t = Instant::now();
    let sanitized = std::mem::take(&mut frame.sanitized);
    let missing_variances = std::mem::take(&mut frame.missing_variances);
    let mut warnings = Vec::new();
    if frame.beauty_only && out.variant != Variant::Beauty {
        warnings.push(crate::frame::renderers::no_split_warning(out.variant.name()));
    }
    warnings.extend(rescaled.map(|s| s.warning()));
    for (name, value) in attributes(&*denoiser, out.variant) {
        carried.header.set_text(name, &value);
    }
    if out.exposure != 1.0 {
        warnings.push(exposure_warning(out.exposure));
    }
    let Denoised { width, height, variant, tiles, staged, timings: stages, fireflies, color, components, .. } = out;
    let (diffuse, specular) = components.map(|c| (c.diffuse, c.specular)).unzip();
    let mut components = [(Layer::Diffuse, diffuse), (Layer::Specular, specular)];
    let mut denoised: Vec<(String, Vec<f32>)> = rgb_names("").into_iter().zip(color).collect();
    for layer in request.layers {
        if let Some((_, planes)) = components.iter_mut().find(|(l, _)| l == layer) {
            denoised.extend(planes.take().into_iter().flat_map(|p| rgb_names(layer.name()).into_iter().zip(p)));
        }
    }
    drop(components);
    let encoded = tracing::info_span!("encode")
        .in_scope(|| carried.encode(frame, denoised))
        .map_err(|e| Failure::Encode(e.to_string()))?;
    let encode_ms = ms(t);

    let timings = Timings {
        queue: 0.0,
        decode: decode_ms,
        preprocess: (stages.fireflies + stages.preprocess).as_secs_f64() * 1e3,
        inference: stages.inference.as_secs_f64() * 1e3,
        reconstruction: stages.reconstruction.as_secs_f64() * 1e3,
        encode: encode_ms,
        total: ms(started),
    };
    Ok(Output {
        width,
        height,
        variant,
        tiles,
        staged,
        encoded,
        metrics,
        sanitized,
        missing_variances,
        warnings,
        fireflies,
        timings,
        fireflies_ms: stages.fireflies.as_secs_f64() * 1e3,
        input_color,
        reference_color,
    })
}
