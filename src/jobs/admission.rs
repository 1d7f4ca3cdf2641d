//! Admission: whether a submission may start uploading (readiness, idempotency key,
//! capacity, the client's own limits), and queuing it once its upload is complete.
//!
//! An upload holds a [`Slot`] from before its first byte is read to its queuing: a place
//! in the capacity and one of its client's uploads in flight. A raw body is admitted with
//! its options at once ([`JobService::admit`]); a multipart body reserves its slot first
//! ([`JobService::reserve`]), since its options arrive inside it, then is admitted
//! ([`JobService::admit_reserved`]).
//!
//! Locking: [`JobService::admit`], `reserve` and the release of a slot only change memory
//! under the state lock.
//! `enqueue` writes the new record to the store with no lock held (nobody else knows the
//! job yet), then inserts it under the state lock.

use std::time::Duration;

use super::uploads::Ticket;
use super::{scoped_key, Entry, JobService, State};
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

/// A place held by an upload in progress: counted in the capacity (`reserved`) and in its
/// client's uploads in flight until it is queued or dropped.
pub struct Slot {
    service: JobService,
    client: ClientId,
    held: std::sync::atomic::AtomicBool,
}

impl Slot {
    pub fn client(&self) -> &ClientId {
        &self.client
    }

    /// Gives the place back (once), under the state lock the caller holds.
    pub(super) fn release_in(&self, st: &mut State) {
        if self.held.swap(false, std::sync::atomic::Ordering::AcqRel) {
            st.reserved -= 1;
            release_upload(st, &self.client);
            self.service.inner.telemetry.set_uploads(st.reserved);
        }
    }
}

impl Drop for Slot {
    fn drop(&mut self) {
        if self.held.load(std::sync::atomic::Ordering::Acquire) {
            let service = self.service.clone();
            self.release_in(&mut service.lock());
        }
    }
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
        self.admit_inner(options, transport, client, None)
    }

    /// Reserves a place for an upload whose options are not known yet (they come inside
    /// a multipart body): checks the capacity and the client's limits before any of the
    /// body is read. Memory only.
    pub fn reserve(&self, client: &ClientId) -> Result<Slot> {
        let mut st = self.lock();
        self.take_slot(&mut st, client)
    }

    /// Admits a submission that holds a [`Slot`] already (see [`JobService::admit`]).
    pub fn admit_reserved(&self, slot: Slot, options: JobOptions, transport: &'static str) -> Result<Admission> {
        let client = slot.client.clone();
        self.admit_inner(options, transport, &client, Some(slot))
    }

    fn take_slot(&self, st: &mut State, client: &ClientId) -> Result<Slot> {
        let capacity = self.inner.settings.capacity;
        if st.queue.len() + st.reserved >= capacity {
            return Err(Error::QueueFull { capacity, retry_after_s: self.retry_after_s(st) });
        }
        self.check_client(st, client)?;
        st.reserved += 1;
        *st.uploads.entry(client.clone()).or_default() += 1;
        self.inner.telemetry.set_uploads(st.reserved);
        Ok(Slot { service: self.clone(), client: client.clone(), held: true.into() })
    }

    fn admit_inner(
        &self,
        options: JobOptions,
        transport: &'static str,
        client: &ClientId,
        slot: Option<Slot>,
    ) -> Result<Admission> {
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
        // An unknown or malformed channel map is refused before the upload is read.
        self.channel_maps(&options)?;
        let scoped = options.idempotency_key.as_deref().map(|k| scoped_key(Some(client.as_str()), k));
        if let (Some(key), Some(scoped)) = (&options.idempotency_key, &scoped) {
            if let Some(id) = st.keys.get(scoped) {
                if let Some(entry) = st.jobs.get(id) {
                    return Ok(Admission::Existing(self.status_of(&st, entry)));
                }
            }
            if st.uploading.contains(scoped) {
                return Err(Error::InProgress(format!(
                    "a submission with idempotency key `{key}` is still being uploaded; retry when it completes"
                )));
            }
        }
        let slot = match slot {
            Some(slot) => slot,
            None => self.take_slot(&mut st, client)?,
        };
        if let Some(scoped) = scoped {
            st.uploading.insert(scoped);
        }
        drop(st);
        let id = uuid::Uuid::now_v7().to_string();
        Ok(Admission::New(Ticket::new(self.clone(), id, options, transport, slot)))
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

    /// Logs a caller refused by the token check (`e`: which check, never the token) on
    /// `transport`'s `route`, and counts it as a rejected job when it was a `submission`.
    pub fn note_refused_caller(
        &self,
        e: &Error,
        transport: &str,
        route: &str,
        peer: Option<std::net::SocketAddr>,
        submission: bool,
    ) {
        let peer = peer.map(|p| p.to_string()).unwrap_or_default();
        tracing::warn!(transport, route, peer, reason = e.code(), "request refused: {e}");
        if submission {
            self.note_rejection(e);
        }
    }

    /// Counts a refused submission in the metrics.
    pub fn note_rejection(&self, e: &Error) {
        let reason = match e {
            Error::QueueFull { .. } => "queue_full",
            Error::ClientLimit { .. } => "client_limit",
            Error::BadRequest(_) | Error::InvalidFrame(_) => "invalid",
            Error::TooLarge(_) => "too_large",
            Error::Timeout(_) => "timeout",
            Error::Unavailable(_) => "unavailable",
            Error::Storage { full: true, .. } => "storage_full",
            Error::Storage { full: false, .. } => "storage_unavailable",
            Error::Unauthenticated(_) => "unauthenticated",
            Error::Forbidden(_)
            | Error::NotFound(_)
            | Error::Conflict(_)
            | Error::InProgress(_)
            | Error::Internal(_) => "other",
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
        let seq = if self.shared().is_some() {
            super::mirror::shared_seq(ticket.id())
        } else {
            let mut st = self.lock();
            st.next_seq += 1;
            st.next_seq - 1
        };
        let mut record = JobRecord {
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
            warnings: Vec::new(),
            error: None,
            result_bytes: None,
            client: Some(ticket.client().as_str().to_string()),
            storage_failures: 0,
            trace_parent: ticket.trace_parent.clone(),
            rev: 0,
        };
        if let Some(shared) = self.shared() {
            if let Some(existing) = self.enqueue_shared(shared, ticket, &mut record)? {
                // The idempotency key belongs to a job another replica queued meanwhile.
                let _ = std::fs::remove_dir_all(self.inner.store.job_dir(ticket.id()));
                let id = existing.id.clone();
                self.apply_change(super::shared::Change::Put { record: Box::new(existing), own: false });
                let mut st = self.lock();
                ticket.slot().release_in(&mut st);
                if let Some(key) = &record.options.idempotency_key {
                    st.uploading.remove(&scoped_key(record.client.as_deref(), key));
                }
                let entry = st.jobs.get(&id).ok_or_else(|| super::not_found(&id))?;
                return Ok(self.status_of(&st, entry));
            }
        } else {
            self.inner.store.put(&record)?;
        }
        let mut st = self.lock();
        ticket.slot().release_in(&mut st);
        if let Some(key) = &record.options.idempotency_key {
            let scoped = scoped_key(record.client.as_deref(), key);
            st.uploading.remove(&scoped);
            st.keys.insert(scoped, record.id.clone());
        }
        let id = record.id.clone();
        // Shared mode: a worker here may have taken the job from the shared queue (and
        // put it in memory) already; that newer state stays.
        let fresh = !st.jobs.contains_key(&id);
        if fresh {
            st.queue.push(record.options.priority, record.seq, record.id.clone());
            st.jobs.insert(id.clone(), Entry::new(record));
        }
        self.update_depth(&st);
        self.inner.telemetry.job_submitted(ticket.transport());
        self.inner.work.notify_one();
        let entry = &st.jobs[&id];
        let status = self.status_of(&st, entry);
        if fresh {
            let _ = entry.events.send(JobEvent::Queued { status: Box::new(status.clone()) });
        }
        Ok(status)
    }

    /// Shared mode's durable half of `enqueue`: the idempotency key claimed, the frames
    /// stored, the record written, the job put on the work queue (each undone if a later
    /// step fails). `Some(job)`: the key belongs to that job, which is the answer.
    fn enqueue_shared(
        &self,
        shared: &super::shared::SharedRef,
        ticket: &Ticket,
        record: &mut JobRecord,
    ) -> Result<Option<JobRecord>> {
        let id = record.id.clone();
        let scoped = record.options.idempotency_key.as_deref().map(|k| scoped_key(record.client.as_deref(), k));
        if let Some(scoped) = &scoped {
            if let Some(other) = shared.claim_key(scoped, &id)? {
                if let Some(existing) = shared.get(&other)? {
                    return Ok(Some(existing));
                }
            }
        }
        let store = &self.inner.store;
        let stored = shared
            .upload(&id, "input.exr", &store.input_path(&id))
            .and_then(|()| match ticket.has_reference() {
                true => shared.upload(&id, "reference.exr", &store.reference_path(&id)),
                false => Ok(()),
            })
            .and_then(|()| shared.put(record))
            .and_then(|()| shared.publish(&id, record.options.priority));
        if let Err(e) = stored {
            if let Err(undo) = shared.remove(&[(id.as_str(), scoped)]) {
                tracing::warn!(job_id = id.as_str(), error = %undo, "cannot undo a submission that was not queued");
            }
            return Err(e);
        }
        Ok(None)
    }

    /// Gives back the place and the idempotency key of an admission that was not queued.
    pub(super) fn release(&self, key: Option<&str>, slot: &Slot) {
        let mut st = self.lock();
        slot.release_in(&mut st);
        if let Some(key) = key {
            st.uploading.remove(&scoped_key(Some(slot.client().as_str()), key));
        }
    }
}
