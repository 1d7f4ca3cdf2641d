//! Reads: one job, a filtered page of jobs, a job's events, a job's result.
//!
//! Locking: every read takes the state lock once, briefly, and never waits for the disk
//! (`open_result` opens the file on the blocking pool, after the lock is released).

use std::collections::BTreeMap;

use futures_util::stream::{self, BoxStream, StreamExt};
use serde::Serialize;
use tokio::sync::broadcast;

use super::{entry_for, not_found, Entry, JobService};
use crate::auth::Caller;
use crate::error::{Error, Result};
use crate::jobs::{JobEvent, JobState, JobStatus, Priority};

/// Jobs in a page when the request names no `limit`.
pub const DEFAULT_PAGE: usize = 100;
/// The largest `limit` (`page_size`) accepted, as the OpenAPI document states.
pub const MAX_PAGE: usize = 1000;

/// Filters of [`JobService::list`].
#[derive(Clone, Debug, Default)]
pub struct ListFilter {
    pub state: Option<JobState>,
    pub priority: Option<Priority>,
    pub label: Option<String>,
    pub limit: Option<usize>,
    pub after: Option<String>,
    /// Only jobs submitted by this client (`Caller::owner_filter`).
    pub owner: Option<String>,
    /// Only jobs whose `client` is exactly this (a listing's `client` filter; within what
    /// `owner` allows).
    pub client: Option<String>,
    /// Newest first (and `after` pages towards older jobs) instead of oldest first.
    pub newest_first: bool,
}

/// The window of [`Stats::last_hour`], in milliseconds.
pub const STATS_WINDOW_MS: i64 = 3_600_000;

/// Totals over the jobs a caller may see (`GET /v1/stats`).
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Stats {
    /// Jobs in the store.
    pub jobs: usize,
    /// Every state, with 0 for the empty ones.
    pub by_state: BTreeMap<&'static str, usize>,
    /// Queued jobs by priority class, with 0 for the empty ones.
    pub queued_by_priority: BTreeMap<&'static str, usize>,
    pub last_hour: Throughput,
}

/// What finished in the last [`STATS_WINDOW_MS`].
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Throughput {
    pub window_seconds: u64,
    pub succeeded: usize,
    pub failed: usize,
    pub cancelled: usize,
    /// Frames denoised in the window: as it is an hour, frames per hour.
    pub frames_per_hour: usize,
    /// Megapixels of those frames.
    pub megapixels: f64,
    /// Run time (the `total` timing: decode to result on disk, queue excluded) per megapixel
    /// over those frames; `None` when none finished.
    pub mean_seconds_per_megapixel: Option<f64>,
}

impl JobService {
    /// The job's status as the transports answer a read by id: in shared mode a job this
    /// replica has not seen yet is read from the store first ([`JobService::catch_up`]), so
    /// that a job is found through any replica from the moment it is accepted.
    pub async fn find(&self, id: &str, caller: &Caller) -> Result<JobStatus> {
        self.catch_up(id).await?;
        self.get(id, caller)
    }

    /// The job's events ([`JobService::events`]), looked up as [`JobService::find`] does.
    pub async fn follow(&self, id: &str, caller: &Caller) -> Result<BoxStream<'static, JobEvent>> {
        self.catch_up(id).await?;
        self.events(id, caller)
    }

    /// The job's status from this replica's mirror alone.
    pub fn get(&self, id: &str, caller: &Caller) -> Result<JobStatus> {
        let st = self.lock();
        let entry = entry_for(&st, id, caller)?;
        Ok(self.status_of(&st, entry))
    }

    /// Jobs in submission order (or its reverse: `newest_first`), filtered; `after` is the
    /// `next_page_token` of the previous page.
    pub fn list(&self, filter: &ListFilter) -> Result<(Vec<JobStatus>, Option<String>)> {
        let after = match filter.after.as_deref() {
            None | Some("") => None,
            Some(t) => Some(t.parse::<u64>().map_err(|_| {
                Error::BadRequest(format!(
                    "bad page token `{}`: pass the next_page_token of the previous page",
                    crate::error::truncate(t, crate::error::ECHO_CHARS)
                ))
            })?),
        };
        let limit = match filter.limit {
            None => DEFAULT_PAGE,
            Some(n) if (1..=MAX_PAGE).contains(&n) => n,
            Some(n) => return Err(Error::BadRequest(format!("limit must be 1 to {MAX_PAGE}, not {n}"))),
        };
        let st = self.lock();
        let mut matching: Vec<&Entry> = st
            .jobs
            .values()
            .filter(|e| {
                let r = &e.record;
                after.is_none_or(|a| if filter.newest_first { r.seq < a } else { r.seq > a })
                    && filter.owner.as_deref().is_none_or(|o| crate::auth::owns(o, r.client.as_deref()))
                    && filter.state.is_none_or(|s| r.state == s)
                    && filter.priority.is_none_or(|p| r.options.priority == p)
                    && filter.label.as_deref().is_none_or(|l| r.options.label.as_deref() == Some(l))
                    && filter.client.as_deref().is_none_or(|c| r.client.as_deref() == Some(c))
            })
            .collect();
        matching.sort_unstable_by_key(|e| e.record.seq);
        if filter.newest_first {
            matching.reverse();
        }
        let more = matching.len() > limit;
        matching.truncate(limit);
        let next = if more { matching.last().map(|e| e.record.seq.to_string()) } else { None };
        Ok((matching.into_iter().map(|e| self.status_of(&st, e)).collect(), next))
    }

    /// Totals and the last hour's throughput over the jobs of `owner` (every job: `None`).
    pub fn stats(&self, owner: Option<&str>) -> Stats {
        let since = self.now() - STATS_WINDOW_MS;
        let mut by_state: BTreeMap<&'static str, usize> = JobState::ALL.iter().map(|s| (s.name(), 0)).collect();
        let mut queued_by_priority: BTreeMap<&'static str, usize> =
            Priority::ALL.iter().map(|p| (p.name(), 0)).collect();
        let (mut jobs, mut succeeded, mut failed, mut cancelled) = (0, 0, 0, 0);
        let (mut megapixels, mut seconds) = (0.0f64, 0.0f64);
        let st = self.lock();
        for entry in st.jobs.values() {
            let r = &entry.record;
            if !owner.is_none_or(|o| crate::auth::owns(o, r.client.as_deref())) {
                continue;
            }
            jobs += 1;
            *by_state.entry(r.state.name()).or_default() += 1;
            if r.state == JobState::Queued {
                *queued_by_priority.entry(r.options.priority.name()).or_default() += 1;
            }
            if r.finished_at_ms.is_none_or(|t| t <= since) {
                continue;
            }
            match r.state {
                JobState::Succeeded => {
                    succeeded += 1;
                    megapixels += f64::from(r.width) * f64::from(r.height) / 1e6;
                    seconds += r.timings.map_or(0.0, |t| t.total) / 1e3;
                }
                JobState::Failed => failed += 1,
                JobState::Cancelled => cancelled += 1,
                JobState::Queued | JobState::Running => {}
            }
        }
        drop(st);
        Stats {
            jobs,
            by_state,
            queued_by_priority,
            last_hour: Throughput {
                window_seconds: (STATS_WINDOW_MS / 1000) as u64,
                succeeded,
                failed,
                cancelled,
                frames_per_hour: succeeded,
                megapixels,
                mean_seconds_per_megapixel: (megapixels > 0.0).then(|| seconds / megapixels),
            },
        }
    }

    /// The current status and a receiver of every later event, taken atomically.
    pub fn watch(&self, id: &str, caller: &Caller) -> Result<(JobStatus, broadcast::Receiver<JobEvent>)> {
        let st = self.lock();
        let entry = entry_for(&st, id, caller)?;
        Ok((self.status_of(&st, entry), entry.events.subscribe()))
    }

    /// The job's events: its current state first (`queued`; or `started` and `progress`;
    /// or the terminal event), then every change, ending after the terminal event (or
    /// when the job is deleted).
    pub fn events(&self, id: &str, caller: &Caller) -> Result<BoxStream<'static, JobEvent>> {
        let (status, rx) = self.watch(id, caller)?;
        let r = &status.record;
        let initial = match r.state {
            JobState::Queued => vec![JobEvent::Queued { status: Box::new(status.clone()) }],
            JobState::Running => vec![JobEvent::Started { attempt: r.attempts }, JobEvent::Progress(r.progress)],
            JobState::Succeeded | JobState::Failed | JobState::Cancelled => {
                let terminal = JobEvent::terminal(status).expect("terminal state");
                return Ok(stream::iter([terminal]).boxed());
            }
        };
        let live = stream::unfold(Some(rx), |rx| async move {
            let mut rx = rx?;
            loop {
                match rx.recv().await {
                    Ok(ev) => {
                        let next = if ev.is_terminal() { None } else { Some(rx) };
                        return Some((ev, next));
                    }
                    Err(broadcast::error::RecvError::Lagged(_)) => continue,
                    Err(broadcast::error::RecvError::Closed) => return None,
                }
            }
        });
        Ok(stream::iter(initial).chain(live).boxed())
    }

    /// Opens the result of a succeeded job: the file and its size.
    pub async fn open_result(&self, id: &str, caller: &Caller) -> Result<(tokio::fs::File, u64)> {
        self.catch_up(id).await?;
        let behind = self.shared().is_some() && {
            let st = self.lock();
            entry_for(&st, id, caller)?.record.state != JobState::Succeeded
        };
        if behind {
            // Shared mode: another replica may have finished it a moment ago.
            let id = id.to_string();
            self.blocking(move |s| s.refresh(&id).map(|_| ())).await?;
        }
        {
            let st = self.lock();
            let entry = entry_for(&st, id, caller)?;
            match entry.record.state {
                JobState::Succeeded => {}
                s => {
                    return Err(Error::Conflict(format!(
                        "job {id} is {}; a result exists only once it has succeeded",
                        s.name()
                    )))
                }
            }
        }
        let path = self.inner.store.result_path(id);
        let id = id.to_string();
        let (file, len) = self
            .blocking(move |s| {
                s.fetch_shared_file(&id, "result.exr", &path)?;
                let file = std::fs::File::open(&path).map_err(|e| match e.kind() {
                    // Deleted or expired since the check above.
                    std::io::ErrorKind::NotFound => not_found(&id),
                    _ => Error::internal(&format!("cannot open {}", path.display()), e),
                })?;
                let len = file.metadata().map_err(|e| Error::internal("cannot stat the result", e))?.len();
                Ok((file, len))
            })
            .await?;
        Ok((tokio::fs::File::from_std(file), len))
    }
}
