//! Cheap checks of an uploaded frame at submission time: only the EXR header is read (no
//! pixel data), so a wrong file is refused at once with the channel or limit it breaks.
//! The full decode happens in the worker; a defect found there fails the job.

use std::io::BufReader;
use std::path::Path;

use exr::math::Vec2;
use exr::meta::MetaData;

use crate::frame::{layout, Buffer, FrameError, Limits};

/// What the header of an accepted frame says.
#[derive(Clone, Debug, PartialEq)]
pub struct HeaderInfo {
    pub width: usize,
    pub height: usize,
    pub channels: Vec<String>,
}

/// Reads the header of the EXR file at `path`: size limit, deep data, subsampling, parts
/// of different sizes. Channel names are full names (`<part>.<channel>` in multi-part
/// files), as the frame reader matches them.
pub fn read_header(path: &Path, limits: &Limits) -> Result<HeaderInfo, FrameError> {
    let file = std::fs::File::open(path).map_err(|e| FrameError::Corrupt(format!("cannot open the upload: {e}")))?;
    let meta = MetaData::read_from_buffered(BufReader::new(file), false).map_err(map_exr_error)?;
    let mut size: Option<(String, (usize, usize))> = None;
    let mut channels = Vec::new();
    for header in meta.headers.iter() {
        let part = header.own_attributes.layer_name.as_ref().map(|t| t.to_string()).unwrap_or_default();
        if header.deep {
            return Err(FrameError::Deep(if part.is_empty() { "0".into() } else { part }));
        }
        let (w, h) = (header.layer_size.0, header.layer_size.1);
        let pixels = w as u64 * h as u64;
        if pixels > limits.max_pixels {
            return Err(FrameError::TooLarge { width: w, height: h, pixels, limit: limits.max_pixels });
        }
        for ch in header.channels.list.iter() {
            let name = full_name(&part, &ch.name.to_string());
            if ch.sampling != Vec2(1, 1) {
                return Err(FrameError::Subsampled(name));
            }
            match &size {
                None => size = Some((name.clone(), (w, h))),
                Some((reference, expected)) if *expected != (w, h) => {
                    return Err(FrameError::SizeMismatch {
                        channel: name,
                        size: (w, h),
                        reference: reference.clone(),
                        expected: *expected,
                    })
                }
                Some(_) => {}
            }
            if channels.contains(&name) {
                return Err(FrameError::DuplicateChannel(name));
            }
            channels.push(name);
        }
    }
    let Some((_, (width, height))) = size else {
        return Err(FrameError::MissingChannels { missing: vec!["any channel".into()], available: vec![] });
    };
    if width == 0 || height == 0 {
        return Err(FrameError::Empty { width, height });
    }
    Ok(HeaderInfo { width, height, channels })
}

/// Checks that the header provides every buffer a frame must have.
pub fn check_frame(path: &Path, limits: &Limits) -> Result<HeaderInfo, FrameError> {
    let info = read_header(path, limits)?;
    require(&info, layout::REQUIRED)?;
    Ok(info)
}

/// Checks that the header provides a color (`R,G,B`, or diffuse and specular).
pub fn check_reference(path: &Path, limits: &Limits) -> Result<HeaderInfo, FrameError> {
    let info = read_header(path, limits)?;
    let names: Vec<&str> = info.channels.iter().map(String::as_str).collect();
    let resolved = layout::resolve(&names);
    let has = |b: Buffer| resolved[b as usize].is_some();
    if !(has(Buffer::Color) || (has(Buffer::Diffuse) && has(Buffer::Specular))) {
        let mut available = info.channels.clone();
        available.sort();
        return Err(FrameError::MissingChannels {
            missing: vec!["R, G, B (or diffuse.R/G/B and specular.R/G/B)".into()],
            available,
        });
    }
    Ok(info)
}

fn require(info: &HeaderInfo, required: &[Buffer]) -> Result<(), FrameError> {
    let names: Vec<&str> = info.channels.iter().map(String::as_str).collect();
    let resolved = layout::resolve(&names);
    let missing: Vec<String> = required
        .iter()
        .filter(|b| resolved[**b as usize].is_none())
        .flat_map(|b| layout::spec(*b).alternatives[0].iter().map(|s| s.to_string()))
        .collect();
    if missing.is_empty() {
        Ok(())
    } else {
        let mut available = info.channels.clone();
        available.sort();
        Err(FrameError::MissingChannels { missing, available })
    }
}

/// The frame reader's naming rule (`src/frame/exr_io.rs`): the part name goes in front
/// unless the channel name already starts with it.
fn full_name(part: &str, channel: &str) -> String {
    if part.is_empty() || channel.starts_with(&format!("{part}.")) {
        channel.to_string()
    } else {
        format!("{part}.{channel}")
    }
}

fn map_exr_error(e: exr::error::Error) -> FrameError {
    use exr::error::Error as E;
    match e {
        E::Io(io) if io.kind() == std::io::ErrorKind::UnexpectedEof => FrameError::Truncated(io.to_string()),
        E::Io(io) => FrameError::Corrupt(io.to_string()),
        E::Invalid(msg) => FrameError::Corrupt(msg.to_string()),
        E::NotSupported(msg) => FrameError::Unsupported(msg.to_string()),
        E::Aborted => FrameError::Corrupt("reading was aborted".into()),
    }
}
