//! Storage health: whether the data directory can take the daemon's writes.
//!
//! Checked every `--storage-check-interval` and marked at once when a write fails for a
//! storage reason. The directory is healthy while it is still the one the daemon opened
//! (same device and inode: a directory moved or replaced underneath a running daemon
//! would otherwise split its database from its files), has at least `--min-free-bytes`
//! available, takes a small durable write, and its job database is open. While it is not,
//! `/readyz` and gRPC health say not serving with the reason, submissions get 503
//! `storage_full` / `storage_unavailable` with `Retry-After`, and workers claim no job;
//! jobs already accepted stay queued. The next check that passes (after the database is
//! reopened, if a write failed) makes the daemon ready again: no restart.
//!
//! Locking: a check takes no job-state lock; it only touches the disk and the `watch`
//! channel that publishes the result.

use std::os::unix::fs::MetadataExt;
use std::path::{Path, PathBuf};

use serde::Serialize;

use super::JobService;
use crate::error::Error;

/// The file the storage check writes and removes in `jobs/` to see that the data directory
/// takes writes (its atomic write's temporary file starts with the same name). Whoever
/// lists `jobs/` may find either there for a moment.
pub const HEALTH_PROBE: &str = ".health-probe";

/// Why the data directory cannot take writes now.
#[derive(Clone, Debug, PartialEq, Eq, Serialize)]
pub struct StorageProblem {
    /// `full`, `unavailable` or `moved`.
    pub kind: &'static str,
    pub reason: String,
}

impl StorageProblem {
    pub fn from_error(e: &Error) -> Option<StorageProblem> {
        let kind = e.storage_kind()?;
        Some(StorageProblem { kind, reason: e.to_string() })
    }

    /// The error a refused submission gets.
    pub fn error(&self) -> Error {
        Error::Storage {
            full: self.kind == "full",
            message: format!("not accepting jobs: {} (retry when the data directory is healthy)", self.reason),
        }
    }
}

/// Device and inode of a directory.
pub(super) fn identity(dir: &Path) -> std::io::Result<(u64, u64)> {
    let m = std::fs::metadata(dir)?;
    Ok((m.dev(), m.ino()))
}

/// Bytes available to unprivileged writers on the file system of `dir`.
fn available_bytes(dir: &Path) -> std::io::Result<u64> {
    let s = rustix::fs::statvfs(dir)?;
    Ok(s.f_bavail.saturating_mul(s.f_frsize))
}

/// One check of `root` against the identity it had at open and the free-space floor.
/// Returns the problem, if any, and the free bytes when they could be read.
pub(super) fn check(root: &Path, opened: (u64, u64), min_free: u64) -> (Option<StorageProblem>, Option<u64>) {
    let unavailable = |e: Error| {
        StorageProblem::from_error(&e).unwrap_or(StorageProblem { kind: "unavailable", reason: e.to_string() })
    };
    match identity(root) {
        Err(e) => return (Some(unavailable(Error::storage(&format!("data directory {}", root.display()), &e))), None),
        Ok(now) if now != opened => {
            return (
                Some(StorageProblem {
                    kind: "moved",
                    reason: format!(
                        "the data directory {} is not the one the daemon opened (moved, deleted or replaced); \
                         put it back, or restart the daemon",
                        root.display()
                    ),
                }),
                None,
            )
        }
        Ok(_) => {}
    }
    let free = available_bytes(root).ok();
    if let Some(free) = free.filter(|f| *f < min_free) {
        let reason =
            format!("{free} bytes free on the file system of {}, below --min-free-bytes {min_free}", root.display());
        return (Some(StorageProblem { kind: "full", reason }), Some(free));
    }
    let probe: PathBuf = root.join("jobs").join(HEALTH_PROBE);
    let written = crate::atomic::write(&probe, b"ok").and_then(|()| std::fs::remove_file(&probe));
    if let Err(e) = written {
        let _ = std::fs::remove_file(crate::atomic::part_path(&probe));
        return (Some(unavailable(Error::storage(&format!("test write in {}", root.display()), &e))), free);
    }
    (None, free)
}

impl JobService {
    /// The current storage problem, if any.
    pub fn storage_problem(&self) -> Option<StorageProblem> {
        self.inner.storage.borrow().clone()
    }

    pub fn subscribe_storage(&self) -> tokio::sync::watch::Receiver<Option<StorageProblem>> {
        self.inner.storage.subscribe()
    }

    /// Ready for new jobs: models loaded, not draining, storage healthy.
    pub fn is_ready(&self) -> bool {
        self.phase() == super::Phase::Ready && self.storage_problem().is_none()
    }

    /// Checks the data directory now (blocking I/O on tokio's blocking pool) and publishes
    /// the result; a database left unusable by a failed write is reopened first.
    pub async fn check_storage(&self) -> Option<StorageProblem> {
        let service = self.clone();
        let checked = tokio::task::spawn_blocking(move || {
            let s = &service.inner;
            let (mut problem, free) = check(s.store.root(), s.opened, s.settings.min_free_bytes);
            if problem.is_none() && s.shared.as_ref().is_some_and(|shared| !shared.connected()) {
                problem = Some(StorageProblem {
                    kind: "unavailable",
                    reason: "the shared store (NATS JetStream) is unreachable; reconnecting".into(),
                });
            }
            if problem.is_none() && service.storage_problem().is_some() && s.shared.is_none() {
                // Writes failed earlier: the database needs reopening before it takes more.
                if let Err(e) = s.store.reopen() {
                    problem = StorageProblem::from_error(&e)
                        .or(Some(StorageProblem { kind: "unavailable", reason: e.to_string() }));
                }
            }
            service.publish_storage(problem.clone(), free);
            problem
        })
        .await;
        checked.unwrap_or_else(|e| {
            Some(StorageProblem { kind: "unavailable", reason: format!("storage check failed: {e}") })
        })
    }

    /// Marks the storage unhealthy after a failed write (the next check clears it).
    pub(super) fn storage_failed(&self, e: &Error) {
        if let Some(problem) = StorageProblem::from_error(e) {
            self.publish_storage(Some(problem), None);
        }
    }

    fn publish_storage(&self, problem: Option<StorageProblem>, free: Option<u64>) {
        let inner = &self.inner;
        let changed = *inner.storage.borrow() != problem;
        if changed {
            match &problem {
                Some(p) => {
                    inner.telemetry.storage_error(p.kind);
                    tracing::error!(kind = p.kind, reason = %p.reason, "storage unhealthy: not ready, not accepting jobs");
                }
                None => tracing::info!("storage healthy again: accepting jobs"),
            }
            inner.storage.send_replace(problem.clone());
            inner.telemetry.set_ready(self.is_ready());
            inner.work.notify_all();
        }
        inner.telemetry.set_storage(problem.is_none(), free);
    }
}
