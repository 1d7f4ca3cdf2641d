//! A frame: the planar f32 buffers of one rendered image, read from OpenEXR and validated.
//!
//! See `docs/frame-layout.md` for the channel names and what each buffer means.

mod carry;
mod exr_io;
pub mod layout;
mod plane;
pub mod presets;
pub mod renderers;

pub use carry::{Carried, Carry, FrameHeader, ALPHA};
pub use exr_io::{read_header, write_exr, write_planes, HeaderInfo, OutputLayer, SampleType, RESULT_ENCODING};
pub use layout::{Buffer, BUFFER_COUNT, NO_HIT_DEPTH};
pub use plane::PlaneRef;
pub use presets::ChannelMaps;

use std::sync::Arc;

use plane::Stored;

use serde::Serialize;

/// One channel of a frame, row-major, `width * height` samples.
pub type Plane = Vec<f32>;

/// Planes with their full channel names, as read from a file.
pub type NamedPlanes = Vec<(String, Plane)>;

/// Limits applied while reading a frame, before any pixel data is decompressed.
#[derive(Clone, Copy, Debug)]
pub struct Limits {
    /// Largest accepted `width * height`.
    pub max_pixels: u64,
}

impl Default for Limits {
    fn default() -> Self {
        // 8K UHD (7680×4320): larger frames are almost certainly a mistake or an attack.
        Limits { max_pixels: 7680 * 4320 }
    }
}

/// Why a frame was refused. Every variant names what is wrong.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum FrameError {
    #[error("missing channels: {} (the file has: {}){}", missing.join(", "), available_summary(available),
            hint.as_ref().map(|h| format!("; {h}")).unwrap_or_default())]
    MissingChannels { missing: Vec<String>, available: Vec<String>, hint: Option<String> },
    #[error("channel {channel} is {}x{} but {reference} is {}x{}", size.0, size.1, expected.0, expected.1)]
    SizeMismatch { channel: String, size: (usize, usize), reference: String, expected: (usize, usize) },
    #[error(
        "part {part} starts at ({}, {}) but part {reference} at ({}, {}); the parts of a frame must share one data window",
        origin.0, origin.1, expected.0, expected.1
    )]
    PartOrigins { part: String, origin: (i32, i32), reference: String, expected: (i32, i32) },
    #[error("channel {0} appears more than once")]
    DuplicateChannel(String),
    #[error("channel {0} is subsampled; only full-resolution channels are supported")]
    Subsampled(String),
    #[error("image is empty ({width}x{height})")]
    Empty { width: usize, height: usize },
    #[error("image is {width}x{height} = {pixels} pixels, over the limit of {limit}")]
    TooLarge { width: usize, height: usize, pixels: u64, limit: u64 },
    #[error("deep data is not supported (part {0})")]
    Deep(String),
    #[error("truncated EXR: {0}")]
    Truncated(String),
    #[error("not a valid EXR: {0}")]
    Corrupt(String),
    #[error("unsupported EXR feature: {0}")]
    Unsupported(String),
}

fn available_summary(names: &[String]) -> String {
    const SHOWN: usize = 40;
    if names.is_empty() {
        return "no channels".into();
    }
    let mut s = names.iter().take(SHOWN).cloned().collect::<Vec<_>>().join(", ");
    if names.len() > SHOWN {
        s.push_str(&format!(", … {} more", names.len() - SHOWN));
    }
    s
}

/// Non-finite samples replaced by 0, per buffer.
#[derive(Clone, Debug, Default, Serialize, serde::Deserialize, PartialEq)]
pub struct Sanitized {
    pub total: u64,
    /// Buffer name → count, only buffers with replacements.
    pub by_buffer: std::collections::BTreeMap<String, u64>,
}

/// What chooses a frame's variant (`Engine::select`): whether it lacks the
/// diffuse/specular split and whether it has covariance. Both follow from the channel names
/// alone, so a header tells them before any pixel is decoded ([`FrameKind::of_channels`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct FrameKind {
    /// [`Frame::beauty_only`].
    pub beauty_only: bool,
    /// The frame has a covariance buffer.
    pub covariance: bool,
}

impl FrameKind {
    /// The kind of a frame whose file has channels `names` (renderers' AOV names through
    /// `maps`), as [`Frame::kind`] gives it once decoded.
    pub fn of_channels(names: &[&str], maps: &ChannelMaps) -> FrameKind {
        let all = renderers::with_derived(names, maps);
        let all: Vec<&str> = all.iter().map(String::as_str).collect();
        let covariance = layout::resolve(&all)[Buffer::Covariance as usize].is_some();
        FrameKind { beauty_only: renderers::beauty_only(names, maps), covariance }
    }
}

/// A validated frame: every required buffer present, all of one size, all samples finite.
#[derive(Clone, Debug)]
pub struct Frame {
    pub width: usize,
    pub height: usize,
    /// Indexed by `Buffer as usize`: 3 planes for colors, 1 or 3 for variances, 1 for depth
    /// and covariance; the colors and depth as f32, the rest as f16 where it fits
    /// ([`plane`]). Shared between clones: a clone costs no pixels until a buffer is
    /// changed ([`Frame::planes_mut`] copies that buffer alone), so the engine's firefly
    /// handling copies only the diffuse and specular of a 4K frame, not all of it.
    buffers: [Option<Arc<Stored>>; BUFFER_COUNT],
    pub sanitized: Sanitized,
    /// Variance buffers the file did not have, taken as 0
    /// ([`Frame::fill_missing_variances`]).
    pub missing_variances: Vec<String>,
    /// The file has no diffuse/specular split, only a beauty: its diffuse is the beauty and
    /// its specular zero ([`renderers::beauty_only`]); the `beauty` variant is made for it.
    pub beauty_only: bool,
}

impl Frame {
    /// Builds a frame from named planes (already of one size), checking that the required
    /// buffers are present and replacing non-finite samples.
    pub fn from_planes(
        width: usize,
        height: usize,
        mut planes: NamedPlanes,
        required: &[Buffer],
        maps: &ChannelMaps,
    ) -> Result<Frame, FrameError> {
        if width == 0 || height == 0 {
            return Err(FrameError::Empty { width, height });
        }
        let names: Vec<&str> = planes.iter().map(|(n, _)| n.as_str()).collect();
        let beauty_only = renderers::beauty_only(&names, maps);
        renderers::derive(&mut planes, width * height, maps);
        let names: Vec<&str> = planes.iter().map(|(n, _)| n.as_str()).collect();
        check_required(&names, required, maps)?;
        let resolved = layout::resolve(&names);
        let mut buffers: [Option<Arc<Stored>>; BUFFER_COUNT] = Default::default();
        let mut sanitized = Sanitized::default();
        for buffer in Buffer::ALL {
            let Some(indices) = &resolved[buffer as usize] else { continue };
            let mut count = 0u64;
            let mut taken = Vec::with_capacity(indices.len());
            for &i in indices {
                let mut plane = std::mem::take(&mut planes[i].1);
                for v in plane.iter_mut() {
                    if !v.is_finite() {
                        *v = 0.0;
                        count += 1;
                    }
                }
                if buffer == Buffer::Depth {
                    // A renderer's "infinitely far" is the canonical "no hit".
                    plane.iter_mut().filter(|v| **v >= NO_HIT_DEPTH).for_each(|v| *v = 0.0);
                }
                taken.push(plane);
            }
            if count > 0 {
                sanitized.total += count;
                sanitized.by_buffer.insert(buffer.name().to_string(), count);
            }
            buffers[buffer as usize] = Some(Arc::new(Stored::new(buffer, taken)));
        }
        Ok(Frame { width, height, buffers, sanitized, missing_variances: Vec::new(), beauty_only })
    }

    /// Fills the variance buffers the renderer did not write with 0 for every buffer that is
    /// present, and lists them in [`Frame::missing_variances`].
    ///
    /// Zero, "no information", because it is what the networks handle best: on the
    /// committed fixtures, zero variances change the output's RelMSE by at most 12 %
    /// (cornell 0.0079 → 0.0081, caustic 0.036 → 0.040, shadow equal), while a local
    /// estimate (the sample variance of the image over 5×5 pixels) made it 21–26× worse on
    /// cornell and caustic (2–6.5× over 3×3), since it counts edges and texture as noise.
    pub fn fill_missing_variances(&mut self) {
        let n = self.pixels();
        for (base, var) in Buffer::ALL.into_iter().filter_map(|b| b.variance().map(|v| (b, v))) {
            if self.has(var) || !self.has(base) {
                continue;
            }
            self.buffers[var as usize] = Some(Arc::new(Stored::zeros(var, 1, n)));
            self.missing_variances.push(var.name().to_string());
        }
    }

    pub fn pixels(&self) -> usize {
        self.width * self.height
    }

    pub fn has(&self, buffer: Buffer) -> bool {
        self.buffers[buffer as usize].is_some()
    }

    /// What chooses its variant.
    pub fn kind(&self) -> FrameKind {
        FrameKind { beauty_only: self.beauty_only, covariance: self.has(Buffer::Covariance) }
    }

    fn stored(&self, buffer: Buffer) -> &Stored {
        self.buffers[buffer as usize]
            .as_deref()
            .unwrap_or_else(|| panic!("buffer {} is absent; check Frame::has first", buffer.name()))
    }

    /// All planes of a buffer, whatever their storage ([`PlaneRef`]).
    ///
    /// # Panics
    /// If the buffer is absent; required buffers are always present.
    pub fn planes(&self, buffer: Buffer) -> Vec<PlaneRef<'_>> {
        let stored = self.stored(buffer);
        (0..stored.len()).map(|c| stored.plane(c)).collect()
    }

    /// Plane `c` of a buffer; a one-plane buffer (a mono variance) answers for every `c`.
    pub fn plane(&self, buffer: Buffer, c: usize) -> PlaneRef<'_> {
        let stored = self.stored(buffer);
        stored.plane(c.min(stored.len() - 1))
    }

    /// The three planes of a color-like buffer; a one-plane buffer (a mono variance) stands
    /// in all three.
    pub fn rgb(&self, buffer: Buffer) -> [PlaneRef<'_>; 3] {
        std::array::from_fn(|c| self.plane(buffer, c))
    }

    /// The planes of a buffer that is always f32: a color (diffuse, specular, color) or the
    /// depth ([`Buffer::half_precision`] is false).
    ///
    /// # Panics
    /// If the buffer is absent or may be kept as f16.
    pub fn f32_planes(&self, buffer: Buffer) -> &[Plane] {
        match self.stored(buffer) {
            Stored::F32(planes) => planes,
            Stored::F16(_) => panic!("buffer {} is kept as f16; read it with Frame::planes", buffer.name()),
        }
    }

    /// Plane `c` of a buffer that is always f32 ([`Frame::f32_planes`]).
    pub fn f32_plane(&self, buffer: Buffer, c: usize) -> &[f32] {
        let planes = self.f32_planes(buffer);
        &planes[c.min(planes.len() - 1)]
    }

    /// All planes of a buffer as f32, to change them in place (e.g. the engine's firefly
    /// handling); a buffer shared with a clone is copied first, and one kept as f16 is
    /// converted (and kept as f32 from then on).
    ///
    /// # Panics
    /// If the buffer is absent.
    pub fn planes_mut(&mut self, buffer: Buffer) -> &mut [Plane] {
        let slot = self.buffers[buffer as usize]
            .as_mut()
            .unwrap_or_else(|| panic!("buffer {} is absent; check Frame::has first", buffer.name()));
        let stored = Arc::make_mut(slot);
        if let Stored::F16(_) = stored {
            *stored = Stored::F32(std::mem::replace(stored, Stored::F32(Vec::new())).into_f32());
        }
        match stored {
            Stored::F32(planes) => planes.as_mut_slice(),
            Stored::F16(_) => unreachable!("converted above"),
        }
    }

    /// Replaces a buffer's planes (e.g. by a filtered copy computed from them), without
    /// copying what it held; stored as decoded planes are (f16 where the buffer allows it
    /// and every sample fits).
    pub fn set_planes(&mut self, buffer: Buffer, planes: Vec<Plane>) {
        self.buffers[buffer as usize] = Some(Arc::new(Stored::new(buffer, planes)));
    }

    /// Drops a buffer (e.g. covariance, to run the no-covariance model on a full frame).
    pub fn remove(&mut self, buffer: Buffer) {
        self.buffers[buffer as usize] = None;
    }

    /// Takes a buffer's planes out of the frame as f32, which then lacks it.
    pub fn take(&mut self, buffer: Buffer) -> Option<Vec<Plane>> {
        self.buffers[buffer as usize].take().map(|s| Arc::unwrap_or_clone(s).into_f32())
    }

    /// The frame's total radiance: `R,G,B` if present, else diffuse + specular.
    pub fn color(&self) -> [Plane; 3] {
        if self.has(Buffer::Color) {
            let p = self.f32_planes(Buffer::Color);
            return [p[0].clone(), p[1].clone(), p[2].clone()];
        }
        self.diffuse_plus_specular()
    }

    /// The frame as the `beauty` variant takes it: the beauty (diffuse + specular) in the
    /// diffuse slot, the specular zero, every variance zero, no covariance; albedo, normal
    /// and depth as they are. A frame that is already [`Frame::beauty_only`] keeps its
    /// color buffers, and variance buffers that are zero already (those
    /// [`Frame::fill_missing_variances`] added) are kept as they are, not allocated again.
    pub fn to_beauty(&self) -> Frame {
        let mut out = self.clone();
        let n = self.pixels();
        if !self.beauty_only {
            let beauty = self.diffuse_plus_specular();
            out.buffers[Buffer::Diffuse as usize] = Some(Arc::new(Stored::F32(beauty.into())));
            out.buffers[Buffer::Specular as usize] = Some(Arc::new(Stored::zeros(Buffer::Specular, 3, n)));
        }
        out.remove(Buffer::Covariance);
        out.remove(Buffer::CovarianceVariance);
        for var in Buffer::ALL.into_iter().filter_map(Buffer::variance) {
            if out.has(var) && out.planes(var).iter().any(PlaneRef::any_nonzero) {
                out.buffers[var as usize] = Some(Arc::new(Stored::zeros(var, 1, n)));
            }
        }
        out.beauty_only = true;
        out
    }

    /// Diffuse + specular, per channel.
    pub fn diffuse_plus_specular(&self) -> [Plane; 3] {
        std::array::from_fn(|c| {
            let d = self.f32_plane(Buffer::Diffuse, c);
            let s = self.f32_plane(Buffer::Specular, c);
            d.iter().zip(s).map(|(a, b)| a + b).collect()
        })
    }

    /// Reads and validates a frame from the bytes of an EXR file (renderers' AOV names
    /// through the shipped channel maps).
    pub fn from_exr_bytes(bytes: &[u8], limits: &Limits) -> Result<Frame, FrameError> {
        Frame::from_exr_bytes_carrying(bytes, limits, &Carry::default(), &ChannelMaps::default())
            .map(|(frame, _)| frame)
    }

    /// Reads and validates a frame, and what its output is to carry of it: the header
    /// (windows, pixel aspect, attributes), the beauty's alpha and the channels `carry`
    /// asks for. Only the channels the frame reads are converted to f32. Renderers' AOV
    /// names are read through `maps`.
    pub fn from_exr_bytes_carrying(
        bytes: &[u8],
        limits: &Limits,
        carry: &Carry,
        maps: &ChannelMaps,
    ) -> Result<(Frame, Carried), FrameError> {
        Frame::from_exr_reader_carrying(std::io::Cursor::new(bytes), limits, carry, maps)
    }

    /// [`Frame::from_exr_bytes_carrying`] from a reader, such as a buffered file: the file's
    /// bytes are never all in memory (at 4K, 0.65 GB of float32 input beside its decoded
    /// planes). An I/O error while reading reads as a truncated or corrupt file.
    pub fn from_exr_reader_carrying(
        input: impl std::io::Read + std::io::Seek,
        limits: &Limits,
        carry: &Carry,
        maps: &ChannelMaps,
    ) -> Result<(Frame, Carried), FrameError> {
        let decoded = exr_io::decode_from(input, limits)?;
        let (w, h) = (decoded.width, decoded.height);
        // Checked on every name: the error lists what the file has.
        let names: Vec<String> = decoded.channels.iter().map(|(_, c)| c.name.to_string()).collect();
        check_required(&names.iter().map(String::as_str).collect::<Vec<_>>(), layout::REQUIRED, maps)?;
        let (planes, carried) = carry::split(decoded, carry, maps);
        let mut frame = Frame::from_planes(w, h, planes, layout::REQUIRED, maps)?;
        frame.fill_missing_variances();
        Ok((frame, carried))
    }

    /// Reads a reference frame: only a color is needed (`R,G,B`, or diffuse and specular).
    pub fn reference_from_exr_bytes(bytes: &[u8], limits: &Limits) -> Result<Frame, FrameError> {
        Frame::reference_from_exr_reader(std::io::Cursor::new(bytes), limits)
    }

    /// [`Frame::reference_from_exr_bytes`] from a reader, such as a buffered file.
    pub fn reference_from_exr_reader(
        input: impl std::io::Read + std::io::Seek,
        limits: &Limits,
    ) -> Result<Frame, FrameError> {
        let (w, h, planes) = exr_io::read_planes(input, limits)?;
        let names: Vec<&str> = planes.iter().map(|(n, _)| n.as_str()).collect();
        check_reference(&names)?;
        let required = reference_buffers(&names);
        Frame::from_planes(w, h, planes, required, &ChannelMaps::default())
    }
}

/// Checks that channels `names` provide every buffer of `required` (renderers' AOV names
/// through `maps`); the error lists the names of what is missing and every name the file
/// has.
pub fn check_required(names: &[&str], required: &[Buffer], maps: &ChannelMaps) -> Result<(), FrameError> {
    let all = renderers::with_derived(names, maps);
    let all: Vec<&str> = all.iter().map(String::as_str).collect();
    let resolved = layout::resolve(&all);
    let missing: Vec<String> =
        required.iter().filter(|b| resolved[**b as usize].is_none()).flat_map(|b| missing_of(&all, *b)).collect();
    if missing.is_empty() {
        return Ok(());
    }
    let mut available: Vec<String> = names.iter().map(|s| s.to_string()).collect();
    available.sort();
    Err(FrameError::MissingChannels { missing, available, hint: renderers::hint(names, maps) })
}

/// The channels `names` lacks for `buffer`: the rest of its most complete spelling (a file
/// with `diffuse.R` and `diffuse.B` lacks `diffuse.G`), or all of the preferred spelling
/// when the file has none of them.
fn missing_of(names: &[&str], buffer: Buffer) -> Vec<String> {
    let alternatives = layout::spec(buffer).alternatives;
    let present = |alt: &[&str]| alt.iter().filter(|n| names.contains(n)).count();
    let mut best = alternatives[0];
    for alt in &alternatives[1..] {
        if present(alt) > present(best) {
            best = alt;
        }
    }
    best.iter().filter(|n| !names.contains(n)).map(|n| n.to_string()).collect()
}

/// The buffers a reference is read from: `R,G,B` when present, else diffuse and specular.
fn reference_buffers(names: &[&str]) -> &'static [Buffer] {
    if layout::resolve(names)[Buffer::Color as usize].is_some() {
        &[Buffer::Color]
    } else {
        &[Buffer::Diffuse, Buffer::Specular]
    }
}

/// Checks that channels `names` hold a reference color (`R,G,B`, or diffuse and specular).
pub fn check_reference(names: &[&str]) -> Result<(), FrameError> {
    check_required(names, reference_buffers(names), &ChannelMaps::default()).map_err(|e| match e {
        FrameError::MissingChannels { available, .. } => FrameError::MissingChannels {
            missing: vec!["R, G, B (or diffuse.R/G/B and specular.R/G/B)".into()],
            available,
            hint: None,
        },
        other => other,
    })
}
