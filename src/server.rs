//! Starting and stopping the daemon: one [`JobService`], the HTTP and gRPC servers on
//! their own listeners, the retention sweeper, and the graceful shutdown sequence.
//!
//! Shutdown (SIGTERM/SIGINT, or [`Server::shutdown`]):
//! 1. readiness turns false and new submissions get 503 / UNAVAILABLE (queued jobs stay
//!    queued, persisted, for the next start); reads, event streams and result downloads
//!    keep working;
//! 2. running jobs get `--shutdown-timeout` to finish; those still running then stop at
//!    their next tile and go back to the queue;
//! 3. workers exit, then both servers stop (open event streams end).

use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use anyhow::Context;
use tokio::net::TcpListener;
use tokio::task::JoinHandle;
use tokio_util::sync::CancellationToken;

use crate::config::ServeArgs;
use crate::engine::{
    Denoised, Denoiser, DenoiserFactory, Engine, EngineConfig, EngineError, ModelInfo, Options, Progress,
};
use crate::frame::Frame;
use crate::jobs::shared::{Change, Shared};
use crate::jobs::{Backend, JobService, Settings};
use crate::telemetry::Telemetry;

/// How long the servers get to close their connections after the drain.
const TRANSPORT_GRACE: Duration = Duration::from_secs(10);
/// How long workers get to stop after running jobs were told to stop at their next tile.
const WORKER_GRACE: Duration = Duration::from_secs(60);

/// A running daemon.
pub struct Server {
    pub http_addr: SocketAddr,
    pub grpc_addr: SocketAddr,
    /// The probe listener's address (`--probe-http`).
    pub probe_addr: Option<SocketAddr>,
    pub service: JobService,
    trigger: CancellationToken,
    task: JoinHandle<anyhow::Result<()>>,
}

impl Server {
    /// Takes the data directory, binds the configured addresses and starts the daemon.
    /// Models load in the background: `/livez` answers at once, `/readyz` once every
    /// worker is warmed up. A second daemon on the same data directory stops here, before
    /// binding anything.
    pub async fn start(args: ServeArgs) -> anyhow::Result<Server> {
        let lock = lock_data_dir(&args).await?;
        let http =
            TcpListener::bind(args.http).await.with_context(|| format!("cannot listen on {} (HTTP)", args.http))?;
        let grpc =
            TcpListener::bind(args.grpc).await.with_context(|| format!("cannot listen on {} (gRPC)", args.grpc))?;
        Server::start_locked(args, http, grpc, lock).await
    }

    /// Starts the daemon on listeners that are already bound.
    pub async fn start_on(args: ServeArgs, http: TcpListener, grpc: TcpListener) -> anyhow::Result<Server> {
        let lock = lock_data_dir(&args).await?;
        Server::start_locked(args, http, grpc, lock).await
    }

    async fn start_locked(
        args: ServeArgs,
        http: TcpListener,
        grpc: TcpListener,
        lock: crate::jobs::store::DataDirLock,
    ) -> anyhow::Result<Server> {
        let http_addr = http.local_addr()?;
        let grpc_addr = grpc.local_addr()?;
        let probe = match args.probe_http {
            Some(addr) => {
                Some(TcpListener::bind(addr).await.with_context(|| format!("cannot listen on {addr} (probe HTTP)"))?)
            }
            None => None,
        };
        let probe_addr = probe.as_ref().map(TcpListener::local_addr).transpose()?;
        let telemetry = Arc::new(Telemetry::new());
        let file_limit = crate::conn::raise_file_limit();
        let max_connections = crate::conn::connection_cap(args.max_connections as usize, file_limit);
        if max_connections < args.max_connections as usize {
            tracing::warn!(
                wanted = args.max_connections,
                file_limit,
                max_connections,
                "--max-connections lowered to stay below the open-file limit"
            );
        }
        let admission = crate::conn::Admission::new(
            "api",
            max_connections,
            args.max_connections_per_peer as usize,
            telemetry.clone(),
        );
        // The probe port has its own small caps: a flood of the API ports cannot fill them.
        let probe_admission = crate::conn::Admission::new(
            "probe",
            crate::conn::PROBE_CONNECTIONS,
            crate::conn::PROBE_CONNECTIONS_PER_PEER,
            telemetry.clone(),
        );
        // Before the job store and the workers: a bad certificate stops the start cleanly.
        let tls = crate::tls::Tls::load(args.tls_cert.as_deref(), args.tls_key.as_deref())?;
        let settings = Settings::from_args(&args);
        let denoisers = denoisers(&args, settings.engine.clone());
        let data_dir = args.data_dir.clone();
        let (backend, feeds) = match args.shared_store() {
            None => (Backend::Embedded, None),
            Some(config) => {
                let shared = Arc::new(
                    Shared::connect(&config, SHARED_CONNECT_WAIT).await.context("cannot open the shared job store")?,
                );
                // Watch first, then read: no change falls between the two.
                let changes = shared.watch().await?;
                let progress = shared.progress_updates().await?;
                let records = shared.load_all().await?;
                (Backend::Shared(shared.clone(), records), Some((shared, changes, progress)))
            }
        };
        let (service, workers) =
            tokio::task::spawn_blocking(move || JobService::start(&data_dir, settings, telemetry, denoisers, backend))
                .await?
                .context("cannot open the job store")?;
        if let Some((shared, changes, progress)) = feeds {
            tokio::spawn(follow_shared(
                service.clone(),
                shared,
                Box::pin(changes),
                Box::pin(progress),
                args.debug_watch_delay,
            ));
        }

        let trigger = CancellationToken::new();
        let stop = CancellationToken::new();
        let tokens = Arc::new(crate::auth::Tokens::new(&args.auth_tokens, &args.operator_tokens));
        let state = crate::http::AppState {
            service: service.clone(),
            tokens: tokens.clone(),
            shutdown: stop.clone(),
            info: Arc::new(crate::http::Info::new(args.summary())),
        };
        let timeouts = args.timeouts();
        let http_task = tokio::spawn(crate::conn::serve(
            http,
            tls.as_ref().map(|t| t.http.clone()),
            crate::conn::Protocols::Http,
            timeouts,
            admission.clone(),
            crate::http::per_peer(crate::http::router(state.clone())),
            stop.clone(),
        ));
        let probe_task = probe.map(|listener| {
            tokio::spawn(crate::conn::serve(
                listener,
                None,
                crate::conn::Protocols::Http,
                timeouts,
                probe_admission,
                crate::http::per_peer(crate::http::probe_router(state)),
                stop.clone(),
            ))
        });
        let grpc_task = tokio::spawn(crate::grpc::serve(
            grpc,
            service.clone(),
            tokens,
            tls.clone(),
            timeouts,
            admission,
            stop.clone(),
        ));
        let janitor = tokio::spawn(janitor(service.clone(), args.janitor_interval, stop.clone()));
        let storage = tokio::spawn(storage_checks(service.clone(), args.storage_check_interval, stop.clone()));
        tracing::info!(
            http = %http_addr,
            grpc = %grpc_addr,
            probe = probe_addr.map(tracing::field::display),
            tls = tls.is_some(),
            max_connections,
            file_limit,
            "listening"
        );

        let task = tokio::spawn(run(
            service.clone(),
            workers,
            trigger.clone(),
            stop,
            Transports { http: http_task, grpc: grpc_task, probe: probe_task, janitor, storage },
            args.shutdown_timeout,
            lock,
        ));
        Ok(Server { http_addr, grpc_addr, probe_addr, service, trigger, task })
    }

    /// Starts the graceful shutdown (returns at once; see [`Server::wait`]).
    pub fn shutdown(&self) {
        self.trigger.cancel();
    }

    /// A token that starts the shutdown when cancelled (for signal handlers).
    pub fn shutdown_token(&self) -> CancellationToken {
        self.trigger.clone()
    }

    /// Waits until the daemon has stopped. An error means it could not run (e.g. the
    /// models failed to load) or a server failed.
    pub async fn wait(self) -> anyhow::Result<()> {
        drop(self.service);
        self.task.await.context("the daemon's main task panicked")?
    }
}

struct Transports {
    http: JoinHandle<std::io::Result<()>>,
    grpc: JoinHandle<anyhow::Result<()>>,
    probe: Option<JoinHandle<std::io::Result<()>>>,
    janitor: JoinHandle<()>,
    storage: JoinHandle<()>,
}

/// Takes the data directory's lock (waiting up to 10 s for a daemon that is still
/// exiting).
async fn lock_data_dir(args: &ServeArgs) -> anyhow::Result<crate::jobs::store::DataDirLock> {
    let dir = args.data_dir.clone();
    let lock =
        tokio::task::spawn_blocking(move || crate::jobs::store::DataDirLock::acquire(&dir, Duration::from_secs(10)))
            .await?;
    Ok(lock?)
}

async fn run(
    service: JobService,
    workers: Vec<std::thread::JoinHandle<()>>,
    trigger: CancellationToken,
    stop: CancellationToken,
    mut transports: Transports,
    shutdown_timeout: Duration,
    // Held until the daemon has stopped.
    _lock: crate::jobs::store::DataDirLock,
) -> anyhow::Result<()> {
    let mut fatal = service.subscribe_fatal();
    let failure: Option<anyhow::Error> = tokio::select! {
        _ = trigger.cancelled() => None,
        f = fatal.wait_for(|f| f.is_some()) => Some(anyhow::anyhow!(
            "{}", f.ok().and_then(|f| f.clone()).unwrap_or_else(|| "a worker failed".into())
        )),
        r = &mut transports.http => Some(anyhow::anyhow!("the HTTP server stopped: {r:?}")),
        r = &mut transports.grpc => Some(anyhow::anyhow!("the gRPC server stopped: {r:?}")),
    };
    match &failure {
        None => tracing::info!(running = service.running(), "shutting down: draining"),
        Some(e) => tracing::error!(error = %e, "shutting down after a failure"),
    }
    service.begin_drain();
    if !service.wait_idle(shutdown_timeout).await {
        tracing::warn!(
            running = service.running(),
            "shutdown timeout reached: stopping running jobs at their next tile; they stay queued for the next start"
        );
        service.abort_running();
        if !service.wait_idle(WORKER_GRACE).await {
            tracing::error!("workers did not stop in time; their jobs will run again at the next start");
        }
    }
    service.stop_workers();
    let joined = tokio::task::spawn_blocking(move || {
        for w in workers {
            let _ = w.join();
        }
    });
    if tokio::time::timeout(WORKER_GRACE, joined).await.is_err() {
        tracing::error!("a worker thread did not exit");
    }
    stop.cancel();
    for (name, handle) in [("http", transports.http.abort_handle()), ("grpc", transports.grpc.abort_handle())] {
        let finished = async {
            while !handle.is_finished() {
                tokio::time::sleep(Duration::from_millis(20)).await;
            }
        };
        if tokio::time::timeout(TRANSPORT_GRACE, finished).await.is_err() {
            tracing::warn!(transport = name, "connections still open after the grace period: closing them");
            handle.abort();
        }
    }
    if let Some(probe) = transports.probe {
        // Probes are answered until the API is closed; their connections are short.
        probe.abort();
    }
    let _ = transports.janitor.await;
    let _ = transports.storage.await;
    tracing::info!("stopped");
    match failure {
        Some(e) => Err(e),
        None => Ok(()),
    }
}

/// Runs `task` every `every` (the first time at once) until `stop`.
async fn periodically<F: std::future::Future<Output = ()>>(
    every: Duration,
    stop: CancellationToken,
    mut task: impl FnMut() -> F,
) {
    let mut tick = tokio::time::interval(every);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        tokio::select! {
            _ = stop.cancelled() => break,
            _ = tick.tick() => task().await,
        }
    }
}

/// Checks the data directory periodically (see `jobs::health`).
async fn storage_checks(service: JobService, every: Duration, stop: CancellationToken) {
    periodically(every, stop, || async {
        service.check_storage().await;
    })
    .await
}

/// How often shared mode checks its mirror of the records against the store.
const RECONCILE_INTERVAL: Duration = Duration::from_secs(3);

/// How long the daemon waits for NATS at startup in shared mode.
const SHARED_CONNECT_WAIT: Duration = Duration::from_secs(30);

/// Shared mode: applies the other replicas' changes and progress to this one's memory, and
/// reads the shared queue's depth for the metrics. A watch that ends (NATS went away) is
/// opened again with a fresh read of every record.
async fn follow_shared(
    service: JobService,
    shared: Arc<Shared>,
    mut changes: std::pin::Pin<Box<dyn futures_util::Stream<Item = Change> + Send>>,
    mut progress: std::pin::Pin<Box<dyn futures_util::Stream<Item = (String, crate::jobs::record::Progress)> + Send>>,
    lag: Duration,
) {
    use futures_util::StreamExt;
    let mut depth = tokio::time::interval(Duration::from_secs(2));
    let mut check = tokio::time::interval(RECONCILE_INTERVAL);
    loop {
        tokio::select! {
            change = changes.next() => match change {
                // Off the async threads: a change may remove a job's files. Awaited, so
                // changes stay in order.
                Some(change) => {
                    if !lag.is_zero() && !matches!(change, Change::Put { own: true, .. }) {
                        tokio::time::sleep(lag).await;
                    }
                    let service = service.clone();
                    let _ = tokio::task::spawn_blocking(move || service.apply_change(change)).await;
                }
                None => {
                    tracing::warn!("the watch of the shared job records ended; opening it again");
                    loop {
                        tokio::time::sleep(Duration::from_secs(1)).await;
                        let reopened = async {
                            let watch = shared.watch().await?;
                            let records = shared.load_all().await?;
                            Ok::<_, crate::error::Error>((watch, records))
                        };
                        match reopened.await {
                            Ok((watch, records)) => {
                                changes = Box::pin(watch);
                                let service = service.clone();
                                let _ = tokio::task::spawn_blocking(move || service.resync(records)).await;
                                break;
                            }
                            Err(e) => tracing::warn!(error = %e, "cannot watch the shared job records yet"),
                        }
                    }
                }
            },
            update = progress.next() => match update {
                Some((id, p)) => service.apply_progress(&id, p),
                None => match shared.progress_updates().await {
                    Ok(p) => progress = Box::pin(p),
                    Err(_) => tokio::time::sleep(Duration::from_secs(1)).await,
                },
            },
            _ = check.tick() => {
                let service = service.clone();
                let checked = tokio::task::spawn_blocking(move || service.reconcile()).await;
                if let Ok(Err(e)) = checked {
                    tracing::debug!(error = %e, "cannot check the mirror of the shared records now");
                }
            }
            _ = depth.tick() => {
                let shared = shared.clone();
                let read = tokio::task::spawn_blocking(move || (shared.queue_messages(), shared.connected())).await;
                if let Ok((messages, connected)) = read {
                    service.telemetry().set_shared_queue(messages.unwrap_or(0), connected);
                }
            }
        }
    }
}

/// Removes expired jobs and fails queued jobs past their deadline, periodically.
async fn janitor(service: JobService, every: Duration, stop: CancellationToken) {
    periodically(every, stop, || async {
        if let Err(e) = service.sweep().await {
            tracing::error!(error = %e, "retention sweep failed");
        }
    })
    .await
}

/// The denoisers of the workers: engines loaded from `engine`, slowed down by the hidden
/// test hooks `--debug-startup-delay` (before loading) and `--debug-tile-delay` (after
/// every tile) when those are set.
pub fn denoisers(args: &ServeArgs, engine: EngineConfig) -> DenoiserFactory {
    let engines = Engine::factory(engine);
    let (startup, tile) = (args.debug_startup_delay, args.debug_tile_delay);
    if startup.is_zero() && tile.is_zero() {
        return engines;
    }
    Arc::new(move || {
        std::thread::sleep(startup);
        Ok(Box::new(Slowed { inner: engines()?, tile }) as Box<dyn Denoiser>)
    })
}

/// A denoiser that sleeps after every tile, before reporting it (`--debug-tile-delay`).
struct Slowed {
    inner: Box<dyn Denoiser>,
    tile: Duration,
}

impl Denoiser for Slowed {
    fn models(&self) -> Vec<ModelInfo> {
        self.inner.models()
    }

    fn device(&self) -> Option<crate::engine::Device> {
        self.inner.device()
    }

    fn denoise(
        &mut self,
        frame: &Frame,
        options: Options,
        on_tile: &mut dyn FnMut(Progress) -> bool,
    ) -> Result<Denoised, EngineError> {
        let delay = self.tile;
        self.inner.denoise(frame, options, &mut |p| {
            std::thread::sleep(delay);
            on_tile(p)
        })
    }
}

/// Resolves on SIGTERM or SIGINT. The listeners are registered when this is called, not
/// when the future is first polled: `serve` calls it before the daemon listens, so that a
/// signal arriving as soon as it does starts the graceful shutdown instead of ending the
/// process (the signals' default action). Call it inside the runtime.
pub fn shutdown_signal() -> impl std::future::Future<Output = ()> {
    #[cfg(unix)]
    {
        use tokio::signal::unix::{signal, Signal, SignalKind};
        async fn next(s: Option<Signal>) {
            match s {
                Some(mut s) => {
                    s.recv().await;
                }
                None => std::future::pending::<()>().await,
            }
        }
        let (interrupt, terminate) = (signal(SignalKind::interrupt()).ok(), signal(SignalKind::terminate()).ok());
        async move {
            tokio::select! {
                _ = next(interrupt) => tracing::info!("SIGINT received"),
                _ = next(terminate) => tracing::info!("SIGTERM received"),
            }
        }
    }
    #[cfg(not(unix))]
    async {
        let _ = tokio::signal::ctrl_c().await;
        tracing::info!("SIGINT received");
    }
}

/// `mcdenoise serve`: runs until SIGTERM/SIGINT, then shuts down gracefully.
pub fn serve(args: ServeArgs) -> anyhow::Result<()> {
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .thread_name("mcdenoise-io")
        .build()
        .context("cannot start the async runtime")?;
    // The exporter's connection lives on the daemon's runtime.
    let traces = match &args.otlp_endpoint {
        Some(endpoint) => Some(runtime.block_on(async { crate::otlp::start(endpoint, &args.otlp_service_name) })?),
        None => None,
    };
    let (traces, tracer) = traces.map_or((None, None), |(t, tracer)| (Some(t), Some(tracer)));
    crate::telemetry::init_logging(args.log_format, &args.log, tracer);
    tracing::info!(config = %args.summary(), version = env!("CARGO_PKG_VERSION"), "starting mcdenoise serve");
    let served = runtime.block_on(async {
        let signal = shutdown_signal();
        let server = Server::start(args).await?;
        let token = server.shutdown_token();
        tokio::spawn(async move {
            signal.await;
            token.cancel();
        });
        server.wait().await
    });
    if let Some(traces) = traces {
        // Sends what is still batched, on the runtime the exporter's connection lives on.
        let _ = runtime.block_on(async { tokio::task::spawn_blocking(move || traces.shutdown()).await });
    }
    served
}
