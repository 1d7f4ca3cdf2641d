//! Admission: whether a submission may start uploading (readiness, idempotency key,
//! capacity, the client's own limits), and queuing it once its upload is complete.
//!
//! Locking: [`JobService::admit`] and `release` only change memory under the state lock.
//! `enqueue` writes the new record to the store with no lock held (nobody else knows the
//! job yet), then inserts it under the state lock.

use std::time::Duration;

use super::uploads::Ticket;
use super::{Entry, JobService, State};
use crate::auth::ClientId;
use crate::error::{Error, Result};
use crate::jobs::{JobEvent, JobOptions, JobRecord, JobState, JobStatus, Phase, Progress};

/// The result of an admission (short-lived: the size of its variants does not matter).
#[allow(clippy::large_enum_variant)]
pub enum Admission {
    /// A new job: upload its frame through the ticket, then [`Ticket::commit`].
    New(Ticket),
    /// A job with the same idempotency key exists: this is it.
    Existing(JobStatus),
}

/// One fewer upload in progress for `client`.
pub(super) fn release_upload(st: &mut State, client: &ClientId) {
    if let Some(n) = st.uploads.get_mut(client) {
        *n -= 1;
        if *n == 0 {
            st.uploads.remove(client);
        }
    }
}

impl JobService {
    /// Admits a submission before its frame is read: checks readiness, the idempotency key
    /// and the capacity, and reserves a place in the queue. Memory only: returns at once.
    pub fn admit(&self, options: JobOptions, transport: &'static str, client: &ClientId) -> Result<Admission> {
        let options = options.normalize().map_err(Error::BadRequest)?;
        let mut st = self.lock();
        match self.phase() {
            Phase::Ready => {}
            Phase::Loading => return Err(Error::Unavailable("not ready: the models are still loading".into())),
            Phase::Draining | Phase::Stopped => {
                return Err(Error::Unavailable("shutting down: not accepting new jobs".into()))
            }
        }
        if let Some(problem) = self.storage_problem() {
            return Err(problem.error());
        }
        if let (Some(v), Some(models)) = (options.variant, self.models()) {
            if !models.iter().any(|m| m.variant == v) {
                let mut loaded: Vec<&str> = models.iter().map(|m| m.variant.name()).collect();
                loaded.dedup();
                return Err(Error::BadRequest(format!("no `{v}` model is loaded (loaded: {})", loaded.join(", "))));
            }
        }
        if let Some(key) = &options.idempotency_key {
            if let Some(id) = st.keys.get(key) {
                if let Some(entry) = st.jobs.get(id) {
                    return Ok(Admission::Existing(self.status_of(&st, entry)));
                }
            }
            if st.uploading.contains(key) {
                return Err(Error::InProgress(format!(
                    "a submission with idempotency key `{key}` is still being uploaded; retry when it completes"
                )));
            }
        }
        let capacity = self.inner.settings.capacity;
        if st.queue.len() + st.reserved >= capacity {
            return Err(Error::QueueFull { capacity, retry_after_s: self.retry_after_s(&st) });
        }
        self.check_client(&st, client)?;
        st.reserved += 1;
        *st.uploads.entry(client.clone()).or_default() += 1;
        if let Some(key) = &options.idempotency_key {
            st.uploading.insert(key.clone());
        }
        drop(st);
        let id = uuid::Uuid::now_v7().to_string();
        Ok(Admission::New(Ticket::new(self.clone(), id, options, transport, client.clone())))
    }

    /// Refuses a new upload when `client` is at its own limits.
    fn check_client(&self, st: &State, client: &ClientId) -> Result<()> {
        let s = &self.inner.settings;
        let uploads = st.uploads.get(client).copied().unwrap_or(0);
        if uploads >= s.max_uploads_per_client {
            return Err(Error::ClientLimit {
                message: format!(
                    "{} has {uploads} uploads in progress, the most one client may have at once \
                     (--max-uploads-per-client); retry when one completes",
                    client.as_str()
                ),
                retry_after_s: 1,
            });
        }
        let unfinished = st
            .jobs
            .values()
            .filter(|e| !e.record.state.is_terminal() && e.record.client.as_deref() == Some(client.as_str()))
            .count();
        if unfinished + uploads >= s.max_jobs_per_client {
            return Err(Error::ClientLimit {
                message: format!(
                    "{} has {} unfinished jobs, the most one client may have (--max-jobs-per-client); \
                     retry when some finish",
                    client.as_str(),
                    unfinished + uploads
                ),
                retry_after_s: self.retry_after_s(st),
            });
        }
        Ok(())
    }

    /// Counts a refused submission in the metrics.
    pub fn note_rejection(&self, e: &Error) {
        let reason = match e {
            Error::QueueFull { .. } => "queue_full",
            Error::ClientLimit { .. } => "client_limit",
            Error::BadRequest(_) | Error::InvalidFrame(_) => "invalid",
            Error::TooLarge(_) => "too_large",
            Error::Unavailable(_) => "unavailable",
            Error::Storage { full: true, .. } => "storage_full",
            Error::Storage { full: false, .. } => "storage_unavailable",
            Error::Unauthenticated(_) => "unauthenticated",
            Error::NotFound(_) | Error::Conflict(_) | Error::InProgress(_) | Error::Internal(_) => "other",
        };
        self.inner.telemetry.job_rejected(reason);
    }

    /// Queues an uploaded job: its record is durable before it is visible. Blocking.
    pub(super) fn enqueue(&self, ticket: &Ticket, info: crate::frame::HeaderInfo) -> Result<JobStatus> {
        let now = self.now();
        let options = ticket.options().clone();
        let deadline = options
            .deadline_seconds
            .map(Duration::from_secs)
            .or(self.inner.settings.default_deadline)
            .map(|d| now + d.as_millis() as i64);
        // A sequence number lost to a failed write leaves a gap, which is harmless.
        let seq = {
            let mut st = self.lock();
            st.next_seq += 1;
            st.next_seq - 1
        };
        let record = JobRecord {
            id: ticket.id().to_string(),
            seq,
            state: JobState::Queued,
            options,
            width: info.width as u32,
            height: info.height as u32,
            input_bytes: ticket.received(),
            has_reference: ticket.has_reference(),
            created_at_ms: now,
            started_at_ms: None,
            finished_at_ms: None,
            deadline_at_ms: deadline,
            expires_at_ms: None,
            attempts: 0,
            cancel_requested: false,
            variant: None,
            progress: Progress::default(),
            timings: None,
            metrics: None,
            sanitized: None,
            fireflies: None,
            missing_variances: Vec::new(),
            error: None,
            result_bytes: None,
            client: Some(ticket.client().as_str().to_string()),
            storage_failures: 0,
            rev: 0,
        };
        self.inner.store.put(&record)?;
        let mut st = self.lock();
        st.reserved -= 1;
        release_upload(&mut st, ticket.client());
        if let Some(key) = &record.options.idempotency_key {
            st.uploading.remove(key);
            st.keys.insert(key.clone(), record.id.clone());
        }
        st.queue.push(record.options.priority, record.seq, record.id.clone());
        let id = record.id.clone();
        st.jobs.insert(id.clone(), Entry::new(record));
        self.update_depth(&st);
        self.inner.telemetry.job_submitted(ticket.transport());
        self.inner.work.notify_one();
        let entry = &st.jobs[&id];
        let status = self.status_of(&st, entry);
        let _ = entry.events.send(JobEvent::Queued { status: Box::new(status.clone()) });
        Ok(status)
    }

    /// Gives back the place of an admission that was not queued.
    pub(super) fn release(&self, key: Option<&str>, client: &ClientId) {
        let mut st = self.lock();
        st.reserved -= 1;
        release_upload(&mut st, client);
        if let Some(key) = key {
            st.uploading.remove(key);
        }
    }
}
