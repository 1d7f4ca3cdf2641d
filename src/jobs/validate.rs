//! Cheap checks of an uploaded frame at submission time: only the EXR header is read (no
//! pixel data), so a wrong file is refused at once with the channel or limit it breaks.
//! The full decode happens in the worker; a defect found there fails the job.
//!
//! Locking: none; it runs on the blocking pool during a commit, before the job exists.

use std::io::BufReader;
use std::path::Path;

use crate::frame::{self, layout, ChannelMaps, FrameError, HeaderInfo, Limits};

fn read_header(path: &Path, limits: &Limits) -> Result<HeaderInfo, FrameError> {
    let file = std::fs::File::open(path).map_err(|e| FrameError::Corrupt(format!("cannot open the upload: {e}")))?;
    frame::read_header(BufReader::new(file), limits)
}

fn names(info: &HeaderInfo) -> Vec<&str> {
    info.channels.iter().map(String::as_str).collect()
}

/// Checks that the header provides every buffer a frame must have (renderers' AOV names
/// through `maps`).
pub fn check_frame(path: &Path, limits: &Limits, maps: &ChannelMaps) -> Result<HeaderInfo, FrameError> {
    let info = read_header(path, limits)?;
    frame::check_required(&names(&info), layout::REQUIRED, maps)?;
    Ok(info)
}

/// Checks that the header provides a color (`R,G,B`, or diffuse and specular).
pub fn check_reference(path: &Path, limits: &Limits) -> Result<HeaderInfo, FrameError> {
    let info = read_header(path, limits)?;
    frame::check_reference(&names(&info))?;
    Ok(info)
}
