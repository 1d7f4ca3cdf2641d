//! A job's life after admission: the final states, cancel, delete, the retention sweep
//! and the shutdown steps. Every final state (succeeded, failed, cancelled) is reached
//! through one path: `prepare` then `commit` (together: `settle`).
//!
//! Locking (see the module docs of [`crate::jobs`]): `prepare` runs under the state lock
//! and only computes the final record (taking a queued job off the queue, so no worker
//! claims it). `commit` holds the journal: it checks that the job is still in the state
//! `prepare` saw, writes the record with no state lock held, then applies it in memory and
//! sends the terminal event under the state lock. Whatever came in between (a delete, a
//! concurrent cancel) makes the commit a no-op instead of writing a stale record.

use std::sync::atomic::Ordering;
use std::time::Duration;

use super::{entry_for, not_found, scoped_key, JobService, Journal, State};
use crate::auth::Caller;
use crate::error::{Error, Result};
use crate::jobs::{
    FireflyCounts, JobError, JobErrorCode, JobEvent, JobMetrics, JobRecord, JobState, JobStatus, Phase, Progress,
    SanitizedCounts, Timings, MAX_STORAGE_FAILURES,
};

/// The fields a successful run fills in.
#[derive(Clone)]
pub(super) struct Finished {
    pub variant: crate::engine::Variant,
    pub progress: Progress,
    pub timings: Timings,
    pub metrics: Option<JobMetrics>,
    pub sanitized: SanitizedCounts,
    pub fireflies: FireflyCounts,
    pub missing_variances: Vec<String>,
    pub warnings: Vec<String>,
    pub result_bytes: u64,
}

impl Finished {
    pub(super) fn apply(self, r: &mut JobRecord) {
        r.state = JobState::Succeeded;
        r.variant = Some(self.variant);
        r.progress = self.progress;
        r.timings = Some(self.timings);
        r.metrics = self.metrics;
        r.sanitized = Some(self.sanitized);
        r.fireflies = Some(self.fireflies);
        r.missing_variances = self.missing_variances;
        r.warnings = self.warnings;
        r.error = None;
        r.result_bytes = Some(self.result_bytes);
    }
}

/// How a job ends.
pub(super) enum Ending {
    Succeeded(Box<Finished>),
    Failed(JobError, Option<Timings>),
    Cancelled,
}

/// A final record computed under the state lock, waiting for its commit.
pub(super) struct Prepared {
    id: String,
    /// The state `prepare` saw; the commit happens only if the job is still in it.
    from: JobState,
    next: JobRecord,
    /// The terminal event that announces it.
    event: fn(Box<JobStatus>) -> JobEvent,
}

impl JobService {
    /// Computes the final record of `id` (under the caller's state lock). `None` if the job
    /// is gone or already final.
    pub(super) fn prepare(&self, st: &mut State, id: &str, ending: Ending) -> Option<Prepared> {
        let entry = st.jobs.get(id)?;
        let from = entry.record.state;
        if from.is_terminal() {
            return None;
        }
        let mut next = entry.record.clone();
        if from == JobState::Queued && st.queue.remove(next.options.priority, next.seq) {
            self.update_depth(st);
        }
        let event: fn(Box<JobStatus>) -> JobEvent = match ending {
            Ending::Succeeded(finished) => {
                finished.apply(&mut next);
                JobEvent::Succeeded
            }
            Ending::Failed(error, timings) => {
                next.state = JobState::Failed;
                next.error = Some(error);
                if timings.is_some() {
                    next.timings = timings;
                }
                JobEvent::Failed
            }
            Ending::Cancelled => {
                next.state = JobState::Cancelled;
                next.cancel_requested = true;
                JobEvent::Cancelled
            }
        };
        let now = self.now();
        next.finished_at_ms = Some(now);
        next.expires_at_ms = Some(now + self.inner.settings.ttl_ms());
        Some(Prepared { id: id.to_string(), from, next, event })
    }

    /// Makes a prepared final state durable, then visible: the record is written, the
    /// memory updated, the terminal event sent, the uploaded frames removed. A state that
    /// cannot be written is never shown: the job stays as it was in memory (a queued job
    /// goes back into the queue) and the error is returned, so no client sees a final state
    /// that a restart could take back.
    pub(super) fn commit(&self, _journal: &Journal<'_>, prepared: Prepared) -> Result<Option<JobStatus>> {
        let Prepared { id, from, mut next, event } = prepared;
        let current = self.lock().jobs.get(&id).map(|e| e.record.state);
        if current != Some(from) {
            // Deleted or ended by someone else since `prepare`.
            return Ok(None);
        }
        if let Err(e) = self.write_record(&mut next) {
            if matches!(e, Error::Conflict(_)) {
                tracing::info!(
                    job_id = id.as_str(),
                    state = next.state.name(),
                    "changed by another replica meanwhile; not ended here"
                );
            } else {
                tracing::error!(job_id = id.as_str(), error = %e, state = next.state.name(), "cannot persist the job's end; it stays {}", from.name());
                self.storage_failed(&e);
            }
            if from == JobState::Queued {
                let mut st = self.lock();
                st.queue.push(next.options.priority, next.seq, id.clone());
                self.update_depth(&st);
            }
            return Err(e);
        }
        let state = next.state;
        let run_ms = next.timings.map(|t| t.total).unwrap_or(0.0);
        let mut guard = self.lock();
        let st = &mut *guard;
        // Deletes here hold the journal; only another replica's (shared mode) comes between.
        let Some(entry) = st.jobs.get_mut(&id) else { return Ok(None) };
        entry.record = next;
        let status = JobStatus { record: entry.record.clone(), queue_position: 0 };
        if state == JobState::Cancelled {
            entry.cancel.store(true, Ordering::SeqCst);
        }
        let _ = entry.events.send(event(Box::new(status.clone())));
        if state == JobState::Succeeded {
            st.avg_run_ms = if st.avg_run_ms == 0.0 { run_ms } else { 0.8 * st.avg_run_ms + 0.2 * run_ms };
        }
        drop(guard);
        self.inner.telemetry.job_finished(state.name());
        self.inner.store.remove_inputs(&id);
        if let Some(shared) = self.shared() {
            shared.remove_inputs(&id);
        }
        match (&status.record.error, from) {
            (Some(error), JobState::Queued) => {
                tracing::warn!(job_id = id.as_str(), code = error.code.name(), error = %error.message, "failed while queued")
            }
            (Some(error), _) => {
                tracing::warn!(job_id = id.as_str(), code = error.code.name(), error = %error.message, "failed")
            }
            (None, _) => tracing::info!(job_id = id.as_str(), state = state.name(), from = from.name(), "finished"),
        }
        Ok(Some(status))
    }

    /// `prepare` and `commit` in one.
    pub(super) fn settle(&self, journal: &Journal<'_>, id: &str, ending: Ending) -> Result<Option<JobStatus>> {
        let prepared = self.prepare(&mut self.lock(), id, ending);
        match prepared {
            Some(p) => self.commit(journal, p),
            None => Ok(None),
        }
    }

    /// Writes the job's current in-memory record (for changes that need not be durable
    /// before they are visible). Nothing if the job was deleted meanwhile.
    pub(super) fn persist(&self, id: &str) {
        let _journal = self.journal();
        let Some(mut record) = self.lock().jobs.get(id).map(|e| e.record.clone()) else { return };
        match self.write_record(&mut record) {
            Ok(()) => {
                if let Some(entry) = self.lock().jobs.get_mut(id) {
                    entry.record.rev = record.rev;
                }
            }
            Err(e) => {
                // The job still runs; after a crash it would run again, which is safe.
                tracing::error!(job_id = id, error = %e, "cannot persist the job's state");
                self.storage_failed(&e);
            }
        }
    }

    /// Puts a running job back in the queue (stopped by the shutdown deadline) for the next
    /// start.
    pub(super) fn requeue(&self, id: &str) {
        let journal = self.journal();
        if self.back_to_queue(&journal, id, None) {
            drop(journal);
            self.inner.telemetry.job_interrupted();
            tracing::info!(job_id = id, "interrupted by shutdown; queued for the next start");
        }
    }

    /// A running job queued again, written (a failed write is only logged: queued and
    /// running are both run again after a restart) and applied in memory: into the queue
    /// at once, or at `due` (Unix ms). False if the job is gone or not running.
    fn back_to_queue(&self, _journal: &Journal<'_>, id: &str, due: Option<i64>) -> bool {
        let next = {
            let st = self.lock();
            let Some(entry) = st.jobs.get(id).filter(|e| e.record.state == JobState::Running) else { return false };
            let mut next = entry.record.clone();
            next.state = JobState::Queued;
            next.progress = Progress::default();
            next
        };
        let mut next = next;
        if let Err(e) = self.write_record(&mut next) {
            tracing::error!(job_id = id, error = %e, "cannot persist the re-queued job");
            self.storage_failed(&e);
            if self.shared().is_some() {
                // The stored record still says running; its message, delivered again, runs it.
                return false;
            }
        }
        let mut st = self.lock();
        match due {
            // Shared mode: the queue in memory only mirrors the shared one, whose message
            // comes back after the pause by itself.
            Some(t) if self.shared().is_none() => st.delayed.push((t, id.to_string())),
            _ => st.queue.push(next.options.priority, next.seq, next.id.clone()),
        }
        if let Some(entry) = st.jobs.get_mut(id) {
            entry.record = next;
            let _ = entry.events.send(JobEvent::Progress(Progress::default()));
        }
        self.update_depth(&st);
        true
    }

    /// Puts a running job whose input could not be read or whose result could not be
    /// written for a storage reason back in the queue after a pause (1 s, doubling, at
    /// most 30 s); after [`MAX_STORAGE_FAILURES`] such runs it fails with code `storage`.
    /// Returns the pause when the job was queued again.
    pub(super) fn retry_later(&self, id: &str, message: String) -> Option<Duration> {
        let journal = self.journal();
        let failures = {
            let mut st = self.lock();
            let entry = st.jobs.get_mut(id).filter(|e| e.record.state == JobState::Running)?;
            entry.record.storage_failures += 1;
            entry.record.storage_failures
        };
        self.inner.telemetry.storage_retry();
        if failures >= MAX_STORAGE_FAILURES {
            let error = JobError {
                code: JobErrorCode::Storage,
                message: format!("gave up after {failures} runs that hit a storage fault; the last: {message}"),
            };
            if self.settle(&journal, id, Ending::Failed(error, None)).is_ok() {
                return None;
            }
            // Not even the failure can be written: keep it queued until storage heals.
        }
        let delay_ms = (1000i64 << (failures.saturating_sub(1)).min(5)).min(30_000);
        if self.back_to_queue(&journal, id, Some(self.now() + delay_ms)) {
            drop(journal);
            tracing::warn!(job_id = id, failures, retry_in_ms = delay_ms, error = %message, "storage fault: queued again after a pause");
            self.inner.work.notify_all();
        }
        Some(Duration::from_millis(delay_ms as u64))
    }

    /// Moves the delayed jobs that are due into the queue (under the caller's state lock).
    pub(super) fn promote_due(&self, st: &mut State) {
        if st.delayed.is_empty() {
            return;
        }
        let now = self.now();
        let (due, waiting): (Vec<_>, Vec<_>) =
            std::mem::take(&mut st.delayed).into_iter().partition(|(t, _)| *t <= now);
        st.delayed = waiting;
        for (_, id) in due {
            if let Some(entry) = st.jobs.get(&id).filter(|e| e.record.state == JobState::Queued) {
                let r = &entry.record;
                st.queue.push(r.options.priority, r.seq, id.clone());
            }
        }
        self.update_depth(st);
    }

    // --- Changes asked for by clients ------------------------------------------------------

    /// Cancels a queued job at once, or asks a running one to stop at its next tile.
    pub async fn cancel(&self, id: &str, caller: &Caller) -> Result<JobStatus> {
        let (id, caller) = (id.to_string(), caller.clone());
        self.blocking(move |s| {
            s.catch_up_blocking(&id)?;
            let mut tries = 0;
            loop {
                match s.cancel_now(&id, &caller) {
                    // Shared mode: changed by another replica since this one last heard
                    // (claimed, say): read it again and decide again.
                    Err(Error::Conflict(_)) if s.shared().is_some() && tries < 5 => {
                        tries += 1;
                        if s.refresh(&id)?.is_none_or(|r| r.state.is_terminal()) {
                            // Gone or ended: its answer says so.
                            return s.cancel_now(&id, &caller);
                        }
                    }
                    other => return other,
                }
            }
        })
        .await
    }

    fn cancel_now(&self, id: &str, caller: &Caller) -> Result<JobStatus> {
        let journal = self.journal();
        let prepared = {
            let mut st = self.lock();
            entry_for(&st, id, caller)?;
            let entry = st.jobs.get_mut(id).expect("found above, under the same lock");
            match entry.record.state {
                JobState::Queued => self.prepare(&mut st, id, Ending::Cancelled),
                JobState::Running if self.shared().is_some_and(|s| !s.holds(id)) => {
                    drop(st);
                    drop(journal);
                    return self.request_cancel_elsewhere(id);
                }
                JobState::Running => {
                    entry.cancel.store(true, Ordering::SeqCst);
                    entry.record.cancel_requested = true;
                    tracing::info!(job_id = id, "cancellation requested");
                    let entry = &st.jobs[id];
                    return Ok(self.status_of(&st, entry));
                }
                s @ (JobState::Succeeded | JobState::Failed | JobState::Cancelled) => {
                    return Err(Error::Conflict(format!("job {id} has already {}", s.name())))
                }
            }
        };
        let status = prepared.map(|p| self.commit(&journal, p)).transpose()?.flatten();
        status.ok_or_else(|| not_found(id))
    }

    /// Removes a job with its files (a running job is cancelled first).
    pub async fn delete(&self, id: &str, caller: &Caller) -> Result<()> {
        let (id, caller) = (id.to_string(), caller.clone());
        self.blocking(move |s| {
            s.catch_up_blocking(&id)?;
            s.delete_now(&id, &caller)
        })
        .await
    }

    fn delete_now(&self, id: &str, caller: &Caller) -> Result<()> {
        let journal = self.journal();
        entry_for(&self.lock(), id, caller)?;
        self.remove_records(&[id])?;
        let mut st = self.lock();
        // Deletes here hold the journal; in shared mode the watch may have applied this
        // very delete already (and told the watchers).
        let Some(entry) = st.jobs.remove(id) else { return Ok(()) };
        entry.cancel.store(true, Ordering::SeqCst);
        let r = &entry.record;
        if r.state == JobState::Queued && st.queue.remove(r.options.priority, r.seq) {
            self.update_depth(&st);
        }
        if let Some(key) = &r.options.idempotency_key {
            st.keys.remove(&scoped_key(r.client.as_deref(), key));
        }
        drop(st);
        drop(journal);
        // Watchers of an unfinished job learn why their stream ends; dropping `entry`
        // closes its event channel.
        if !entry.record.state.is_terminal() {
            let _ = entry.events.send(JobEvent::Deleted);
        }
        drop(entry);
        self.inner.store.remove_files(id);
        tracing::info!(job_id = id, "deleted");
        Ok(())
    }

    /// Removes finished jobs past their retention time and fails queued jobs past their
    /// deadline. Returns how many jobs were removed.
    pub async fn sweep(&self) -> Result<usize> {
        self.blocking(JobService::sweep_now).await
    }

    fn sweep_now(&self) -> Result<usize> {
        if self.shared().is_some_and(|s| !s.take_lease("sweep")) {
            // Another replica sweeps this round.
            return Ok(0);
        }
        let journal = self.journal();
        let now = self.now();
        let (expired, overdue) = {
            let mut st = self.lock();
            let expired: Vec<String> = st
                .jobs
                .values()
                .filter(|e| e.record.state.is_terminal() && e.record.expires_at_ms.is_some_and(|t| t <= now))
                .map(|e| e.record.id.clone())
                .collect();
            let overdue: Vec<String> = st
                .jobs
                .values()
                .filter(|e| e.record.state == JobState::Queued && e.record.deadline_at_ms.is_some_and(|t| t <= now))
                .map(|e| e.record.id.clone())
                .collect();
            let overdue: Vec<_> =
                overdue.iter().filter_map(|id| self.prepare(&mut st, id, deadline_passed())).collect();
            (expired, overdue)
        };
        if !expired.is_empty() {
            let ids: Vec<&str> = expired.iter().map(String::as_str).collect();
            self.remove_records(&ids)?;
            let mut st = self.lock();
            for id in &expired {
                if let Some(entry) = st.jobs.remove(id) {
                    if let Some(key) = &entry.record.options.idempotency_key {
                        st.keys.remove(&scoped_key(entry.record.client.as_deref(), key));
                    }
                }
            }
        }
        let mut failure = None;
        for prepared in overdue {
            match self.commit(&journal, prepared) {
                // Claimed or ended by another replica meanwhile.
                Ok(_) | Err(Error::Conflict(_)) => {}
                Err(e) => failure = Some(e),
            }
        }
        drop(journal);
        for id in &expired {
            self.inner.store.remove_files(id);
            tracing::info!(job_id = id.as_str(), "expired and removed");
        }
        match failure {
            Some(e) => Err(e),
            None => Ok(expired.len()),
        }
    }

    // --- Shutdown --------------------------------------------------------------------------

    /// Stops admitting jobs and starting queued ones; readiness turns false.
    pub fn begin_drain(&self) {
        let _st = self.lock();
        if matches!(self.phase(), Phase::Loading | Phase::Ready) {
            self.set_phase(Phase::Draining);
        }
        self.inner.work.notify_all();
    }

    /// Waits until no job is running, at most `timeout`. True if idle.
    pub async fn wait_idle(&self, timeout: Duration) -> bool {
        let mut rx = self.inner.running.subscribe();
        let idle = tokio::time::timeout(timeout, rx.wait_for(|n| *n == 0)).await.is_ok();
        idle
    }

    /// Makes running jobs stop at their next tile; they go back to the queue (persisted)
    /// and run again at the next start.
    pub fn abort_running(&self) {
        self.inner.abort.store(true, Ordering::SeqCst);
    }

    /// Tells the workers to exit once their current job is over.
    pub fn stop_workers(&self) {
        let _st = self.lock();
        self.set_phase(Phase::Stopped);
        self.inner.work.notify_all();
    }
}

/// The failure of a job whose deadline passed before it started.
pub(super) fn deadline_passed() -> Ending {
    Ending::Failed(
        JobError {
            code: JobErrorCode::DeadlineExceeded,
            message: "the job's deadline passed while it was queued".into(),
        },
        None,
    )
}
