//! Previews of a job's frames (`GET /v1/jobs/{id}/preview`): the noisy input, the result
//! and the reference, tone mapped by [`crate::preview`] and cached.
//!
//! Sources: while a job is queued or running, its uploads (`input.exr`, `reference.exr`,
//! decoded as a worker would, so Cycles and renderer-preset frames show their beauty).
//! When it succeeds the worker keeps the colour it decoded of each upload as
//! `preview-input.exr` and `preview-reference.exr` (half float) before the uploads are
//! removed, so a finished job still shows its before and after; the result comes from
//! `result.exr`. A failed or cancelled job keeps nothing to show.
//!
//! Encoded previews are kept in memory, least recently used out first, up to
//! [`CACHE_BYTES`]; the key is the job, the source and every parameter, and every source is
//! immutable once written, so an entry never goes stale.
//!
//! Locking: the state lock is taken once to check the job and pick the source; reading
//! and rendering run on the blocking pool with no lock held; the cache has its own mutex,
//! held only to look up or insert.

use std::collections::{HashMap, VecDeque};
use std::path::PathBuf;
use std::sync::{Arc, Mutex};

use super::{entry_for, lock_poisoned, not_found, JobService};
use crate::auth::Caller;
use crate::error::{Error, Result};
use crate::jobs::{JobRecord, JobState};
use crate::pipeline::{self, Input};
use crate::preview::{self, Rgb, Spec};

/// Bytes of encoded previews kept in memory, at most.
pub const CACHE_BYTES: usize = 64 << 20;

/// Which frame of a job to preview.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum PreviewImage {
    Input,
    Result,
    Reference,
}

impl PreviewImage {
    pub const ALL: [PreviewImage; 3] = [PreviewImage::Input, PreviewImage::Result, PreviewImage::Reference];

    pub fn name(self) -> &'static str {
        match self {
            PreviewImage::Input => "input",
            PreviewImage::Result => "result",
            PreviewImage::Reference => "reference",
        }
    }
}

impl std::str::FromStr for PreviewImage {
    type Err = String;

    fn from_str(s: &str) -> std::result::Result<PreviewImage, String> {
        PreviewImage::ALL.into_iter().find(|i| i.name() == s).ok_or_else(|| {
            format!(
                "unknown image `{}` (expected input, result or reference)",
                crate::error::truncate(s, crate::error::ECHO_CHARS)
            )
        })
    }
}

/// Where a preview's pixels come from.
#[derive(Clone, Debug)]
enum Source {
    /// An upload, decoded as the worker decodes it.
    Upload(PathBuf, Input),
    /// A file with `R,G,B` (the result, a kept colour).
    Rgb(PathBuf),
}

impl Source {
    fn path(&self) -> &std::path::Path {
        match self {
            Source::Upload(p, _) | Source::Rgb(p) => p,
        }
    }

    fn read(&self, id: &str, limits: &crate::frame::Limits) -> Result<Rgb> {
        let gone = |e: &std::io::Error| e.kind() == std::io::ErrorKind::NotFound;
        match self {
            Source::Upload(path, which) => match pipeline::decode(path, *which, limits) {
                Ok(frame) => Ok(Rgb::new(frame.width, frame.height, frame.color())),
                Err(pipeline::Failure::Read { error, .. }) if gone(&error) => Err(not_found(id)),
                Err(pipeline::Failure::Read { error, .. }) => Err(Error::internal("cannot read the upload", error)),
                Err(e) => Err(Error::InvalidFrame(e.to_string())),
            },
            Source::Rgb(path) => preview::read_rgb_exr(path).map_err(|e| match e {
                // Deleted or expired since the job was checked.
                exr::error::Error::Io(io) if gone(&io) => not_found(id),
                e => Error::Internal(format!("cannot read {}: {e}", path.display())),
            }),
        }
    }
}

/// Encoded previews, least recently used out first, within a byte budget.
pub(super) struct PreviewCache {
    capacity: usize,
    state: Mutex<CacheState>,
}

#[derive(Default)]
struct CacheState {
    entries: HashMap<String, Arc<Vec<u8>>>,
    /// Keys, least recently used first.
    order: VecDeque<String>,
    bytes: usize,
}

impl PreviewCache {
    pub(super) fn new(capacity: usize) -> PreviewCache {
        PreviewCache { capacity, state: Mutex::new(CacheState::default()) }
    }

    fn get(&self, key: &str) -> Option<Arc<Vec<u8>>> {
        let mut st = self.state.lock().unwrap_or_else(lock_poisoned);
        let hit = st.entries.get(key).cloned()?;
        if let Some(i) = st.order.iter().position(|k| k == key) {
            let k = st.order.remove(i).expect("found above");
            st.order.push_back(k);
        }
        Some(hit)
    }

    fn put(&self, key: String, value: Arc<Vec<u8>>) {
        if value.len() > self.capacity {
            return;
        }
        let mut st = self.state.lock().unwrap_or_else(lock_poisoned);
        if st.entries.contains_key(&key) {
            return;
        }
        while st.bytes + value.len() > self.capacity {
            let Some(old) = st.order.pop_front() else { break };
            if let Some(v) = st.entries.remove(&old) {
                st.bytes -= v.len();
            }
        }
        st.bytes += value.len();
        st.order.push_back(key.clone());
        st.entries.insert(key, value);
    }

    /// Entries and bytes held.
    #[cfg(test)]
    fn usage(&self) -> (usize, usize) {
        let st = self.state.lock().unwrap_or_else(lock_poisoned);
        (st.entries.len(), st.bytes)
    }
}

impl JobService {
    /// A PNG preview of one of a job's frames (see the module docs for the sources).
    /// Another client's job answers like a missing one; a frame the job does not have (yet)
    /// answers `Conflict` (no result yet) or `NotFound` (no reference, or not kept).
    pub async fn preview(&self, id: &str, caller: &Caller, image: PreviewImage, spec: Spec) -> Result<Arc<Vec<u8>>> {
        spec.check().map_err(Error::BadRequest)?;
        self.catch_up(id).await?;
        let source = {
            let st = self.lock();
            let entry = entry_for(&st, id, caller)?;
            self.preview_source(&entry.record, image)?
        };
        let name = source.path().file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
        let key = format!("{id}/{name}/{}", spec.key());
        if let Some(png) = self.inner.previews.get(&key) {
            return Ok(png);
        }
        let id = id.to_string();
        let png = self
            .blocking(move |s| {
                s.fetch_shared_file(&id, &name, source.path())?;
                let rgb = source.read(&id, &s.inner.settings.limits)?;
                let (w, h, pixels) = preview::render(&rgb, &spec).map_err(Error::BadRequest)?;
                drop(rgb);
                preview::encode_png(w, h, &pixels).map_err(|e| Error::internal("cannot encode the preview", e))
            })
            .await?;
        let png = Arc::new(png);
        self.inner.previews.put(key, png.clone());
        Ok(png)
    }

    /// The file `image` of job `r` is made from, or why there is none.
    fn preview_source(&self, r: &JobRecord, image: PreviewImage) -> Result<Source> {
        let store = &self.inner.store;
        let id = r.id.as_str();
        let upload = |which: Input| match which {
            Input::Frame => Source::Upload(store.input_path(id), which),
            Input::Reference => Source::Upload(store.reference_path(id), which),
        };
        let kept = |which: &str| Source::Rgb(store.preview_source_path(id, which));
        let not_kept = |what: &str| {
            Error::NotFound(format!(
                "job {id} is {}: its uploaded {what} was removed when it ended and only a succeeded job keeps it for previews",
                r.state.name()
            ))
        };
        if image == PreviewImage::Reference && !r.has_reference {
            return Err(Error::NotFound(format!("job {id} was submitted without a reference")));
        }
        match (image, r.state) {
            (PreviewImage::Result, JobState::Succeeded) => Ok(Source::Rgb(store.result_path(id))),
            (PreviewImage::Result, s) => Err(Error::Conflict(format!(
                "job {id} is {}; a result preview exists only once it has succeeded",
                s.name()
            ))),
            (PreviewImage::Input, JobState::Queued | JobState::Running) => Ok(upload(Input::Frame)),
            (PreviewImage::Reference, JobState::Queued | JobState::Running) => Ok(upload(Input::Reference)),
            (PreviewImage::Input, JobState::Succeeded) => Ok(kept("input")),
            (PreviewImage::Reference, JobState::Succeeded) => Ok(kept("reference")),
            (PreviewImage::Input, JobState::Failed | JobState::Cancelled) => Err(not_kept("frame")),
            (PreviewImage::Reference, JobState::Failed | JobState::Cancelled) => Err(not_kept("reference")),
        }
    }

    /// Keeps the colour of a succeeded job's uploads for its previews, before the uploads
    /// are removed. A failure costs only the previews: it is logged, the job goes on.
    pub(super) fn keep_preview_sources(&self, id: &str, input: Option<&Rgb>, reference: Option<&Rgb>) {
        for (which, rgb) in [("input", input), ("reference", reference)] {
            let Some(rgb) = rgb else { continue };
            let path = self.inner.store.preview_source_path(id, which);
            if let Err(e) = preview::write_rgb_exr(&path, rgb) {
                tracing::warn!(job_id = id, error = %e, "cannot keep the {which} for previews; the dashboard will not show it");
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_cache_keeps_the_most_recently_used_within_its_budget() {
        let cache = PreviewCache::new(100);
        cache.put("a".into(), Arc::new(vec![0; 40]));
        cache.put("b".into(), Arc::new(vec![0; 40]));
        assert!(cache.get("a").is_some(), "a becomes the most recent");
        cache.put("c".into(), Arc::new(vec![0; 40]));
        assert!(cache.get("b").is_none(), "b was the least recently used");
        assert!(cache.get("a").is_some() && cache.get("c").is_some());
        assert_eq!(cache.usage(), (2, 80));
        cache.put("huge".into(), Arc::new(vec![0; 101]));
        assert!(cache.get("huge").is_none(), "larger than the whole budget: not kept");
        assert_eq!(cache.usage(), (2, 80));
    }

    #[test]
    fn image_names_parse_and_unknown_ones_list_the_valid_values() {
        assert_eq!("result".parse::<PreviewImage>().unwrap(), PreviewImage::Result);
        let e = "denoised".parse::<PreviewImage>().unwrap_err();
        assert!(e.contains("expected input, result or reference"), "{e}");
    }
}
