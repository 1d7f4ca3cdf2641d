//! Recovery: the in-memory state rebuilt from the store at startup, whether the last run
//! ended cleanly or not.
//!
//! - Finished jobs are kept until they expire; a success whose result file is missing
//!   becomes a failure.
//! - Queued and running jobs go back to the queue in their admission order; a running job
//!   counts as interrupted. One whose result was written just before the process stopped
//!   (`result.json` and `result.exr` present) is completed from that summary instead of
//!   running again; one whose upload is missing fails.
//! - Files without a record (uploads cut short, deleted jobs) and `.part` leftovers go.
//!
//! Locking: runs before the service exists; nothing else can see the state yet.

use super::store::Store;
use super::{Entry, Settings, State};
use crate::error::Result;
use crate::jobs::{JobError, JobErrorCode, JobRecord, JobState, Progress};
use crate::telemetry::Telemetry;

/// Rebuilds the in-memory state from the store at `now` (see [`super::JobService::start`]).
pub(super) fn recover(store: &Store, settings: &Settings, telemetry: &Telemetry, now: i64) -> Result<State> {
    let mut st = State::default();
    let mut expired = Vec::new();
    let mut records = store.load_all()?;
    records.sort_by_key(|r| r.seq);
    let (mut requeued, mut kept, mut completed) = (0, 0, 0);
    for mut r in records {
        st.next_seq = st.next_seq.max(r.seq + 1);
        match r.state {
            JobState::Succeeded | JobState::Failed | JobState::Cancelled => {
                if r.expires_at_ms.is_some_and(|t| t <= now) {
                    expired.push(r.id.clone());
                    continue;
                }
                if r.state == JobState::Succeeded && !store.result_path(&r.id).is_file() {
                    r.state = JobState::Failed;
                    r.error =
                        Some(JobError { code: JobErrorCode::Internal, message: "the result file is missing".into() });
                    store.put(&r)?;
                }
                kept += 1;
            }
            JobState::Queued | JobState::Running => {
                let summary = store.summary_path(&r.id);
                let adopted = if store.result_path(&r.id).is_file() && summary.is_file() {
                    std::fs::read(&summary).ok().and_then(|b| serde_json::from_slice::<JobRecord>(&b).ok())
                } else {
                    None
                };
                if let Some(done) = adopted {
                    // Finished just before the process stopped: keep that result.
                    r = done;
                    store.put(&r)?;
                    store.remove_inputs(&r.id);
                    completed += 1;
                } else if !store.input_path(&r.id).is_file() {
                    r.state = JobState::Failed;
                    r.error = Some(JobError {
                        code: JobErrorCode::Internal,
                        message: "the uploaded frame is missing".into(),
                    });
                    r.finished_at_ms = Some(now);
                    r.expires_at_ms = Some(now + settings.result_ttl.as_millis() as i64);
                    store.put(&r)?;
                } else {
                    if r.state == JobState::Running {
                        telemetry.job_interrupted();
                        tracing::info!(job_id = r.id.as_str(), attempts = r.attempts, "interrupted run: queued again");
                    }
                    r.state = JobState::Queued;
                    r.progress = Progress::default();
                    r.cancel_requested = false;
                    store.put(&r)?;
                    st.queue.push(r.options.priority, r.seq, r.id.clone());
                    requeued += 1;
                }
            }
        }
        if let Some(key) = &r.options.idempotency_key {
            st.keys.insert(key.clone(), r.id.clone());
        }
        st.jobs.insert(r.id.clone(), Entry::new(r));
    }
    if !expired.is_empty() {
        let ids: Vec<&str> = expired.iter().map(String::as_str).collect();
        store.remove(&ids)?;
    }
    // Files of jobs without a record: uploads cut short, expired or deleted jobs.
    if let Ok(dir) = std::fs::read_dir(store.jobs_dir()) {
        for entry in dir.flatten() {
            let name = entry.file_name().to_string_lossy().to_string();
            if !st.jobs.contains_key(&name) {
                store.remove_files(&name);
            } else {
                for leftover in std::fs::read_dir(entry.path()).into_iter().flatten().flatten() {
                    if crate::atomic::is_part(&leftover.path()) {
                        let _ = std::fs::remove_file(leftover.path());
                    }
                }
            }
        }
    }
    if requeued + kept + completed + expired.len() > 0 {
        tracing::info!(requeued, kept, completed, expired = expired.len(), "recovered the job store");
    }
    Ok(st)
}
