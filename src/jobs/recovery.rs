//! Recovery: the in-memory state rebuilt from the store at startup, whether the last run
//! ended cleanly or not.
//!
//! - Each job's record is the newer (by revision) of the database's and the job
//!   directory's copy, so a database that was lost, emptied, replaced after damage or
//!   rolled back is rebuilt from the directories (and written back).
//! - Finished jobs are kept until they expire; a success whose result file is missing
//!   becomes a failure.
//! - Queued and running jobs go back to the queue in their admission order; a running job
//!   counts as interrupted. One whose result was written just before the process stopped
//!   (`result.json` and `result.exr` present) is completed from that summary instead of
//!   running again; one whose upload is missing fails.
//! - `.part` leftovers go, and so do job directories left empty by an upload cut short.
//!   Anything else that no record accounts for (a directory with files but no readable
//!   record, a database entry that is not a record) is moved to `DATA_DIR/quarantine/`
//!   with a log line and `mcdenoise_storage_quarantined_total`: recovery deletes nothing
//!   it cannot account for.
//!
//! Locking: runs before the service exists; nothing else can see the state yet.

use std::collections::{HashMap, HashSet};
use std::path::Path;

use super::store::{Store, RECORD_FILE};
use super::{Entry, Settings, State};
use crate::error::{Error, Result};
use crate::jobs::{JobError, JobErrorCode, JobRecord, JobState, Progress};
use crate::telemetry::Telemetry;

/// A job directory's own copy of its record.
enum DirCopy {
    Missing,
    Readable(JobRecord),
    Unreadable(String),
}

fn read_dir_copy(dir: &Path) -> DirCopy {
    match std::fs::read(dir.join(RECORD_FILE)) {
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => DirCopy::Missing,
        Err(e) => DirCopy::Unreadable(e.to_string()),
        Ok(bytes) => match serde_json::from_slice::<JobRecord>(&bytes) {
            Ok(r) => DirCopy::Readable(r),
            Err(e) => DirCopy::Unreadable(e.to_string()),
        },
    }
}

/// Removes the `.part` files a crash left in `dir`; true if `dir` is empty afterwards.
fn clean_parts(dir: &Path) -> bool {
    let mut empty = true;
    for entry in std::fs::read_dir(dir).into_iter().flatten().flatten() {
        if crate::atomic::is_part(&entry.path()) {
            let _ = std::fs::remove_file(entry.path());
        } else {
            empty = false;
        }
    }
    empty
}

fn quarantine(store: &Store, telemetry: &Telemetry, dir: &Path, why: &str) -> Result<()> {
    let kept = store
        .quarantine(dir)
        .map_err(|e| Error::storage(&format!("cannot move {} to the quarantine folder", dir.display()), &e))?;
    telemetry.storage_quarantined();
    tracing::error!(from = %dir.display(), kept = %kept.display(), reason = why, "quarantined what no record accounts for");
    Ok(())
}

/// What [`gather`] found.
struct Gathered {
    records: Vec<JobRecord>,
    /// Jobs whose two copies agree (nothing to write back unless recovery changes them).
    in_step: HashSet<String>,
    rebuilt: usize,
}

/// The records of the store: per job, the newer of the database's and the directory's
/// copy. What cannot be accounted for is quarantined on the way.
fn gather(store: &Store, telemetry: &Telemetry) -> Result<Gathered> {
    let (from_db, unreadable) = store.load_all()?;
    let mut records: HashMap<String, JobRecord> = from_db.into_iter().map(|r| (r.id.clone(), r)).collect();
    let unreadable: HashMap<String, Vec<u8>> = unreadable.into_iter().collect();
    let mut rebuilt = 0;
    let mut in_step = HashSet::new();
    let jobs = store.jobs_dir();
    let dirs = std::fs::read_dir(&jobs).map_err(|e| Error::storage(&format!("cannot read {}", jobs.display()), &e))?;
    for entry in dirs.flatten() {
        let dir = entry.path();
        if !dir.is_dir() {
            continue;
        }
        let id = entry.file_name().to_string_lossy().to_string();
        let empty = clean_parts(&dir);
        match (read_dir_copy(&dir), records.get(&id)) {
            (DirCopy::Readable(copy), db) => {
                if copy.id != id {
                    quarantine(store, telemetry, &dir, "its record names another job")?;
                    continue;
                }
                if db.is_some_and(|db| db.rev == copy.rev) {
                    in_step.insert(id);
                } else if db.is_none_or(|db| copy.rev > db.rev) {
                    if db.is_none() {
                        tracing::warn!(
                            job_id = id.as_str(),
                            "the database has no record of this job: rebuilt from its directory"
                        );
                    } else {
                        tracing::warn!(
                            job_id = id.as_str(),
                            "the database's record is older than the directory's: rebuilt"
                        );
                    }
                    rebuilt += 1;
                    records.insert(id, copy);
                }
            }
            (DirCopy::Missing, Some(_)) => {}
            (DirCopy::Unreadable(e), Some(_)) => {
                tracing::warn!(job_id = id.as_str(), error = %e, "the directory's copy of the record is unreadable; the database's is used");
            }
            (DirCopy::Missing, None) if empty => {
                // An upload cut short before its job existed.
                let _ = std::fs::remove_dir(&dir);
            }
            (DirCopy::Missing, None) => {
                if let Some(raw) = unreadable.get(&id) {
                    let _ = std::fs::write(dir.join("record.database.json"), raw);
                }
                quarantine(store, telemetry, &dir, "files without any record of their job")?;
            }
            (DirCopy::Unreadable(e), None) => {
                if let Some(raw) = unreadable.get(&id) {
                    let _ = std::fs::write(dir.join("record.database.json"), raw);
                }
                quarantine(store, telemetry, &dir, &format!("its record cannot be read: {e}"))?;
            }
        }
    }
    // Database entries that are not records and have no directory: kept as files too.
    let mut dropped = Vec::new();
    for (key, raw) in unreadable {
        if !records.contains_key(&key) && store.job_dir(&key).exists() {
            // Its directory was quarantined above with the raw entry.
        } else if !records.contains_key(&key) {
            let dir = store.quarantine_dir().join(format!("{key}.database-entry"));
            std::fs::create_dir_all(&dir)
                .and_then(|()| std::fs::write(dir.join("record.database.json"), &raw))
                .map_err(|e| Error::storage("cannot keep an unreadable database entry", &e))?;
            telemetry.storage_quarantined();
            tracing::error!(key = key.as_str(), kept = %dir.display(), "quarantined a database entry that is not a record");
        }
        dropped.push(key);
    }
    if !dropped.is_empty() {
        store.drop_entries(&dropped)?;
    }
    Ok(Gathered { records: records.into_values().collect(), in_step, rebuilt })
}

/// Rebuilds the in-memory state from the store at `now` (see [`super::JobService::start`]).
pub(super) fn recover(store: &Store, settings: &Settings, telemetry: &Telemetry, now: i64) -> Result<State> {
    let mut st = State::default();
    let mut expired = Vec::new();
    let Gathered { mut records, in_step, rebuilt } = gather(store, telemetry)?;
    store.note_revision(records.iter().map(|r| r.rev).max().unwrap_or(0));
    records.sort_by_key(|r| r.seq);
    let (mut requeued, mut kept, mut completed) = (0, 0, 0);
    for mut r in records {
        st.next_seq = st.next_seq.max(r.seq + 1);
        let before = r.clone();
        let dir = store.job_dir(&r.id);
        if !dir.is_dir() {
            // The record outlived its files; it is written back below with what is known.
            std::fs::create_dir_all(&dir)
                .map_err(|e| Error::storage(&format!("cannot create {}", dir.display()), &e))?;
        }
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
                } else {
                    if r.state == JobState::Running {
                        telemetry.job_interrupted();
                        tracing::info!(job_id = r.id.as_str(), attempts = r.attempts, "interrupted run: queued again");
                    }
                    r.state = JobState::Queued;
                    r.progress = Progress::default();
                    r.cancel_requested = false;
                    st.queue.push(r.options.priority, r.seq, r.id.clone());
                    requeued += 1;
                }
            }
        }
        // Both copies in step again (also migrates stores written before directory copies).
        if r != before || !in_step.contains(&r.id) {
            store.put(&r)?;
        }
        if let Some(key) = &r.options.idempotency_key {
            st.keys.insert(super::scoped_key(r.client.as_deref(), key), r.id.clone());
        }
        st.jobs.insert(r.id.clone(), Entry::new(r));
    }
    if !expired.is_empty() {
        let ids: Vec<&str> = expired.iter().map(String::as_str).collect();
        store.remove(&ids)?;
        for id in &expired {
            store.remove_files(id);
        }
    }
    if requeued + kept + completed + expired.len() + rebuilt > 0 {
        tracing::info!(requeued, kept, completed, expired = expired.len(), rebuilt, "recovered the job store");
    }
    Ok(st)
}
