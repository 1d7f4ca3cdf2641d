//! The one error type of the daemon's core, shared by both transports.
//!
//! Each transport maps it with an exhaustive `match` (no catch-all arm), so a new variant
//! cannot be added without deciding its HTTP status and its gRPC code:
//! `http::error` and `grpc::status`. The table is repeated in `docs/api.md`.
//!
//! | variant | HTTP | gRPC |
//! |---|---|---|
//! | `BadRequest` | 400 | INVALID_ARGUMENT |
//! | `InvalidFrame` | 422 | INVALID_ARGUMENT |
//! | `TooLarge` | 413 | INVALID_ARGUMENT |
//! | `Timeout` | 408 | DEADLINE_EXCEEDED |
//! | `Unauthenticated` | 401 | UNAUTHENTICATED |
//! | `Forbidden` | 403 | PERMISSION_DENIED |
//! | `NotFound` | 404 | NOT_FOUND |
//! | `Conflict` | 409 | FAILED_PRECONDITION |
//! | `InProgress` | 409 | ABORTED |
//! | `QueueFull` | 429 + `Retry-After` | RESOURCE_EXHAUSTED + `retry-after` |
//! | `ClientLimit` | 429 + `Retry-After` | RESOURCE_EXHAUSTED + `retry-after` |
//! | `Unavailable` | 503 | UNAVAILABLE |
//! | `Storage` | 503 + `Retry-After` (`storage_full`, `storage_unavailable`) | UNAVAILABLE |
//! | `Internal` | 500 | INTERNAL |

use crate::frame::FrameError;

/// Why a request could not be served.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// The request itself is malformed: unknown option, bad JSON, bad chunk order.
    #[error("{0}")]
    BadRequest(String),
    /// The frame (or reference) is not usable; the message names the channel or field.
    #[error("{0}")]
    InvalidFrame(String),
    /// Body or frame over a configured limit.
    #[error("{0}")]
    TooLarge(String),
    /// An upload stopped sending for longer than `--upload-timeout`.
    #[error("{0}")]
    Timeout(String),
    #[error("{0}")]
    Unauthenticated(String),
    /// The token is valid but its scope does not cover the route (`/metrics` for a
    /// `submit` token when operator tokens are configured).
    #[error("{0}")]
    Forbidden(String),
    #[error("{0}")]
    NotFound(String),
    /// The job is not in a state that allows the operation (e.g. fetching the result of a
    /// job that has not succeeded, cancelling a finished job).
    #[error("{0}")]
    Conflict(String),
    /// A submission with the same idempotency key is still being uploaded.
    #[error("{0}")]
    InProgress(String),
    /// The queue is at capacity; retry after `retry_after_s` seconds.
    #[error("the queue is full ({capacity} jobs); retry in {retry_after_s} s")]
    QueueFull { capacity: usize, retry_after_s: u64 },
    /// This client has reached its own share (concurrent uploads or unfinished jobs);
    /// retry after `retry_after_s` seconds.
    #[error("{message}")]
    ClientLimit { message: String, retry_after_s: u64 },
    /// Not ready (models loading) or draining for shutdown.
    #[error("{0}")]
    Unavailable(String),
    /// The data directory cannot take the write: its disk is full (`full`), or it is
    /// read-only, gone, not writable or failing. Not the request's fault; retry later.
    #[error("{message}")]
    Storage { full: bool, message: String },
    /// A bug or an I/O failure on the daemon's side. The message is logged in full and
    /// returned to clients (it names no secret: paths under the data directory at most).
    #[error("internal error: {0}")]
    Internal(String),
}

impl Error {
    /// Stable machine-readable code, used in JSON error bodies.
    pub fn code(&self) -> &'static str {
        match self {
            Error::BadRequest(_) => "bad_request",
            Error::InvalidFrame(_) => "invalid_frame",
            Error::TooLarge(_) => "too_large",
            Error::Timeout(_) => "timeout",
            Error::Unauthenticated(_) => "unauthenticated",
            Error::Forbidden(_) => "forbidden",
            Error::NotFound(_) => "not_found",
            Error::Conflict(_) => "conflict",
            Error::InProgress(_) => "in_progress",
            Error::QueueFull { .. } => "queue_full",
            Error::ClientLimit { .. } => "client_limit",
            Error::Unavailable(_) => "unavailable",
            Error::Storage { full: true, .. } => "storage_full",
            Error::Storage { full: false, .. } => "storage_unavailable",
            Error::Internal(_) => "internal",
        }
    }

    /// An I/O error of the data directory, by its cause: a full disk or quota is
    /// `storage_full`; a read-only file system, a permission refused, a missing directory
    /// or a device error is `storage_unavailable` (each named in the message); anything
    /// else is internal.
    pub fn storage(context: &str, e: &std::io::Error) -> Error {
        use std::io::ErrorKind as K;
        let cause = match e.kind() {
            K::StorageFull | K::QuotaExceeded => Some((true, "no space left on the device")),
            K::ReadOnlyFilesystem => Some((false, "the file system is read-only")),
            K::PermissionDenied => Some((false, "permission denied")),
            K::NotFound | K::NotADirectory => Some((false, "the path is gone (was the data directory moved?)")),
            K::StaleNetworkFileHandle => Some((false, "stale network file handle")),
            _ if e.raw_os_error() == Some(5) => Some((false, "input/output error from the device")),
            _ => None,
        };
        match cause {
            Some((full, why)) => Error::Storage { full, message: format!("{context}: {why} ({e})") },
            None => Error::Internal(format!("{context}: {e}")),
        }
    }

    /// The kind label of a storage error in metrics, `None` for other errors.
    pub fn storage_kind(&self) -> Option<&'static str> {
        match self {
            Error::Storage { full: true, .. } => Some("full"),
            Error::Storage { full: false, .. } => Some("unavailable"),
            _ => None,
        }
    }

    pub fn internal(context: &str, e: impl std::fmt::Display) -> Error {
        Error::Internal(format!("{context}: {e}"))
    }

    /// Prefixes the message of a frame error with which upload it concerns.
    pub fn frame(which: &str, e: FrameError) -> Error {
        match e {
            FrameError::TooLarge { .. } => Error::TooLarge(format!("{which}: {e}")),
            other => Error::InvalidFrame(format!("{which}: {other}")),
        }
    }
}

pub type Result<T, E = Error> = std::result::Result<T, E>;

/// At most `max` characters of `s`, with `…` when cut: for client-supplied strings (job
/// ids, page tokens, part names) echoed in error messages.
pub fn truncate(s: &str, max: usize) -> std::borrow::Cow<'_, str> {
    match s.char_indices().nth(max) {
        None => s.into(),
        Some((at, _)) => format!("{}…", &s[..at]).into(),
    }
}

/// How much of a client-supplied string an error message echoes.
pub const ECHO_CHARS: usize = 64;

/// The message of a caught panic.
pub fn panic_message(panic: &(dyn std::any::Any + Send)) -> String {
    match (panic.downcast_ref::<&str>(), panic.downcast_ref::<String>()) {
        (Some(s), _) => s.to_string(),
        (_, Some(s)) => s.clone(),
        _ => "unknown panic".into(),
    }
}
