//! The connections of both listeners: accepting, TLS, timeouts, graceful shutdown.
//!
//! Each accepted connection runs in its own task, from its first byte to its last: a
//! client that stalls holds up only its own task (there is no shared pool of handshakes
//! or connections for strangers to fill). A connection is bounded at every stage:
//!
//! | stage | bound | flag |
//! |---|---|---|
//! | TLS handshake | dropped when not done in time | `--tls-handshake-timeout` |
//! | HTTP/1 request head | closed when not complete in time, counted from when the connection is ready for a request (so it also closes idle keep-alive connections) | `--header-timeout` |
//! | any connection, HTTP/1, HTTP/2 or gRPC | no byte read or written for this long: asked to close (in-flight requests finish), then dropped after as long again | `--idle-timeout` |
//! | HTTP/2 and gRPC peers | a PING every interval, closed when unanswered | `--keepalive-interval`, `--keepalive-timeout` |
//! | upload bodies | no byte for this long: refused with 408 / DEADLINE_EXCEEDED, its slot released | `--upload-timeout` (in `http` and `grpc`) |
//!
//! Connections are counted, in total and per peer address, over both API listeners
//! ([`Admission`]): past `--max-connections` or `--max-connections-per-peer` a new
//! connection is closed at once, before any byte is read, and counted in
//! `mcdenoise_connections_refused_total{reason}`. The total is kept below the process's
//! file limit (raised to its hard maximum at start, [`raise_file_limit`]), so a flood
//! cannot use up the descriptors the job store and the probes need. The optional probe
//! listener (`--probe-http`) has an admission of its own: a flood of the API ports does
//! not reach it.
//!
//! Shutdown: when `shutdown` is cancelled the accept loop stops and every connection is
//! asked to close gracefully; [`serve`] returns once all have. Dropping (aborting) the
//! future of [`serve`] drops every connection at once.

use std::collections::HashMap;
use std::net::{IpAddr, SocketAddr};
use std::pin::Pin;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, PoisonError};
use std::task::{Context, Poll};
use std::time::{Duration, Instant};

use hyper::body::Incoming;
use hyper_util::rt::{TokioExecutor, TokioIo, TokioTimer};
use hyper_util::server::conn::auto::Builder;
use hyper_util::service::TowerToHyperService;
use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::{TcpListener, TcpStream};
use tokio::task::JoinSet;
use tokio_rustls::rustls::ServerConfig;
use tokio_rustls::TlsAcceptor;
use tokio_util::sync::CancellationToken;

/// The time limits of a listener's connections (see the module docs).
#[derive(Clone, Copy, Debug)]
pub struct Timeouts {
    pub tls_handshake: Duration,
    pub header: Duration,
    pub idle: Duration,
    pub keepalive_interval: Duration,
    pub keepalive_timeout: Duration,
}

type BoxError = Box<dyn std::error::Error + Send + Sync>;

/// Descriptors kept free of connections for the job store, the models and the logs.
pub const RESERVED_FILES: u64 = 256;

/// The probe listener's own caps: a few kubelets and scrapers, never a farm.
pub const PROBE_CONNECTIONS: usize = 64;
pub const PROBE_CONNECTIONS_PER_PEER: usize = 16;

/// Raises the soft limit on open files to the hard one; returns the soft limit in force
/// afterwards (`None` when it is unlimited or cannot be read).
pub fn raise_file_limit() -> Option<u64> {
    use rustix::process::{getrlimit, setrlimit, Resource};
    let mut limit = getrlimit(Resource::Nofile);
    if limit.current != limit.maximum {
        let raised = rustix::process::Rlimit { current: limit.maximum, maximum: limit.maximum };
        match setrlimit(Resource::Nofile, raised) {
            Ok(()) => limit = getrlimit(Resource::Nofile),
            Err(e) => tracing::warn!(error = %e, "cannot raise the open-file limit to its hard maximum"),
        }
    }
    limit.current
}

/// The connection cap to use: `wanted`, kept [`RESERVED_FILES`] below the file limit.
pub fn connection_cap(wanted: usize, file_limit: Option<u64>) -> usize {
    match file_limit {
        Some(limit) => wanted.min(limit.saturating_sub(RESERVED_FILES).max(1) as usize),
        None => wanted,
    }
}

/// Open connections in total and per peer address, shared by the listeners it is given to.
pub struct Admission {
    /// The listeners' name in the metrics (`api`, `probe`).
    listener: &'static str,
    total: usize,
    per_peer: usize,
    open: Mutex<(usize, HashMap<IpAddr, usize>)>,
    telemetry: Arc<crate::telemetry::Telemetry>,
}

/// Why a connection was closed at once.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Refusal {
    Total,
    PerPeer,
}

impl Refusal {
    pub fn name(self) -> &'static str {
        match self {
            Refusal::Total => "total",
            Refusal::PerPeer => "per_peer",
        }
    }
}

impl Admission {
    pub fn new(
        listener: &'static str,
        total: usize,
        per_peer: usize,
        telemetry: Arc<crate::telemetry::Telemetry>,
    ) -> Arc<Admission> {
        Arc::new(Admission { listener, total, per_peer, open: Mutex::new((0, HashMap::new())), telemetry })
    }

    /// A place for a connection from `peer`, given back when the [`Permit`] drops.
    pub fn admit(self: &Arc<Self>, peer: IpAddr) -> Result<Permit, Refusal> {
        let mut open = self.open.lock().unwrap_or_else(PoisonError::into_inner);
        let (total, peers) = &mut *open;
        let from_peer = peers.get(&peer).copied().unwrap_or(0);
        let refusal = if *total >= self.total {
            Some(Refusal::Total)
        } else if from_peer >= self.per_peer {
            Some(Refusal::PerPeer)
        } else {
            None
        };
        if let Some(r) = refusal {
            drop(open);
            self.telemetry.connection_refused(self.listener, r.name());
            return Err(r);
        }
        *total += 1;
        peers.insert(peer, from_peer + 1);
        self.telemetry.set_connections(self.listener, *total);
        Ok(Permit { admission: self.clone(), peer })
    }
}

/// One admitted connection's place.
pub struct Permit {
    admission: Arc<Admission>,
    peer: IpAddr,
}

impl Drop for Permit {
    fn drop(&mut self) {
        let mut open = self.admission.open.lock().unwrap_or_else(PoisonError::into_inner);
        let (total, peers) = &mut *open;
        *total -= 1;
        if let Some(n) = peers.get_mut(&self.peer) {
            *n -= 1;
            if *n == 0 {
                peers.remove(&self.peer);
            }
        }
        self.admission.telemetry.set_connections(self.admission.listener, *total);
    }
}

/// The service of one connection: HTTP requests in, responses with a [`ConnBody`] out.
pub trait ConnService<B>:
    tower::Service<
        axum::http::Request<Incoming>,
        Response = axum::http::Response<B>,
        Error: Into<BoxError>,
        Future: Send + 'static,
    > + Clone
    + Send
    + 'static
{
}

impl<S, B> ConnService<B> for S where
    S: tower::Service<
            axum::http::Request<Incoming>,
            Response = axum::http::Response<B>,
            Error: Into<BoxError>,
            Future: Send + 'static,
        > + Clone
        + Send
        + 'static
{
}

/// A response body a connection can send.
pub trait ConnBody: http_body::Body<Data: Send, Error: Into<BoxError>> + Send + 'static {}

impl<B> ConnBody for B where B: http_body::Body<Data: Send, Error: Into<BoxError>> + Send + 'static {}

/// Which protocols a listener speaks.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Protocols {
    /// HTTP/1.1 and HTTP/2 (prior knowledge or ALPN).
    Http,
    /// HTTP/2 only (gRPC).
    Http2,
}

/// Serves every connection of `listener` with the service that `service` makes for its
/// peer address, until `shutdown` is cancelled and the last connection has closed.
pub async fn serve<F, S, B>(
    listener: TcpListener,
    tls: Option<Arc<ServerConfig>>,
    protocols: Protocols,
    timeouts: Timeouts,
    admission: Arc<Admission>,
    service: F,
    shutdown: CancellationToken,
) -> std::io::Result<()>
where
    F: Fn(SocketAddr) -> S,
    S: ConnService<B>,
    B: ConnBody,
{
    let mut builder = Builder::new(TokioExecutor::new());
    builder.http1().timer(TokioTimer::new()).header_read_timeout(timeouts.header).keep_alive(true);
    builder
        .http2()
        .timer(TokioTimer::new())
        .keep_alive_interval(timeouts.keepalive_interval)
        .keep_alive_timeout(timeouts.keepalive_timeout);
    if protocols == Protocols::Http2 {
        builder = builder.http2_only();
    }
    let builder = Arc::new(builder);
    let acceptor = tls.map(TlsAcceptor::from);
    let mut connections = JoinSet::new();
    loop {
        let (stream, peer) = tokio::select! {
            _ = shutdown.cancelled() => break,
            Some(_) = connections.join_next(), if !connections.is_empty() => continue,
            accepted = listener.accept() => match accepted {
                Ok(c) => c,
                Err(e) => {
                    // Out of file descriptors and the like: wait instead of spinning.
                    tracing::warn!(error = %e, "cannot accept a connection");
                    tokio::time::sleep(Duration::from_millis(50)).await;
                    continue;
                }
            },
        };
        let permit = match admission.admit(peer.ip()) {
            Ok(p) => p,
            Err(refusal) => {
                tracing::debug!(%peer, reason = refusal.name(), "connection refused: too many open");
                continue;
            }
        };
        let _ = stream.set_nodelay(true);
        let svc = TowerToHyperService::new(service(peer));
        let (builder, acceptor, shutdown) = (builder.clone(), acceptor.clone(), shutdown.clone());
        connections.spawn(async move {
            let _permit = permit;
            let activity = Activity::new();
            let io = Watched { io: stream, activity: activity.clone() };
            match acceptor {
                None => connection(&builder, io, svc, activity, timeouts.idle, &shutdown).await,
                Some(acceptor) => {
                    let tls = tokio::select! {
                        _ = shutdown.cancelled() => return,
                        r = tokio::time::timeout(timeouts.tls_handshake, acceptor.accept(io)) => r,
                    };
                    match tls {
                        Ok(Ok(tls)) => connection(&builder, tls, svc, activity, timeouts.idle, &shutdown).await,
                        Ok(Err(e)) => tracing::debug!(%peer, error = %e, "TLS handshake failed"),
                        Err(_) => tracing::debug!(%peer, "TLS handshake timed out"),
                    }
                }
            }
        });
    }
    drop(listener);
    while connections.join_next().await.is_some() {}
    Ok(())
}

/// One connection after its handshake: served until it ends, is idle too long (asked to
/// close, then dropped after as long again) or the server shuts down (asked to close).
async fn connection<I, S, B>(
    builder: &Builder<TokioExecutor>,
    io: I,
    service: TowerToHyperService<S>,
    activity: Activity,
    idle: Duration,
    shutdown: &CancellationToken,
) where
    I: AsyncRead + AsyncWrite + Unpin + Send + 'static,
    S: ConnService<B>,
    B: ConnBody,
{
    let conn = builder.serve_connection_with_upgrades(TokioIo::new(io), service);
    tokio::pin!(conn);
    let mut closing = false;
    let mut idle_strikes = 0;
    loop {
        let quiet_until = activity.last() + idle;
        tokio::select! {
            _ = conn.as_mut() => return,
            _ = shutdown.cancelled(), if !closing => {
                closing = true;
                conn.as_mut().graceful_shutdown();
            }
            _ = tokio::time::sleep_until(quiet_until.into()) => {
                if activity.last() + idle > Instant::now() {
                    idle_strikes = 0;
                    continue;
                }
                idle_strikes += 1;
                if idle_strikes > 1 {
                    tracing::debug!(idle = ?idle, "closing an idle connection");
                    return;
                }
                if !closing {
                    closing = true;
                    conn.as_mut().graceful_shutdown();
                }
                activity.touch();
            }
        }
    }
}

/// When a connection last read or wrote a byte.
#[derive(Clone)]
struct Activity {
    epoch: Instant,
    /// Milliseconds since `epoch`.
    last_ms: Arc<AtomicU64>,
}

impl Activity {
    fn new() -> Activity {
        Activity { epoch: Instant::now(), last_ms: Arc::new(AtomicU64::new(0)) }
    }

    fn touch(&self) {
        self.last_ms.store(self.epoch.elapsed().as_millis() as u64, Ordering::Relaxed);
    }

    fn last(&self) -> Instant {
        self.epoch + Duration::from_millis(self.last_ms.load(Ordering::Relaxed))
    }
}

/// A stream that records its activity.
struct Watched {
    io: TcpStream,
    activity: Activity,
}

impl AsyncRead for Watched {
    fn poll_read(mut self: Pin<&mut Self>, cx: &mut Context<'_>, buf: &mut ReadBuf<'_>) -> Poll<std::io::Result<()>> {
        let before = buf.filled().len();
        let r = Pin::new(&mut self.io).poll_read(cx, buf);
        if matches!(r, Poll::Ready(Ok(()))) && buf.filled().len() > before {
            self.activity.touch();
        }
        r
    }
}

impl AsyncWrite for Watched {
    fn poll_write(mut self: Pin<&mut Self>, cx: &mut Context<'_>, data: &[u8]) -> Poll<std::io::Result<usize>> {
        let r = Pin::new(&mut self.io).poll_write(cx, data);
        if matches!(r, Poll::Ready(Ok(n)) if n > 0) {
            self.activity.touch();
        }
        r
    }

    fn poll_write_vectored(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[std::io::IoSlice<'_>],
    ) -> Poll<std::io::Result<usize>> {
        let r = Pin::new(&mut self.io).poll_write_vectored(cx, bufs);
        if matches!(r, Poll::Ready(Ok(n)) if n > 0) {
            self.activity.touch();
        }
        r
    }

    fn is_write_vectored(&self) -> bool {
        self.io.is_write_vectored()
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<std::io::Result<()>> {
        Pin::new(&mut self.io).poll_flush(cx)
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<std::io::Result<()>> {
        Pin::new(&mut self.io).poll_shutdown(cx)
    }
}

/// A service that puts one value (the peer's address, in the form its transport reads)
/// into the extensions of every request of a connection.
#[derive(Clone)]
pub struct WithExtension<S, T> {
    inner: S,
    value: T,
}

impl<S, T> WithExtension<S, T> {
    pub fn new(inner: S, value: T) -> WithExtension<S, T> {
        WithExtension { inner, value }
    }
}

impl<S, T, B> tower::Service<axum::http::Request<B>> for WithExtension<S, T>
where
    S: tower::Service<axum::http::Request<B>>,
    T: Clone + Send + Sync + 'static,
{
    type Response = S::Response;
    type Error = S::Error;
    type Future = S::Future;

    fn poll_ready(&mut self, cx: &mut Context<'_>) -> Poll<Result<(), S::Error>> {
        self.inner.poll_ready(cx)
    }

    fn call(&mut self, mut request: axum::http::Request<B>) -> S::Future {
        request.extensions_mut().insert(self.value.clone());
        self.inner.call(request)
    }
}

/// `events` until the daemon shuts down, with every event that is ready when it does: a job
/// that finishes during the drain broadcasts its end just before the listeners stop, and a
/// client watching it must still receive that end (a plain `take_until` ends the stream
/// first whenever both are ready).
pub fn until_shutdown<S>(
    events: S,
    shutdown: tokio_util::sync::CancellationToken,
) -> impl futures_util::Stream<Item = S::Item> + Send
where
    S: futures_util::Stream + Send + 'static,
    S::Item: Send,
{
    use futures_util::StreamExt;
    futures_util::stream::unfold((Box::pin(events), shutdown), |(mut events, shutdown)| async move {
        tokio::select! {
            biased;
            item = events.next() => item.map(|i| (i, (events, shutdown))),
            () = shutdown.cancelled() => None,
        }
    })
}

#[cfg(test)]
mod shutdown_tests {
    use futures_util::StreamExt;
    use tokio_util::sync::CancellationToken;

    use super::until_shutdown;

    #[tokio::test]
    async fn events_ready_at_shutdown_are_delivered_and_then_the_stream_ends() {
        let token = CancellationToken::new();
        token.cancel();
        // Ready when the shutdown has already come: all delivered (a plain take_until
        // would deliver none).
        let ready = until_shutdown(futures_util::stream::iter(["progress", "succeeded"]), token.clone());
        assert_eq!(ready.collect::<Vec<_>>().await, ["progress", "succeeded"]);
        // Nothing ready: the stream ends with the shutdown instead of waiting.
        let (tx, rx) = tokio::sync::mpsc::channel::<&str>(1);
        let pending = until_shutdown(tokio_stream::wrappers::ReceiverStream::new(rx), token);
        let got = tokio::time::timeout(std::time::Duration::from_secs(5), pending.collect::<Vec<_>>()).await;
        assert_eq!(got.expect("ended at the shutdown"), Vec::<&str>::new());
        drop(tx);
    }
}
