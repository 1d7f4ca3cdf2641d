//! Uploads: an admitted submission ([`Ticket`]) receives its frame and optional reference
//! through a [`Sink`] each, written to disk as they arrive, then is committed (headers
//! checked, job queued) or dropped (its place released, its files removed).
//!
//! Locking: a ticket holds no lock while bytes arrive; files are written with async I/O.
//! Only the commit (through `admission`) and the release on drop take the state lock.

use std::sync::Arc;

use super::admission::Slot;
use super::{validate, JobService};
use crate::atomic::AsyncFile;
use crate::auth::ClientId;
use crate::error::{Error, Result};
use crate::jobs::{JobOptions, JobStatus};
use crate::telemetry::Telemetry;

/// Which upload a [`Sink`] receives.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum UploadPart {
    Frame,
    Reference,
}

impl UploadPart {
    pub fn name(self) -> &'static str {
        match self {
            UploadPart::Frame => "frame",
            UploadPart::Reference => "reference",
        }
    }
}

/// An admitted submission whose frame is being uploaded. Dropping it without
/// [`Ticket::commit`] releases its place and removes what was written.
pub struct Ticket {
    service: JobService,
    id: String,
    options: JobOptions,
    transport: &'static str,
    received: u64,
    frame: Option<u64>,
    reference: Option<u64>,
    done: bool,
    slot: Slot,
    /// The submission's trace context, kept with the job ([`crate::otlp`]).
    pub(super) trace_parent: Option<String>,
}

impl Ticket {
    pub(super) fn new(
        service: JobService,
        id: String,
        options: JobOptions,
        transport: &'static str,
        slot: Slot,
    ) -> Ticket {
        let trace_parent = crate::otlp::current_traceparent();
        Ticket {
            service,
            id,
            options,
            transport,
            received: 0,
            frame: None,
            reference: None,
            done: false,
            slot,
            trace_parent,
        }
    }

    pub fn id(&self) -> &str {
        &self.id
    }

    pub fn options(&self) -> &JobOptions {
        &self.options
    }

    pub(super) fn received(&self) -> u64 {
        self.received
    }

    pub(super) fn has_reference(&self) -> bool {
        self.reference.is_some()
    }

    pub(super) fn client(&self) -> &ClientId {
        self.slot.client()
    }

    pub(super) fn slot(&self) -> &Slot {
        &self.slot
    }

    pub(super) fn transport(&self) -> &'static str {
        self.transport
    }

    /// Marks the ticket queued: dropping it no longer releases anything.
    fn committed(&mut self) {
        self.done = true;
    }

    /// Bytes still allowed under the body limit.
    pub fn remaining(&self) -> u64 {
        self.service.inner.settings.max_body_bytes.saturating_sub(self.received)
    }

    /// Starts writing one part of the upload (each part at most once).
    pub async fn sink(&mut self, part: UploadPart) -> Result<Sink> {
        let already = match part {
            UploadPart::Frame => self.frame.is_some(),
            UploadPart::Reference => self.reference.is_some(),
        };
        if already {
            return Err(Error::BadRequest(format!("the {} was sent twice", part.name())));
        }
        let store = &self.service.inner.store;
        let path = match part {
            UploadPart::Frame => store.input_path(&self.id),
            UploadPart::Reference => store.reference_path(&self.id),
        };
        let dir = store.job_dir(&self.id);
        // Not `create_dir_all`: a data directory moved away must not be re-created here.
        match tokio::fs::create_dir(&dir).await {
            Ok(()) => {}
            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => {}
            Err(e) => {
                let e = Error::storage("cannot create the job directory", &e);
                self.service.storage_failed(&e);
                return Err(e);
            }
        }
        let file = AsyncFile::create(&path).await.map_err(|e| {
            let e = Error::storage("cannot create the upload file", &e);
            self.service.storage_failed(&e);
            e
        })?;
        Ok(Sink {
            file,
            part,
            written: 0,
            limit: self.remaining(),
            max_body: self.service.inner.settings.max_body_bytes,
            telemetry: self.service.inner.telemetry.clone(),
            transport: self.transport,
        })
    }

    /// Completes one part: flushes it to disk and moves it into place.
    pub async fn finish(&mut self, sink: Sink) -> Result<()> {
        let part = sink.part;
        let n = sink.finish().await?;
        self.received += n;
        match part {
            UploadPart::Frame => self.frame = Some(n),
            UploadPart::Reference => self.reference = Some(n),
        }
        Ok(())
    }

    /// Validates the uploaded headers and queues the job.
    pub async fn commit(mut self) -> Result<JobStatus> {
        if self.frame.is_none() {
            return Err(Error::BadRequest("no frame was uploaded".into()));
        }
        let store = &self.service.inner.store;
        let input = store.input_path(&self.id);
        let reference = self.reference.map(|_| store.reference_path(&self.id));
        let limits = self.service.inner.settings.limits;
        let maps = self.service.channel_maps(&self.options)?;
        let service = self.service.clone();
        let status = service
            .blocking(move |service| {
                let info = validate::check_frame(&input, &limits, &maps).map_err(|e| Error::frame("frame", e))?;
                if let Some(reference) = reference {
                    let r = validate::check_reference(&reference, &limits).map_err(|e| Error::frame("reference", e))?;
                    crate::pipeline::check_same_size((info.width, info.height), (r.width, r.height))
                        .map_err(|e| Error::InvalidFrame(e.to_string()))?;
                }
                let status = service.enqueue(&self, info);
                if status.is_ok() {
                    self.committed();
                }
                status
            })
            .await?;
        tracing::info!(
            job_id = status.record.id.as_str(),
            priority = status.record.options.priority.name(),
            width = status.record.width,
            height = status.record.height,
            bytes = status.record.input_bytes,
            client = status.record.client.as_deref().unwrap_or(""),
            "queued"
        );
        Ok(status)
    }
}

impl Drop for Ticket {
    fn drop(&mut self) {
        if !self.done {
            self.service.release(self.options.idempotency_key.as_deref(), &self.slot);
            let dir = self.service.inner.store.job_dir(&self.id);
            // Small and rare (refused uploads): removing inline is fine.
            let _ = std::fs::remove_dir_all(dir);
        }
    }
}

/// Receives one uploaded file, enforcing the body limit as bytes arrive.
pub struct Sink {
    file: AsyncFile,
    part: UploadPart,
    written: u64,
    limit: u64,
    max_body: u64,
    telemetry: Arc<Telemetry>,
    transport: &'static str,
}

impl Sink {
    pub fn written(&self) -> u64 {
        self.written
    }

    pub async fn write(&mut self, data: &[u8]) -> Result<()> {
        self.written += data.len() as u64;
        self.telemetry.bytes_received(self.transport, data.len() as u64);
        if self.written > self.limit {
            return Err(Error::TooLarge(format!("the upload is over the limit of {} bytes", self.max_body)));
        }
        self.file.write_all(data).await.map_err(|e| Error::storage("cannot write the upload", &e))
    }

    async fn finish(self) -> Result<u64> {
        self.file.commit().await.map_err(|e| Error::storage("cannot store the upload", &e))?;
        Ok(self.written)
    }
}
