//! What a denoised frame keeps of its input: where it lies (data window, display window,
//! pixel aspect), the header's attributes, the beauty's alpha and, on request
//! (`layers=all`), every other channel.
//!
//! A result must composite exactly where its input did: a frame with overscan (data window
//! −8..263 inside a display window 0..255) comes back with the same windows, and the
//! channels the denoiser does not produce come back bit for bit, in their own sample types.
//!
//! # Memory
//! Carried channels are moved out of the decoded file, never converted: an f16 AOV stays
//! f16 and a u32 ID stays exact. A channel that is both a network input and carried (the
//! albedo under `layers=all`) is held once, as the frame's plane, and written back from it
//! in its own sample type once the frame is no longer needed. Only where the frame's plane
//! would not give the input back (non-finite samples, which the frame replaces by 0; u32
//! samples; float samples of a buffer the frame keeps as half, `plane.rs`; Cycles passes
//! the frame derives its buffers from) is the input kept as well.

use std::collections::{HashMap, HashSet};

use exr::prelude::*;

use super::exr_io::{copy_plane, to_plane, Decoded};
use super::{layout, renderers, Buffer, ChannelMaps, Frame, NamedPlanes, Plane, SampleType};

/// The header of an input that its output keeps.
#[derive(Clone, Debug, PartialEq)]
pub struct FrameHeader {
    /// What all parts share: display window, pixel aspect, chromaticities, time code.
    pub image: ImageAttributes,
    /// The own attributes of the part holding the beauty (of the first part when no part
    /// does), without the part name: the data window's origin (`layer_position`), camera
    /// matrices, renderer metadata, custom attributes.
    pub layer: LayerAttributes,
}

impl FrameHeader {
    /// The data window's top-left corner; negative with overscan.
    pub fn origin(&self) -> (i32, i32) {
        (self.layer.layer_position.x(), self.layer.layer_position.y())
    }

    /// Sets a text attribute, replacing one of the same name. A name or value with
    /// characters outside Latin-1 is skipped (EXR text is bytes).
    pub fn set_text(&mut self, name: &str, value: &str) {
        if let (Some(name), Some(value)) = (Text::new_or_none(name), Text::new_or_none(value)) {
            self.image.other.remove(&name);
            self.layer.other.insert(name, AttributeValue::Text(value));
        }
    }
}

/// Which input channels an output carries besides the beauty's alpha.
#[derive(Clone, Debug, Default)]
pub struct Carry {
    /// Every channel but the beauty (`layers=all`).
    pub all: bool,
    /// The channels the output writes itself (the denoised `R,G,B`, `diffuse.*`, ...): an
    /// input channel of one of these names is not carried.
    pub written: Vec<String>,
}

/// The name under which the output carries the beauty's alpha, beside `R,G,B`.
pub const ALPHA: &str = "A";

/// One carried channel.
enum Source {
    /// The input's channel, moved, named as the output names it.
    Own(AnyChannel<FlatSamples>),
    /// Equal to plane `component` of the frame's `buffer`, written back as `sample`.
    Frame { name: Text, quantize_linearly: bool, sample: SampleType, buffer: Buffer, component: usize },
}

/// What an output carries of its input (see the module documentation).
pub struct Carried {
    pub header: FrameHeader,
    channels: Vec<Source>,
}

impl Carried {
    /// The names of the carried channels, as the output names them.
    pub fn names(&self) -> Vec<String> {
        self.channels
            .iter()
            .map(|s| match s {
                Source::Own(c) => c.name.to_string(),
                Source::Frame { name, .. } => name.to_string(),
            })
            .collect()
    }

    /// Encodes the result of `frame`: the `denoised` float32 channels (`R,G,B`,
    /// `diffuse.R`, ...) beside the carried ones, with the carried header. The planes are
    /// moved into the encoder, not copied: the frame's planes that stand for carried
    /// channels are taken from it, and the rest of it is dropped first. A carried channel
    /// named like a denoised one is left out.
    ///
    /// # Panics
    /// If a buffer a carried channel stands for was removed from the frame
    /// ([`Frame::remove`]); frames are only read while they are denoised.
    pub fn encode(self, frame: Frame, denoised: Vec<(String, Plane)>) -> exr::error::Result<Vec<u8>> {
        let (width, height) = (frame.width, frame.height);
        let (header, mut channels) = self.into_channels(frame);
        let names: HashSet<&str> = denoised.iter().map(|(n, _)| n.as_str()).collect();
        channels.retain(|c| !names.contains(c.name.to_string().as_str()));
        channels.extend(denoised.into_iter().map(|(n, p)| AnyChannel::new(n.as_str(), FlatSamples::F32(p))));
        super::exr_io::encode(width, height, header, channels)
    }

    /// The header and the carried channels, in the input's sample types (see [`Carried::encode`]).
    fn into_channels(self, mut frame: Frame) -> (FrameHeader, Vec<AnyChannel<FlatSamples>>) {
        let mut taken: HashMap<Buffer, Vec<Plane>> = HashMap::new();
        // What no carried channel stands for goes before the planes are converted.
        let kept: HashSet<Buffer> = self
            .channels
            .iter()
            .filter_map(|s| if let Source::Frame { buffer, .. } = s { Some(*buffer) } else { None })
            .collect();
        for buffer in Buffer::ALL.into_iter().filter(|b| !kept.contains(b)) {
            frame.remove(buffer);
        }
        let channels = self
            .channels
            .into_iter()
            .map(|source| match source {
                Source::Own(channel) => channel,
                Source::Frame { name, quantize_linearly, sample, buffer, component } => {
                    let planes = taken.entry(buffer).or_insert_with(|| {
                        frame.take(buffer).expect("a buffer that carried channels stand for is in the frame")
                    });
                    let plane = std::mem::take(&mut planes[component]);
                    let sample_data = match sample {
                        SampleType::F32 => FlatSamples::F32(plane),
                        SampleType::F16 => FlatSamples::F16(plane.into_iter().map(f16::from_f32).collect()),
                    };
                    AnyChannel { name, sample_data, quantize_linearly, sampling: Vec2(1, 1) }
                }
            })
            .collect();
        (self.header, channels)
    }
}

/// The sample type in which a frame plane converted from `samples` gives them back exactly:
/// `None` for u32 and for non-finite samples (the frame replaces those by 0).
fn exact_type(samples: &FlatSamples) -> Option<SampleType> {
    match samples {
        FlatSamples::F16(v) => v.iter().all(|x| x.is_finite()).then_some(SampleType::F16),
        FlatSamples::F32(v) => v.iter().all(|x| x.is_finite()).then_some(SampleType::F32),
        FlatSamples::U32(_) => None,
    }
}

/// Splits a decoded file into the f32 planes a frame is built from (only the channels the
/// frame reads: its buffers and what Cycles buffers are derived from) and what the output
/// carries.
pub(super) fn split(decoded: Decoded, carry: &Carry, maps: &ChannelMaps) -> (NamedPlanes, Carried) {
    let Decoded { image, mut parts, channels, .. } = decoded;
    let names: Vec<String> = channels.iter().map(|(_, c)| c.name.to_string()).collect();
    let refs: Vec<&str> = names.iter().map(String::as_str).collect();

    // The frame's buffers, resolved as `Frame::from_planes` resolves them: each input
    // channel's (buffer, component), and the channels derived buffers are made from.
    let all = renderers::with_derived(&refs, maps);
    let all: Vec<&str> = all.iter().map(String::as_str).collect();
    let mut role: Vec<Option<(Buffer, usize)>> = vec![None; refs.len()];
    for (buffer, indices) in Buffer::ALL.into_iter().zip(layout::resolve(&all)) {
        for (component, i) in indices.into_iter().flatten().enumerate() {
            if i < role.len() {
                role[i] = Some((buffer, component));
            }
        }
    }
    let recipes = renderers::recipes(&refs, maps);
    let sources: HashSet<&str> = recipes.iter().flat_map(|(_, r)| r.sources()).collect();

    let beauty = renderers::beauty(&refs);
    let carried = |name: &str| {
        Some(name) == beauty.alpha
            || (carry.all && !beauty.color.contains(&name) && !carry.written.iter().any(|w| w == name))
    };
    let home = |name: Option<&&str>| name.and_then(|n| refs.iter().position(|r| r == n)).map(|i| channels[i].0);
    let part = home(beauty.color.first()).or_else(|| home(beauty.alpha.as_ref())).unwrap_or(0);
    let mut layer = if part < parts.len() { parts.swap_remove(part) } else { LayerAttributes::default() };
    layer.layer_name = None;

    let mut planes: NamedPlanes = Vec::new();
    let mut out = Vec::new();
    for (i, (_, mut channel)) in channels.into_iter().enumerate() {
        let name = refs[i];
        let needed = role[i].is_some() || sources.contains(name);
        if !carried(name) {
            if needed {
                planes.push((name.to_string(), to_plane(channel.sample_data)));
            }
            continue;
        }
        if Some(name) == beauty.alpha {
            channel.name = Text::from(ALPHA);
        }
        if !needed {
            out.push(Source::Own(channel));
            continue;
        }
        match (role[i], exact_type(&channel.sample_data)) {
            (Some((buffer, component)), Some(sample)) if sample == SampleType::F16 || !buffer.half_precision() => {
                let AnyChannel { name: carried_name, sample_data, quantize_linearly, .. } = channel;
                planes.push((name.to_string(), to_plane(sample_data)));
                out.push(Source::Frame { name: carried_name, quantize_linearly, sample, buffer, component });
            }
            _ => {
                planes.push((name.to_string(), copy_plane(&channel.sample_data)));
                out.push(Source::Own(channel));
            }
        }
    }
    (planes, Carried { header: FrameHeader { image, layer }, channels: out })
}
