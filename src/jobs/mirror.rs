//! The core's side of shared mode ([`super::shared`]): the in-memory state as a mirror of
//! the shared records, and the workers' claims through the JetStream queue.
//!
//! - At startup the state is built from every stored record; afterwards each change another
//!   replica makes arrives through the watch ([`JobService::apply_change`]) and is applied
//!   in memory with the same events the embedded mode sends, so a watcher on any replica
//!   sees the whole life of a job. Progress of jobs running elsewhere comes over plain NATS.
//! - A worker takes a job message from the queue and moves the record from queued (or
//!   running, when the message was delivered again because its replica died) to running
//!   with a compare-and-set; losing that race means someone else changed the job, and the
//!   worker reads it again. The message is acknowledged when the job's end is written, put
//!   back (nak) when the run is interrupted or hits a storage fault, and left alone by a run
//!   that lost its job to another replica.
//!
//! Locking: as in the rest of the core; the NATS calls are made with no state lock held.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

use super::claims::Claim;
use super::lifecycle::{deadline_passed, Ending};
use super::shared::{Change, SharedRef};
use super::{lock_poisoned, scoped_key, Entry, JobService, State};
use crate::error::{Error, Result};
use crate::jobs::{JobError, JobErrorCode, JobEvent, JobRecord, JobState, JobStatus, Phase, Progress};

/// Runs of one job after which it fails instead of being delivered again (each run was
/// cut short by its replica stopping).
pub(crate) const MAX_SHARED_RUNS: u32 = 8;

/// The state at startup: every stored record (finished ones until they expire).
pub(super) fn initial_state(records: Vec<JobRecord>) -> State {
    let mut st = State::default();
    for r in records {
        insert(&mut st, r);
    }
    st
}

fn insert(st: &mut State, r: JobRecord) {
    if r.state == JobState::Queued {
        st.queue.push(r.options.priority, r.seq, r.id.clone());
    }
    if let Some(key) = &r.options.idempotency_key {
        st.keys.insert(scoped_key(r.client.as_deref(), key), r.id.clone());
    }
    st.jobs.insert(r.id.clone(), Entry::new(r));
}

/// How far the watch has delivered the changes of the shared records without a gap: the
/// jobs bucket's stream sequence (a record's revision) through which every change has been
/// seen, 0 while unknown (at startup, after the watch was reopened, after a gap). The watch
/// delivers the stream's messages in order, so a revision more than one past the cursor
/// means a change was missed; [`JobService::reconcile`] then reads the unfinished jobs again,
/// and skips that (a read per job every few seconds) while the cursor has reached the
/// store's last sequence.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub(super) struct WatchCursor {
    through: u64,
}

impl WatchCursor {
    /// The watch delivered the change of stream sequence `revision`.
    fn saw(&mut self, revision: u64) {
        if self.through > 0 && revision <= self.through + 1 {
            self.through = self.through.max(revision);
        } else if revision > self.through + 1 {
            self.through = 0;
        }
    }

    /// Whether every change through `last` was delivered.
    fn caught_up(&self, last: u64) -> bool {
        self.through > 0 && self.through >= last
    }

    /// Every change through `last` is in memory (read again by a full reconciliation).
    fn reconciled(&mut self, last: u64) {
        self.through = self.through.max(last);
    }
}

/// The event that announces a record's new state to watchers.
fn event_for(status: JobStatus) -> JobEvent {
    match status.record.state {
        JobState::Queued => JobEvent::Queued { status: Box::new(status) },
        JobState::Running => JobEvent::Started { attempt: status.record.attempts },
        _ => JobEvent::terminal(status).expect("a final state"),
    }
}

/// A job's sequence number in the queue's order, from its id (a UUIDv7: milliseconds, then
/// random bits), so replicas agree on the order without a shared counter.
pub(super) fn shared_seq(id: &str) -> u64 {
    let hex: String = id.chars().filter(|c| *c != '-').collect();
    let ms = u64::from_str_radix(hex.get(0..12).unwrap_or("0"), 16).unwrap_or(0);
    let random = u64::from_str_radix(hex.get(20..24).unwrap_or("0"), 16).unwrap_or(0);
    (ms << 16) | random
}

impl JobService {
    pub(super) fn shared(&self) -> Option<&SharedRef> {
        self.inner.shared.as_ref()
    }

    /// Applies a change from the shared store to memory (a later revision than the one held
    /// replaces it; this replica's own writes were applied when they were made).
    pub(crate) fn apply_change(&self, change: Change) {
        let revision = match &change {
            Change::Put { record, .. } => record.rev,
            Change::Deleted { revision, .. } => *revision,
        };
        self.lock().watched.saw(revision);
        match change {
            Change::Put { record, own } => self.apply_record(*record, !own),
            Change::Deleted { id, revision } => {
                let mut st = self.lock();
                if st.jobs.get(&id).is_some_and(|e| e.record.rev < revision) {
                    self.forget_entry(&mut st, &id);
                }
            }
        }
    }

    /// Puts `record` in memory if it is newer than the one held; `announce`: send the event
    /// of a changed state.
    fn apply_record(&self, record: JobRecord, announce: bool) {
        let mut guard = self.lock();
        let st = &mut *guard;
        let id = record.id.clone();
        let Some(entry) = st.jobs.get_mut(&id) else {
            let queued = record.state == JobState::Queued;
            insert(st, record);
            if announce {
                let entry = &st.jobs[&id];
                let _ = entry.events.send(event_for(self.status_of(st, entry)));
            }
            self.update_depth(st);
            if queued {
                self.inner.work.notify_all();
            }
            return;
        };
        if entry.record.rev >= record.rev {
            return;
        }
        let old = entry.record.state;
        let mut record = record;
        let held = self.shared().is_some_and(|s| s.holds(&id));
        if held {
            // Run here: stop if cancelled, or if another replica has taken the job over (this
            // run's end would not be written).
            if record.cancel_requested || record.attempts != entry.record.attempts || record.state.is_terminal() {
                entry.cancel.store(true, Ordering::SeqCst);
            }
            if record.state == JobState::Running {
                record.progress = entry.record.progress;
            }
        } else if old == JobState::Running && record.state == JobState::Running {
            record.progress = entry.record.progress;
        }
        let (priority, seq) = (entry.record.options.priority, entry.record.seq);
        let restarted = record.attempts != entry.record.attempts;
        let new = record.state;
        entry.record = record;
        if old == JobState::Queued && new != JobState::Queued {
            st.queue.remove(priority, seq);
        }
        if new == JobState::Queued && old != JobState::Queued {
            let r = &st.jobs[&id].record;
            st.queue.push(r.options.priority, r.seq, id.clone());
            self.inner.work.notify_all();
        }
        if new.is_terminal() && old != new {
            // Ended elsewhere: the frames uploaded here are not needed any more.
            self.inner.store.remove_inputs(&id);
        }
        if announce && (old != new || (new == JobState::Running && restarted)) {
            let entry = &st.jobs[&id];
            let _ = entry.events.send(event_for(self.status_of(st, entry)));
        }
        self.update_depth(st);
    }

    /// Puts `record` back in memory as it was read (a claim that could not be written),
    /// unless a later revision arrived meanwhile: the watch may have applied another
    /// replica's change while the write was timing out, and the read record would hide it
    /// for good (the watch's cursor counts that change as seen).
    pub(super) fn restore(&self, record: JobRecord) {
        let mut st = self.lock();
        let Some(entry) = st.jobs.get_mut(&record.id) else { return };
        if entry.record.rev > record.rev {
            return;
        }
        let queued = record.state == JobState::Queued;
        let (priority, seq, id) = (record.options.priority, record.seq, record.id.clone());
        entry.record = record;
        if queued {
            st.queue.push(priority, seq, id);
            self.update_depth(&st);
        }
    }

    /// Removes a job deleted by another replica from memory (a run here stops).
    fn forget_entry(&self, st: &mut State, id: &str) {
        let Some(entry) = st.jobs.remove(id) else { return };
        entry.cancel.store(true, Ordering::SeqCst);
        let r = &entry.record;
        if r.state == JobState::Queued {
            st.queue.remove(r.options.priority, r.seq);
            self.update_depth(st);
        }
        if let Some(key) = &r.options.idempotency_key {
            st.keys.remove(&scoped_key(r.client.as_deref(), key));
        }
        if !r.state.is_terminal() {
            let _ = entry.events.send(JobEvent::Deleted);
        }
        if !self.shared().is_some_and(|s| s.holds(id)) {
            self.inner.store.remove_files(id);
        }
    }

    /// Shared mode: copies the stored file `name` of job `id` to `path` unless it is there
    /// already (a job run or submitted on another replica). Nothing in embedded mode.
    /// Blocking.
    pub(super) fn fetch_shared_file(&self, id: &str, name: &str, path: &std::path::Path) -> Result<()> {
        match self.shared() {
            Some(shared) if !path.is_file() => shared.download(id, name, path).map(|_| ()),
            _ => Ok(()),
        }
    }

    /// Shared mode: stores the files a run wrote for the other replicas (the result and
    /// the preview sources). Blocking.
    pub(super) fn share_result(&self, id: &str) -> Result<()> {
        let Some(shared) = self.shared() else { return Ok(()) };
        let store = &self.inner.store;
        shared.upload(id, "result.exr", &store.result_path(id))?;
        for which in ["input", "reference"] {
            let path = store.preview_source_path(id, which);
            if path.is_file() {
                shared.upload(id, &format!("preview-{which}.exr"), &path)?;
            }
        }
        Ok(())
    }

    /// Makes up for changes the watch did not deliver (it can miss one when its consumer
    /// is recreated under load): jobs no longer stored go, stored jobs not in memory come,
    /// and, unless the watch delivered every change so far ([`WatchCursor`]), unfinished
    /// jobs are read again. Run every few seconds. Blocking.
    pub(crate) fn reconcile(&self) -> Result<()> {
        let shared = self.shared().expect("shared mode").clone();
        let (last, stored) = shared.stored_ids()?;
        let (gone, read): (Vec<String>, Vec<String>) = {
            let st = self.lock();
            let all = !st.watched.caught_up(last);
            let gone = st
                .jobs
                .iter()
                .filter(|(id, e)| e.record.rev <= last && !stored.contains(*id))
                .map(|(id, _)| id.clone())
                .collect();
            let unfinished =
                st.jobs.iter().filter(|(_, e)| all && !e.record.state.is_terminal()).map(|(id, _)| id.clone());
            let missing = stored.iter().filter(|id| !st.jobs.contains_key(*id)).cloned();
            (gone, unfinished.chain(missing).collect())
        };
        let mut fixed = 0;
        {
            let mut st = self.lock();
            for id in &gone {
                if st.jobs.get(id).is_some_and(|e| e.record.rev <= last) {
                    self.forget_entry(&mut st, id);
                    fixed += 1;
                }
            }
        }
        for id in &read {
            let before = self.lock().jobs.get(id).map(|e| e.record.rev);
            let after = self.refresh(id)?.map(|r| r.rev);
            fixed += usize::from(before.is_some_and(|b| after.is_some_and(|a| a > b)) || before.is_none());
        }
        if fixed > 0 {
            tracing::info!(jobs = fixed, "the watch of the shared records had missed changes; applied now");
        }
        self.lock().watched.reconciled(last);
        Ok(())
    }

    /// Brings memory in line with every stored record (after the watch was lost): newer
    /// records replace older ones, jobs no longer stored go.
    pub(crate) fn resync(&self, records: Vec<JobRecord>) {
        self.lock().watched = WatchCursor::default();
        let ids: std::collections::HashSet<String> = records.iter().map(|r| r.id.clone()).collect();
        for record in records {
            self.apply_record(record, true);
        }
        let mut st = self.lock();
        let gone: Vec<String> = st.jobs.keys().filter(|id| !ids.contains(*id)).cloned().collect();
        for id in gone {
            self.forget_entry(&mut st, &id);
        }
    }

    /// Progress of a job another replica runs.
    pub(crate) fn apply_progress(&self, id: &str, progress: Progress) {
        let mut st = self.lock();
        if let Some(entry) = st.jobs.get_mut(id).filter(|e| e.record.state == JobState::Running) {
            entry.record.progress = progress;
            let _ = entry.events.send(JobEvent::Progress(progress));
        }
    }

    /// Reads job `id` from the shared store into memory; the record, `None` if it is gone.
    pub(super) fn refresh(&self, id: &str) -> Result<Option<JobRecord>> {
        let shared = self.shared().expect("shared mode");
        match shared.get(id)? {
            Some(record) => {
                self.apply_record(record.clone(), true);
                Ok(Some(record))
            }
            None => {
                self.forget_entry(&mut self.lock(), id);
                Ok(None)
            }
        }
    }

    /// Shared mode: reads the stored record of a job this replica's mirror does not hold
    /// yet. A job accepted by another replica reaches the mirror through the watch a moment
    /// later; without this, a client that submits through one replica and asks another at
    /// once (replicas behind one load balancer) would be told that its job does not exist.
    /// Only canonical job ids are looked up (anything else cannot be a job). Blocking;
    /// nothing to do in embedded mode or for a job already known.
    pub(super) fn catch_up_blocking(&self, id: &str) -> Result<()> {
        if !self.may_be_elsewhere(id) {
            return Ok(());
        }
        self.refresh(id).map(|_| ())
    }

    /// [`JobService::catch_up_blocking`] on the blocking pool: what every read by job id
    /// (`find`, `follow`, `open_result`, `preview`) does first.
    pub(super) async fn catch_up(&self, id: &str) -> Result<()> {
        if !self.may_be_elsewhere(id) {
            return Ok(());
        }
        let id = id.to_string();
        self.blocking(move |s| s.catch_up_blocking(&id)).await
    }

    /// Shared mode, a canonical job id, and not in this replica's mirror.
    fn may_be_elsewhere(&self, id: &str) -> bool {
        self.shared().is_some()
            && uuid::Uuid::try_parse(id).is_ok_and(|u| u.hyphenated().to_string() == id)
            && !self.lock().jobs.contains_key(id)
    }

    /// Shared mode's `next_job`: the next job message this replica can run, claimed.
    pub(super) fn next_shared(&self, link: &super::claims::WorkerLink) -> Option<Claim> {
        let shared = self.shared().expect("shared mode").clone();
        loop {
            {
                let st = self.lock();
                match self.phase() {
                    Phase::Draining | Phase::Stopped => return None,
                    Phase::Ready if self.storage_problem().is_none() => {}
                    _ => {
                        let _ =
                            self.inner.work.wait_timeout(st, Duration::from_millis(250)).unwrap_or_else(lock_poisoned);
                        continue;
                    }
                }
            }
            match shared.take() {
                Ok(Some(id)) => {
                    if let Some(claim) = self.claim_shared(link, &id) {
                        return Some(claim);
                    }
                }
                Ok(None) => {
                    // Woken early by a job queued anywhere (the watch), else polls again.
                    let st = self.lock();
                    let _ = self.inner.work.wait_timeout(st, Duration::from_millis(250)).unwrap_or_else(lock_poisoned);
                }
                Err(e) => {
                    tracing::warn!(error = %e, "cannot take a job from the shared queue");
                    self.storage_failed(&e);
                    std::thread::sleep(Duration::from_millis(500));
                }
            }
        }
    }

    /// Claims the job of a message this replica took: `None` when there is nothing to run
    /// (the message is settled here).
    fn claim_shared(&self, link: &super::claims::WorkerLink, id: &str) -> Option<Claim> {
        let shared = self.shared().expect("shared mode").clone();
        for _ in 0..5 {
            let record = match self.refresh(id) {
                Ok(Some(record)) => record,
                Ok(None) => {
                    // Deleted: the message goes with it.
                    shared.ack(id);
                    return None;
                }
                Err(e) => {
                    tracing::warn!(job_id = id, error = %e, "cannot read the job record of a queued job");
                    shared.nak(id, Some(Duration::from_secs(1)));
                    return None;
                }
            };
            if record.state.is_terminal() {
                // Ended already (by a run whose acknowledgement was lost): nothing to do.
                shared.ack(id);
                return None;
            }
            let ending = if record.cancel_requested {
                Some(Ending::Cancelled)
            } else if record.deadline_at_ms.is_some_and(|t| t <= self.now()) {
                Some(deadline_passed())
            } else if record.attempts >= MAX_SHARED_RUNS {
                Some(Ending::Failed(
                    JobError {
                        code: JobErrorCode::Internal,
                        message: format!(
                            "gave up after {} runs, each cut short by its replica stopping",
                            record.attempts
                        ),
                    },
                    None,
                ))
            } else {
                None
            };
            if let Some(ending) = ending {
                match self.settle_running_or_queued(id, ending) {
                    Err(Error::Conflict(_)) => continue,
                    Err(e) => {
                        shared.nak(id, Some(Duration::from_secs(1)));
                        tracing::warn!(job_id = id, error = %e, "cannot write the job's end");
                    }
                    Ok(()) => shared.ack(id),
                }
                return None;
            }
            // Queued, or running on a replica that stopped: run it here. `claim` marks it
            // running in memory (attempt and tiles counted); that is written before the run,
            // so a run that loses the race to another replica never starts.
            let now = self.now();
            let claim = {
                let mut st = self.lock();
                let Some(entry) = st.jobs.get_mut(id) else { continue };
                // A flag of its own for this run: an earlier run's stop (taken over, say)
                // is not this one's; a cancellation is in the record, checked above.
                entry.cancel = Arc::new(AtomicBool::new(false));
                if entry.record.state == JobState::Running {
                    // Delivered again: the replica that ran it stopped.
                    entry.record.state = JobState::Queued;
                    tracing::info!(job_id = id, attempts = record.attempts, "its replica stopped: running it here");
                } else {
                    st.queue.remove(record.options.priority, record.seq);
                }
                link.claim(&mut st, id, now)
            };
            let mut next = match self.lock().jobs.get(id) {
                Some(e) => e.record.clone(),
                None => {
                    link.release(claim);
                    shared.ack(id);
                    return None;
                }
            };
            match self.write_record(&mut next) {
                Ok(()) => {
                    if let Some(entry) = self.lock().jobs.get_mut(id) {
                        entry.record.rev = next.rev;
                    }
                }
                Err(Error::Conflict(_)) => {
                    link.release(claim);
                    continue;
                }
                Err(e) => {
                    tracing::warn!(job_id = id, error = %e, "cannot claim a queued job");
                    self.storage_failed(&e);
                    link.release(claim);
                    self.restore(record);
                    shared.nak(id, Some(Duration::from_secs(1)));
                    return None;
                }
            }
            let record = next;
            // The frames, from the object store into the scratch directory.
            let store = &self.inner.store;
            let mut fetched = shared.download(id, "input.exr", &store.input_path(id));
            if record.has_reference && matches!(fetched, Ok(true)) {
                fetched = shared.download(id, "reference.exr", &store.reference_path(id));
            }
            match fetched {
                Ok(true) => {
                    tracing::info!(job_id = id, attempt = claim.attempt, "claimed from the shared queue");
                    return Some(claim);
                }
                Ok(false) => {
                    let error =
                        JobError { code: JobErrorCode::Internal, message: "the uploaded frame is missing".into() };
                    link.finish(claim, super::claims::Outcome::Failed(error, None));
                    return None;
                }
                Err(e) => {
                    link.finish(claim, super::claims::Outcome::StorageFault(e.to_string()));
                    return None;
                }
            }
        }
        // Changed by others on every try: leave it for later.
        shared.nak(id, Some(Duration::from_secs(1)));
        None
    }

    /// Writes the final state of a job not running here (found cancelled, overdue or given
    /// up on at its claim).
    fn settle_running_or_queued(&self, id: &str, ending: Ending) -> Result<()> {
        let journal = self.journal();
        // `prepare` ends queued and running jobs alike.
        let prepared = self.prepare(&mut self.lock(), id, ending);
        match prepared {
            Some(p) => self.commit(&journal, p).map(|_| ()),
            None => Ok(()),
        }
    }

    /// Settles the message of a run that ended here, as its record now says: final (or
    /// gone) → acknowledged; queued again → back to the queue after `requeue_after`; running
    /// another attempt → that run's, left alone; still this run's → delivered again later.
    pub(super) fn settle_message(&self, id: &str, attempt: u32, requeue_after: Option<Duration>) {
        let Some(shared) = self.shared() else { return };
        let current = self.lock().jobs.get(id).map(|e| (e.record.state, e.record.attempts));
        match current {
            None => shared.ack(id),
            Some((state, _)) if state.is_terminal() => shared.ack(id),
            Some((JobState::Running, attempts)) if attempts != attempt => {
                tracing::warn!(job_id = id, attempt, "another replica took the job over; this run's end is dropped");
                shared.forget(id);
            }
            Some((JobState::Queued, _)) => shared.nak(id, requeue_after),
            Some(_) => shared.nak(id, Some(requeue_after.unwrap_or(Duration::from_secs(1)))),
        }
    }

    /// After a run's end lost a compare-and-set: reads the job again and, if it is still
    /// this run's and was cancelled meanwhile, ends it so.
    pub(super) fn end_after_conflict(&self, id: &str, attempt: u32) {
        for _ in 0..5 {
            match self.refresh(id) {
                Ok(Some(r)) if r.state == JobState::Running && r.attempts == attempt && r.cancel_requested => {
                    match self.settle(&self.journal(), id, Ending::Cancelled) {
                        Err(Error::Conflict(_)) => continue,
                        _ => return,
                    }
                }
                _ => return,
            }
        }
    }

    /// Asks the replica running job `id` to stop it: the record says `cancel_requested`.
    pub(super) fn request_cancel_elsewhere(&self, id: &str) -> Result<JobStatus> {
        for _ in 0..5 {
            let mut next = match self.lock().jobs.get(id) {
                Some(e) => e.record.clone(),
                None => return Err(super::not_found(id)),
            };
            if next.state != JobState::Running {
                // Ended or requeued meanwhile: the caller decides again.
                return Err(Error::Conflict(format!("job {id} changed while it was being cancelled; retry")));
            }
            next.cancel_requested = true;
            match self.write_record(&mut next) {
                Ok(()) => {
                    self.apply_record(next, false);
                    tracing::info!(job_id = id, "cancellation requested (the job runs on another replica)");
                    let st = self.lock();
                    let entry = st.jobs.get(id).ok_or_else(|| super::not_found(id))?;
                    return Ok(self.status_of(&st, entry));
                }
                Err(Error::Conflict(_)) => {
                    self.refresh(id)?;
                }
                Err(e) => return Err(e),
            }
        }
        Err(Error::Conflict(format!("job {id} keeps changing; retry the cancellation")))
    }
}

#[cfg(test)]
mod tests {
    use super::WatchCursor;

    #[test]
    fn the_cursor_follows_contiguous_changes_and_forgets_on_a_gap() {
        let mut c = WatchCursor::default();
        c.saw(1);
        assert!(!c.caught_up(1), "unknown until a reconciliation");
        c.reconciled(5);
        assert!(c.caught_up(5) && !c.caught_up(6));
        c.saw(6);
        c.saw(7);
        c.saw(4); // an older change delivered again
        assert!(c.caught_up(7));
        c.saw(9); // 8 was missed
        assert!(!c.caught_up(9) && !c.caught_up(1));
        c.reconciled(9);
        assert!(c.caught_up(9));
        c.saw(10);
        assert!(c.caught_up(10));
    }
}
