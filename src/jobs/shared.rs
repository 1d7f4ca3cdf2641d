//! Shared mode (`--store nats://…`): several daemons share one durable queue, job records
//! and files on NATS JetStream, so any replica answers for any job and a job whose replica
//! dies is finished by another.
//!
//! What lives where (names start with `--nats-prefix`, `mcdenoise` by default):
//!
//! ```text
//! stream  <PREFIX>_QUEUE     work queue, subjects <prefix>.queue.{high,normal,low}: one
//!                            message (the job id) per queued job, one durable pull consumer
//!                            per priority; the message is acknowledged when the job ends
//! KV      <PREFIX>_jobs      one record per job (key = job id), written with compare-and-set
//! KV      <PREFIX>_keys      idempotency keys (key = SHA-256 of client + key) → job id
//! KV      <PREFIX>_leases    short-lived keys: who runs the retention sweep this round
//! objects <PREFIX>_files     <id>/input.exr, reference.exr, result.exr and the preview sources
//! subject <prefix>.progress.<id>   tile progress (plain NATS, not stored)
//! ```
//!
//! Each replica keeps the whole set of records in memory, as the embedded mode does (the
//! core's `State`), fed by a watch of the jobs bucket: reads (status, lists, events, the
//! queue positions and the admission limits) are answered from memory; every durable change
//! is a compare-and-set on the record's revision, so two replicas never both move a job
//! out of the same state. A worker claims a job by taking its message from JetStream and
//! moving its record from queued to running; while the job's tiles progress it tells
//! JetStream it is still working, which extends the ack deadline (`--nats-ack-wait`). If the
//! replica dies, the message is delivered again after that deadline and another replica runs
//! the job from its stored input; a run that finds the record already final only
//! acknowledges the message, so each job ends exactly once. The local data directory is a
//! scratch cache of the files.
//!
//! Locking: the methods here do network I/O and block the calling thread (a worker's or
//! tokio's blocking pool, never an async task); none is called with the core's state lock
//! held.

use std::collections::HashMap;
use std::path::Path;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use async_nats::jetstream::{self, consumer::pull, kv, object_store, stream, AckKind};
use futures_util::StreamExt;
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use tokio::io::AsyncWriteExt;

use super::record::{JobRecord, Priority, Progress};
use crate::error::{Error, Result};

/// How long one NATS request may take before it counts as failed.
const REQUEST_TIMEOUT: Duration = Duration::from_secs(10);

/// How long storing or fetching one file may take.
const TRANSFER_TIMEOUT: Duration = Duration::from_secs(600);

/// How the daemon reaches JetStream (`serve --store nats://… --nats-*`).
#[derive(Clone, Debug)]
pub struct SharedConfig {
    /// One or more server URLs, comma-separated (`nats://user:pass@host:4222,...`).
    pub servers: String,
    /// Replicas of the stream, buckets and object store (a clustered NATS: 3).
    pub replicas: usize,
    /// How long a job's message waits for a heartbeat before it is delivered again.
    pub ack_wait: Duration,
    /// Prefix of the stream, bucket and subject names.
    pub prefix: String,
}

/// A record as kept in the jobs bucket: who wrote it, so a replica's watch skips the
/// events of its own writes (it sent them itself).
#[derive(Serialize, Deserialize)]
struct Stored {
    writer: String,
    record: JobRecord,
}

/// A change to the jobs bucket, as the watch delivers it.
pub enum Change {
    Put { record: Box<JobRecord>, own: bool },
    Deleted { id: String, revision: u64 },
}

/// A job message this replica holds: acknowledged when the job ends, kept alive meanwhile.
struct Held {
    message: jetstream::Message,
    last_beat: Instant,
}

pub struct Shared {
    rt: tokio::runtime::Handle,
    client: async_nats::Client,
    js: jetstream::Context,
    jobs: kv::Store,
    keys: kv::Store,
    leases: kv::Store,
    files: object_store::ObjectStore,
    stream_name: String,
    consumers: Vec<(Priority, jetstream::consumer::PullConsumer)>,
    prefix: String,
    /// This process (host, pid and a random part): the `writer` of its records.
    replica: String,
    ack_wait: Duration,
    held: Mutex<HashMap<String, Held>>,
}

/// A NATS failure as the core classifies it: the shared store is unavailable.
fn unavailable(context: &str, e: impl std::fmt::Display) -> Error {
    Error::Storage { full: false, message: format!("shared store (NATS JetStream): {context}: {e}") }
}

/// How often creating a stream, bucket, consumer or object store is tried.
const CREATE_ATTEMPTS: u32 = 6;

/// Gets or creates a stream, bucket, consumer or object store, trying again after a
/// failure (50 ms, doubling). Replicas that start together race to create the same thing,
/// and the server answers the losers with an error ("subjects overlap with an existing
/// stream", "already in use") although it now exists: the next attempt finds it. The last
/// failure is reported as `what`.
async fn get_or_create<T, E, F>(what: &str, mut attempt: impl FnMut() -> F) -> Result<T>
where
    E: std::fmt::Display,
    F: std::future::Future<Output = std::result::Result<T, E>>,
{
    let mut delay = Duration::from_millis(50);
    for _ in 1..CREATE_ATTEMPTS {
        match attempt().await {
            Ok(made) => return Ok(made),
            Err(e) => tracing::debug!(error = %e, "{what}; trying again"),
        }
        tokio::time::sleep(delay).await;
        delay *= 2;
    }
    attempt().await.map_err(|e| unavailable(what, e))
}

/// The idempotency key's name in the keys bucket (KV keys allow only a few characters).
pub(crate) fn key_name(scoped: &str) -> String {
    let digest = Sha256::digest(scoped.as_bytes());
    digest.iter().map(|b| format!("{b:02x}")).collect()
}

impl Shared {
    /// Connects (waiting at most `wait` for the first connection) and creates the stream,
    /// buckets and consumers that do not exist yet. Async: called once at startup.
    pub async fn connect(config: &SharedConfig, wait: Duration) -> Result<Shared> {
        let what = format!("cannot reach {}", redact(&config.servers));
        let options = async_nats::ConnectOptions::new()
            .name("mcdenoise")
            .retry_on_initial_connect()
            .request_timeout(Some(REQUEST_TIMEOUT))
            .event_callback(|event| async move {
                match event {
                    async_nats::Event::Disconnected => tracing::warn!("NATS connection lost; reconnecting"),
                    async_nats::Event::Connected => tracing::info!("NATS connected"),
                    other => tracing::debug!(event = %other, "NATS event"),
                }
            });
        let servers: Vec<async_nats::ServerAddr> = config
            .servers
            .split(',')
            .map(|s| s.trim().parse())
            .collect::<std::result::Result<_, _>>()
            .map_err(|e| Error::BadRequest(format!("--store: {e}")))?;
        let client = options.connect(servers).await.map_err(|e| unavailable(&what, e))?;
        let deadline = Instant::now() + wait;
        while client.connection_state() != async_nats::connection::State::Connected {
            if Instant::now() > deadline {
                return Err(unavailable(&what, format!("no connection after {wait:?}")));
            }
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
        let js = jetstream::new(client.clone());
        let p = &config.prefix;
        let replicas = config.replicas;
        let stream_name = format!("{}_QUEUE", p.to_uppercase());
        let queue = stream::Config {
            name: stream_name.clone(),
            subjects: vec![format!("{p}.queue.*")],
            retention: stream::RetentionPolicy::WorkQueue,
            storage: stream::StorageType::File,
            num_replicas: replicas,
            duplicate_window: Duration::from_secs(120),
            ..Default::default()
        };
        let stream = get_or_create("cannot create the queue stream", || js.get_or_create_stream(queue.clone())).await?;
        let mut consumers = Vec::new();
        for priority in Priority::ALL {
            let name = format!("{}_{}", p.to_uppercase(), priority.name());
            let config = pull::Config {
                durable_name: Some(name.clone()),
                filter_subject: format!("{p}.queue.{}", priority.name()),
                ack_policy: jetstream::consumer::AckPolicy::Explicit,
                ack_wait: config.ack_wait,
                max_deliver: -1,
                num_replicas: replicas,
                ..Default::default()
            };
            let consumer = get_or_create(&format!("cannot create the consumer {name}"), || {
                stream.get_or_create_consumer(&name, config.clone())
            })
            .await?;
            consumers.push((priority, consumer));
        }
        // The buckets' streams are made here with the settings a key-value bucket has
        // (what `create_key_value` would make): that call asks for account details that
        // servers before 2.10 do not send.
        let open_kv = |bucket: String, max_age: Duration| {
            let js = js.clone();
            async move {
                let config = stream::Config {
                    name: format!("KV_{bucket}"),
                    subjects: vec![format!("$KV.{bucket}.>")],
                    max_messages_per_subject: 1,
                    max_age,
                    storage: stream::StorageType::File,
                    num_replicas: replicas,
                    allow_rollup: true,
                    deny_delete: true,
                    allow_direct: true,
                    discard: stream::DiscardPolicy::New,
                    ..Default::default()
                };
                get_or_create(&format!("cannot create the bucket {bucket}"), || {
                    js.get_or_create_stream(config.clone())
                })
                .await?;
                js.get_key_value(&bucket).await.map_err(|e| unavailable(&format!("cannot open the bucket {bucket}"), e))
            }
        };
        let jobs = open_kv(format!("{p}_jobs"), Duration::ZERO).await?;
        let keys = open_kv(format!("{p}_keys"), Duration::ZERO).await?;
        let leases = open_kv(format!("{p}_leases"), LEASE).await?;
        let files_name = format!("{p}_files");
        let files = get_or_create(&format!("cannot create the object store {files_name}"), || async {
            match js.get_object_store(&files_name).await {
                Ok(store) => Ok(store),
                Err(_) => js
                    .create_object_store(object_store::Config {
                        bucket: files_name.clone(),
                        storage: stream::StorageType::File,
                        num_replicas: replicas,
                        ..Default::default()
                    })
                    .await
                    .map_err(|e| e.to_string()),
            }
        })
        .await?;
        let host = std::env::var("HOSTNAME")
            .ok()
            .or_else(|| std::fs::read_to_string("/etc/hostname").ok())
            .map(|h| h.trim().to_string())
            .filter(|h| !h.is_empty())
            .unwrap_or_else(|| "replica".into());
        let replica = format!("{host}/{}/{}", std::process::id(), &uuid::Uuid::now_v7().simple().to_string()[24..]);
        tracing::info!(servers = %redact(&config.servers), prefix = %p, replica = %replica, "shared store on NATS JetStream");
        Ok(Shared {
            rt: tokio::runtime::Handle::current(),
            client,
            js,
            jobs,
            keys,
            leases,
            files,
            stream_name,
            consumers,
            prefix: p.clone(),
            replica,
            ack_wait: config.ack_wait,
            held: Mutex::new(HashMap::new()),
        })
    }

    /// Runs a NATS exchange to completion on the runtime from a blocking thread, failing it
    /// after `limit` (a request in flight when the connection drops may never be answered).
    fn block<T>(&self, limit: Duration, f: impl std::future::Future<Output = Result<T>>) -> Result<T> {
        self.rt.block_on(async {
            tokio::time::timeout(limit, f)
                .await
                .unwrap_or_else(|_| Err(unavailable("no answer", format!("after {limit:?}"))))
        })
    }

    /// [`Shared::block`] for what may fail without consequence (acknowledgements, clean-ups).
    fn block_quietly<T>(&self, f: impl std::future::Future<Output = T>) {
        let _ = self.block(REQUEST_TIMEOUT, async {
            f.await;
            Ok(())
        });
    }

    pub fn connected(&self) -> bool {
        self.client.connection_state() == async_nats::connection::State::Connected
    }

    // --- Records -----------------------------------------------------------------------

    fn encode(&self, record: &JobRecord) -> Result<bytes::Bytes> {
        let stored = Stored { writer: self.replica.clone(), record: record.clone() };
        serde_json::to_vec(&stored).map(Into::into).map_err(|e| Error::internal("cannot encode a job record", e))
    }

    /// Writes `record` if the stored one is still the version it was made from (its `rev`,
    /// the bucket's revision; 0: a new job), and sets `rev` to the new revision. A record
    /// changed by another replica meanwhile is a [`Error::Conflict`]. Blocking.
    pub fn put(&self, record: &mut JobRecord) -> Result<()> {
        let value = self.encode(record)?;
        let id = record.id.clone();
        let expected = record.rev;
        let written = self.block(REQUEST_TIMEOUT, async {
            if expected == 0 {
                self.jobs.create(&id, value).await.map_err(|e| match e.kind() {
                    kv::CreateErrorKind::AlreadyExists => conflict(&id),
                    _ => unavailable("cannot write a job record", e),
                })
            } else {
                self.jobs.update(&id, value, expected).await.map_err(|e| match e.kind() {
                    kv::UpdateErrorKind::WrongLastRevision => conflict(&id),
                    _ => unavailable("cannot write a job record", e),
                })
            }
        })?;
        record.rev = written;
        Ok(())
    }

    /// The stored record of `id` (its `rev` set), `None` if there is none. Blocking.
    pub fn get(&self, id: &str) -> Result<Option<JobRecord>> {
        let entry = self.block(REQUEST_TIMEOUT, async {
            self.jobs.entry(id).await.map_err(|e| unavailable("cannot read a job record", e))
        })?;
        match entry {
            Some(e) if matches!(e.operation, kv::Operation::Put) => Ok(Some(decode(&e.value, e.revision)?.0)),
            _ => Ok(None),
        }
    }

    /// Removes the records, idempotency keys and files of jobs (`(id, scoped key)`). Blocking.
    pub fn remove(&self, jobs: &[(&str, Option<String>)]) -> Result<()> {
        self.block(REQUEST_TIMEOUT, async {
            for (id, key) in jobs {
                self.jobs.purge(*id).await.map_err(|e| unavailable("cannot remove a job record", e))?;
                if let Some(key) = key {
                    let _ = self.keys.purge(key_name(key)).await;
                }
            }
            Ok::<_, Error>(())
        })?;
        for (id, _) in jobs {
            self.remove_files(id);
        }
        Ok(())
    }

    /// Every stored record, for the start of the watch. Async.
    pub async fn load_all(&self) -> Result<Vec<JobRecord>> {
        let mut keys = self.jobs.keys().await.map_err(|e| unavailable("cannot list the job records", e))?;
        let mut ids = Vec::new();
        while let Some(key) = keys.next().await {
            ids.push(key.map_err(|e| unavailable("cannot list the job records", e))?);
        }
        let mut records = Vec::with_capacity(ids.len());
        for id in ids {
            match self.jobs.entry(id.as_str()).await {
                Ok(Some(e)) if matches!(e.operation, kv::Operation::Put) => match decode(&e.value, e.revision) {
                    Ok((r, _)) => records.push(r),
                    Err(err) => {
                        tracing::error!(job_id = id.as_str(), error = %err, "a shared job record cannot be decoded")
                    }
                },
                Ok(_) => {}
                Err(e) => return Err(unavailable("cannot read a job record", e)),
            }
        }
        Ok(records)
    }

    /// The jobs bucket's last revision and the ids of every job stored now (read after
    /// it), for the periodic check of the watch. Blocking.
    pub fn stored_ids(&self) -> Result<(u64, std::collections::HashSet<String>)> {
        self.block(REQUEST_TIMEOUT, async {
            let name = format!("KV_{}_jobs", self.prefix);
            let mut stream =
                self.js.get_stream(&name).await.map_err(|e| unavailable("cannot read the job records", e))?;
            let last =
                stream.info().await.map_err(|e| unavailable("cannot read the job records", e))?.state.last_sequence;
            let mut keys = self.jobs.keys().await.map_err(|e| unavailable("cannot list the job records", e))?;
            let mut ids = std::collections::HashSet::new();
            while let Some(key) = keys.next().await {
                ids.insert(key.map_err(|e| unavailable("cannot list the job records", e))?);
            }
            Ok((last, ids))
        })
    }

    /// Changes to the jobs bucket from now on (every replica's, this one's marked `own`).
    /// Async.
    pub async fn watch(&self) -> Result<impl futures_util::Stream<Item = Change> + Send + 'static> {
        let watch = self.jobs.watch_all().await.map_err(|e| unavailable("cannot watch the job records", e))?;
        let me = self.replica.clone();
        Ok(watch.filter_map(move |entry| {
            let me = me.clone();
            async move {
                let entry = match entry {
                    Ok(entry) => entry,
                    Err(e) => {
                        tracing::warn!(error = %e, "watch of the shared job records");
                        return None;
                    }
                };
                match entry.operation {
                    kv::Operation::Put => match decode(&entry.value, entry.revision) {
                        Ok((record, writer)) => Some(Change::Put { own: writer == me, record: Box::new(record) }),
                        Err(e) => {
                            tracing::error!(job_id = entry.key.as_str(), error = %e, "a shared job record cannot be decoded");
                            None
                        }
                    },
                    kv::Operation::Delete | kv::Operation::Purge => {
                        Some(Change::Deleted { id: entry.key, revision: entry.revision })
                    }
                }
            }
        }))
    }

    // --- Idempotency keys --------------------------------------------------------------

    /// Claims the scoped idempotency key for job `id`. `Some(other)` if it belongs to
    /// another job that still exists. Blocking.
    pub fn claim_key(&self, scoped: &str, id: &str) -> Result<Option<String>> {
        let name = key_name(scoped);
        self.block(REQUEST_TIMEOUT, async {
            loop {
                match self.keys.create(&name, id.to_string().into()).await {
                    Ok(_) => return Ok(None),
                    Err(e) if e.kind() == kv::CreateErrorKind::AlreadyExists => {}
                    Err(e) => return Err(unavailable("cannot write an idempotency key", e)),
                }
                let Some(entry) = self
                    .keys
                    .entry(name.as_str())
                    .await
                    .map_err(|e| unavailable("cannot read an idempotency key", e))?
                else {
                    continue;
                };
                let other = String::from_utf8_lossy(&entry.value).into_owned();
                let alive = matches!(
                    self.jobs.entry(other.as_str()).await,
                    Ok(Some(ref e)) if matches!(e.operation, kv::Operation::Put)
                );
                if alive {
                    return Ok(Some(other));
                }
                // Left by a submission that never completed: take it over.
                match self.keys.update(&name, id.to_string().into(), entry.revision).await {
                    Ok(_) => return Ok(None),
                    Err(e) if e.kind() == kv::UpdateErrorKind::WrongLastRevision => continue,
                    Err(e) => return Err(unavailable("cannot write an idempotency key", e)),
                }
            }
        })
    }

    // --- The queue -----------------------------------------------------------------------

    fn subject(&self, priority: Priority) -> String {
        format!("{}.queue.{}", self.prefix, priority.name())
    }

    /// Puts job `id` on the work queue (deduplicated by id for two minutes). Blocking.
    pub fn publish(&self, id: &str, priority: Priority) -> Result<()> {
        let mut headers = async_nats::HeaderMap::new();
        headers.insert("Nats-Msg-Id", id);
        self.block(REQUEST_TIMEOUT, async {
            let ack = self
                .js
                .publish_with_headers(self.subject(priority), headers, id.to_string().into())
                .await
                .map_err(|e| unavailable("cannot queue the job", e))?;
            ack.await.map_err(|e| unavailable("cannot queue the job", e))?;
            Ok(())
        })
    }

    /// Takes the next job message, highest priority first, without waiting; the job id.
    /// The message is held until [`Shared::ack`] or [`Shared::nak`]. Blocking.
    pub fn take(&self) -> Result<Option<String>> {
        let message = self.block(REQUEST_TIMEOUT, async {
            for (_, consumer) in &self.consumers {
                let mut batch = consumer
                    .fetch()
                    .max_messages(1)
                    .messages()
                    .await
                    .map_err(|e| unavailable("cannot read the queue", e))?;
                if let Some(message) = batch.next().await {
                    return message.map(Some).map_err(|e| unavailable("cannot read the queue", e));
                }
            }
            Ok(None)
        })?;
        let Some(message) = message else { return Ok(None) };
        let id = String::from_utf8_lossy(&message.payload).into_owned();
        let mut held = self.held.lock().unwrap_or_else(super::lock_poisoned);
        if held.insert(id.clone(), Held { message, last_beat: Instant::now() }).is_some() {
            // Delivered again to the replica that still runs it (its heartbeats came too
            // late): the run goes on, answering through the newer delivery.
            return Ok(None);
        }
        Ok(Some(id))
    }

    /// Whether this replica holds job `id`'s message (it runs the job).
    pub fn holds(&self, id: &str) -> bool {
        self.held.lock().unwrap_or_else(super::lock_poisoned).contains_key(id)
    }

    /// Tells JetStream the job is still being worked on (at most once a second), which
    /// extends its ack deadline. Does not block.
    pub fn heartbeat(&self, id: &str) {
        let mut held = self.held.lock().unwrap_or_else(super::lock_poisoned);
        let Some(h) = held.get_mut(id) else { return };
        if h.last_beat.elapsed() < Duration::from_secs(1).min(self.ack_wait / 3) {
            return;
        }
        h.last_beat = Instant::now();
        let reply = h.message.reply.clone();
        let client = self.client.clone();
        self.rt.spawn(async move {
            if let Some(reply) = reply {
                let _ = client.publish(reply, AckKind::Progress.into()).await;
            }
        });
    }

    /// The job ended here: its message goes (waits for the server's confirmation). Blocking.
    pub fn ack(&self, id: &str) {
        let held = self.held.lock().unwrap_or_else(super::lock_poisoned).remove(id);
        if let Some(h) = held {
            let acked = self.block(REQUEST_TIMEOUT, async {
                h.message.double_ack().await.map_err(|e| unavailable("cannot acknowledge", e))
            });
            if let Err(e) = acked {
                tracing::warn!(job_id = id, error = %e, "cannot acknowledge the job's message; it may be delivered again (and only acknowledged then)");
            }
        }
    }

    /// The job goes back to the queue (after `delay`) for any replica. Blocking.
    pub fn nak(&self, id: &str, delay: Option<Duration>) {
        let held = self.held.lock().unwrap_or_else(super::lock_poisoned).remove(id);
        if let Some(h) = held {
            self.block_quietly(h.message.ack_with(AckKind::Nak(delay)));
        }
    }

    /// Forgets the message of a run that lost its job to another replica (neither acked nor
    /// nakked: the message belongs to the other run now).
    pub fn forget(&self, id: &str) {
        self.held.lock().unwrap_or_else(super::lock_poisoned).remove(id);
    }

    /// Job messages in the work queue (waiting or being worked on). Blocking.
    pub fn queue_messages(&self) -> Result<u64> {
        self.block(REQUEST_TIMEOUT, async {
            let mut stream =
                self.js.get_stream(&self.stream_name).await.map_err(|e| unavailable("cannot read the queue", e))?;
            let info = stream.info().await.map_err(|e| unavailable("cannot read the queue", e))?;
            Ok(info.state.messages)
        })
    }

    // --- Progress ------------------------------------------------------------------------

    fn progress_subject(&self, id: &str) -> String {
        format!("{}.progress.{id}", self.prefix)
    }

    /// Tells the other replicas' watchers how far job `id` is. Does not block.
    pub fn publish_progress(&self, id: &str, progress: Progress) {
        let Ok(body) = serde_json::to_vec(&(&self.replica, progress)) else { return };
        let client = self.client.clone();
        let subject = self.progress_subject(id);
        self.rt.spawn(async move {
            let _ = client.publish(subject, body.into()).await;
        });
    }

    /// Progress of jobs run by other replicas: (job id, progress). Async.
    pub async fn progress_updates(
        &self,
    ) -> Result<impl futures_util::Stream<Item = (String, Progress)> + Send + 'static> {
        let prefix = format!("{}.progress.", self.prefix);
        let sub = self
            .client
            .subscribe(format!("{prefix}*"))
            .await
            .map_err(|e| unavailable("cannot subscribe to progress", e))?;
        let me = self.replica.clone();
        Ok(sub.filter_map(move |message| {
            let parsed = serde_json::from_slice::<(String, Progress)>(&message.payload).ok();
            let id = message.subject.as_str().strip_prefix(&prefix).map(str::to_string);
            let me = me.clone();
            async move {
                match (id, parsed) {
                    (Some(id), Some((writer, progress))) if writer != me => Some((id, progress)),
                    _ => None,
                }
            }
        }))
    }

    // --- Leases --------------------------------------------------------------------------

    /// True for the one replica that holds lease `name`: it takes the lease when nobody
    /// holds it and renews it while it does; a holder that stops renewing loses it
    /// [`LEASE`] later. Blocking.
    pub fn take_lease(&self, name: &str) -> bool {
        let me: bytes::Bytes = self.replica.clone().into();
        let held = self.block(REQUEST_TIMEOUT, async {
            if self.leases.create(name, me.clone()).await.is_ok() {
                return Ok(true);
            }
            Ok(match self.leases.entry(name).await {
                Ok(Some(e)) if matches!(e.operation, kv::Operation::Put) && e.value == me => {
                    self.leases.update(name, me, e.revision).await.is_ok()
                }
                _ => false,
            })
        });
        held.unwrap_or(false)
    }

    // --- Files ---------------------------------------------------------------------------

    /// Stores a local file as object `<id>/<name>`. Blocking.
    pub fn upload(&self, id: &str, name: &str, path: &Path) -> Result<()> {
        self.block(TRANSFER_TIMEOUT, async {
            let mut file = tokio::fs::File::open(path)
                .await
                .map_err(|e| Error::storage(&format!("cannot read {}", path.display()), &e))?;
            self.files
                .put(format!("{id}/{name}").as_str(), &mut file)
                .await
                .map_err(|e| unavailable(&format!("cannot store {name}"), e))?;
            Ok(())
        })
    }

    /// Copies object `<id>/<name>` to `path` (atomically). `false` if there is no such
    /// object. Blocking.
    pub fn download(&self, id: &str, name: &str, path: &Path) -> Result<bool> {
        self.block(TRANSFER_TIMEOUT, async {
            let mut object = match self.files.get(format!("{id}/{name}")).await {
                Ok(object) => object,
                Err(e) if e.kind() == object_store::GetErrorKind::NotFound => return Ok(false),
                Err(e) => return Err(unavailable(&format!("cannot read {name}"), e)),
            };
            if let Some(dir) = path.parent() {
                tokio::fs::create_dir_all(dir)
                    .await
                    .map_err(|e| Error::storage(&format!("cannot create {}", dir.display()), &e))?;
            }
            let part = crate::atomic::part_path(path);
            let mut file = tokio::fs::File::create(&part)
                .await
                .map_err(|e| Error::storage(&format!("cannot write {}", part.display()), &e))?;
            let copied = tokio::io::copy(&mut object, &mut file).await;
            let done = match copied {
                Ok(_) => file.flush().await.map_err(|e| Error::storage("cannot write a downloaded file", &e)),
                Err(e) => Err(unavailable(&format!("cannot read {name}"), e)),
            };
            drop(file);
            if let Err(e) = done.and_then(|()| {
                std::fs::rename(&part, path).map_err(|e| Error::storage("cannot place a downloaded file", &e))
            }) {
                let _ = std::fs::remove_file(&part);
                return Err(e);
            }
            Ok(true)
        })
    }

    /// Removes a finished job's uploaded frames (its result and preview sources stay).
    /// Blocking.
    pub fn remove_inputs(&self, id: &str) {
        self.block_quietly(async {
            for name in ["input.exr", "reference.exr"] {
                let _ = self.files.delete(format!("{id}/{name}")).await;
            }
        })
    }

    fn remove_files(&self, id: &str) {
        self.block_quietly(async {
            for name in FILES {
                let _ = self.files.delete(format!("{id}/{name}")).await;
            }
        })
    }
}

/// The files a job may have in the object store.
pub(crate) const FILES: [&str; 5] =
    ["input.exr", "reference.exr", "result.exr", "preview-input.exr", "preview-reference.exr"];

/// How long the retention sweep's lease lasts: one replica sweeps per period.
pub(crate) const LEASE: Duration = Duration::from_secs(20);

fn conflict(id: &str) -> Error {
    Error::Conflict(format!("job {id} was changed by another replica"))
}

fn decode(value: &[u8], revision: u64) -> Result<(JobRecord, String)> {
    let stored: Stored =
        serde_json::from_slice(value).map_err(|e| Error::internal("cannot decode a shared job record", e))?;
    let mut record = stored.record;
    record.rev = revision;
    Ok((record, stored.writer))
}

/// The server list without passwords or tokens, for logs and errors.
pub(crate) fn redact(servers: &str) -> String {
    servers
        .split(',')
        .map(|s| match (s.find("://"), s.rfind('@')) {
            (Some(scheme), Some(at)) if at > scheme => format!("{}://***@{}", &s[..scheme], &s[at + 1..]),
            _ => s.to_string(),
        })
        .collect::<Vec<_>>()
        .join(",")
}

/// Keeps `Arc<Shared>` names short in the core.
pub(crate) type SharedRef = Arc<Shared>;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn server_lists_are_logged_without_credentials() {
        assert_eq!(redact("nats://a:secret@h1:4222,nats://h2:4222"), "nats://***@h1:4222,nats://h2:4222");
        assert_eq!(redact("nats://tok@h"), "nats://***@h");
    }

    #[test]
    fn idempotency_key_names_are_valid_kv_keys_and_differ_per_client() {
        let a = key_name("client-a f0001");
        assert_eq!(a.len(), 64);
        assert!(a.chars().all(|c| c.is_ascii_hexdigit()));
        assert_ne!(a, key_name("client-b f0001"));
    }
}
